"""SSR: analytic floor + wall reference, mirrored-camera render reference, composite
contract, misses, fades, hostile inputs, gradients, renderer plan."""

from __future__ import annotations

import math
import warnings

import pytest
import torch
import torch.nn.functional as F

import torchraster as tr
from torchraster.camera import look_at, perspective
from torchraster.post import SSR
from torchraster.post.ssao import camera_intrinsics
from torchraster.post.ssr import (
    MAX_REFINE_STEPS,
    MAX_STEPS,
    SSRMaps,
    march_step_bound,
    specular_weight,
    trace_reflections,
)
from torchraster.shading.surface import Surface

N = 48
F_PX = N / 2 / math.tan(math.radians(30))  # 60 degree field of view
K = torch.tensor([F_PX, F_PX, (N - 1) / 2, (N - 1) / 2], dtype=torch.float64)
FLOOR_Y, WALL_Z = -1.0, -4.0


def _rays() -> torch.Tensor:
    j = torch.arange(N, dtype=torch.float64).reshape(1, N).expand(N, N)
    i = torch.arange(N, dtype=torch.float64).reshape(N, 1).expand(N, N)
    return torch.stack([(j - K[2]) / F_PX, -(i - K[3]) / F_PX, -torch.ones(N, N,
                                                                          dtype=torch.float64)])


def _pattern(p: torch.Tensor) -> torch.Tensor:
    """Smooth colour of wall points ``(3, ...)`` -> ``(3, ...)``."""
    return torch.stack([0.5 + 0.5 * torch.sin(3 * p[0]), 0.5 + 0.5 * torch.cos(2 * p[1]),
                        0.3 + 0 * p[0]])


def _floor_and_wall():
    """Camera at the origin looking down -z; floor y = -1 (mirror), wall z = -4 (coloured,
    rough). Returns image, depth, view-space normals, roughness, and the analytic reflection
    of every floor pixel (the wall point hit by the mirrored ray, NaN where it misses)."""
    ray = _rays()  # P = d * ray
    d_floor = torch.where(ray[1] < 0, FLOOR_Y / ray[1], torch.full_like(ray[1], math.inf))
    d_wall = torch.full_like(d_floor, -WALL_Z)
    floor = d_floor < d_wall
    depth = torch.where(floor, d_floor, d_wall)
    p = depth * ray
    normal = torch.where(floor, torch.tensor([0.0, 1, 0], dtype=torch.float64).view(3, 1, 1),
                         torch.tensor([0.0, 0, 1], dtype=torch.float64).view(3, 1, 1))
    image = torch.where(floor, torch.zeros(3, N, N, dtype=torch.float64), _pattern(p))
    rough = torch.where(floor, 0.0, 0.9).to(torch.float64)[None]
    # analytic mirror ray: reflect the view direction about +y, intersect z = -4
    v = ray / ray.norm(dim=0, keepdim=True)
    r = v * torch.tensor([1.0, -1, 1], dtype=torch.float64).view(3, 1, 1)
    t = (WALL_Z - p[2]) / r[2]
    q = p + t * r
    ref = torch.where(floor & (q[1] / -WALL_Z < math.tan(math.radians(30)) - 2 / F_PX), _pattern(q),
                      torch.full_like(image, math.nan))
    return image[None], depth[None, None], normal[None], rough[None], ref[None], floor


def test_floor_reflects_the_wall_like_the_analytic_mirror() -> None:
    image, depth, normal, rough, ref, floor = _floor_and_wall()
    refl, conf = trace_reflections(image, depth, normal, rough, K, edge_fade=0.0, thickness=0.5)
    expect = torch.isfinite(ref[0, 0])
    hit = conf[0, 0] > 0
    assert not bool((hit & ~floor).any())  # the rough wall is not marched
    assert int(expect.sum()) > 300
    assert float((hit & expect).sum()) / float(expect.sum()) > 0.97
    err = (refl[0] - ref[0]).abs().amax(0)[hit & expect]
    # smooth pattern, bilinear reads at a refined hit: a few percent at most
    assert float(err.median()) < 0.01 and float(err.max()) < 0.1


def test_error_shrinks_with_refinement() -> None:
    image, depth, normal, rough, ref, _ = _floor_and_wall()
    errs = []
    for steps in (0, 6):
        refl, conf = trace_reflections(image, depth, normal, rough, K, refine_steps=steps,
                                       edge_fade=0.0, thickness=0.5)
        ok = (conf[0, 0] > 0) & torch.isfinite(ref[0, 0])
        errs.append(float((refl[0] - ref[0]).abs().amax(0)[ok].mean()))
    assert errs[1] < 0.6 * errs[0]


