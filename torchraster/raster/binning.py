"""Edge-function setup and binning of screen triangles into pixel blocks.

Every screen triangle becomes one or more *records*: a block of kh x kw pixel centres at
(x0, y0) whose coverage is tested by :func:`torchraster.raster.rasterize.covered_keys`.

* Small triangles (bounding box at most ``tile`` pixels wide and high) get one square
  block of the next :func:`block_sizes` side that holds their box, so a 2x3-pixel
  triangle tests 4x4 centres, not a whole tile.
* Large triangles are binned to the ``tile x tile`` screen tiles their box touches; tiles
  that an edge function proves empty are dropped, so work follows covered area.

Records of one block shape are processed together in chunks of at most
``max_candidates`` pixel centres, which bounds the peak memory of a chunk independently of
triangle size, resolution and batch size. (Runs of small triangles with few candidates are
instead tested all shapes at once by :func:`torchraster.raster.rasterize.ragged_keys`.)

Exact shared edges: each edge's coefficients are computed from its two endpoints in a
canonical (lexicographic) order and negated for the other side, and E(p) = A x + (B y + C)
is evaluated with the same float ops for every triangle. IEEE rounding is symmetric, so two
triangles sharing an edge get E values of exactly opposite sign at every pixel centre:
with the top-left tie rule below, no centre is covered twice or missed (no cracks).
"""

from __future__ import annotations

import bisect
from collections.abc import Iterator
from dataclasses import dataclass

import torch

from ..numerics import take_columns
from .clip import ScreenTriangles

# Rows of TriangleSetup.coef, defined once: the per-triangle table is read by name only.
EDGE_A = slice(0, 3)  #: edge function x coefficients A_e, e = 0, 1, 2 (edge opposite vertex e)
EDGE_B = slice(3, 6)  #: y coefficients B_e
EDGE_C = slice(6, 9)  #: constants C_e
EDGE_MIN = slice(9, 12)  #: tie thresholds: edge e covers p iff A x + (B y + C) >= EDGE_MIN
DZDX, DZDY = 12, 13  #: depth plane slopes per pixel
REF_X, REF_Y, REF_Z = 14, 15, 16  #: the depth plane's reference vertex and its NDC z
COEF_ROWS = 17


#: Rows of a ``(4, N)`` int64 inclusive pixel box (``TriangleSetup.box`` and the boxes
#: derived from it): xmin, xmax, ymin, ymax.
BOX_XMIN, BOX_XMAX, BOX_YMIN, BOX_YMAX = 0, 1, 2, 3


@dataclass
class TriangleSetup:
    """Per-triangle coverage and depth equations of N triangles, component-major.

    coef:  (COEF_ROWS, N) float rows, named by the module constants: edge A (EDGE_A), B
           (EDGE_B), C (EDGE_C), tie threshold (EDGE_MIN), depth slopes dz/dx, dz/dy (DZDX,
           DZDY), reference vertex (REF_X, REF_Y) and its depth (REF_Z). Edge e (opposite
           vertex e) covers p iff A x + (B y + C) >= threshold; depth = z0 + dzdx (x - x0)
           + dzdy (y - y0).
    box:   (4, N) int64 inclusive pixel box, rows BOX_XMIN, BOX_XMAX, BOX_YMIN, BOX_YMAX
           (clamped to the image)
    key_lo:(N,) int64 face id (low 32 bits of the depth-resolve key)
    batch: (N,) int64 batch item
    """

    coef: torch.Tensor
    box: torch.Tensor
    key_lo: torch.Tensor
    batch: torch.Tensor


