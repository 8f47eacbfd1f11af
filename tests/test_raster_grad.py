"""Gradients: float64 gradcheck of interpolate w.r.t. vertex attributes and clip positions
(through the barycentrics), and finite outputs / gradients for hostile inputs."""

from __future__ import annotations

import pytest
import torch

import torchraster as tr
from torchraster.testing.reference_raster import (
    boundary_distance_px,
    perspective_matrix,
    pixel_centres,
    random_soup,
    to_clip,
)

RES = (8, 8)
MIN_EDGE_DIST_PX = 1e-3  # pixel centres this far from every boundary line: FD steps (1e-6)
# move edges by ~1e-5 px, so coverage stays fixed during gradcheck


def _scene() -> tuple[torch.Tensor, torch.Tensor]:
    """Three overlapping triangles in float64 clip space (B=2): a plain one, one with
    perspective (different w), and one crossing the near plane with a vertex behind the
    camera. Returns clip (2, 9, 4), faces (3, 3)."""
    clip = torch.tensor(
        [
            [-0.83, -0.71, 0.20, 1.0], [0.77, -0.52, 0.10, 1.0], [-0.31, 0.88, 0.30, 1.0],
            [-0.45, -0.95, 0.4, 1.7], [1.45, 0.13, -0.2, 1.3], [0.20, 1.20, 0.0, 2.1],
            [-1.10, 0.30, -1.9, 1.2], [0.90, 0.55, 0.5, 1.1], [-0.613, 0.41, 0.7, -0.4],
        ],
        dtype=torch.float64,
    )
    clip2 = clip.clone()
    clip2[:, 0] = clip[:, 0] * 0.93 + 0.031 * clip[:, 3]  # shifted and squeezed in x
    return torch.stack([clip, clip2]), torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8]])


def _min_boundary_distance(clip: torch.Tensor, faces: torch.Tensor) -> float:
    """Smallest distance (px) of any pixel centre to any boundary of any face."""
    pix = pixel_centres(*RES)
    n = pix.shape[0]
    out = float("inf")
    for b in range(clip.shape[0]):
        for f in range(faces.shape[0]):
            d = boundary_distance_px(clip[b], faces, torch.full((n,), f), pix, RES)
            out = min(out, float(d.min()))
    return out


def test_scene_is_away_from_edges_and_covers() -> None:
    clip, faces = _scene()
    assert _min_boundary_distance(clip, faces) > MIN_EDGE_DIST_PX
    fid = tr.rasterize(clip, faces, resolution=RES).face_id
    assert set(fid.unique().tolist()) == {-1, 0, 1, 2}


def test_gradcheck_interpolate_wrt_vertex_attrs() -> None:
    clip, faces = _scene()
    frags = tr.rasterize(clip, faces, resolution=RES)
    attrs = torch.randn(2, 9, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a: tr.interpolate(a, frags, faces), (attrs,))
    shared = torch.randn(9, 2, dtype=torch.float64, requires_grad=True)  # (V, C) form
    assert torch.autograd.gradcheck(lambda a: tr.interpolate(a, frags, faces), (shared,))


def test_gradcheck_interpolate_wrt_clip_pos() -> None:
    clip, faces = _scene()
    clip = clip.clone().requires_grad_(True)
    attrs = torch.randn(2, 9, 3, dtype=torch.float64)

    def f(c: torch.Tensor) -> torch.Tensor:
        return tr.interpolate(attrs, tr.rasterize(c, faces, resolution=RES), faces)

    assert torch.autograd.gradcheck(f, (clip,), eps=1e-6, atol=1e-6)