def _quad_scene(mirror_view: bool = False):
    """A textured vertical quad standing above a mirror floor (y = 0), and its camera."""
    uu, vv = torch.meshgrid(torch.linspace(0, 1, 16), torch.linspace(0, 1, 16), indexing="xy")
    tex = torch.stack([0.5 + 0.5 * torch.sin(9 * uu), 0.5 + 0.5 * torch.cos(7 * vv),
                       0.2 + 0.6 * uu * vv])
    quad = torch.tensor([[-0.9, 0.15, 0.0], [0.9, 0.15, 0.0], [0.9, 1.2, 0.0], [-0.9, 1.2, 0.0]])
    floor = torch.tensor([[-6.0, 0, -6], [-6, 0, 6], [6, 0, 6], [6, 0, -6]])
    positions = torch.cat([quad, floor])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    uvs = torch.tensor([[0.0, 0], [1, 0], [1, 1], [0, 1]] + [[0.0, 0]] * 4)
    normals = torch.tensor([[0.0, 0, 1]] * 4 + [[0.0, 1, 0]] * 4)
    mats = [tr.Material(base_color_texture=tex, roughness_factor=0.9),
            tr.Material(metallic_factor=1.0, roughness_factor=0.0)]
    face_material = torch.tensor([0, 0, 1, 1])
    if mirror_view:  # the reference draws the quad only
        positions, faces, uvs, normals = quad, faces[:2, [0, 2, 1]], uvs[:4], normals[:4]
        mats, face_material = mats[:1], face_material[:2]
    scene = tr.RenderScene(positions=positions, faces=faces, uvs=uvs, normals=normals,
                           materials=mats, face_material=face_material)
    view = look_at([0.3, 0.9, 3.0], [0.0, 0.35, 0.0])
    if mirror_view:  # reflect the world through y = 0 before the camera (winding flipped)
        view = view @ torch.diag(torch.tensor([1.0, -1.0, 1.0, 1.0]))
    return scene, view, perspective(50.0, 1.0, 0.1, 50.0)


def test_mirror_plane_matches_the_mirrored_camera_render() -> None:
    res = 64
    scene, view, proj = _quad_scene()
    renderer = tr.Renderer(res, shading="unlit")
    out = renderer(scene, view, proj, channels=["depth", "normal", "roughness", "metallic",
                                                "albedo", "mask"])
    g = out.gbuffer
    n_view = torch.einsum("ij,bjhw->bihw", view[0, :3, :3], g["normal"])
    maps = SSR(edge_fade=0.0)(out.image, g["depth"], n_view,
            Surface(albedo=g["albedo"], metallic=g["metallic"], roughness=g["roughness"]),
            projection=proj, return_maps=True)
    ref_scene, ref_view, _ = _quad_scene(mirror_view=True)
    ref = renderer(ref_scene, ref_view, proj)
    floor = g["roughness"][0, 0] == 0
    hit = (maps.confidence[0, 0] > 0) & floor
    seen = (ref.alpha[0, 0] > 0) & floor
    assert int(seen.sum()) > 200
    # a depth buffer knows silhouettes to a pixel: hits and misses disagree within 1 px only
    grown = F.max_pool2d(seen[None].float(), 3, 1, 1)[0] > 0
    shrunk = -F.max_pool2d(-F.pad(seen[None].float(), (1, 1, 1, 1)), 3, 1)[0] > 0
    assert int((hit & ~grown).sum()) == 0
    assert int((shrunk & ~hit).sum()) == 0
    err = (maps.reflection[0] - ref.image[0]).abs().amax(0)
    assert float(err[hit & shrunk].max()) < 0.06  # inside: bilinear reads of the texture
    assert float(err[hit & seen].median()) < 0.01


def test_composite_replaces_the_fallback_where_it_hits() -> None:
    image, depth, normal, rough, _, floor = _floor_and_wall()
    albedo = torch.full_like(image, 0.9)
    metallic = torch.ones_like(rough)
    fallback = torch.rand_like(image) * 0.1
    ssr = SSR(edge_fade=0.0, thickness=0.5)
    maps = ssr(image, depth, normal,
            Surface(albedo=albedo, metallic=metallic, roughness=rough),
            intrinsics=K, fallback=fallback,
               return_maps=True)
    expect = image + maps.confidence * (maps.weight * maps.reflection - fallback)
    torch.testing.assert_close(maps.image, expect)
    hit = maps.confidence[0, 0] == 1
    assert int(hit.sum()) > 300
    # a full hit: the fallback is gone, the reflection is in, weighted like the split sum
    ray = _rays()
    n_dot_v = (ray[1:2] / ray.norm(dim=0, keepdim=True)).abs()[None]
    w = specular_weight(n_dot_v, albedo, metallic, rough)
    torch.testing.assert_close(maps.weight[:, :, hit], w[:, :, hit])
    torch.testing.assert_close((maps.image - image + fallback)[:, :, hit],
                               (w * maps.reflection)[:, :, hit])
    # roughness 0, f0 = 0.9: Schlick's Fresnel between f0 and f90 = 1
    assert 0.89 < float(maps.weight[:, :, hit].min()) and float(maps.weight.max()) <= 1.0
    out = ssr(image, depth, normal,
            Surface(albedo=albedo, metallic=metallic, roughness=rough),
            intrinsics=K)
    torch.testing.assert_close(out, image + maps.confidence * maps.weight * maps.reflection)


