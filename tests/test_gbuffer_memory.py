"""The memory-lean G-buffer and lighting passes (issue 23) against straightforward references:
``to_image`` scatters in place and keeps no packed copy for backward, the one-material
G-buffer (values written straight to images) equals the several-material path (packed
scatters) and the interpolated images, and the lighting pass without a graph (in-place
frame, one batch item packed at a time) equals the pass with a graph and a float64
full-frame reference."""

import dataclasses

import pytest
import torch

import torchraster as tr
from torchraster import camera
from torchraster.gbuffer import geometry_pass
from torchraster.material import Material
from torchraster.raster import interpolate_packed, to_image
from torchraster.shading.lighting import shade
from torchraster.shading.lights import DirectionalLights, Lights, PointLights, SpotLights
from torchraster.shading.models import cook_torrance as cook_torrance_model

F64 = torch.float64
MATERIAL_CHANNELS = ("albedo", "alpha", "metallic", "roughness", "ao", "emissive")


def _triangle_frags(size=(5, 6)):
    clip = torch.tensor([[[-1.0, -1, 0, 1], [3, -1, 0, 1], [-1, 3, 0, 1]],
                         [[-0.5, -0.9, 0, 1], [0.9, -0.2, 0, 1], [-0.2, 0.8, 0, 1]]], dtype=F64)
    faces = torch.tensor([[0, 1, 2]])
    return tr.rasterize(clip, faces, size), faces


def test_to_image_scatter_and_gradients() -> None:
    frags, _ = _triangle_frags()
    n = frags.pixels.numel()
    assert 0 < n < frags.face_id.numel()
    packed = torch.randn(2, n, dtype=F64)
    img = to_image(packed, frags, fill=-3.0)
    # reference: a per-pixel loop over the covered pixels
    ref = torch.full((2, frags.face_id.numel()), -3.0, dtype=F64)
    for k, p in enumerate(frags.pixels.tolist()):
        ref[:, p] = packed[:, k]
    b, h, w = frags.face_id.shape
    assert torch.equal(img, ref.view(2, b, h, w).transpose(0, 1))
    assert torch.autograd.gradcheck(lambda x: to_image(x, frags, fill=2.0),
                                    (packed.clone().requires_grad_(),))
    const = torch.randn(3, 1, dtype=F64, requires_grad=True)  # an expanded constant
    assert torch.autograd.gradcheck(lambda x: to_image(x.expand(-1, n), frags), (const,))


def test_to_image_keeps_no_packed_copy_for_backward() -> None:
    frags, _ = _triangle_frags((16, 16))
    n = frags.pixels.numel()
    packed = torch.randn(3, n, requires_grad=True) * 2.0  # a non-leaf
    saved = []
    with torch.autograd.graph.saved_tensors_hooks(lambda t: saved.append(t) or t, lambda t: t):
        img = to_image(packed, frags)
    assert all(not t.is_floating_point() for t in saved), [t.shape for t in saved]
    img.sum().backward()  # still differentiable


def _spot_scene(materials: str):
    spot = tr.load_spot()
    g = torch.Generator().manual_seed(0)
    other = Material(base_color_texture=torch.rand(4, 16, 16, generator=g),
                     metallic_roughness_texture=torch.rand(3, 16, 16, generator=g),
                     occlusion_texture=torch.rand(1, 16, 16, generator=g),
                     emissive_factor=[0.5, 0.2, 1.0], occlusion_strength=0.6,
                     metallic_factor=0.7, roughness_factor=0.4)
    mats = {"spot": [spot.material], "other": [other]}.get(materials, [spot.material, other])
    fm = None
    if materials == "both":
        fm = (torch.arange(spot.faces.shape[0]) % 3 == 0).long()
    return tr.RenderScene(spot.positions, spot.faces, spot.normals, spot.uvs,
                          face_material=fm, materials=mats)


def _gbuffer(scene, channels, filt="trilinear", grad=False):
    view = camera.orbit(torch.tensor([20.0, 200.0]), 15.0, 2.2)
    proj = camera.perspective(45.0, 1.0, 0.1)
    clip = camera.transform_points(scene.positions, proj @ view)
    frags = tr.rasterize(clip, scene.faces, (40, 40), derivatives=True)
    gb = geometry_pass(frags, channels, positions=scene.positions, view=view,
                       normals=scene.normals, uvs=scene.uvs, face_material=scene.face_material,
                       materials=scene.materials, texture_filter=filt)
    return gb, frags


