"""Without autograd the renderer finishes its frames in place (memory: the lit radiance
masked in place, the background added a channel at a time, the lighting pass writing one
batch item at a time). Those paths must give the bits of the autograd path, which builds
every frame out of place, in every mode that reaches them."""

from __future__ import annotations

import pytest
import torch

import torchraster as tr
from torchraster.dissolve import Dissolve
from torchraster.testing import raytrace as rt

RES = 24


def _scene(blend: bool = False) -> tr.RenderScene:
    """A sphere on a plane, the sphere BLEND (alpha 0.6) or opaque, two materials."""
    pos, faces, cast = rt.sphere_on_plane()
    n_plane = int((~cast).sum()) if cast.dtype == torch.bool else 2
    face_material = torch.zeros(faces.shape[0], dtype=torch.int64)
    face_material[n_plane:] = 1
    sphere = tr.Material(base_color_factor=(0.8, 0.3, 0.2, 0.6 if blend else 1.0),
                         roughness_factor=0.4, metallic_factor=0.3,
                         emissive_factor=(0.3, 0.1, 0.0),
                         alpha_mode="BLEND" if blend else "OPAQUE")
    plane = tr.Material(base_color_factor=(0.5, 0.5, 0.5, 1.0), roughness_factor=0.8)
    return tr.RenderScene(pos.float(), faces, face_material=face_material,
                          materials=[plane, sphere], cast_shadows=cast)


CASES = {
    "pbr, sun, point and ambient, emissive, colour background": dict(),
    "unlit": dict(shading="unlit"),
    "headlight": dict(shading="headlight"),
    "pbr, BLEND sphere": dict(blend=True),
    "pbr, dissolve": dict(dissolve=Dissolve(threshold=0.4, edge_width=0.1)),
    "pbr, fog": dict(fog=tr.Fog(density=0.3, height_falloff=0.5)),
    "pbr, edge antialiasing": dict(raster=tr.RasterSettings(edge_supersample=2)),
    "pbr, batch of 2 views": dict(batch=2),
}


@pytest.mark.parametrize("case", list(CASES))
def test_no_grad_render_equals_the_autograd_render(case):
    opts = dict(CASES[case])
    blend, batch = opts.pop("blend", False), opts.pop("batch", 1)
    scene = _scene(blend)
    view = tr.camera.orbit(torch.tensor([10.0, 130.0][:batch]), torch.tensor([30.0, 20.0][:batch]),
                           torch.tensor([3.5, 4.0][:batch]))
    proj = tr.camera.perspective(45.0, 1.0, 0.1)
    ambient = torch.zeros(1, 9, 3)
    ambient[0, 0] = 0.1 / 0.282095  # a constant ambient radiance of 0.1 (band 0 only)
    lights = tr.Lights(ambient=ambient, directional=rt.make_lights("directional").directional,
                       point=rt.make_lights("point").point)
    renderer = tr.Renderer(RES, background=(0.2, 0.3, 0.4), **opts)
    with torch.no_grad():
        quick = renderer(scene, view, proj, lights)
    scene.positions = scene.positions.clone().requires_grad_(True)
    graph = renderer(scene, view, proj, lights)  # grad mode on: the out-of-place path
    assert torch.equal(quick.image, graph.image.detach())
    assert torch.equal(quick.alpha, graph.alpha.detach())
    covered = quick.alpha > 0
    assert covered.any() and (~covered).any()  # both the surface and the background


def test_textured_no_grad_renders_keep_their_texture_lod():
    """Without autograd the renderer drops the fragments' barycentric derivatives once the
    G-buffer is made (memory): trilinear texturing still sees them, in every call, and the
    image is the autograd render's."""
    mesh = tr.load_spot()
    scene = tr.RenderScene.from_mesh(mesh)
    view = tr.camera.orbit(torch.tensor([30.0]), torch.tensor([15.0]), torch.tensor([2.4]))
    proj = tr.camera.perspective(45.0, 1.0, 0.1)
    lights = tr.Lights(directional=rt.make_lights("directional").directional)
    renderer = tr.Renderer(48)
    with torch.no_grad():
        first = renderer(scene, view, proj, lights).image
        second = renderer(scene, view, proj, lights).image
    scene.positions = scene.positions.clone().requires_grad_(True)
    full = renderer(scene, view, proj, lights).image
    bilinear = tr.Renderer(48, textures=tr.TextureSettings(filter="bilinear"))
    with torch.no_grad():
        flat = bilinear(scene, view, proj, lights).image
    assert torch.equal(first, second) and torch.equal(first, full.detach())
    assert not torch.equal(first, flat)  # the LOD acts on this view


def test_kept_rasters_keep_their_texture_lod():
    """A frame rasterized as another frame's neighbour (flow validity) is kept for when that
    frame renders; its derivatives must survive its own render too, so rendering the same
    frame again (a view re-rendered) gives the same trilinear-textured image."""
    from torchraster.motion import OtherFrame

    mesh = tr.load_spot()
    proj = tr.camera.perspective(45.0, 1.0, 0.1)
    views = [tr.camera.orbit(torch.tensor([a]), torch.tensor([15.0]), torch.tensor([2.4]))
             for a in (20.0, 26.0, 32.0)]
    lights = tr.Lights(directional=rt.make_lights("directional").directional)
    scene = tr.RenderScene.from_mesh(mesh)
    renderer = tr.Renderer(48)

    def frame(i: int):
        return renderer(scene, views[i], proj, lights, channels={"flow_forward_valid"},
                        next_frame=OtherFrame(mesh.positions, views[i + 1], proj)).image

    with torch.no_grad():
        frame(0)  # rasterizes frame 1 as its neighbour and keeps it
        once, again = frame(1), frame(1)  # frame 1's raster comes from the memo both times
        fresh = tr.Renderer(48)(scene, views[1], proj, lights).image
    assert torch.equal(once, fresh) and torch.equal(again, fresh)