def test_misses_fall_back_and_edges_fade() -> None:
    image, depth, normal, rough, ref, floor = _floor_and_wall()
    # no wall: every mirror ray leaves the frame -> confidence 0, image untouched
    only_floor = torch.where(floor, depth[0, 0], torch.full_like(depth[0, 0], math.inf))
    refl, conf = trace_reflections(image, only_floor[None, None], normal, rough, K)
    assert float(conf.abs().max()) == 0.0 and float(refl.abs().max()) == 0.0
    # edge fade: hits close to the border lose confidence, central ones keep 1
    _, hard = trace_reflections(image, depth, normal, rough, K, edge_fade=0.0, thickness=0.5)
    _, soft = trace_reflections(image, depth, normal, rough, K, edge_fade=0.25, thickness=0.5)
    hit = hard > 0
    assert bool((soft <= hard).all()) and bool((soft[hit] < 1).any())
    assert float(soft[hit].max()) == pytest.approx(1.0)
    # max_roughness: a floor rougher than the cutoff is not marched
    _, none = trace_reflections(image, depth, normal, torch.full_like(rough, 0.7), K,
                                max_roughness=0.6)
    assert float(none.max()) == 0.0
    # max_distance shorter than the way to the wall: nothing is hit
    _, short = trace_reflections(image, depth, normal, rough, K, max_distance=0.5,
                                 thickness=0.5)
    assert 0 < int((short > 0).sum()) < 0.5 * int(hit.sum())
    assert float(depth[short > 0].min()) > 3.5  # |R_z| <= 1: the wall is >= 4 - d away


@pytest.mark.parametrize("case", ["empty", "sky", "grazing", "hostile"])
def test_stress_inputs_are_finite(case: str) -> None:
    torch.manual_seed(0)
    b, h, w = 2, 12, 16
    image = torch.rand(b, 3, h, w, dtype=torch.float64, requires_grad=True)
    depth = torch.rand(b, 1, h, w, dtype=torch.float64) * 4 + 0.5
    normal = torch.randn(b, 3, h, w, dtype=torch.float64)
    rough = torch.zeros(b, 1, h, w, dtype=torch.float64)
    if case == "empty":
        depth = torch.zeros_like(depth)
    elif case == "sky":
        depth = torch.full_like(depth, math.inf)
    elif case == "grazing":  # camera skimming a floor: normals almost perpendicular to view
        depth = torch.linspace(0.5, 1e4, h, dtype=torch.float64).view(1, 1, h, 1).expand(
            b, 1, h, w).contiguous()
        normal = torch.tensor([0.0, 1.0, 1e-7], dtype=torch.float64).view(1, 3, 1, 1).expand(
            b, 3, h, w)
    else:  # zero normals, depth 0 / inf / huge / tiny, blinding and black pixels
        normal[:, :, 0, :4] = 0
        depth[:, :, 1, :3] = math.inf
        depth[:, :, 2, :3] = 0
        depth[:, :, 3, :3] = 1e30
        depth[:, :, 4, :3] = 1e-30
        with torch.no_grad():
            image[:, :, 5] = 1e30
            image[:, :, 6] = 0
    albedo = torch.rand(b, 3, h, w, dtype=torch.float64)
    metallic = torch.rand(b, 1, h, w, dtype=torch.float64)
    k = torch.tensor([10.0, 10.0, (w - 1) / 2, (h - 1) / 2], dtype=torch.float64)
    maps = SSR()(image, depth, normal,
            Surface(albedo=albedo, metallic=metallic, roughness=rough),
            intrinsics=k, return_maps=True)
    for t in maps:
        assert bool(torch.isfinite(t).all())
    maps.image.sum().backward()
    assert bool(torch.isfinite(image.grad).all())
    if case in ("empty", "sky"):
        assert torch.equal(maps.image, image) and float(maps.confidence.max()) == 0


