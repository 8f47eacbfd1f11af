"""The half-precision policy (numerics.compute_dtype): float16 / bfloat16 geometry is
evaluated in float32 and its gradients come back saturated, never Inf / NaN. Regressions
found by scripts/stress.py (kind "half", seed 20261125): vertex normals' cross-product
backward and the rasterizer's per-pixel barycentric backward overflowed float16."""

import pytest
import torch

import torchraster as tr
from torchraster.motion import OtherFrame
from torchraster.testing.raytrace import icosphere


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_vertex_normals_backward_is_finite_and_matches_float32(dtype):
    g = torch.Generator().manual_seed(0)
    pos32 = torch.rand(200, 3, generator=g) * 0.05  # small faces: |cross| ~ 1e-4, so the
    faces = torch.randint(0, 200, (300, 3), generator=g)  # normalisation's gradient ~ 1e4 x
    weight = torch.randn(200, 3, generator=g) * 2000
    grads = []
    for dt in (dtype, torch.float32):
        pos = pos32.to(dt).float().to(dt).requires_grad_(True)
        (tr.vertex_normals(pos, faces).float() * weight).sum().backward()
        grads.append(pos.grad.float())
    assert torch.isfinite(grads[0]).all()
    # the same (half-rounded) positions: where float32's gradient fits the half range, the
    # half gradient is it up to half rounding of the incoming gradient; beyond, saturated
    big = torch.finfo(dtype).max
    fits = grads[1].abs() < big
    err = (grads[0] - grads[1])[fits].norm() / grads[1][fits].norm()
    assert err < 0.05
    assert (grads[0][~fits].abs() == big).all()


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_rasterize_half_evaluates_in_float32(dtype):
    # a long sliver and a big triangle: 1 / sum(l) and its derivative exceed float16
    clip = torch.tensor([[[-1.0, -1, 0, 1], [1, -0.999, 0, 1], [-1, -0.998, 0, 1],
                          [-0.9, -0.9, 0.5, 1e-2], [0.9, -0.9, 0.5, 1e-2],
                          [0, 0.9, 0.5, 1e-2]]], dtype=dtype).requires_grad_(True)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    frags = tr.rasterize(clip, faces, (64, 64))
    assert frags.bary.dtype == torch.float32
    (frags.bary * 1e4).sum().backward()
    assert clip.grad.dtype == dtype and torch.isfinite(clip.grad).all()


def _half_scene(dtype, env_peak):
    """A floor and a sphere in ``dtype`` with a texture and a sun casting shadows, under a
    map holding one ``env_peak`` texel; every input that can take a gradient requires one."""
    sphere, sphere_faces = icosphere(0.5, (0.0, 0.5, 0.0), 2)
    floor_pos = torch.tensor([[-2.0, 0, -2], [2, 0, -2], [2, 0, 2], [-2, 0, 2]])
    pos = torch.cat([floor_pos, sphere.float()])
    faces = torch.cat([torch.tensor([[0, 2, 1], [0, 3, 2]]), sphere_faces + 4])
    uvs = torch.cat([floor_pos[:, [0, 2]] / 4 + 0.5, pos[4:, :2] + 0.5])
    g = torch.Generator().manual_seed(1)
    leaves = {
        "positions": pos.to(dtype).requires_grad_(True),
        "texture": torch.rand(3, 16, 16, generator=g).to(dtype).requires_grad_(True),
        "sun": torch.tensor([[[0.3, -1.0, 0.2]]], dtype=dtype).requires_grad_(True),
        "radiance": torch.full((3, 8, 16), 0.5).index_put_(
            (torch.tensor([0, 1, 2]), torch.tensor(2), torch.tensor(5)),
            torch.tensor(env_peak)).requires_grad_(True),
    }
    scene = tr.RenderScene(leaves["positions"], faces, uvs=uvs.to(dtype), materials=[
        tr.Material(base_color_texture=leaves["texture"], roughness_factor=0.4,
                    metallic_factor=1.0)])
    lights = tr.Lights(directional=tr.DirectionalLights(
        leaves["sun"], torch.ones(1, 1, 3, dtype=dtype), torch.full((1, 1), 3.0, dtype=dtype),
        cast_shadows=torch.tensor([[True]])))
    env = tr.Environment(leaves["radiance"])
    view = tr.camera.orbit(torch.tensor([30.0]), torch.tensor([25.0]), torch.tensor([3.0]),
                           torch.tensor([0.0, 0.3, 0.0])).to(dtype)
    proj = tr.camera.perspective(45.0, 1.0, 0.05).to(dtype)
    return leaves, (scene, view, proj, lights, env)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_renderer_half_bright_environment_is_finite_and_matches_float32(dtype):
    # a 1e6 texel (a sun in the map): the image, the normals' and the positions' gradients
    # exceed float16; before the renders were lifted to float32 as a whole, gradients
    # summed in half precision overflowed to Inf and Inf * 0 gave NaN (stress kind half)
    renderer = tr.Renderer((24, 24), textures=tr.TextureSettings(filter="bilinear"))
    outs, grads = [], []
    for dt in (dtype, torch.float32):
        leaves, args = _half_scene(dtype, 1e6)
        if dt == torch.float32:  # the same half-rounded values, in float32
            leaves, args = _half_scene(dtype, 1e6)
            lifted = {k: v.detach().float().requires_grad_(True) for k, v in leaves.items()}
            scene, view, proj, lights, env = args
            scene = tr.RenderScene(lifted["positions"], scene.faces, uvs=scene.uvs.float(),
                                   materials=[tr.Material(
                                       base_color_texture=lifted["texture"],
                                       roughness_factor=0.4, metallic_factor=1.0)])
            lights = tr.Lights(directional=tr.DirectionalLights(
                lifted["sun"], torch.ones(1, 1, 3), torch.full((1, 1), 3.0),
                cast_shadows=torch.tensor([[True]])))
            args = (scene, view.float(), proj.float(), lights, tr.Environment(
                lifted["radiance"]))
            leaves = lifted
        out = renderer(*args, channels=["normal", "depth", "face_id"])
        weight = torch.linspace(-1.0, 1.0, out.image.numel()).view(out.image.shape).to(
            dtype).float()  # exact in half: the incoming gradient is not rounded
        big = torch.finfo(dtype).max  # saturated pixels pass no gradient, in both
        loss = (out.image.float().clamp(-big, big) * weight).sum() + out.gbuffer.normal.sum()
        grads.append(dict(zip(leaves, torch.autograd.grad(loss, list(leaves.values())),
                              strict=True)))
        outs.append(out)
    half, full = outs
    assert half.image.dtype == half.gbuffer.normal.dtype == half.alpha.dtype == dtype
    assert half.gbuffer.face_id.dtype == torch.int64
    assert torch.equal(half.gbuffer.face_id, full.gbuffer.face_id)  # the same fragments
    big = torch.finfo(dtype).max
    assert torch.isfinite(half.image).all()
    assert torch.equal(half.image.float(), full.image.clamp(-big, big).to(dtype).float())
    assert float(full.image.detach().max()) > big or dtype == torch.bfloat16  # float16 saturates
    for name, g_half in grads[0].items():
        g_full = grads[1][name]
        assert torch.isfinite(g_half).all(), name
        if name == "radiance":  # a float32 map: float32 gradients, the same
            assert torch.equal(g_half, g_full)
            continue
        # one saturating cast per leaf, nothing summed in half precision
        assert g_half.dtype == dtype and torch.equal(g_half, g_full.clamp(-big, big).to(
            dtype)), name


