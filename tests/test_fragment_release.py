"""Memory: fragments released after interpolation, texture lookups in bounded chunks."""

from __future__ import annotations

import pytest
import torch

import torchraster as tr
from torchraster import mip_atlas
from torchraster.raster import interpolate, rasterize


def _quad_frags():
    pos = torch.tensor([[[-0.9, -0.9, 0.2, 1.0], [0.9, -0.9, 0.4, 1.0], [0.9, 0.9, 0.6, 1.0],
                         [-0.9, 0.9, 0.1, 1.0]]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    return pos, faces, rasterize(pos, faces, (16, 12))


def test_release_keeps_face_ids_depth_and_mask_and_refuses_interpolation() -> None:
    pos, faces, frags = _quad_frags()
    face_id, depth, mask = frags.face_id.clone(), frags.depth.clone(), frags.mask.clone()
    before = interpolate(pos[..., :3], frags, faces)
    frags.release_interpolation()
    assert frags.bary_packed is None and frags.rows is None
    assert torch.equal(frags.face_id, face_id) and torch.equal(frags.mask, mask)
    assert torch.equal(frags.depth, depth) and torch.equal(
        rasterize(pos, faces, (16, 12)).depth_packed, frags.depth_packed)
    with pytest.raises(ValueError, match="release_interpolation"):
        interpolate(pos[..., :3], frags, faces)
    assert torch.isfinite(before).all()


def test_released_depth_is_the_unreleased_one_when_never_read_before() -> None:
    # depth_packed is lazy (computed from rows and barycentrics): release evaluates it first
    pos, faces, frags = _quad_frags()
    frags.release_interpolation()
    torch.testing.assert_close(frags.depth, rasterize(pos, faces, (16, 12)).depth,
                               rtol=0.0, atol=0.0)


def test_chunked_texture_lookups_are_bit_identical(monkeypatch) -> None:
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(3, 32, 32, generator=g)
    atlas = mip_atlas.MipAtlas([tex])
    uv = torch.rand(2, 1000, generator=g, dtype=torch.float32).requires_grad_(True)
    dx = (0.05 * torch.rand(2, 1000, generator=g)).requires_grad_(True)
    dy = (0.05 * torch.rand(2, 1000, generator=g)).requires_grad_(True)
    whole = atlas.sample(uv, dx, dy)
    grads = torch.autograd.grad(whole.square().sum(), (uv, dx, dy))
    monkeypatch.setattr(mip_atlas, "LOOKUP_CHUNK", 37)
    chunked = atlas.sample(uv, dx, dy)
    assert torch.equal(chunked, whole)
    for a, b in zip(torch.autograd.grad(chunked.square().sum(), (uv, dx, dy)), grads,
                    strict=True):
        assert torch.equal(a, b)


def _sphere_scene():
    """An icosphere, a camera and one point light: (mesh, view, proj, lights)."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=2)
    mesh = tr.Mesh(torch.tensor(ico.vertices, dtype=torch.float32), torch.tensor(ico.faces))
    view = tr.camera.look_at([0.0, 0.4, 3.0], [0.0, 0.0, 0.0])
    proj = tr.camera.perspective(40.0, 1.0, 0.1, 10.0)
    lights = tr.config.lights_from_config([{"type": "point", "position": [1, 2, 2],
                                            "intensity": 10.0}])
    return mesh, view, proj, lights


def test_no_grad_render_equals_the_autograd_render_after_release() -> None:
    mesh, view, proj, lights = _sphere_scene()
    r = tr.Renderer(32, shading="pbr", raster=tr.RasterSettings(antialias=True))
    chans = {"face_id", "depth", "normal"}
    with torch.no_grad():
        a = r(mesh, view, proj, lights, channels=chans)
    b = r(mesh, view, proj, lights, channels=chans)
    assert torch.equal(a.image, b.image.detach())
    for ch in chans:
        assert torch.equal(getattr(a.gbuffer, ch), getattr(b.gbuffer, ch).detach())


def test_shade_writing_into_the_albedo_equals_a_fresh_frame() -> None:
    from torchraster.gbuffer import GBuffer
    from torchraster.shading import shade
    from torchraster.shading.lights import Lights, PointLights

    g = torch.Generator().manual_seed(3)
    b, h, w = 3, 5, 7
    mask = (torch.rand(b, 1, h, w, generator=g) > 0.4).float()
    mask[1] = 0.0  # an item with nothing covered keeps no albedo either
    albedo = torch.rand(b, 3, h, w, generator=g) + 5.0  # garbage where uncovered
    gb = GBuffer(position=torch.randn(b, 3, h, w, generator=g),
                 normal=torch.randn(b, 3, h, w, generator=g), albedo=albedo,
                 metallic=torch.rand(b, 1, h, w, generator=g),
                 roughness=torch.rand(b, 1, h, w, generator=g), mask=mask)
    lights = Lights(point=PointLights(position=torch.tensor([[[0.0, 3.0, 2.0]]]),
                                      color=torch.ones(1, 1, 3), intensity=torch.ones(1, 1)))
    eye = torch.tensor([[0.0, 0.0, 4.0]]).expand(b, 3)
    with torch.no_grad():
        fresh = shade(gb, camera_position=eye, lights=lights)
        kept = albedo.clone()
        reused = shade(gb.replace(albedo=kept), camera_position=eye, lights=lights,
                       reuse_albedo=True)
    assert reused.data_ptr() == kept.data_ptr()  # written into the albedo's frame
    assert torch.equal(reused, fresh)
    # with autograd (or an expanded albedo) the option is ignored: the albedo is untouched
    const = torch.full((1, 3, 1, 1), 0.5).expand(b, 3, h, w)
    with torch.no_grad():
        out = shade(gb.replace(albedo=const), camera_position=eye, lights=lights,
                    reuse_albedo=True)
    assert out.data_ptr() != const.data_ptr() and bool((const == 0.5).all())


def test_renderer_keeps_a_requested_albedo() -> None:
    mesh, view, proj, lights = _sphere_scene()
    r = tr.Renderer(32, shading="pbr")
    with torch.no_grad():
        a = r(mesh, view, proj, lights, channels={"albedo"})
        b = r(mesh, view, proj, lights)
    ref = r(mesh, view, proj, lights, channels={"albedo"})
    assert torch.equal(a.gbuffer.albedo, ref.gbuffer.albedo.detach())
    assert torch.equal(a.image, ref.image.detach()) and torch.equal(b.image, a.image)


def test_ssr_without_environment_reads_the_albedo_after_lighting() -> None:
    # SSR's Fresnel weight reads gb.albedo after the lighting pass: the lighting must not
    # write its radiance there (with no environment nor ambient light it otherwise would)
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=2)
    sphere = torch.tensor(ico.vertices, dtype=torch.float32) * 0.5 + torch.tensor([0, 0.5, 0])
    floor = torch.tensor([[-3.0, 0, -3], [3, 0, -3], [3, 0, 3], [-3, 0, 3]])
    pos = torch.cat([sphere, floor])
    faces = torch.cat([torch.tensor(ico.faces), torch.tensor([[0, 2, 1], [0, 3, 2]]) + len(sphere)])
    mats = [tr.Material(base_color_factor=(0.9, 0.3, 0.2, 1.0), roughness_factor=0.05,
                        metallic_factor=1.0)]
    scene = tr.RenderScene.from_mesh(tr.Mesh(pos, faces), torch.zeros(len(faces),
                                                                      dtype=torch.long), mats)
    view = tr.camera.look_at([0.0, 1.0, 3.0], [0.0, 0.3, 0.0])
    proj = tr.camera.perspective(50.0, 1.0, 0.1, 20.0)
    lights = tr.config.lights_from_config([{"type": "point", "position": [1, 3, 2],
                                            "intensity": 30.0}])
    r = tr.Renderer(32, shading="pbr", ssr=tr.post.SSR(max_steps=16))
    with torch.no_grad():
        a = r(scene, view, proj, lights)
    b = r(scene, view, proj, lights)
    assert "ssr" in a.plan
    torch.testing.assert_close(a.image, b.image.detach(), rtol=1e-5, atol=1e-6)


def test_half_precision_gbuffer_gradients_saturate_instead_of_overflowing() -> None:
    # the lighting shades a float16 G-buffer in float32; the gradients going back to the
    # float16 channels saturate at float16's largest value (the half-precision policy of
    # finish_low_precision) instead of overflowing to inf (and to NaN further back)
    from torchraster.gbuffer import GBuffer
    from torchraster.shading import shade
    from torchraster.shading.lights import Lights, PointLights

    h = torch.float16
    normal = torch.tensor([0.0, 0.0, 1.0], dtype=h).view(1, 3, 1, 1).requires_grad_(True)
    gb = GBuffer(position=torch.zeros(1, 3, 1, 1, dtype=h), normal=normal,
                 albedo=torch.ones(1, 3, 1, 1, dtype=h), metallic=torch.ones(1, 1, 1, 1, dtype=h),
                 roughness=torch.full((1, 1, 1, 1), 0.05, dtype=h),
                 mask=torch.ones(1, 1, 1, 1, dtype=h))
    lights = Lights(point=PointLights(position=torch.tensor([[[0.3, 0.0, 1.0]]]),
                                      color=torch.ones(1, 1, 3),
                                      intensity=torch.full((1, 1), 6e4)))
    rad = shade(gb, camera_position=torch.tensor([[-0.3, 0.0, 1.0]]), lights=lights)
    (grad,) = torch.autograd.grad(rad.float().sum(), normal)
    assert grad.dtype == h and torch.isfinite(grad).all()
    assert float(grad.abs().max()) == float(torch.finfo(h).max)  # saturated, not inf
