"""tr.rasterize against the independent float64 reference (torchraster/testing/reference_raster.py).

First the reference itself is checked on hand-computed cases and against a second, scalar
clip-then-project implementation written here; then the engine is compared with it on hostile
triangle soups and real meshes: face ids must agree on >= 99.99 % of pixels, and every
disagreement must sit within EDGE_TOL_PX of a face boundary or on a depth tie; depth and
barycentrics must match where the face agrees.
"""

from __future__ import annotations

import pytest
import torch

import torchraster as tr
from torchraster.testing.reference_raster import (
    SOUP_KINDS,
    compare_fragments,
    error_ratios,
    load_mesh,
    pixel_centres,
    random_soup,
    random_view_clip,
    reference_rasterize,
)

DEPTH_TOL = {torch.float32: 1e-6, torch.float64: 1e-10}
BARY_TOL = {torch.float32: 1e-5, torch.float64: 1e-9}
MIN_AGREE = 0.9999


def _tri(*verts: tuple[float, float, float, float]) -> torch.Tensor:
    return torch.tensor([verts], dtype=torch.float64)


# ------------------------------------------------------------------ the reference on its own


def test_reference_hand_computed_triangle() -> None:
    """Lower-left half of the screen; the diagonal's pixel centres belong to the other half."""
    clip = _tri((-1, -1, 0.5, 1), (1, -1, 0.5, 1), (-1, 1, -0.5, 1))
    ref = reference_rasterize(clip, torch.tensor([[0, 1, 2]]), (4, 4))
    want = torch.tensor([[-1, -1, -1, -1], [0, -1, -1, -1], [0, 0, -1, -1], [0, 0, 0, -1]])
    assert torch.equal(ref.face_id[0], want)
    # pixel (3, 0): NDC (-0.75, -0.75): screen barycentrics (0.75, 0.125, 0.125)
    want_b = torch.tensor([0.75, 0.125, 0.125], dtype=torch.float64)
    assert torch.allclose(ref.bary[0, 3, 0], want_b)
    assert ref.depth[0, 3, 0].item() == pytest.approx(0.75 * 0.5 + 0.125 * 0.5 - 0.125 * 0.5)
    assert torch.isinf(ref.depth[0, 0, 0]) and (ref.bary[0, 0, 0] == 0).all()
    # the complementary triangle takes exactly the diagonal and the upper right
    other = reference_rasterize(
        torch.cat([clip, _tri((1, 1, 0, 1))], 1), torch.tensor([[1, 3, 2]]), (4, 4)
    )
    assert torch.equal((other.face_id[0] >= 0), want < 0)


def test_reference_perspective_correct_bary() -> None:
    """Scaling one vertex's clip coordinates by w keeps the screen triangle; the barycentrics
    become b_k / w_k renormalised (hand computed: (0.75, 0.0625, 0.125) / 0.9375)."""
    clip = _tri((-1, -1, 0, 1), (2, -2, 0, 2), (-1, 1, 0, 1))
    ref = reference_rasterize(clip, torch.tensor([[0, 1, 2]]), (4, 4))
    want = torch.tensor([0.75, 0.0625, 0.125], dtype=torch.float64) / 0.9375
    assert torch.allclose(ref.bary[0, 3, 0], want)


def test_reference_near_far_and_behind() -> None:
    """NDC z = 2x across the screen: only |x| <= 0.5 lies inside [-1, 1]; the same triangle
    with all coordinates negated (w < 0, behind the camera) projects identically but is empty."""
    clip = _tri((-1, -1, -2, 1), (1, -1, 2, 1), (-1, 1, -2, 1), (1, 1, 2, 1))
    faces = torch.tensor([[0, 1, 3], [0, 3, 2]])
    ref = reference_rasterize(clip, faces, (8, 8))
    x = pixel_centres(8, 8)[:, 0].view(8, 8)
    assert torch.equal(ref.face_id[0] >= 0, x.abs() <= 0.5)
    assert torch.allclose(ref.depth[0][x.abs() <= 0.5], 2 * x[x.abs() <= 0.5])
    behind = reference_rasterize(-clip, faces, (8, 8))
    assert (behind.face_id == -1).all()


