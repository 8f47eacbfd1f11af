"""Soft rasterization (torchraster.raster.soft): distances against a float64 brute force,
the hard limit sigma -> 0, gradients (gradcheck, outside the silhouette) and hostile
geometry (slivers, degenerate faces, near-plane crossers)."""

from __future__ import annotations

import math

import pytest
import torch

import torchraster as tr
from torchraster.raster.soft import SoftFragments, soft_blend, soft_rasterize

try:
    from torchraster.testing import reference_raster as ref
except ImportError:  # the reference's former home, tests/reference_raster.py
    import reference_raster as ref  # type: ignore[no-redef]


def _segment_distance(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Distance from points p (P, 2) to segments a-b (F, 2) -> (F, P), float64."""
    ab = (b - a)[:, None]
    ap = p[None] - a[:, None]
    t = ((ap * ab).sum(-1) / (ab * ab).sum(-1)).clamp(0, 1)
    return (ap - t[..., None] * ab).norm(dim=-1)


def reference_distance(clip: torch.Tensor, faces: torch.Tensor, res) -> torch.Tensor:
    """Signed pixel distance (F, H*W) from every pixel centre to every face's screen triangle
    (positive inside), brute force in float64, for faces in front of the camera."""
    h, w = res
    v = clip.double()[faces]  # (F, 3, 4)
    assert (v[..., 3] > 0).all()
    x = (v[..., 0] / v[..., 3] + 1) * w / 2 - 0.5
    y = (1 - v[..., 1] / v[..., 3]) * h / 2 - 0.5
    ndc = ref.pixel_centres(h, w)
    p = torch.stack([(ndc[:, 0] + 1) * w / 2 - 0.5, (1 - ndc[:, 1]) * h / 2 - 0.5], -1)
    s = torch.stack([x, y], -1)  # (F, 3, 2)
    d = torch.stack([_segment_distance(p, s[:, i], s[:, (i + 1) % 3]) for i in range(3)])
    cross = []
    for i in range(3):
        a, b = s[:, i], s[:, (i + 1) % 3]
        cross.append((b - a)[:, None, 0] * (p[None, :, 1] - a[:, None, 1])
                     - (b - a)[:, None, 1] * (p[None, :, 0] - a[:, None, 0]))
    cross = torch.stack(cross)  # (3, F, P)
    inside = (cross >= 0).all(0) | (cross <= 0).all(0)
    dist = d.min(0).values
    return torch.where(inside, dist, -dist)


def _two_triangles(dtype=torch.float64):
    clip = torch.tensor([[[-0.6, -0.5, 0.1, 1.0], [0.4, -0.6, 0.2, 1.1], [-0.1, 0.5, 0.3, 0.9],
                          [-0.2, -0.3, -0.2, 1.0], [0.7, -0.1, -0.1, 1.2],
                          [0.3, 0.7, 0.0, 1.0]]], dtype=dtype)
    return clip, torch.tensor([[0, 1, 2], [3, 4, 5]])


# ------------------------------------------------------------------ distances and selection


def test_distances_and_selection_match_brute_force():
    gen = torch.Generator().manual_seed(0)
    n, res = 12, (24, 28)
    centre = torch.rand(n, 1, 2, generator=gen, dtype=torch.float64) * 1.6 - 0.8
    xy = centre + 0.25 * torch.randn(n, 3, 2, generator=gen, dtype=torch.float64)
    wz = torch.rand(n, 1, 2, generator=gen, dtype=torch.float64).expand(n, 3, 2)
    clip = torch.cat([xy * (1 + wz[..., 1:]), wz[..., :1] - 0.5, 1 + wz[..., 1:]], -1)
    clip = clip.reshape(1, -1, 4)
    faces = torch.arange(3 * n).view(n, 3)
    sigma = 0.4
    sf = soft_rasterize(clip, faces, res, sigma=sigma, k=n)
    ref = reference_distance(clip[0], faces, res)  # (F, P)
    cutoff = sigma * math.log(1 / 1e-4 - 1)
    fid = sf.face_id.view(-1, n)  # (P, K)
    dist = sf.dist.view(-1, n)
    for f in range(n):
        slot = fid == f
        kept = slot.any(1)
        clear = (ref[f] - (-cutoff)).abs() > 1e-6
        assert torch.equal(kept[clear], (ref[f] >= -cutoff)[clear])
        assert torch.allclose(dist[slot], ref[f][kept], atol=1e-9)
    expect = torch.sigmoid(sf.dist / sigma)
    valid = sf.face_id >= 0
    assert torch.allclose(sf.prob[valid], expect[valid]) and (sf.prob[~valid] == 0).all()
    assert (sf.depth[valid] <= 1).all() and torch.isinf(sf.depth[~valid]).all()
    # slots are ordered nearest first; the empty ones come last
    assert (sf.depth[..., 1:] >= sf.depth[..., :-1] - 1e-6).all()


def test_k_nearest_by_depth_when_more_faces_than_slots():
    """Five stacked copies of a triangle at increasing depth, k = 2: the two nearest."""
    base = torch.tensor([[-0.5, -0.5], [0.5, -0.5], [0.0, 0.5]], dtype=torch.float64)
    clip = torch.cat([torch.cat([base, torch.full((3, 1), z), torch.ones(3, 1)], 1)
                      for z in (0.5, -0.1, 0.3, -0.4, 0.0)])[None]
    faces = torch.arange(15).view(5, 3)
    sf = soft_rasterize(clip, faces, (16, 16), sigma=0.5, k=2)
    valid = sf.face_id[..., 0] >= 0
    assert valid.sum() > 50
    assert (sf.face_id[valid] == torch.tensor([3, 1])).all()


# ------------------------------------------------------------------ the hard limit


@pytest.mark.parametrize("squared", [False, True])
def test_small_sigma_converges_to_hard_coverage(squared):
    gen = torch.Generator().manual_seed(3)
    clip, faces, kind = ref.random_soup(gen, 1, 40)
    keep = (kind == 0).nonzero().squeeze(1)  # ordinary triangles
    faces = faces[keep]
    res = (40, 40)
    hard = tr.rasterize(clip, faces, res)
    errors = []
    for sigma in (1e-1, 1e-2, 1e-3):
        sf = soft_rasterize(clip, faces, res, sigma=sigma ** 2 if squared else sigma, k=4)
        errors.append(float((sf.silhouette()[:, 0] - hard.mask[:, 0]).abs().sum()))
        if sigma == 1e-3:
            near = (sf.face_id[..., 0] == hard.face_id) | (sf.dist.abs() < 1e-2).any(-1)
            assert near.all()
    assert errors[0] > errors[1] > errors[2] and errors[2] < 0.05 * errors[0]


def test_blend_of_sharp_profile_is_the_hard_render():
    clip, faces = _two_triangles()
    colors = torch.rand(6, 3, dtype=torch.float64)
    hard = tr.interpolate(colors, tr.rasterize(clip, faces, (16, 16)), faces)
    sf = soft_rasterize(clip, faces, (16, 16), sigma=1e-4, k=2)
    rgba = soft_blend(sf.interpolate(colors, faces), sf, gamma=1e-6)
    clear = sf.dist.abs().amin(-1) > 1e-2
    assert torch.allclose(rgba[:, :3].permute(0, 2, 3, 1)[clear],
                          hard.permute(0, 2, 3, 1)[clear], atol=1e-5)
    mask = tr.rasterize(clip, faces, (16, 16)).mask
    assert torch.allclose(rgba[:, 3:][clear[:, None]], mask[clear[:, None]], atol=1e-6)


def test_blend_background_and_shapes():
    clip, faces = _two_triangles(torch.float32)
    sf = soft_rasterize(clip, faces, (12, 10), sigma=0.3, k=3)
    assert isinstance(sf, SoftFragments)
    assert sf.face_id.shape == (1, 12, 10, 3) and sf.bary.shape == (1, 12, 10, 3, 3)
    colors = sf.interpolate(torch.ones(6, 2), faces)
    assert colors.shape == (1, 12, 10, 3, 2)
    bg = torch.tensor([0.25, 0.5])
    rgba = soft_blend(colors, sf, background=bg)
    assert rgba.shape == (1, 3, 12, 10)
    empty = (sf.face_id < 0).all(-1)
    assert torch.allclose(rgba[0, :2].permute(1, 2, 0)[empty[0]], bg)
    assert torch.allclose(rgba[:, 2:], sf.silhouette())
    image = torch.rand(1, 2, 12, 10)
    assert torch.allclose(soft_blend(colors, sf, background=image)[0, :2][:, empty[0]],
                          image[0][:, empty[0]])
    with pytest.raises(ValueError, match="colors"):
        soft_blend(colors[..., :2, :], sf)
    with pytest.raises(ValueError, match="sigma"):
        soft_rasterize(clip, faces, 8, sigma=0.0)
    with pytest.raises(ValueError, match="k"):
        soft_rasterize(clip, faces, 8, k=0)


# ------------------------------------------------------------------ gradients


def test_gradcheck_probabilities_bary_depth():
    clip, faces = _two_triangles()

    def f(c):
        sf = soft_rasterize(c, faces, (6, 6), sigma=0.7, k=2)
        valid = sf.face_id >= 0
        return sf.prob, sf.bary, torch.where(valid, sf.depth, 0.0)

    assert torch.autograd.gradcheck(f, (clip.clone().requires_grad_(True),))


@pytest.mark.parametrize("squared", [False, True])
def test_gradcheck_blend(squared):
    clip, faces = _two_triangles()
    colors = torch.rand(6, 3, dtype=torch.float64, requires_grad=True)

    def f(c, col):
        sf = soft_rasterize(c, faces, (5, 6), sigma=0.6 if not squared else 0.5, k=2,
                            squared=squared)
        return soft_blend(sf.interpolate(col, faces), sf, gamma=0.05, background=0.3)

    assert torch.autograd.gradcheck(f, (clip.clone().requires_grad_(True), colors))


def test_gradient_outside_the_silhouette():
    """A pixel 3 sigma outside the triangle: no hard coverage, yet its soft value pulls the
    triangle towards it (the gradient moves the nearest edge)."""
    sigma = 0.5
    clip = torch.tensor([[[-0.5, -0.5, 0, 1], [0.5, -0.5, 0, 1], [0.0, 0.5, 0, 1]]],
                        dtype=torch.float64, requires_grad=True)
    faces = torch.tensor([[0, 1, 2]])
    res = (16, 16)
    sf = soft_rasterize(clip, faces, res, sigma=sigma, k=1)
    hard = tr.rasterize(clip, faces, res)
    # bottom edge at NDC y = -0.5, i.e. pixel y = 11.5: row 12 is 0.5 px outside, row 13
    # 1.5 px (3 sigma) outside
    i, j = 13, 8
    assert hard.face_id[0, i, j] == -1
    assert sf.dist[0, i, j, 0].item() == pytest.approx(-1.5)
    rgba = soft_blend(sf.interpolate(torch.ones(3, 1, dtype=torch.float64), faces), sf)
    rgba[0, 1, i, j].backward()  # alpha of that pixel
    g = clip.grad[0]
    assert g.abs().sum() > 1e-3
    assert g[0, 1] < 0 and g[1, 1] < 0  # the bottom edge moving down (-y) raises alpha ...
    assert abs(g[2, 1]) < 1e-12  # ... the apex does not matter for this pixel


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_hostile_soup_is_finite(dtype):
    """Slivers, degenerate faces, near-plane crossers and faces behind the camera."""
    gen = torch.Generator().manual_seed(7)
    clip, faces, kind = ref.random_soup(gen, 2, 60)
    assert {1, 2, 3, 4} <= set(kind.tolist())
    clip = clip.to(dtype).requires_grad_(True)
    colors = torch.rand(clip.shape[1], 3, dtype=dtype)
    sf = soft_rasterize(clip, faces, (32, 32), sigma=0.8, k=4)
    rgba = soft_blend(sf.interpolate(colors, faces), sf, gamma=1e-2)
    assert torch.isfinite(rgba).all() and (sf.face_id >= 0).any()
    valid = sf.face_id >= 0
    assert torch.isfinite(sf.dist[valid]).all() and torch.isfinite(sf.depth[valid]).all()
    assert ((sf.bary[valid] >= 0) & (sf.bary[valid] <= 1 + 1e-5)).all()
    (rgba.square().sum() + sf.dist[valid].sum() + sf.depth[valid].sum()).backward()
    assert torch.isfinite(clip.grad).all() and clip.grad.abs().sum() > 0


def test_near_plane_crosser_takes_one_slot():
    """A big face crossing the near plane (clipped into several screen triangles) holds one
    slot per pixel; where it covers, probabilities follow the hard coverage."""
    clip = torch.tensor([[[-2.0, -1.5, -3.0, -1.0], [1.5, -1.0, 0.5, 1.5],
                          [0.0, 1.5, 0.9, 2.0]]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2]])
    hard = tr.rasterize(clip, faces, (24, 24))
    assert (hard.face_id >= 0).sum() > 20
    sf = soft_rasterize(clip, faces, (24, 24), sigma=0.5, k=3)
    assert ((sf.face_id >= 0).sum(-1) <= 1).all()
    assert (sf.face_id[..., 1:] < 0).all()  # the freed slots come last
    clear = sf.dist[..., 0].abs() > 1e-3
    assert torch.equal((sf.prob[..., 0] > 0.5)[clear], (hard.face_id >= 0)[clear])
    inside = hard.face_id >= 0
    assert torch.allclose(sf.bary[..., 0, :][inside], hard.bary[inside], atol=1e-9)
    assert torch.allclose(sf.depth[..., 0][inside], hard.depth[inside], atol=1e-9)


def test_chunked_checkpointed_pass_matches():
    """A tiny memory budget (many chunks, activation checkpointing): same values and
    gradients."""
    clip, faces = _two_triangles()
    grads = []
    outs = []
    for budget in (96 * 2**20, 1):
        c = clip.clone().requires_grad_(True)
        sf = soft_rasterize(c, faces, (48, 48), sigma=0.5, k=2, memory_budget=budget)
        loss = soft_blend(sf.interpolate(torch.rand(6, 3, dtype=torch.float64,
                                                    generator=torch.Generator().manual_seed(0)),
                                         faces), sf, gamma=0.1)
        loss.square().sum().backward()
        grads.append(c.grad)
        outs.append(loss.detach())
    assert torch.allclose(outs[0], outs[1]) and torch.allclose(grads[0], grads[1])


def test_soft_on_device_names_its_factories(device, dtype):
    from test_device import _FactoriesWithoutDevice

    clip = torch.tensor([[[-2.0, -1.5, -3.0, -1.0], [1.5, -1.0, 0.5, 1.5], [0.0, 1.5, 0.9, 2.0],
                          [-0.5, -0.5, 0.1, 1], [0.5, -0.5, 0.2, 1], [0.0, 0.5, 0.3, 1]]],
                        dtype=dtype, device=device, requires_grad=True)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]], device=device)
    mode = _FactoriesWithoutDevice()
    with mode:
        sf = soft_rasterize(clip, faces, (48, 40), sigma=0.5, k=3, memory_budget=1)
        rgba = soft_blend(sf.interpolate(torch.ones(6, 3, dtype=dtype, device=device), faces),
                          sf, background=torch.zeros(3, dtype=dtype, device=device))
        rgba.sum().backward()
    assert not mode.found, sorted(mode.found)
    assert rgba.device.type == torch.device(device).type and rgba.dtype == dtype
    assert torch.isfinite(clip.grad).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_extreme_vertices_are_finite(dtype):
    """A vertex at w = 1e-20 (projects ~1e20 viewports away: the guard band clips it), one at
    the eye (0, 0, 0, 0), a sliver and an exactly degenerate face."""
    clip = torch.tensor([[[1.0, 0.0, 0.0, 1e-20], [-0.5, -0.5, 0.0, 1.0], [0.5, -0.3, 0.1, 1.0],
                          [0.0, 0.0, 0.0, 0.0], [-0.4, 0.6, 0.2, 1.0], [0.6, 0.5, 0.2, 1.0],
                          [-0.9, 0.1, 0.3, 1.0], [0.9, 0.1 + 1e-6, 0.3, 1.0],
                          [0.0, 0.1 + 3e-6, 0.3, 1.0]]], dtype=dtype, requires_grad=True)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8], [1, 1, 2]])
    sf = soft_rasterize(clip, faces, (32, 32), sigma=0.5, k=4)
    rgba = soft_blend(sf.interpolate(torch.rand(9, 3, dtype=dtype), faces), sf, gamma=1e-2)
    valid = sf.face_id >= 0
    assert {0, 2} <= set(sf.face_id[valid].tolist()) and 3 not in sf.face_id[valid].tolist()
    assert torch.isfinite(sf.dist[valid]).all() and torch.isfinite(sf.depth[valid]).all()
    (rgba.square().sum() + sf.dist[valid].sum()).backward()
    assert torch.isfinite(clip.grad).all()