@pytest.mark.parametrize("filt", ["trilinear", "bilinear"])
def test_one_material_images_equal_the_scattered_path(filt: str) -> None:
    """A two-material scene (packed scatters per material) equals, pixel for pixel, each
    material rendered alone on every face (values written straight to images)."""
    both = _spot_scene("both")
    gb, frags = _gbuffer(both, MATERIAL_CHANNELS, filt)
    fm = frags.face_id.clamp_min(0).flatten()
    mat_img = both.face_material[fm].view_as(frags.face_id)[:, None]  # (B, 1, H, W)
    alone = [_gbuffer(_spot_scene(k), MATERIAL_CHANNELS, filt)[0] for k in ("spot", "other")]
    mask = frags.mask  # (B, 1, H, W)
    for ch in MATERIAL_CHANNELS:
        ref = torch.where(mat_img == 0, alone[0][ch], alone[1][ch]) * mask
        assert torch.equal(gb[ch], ref), ch
    # a constant channel (Spot has only a base colour texture) is its factor on covered
    # pixels, 0 elsewhere
    spot = tr.load_spot().material
    for ch, factor in (("metallic", spot.metallic_factor), ("roughness", spot.roughness_factor),
                       ("ao", 1.0), ("emissive", spot.emissive_factor.view(1, 3, 1, 1))):
        assert torch.equal(alone[0][ch], torch.as_tensor(factor, dtype=torch.float32)
                           * mask.float()), ch


def test_position_and_uv_images_equal_interpolate() -> None:
    scene = _spot_scene("spot")
    gb, frags = _gbuffer(scene, ["position", "uv", "mask"])
    assert torch.equal(gb.position, tr.interpolate(scene.positions, frags, scene.faces))
    assert torch.equal(gb.uv, tr.interpolate(scene.uvs, frags, scene.faces))
    assert torch.equal(gb.mask, frags.mask.float())