def test_reference_ties_and_culling() -> None:
    clip = _tri((-1, -1, 0, 1), (1, -1, 0, 1), (-1, 1, 0, 1))
    faces = torch.tensor([[0, 2, 1], [0, 1, 2], [0, 1, 2]])  # CW first, then two CCW twins
    ref = reference_rasterize(clip, faces, (8, 8))
    assert set(ref.face_id.unique().tolist()) == {-1, 0}
    culled = reference_rasterize(clip, faces, (8, 8), cull_backfaces=True)
    assert set(culled.face_id.unique().tolist()) == {-1, 1}


def _clip_project_face(tri: torch.Tensor, pix: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Second, scalar method for one face: Sutherland-Hodgman clipping of the triangle against
    z >= -w and z <= w in clip space (which also gives w >= 0), projection, fan triangulation,
    screen-space interpolation of 1/w, b/w and z/w. Returns covered (P,), bary (P,3), z (P,)."""
    poly = [(tri[k], torch.eye(3, dtype=torch.float64)[k]) for k in range(3)]
    for sign in (1.0, -1.0):  # z + w >= 0, then w - z >= 0
        out = []
        for k in range(len(poly)):
            (p, bp), (q, bq) = poly[k], poly[(k + 1) % len(poly)]
            dp, dq = sign * p[2] + p[3], sign * q[2] + q[3]
            if dp >= 0:
                out.append((p, bp))
            if (dp >= 0) != (dq >= 0):
                t = dp / (dp - dq)
                out.append((p + t * (q - p), bp + t * (bq - bp)))
        poly = out
        if len(poly) < 3:
            break
    npix = pix.shape[0]
    covered = torch.zeros(npix, dtype=torch.bool)
    bary = torch.zeros(npix, 3, dtype=torch.float64)
    z = torch.full((npix,), float("inf"), dtype=torch.float64)
    for k in range(1, len(poly) - 1):
        (p0, b0), (p1, b1), (p2, b2) = poly[0], poly[k], poly[k + 1]
        s = [p[:2] / p[3] for p in (p0, p1, p2)]
        area = (s[1][0] - s[0][0]) * (s[2][1] - s[0][1]) - (s[1][1] - s[0][1]) * (s[2][0] - s[0][0])
        if area == 0:
            continue

        def edge(a: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
            return (c[0] - a[0]) * (pix[:, 1] - a[1]) - (c[1] - a[1]) * (pix[:, 0] - a[0])

        lam = torch.stack([edge(s[1], s[2]), edge(s[2], s[0]), edge(s[0], s[1])], -1) / area
        inside = (lam >= 0).all(-1) & ~covered
        inv_w = lam @ torch.stack([1 / p0[3], 1 / p1[3], 1 / p2[3]])
        bw = lam @ torch.stack([b0 / p0[3], b1 / p1[3], b2 / p2[3]])
        zw = lam @ torch.stack([p0[2] / p0[3], p1[2] / p1[3], p2[2] / p2[3]])
        covered |= inside
        bary[inside] = (bw / inv_w[:, None])[inside]
        z[inside] = zw[inside]
    return covered, bary, z


@pytest.mark.parametrize("weights", [(2, 0, 0, 1, 1, 0), (1, 0, 0, 0, 0, 2)])
def test_reference_matches_clip_then_project(weights: tuple[float, ...]) -> None:
    """The 2D-homogeneous reference and a clip-then-project scalar rasterizer agree on soups
    with near/far crossers and faces behind the camera (pixels away from boundaries)."""
    gen = torch.Generator().manual_seed(3)
    clip, faces, _ = random_soup(gen, 1, 60, weights=weights)
    h = w = 24
    ref = reference_rasterize(clip, faces, (h, w))
    pix = pixel_centres(h, w)
    best_z = torch.full((h * w,), float("inf"), dtype=torch.float64)
    best_f = torch.full((h * w,), -1)
    best_b = torch.zeros(h * w, 3, dtype=torch.float64)
    for f in range(faces.shape[0]):
        if torch.linalg.matrix_rank(clip[0, faces[f]][:, [0, 1, 3]]) < 3:
            continue
        cov, b, z = _clip_project_face(clip[0, faces[f]], pix)
        better = cov & (z < best_z)
        best_z[better], best_f[better], best_b[better] = z[better], f, b[better]
    stats = compare_fragments(
        best_f.view(1, h, w), best_b.view(1, h, w, 3), best_z.view(1, h, w), clip, faces, ref
    )
    assert stats["covered"] > 200
    assert stats["unexplained"] == 0, stats
    assert stats["max_depth_err"] < 1e-9 and stats["max_bary_err"] < 1e-9, stats


# ------------------------------------------------------------------ engine vs reference


def _engine_vs_reference(
    clip64: torch.Tensor,
    faces: torch.Tensor,
    res: tuple[int, int],
    dtype: torch.dtype,
    **kw: object,
) -> dict:
    clip = clip64.to(dtype)
    frags = tr.rasterize(clip, faces, resolution=res, **kw)
    assert frags.face_id.shape == (clip.shape[0], *res) and frags.face_id.dtype == torch.int64
    assert frags.bary.shape == (clip.shape[0], *res, 3) and frags.bary.dtype == dtype
    assert frags.depth.shape == (clip.shape[0], *res) and frags.depth.dtype == dtype
    ref = reference_rasterize(clip.double(), faces, res, **kw)  # same rounded inputs
    stats = compare_fragments(frags.face_id, frags.bary, frags.depth, clip, faces, ref)
    empty = frags.face_id < 0
    assert torch.isinf(frags.depth[empty]).all() and (frags.depth[empty] > 0).all()
    assert (frags.bary[empty] == 0).all()
    return stats


def _summary(stats: dict) -> dict:
    return {k: v for k, v in stats.items() if not isinstance(v, torch.Tensor)}


def _assert_agrees(stats: dict, dtype: torch.dtype, strict: bool = False) -> dict:
    """Face ids agree (disagreements explained), depth / barycentrics within DEPTH_TOL /
    BARY_TOL, or, on ill-conditioned pixels (slivers, huge near-plane crossers), within the
    float rounding bound ROUNDOFF_FACTOR * u * cond; ``strict``: the fixed tolerances only."""
    assert stats["unexplained"] == 0, _summary(stats)
    # Depth ties are left out of the agreement fraction: they are pixels where two faces are
    # at the same depth up to rounding, e.g. the duplicate faces with reversed winding in
    # bunny-res2, whose float depths differ by 1e-14 in float64 (the reference) but the other
    # way round in float32, so "lower index wins" legitimately picks either.
    assert 1 - (stats["disagree"] - stats["depth_tie"]) / stats["pixels"] >= MIN_AGREE, (
        _summary(stats))
    ratios = error_ratios(stats, dtype, DEPTH_TOL[dtype], BARY_TOL[dtype])
    info = {**_summary(stats), **ratios}
    if strict:
        assert stats["max_depth_err"] <= DEPTH_TOL[dtype], info
        assert stats["max_bary_err"] <= BARY_TOL[dtype], info
    assert ratios["depth_ratio"] <= 1 and ratios["bary_ratio"] <= 1, info
    return info


MIXES = {
    "all": (4, 2, 1, 0.5, 1, 1),
    "slivers_degenerate": (0, 3, 1, 0, 0, 0),
    "near_behind": (1, 0, 0, 1, 2, 0),
    "far": (1, 0, 0, 0, 0, 2),
}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("mix", list(MIXES))
def test_soup_matches_reference(mix: str, dtype: torch.dtype) -> None:
    gen = torch.Generator().manual_seed(10 + list(MIXES).index(mix))
    clip, faces, kind = random_soup(gen, 2, 250, weights=MIXES[mix])
    stats = _engine_vs_reference(clip, faces, (48, 64), dtype)
    _assert_agrees(stats, dtype)
    assert stats["covered"] > 100, stats


@pytest.mark.parametrize("cull", [False, True])
def test_soup_culling_matches_reference(cull: bool) -> None:
    gen = torch.Generator().manual_seed(21)
    clip, faces, _ = random_soup(gen, 2, 250, weights=(4, 1, 1, 0.3, 1, 1))
    stats = _engine_vs_reference(clip, faces, (40, 40), torch.float32, cull_backfaces=cull)
    _assert_agrees(stats, torch.float32)


@pytest.mark.parametrize("res", [(5, 30), (30, 5), (3, 3)])
def test_thin_frames_match_reference(res: tuple[int, int]) -> None:
    """Frames narrower than the blocks of small triangles in one direction: the blocks are
    clamped to the frame per axis (rows to H, columns to W)."""
    gen = torch.Generator().manual_seed(23)
    clip, faces, _ = random_soup(gen, 2, 150, weights=(4, 1, 1, 0.3, 1, 1))
    stats = _engine_vs_reference(clip, faces, res, torch.float32)
    _assert_agrees(stats, torch.float32)
    assert stats["covered"] > 5, stats


def test_face_ranges_match_reference() -> None:
    gen = torch.Generator().manual_seed(22)
    clip, faces, _ = random_soup(gen, 3, 200, weights=(4, 1, 1, 0.3, 1, 1))
    ranges = torch.tensor([[0, 200], [50, 120], [199, 200]])
    stats = _engine_vs_reference(clip, faces, (32, 32), torch.float32, face_ranges=ranges)
    _assert_agrees(stats, torch.float32)


def test_exact_ties_go_to_lower_face_index() -> None:
    """Identical triangles (also through duplicated vertices) tie exactly on every pixel: the
    lowest face index wins whatever the order of the face list."""
    tri = torch.tensor([[-0.9, -0.8, 0.1, 1.0], [0.7, -0.6, 0.3, 1.3], [-0.2, 0.9, -0.2, 0.8]])
    clip = torch.cat([tri, tri])[None]  # vertices 3..5 duplicate 0..2
    faces = torch.tensor([[0, 1, 2], [3, 4, 5], [0, 1, 2], [3, 4, 5]])
    for perm in ([0, 1, 2, 3], [3, 2, 1, 0], [1, 3, 0, 2]):
        f = faces[perm]
        frags = tr.rasterize(clip, f, resolution=(16, 16))
        ids = frags.face_id[frags.face_id >= 0]
        assert ids.numel() > 50
        assert (ids == 0).all(), (perm, ids.unique())
        ref = reference_rasterize(clip, f, (16, 16))
        assert torch.equal(ref.face_id, frags.face_id)


MESHES = {
    "suzanne": "meshes/suzanne.obj",
    "spot": "meshes/spot/spot_triangulated.obj",
    "fandisk": "meshes/fandisk.obj",
    "bunny-res2": "meshes/stanford-bunny-res2.ply",
}


def _mesh_views(path: str, seed: int, n_views: int) -> tuple[torch.Tensor, torch.Tensor]:
    verts, faces = load_mesh(path)
    gen = torch.Generator().manual_seed(seed)
    clips = [random_view_clip(verts, gen) for _ in range(n_views)]
    # and one close view whose near plane (0.5) cuts through the mesh
    clips.append(random_view_clip(verts, gen, distance=(0.9, 1.1), near=0.5))
    return torch.stack(clips), faces


def _mesh_case(shared_data, name: str, cull: bool, res: tuple[int, int], n_views: int) -> None:
    clip, faces = _mesh_views(str(shared_data / MESHES[name]), seed=len(name), n_views=n_views)
    stats = _engine_vs_reference(clip, faces, res, torch.float32, cull_backfaces=cull)
    _assert_agrees(stats, torch.float32)
    assert stats["covered"] > 0.1 * stats["pixels"], stats


@pytest.mark.parametrize("cull", [False, True])
@pytest.mark.parametrize("name", ["suzanne", "spot"])
def test_real_mesh_matches_reference(shared_data, name: str, cull: bool) -> None:
    _mesh_case(shared_data, name, cull, (48, 48), n_views=1)


@pytest.mark.slow
@pytest.mark.parametrize("cull", [False, True])
@pytest.mark.parametrize("name", list(MESHES))
def test_real_mesh_matches_reference_slow(shared_data, name: str, cull: bool) -> None:
    _mesh_case(shared_data, name, cull, (64, 64), n_views=5)


def test_soup_kinds_all_present() -> None:
    """The hostile soup really contains every kind (guards the generator)."""
    gen = torch.Generator().manual_seed(0)
    _, _, kind = random_soup(gen, 1, 400)
    assert kind.bincount(minlength=len(SOUP_KINDS)).min() > 0
