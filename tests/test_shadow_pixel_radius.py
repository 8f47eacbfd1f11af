"""``ShadowSettings(pixel_radius=...)``: the PCF / PCSS filter widened by each receiver's
pixel footprint, so that shadow edges are about as soft as averaging over the pixel."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

import torchraster as tr
from torchraster.renderer import pixel_size
from torchraster.shading.shadows import (
    ShadowSettings,
    directional_views,
    render_shadow_maps,
    shadow_visibility,
)
from torchraster.testing import raytrace as rt

RES = 96


def _scene(pixel_radius: float):
    """A sphere on a plane under a sun whose 1024² map makes texels ~5x smaller than the
    frame's pixels (so PCF alone leaves a staircase shadow edge)."""
    pos, faces, cast = rt.sphere_on_plane()
    settings = ShadowSettings(map_size=1024, pixel_radius=pixel_radius)
    lights = rt.make_lights("directional", settings)
    scene = tr.RenderScene(pos.float(), faces, cast_shadows=cast, materials=[tr.Material(
        base_color_factor=(0.5, 0.5, 0.5, 1.0), metallic_factor=0.0, roughness_factor=0.6)])
    view = tr.camera.look_at([0.0, 2.5, 4.0], [0.0, 0.3, 0.0])
    return scene, view, tr.camera.perspective(45.0, 1.0, 0.1), lights


def test_pixel_size_is_the_projected_pixel():
    """At depth d a perspective pixel is 2 d tan(fov / 2) / rows high; an orthographic
    one is the view height / rows everywhere."""
    view = tr.camera.look_at([0.0, 0.0, 5.0], [0.0, 0.0, 0.0])
    p = torch.tensor([[0.0, 0.0, 1.0], [0.3, -0.2, -2.0]]).T.reshape(1, 3, 1, 2)
    persp = tr.camera.perspective(40.0, 1.0, 0.1)
    got = pixel_size(p, view, persp, 64)[0, 0, 0]
    want = torch.tensor([4.0, 7.0]) * 2 * math.tan(math.radians(20.0)) / 64
    torch.testing.assert_close(got, want)
    ortho = tr.camera.orthographic(-3.0, 3.0, -3.0, 3.0, 0.1, 20.0)
    torch.testing.assert_close(pixel_size(p, view, ortho, 64)[0, 0, 0],
                               torch.full((2,), 6.0 / 64))


def test_pixel_radius_softens_shadow_edges_like_supersampling():
    """Against 8 x 8 supersampling (whose shadow edges are averaged over each pixel), the
    1x frame with antialiased silhouettes gets closer with pixel_radius 0.56 (a disc of a
    pixel's area) on the shadow-edge pixels, with the same taps."""
    with torch.no_grad():
        ref = tr.Renderer(RES, raster=tr.RasterSettings(supersample=8))(*_scene(0.0)).image
        aa = tr.RasterSettings(antialias=True)
        plain = tr.Renderer(RES, raster=aa)(*_scene(0.0)).image
        wide = tr.Renderer(RES, raster=aa)(*_scene(0.56)).image
    edge = (plain - ref).abs().amax(1) > 0.02  # where the 1x frame misses the reference
    assert int(edge.sum()) > 30

    def err(img: torch.Tensor) -> float:
        return float(((img - ref).abs().amax(1))[edge].pow(2).mean())

    assert err(wide) < 0.5 * err(plain)


def test_pixel_radius_zero_or_without_pixel_size_changes_nothing():
    """pixel_radius 0 with a pixel size, and pixel_radius > 0 without one, give the
    filter's own visibility, bit for bit."""
    scene, view, proj, _ = _scene(0.0)
    casters = scene.faces[scene.cast_shadows]
    bounds = torch.stack([scene.positions.amin(0), scene.positions.amax(0)])[None]
    g = directional_views(torch.tensor([[[0.3, -1.0, 0.2]]]), ShadowSettings(map_size=1024),
                          bounds, view, proj)
    render_shadow_maps([g], scene.positions, casters)
    p = torch.rand(1, 3, 8, 8) * torch.tensor([3.0, 0.0, 3.0]).view(1, 3, 1, 1) - 1.5
    n = torch.tensor([0.0, 1.0, 0.0]).view(1, 3, 1, 1).expand(1, 3, 8, 8)
    receive = torch.ones(1, 1, 8, 8, dtype=torch.bool)
    size = pixel_size(p, view, proj, RES)
    base = shadow_visibility(g, p, n, receive, view)
    assert torch.equal(shadow_visibility(g, p, n, receive, view, size), base)
    wide = dataclasses.replace(g, settings=ShadowSettings(map_size=1024, pixel_radius=0.56))
    assert torch.equal(shadow_visibility(wide, p, n, receive, view), base)
    assert not torch.equal(shadow_visibility(wide, p, n, receive, view, size * 50), base)


def test_pixel_radius_gradients_are_finite():
    scene, view, proj, lights = _scene(0.56)
    sun = lights.directional
    direction = sun.direction.clone().requires_grad_(True)
    lights = dataclasses.replace(lights, directional=dataclasses.replace(sun, direction=direction))
    out = tr.Renderer(32)(scene, view, proj, lights)
    (grad,) = torch.autograd.grad(out.image.sum(), direction)
    assert bool(torch.isfinite(grad).all()) and bool(grad.abs().sum() > 0)


@pytest.mark.parametrize("filt", ["hard", "vsm"])
def test_pixel_radius_is_refused_where_not_implemented(filt):
    with pytest.raises(NotImplementedError, match="ShadowSettings.pixel_radius.*pcf and pcss"):
        ShadowSettings(filter=filt, pixel_radius=0.5)
    ShadowSettings(filter=filt)  # the default 0 is fine


@pytest.mark.parametrize("value", [-0.1, 8.5, float("nan")])
def test_pixel_radius_bounds(value):
    with pytest.raises(ValueError, match="ShadowSettings.pixel_radius"):
        ShadowSettings(pixel_radius=value)


def test_pixel_radius_in_yaml(tmp_path):
    """render config: lights[*].shadows.pixel_radius reaches ShadowSettings; with a filter
    that does not read it, the error names the key."""
    from torchraster.config import build_setup

    text = """
scene: {{objects: [{{primitive: sphere, size: 1.0}}, {{primitive: plane, size: 4}}]}}
lights:
  - {{type: directional, direction: [0.3, -1, 0.2], shadows: {{filter: {f}, pixel_radius: 0.56}}}}
cameras: [{{name: cam, orbit: {{target: [0, 0, 0]}}}}]
render: {{resolution: [16, 16]}}
"""
    path = tmp_path / "c.yaml"
    path.write_text(text.format(f="pcf"))
    setup = build_setup(tr.load_config(path), "cpu")
    assert setup.lights.directional.shadow[0].pixel_radius == 0.56  # one per light
    path.write_text(text.format(f="hard"))
    with pytest.raises(Exception, match="pixel_radius"):
        tr.load_config(path)


def test_pixel_radius_with_fog_light_shafts():
    """Fog samples look the maps up with one comparison (no footprint, no bias): a light
    with pixel_radius still marches its shafts (it raised NotImplementedError for the
    'hard' lookup the fog uses)."""
    from torchraster.shading.volumetric import Fog

    scene, view, proj, lights = _scene(0.56)
    with torch.no_grad():
        out = tr.Renderer(24, fog=Fog(density=0.3, steps=8))(scene, view, proj, lights)
    assert bool(torch.isfinite(out.image).all())