def test_renderer_half_other_frame_depth_is_stored_back():
    leaves, (scene, view, proj, lights, env) = _half_scene(torch.float16, 1.0)
    other = OtherFrame(leaves["positions"].detach(), view, proj)
    out = tr.Renderer((16, 16), shading="unlit")(scene, view, proj,
                                                 channels=["flow_backward_valid"],
                                                 previous_frame=other)
    assert other.depth is not None  # rasterized once, reusable by the next call
    assert out.gbuffer.flow_backward_valid.dtype == torch.float16
    assert bool(out.gbuffer.flow_backward_valid[out.alpha > 0].eq(1).all())


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_interpolate_half_backward_sums_in_float32(dtype):
    # interpolate_packed on half attributes (the G-buffer pass called directly): the
    # per-pixel dot product of a large gradient with the corners overflowed float16
    clip = torch.tensor([[[-0.9, -0.9, 0.5, 1.0], [0.9, -0.9, 0.5, 1.0],
                          [0.0, 0.9, 0.5, 1.0]]]).requires_grad_(True)
    frags = tr.rasterize(clip, torch.tensor([[0, 1, 2]]), (16, 16))
    attrs = torch.tensor([[[300.0, -300.0, 200.0], [-250.0, 300.0, 100.0],
                           [280.0, 290.0, -300.0]]]).to(dtype).requires_grad_(True)
    from torchraster.raster.interpolate import interpolate_packed
    val = interpolate_packed(attrs, frags)[0]
    (val.float() * 60000.0).sum().backward()
    assert torch.isfinite(attrs.grad).all() and torch.isfinite(clip.grad).all()
    assert attrs.grad.dtype == dtype


def test_renderer_half_lights_with_float32_positions():
    # only the lights in float16: results in the positions' dtype (float32),
    # the light's gradient that of the float32 render, saturated once to float16
    grads = []
    for dt in (torch.float16, torch.float32):
        leaves, (scene, view, proj, _, env) = _half_scene(torch.float32, 1.0)
        intensity = torch.full((1, 1), 3.0, dtype=dt, requires_grad=True)
        lights = tr.Lights(directional=tr.DirectionalLights(
            leaves["sun"].detach().to(dt), torch.ones(1, 1, 3, dtype=dt), intensity,
            cast_shadows=torch.tensor([[True]])))
        out = tr.Renderer((24, 24))(scene, view, proj, lights, env)
        assert out.image.dtype == torch.float32
        (out.image * 1e5).sum().backward()
        grads.append(intensity.grad)
    assert float(grads[1]) > 65504  # beyond float16: saturated, not Inf
    assert torch.equal(grads[0], grads[1].clamp(max=65504).half())
