"""Memory: surface channels only the lighting reads stay packed (no (B, C, H, W) frames).

The reference is the frame path of the same renderer: channels that an output asks for are
made as images and the lighting packs them itself, so requesting them must not change the
image or any gradient by one bit.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch
import trimesh

import torchraster as tr
from torchraster.gbuffer import GBuffer, PackedChannels, geometry_pass
from torchraster.raster import rasterize
from torchraster.shading import shade
from torchraster.shading.lights import Lights

SURFACE = ("position", "normal", "albedo", "metallic", "roughness")


def _scene(dtype: torch.dtype = torch.float32):
    """An icosphere of two materials (one with a base-colour texture), three views (the
    last looks away: an empty item), a sun and two point lights."""
    ico = trimesh.creation.icosphere(subdivisions=2)
    pos = torch.tensor(ico.vertices, dtype=dtype)
    faces = torch.tensor(ico.faces)
    uv = torch.stack([torch.atan2(pos[:, 0], pos[:, 2]) / (2 * torch.pi) + 0.5,
                      pos[:, 1] * 0.5 + 0.5], 1)
    g = torch.Generator().manual_seed(1)
    texture = torch.rand(3, 8, 8, generator=g, dtype=dtype)
    mats = [tr.Material(base_color_factor=(0.9, 0.4, 0.2, 1.0), roughness_factor=0.3,
                        metallic_factor=0.7),
            tr.Material(base_color_texture=texture, roughness_factor=0.8)]
    face_material = (torch.arange(len(faces)) % 2).long()
    mesh = tr.Mesh(pos, faces, uvs=uv)
    scene = tr.RenderScene.from_mesh(mesh, face_material, mats)
    view = torch.cat([tr.camera.look_at(eye, at) for eye, at in (
        ([0.0, 0.4, 3.0], [0.0, 0.0, 0.0]), ([2.0, 1.0, 2.0], [0.0, 0.0, 0.0]),
        ([0.0, 0.0, 3.0], [0.0, 0.0, 6.0]))]).to(dtype)  # the last looks away
    proj = tr.camera.perspective(40.0, 1.0, 0.1, 10.0).to(dtype)
    lights = tr.config.lights_from_config([
        {"type": "directional", "direction": [-1, -1, -1], "intensity": 2.0},
        {"type": "point", "position": [1, 2, 2], "intensity": 10.0},
        {"type": "point", "position": [-2, 0, 1], "intensity": 5.0, "color": [1, 0.5, 0.2]}])
    return scene, view, proj, lights.to(dtype=dtype)


@pytest.mark.parametrize(("grad", "extra", "packed_names"), [
    (False, "", "albedo,metallic,normal,position,roughness"),
    (True, "", "albedo,metallic,normal,position,roughness"),
    (True, "shadows", "albedo,metallic,roughness"),  # receivers read position and normal
    (False, "ssao", "albedo,metallic,position,roughness"),
    (True, "fog", "albedo,metallic,normal,roughness"),
])
def test_renderer_packed_surface_equals_requested_frames(grad: bool, extra: str,
                                                         packed_names: str) -> None:
    scene, view, proj, lights = _scene()
    if extra == "shadows":  # a floor under the sphere for the point lights' shadows
        floor = torch.tensor([[-3.0, -1, -3], [3, -1, -3], [3, -1, 3], [-3, -1, 3]])
        pos = torch.cat([scene.positions, floor])
        n = scene.positions.shape[0]
        faces = torch.cat([scene.faces, torch.tensor([[0, 2, 1], [0, 3, 2]]) + n])
        uvs = torch.cat([scene.uvs, torch.zeros(4, 2)])
        scene = tr.RenderScene(pos, faces, uvs=uvs, materials=scene.materials,
                               face_material=torch.cat([scene.face_material,
                                                        torch.zeros(2, dtype=torch.long)]))
        lights = dataclasses.replace(lights, point=dataclasses.replace(
            lights.point, cast_shadows=torch.ones(1, 2, dtype=torch.bool)))
    kw = {"shadows": {"shadows": True}, "ssao": {"ssao": tr.post.SSAO()},
          "fog": {"fog": tr.shading.volumetric.Fog(density=0.3, steps=4)}}.get(extra, {})
    r = tr.Renderer(24, shading="pbr", **kw)
    results = []
    for channels in ((), SURFACE, ("albedo",)):  # packed, frames, some of each
        positions = scene.positions.clone().requires_grad_(grad)
        intensity = lights.point.intensity.clone().requires_grad_(grad)
        lit = dataclasses.replace(lights, point=dataclasses.replace(lights.point,
                                                                    intensity=intensity))
        sc = dataclasses.replace(scene, positions=positions)
        with torch.set_grad_enabled(grad):
            out = r(sc, view, proj, lit, channels=channels)
            grads = torch.autograd.grad(out.image.square().sum(), (positions, intensity)) \
                if grad else ()
        gb_step = next(p for p in out.plan if p.startswith("gbuffer "))
        results.append((out.image, grads, gb_step))
    packed, frames, some = results
    assert f"(packed {packed_names})" in packed[2]
    assert "packed" not in frames[2]
    assert f"(packed {packed_names.replace('albedo,', '')})" in some[2]
    assert bool((packed[0][0] > 0).any())
    assert extra == "fog" or bool((packed[0][2] == 0).all())  # the empty item
    for other in (frames, some):
        assert torch.equal(packed[0], other[0])
        for a, b in zip(packed[1], other[1], strict=True):
            assert torch.equal(a, b)


@pytest.mark.parametrize("case", ["fused", "ambient", "ibl", "blinn_phong", "mixed"])
def test_shade_reads_packed_channels_like_frames(case: str) -> None:
    # float64 with gradients to every packed channel; ambient, IBL and other models shade
    # full frames, which shade makes from the packed channels
    scene, view, proj, lights = _scene(torch.float64)
    clip = tr.camera.transform_points(scene.positions, proj @ view)
    frags = rasterize(clip, scene.faces, (20, 20))
    kw = dict(positions=scene.positions, view=view, normals=tr.mesh.vertex_normals(
        scene.positions, scene.faces), uvs=scene.uvs, face_material=scene.face_material,
        materials=scene.materials, texture_filter="bilinear")
    channels = set(SURFACE) | {"mask"}
    packed_names = {"normal", "roughness"} if case == "mixed" else set(SURFACE)
    gb_frames = geometry_pass(frags, channels, **kw)
    gb_packed = geometry_pass(frags, channels, packed=packed_names, **kw)
    assert set(gb_packed.packed.values) == packed_names
    assert set(gb_packed.channels()) == channels - packed_names
    if case == "ambient":
        lights = Lights(ambient=torch.rand(1, 9, 3, dtype=torch.float64), point=lights.point)
    ibl = None
    if case == "ibl":
        def ibl(s):  # any function of the surface: a stand-in for an environment
            return s.albedo * s.n.abs() * (1 - s.roughness) + s.metallic * s.v.square()
    model = "blinn_phong" if case == "blinn_phong" else "cook_torrance"
    eye = tr.renderer.camera_position(view)

    def run(gb):
        leaves = {ch: (gb.packed.values[ch] if gb.packed is not None and ch in
                       gb.packed.values else getattr(gb, ch)) for ch in SURFACE}
        leaves = {ch: t.detach().clone().requires_grad_(True) for ch, t in leaves.items()}
        frames = {ch: t for ch, t in leaves.items() if getattr(gb, ch) is not None}
        store = None if gb.packed is None else PackedChannels(gb.packed.pixels, {
            ch: leaves[ch] for ch in gb.packed.values})
        rad = shade(gb.replace(packed=store, **frames), camera_position=eye, lights=lights,
                    model=model, ibl=ibl)
        grads = torch.autograd.grad(rad.square().sum(), list(leaves.values()))
        return rad, dict(zip(leaves, grads, strict=True))

    rad_f, grad_f = run(gb_frames)
    rad_p, grad_p = run(gb_packed)
    torch.testing.assert_close(rad_p, rad_f, rtol=0, atol=0)
    pixels = gb_packed.packed.pixels
    for ch in SURFACE:  # the frame gradient at the covered pixels is the packed one
        g = grad_f[ch]
        if ch in packed_names:
            g = g.transpose(0, 1).reshape(g.shape[1], -1).index_select(1, pixels)
        torch.testing.assert_close(grad_p[ch], g, rtol=0, atol=0)


def test_packed_channels_are_checked() -> None:
    pixels = torch.tensor([0, 3, 5])
    with pytest.raises(ValueError, match=r"PackedChannels.values\['normal'\]"):
        PackedChannels(pixels, {"normal": torch.zeros(3, 2)})
    with pytest.raises(ValueError, match="'mask' is not one of"):
        PackedChannels(pixels, {"mask": torch.zeros(1, 3)})
    with pytest.raises(TypeError, match="PackedChannels.pixels"):
        PackedChannels(pixels.float(), {})
    scene, view, proj, _ = _scene()
    frags = rasterize(tr.camera.transform_points(scene.positions, proj @ view), scene.faces,
                      (8, 8))
    with pytest.raises(ValueError, match=r"packed: \['depth'\]"):
        geometry_pass(frags, {"depth", "position"}, positions=scene.positions, view=view,
                      packed={"depth"})
    with pytest.raises(ValueError, match=r"packed: \['normal'\]"):  # not requested
        geometry_pass(frags, {"position"}, positions=scene.positions, view=view,
                      packed={"normal"})
    # a mask that does not cover the packed pixels is refused, not shaded wrongly
    gb = geometry_pass(frags, set(SURFACE) | {"mask"}, positions=scene.positions, view=view,
                       normals=tr.mesh.vertex_normals(scene.positions, scene.faces),
                       uvs=scene.uvs, face_material=scene.face_material,
                       materials=scene.materials, packed={"position"})
    eye = tr.renderer.camera_position(view)
    with pytest.raises(ValueError, match="gbuffer.packed"):
        shade(gb.replace(mask=torch.ones_like(gb.mask)), camera_position=eye,
              lights=_scene()[3])
    with pytest.raises(ValueError, match="needs its mask"):
        shade(gb.replace(mask=None), camera_position=eye, lights=_scene()[3])
    assert isinstance(gb, GBuffer) and "position" not in gb


@pytest.mark.parametrize("masked", [True, False])
def test_unpacked_radiance_gradcheck(masked: bool) -> None:
    # shade's autograd path writes every item's packed radiance into one frame through a
    # custom function (only the indices saved): float64 gradcheck, an item with nothing
    # covered (zero gradients, still connected) and the unmasked path (every pixel)
    g = torch.Generator().manual_seed(7)
    b, h, w = 3, 3, 4
    mask = (torch.rand(b, 1, h, w, generator=g, dtype=torch.float64) > 0.3).double()
    mask[1] = 0.0
    pos = torch.randn(b, 3, h, w, generator=g, dtype=torch.float64).requires_grad_(True)
    albedo = torch.rand(b, 3, h, w, generator=g, dtype=torch.float64).requires_grad_(True)
    nrm = torch.randn(b, 3, h, w, generator=g, dtype=torch.float64)
    lights = Lights(point=tr.PointLights(
        position=torch.tensor([[[0.0, 3.0, 2.0]]], dtype=torch.float64),
        color=torch.ones(1, 1, 3, dtype=torch.float64),
        intensity=torch.ones(1, 1, dtype=torch.float64)))
    eye = torch.tensor([[0.0, 0.0, 4.0]], dtype=torch.float64).expand(b, 3)
    rough = torch.full((b, 1, h, w), 0.5, dtype=torch.float64)

    def render(p, a):
        gb = GBuffer(position=p, normal=nrm, albedo=a, metallic=rough * 0.0, roughness=rough,
                     mask=mask if masked else None)
        return shade(gb, camera_position=eye, lights=lights)

    assert torch.autograd.gradcheck(render, (pos, albedo))
    out = render(pos, albedo)
    grads = torch.autograd.grad(out.sum(), (pos, albedo))
    if masked:
        assert bool((out[1] == 0).all()) and all(bool((t[1] == 0).all()) for t in grads)


def test_saved_for_backward_is_flat_in_the_number_of_lights(monkeypatch) -> None:
    # above PIXEL_LIGHT_CHUNK * GRAD_CHUNK_FACTOR pixel-lights the lighting checkpoints its
    # pixel chunks (unit vectors made inside): autograd keeps the packed surface and the
    # lights, not per pixel-light temporaries (a small chunk here: a large frame's case)
    from torchraster.shading import lighting

    monkeypatch.setattr(lighting, "PIXEL_LIGHT_CHUNK", 64)
    scene, view, proj, _ = _scene()
    r = tr.Renderer(48, shading="pbr")
    saved = {}
    for n in (1, 16):
        ang = torch.arange(n) * (2 * torch.pi / n)
        lights = Lights(point=tr.PointLights(
            position=torch.stack([2 * ang.cos(), 2 + 0 * ang, 2 * ang.sin()], -1)[None],
            color=torch.ones(1, n, 3), intensity=torch.full((1, n), 10.0 / n)))
        positions = scene.positions.clone().requires_grad_(True)
        storages = {}

        def pack(t, storages=storages):
            storages[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
            return t

        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            image = r(dataclasses.replace(scene, positions=positions), view, proj,
                      lights).image
        torch.autograd.grad(image.square().sum(), positions)
        saved[n] = sum(storages.values())
    assert saved[16] < 1.25 * saved[1], saved


def test_recomputed_chunks_give_the_light_gradients_and_second_derivatives() -> None:
    # checkpointed lighting chunks run their forward without a graph and recompute it in
    # backward: gradients reach every light tensor (not passed to the chunk as inputs but
    # as the lights' fields) and the G-buffer, and a second derivative goes through them
    g = torch.Generator().manual_seed(11)
    b, h, w = 2, 6, 7
    d = torch.float64
    gb = GBuffer(position=torch.randn(b, 3, h, w, generator=g, dtype=d),
                 normal=torch.randn(b, 3, h, w, generator=g, dtype=d),
                 albedo=torch.rand(b, 3, h, w, generator=g, dtype=d),
                 metallic=torch.rand(b, 1, h, w, generator=g, dtype=d),
                 roughness=torch.rand(b, 1, h, w, generator=g, dtype=d) * 0.8 + 0.1,
                 mask=(torch.rand(b, 1, h, w, generator=g, dtype=d) > 0.2).to(d))
    eye = torch.tensor([[0.0, 0.0, 4.0], [1.0, 0.5, 3.0]], dtype=d)
    results = []
    for ckpt in (False, True):
        pos = torch.tensor([[[0.0, 3.0, 2.0], [1.0, -1.0, 3.0]]], dtype=d, requires_grad=True)
        power = torch.tensor([[2.0, 5.0]], dtype=d, requires_grad=True)
        albedo = gb.albedo.clone().requires_grad_(True)
        lights = Lights(point=tr.PointLights(position=pos, color=torch.ones(1, 2, 3, dtype=d),
                                             intensity=power))
        rad = shade(gb.replace(albedo=albedo), camera_position=eye, lights=lights,
                    checkpoint_chunks=ckpt)
        first = torch.autograd.grad(rad.square().sum(), (pos, power, albedo),
                                    create_graph=True)
        second = torch.autograd.grad(first[0].square().sum(), (power, albedo))
        results.append((rad.detach(), *first, *second))
    for a, c in zip(*results, strict=True):
        torch.testing.assert_close(a, c, rtol=1e-10, atol=1e-12)
        assert bool(a.abs().sum() > 0)


@pytest.mark.parametrize("extra", ["ambient", "emissive", "none"])
def test_uncovered_pixels_are_zero_with_autograd(extra: str) -> None:
    # with a graph, shade masks its radiance only when ambient or IBL light (made from the
    # whole frame) is added to the fused pass; the fused pass and emissive (masked when
    # read) leave uncovered pixels 0 themselves
    g = torch.Generator().manual_seed(3)
    b, h, w = 2, 5, 6
    mask = (torch.rand(b, 1, h, w, generator=g) > 0.4).float()
    gb = GBuffer(position=torch.randn(b, 3, h, w, generator=g),
                 normal=torch.randn(b, 3, h, w, generator=g),
                 albedo=torch.rand(b, 3, h, w, generator=g).requires_grad_(True),
                 metallic=torch.rand(b, 1, h, w, generator=g),
                 roughness=torch.rand(b, 1, h, w, generator=g),
                 emissive=torch.rand(b, 3, h, w, generator=g) + 1.0 if extra == "emissive"
                 else None, mask=mask)
    lights = Lights(point=tr.PointLights(position=torch.tensor([[[0.0, 3.0, 2.0]]]),
                                         color=torch.ones(1, 1, 3), intensity=torch.ones(1, 1)),
                    ambient=torch.rand(1, 9, 3, generator=g) if extra == "ambient" else None)
    rad = shade(gb, camera_position=torch.tensor([[0.0, 0.0, 4.0]]).expand(b, 3),
                lights=lights)
    assert rad.requires_grad
    assert bool((rad.masked_select(mask.expand_as(rad) == 0) == 0).all())
    assert bool((rad.masked_select(mask.expand_as(rad) > 0) != 0).any())