def setup_triangles(tris: ScreenTriangles) -> TriangleSetup:
    """Edge functions (with the top-left rule folded in) and depth planes."""
    x, y, z = tris.pos  # each (3, N): vertex rows
    ax, ay = torch.cat([x[1:], x[:1]]), torch.cat([y[1:], y[:1]])  # edge e: vertex e+1 ...
    bx, by = torch.cat([x[2:], x[:2]]), torch.cat([y[2:], y[:2]])  # ... to vertex e+2
    swap = (ax > bx) | ((ax == bx) & (ay > by))
    ax, bx = torch.where(swap, bx, ax), torch.where(swap, ax, bx)
    ay, by = torch.where(swap, by, ay), torch.where(swap, ay, by)
    # E_ab(p) = cross(b - a, p - a) = A x + B y + C has the sign of the area inside the
    # triangle: orient every edge so that inside is positive (negation is exact).
    sign = torch.where(swap, -1.0, 1.0).to(x.dtype) * torch.sign(tris.area)
    ea, eb = ay - by, bx - ax
    # C through the canonical endpoint a: C = -(A ax + B ay). The textbook ax by - ay bx
    # cancels products of size |a| |b| (~1e6 at 1024²) down to C ~ |a| |b - a|, and its
    # float32 rounding moved short edges by ~0.01 px (a crack between two faces whose
    # shared-edge centres fell outside the other face's pixel box). This form rounds
    # terms of size |A| |a| only: the edge moves by a few eps |a| pixels, which the pixel
    # boxes absorb (clip.box_slack).
    ec = torch.add(ea * ax, eb * ay).neg_().mul_(sign)
    ea.mul_(sign)
    eb.mul_(sign)
    # Top-left rule (y down): an edge whose inward normal points right (A > 0), or down
    # on a horizontal edge (A == 0, B > 0), owns the centres exactly on it (E >= 0); other
    # edges need E > 0, written as E >= the smallest positive (subnormal) float.
    top_left = (ea > 0) | ((ea == 0) & (eb > 0))
    tiny = torch.finfo(x.dtype).tiny * torch.finfo(x.dtype).eps
    thresh = (~top_left).to(x.dtype).mul_(tiny)
    plane = depth_planes(x, y, z)
    coef = torch.cat([ea, eb, ec, thresh, plane])
    return TriangleSetup(coef=coef, box=tris.box, key_lo=tris.face, batch=tris.batch)