def test_gradcheck_image_and_fallback() -> None:
    image, depth, normal, rough, _, _ = _floor_and_wall()
    sl = (slice(None), slice(None), slice(30, 38), slice(20, 28))  # 8 x 8 around the crease
    img = image[sl].clone().requires_grad_(True)
    fb = torch.rand_like(img).requires_grad_(True)
    dep, nrm, rgh = depth[sl], normal[sl], rough[sl]
    albedo = torch.full_like(img, 0.8)
    metal = torch.ones_like(rgh)
    k = K - torch.tensor([0.0, 0.0, 20.0, 30.0], dtype=torch.float64)
    ssr = SSR(edge_fade=0.3, thickness=0.5)
    conf = ssr(img, dep, nrm,
            Surface(albedo=albedo, metallic=metal, roughness=rgh),
            intrinsics=k, return_maps=True).confidence
    assert float(conf.max()) > 0  # some pixels reflect others of the crop

    def f(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return ssr(x, dep, nrm,
                Surface(albedo=albedo, metallic=metal, roughness=rgh),
                intrinsics=k, fallback=y)

    assert torch.autograd.gradcheck(f, (img, fb), eps=1e-6, atol=1e-6, fast_mode=True)


def test_gradcheck_roughness_through_the_cone_blur_and_fade() -> None:
    """Issue 21: roughness was detached before the trace, so the cone-blur level of the
    hit colour and the confidence fade had no gradient (numeric 6.18 vs analytic 12.86).
    A glossy floor (roughness 0.2-0.55: footprints of 1-5 px, the fade over the last
    quarter of [0, 0.6]) reflecting a crease of the wall; float64 finite differences."""
    image, depth, normal, _, _, floor = _floor_and_wall()
    sl = (slice(None), slice(None), slice(30, 38), slice(20, 28))
    img, dep, nrm, fl = image[sl], depth[sl], normal[sl], floor[30:38, 20:28]
    gen = torch.Generator().manual_seed(0)
    glossy = 0.2 + 0.35 * torch.rand(8, 8, generator=gen, dtype=torch.float64)
    rgh = torch.where(fl, glossy, 0.9)[None, None].requires_grad_(True)
    albedo, metal, fb = torch.full_like(img, 0.8), torch.ones_like(rgh), torch.full_like(img, 0.05)
    k = K - torch.tensor([0.0, 0.0, 20.0, 30.0], dtype=torch.float64)
    ssr = SSR(edge_fade=0.3, thickness=0.5)

    def maps(r: torch.Tensor) -> SSRMaps:
        return ssr(img, dep, nrm,
                Surface(albedo=albedo, metallic=metal, roughness=r),
                intrinsics=k, fallback=fb, return_maps=True)

    m = maps(rgh)
    fading = (m.confidence > 0) & (m.confidence < 1) & (rgh > 0.45)
    assert int((m.confidence > 0).sum()) > 20 and bool(fading.any())
    (g_refl,) = torch.autograd.grad(m.reflection.sum(), rgh)
    assert int((g_refl != 0).sum()) > 5  # blurred reads: the level moves with roughness
    assert torch.autograd.gradcheck(lambda r: maps(r).image, (rgh,), eps=1e-6, atol=1e-6)
    assert torch.autograd.gradcheck(lambda r: maps(r).reflection, (rgh,), eps=1e-6, atol=1e-6)


def test_float32_matches_float64() -> None:
    image, depth, normal, rough, _, _ = _floor_and_wall()
    r64, c64 = trace_reflections(image, depth, normal, rough, K, thickness=0.5)
    r32, c32 = trace_reflections(image.float(), depth.float(), normal.float(), rough.float(),
                                 K.float(), thickness=0.5)
    both = (c64 > 0) & (c32 > 0)
    assert int(both.sum()) > 0.95 * int((c64 > 0).sum())
    assert float((r64 - r32.double()).abs().amax(1, keepdim=True)[both].median()) < 1e-3


def test_disabled_and_bad_args() -> None:
    img = torch.rand(1, 3, 4, 4)
    d, n, r = torch.ones(1, 1, 4, 4), torch.zeros(1, 3, 4, 4), torch.zeros(1, 1, 4, 4)
    k = torch.tensor([4.0, 4.0, 1.5, 1.5])
    assert SSR(enabled=False)(img, d, n, Surface(albedo=img, metallic=r, roughness=r)) is img
    with pytest.raises(ValueError, match="projection, intrinsics"):
        SSR()(img, d, n, Surface(albedo=img, metallic=r, roughness=r))
    with pytest.raises(ValueError, match="normals"):
        SSR()(img, d, torch.zeros(1, 3, 4, 5),
                Surface(albedo=img, metallic=r, roughness=r),
                intrinsics=k)
    with pytest.raises(ValueError, match="depth: contains NaN"):
        SSR()(img, torch.full_like(d, math.nan), n,
                Surface(albedo=img, metallic=r, roughness=r),
                intrinsics=k)
    with pytest.raises(ValueError, match="fallback"):
        SSR()(img, d, n,
                Surface(albedo=img, metallic=r, roughness=r),
                intrinsics=k, fallback=torch.zeros(1, 3, 2, 2))
    with pytest.raises(TypeError, match="^surface: expected a torchraster.shading.Surface"):
        SSR()(img, d, n, r, intrinsics=k)  # the former positional roughness
    with pytest.raises(ValueError, match="^surface.roughness"):
        SSR()(img, d, n, Surface(albedo=img, metallic=r, roughness=img), intrinsics=k)
    for kw, name in (({"max_steps": 0}, "max_steps"), ({"thickness": 0.0}, "thickness"),
                     ({"max_roughness": 1.5}, "max_roughness"), ({"edge_fade": -1}, "edge_fade"),
                     ({"refine_steps": -1}, "refine_steps"), ({"max_distance": 0}, "max_distance")):
        with pytest.raises(ValueError, match=name):
            SSR(**kw)


@pytest.mark.parametrize("name", ["max_steps", "refine_steps"])
@pytest.mark.parametrize("value", [16.0, 2.5, "8", True, None, -1, 10**7, 2**63, math.inf])
def test_step_bounds_raise_naming_the_argument(name: str, value: object) -> None:
    """Non-integers, <= 0 (< 0 for refine_steps) and huge counts: one clear error, from the
    module and from trace_reflections alike (never a TypeError from range() or a hang)."""
    with pytest.raises(ValueError, match=rf"{name}: expected an int in \["):
        SSR(**{name: value})
    img, d = torch.rand(1, 3, 4, 4), torch.ones(1, 1, 4, 4)
    n, r = torch.zeros(1, 3, 4, 4), torch.zeros(1, 1, 4, 4)
    with pytest.raises(ValueError, match=name):
        trace_reflections(img, d, n, r, torch.tensor([4.0, 4.0, 1.5, 1.5]), **{name: value})


def test_step_bounds_accept_ints_up_to_the_limits() -> None:
    import numpy as np

    ssr = SSR(max_steps=np.int64(MAX_STEPS), refine_steps=MAX_REFINE_STEPS)
    assert ssr.max_steps == MAX_STEPS and type(ssr.max_steps) is int
    assert SSR(max_steps=1, refine_steps=0).refine_steps == 0
    assert march_step_bound(16, 16) == 71 and MAX_STEPS >= march_step_bound(2**17, 2**17)


def _quad_gbuffer(res: int):
    scene, view, proj = _quad_scene()
    out = tr.Renderer(res, shading="unlit")(scene, view, proj, channels=[
        "depth", "normal", "roughness", "metallic", "albedo"])
    g = out.gbuffer
    n_view = torch.einsum("ij,bjhw->bihw", view[0, :3, :3], g["normal"])
    k = camera_intrinsics(proj, None, (1, res, res))
    return out.image, g["depth"], n_view, g["roughness"], k


def test_march_ends_when_every_ray_has_finished() -> None:
    """Issue 21: rays leaving the frame stalled at s = 0.9999998 (their cell index clamped
    to the frame, the exit behind them), so the march ran all ``max_steps``. Every ray
    must now hit or miss within march_step_bound(H, W) steps, whatever the cap, and a
    larger cap must not change the result."""
    image, depth, normal, rough, k = _quad_gbuffer(16)
    stats: dict = {}
    refl, conf = trace_reflections(image, depth, normal, rough, k, max_steps=5000, stats=stats)
    assert stats["rays"] > 50 and float(conf.max()) > 0  # some rays hit, some leave
    assert 0 < stats["steps"] <= march_step_bound(16, 16)
    refl_b, conf_b = trace_reflections(image, depth, normal, rough, k,
                                       max_steps=march_step_bound(16, 16))
    assert torch.equal(refl, refl_b) and torch.equal(conf, conf_b)


@pytest.mark.parametrize("case", ["floor-wall", "random", "grazing"])
def test_steps_used_stay_within_the_geometric_bound(case: str) -> None:
    """float64 and float32 frames where rays leave through every border, hit, and skim:
    the step count actually used never exceeds the bound, and the same cap-free result
    comes out whether the cap is the bound or far above it."""
    if case == "floor-wall":
        image, depth, normal, rough, *_ = _floor_and_wall()
        k = K
    else:
        gen = torch.Generator().manual_seed(3)
        h, w = 20, 28
        image = torch.rand(2, 3, h, w, generator=gen)
        depth = torch.rand(2, 1, h, w, generator=gen) * 4 + 0.5
        normal = torch.randn(2, 3, h, w, generator=gen)
        if case == "grazing":
            depth = torch.linspace(0.5, 1e4, h).view(1, 1, h, 1).expand(2, 1, h, w).contiguous()
            normal = torch.tensor([0.0, 1.0, 1e-3]).view(1, 3, 1, 1).expand(2, 3, h, w)
        rough = torch.rand(2, 1, h, w, generator=gen) * 0.5
        k = torch.tensor([12.0, 12.0, (w - 1) / 2, (h - 1) / 2])
    h, w = depth.shape[-2:]
    stats: dict = {}
    far = trace_reflections(image, depth, normal, rough, k, max_steps=10_000, stats=stats,
                            thickness=0.5)
    assert stats["rays"] > 0 and 0 < stats["steps"] <= march_step_bound(h, w)
    at_bound = trace_reflections(image, depth, normal, rough, k, thickness=0.5,
                                 max_steps=march_step_bound(h, w))
    for a, b in zip(far, at_bound, strict=True):
        assert torch.equal(a, b)



# ------------------------------------------------------------------ packed, hierarchical march
def test_min_max_chain_cells_hold_the_depth_range_of_their_pixels() -> None:
    """The padded chain read at the march's arithmetic index (item b, level l, cell (cu,
    cv): ``2 ph pw (b + 1 - 2^-l) + cv pw_l + cu``) holds for every cell the min and max
    valid depth of its pixels (brute force; +inf / -inf where it has none), on a frame
    padded on both axes."""
    from torchraster.post.ssr import _min_max_chain, _top_cell

    gen = torch.Generator().manual_seed(0)
    b, h, w = 2, 21, 38
    depth = torch.rand(b, 1, h, w, generator=gen, dtype=torch.float64) * 5 + 0.5
    depth[torch.rand(b, 1, h, w, generator=gen) < 0.3] = math.inf
    depth[1, 0, 16:, :] = math.inf  # a band of whole empty cells
    top = _top_cell(h, w)
    cmin, cmax, ph, pw = _min_max_chain(depth, torch.isfinite(depth), top)
    assert (ph % top, pw % top) == (0, 0) and ph > h and pw > w and ph * pw <= 1.5 * h * w
    assert cmin.numel() == b * 2 * ph * pw
    size = 1
    while size <= top:
        phl, pwl = ph // size, pw // size
        for bb in range(b):
            off = 2 * ph * pw * (bb + 1) - 2 * ph * pw // size
            for cv in range(phl):
                for cu in range(pwl):
                    cell = depth[bb, 0, cv * size:(cv + 1) * size, cu * size:(cu + 1) * size]
                    vals = cell[torch.isfinite(cell)]
                    at = off + cv * pwl + cu
                    lo, hi = (vals.min(), vals.max()) if vals.numel() else (math.inf, -math.inf)
                    assert float(cmin[at]) == float(lo) and float(cmax[at]) == float(hi)
        size *= 2


def _random_frames(b: int = 2, h: int = 20, w: int = 28):
    gen = torch.Generator().manual_seed(3)
    image = torch.rand(b, 3, h, w, generator=gen)
    depth = torch.rand(b, 1, h, w, generator=gen) * 4 + 0.5
    depth[:, :, :3] = math.inf  # empty rows: rays leave through them
    normal = torch.randn(b, 3, h, w, generator=gen)
    rough = torch.rand(b, 1, h, w, generator=gen) * 0.5
    k = torch.tensor([12.0, 12.0, (w - 1) / 2, (h - 1) / 2])
    return image, depth, normal, rough, k


@pytest.mark.parametrize("case", ["floor-wall", "quad", "random"])
def test_hierarchical_march_finds_the_hits_of_a_pixel_by_pixel_walk(
        case: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """With a 1-pixel top cell the march is a plain walk through every pixel a ray crosses;
    the min-max hierarchy only skips cells no ray can hit in (and the part of a cell in
    front of its nearest depth), so it must find the same hits: the same hit pixels and
    reflections equal to the bisection's resolution."""
    from torchraster.post import ssr as ssr_module

    if case == "floor-wall":
        image, depth, normal, rough, *_ = _floor_and_wall()
        k = K
    elif case == "quad":
        image, depth, normal, rough, k = _quad_gbuffer(40)
    else:
        image, depth, normal, rough, k = _random_frames()
    kw = {"thickness": 0.5, "max_steps": MAX_STEPS, "edge_fade": 0.0}
    stats_h: dict = {}
    refl_h, conf_h = trace_reflections(image, depth, normal, rough, k, stats=stats_h, **kw)
    monkeypatch.setattr(ssr_module, "_top_cell", lambda h, w: 1)
    stats_p: dict = {}
    refl_p, conf_p = trace_reflections(image, depth, normal, rough, k, stats=stats_p, **kw)
    hit_h, hit_p = conf_h > 0, conf_p > 0
    assert int(hit_p.sum()) > 50
    assert int((hit_h != hit_p).sum()) <= 0.01 * int(hit_p.sum())
    both = (hit_h & hit_p).expand_as(refl_h)
    assert float((refl_h - refl_p).abs()[both].median()) < 1e-3
    if case != "random":  # (noise: no empty space to skip)
        assert stats_h["ray_steps"] < stats_p["ray_steps"]  # and the cheaper walk


def test_batched_frames_march_like_single_frames(monkeypatch: pytest.MonkeyPatch) -> None:
    """Rays of every batch item read their own item's chain (batch offsets in the chain
    index), and the float64 chain index used for frames too large for exact float32
    indices gives the same result as the float32 one."""
    from torchraster.post import ssr as ssr_module

    image, depth, normal, rough, k = _random_frames()
    both = trace_reflections(image, depth, normal, rough, k, thickness=0.5)
    for i in range(2):
        one = trace_reflections(image[i:i + 1], depth[i:i + 1], normal[i:i + 1],
                                rough[i:i + 1], k, thickness=0.5)
        for a, b in zip(both, one, strict=True):
            assert torch.equal(a[i:i + 1], b)
    monkeypatch.setattr(ssr_module, "_FLOAT_INDEX_LIMIT", 0)
    wide = trace_reflections(image, depth, normal, rough, k, thickness=0.5)
    for a, b in zip(both, wide, strict=True):
        assert torch.equal(a, b)


def test_weight_at_the_hits_is_the_split_sum_weight_of_the_frame() -> None:
    """SSR evaluates W and the composite at the hit pixels only: they must equal the
    full-frame specular_weight of n.v (eye rays of the pixels) and the full-frame formula."""
    image, depth, normal, rough, k = _quad_gbuffer(32)
    k = k.reshape(4)
    albedo, metallic = torch.rand_like(image), torch.rand_like(rough)
    fallback = torch.rand_like(image) * 0.1
    maps = SSR(edge_fade=0.0)(image, depth, normal,
            Surface(albedo=albedo, metallic=metallic, roughness=rough),
            intrinsics=k,
                              fallback=fallback, return_maps=True)
    hit = (maps.confidence > 0).expand_as(image)
    assert int(hit.sum()) > 100
    b, _, h, w = image.shape
    jj = torch.arange(w, dtype=image.dtype).view(1, w).expand(h, w)
    ii = torch.arange(h, dtype=image.dtype).view(h, 1).expand(h, w)
    eye = torch.stack([(jj - k[2]) / k[0], -(ii - k[3]) / k[1], -torch.ones(h, w)])
    n_dot_v = (F.normalize(normal, dim=1) * F.normalize(eye, dim=0)).sum(1, keepdim=True)
    w_ref = specular_weight(n_dot_v.abs(), albedo, metallic, rough)
    torch.testing.assert_close(maps.weight[hit], w_ref[hit])
    assert float(maps.weight[~hit].abs().max()) == 0.0
    expect = image + maps.confidence * (w_ref * maps.reflection - fallback)
    torch.testing.assert_close(maps.image, expect)

# ------------------------------------------------------------------------------ renderer
def _glow_scene() -> tuple[tr.RenderScene, torch.Tensor, torch.Tensor]:
    """An emissive quad (radiance independent of the lighting) above a mirror floor."""
    scene, view, proj = _quad_scene()
    scene.materials[0] = tr.Material(base_color_factor=[0.0, 0.0, 0.0, 1.0],
                                     emissive_factor=[0.6, 0.3, 0.1], roughness_factor=1.0)
    return scene, view, proj


def _uniform_env(c: float) -> tr.Environment:
    return tr.Environment(torch.full((3, 8, 16), c), specular_size=16, specular_levels=4,
                          specular_samples=8)


def test_renderer_replaces_the_ibl_specular_where_rays_hit() -> None:
    """Under a uniform sky of radiance c, a mirror floor shows W c where its rays miss and
    W L_quad where they hit: there the sky must be gone entirely (no double counting)."""
    scene, view, proj = _glow_scene()
    renderer = tr.Renderer(48,
                           ssr=SSR(edge_fade=0.0),
                           background=tr.BackgroundSettings(environment=False))
    outs = [renderer(scene, view, proj, environment=_uniform_env(c)) for c in (0.2, 1.0)]
    assert "ssr" in outs[0].plan
    ref_scene, ref_view, _ = _quad_scene(mirror_view=True)
    seen = tr.Renderer(48, shading="unlit")(ref_scene, ref_view, proj).alpha[0, 0] > 0
    # 2 px away from the reflection's silhouette (also where it leaves the frame)
    inside = -F.max_pool2d(-F.pad(seen[None].float(), (2, 2, 2, 2)), 5, 1)[0] > 0
    outside = ~(F.max_pool2d(seen[None].float(), 5, 1, 2)[0] > 0)
    floor = torch.zeros_like(seen)
    floor[30:] = True  # below the quad's reflection's top edge: all floor in this view
    inside, outside = inside & floor, outside & floor
    assert int(inside.sum()) > 50 and int(outside.sum()) > 200
    lo, hi = (o.image[0] for o in outs)
    torch.testing.assert_close(lo[:, inside], hi[:, inside], atol=2e-3, rtol=0)
    glow = torch.tensor([0.6, 0.3, 0.1]).view(3, 1)
    assert float((hi[:, inside] - glow).abs().max()) < 0.05  # W ~ 1 for f0 = 1
    # where rays miss, the floor keeps the sky's specular: W (1.0 - 0.2) with W ~ 1
    assert float((hi[:, outside] - lo[:, outside]).min()) > 0.7


def test_plan_runs_ssr_only_when_asked_and_useful() -> None:
    scene, view, proj = _glow_scene()
    env = _uniform_env(0.5)
    assert "ssr" in tr.Renderer(16, ssr=SSR()).plan(scene, environment=env)
    assert tr.Renderer(16, ssr=SSR()).plan(scene, environment=env).ssr
    for renderer in (tr.Renderer(16), tr.Renderer(16, ssr=SSR(enabled=False)),
                     tr.Renderer(16, shading="headlight", ssr=SSR())):
        plan = renderer.plan(scene, environment=env)
        assert "ssr" not in plan and not plan.ssr and "depth" not in plan.channels
    rough = tr.RenderScene(positions=scene.positions, faces=scene.faces,
                           materials=[tr.Material(roughness_factor=0.7)])
    assert "ssr" not in tr.Renderer(16, ssr=SSR()).plan(rough, environment=env)
    blend = tr.RenderScene(positions=scene.positions, faces=scene.faces, materials=[
        tr.Material(roughness_factor=0.0, alpha_mode="BLEND")])
    with pytest.warns(tr.NotImplementedWarning, match="BLEND"):
        assert "ssr" not in tr.Renderer(16, ssr=SSR()).plan(blend, environment=env)
    # skipped when asked but useless: identical to no SSR at all
    a = tr.Renderer(16, ssr=SSR())(rough, view, proj, environment=env).image
    b = tr.Renderer(16)(rough, view, proj, environment=env).image
    assert torch.equal(a, b)


@pytest.mark.parametrize("eye", [[0.0, 1e-4, 3.0], [0.0, -0.5, 3.0], [0.0, 0.9, 1e-3]])
def test_renderer_stress_grazing_below_and_inside(eye: list[float]) -> None:
    """Edge-on, from below the floor, almost above the quad: finite image and gradients."""
    scene, _, proj = _quad_scene()
    positions = scene.positions.clone().requires_grad_(True)
    scene.positions = positions
    view = look_at(eye, [0.0, 0.35, -1.0])
    env = _uniform_env(0.7)
    lights = tr.Lights(ambient=tr.sh_from_color(torch.tensor([[0.2, 0.2, 0.2]])))
    out = tr.Renderer(24, ssr=SSR(), raster=tr.RasterSettings(supersample=2))(
        scene, view, proj, lights=lights, environment=env)
    assert "ssr" in out.plan and bool(torch.isfinite(out.image).all())
    out.image.square().sum().backward()
    assert bool(torch.isfinite(positions.grad).all())


def test_renderer_backward_to_positions_where_rays_hit() -> None:
    """Found by scripts/stress.py: the march's state was built from depth that carried a
    gradient to the vertices, and its in-place updates broke the backward pass. The march
    is discrete: the image's gradient reaches the positions through the shading only."""
    scene, view, proj = _glow_scene()
    positions = scene.positions.clone().requires_grad_(True)
    scene.positions = positions
    out = tr.Renderer(32, ssr=SSR(edge_fade=0.0))(scene, view, proj,
                                                  environment=_uniform_env(0.5))
    assert float(out.plan.ssr) and "ssr" in out.plan
    out.image.sum().backward()
    assert positions.grad is not None and bool(torch.isfinite(positions.grad).all())


def test_plan_reads_a_roughness_factor_that_needs_grad() -> None:
    """A material fit makes roughness a 0-dim tensor that needs grad: the planner reads it
    without autograd's tensor-to-scalar warning."""
    scene, _, _ = _glow_scene()
    rough = torch.tensor(0.1, requires_grad=True)
    fit = tr.RenderScene(positions=scene.positions, faces=scene.faces,
                         materials=[tr.Material(roughness_factor=rough)])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert "ssr" in tr.Renderer(16, ssr=SSR()).plan(fit, environment=_uniform_env(0.5))