def test_gradcheck_bary_and_depth_wrt_clip_pos() -> None:
    clip, faces = _scene()
    clip = clip.clone().requires_grad_(True)

    def f(c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        frags = tr.rasterize(c, faces, resolution=RES)
        covered = frags.face_id >= 0
        return frags.bary, torch.where(covered, frags.depth, torch.zeros_like(frags.depth))

    assert torch.autograd.gradcheck(f, (clip,), eps=1e-6, atol=1e-6)


def _hostile_scenes() -> list[tuple[str, torch.Tensor, torch.Tensor]]:
    gen = torch.Generator().manual_seed(5)
    scenes = []
    soup, faces, _ = random_soup(gen, 2, 120)
    scenes.append(("soup", soup.float(), faces))
    scenes.append(("huge_1e8", (soup * 1e8).float(), faces))
    sl, sf, _ = random_soup(gen, 2, 120, weights=(0, 1, 1, 0, 0, 0))
    scenes.append(("slivers", sl.float(), sf))
    # extreme near / far: near 1e-6, far 1e8, geometry from 1e-6 to 1e8 away, float32 throughout
    tri = torch.randn(2, 300, 3, generator=gen, dtype=torch.float64)
    scale = 10 ** (-6 + 14 * torch.rand(2, 100, 1, 1, generator=gen, dtype=torch.float64))
    pts = (tri.view(2, 100, 3, 3) * 0.3 + torch.tensor([0, 0, -1.0], dtype=torch.float64)) * scale
    mat = perspective_matrix(60.0, 1.0, 1e-6, 1e8)
    scenes.append(("near_far_1e-6_1e8", to_clip(pts.view(2, 300, 3), mat).float(),
                   torch.arange(300).view(100, 3)))
    # vertices exactly at w = 0 and straddling it by tiny amounts
    w0 = torch.randn(2, 90, 4, generator=gen)
    w0[:, 0::3, 3] = 0.0
    w0[:, 1::3, 3] = 1e-38
    w0[:, 2::3, 3] = w0[:, 2::3, 3].abs()
    scenes.append(("w_zero", w0, torch.arange(90).view(30, 3)))
    return scenes


@pytest.mark.parametrize("cull", [False, True])
def test_hostile_inputs_finite_outputs_and_gradients(cull: bool) -> None:
    for name, clip, faces in _hostile_scenes():
        clip = clip.clone().requires_grad_(True)
        attrs = torch.randn(clip.shape[0], clip.shape[1], 4, requires_grad=True)
        frags = tr.rasterize(clip, faces, resolution=(24, 32), cull_backfaces=cull)
        img = tr.interpolate(attrs, frags, faces)
        hit = frags.face_id >= 0
        assert torch.isfinite(img).all(), name
        assert torch.isfinite(frags.bary).all(), name
        assert torch.isfinite(frags.depth[hit]).all(), name
        assert (frags.depth[hit].abs() <= 1 + 1e-5).all(), name
        assert torch.isinf(frags.depth[~hit]).all(), name
        loss = (img * torch.randn_like(img)).sum() + frags.depth[hit].sum()
        loss.backward()
        assert torch.isfinite(clip.grad).all(), name
        assert torch.isfinite(attrs.grad).all(), name


@pytest.mark.parametrize("scale", [1e-30, 1e-20, 1e-10, 1e8, 1e15, 1e18, 1e19])
def test_clip_scale_invariance(scale: float) -> None:
    """Homogeneous clip positions scaled by any s > 0 describe the same image: face ids,
    barycentrics and depth must not change (up to float32 rounding) and gradients stay
    finite, from denormal-range products (1e-30) to near-overflow ones (1e18)."""
    gen = torch.Generator().manual_seed(6)
    soup, faces, _ = random_soup(gen, 2, 120)
    base = tr.rasterize(soup.float(), faces, resolution=(24, 32))
    clip = (soup * scale).float().requires_grad_(True)
    frags = tr.rasterize(clip, faces, resolution=(24, 32))
    hit = base.face_id >= 0
    assert torch.equal(frags.face_id, base.face_id)
    assert (frags.bary - base.bary).abs().max() < 1e-4
    assert (frags.depth[hit] - base.depth[hit]).abs().max() < 1e-4
    img = tr.interpolate(torch.randn(clip.shape[1], 3), frags, faces)
    (img * torch.randn_like(img)).sum().backward()
    assert torch.isfinite(clip.grad).all()
