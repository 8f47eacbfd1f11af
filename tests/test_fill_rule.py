"""The fill rule pinned exactly (issue 22): which pixel centres lying ON an edge are covered.

docs/design.md: coverage follows the top-left rule (Direct3D's): a pixel centre exactly on a
left edge or a horizontal top edge is covered, one on a right or a horizontal bottom edge is
not. Watertightness alone does not pin this (flipping the horizontal-edge tie keeps every
shared edge covered once), and the reference comparisons elsewhere skip pixels near edges;
here every vertex sits on a pixel centre (dyadic coordinates, power-of-two w), so every
float is exact and the face ids must equal the float64 reference with no tolerance.
"""

from __future__ import annotations

import pytest
import torch

import torchraster as tr
from torchraster.testing.reference_raster import reference_rasterize


def _clip(ij: torch.Tensor, res: tuple[int, int], z: torch.Tensor | float = 0.0,
          w: torch.Tensor | float = 1.0) -> torch.Tensor:
    """(N, 2) pixel (row, col) centres -> (1, N, 4) float64 clip positions with NDC depth
    ``z`` and clip ``w`` (scalars or (N,)), exact for power-of-two sizes and w."""
    h, wd = res
    z, w = (torch.as_tensor(v, dtype=torch.float64).expand(ij.shape[0]) for v in (z, w))
    x = 2 * (ij[:, 1] + 0.5) / wd - 1
    y = 1 - 2 * (ij[:, 0] + 0.5) / h
    return torch.stack([x * w, y * w, z * w, w], -1)[None]


@pytest.mark.parametrize("res,box", [((16, 16), (2, 9, 3, 12)), ((64, 64), (16, 48, 8, 40)),
                                     ((32, 64), (0, 31, 0, 63))])
@pytest.mark.parametrize("diagonal", ["main", "anti"])
@pytest.mark.parametrize("winding", ["ccw", "cw"])
@pytest.mark.parametrize("w", [1.0, 4.0, 0.25])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_axis_aligned_quad_covers_left_and_top_edges_only(
        res: tuple[int, int], box: tuple[int, int, int, int], diagonal: str, winding: str,
        w: float, dtype: torch.dtype) -> None:
    """A quad whose edges lie on pixel centres, rows i0..i1, cols j0..j1: the top row and
    left column are covered, the bottom row and right column are not; centres on the
    diagonal belong to exactly one triangle (face ids disjoint, union exact)."""
    i0, i1, j0, j1 = box
    ij = torch.tensor([[i0, j0], [i1, j0], [i1, j1], [i0, j1]], dtype=torch.float64)
    clip = _clip(ij, res, w=w)
    # vertices 0 top-left, 1 bottom-left, 2 bottom-right, 3 top-right: CCW on screen (y up)
    faces = [[0, 1, 2], [0, 2, 3]] if diagonal == "main" else [[0, 1, 3], [1, 2, 3]]
    faces = torch.tensor(faces)
    if winding == "cw":
        faces = faces[:, [0, 2, 1]]
    face_id = tr.rasterize(clip.to(dtype), faces, res).face_id[0]
    expected = torch.zeros(res, dtype=torch.bool)
    expected[i0:i1, j0:j1] = True  # top-left inclusive, bottom-right exclusive
    assert torch.equal(face_id >= 0, expected), (
        f"covered rows {sorted(set((face_id >= 0).nonzero()[:, 0].tolist()))}, cols "
        f"{sorted(set((face_id >= 0).nonzero()[:, 1].tolist()))}; expected rows {i0}..{i1 - 1}, "
        f"cols {j0}..{j1 - 1}")
    depth_only = tr.raster.rasterize_depth(clip.to(dtype), faces, res)[0]
    assert torch.equal(torch.isfinite(depth_only), expected)


@pytest.mark.parametrize("corner", ["top_left", "bottom_right", "top_right", "bottom_left"])
def test_right_triangle_edges(corner: str) -> None:
    """One right triangle with its legs on pixel centres: a leg owns its centres iff it is a
    left or a top edge (the hypotenuse is neither horizontal nor vertical)."""
    res, a, b = (16, 16), 3, 12
    corners = {"top_left": (a, a), "bottom_right": (b, b), "top_right": (a, b),
               "bottom_left": (b, a)}
    ci, cj = corners[corner]
    oi = b if ci == a else a  # the other row / column of the legs
    oj = b if cj == a else a
    ij = torch.tensor([[ci, cj], [oi, cj], [ci, oj]], dtype=torch.float64)
    clip = _clip(ij, res)
    got = tr.rasterize(clip.float(), torch.tensor([[0, 1, 2]]), res).face_id[0] >= 0
    # the horizontal leg lies on row ci, the vertical one on column cj
    top_leg_owned = ci == a   # horizontal leg is the triangle's top edge
    left_leg_owned = cj == a  # vertical leg is its left edge
    row = got[ci, min(cj, oj) + 1: max(cj, oj)]  # the horizontal leg without its end points
    col = got[min(ci, oi) + 1: max(ci, oi), cj]
    assert bool(row.all()) == top_leg_owned and bool(row.any()) == top_leg_owned
    assert bool(col.all()) == left_leg_owned and bool(col.any()) == left_leg_owned


def _dyadic_scene(seed: int, res: tuple[int, int], n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """n triangles with vertices on pixel centres (many axis-aligned edges: coordinates drawn
    from a coarse lattice), constant dyadic depth per triangle (some equal: exact ties),
    power-of-two w per vertex."""
    gen = torch.Generator().manual_seed(seed)
    h, w = res
    rows = torch.randint(0, h // 4, (n * 3,), generator=gen) * 4 + 1
    cols = torch.randint(0, w // 4, (n * 3,), generator=gen) * 4 + 2
    ij = torch.stack([rows, cols], -1).double()
    z = (torch.randint(-15, 16, (n,), generator=gen).double() / 16).repeat_interleave(3)
    ww = 2.0 ** torch.randint(-1, 2, (n * 3,), generator=gen).double()
    faces = torch.arange(n * 3).view(n, 3)
    return _clip(ij, res, z, ww), faces


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dyadic_scenes_match_reference_exactly(seed: int, dtype: torch.dtype) -> None:
    """Face ids equal the float64 brute-force reference at EVERY pixel (no edge tolerance):
    every edge runs through pixel centres, so any fill-rule difference shows."""
    res = (32, 64)
    clip, faces = _dyadic_scene(seed, res, 40)
    for cull in (False, True):
        ref = reference_rasterize(clip, faces, res, cull_backfaces=cull)
        got = tr.rasterize(clip.to(dtype), faces, res, cull_backfaces=cull)
        diff = (got.face_id != ref.face_id).nonzero().tolist()
        assert not diff, f"{len(diff)} pixels differ from the reference, e.g. {diff[:5]}"
        assert int((ref.face_id >= 0).sum()) > 100  # the scene covers something
