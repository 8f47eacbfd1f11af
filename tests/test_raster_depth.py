"""Depth precision: two parallel planes 1e-4 apart in relative depth, far / near = 1e6.

With ``reverse_z=True`` (NDC z ~ -near/d: float32 keeps its relative precision for 1/d) the
nearer plane wins everywhere, in float32 throughout (world positions, matrices, clip
positions, rasterizer). With the standard projection (NDC z ~ 1 - 2 near/d) both planes round
to the same float32 depth at that range, and the test documents that it then shows the wrong
plane on some pixels: the reason reverse-Z exists.
"""

from __future__ import annotations

import math

import pytest
import torch

import torchraster as tr

NEAR, FAR = 0.01, 1e4  # far / near = 1e6
DIST = 1000.0  # distance of the nearer plane (at 1/10 of the far plane)
GAP = 1e-4  # relative depth gap between the two planes
RES = (32, 32)
FOV = 50.0


def _two_planes(far: float, reverse_z: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Clip positions (1, 8, 4) float32 of two parallel, slightly tilted quads, the farther one
    listed FIRST (faces 0, 1) so the lower-index tie-break would pick the wrong one; faces
    2, 3 are the nearer quad."""
    quads = []
    for d in (DIST * (1 + GAP), DIST):  # far quad first
        half = 1.5 * d * math.tan(math.radians(FOV) / 2)
        xy = torch.tensor([[-half, -half], [half, -half], [half, half], [-half, half]])
        z = -d + 0.05 * xy[:, 0] + 0.03 * xy[:, 1]  # tilted; the same tilt for both
        quads.append(torch.cat([xy, z[:, None]], -1))
    verts = torch.cat(quads).float()[None]
    view = tr.camera.look_at([0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0])
    proj = tr.camera.perspective(FOV, 1.0, NEAR, far, reverse_z=reverse_z)
    clip = tr.camera.transform_points(verts, proj @ view)
    assert clip.dtype == torch.float32
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    return clip, faces


def _wrong_fraction(far: float, reverse_z: bool) -> float:
    clip, faces = _two_planes(far, reverse_z)
    fid = tr.rasterize(clip, faces, resolution=RES).face_id
    assert (fid >= 0).all()
    return float((fid < 2).float().mean())


@pytest.mark.parametrize("far", [FAR, math.inf])
def test_reverse_z_resolves_1e4_relative_gap_at_1e6_range(far: float) -> None:
    assert _wrong_fraction(far, reverse_z=True) == 0.0


def test_standard_projection_fails_at_this_range() -> None:
    """Expected failure of the STANDARD projection, asserted: some pixels show the far plane."""
    assert _wrong_fraction(FAR, reverse_z=False) > 0.05


def test_reverse_z_depth_values() -> None:
    """frags.depth follows the reverse-Z mapping: -1 at near, 0 at far, z_ndc = n(d-f)/(d(f-n))
    (-n/d for an infinite far plane), evaluated at the analytic view depth of each pixel."""
    for far in (FAR, math.inf):
        clip, faces = _two_planes(far, True)
        frags = tr.rasterize(clip.double(), faces, resolution=RES)
        w = RES[0]
        c = (2 * (torch.arange(w, dtype=torch.float64) + 0.5) / w - 1) * math.tan(
            math.radians(FOV) / 2
        )
        cy, cx = torch.meshgrid(-c, c, indexing="ij")  # view-space ray slopes (row 0 = top)
        # ray (cx, cy, -1) * d hits z = -D + 0.05 x + 0.03 y  ->  d = D / (1 + 0.05 cx + 0.03 cy)
        d = DIST / (1 + 0.05 * cx + 0.03 * cy)
        if math.isinf(far):
            z_ref = -NEAR / d
        else:
            z_ref = NEAR * (d - far) / (d * (far - NEAR))
        rel = ((frags.depth[0] - z_ref) / z_ref).abs().max()
        assert rel < 1e-5, (far, float(rel))  # float32 vertices and matrices
        assert (frags.depth[0] < 0).all() and (frags.depth[0] > -1).all()


def test_exact_duplicates_with_rotated_vertices_tie_to_the_lower_index():
    """The same triangle listed three times, vertices rotated: every covered pixel must
    resolve to face 0 (depth is evaluated in a canonical vertex order)."""
    g = torch.Generator().manual_seed(1)
    total = wrong = 0
    for _ in range(20):
        v = torch.rand(3, 4, generator=g, dtype=torch.float64) * 1.6 - 0.8
        v[:, 3] = 1 + torch.rand(3, generator=g, dtype=torch.float64)
        v[:, 2] = torch.rand(3, generator=g, dtype=torch.float64) * 0.5
        v[:, :3] *= v[:, 3:]
        pos = torch.cat([v, v[[1, 2, 0]], v[[2, 0, 1]]])[None].float()
        frags = tr.rasterize(pos, torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8]]), (64, 64))
        covered = frags.face_id >= 0
        total += int(covered.sum())
        wrong += int((frags.face_id[covered] != 0).sum())
    assert total > 1000 and wrong == 0


def test_rasterize_depth_matches_rasterize():
    """The depth-only pass finds the same covered pixels and depths as rasterize."""
    from torchraster.raster import rasterize_depth

    g = torch.Generator().manual_seed(3)
    clip = torch.rand(2, 60, 4, generator=g) * 2 - 1
    clip[..., 3] = 1.0 + torch.rand(2, 60, generator=g)
    faces = torch.randint(0, 60, (40, 3), generator=g)
    frags = tr.rasterize(clip, faces, (48, 40))
    depth = rasterize_depth(clip, faces, (48, 40))
    assert depth.shape == (2, 48, 40) and depth.dtype == torch.float32
    covered = frags.face_id >= 0
    assert torch.equal(torch.isfinite(depth), covered)
    assert (depth[covered] - frags.depth[covered]).abs().max() < 1e-5


def test_depth_stays_in_range_at_an_infinite_far_plane() -> None:
    """Found by scripts/stress.py (near_far, scene 363): one triangle seen through an
    infinite-far projection (z = w at every vertex) far away; float32 rounding of the depth
    plane equation gave NDC depth 1.0000113 at a covered pixel. Depth is clamped to [-1, 1]."""
    clip = torch.tensor([
        [[213650.8125, -490237.84375, 12762203.0, 12762203.0],
         [-1450747.0, 176338.234375, 6287421.5, 6287421.5],
         [2375827.25, 1470811.875, 2274876.25, 2274876.25]],
        [[208514.796875, -481447.59375, 1282732.125, 1282732.125],
         [-184883.828125, -1236667.875, 2283697.25, 2283697.25],
         [174007.921875, 187892.921875, -147049.015625, -147049.015625]],
        [[375.6849670410156, 111.37980651855469, 3670.12451171875, 3670.13037109375],
         [151.49497985839844, -1173.793701171875, 1249.5513916015625, 1249.55712890625],
         [770.131591796875, -862.7061157226562, -280.0410461425781, -280.0352478027344]]])
    frags = tr.rasterize(clip, torch.tensor([[0, 1, 2]]), resolution=(48, 81),
                         cull_backfaces=True)
    hit = frags.face_id >= 0
    assert int(hit.sum()) > 100
    assert float(frags.depth[hit].abs().max()) <= 1.0


def test_rasterize_coverage_is_the_face_id_mask():
    """``rasterize_coverage`` = ``rasterize(...).face_id >= 0`` (culling, face ranges and
    clipping at the near plane included)."""
    import trimesh

    from torchraster.raster import rasterize_coverage

    ico = trimesh.creation.icosphere(subdivisions=2)
    verts = torch.tensor(ico.vertices, dtype=torch.float32)
    faces = torch.tensor(ico.faces, dtype=torch.int64)
    view = tr.camera.orbit(torch.tensor([0.0, 90.0, 200.0]), torch.tensor([10.0, -20.0, 40.0]),
                           torch.tensor([3.0, 1.2, 0.9]))  # the last two cross the near plane
    clip = tr.camera.transform_points(verts, tr.camera.perspective(50.0, 1.3, 0.5) @ view)
    ranges = torch.tensor([[0, 320], [40, 200], [100, 101]])
    for cull in (False, True):
        for fr in (None, ranges):
            got = rasterize_coverage(clip, faces, (23, 30), cull, fr)
            want = tr.rasterize(clip, faces, (23, 30), cull_backfaces=cull,
                                face_ranges=fr).face_id >= 0
            assert got.dtype == torch.bool and torch.equal(got, want)
            assert 0 < int(got.sum()) < got.numel()