def test_gbuffer_gradients_match_packed_reference() -> None:
    """Gradients to positions and UVs through the G-buffer equal those of the same values
    taken packed (no images), weighted alike."""
    spot = _spot_scene("spot")
    view = camera.orbit(torch.tensor([40.0]), 15.0, 2.2)
    proj = camera.perspective(45.0, 1.0, 0.1)
    grads = []
    for packed_ref in (False, True):
        pos = spot.positions.clone().requires_grad_()
        uvs = spot.uvs.clone().requires_grad_()
        clip = camera.transform_points(pos, proj @ view)
        frags = tr.rasterize(clip, spot.faces, (32, 32), derivatives=True)
        g = torch.Generator().manual_seed(1)
        wpos = torch.rand(3, frags.pixels.numel(), generator=g)
        wuv = torch.rand(2, frags.pixels.numel(), generator=g)
        if packed_ref:
            loss = ((interpolate_packed(pos, frags)[0] * wpos).sum()
                    + (interpolate_packed(uvs, frags)[0] * wuv).sum())
        else:
            gb = geometry_pass(frags, ["position", "uv"], positions=pos, view=view, uvs=uvs)
            loss = ((gb.position * to_image(wpos, frags)).sum()
                    + (gb.uv * to_image(wuv, frags)).sum())
        loss.backward()
        grads.append((pos.grad, uvs.grad))
    for a, b in zip(*grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def _hostile_gbuffer(dtype, grad=False, b=3, h=10, w=12):
    """Random surface values, NaN in every uncovered pixel, one item empty."""
    g = torch.Generator().manual_seed(4)
    mask = (torch.rand(b, 1, h, w, generator=g) > 0.4).to(dtype)
    mask[1] = 0.0

    def ch(c, lo=0.0, hi=1.0):
        t = (torch.rand(b, c, h, w, generator=g, dtype=F64) * (hi - lo) + lo).to(dtype)
        return torch.where(mask > 0, t, float("nan")).requires_grad_(grad)

    return tr.GBuffer(position=ch(3, -1, 1), normal=ch(3, -1, 1), albedo=ch(3),
                      metallic=ch(1), roughness=ch(1, 0.2, 1), ao=ch(1), emissive=ch(3, 0, 2),
                      mask=mask)


def _lights(dtype, b):
    g = torch.Generator().manual_seed(2)
    point = PointLights(position=torch.tensor([[[2.0, 2, 3], [-2, 1, 2]]], dtype=dtype),
                        color=torch.rand(1, 2, 3, generator=g).to(dtype) + 0.5,
                        intensity=torch.tensor([[20.0, 6.0]], dtype=dtype))
    sun = DirectionalLights(direction=torch.tensor([[[0.3, -1.0, -0.2]]], dtype=dtype),
                            color=torch.ones(1, 1, 3, dtype=dtype),
                            intensity=torch.full((1, 1), 2.0, dtype=dtype))
    spot = SpotLights(position=torch.tensor([[[0.0, 2.0, 2.0]]], dtype=dtype),
                      direction=torch.tensor([[[0.0, -1.0, -1.0]]], dtype=dtype),
                      color=torch.ones(1, 1, 3, dtype=dtype),
                      intensity=torch.full((1, 1), 30.0, dtype=dtype),
                      inner_cone_angle=torch.tensor([[0.2]], dtype=dtype),
                      outer_cone_angle=torch.tensor([[0.6]], dtype=dtype))
    return {"one": Lights(point=point.select(slice(0, 1))), "point": Lights(point=point),
            "all": Lights(point=point, directional=sun, spot=spot)}


@pytest.mark.parametrize("which", ["one", "point", "all"])
def test_shade_without_graph_matches_full_frame_reference(which: str) -> None:
    """The fused pass without a graph (in-place frame; with one pass over the lights each
    item packed, lit and written in turn) against the full-frame (unfused) pass in float64,
    on a G-buffer with NaN in every uncovered pixel and an empty item."""
    gb = _hostile_gbuffer(torch.float32)
    eye = torch.tensor([[0.0, 0.5, 3.0], [1.0, 1.0, 2.5], [-1.0, 2.0, 2.0]])
    lights = _lights(torch.float32, 3)[which]
    with torch.no_grad():
        ours = shade(gb, camera_position=eye, lights=lights, multiscatter=False)
    gb64 = tr.GBuffer(**{k: v.to(F64) for k, v in gb.items()})
    ref = shade(gb64, camera_position=eye.to(F64), lights=lights.to(dtype=F64),
                model=lambda n, v, l, s: cook_torrance_model(n, v, l, s), multiscatter=False)
    assert torch.isfinite(ours).all()
    assert torch.equal(ours[gb.mask.expand_as(ours) == 0], torch.zeros(int(
        (gb.mask == 0).sum()) * 3))
    torch.testing.assert_close(ours.to(F64), ref, rtol=2e-5, atol=1e-6)


@pytest.mark.parametrize("which", ["one", "all"])
def test_shade_without_graph_equals_shade_with_graph(which: str) -> None:
    """In-place (no graph) and out-of-place (graph) finishing give the same radiance; the
    graph's gradients are finite and 0 at uncovered pixels."""
    lights = _lights(torch.float32, 3)[which]
    eye = torch.tensor([[0.0, 0.5, 3.0], [1.0, 1.0, 2.5], [-1.0, 2.0, 2.0]])
    gb = _hostile_gbuffer(torch.float32, grad=True)
    with torch.no_grad():
        lean = shade(gb, camera_position=eye, lights=lights)
    graph = shade(gb, camera_position=eye, lights=lights)
    torch.testing.assert_close(lean, graph.detach(), rtol=1e-6, atol=1e-7)
    graph.square().sum().backward()
    for name in ("position", "normal", "albedo", "emissive"):
        grad = getattr(gb, name).grad
        assert torch.isfinite(grad).all()
        assert (grad * (1 - gb.mask) == 0).all()


def test_shade_light_chunks_agree_without_graph() -> None:
    """One pass over the lights (items packed lazily, one at a time) and one pass per light
    (all items packed once) agree."""
    gb = _hostile_gbuffer(torch.float32)
    eye = torch.tensor([[0.0, 0.5, 3.0], [1.0, 1.0, 2.5], [-1.0, 2.0, 2.0]])
    lights = _lights(torch.float32, 3)["point"]
    with torch.no_grad():
        whole = shade(gb, camera_position=eye, lights=lights)
        per_light = shade(gb, camera_position=eye, lights=lights, light_chunk=1)
    torch.testing.assert_close(whole, per_light, rtol=1e-6, atol=1e-7)
    # and half of the lights' intensity is half of their radiance minus the emissive
    half = dataclasses.replace(lights.point, intensity=lights.point.intensity * 0.5)
    with torch.no_grad():
        halved = shade(gb, camera_position=eye, lights=Lights(point=half))
    emissive = torch.where(gb.mask > 0, gb.emissive, 0.0)
    torch.testing.assert_close(halved - emissive, 0.5 * (whole - emissive), rtol=1e-5,
                               atol=1e-6)


@pytest.mark.parametrize("which", ["one", "point"])
def test_checkpointed_and_lazily_packed_passes_agree(which: str) -> None:
    """Items packed on first use (with a graph: all kept for backward, one frame scattered
    by indexed assignment): checkpointed chunks, plain chunks and one pass per light give
    the same radiance and gradients."""
    lights = _lights(torch.float32, 3)[which]
    eye = torch.tensor([[0.0, 0.5, 3.0], [1.0, 1.0, 2.5], [-1.0, 2.0, 2.0]])
    results = []
    for ckpt, chunk in ((False, None), (True, None), (True, 1)):
        gb = _hostile_gbuffer(torch.float32, grad=True)
        rad = shade(gb, camera_position=eye, lights=lights, checkpoint_chunks=ckpt,
                    light_chunk=chunk)
        rad.square().sum().backward()
        results.append((rad.detach(), *(gb[k].grad for k in ("position", "normal", "albedo",
                                                               "metallic", "roughness"))))
    for other in results[1:]:
        for a, b in zip(results[0], other, strict=True):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
            assert torch.isfinite(b).all()