def depth_planes(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """Depth planes of N screen triangles: (5, N) rows dz/dx, dz/dy (per pixel), and the
    reference vertex x, y and its NDC z (the rows DZDX .. REF_Z of the setup table).

    x, y, z: (3, N) vertex rows (pixel x, pixel y, NDC z). The plane is written relative to
    the canonical first vertex (the lexicographically smallest (x, y); a rotation keeps the
    winding) and evaluated in that vertex order: the same triangle listed with its vertices
    rotated gets bit-identical depths, so exact duplicates tie and the lower face index
    wins. A constant depth stays exactly constant.
    """
    x, y, z = _canonical_rotation(x, y, z)
    dz1, dz2 = z[1] - z[0], z[2] - z[0]
    dx1, dx2 = x[1] - x[0], x[2] - x[0]
    dy1, dy2 = y[1] - y[0], y[2] - y[0]
    area = dx1 * dy2 - dx2 * dy1
    area = torch.where(area == 0, torch.ones_like(area), area)  # culled later; no 0 / 0
    dzdx = (dz1 * dy2 - dz2 * dy1) / area
    dzdy = (dx1 * dz2 - dx2 * dz1) / area
    return torch.stack([dzdx, dzdy, x[0], y[0], z[0]])


def plane_lower_bound(plane: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """A lower bound (N,) of the depth :func:`block_depth` computes at any pixel centre in
    each triangle's box of tested centres (:func:`tested_boxes`): the plane's minimum over
    the box corners (a plane's minimum over a box is at a corner) minus a bound on the float
    rounding of both evaluations
    (16 unit roundoffs of the magnitudes involved, plus a tiny absolute term so that a
    signed zero cannot tie).

    Args:
        plane: (5, N) rows of :func:`depth_planes`.
        box: (4, N) int64 inclusive pixel boxes xmin, xmax, ymin, ymax.
    """
    dzdx, dzdy, x0, y0, z0 = plane
    lo_x, hi_x = box[BOX_XMIN].to(plane.dtype) - x0, box[BOX_XMAX].to(plane.dtype) - x0
    lo_y, hi_y = box[BOX_YMIN].to(plane.dtype) - y0, box[BOX_YMAX].to(plane.dtype) - y0
    zx = torch.minimum(dzdx * lo_x, dzdx * hi_x)
    zy = torch.minimum(dzdy * lo_y, dzdy * hi_y)
    span = (dzdx.abs() * torch.maximum(lo_x.abs(), hi_x.abs())
            + dzdy.abs() * torch.maximum(lo_y.abs(), hi_y.abs()) + z0.abs())
    eps = torch.finfo(plane.dtype).eps  # 2 unit roundoffs
    return z0 + zy + zx - 8 * eps * span - torch.finfo(plane.dtype).tiny


def block_edge(coef: torch.Tensor, e: int, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """Edge function e of R triangles (``coef`` (rows, R)) at a (kh, kw, R) block of pixel
    centres px (kw, R), py (kh, R): A x + (B y + C), always in this order of float ops, so
    shared edges get exactly opposite values (compare with ``coef[EDGE_MIN][e]``)."""
    ex = coef[EDGE_A.start + e] * px
    ey = (coef[EDGE_B.start + e] * py).add_(coef[EDGE_C.start + e])
    return torch.add(ey.unsqueeze(1), ex)


def block_edges(coef: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """The three edge functions at once: (3, kh, kw, R), entry e bit-identical to
    :func:`block_edge` (the same float ops in the same order, A x + (B y + C))."""
    ex = coef[EDGE_A][:, None, :] * px
    ey = (coef[EDGE_B][:, None, :] * py).add_(coef[EDGE_C][:, None, :])
    return torch.add(ey[:, :, None, :], ex[:, None, :, :])


def block_depth(coef: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """Depth planes of R triangles at a (kh, kw, R) block of pixel centres (see
    :func:`block_edge`): z0 + dzdx (x - x0) + dzdy (y - y0)."""
    zx = coef[DZDX] * (px - coef[REF_X])
    zy = (coef[DZDY] * (py - coef[REF_Y])).add_(coef[REF_Z])  # z0 + ..., commuted: exact
    return torch.add(zy.unsqueeze(1), zx)


def _canonical_rotation(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor):
    """Rotate each triangle's vertex rows (3, N) so that row 0 is its lexicographically
    smallest (x, y) vertex (ties: the earlier one); returns each as a tuple of 3 rows."""
    def before(i: int, j: int) -> torch.Tensor:
        return (x[i] < x[j]) | ((x[i] == x[j]) & (y[i] <= y[j]))

    first0 = before(0, 1) & before(0, 2)
    first1 = ~first0 & before(1, 2)
    first2 = ~(first0 | first1)

    def rotate(r: torch.Tensor) -> tuple[torch.Tensor, ...]:  # selects: ~2x a gather's speed
        return (torch.where(first1, r[1], torch.where(first2, r[2], r[0])),
                torch.where(first1, r[2], torch.where(first2, r[0], r[1])),
                torch.where(first1, r[0], torch.where(first2, r[1], r[2])))

    return rotate(x), rotate(y), rotate(z)


@dataclass
class Records:
    """Blocks of kh x kw pixel centres to test, R records of one block shape.

    tri: the records' triangles in the TriangleSetup: a slice (a run of consecutive
    triangles, no gather needed) or an (R,) int64 index; x0, y0: (R,) int64 block origin;
    full: every centre of every block is proven covered (:func:`_classify_blocks`), so the
    coverage test can be skipped.
    """

    kh: int
    kw: int
    tri: slice | torch.Tensor
    x0: torch.Tensor
    y0: torch.Tensor
    full: bool = False

    def take(self, values: torch.Tensor) -> torch.Tensor:
        """The records' entries of a per-triangle tensor (last dimension = triangles)."""
        if isinstance(self.tri, slice):
            return values[..., self.tri]
        return values.index_select(values.dim() - 1, self.tri)


def block_sizes(tile: int) -> list[int]:
    """Block edge lengths for small triangles: 1, 2, 4, 6, 8, 12, 16, ... (powers of two
    and, from 4 up, 1.5 times them) and ``tile``.

    Blocks are square (:func:`sort_by_block`), so each size is one shape, one run of
    launches. With per-axis shapes, 1.5x steps had doubled the shapes and measured 25-35 %
    slower at 256² - 512², batch 1; with square blocks they are neutral at 512² and up and
    7-15 % faster at 256², batch 1 (scripts/ab_raster.py, in turns), where 10 % of the
    16x16 blocks' centres were covered.
    """
    sizes, s = {tile}, 1
    while s < tile:
        sizes.add(s)
        if s >= 4 and s * 3 // 2 < tile:
            sizes.add(s * 3 // 2)
        s *= 2
    return sorted(sizes)


def _shape_table(tile: int, device: torch.device) -> torch.Tensor:
    """(tile + 1,) uint8 block shape of a triangle, indexed by its pixel box's larger side
    - 1 (clamped to ``tile``): the index in :func:`block_sizes` of the smallest block side
    holding the box, and ``len(block_sizes(tile))`` for boxes over ``tile`` pixels (large
    triangles, binned to tiles). One shape per size, square blocks: with power-of-two
    sizes, 3-16 % faster on the six scripts/bench_raster.py rows compared
    (scripts/ab_raster.py) than a shape per (kh, kw) pair, the launches saved outweighing
    the extra tested centres."""
    sizes = block_sizes(tile)
    shape = [bisect.bisect_left(sizes, side) for side in range(1, tile + 1)] + [len(sizes)]
    return torch.tensor(shape, dtype=torch.uint8, device=device)


def sort_by_block(tris: ScreenTriangles, resolution: tuple[int, int], tile: int,
                  select: torch.Tensor | None = None
                  ) -> tuple[ScreenTriangles, list[tuple[int, int, int, int]], int]:
    """Order triangles by the block shape they need, so each shape is one contiguous run,
    keeping only the valid ones (or those listed in ``select``) in the same gather.

    Args:
        tris: N screen triangles (``tris.valid`` False = culled).
        resolution: (H, W).
        tile: the tile size of large triangles (and the largest block).
        select: (M,) int64 indices of the triangles to keep (instead of ``tris.valid``).

    Returns the reordered triangles, the runs (kh, kw, start, count) of small triangles
    (blocks of the :func:`block_sizes` side holding the box's larger side, clamped to the
    frame), and the index where the large triangles (boxes over ``tile`` pixels) begin.
    """
    h, w = resolution
    if select is None and tris.valid is not None:
        select = tris.valid.nonzero().squeeze(1)
    box = tris.box if select is None else take_columns(tris.box, select)
    side = torch.maximum(box[BOX_XMAX] - box[BOX_XMIN], box[BOX_YMAX] - box[BOX_YMIN])
    shape = _shape_table(tile, box.device).index_select(0, side.clamp_(max=tile))
    shape, by_shape = torch.sort(shape, stable=True)  # uint8 keys: ~6x faster than int64
    keys, counts = torch.unique_consecutive(shape, return_counts=True)
    order = by_shape if select is None else select.index_select(0, by_shape)
    tris = ScreenTriangles(
        pos=tris.pos.view(9, -1).index_select(1, order).view(3, 3, -1),
        area=tris.area.index_select(0, order), box=take_columns(box, by_shape),
        face=tris.face.index_select(0, order), batch=tris.batch.index_select(0, order))
    sizes = block_sizes(tile)
    runs, start, n_small = [], 0, len(order)
    for key, count in zip(keys.tolist(), counts.tolist(), strict=True):
        if key == len(sizes):  # large triangles: the last run
            n_small = start
        else:
            runs.append((min(sizes[key], h), min(sizes[key], w), start, count))
        start += count
    return tris, runs, n_small


def tested_boxes(box: torch.Tensor, resolution: tuple[int, int], tile: int) -> torch.Tensor:
    """(4, N) int64 inclusive boxes xmin, xmax, ymin, ymax of every pixel centre that
    :func:`bin_triangles` will test for triangles with pixel boxes ``box`` (4, N): the
    small triangles' whole block (:func:`block_sizes`), the large ones' whole tiles. A
    covered centre can lie outside the triangle's own box only by float rounding of the
    edge functions, but never outside these.

    The same blocks as :func:`sort_by_block` and :func:`bin_triangles` (tests compare them),
    written for the occlusion test's hundreds of thousands of triangles: the block side is
    one lookup of the box's larger extent, and only the large triangles (usually none or a
    few) take the tile formula.
    """
    h, w = resolution
    extent = torch.maximum(box[BOX_XMAX] - box[BOX_XMIN], box[BOX_YMAX] - box[BOX_YMIN])
    sizes = torch.tensor(block_sizes(tile), device=box.device)
    side = sizes.index_select(0, _shape_table(tile, box.device)[:tile].long())  # by side - 1
    small_extent = extent.clamp(max=tile - 1)  # side - 1 of the box -> the block's side
    kw = side.clamp(max=w).index_select(0, small_extent)
    kh = kw if h == w else side.clamp(max=h).index_select(0, small_extent)
    x0, y0 = torch.minimum(box[BOX_XMIN], w - kw), torch.minimum(box[BOX_YMIN], h - kh)
    out = torch.stack([x0, x0 + kw, y0, y0 + kh])
    out[BOX_XMAX] -= 1
    out[BOX_YMAX] -= 1
    large = (extent >= tile).nonzero().squeeze(1)
    if large.numel():
        th, tw = min(tile, h), min(tile, w)
        big = take_columns(box, large)
        corner = torch.div(big, tile, rounding_mode="floor").mul_(tile)
        corner[:2].clamp_(max=w - tw)
        corner[2:].clamp_(max=h - th)
        corner[BOX_XMAX] += tw - 1
        corner[BOX_YMAX] += th - 1
        out.index_copy_(1, large, corner)
    return out


def bin_triangles(
    setup: TriangleSetup, runs: list[tuple[int, int, int, int]], n_small: int,
    resolution: tuple[int, int], tile: int, max_candidates: int, margin: float = 0.0,
) -> Iterator[Records]:
    """Yield records covering every triangle's pixel box, in bounded-size chunks.

    ``runs`` and ``n_small`` come from :func:`sort_by_block` (setup in that order).
    ``margin``: keep the tiles within this many pixels of a large triangle (soft coverage).
    """
    h, w = resolution
    for kh, kw, start, count in runs:
        step = max(1, max_candidates // (kh * kw))
        for s in range(start, start + count, step):
            sel = slice(s, min(s + step, start + count))
            x0 = setup.box[0, sel].clamp(max=w - kw)
            y0 = setup.box[2, sel].clamp(max=h - kh)
            yield Records(kh, kw, sel, x0, y0)
    n = setup.box.shape[1]
    if n_small < n:
        big = torch.arange(n_small, n, device=setup.box.device)
        yield from _bin_large(setup, big, resolution, tile, max_candidates, margin)


def _bin_large(
    setup: TriangleSetup, big: torch.Tensor, resolution: tuple[int, int], tile: int,
    max_candidates: int, margin: float,
) -> Iterator[Records]:
    """Records for triangles larger than a tile: one per non-empty screen tile they touch."""
    h, w = resolution
    th, tw = min(tile, h), min(tile, w)
    box = take_columns(setup.box, big)
    tx0, tx1 = box[BOX_XMIN] // tile, box[BOX_XMAX] // tile
    ty0, ty1 = box[BOX_YMIN] // tile, box[BOX_YMAX] // tile
    ntx = tx1 - tx0 + 1
    n_tiles = ntx * (ty1 - ty0 + 1)
    per_chunk = max(1, max_candidates // (th * tw))
    # Group triangles so that each group expands to about per_chunk (triangle, tile) pairs.
    cum = torch.cumsum(n_tiles, 0)
    marks = torch.arange(per_chunk, max(per_chunk, int(cum[-1])), per_chunk, device=cum.device)
    cuts = torch.searchsorted(cum, marks) + 1
    bounds = sorted({0, big.numel(), *cuts.clamp(max=big.numel()).tolist()})
    for start, end in zip(bounds[:-1], bounds[1:], strict=False):
        sl = slice(start, end)
        counts = n_tiles[sl]
        tri = torch.repeat_interleave(big[sl], counts)
        local = torch.arange(int(counts.sum()), device=counts.device) - torch.repeat_interleave(
            torch.cumsum(counts, 0) - counts, counts)
        ntx_r = torch.repeat_interleave(ntx[sl], counts)
        x0 = ((torch.repeat_interleave(tx0[sl], counts) + local % ntx_r) * tile).clamp(max=w - tw)
        y0 = ((torch.repeat_interleave(ty0[sl], counts) + local // ntx_r) * tile).clamp(max=h - th)
        keep = _tile_may_overlap(setup.coef.index_select(1, tri), x0, y0, th, tw, margin)
        keep = keep.nonzero()
        keep = keep.squeeze(1)
        tri, x0, y0 = tri.index_select(0, keep), x0.index_select(0, keep), y0.index_select(0, keep)
        if margin == 0 and th % SUB_BLOCK == 0 and tw % SUB_BLOCK == 0 and th * tw > SUB_BLOCK ** 2:
            yield from _sub_blocks(setup, tri, x0, y0, th, tw, max_candidates)
            continue
        for s in range(0, tri.numel(), per_chunk):
            yield Records(th, tw, tri[s:s + per_chunk], x0[s:s + per_chunk], y0[s:s + per_chunk])


#: Side of the sub-blocks a large triangle's tiles are split into (:func:`_sub_blocks`).
SUB_BLOCK = 8


def _sub_blocks(setup: TriangleSetup, tri: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor,
                th: int, tw: int, max_candidates: int) -> Iterator[Records]:
    """Split (triangle, tile) pairs into SUB_BLOCK-square blocks, drop the blocks outside an
    edge, and yield the blocks proven fully covered as ``full`` records (no per-pixel edge
    test, no search for covered centres) and the others as ordinary records.

    The blocks are classified as an (R, S) broadcast over the R pairs' edge coefficients (S
    blocks a tile), without a per-block copy of them. Halving the partial blocks again (a
    quadtree down to 4x4) tests 2.3x fewer centres for 5k faces at 1024² but was measured
    slower overall: the extra launches and smaller records cost more than the tests saved.
    """
    s = SUB_BLOCK
    oy, ox = torch.meshgrid(torch.arange(0, th, s, device=tri.device),
                            torch.arange(0, tw, s, device=tri.device), indexing="ij")
    step = max(1, max_candidates // (th * tw))
    n_sub = ox.numel()
    for c in range(0, tri.numel(), step):
        t = tri[c:c + step]
        coef = setup.coef[:EDGE_MIN.stop].index_select(1, t)  # (12, R), once per pair
        # (R, S) sub-block origins, as floats (exact: pixel coordinates are < 2**24)
        bx = (x0[c:c + step, None] + ox.reshape(1, -1)).to(coef.dtype)
        by = (y0[c:c + step, None] + oy.reshape(1, -1)).to(coef.dtype)
        full, inside = _classify_blocks(coef, bx, by, s)
        for flag in (True, False):
            k = (full if flag else inside & ~full).view(-1).nonzero().squeeze(1)
            yield from _records(s, t.index_select(0, k // n_sub),
                                bx.view(-1).index_select(0, k).long(),
                                by.view(-1).index_select(0, k).long(), flag, max_candidates)


def _records(size: int, tri: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor, full: bool,
             max_candidates: int) -> Iterator[Records]:
    """Square ``size`` records of (R,) triangles and origins, in chunks of at most
    ``max_candidates`` centres."""
    per = max(1, max_candidates // (size * size))
    for k in range(0, tri.numel(), per):
        yield Records(size, size, tri[k:k + per], x0[k:k + per], y0[k:k + per], full=full)


def _classify_blocks(coef: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor, size: int
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """(full (R, S), may_overlap (R, S)) of size x size blocks of pixel centres at (x0, y0)
    (each (R, S) float, integer-valued: S blocks of each of R triangles; ``coef`` (>= 12,
    R)).

    Full is exact: each edge function is evaluated with :func:`block_edge`'s float ops at
    the block's corner where it is smallest (float rounding is monotone, so ``A x + (B y +
    C)`` never decreases towards the other corners along the signs of A and B); if that
    corner passes the edge's tie threshold, every centre of the block does. may_overlap is
    the conservative test of :func:`_tile_may_overlap`.
    """
    full = may = None
    last = float(size - 1)
    for e in range(3):
        ea, eb = coef[EDGE_A][e][:, None], coef[EDGE_B][e][:, None]
        ec, emin = coef[EDGE_C][e][:, None], coef[EDGE_MIN][e][:, None]
        shift_x, shift_y = (ea <= 0).to(coef.dtype) * last, (eb <= 0).to(coef.dtype) * last
        worst = (eb * (y0 + shift_y) + ec) + ea * (x0 + shift_x)
        ok = worst >= emin
        # The largest E over the block's corner centres, conservative by 1e-3 px (see
        # _tile_may_overlap): the corner opposite to the worst one.
        best = ea * (x0 + (last - shift_x)) + eb * (y0 + (last - shift_y)) + ec
        hit = best >= -1e-3 * (ea.abs() + eb.abs())
        full = ok if full is None else full.logical_and_(ok)
        may = hit if may is None else may.logical_and_(hit)
    return full, may


def _tile_may_overlap(coef: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor, th: int,
                      tw: int, margin: float = 0.0) -> torch.Tensor:
    """False for tiles that lie entirely more than ``margin`` pixels outside one edge
    (conservative by 1e-3 px)."""
    ea, eb, ec = coef[EDGE_A], coef[EDGE_B], coef[EDGE_C]  # (3, R) each
    xs = torch.where(ea > 0, x0 + tw - 1, x0).to(coef.dtype)
    ys = torch.where(eb > 0, y0 + th - 1, y0).to(coef.dtype)
    best = ea * xs + eb * ys + ec  # largest E over the tile's corner pixel centres
    slack = (1e-3 + margin) * (ea.abs() + eb.abs())  # |A| + |B| >= the edge's length
    return (best >= -slack).all(dim=0)
