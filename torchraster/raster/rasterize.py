"""Visibility: the public ``rasterize`` (see docs/design.md, "Public contract").

Visibility first, attributes second:

1. *no grad*: triangles are clipped, culled and projected (``clip.py``), binned into pixel
   blocks (``binning.py``), every block's pixel centres are tested against the three edge
   functions, and covered candidates are depth-resolved with one ``scatter_reduce(amin)``
   per chunk over a 64-bit key (depth bits << 32 | face index): nearest wins, exact ties go
   to the lower face index, independently of processing order. With ``layers=K`` the K
   smallest distinct keys per pixel are kept instead (:func:`insert_layers`: depth peeling
   in the same single binning pass);
2. *differentiable*: for each covered pixel the perspective-correct barycentrics of the
   winning face are recomputed from its clip-space vertices with 2-D homogeneous edge
   functions (no divide by w, valid for faces crossing the near plane), so gradients flow
   to ``clip_pos`` through ``Fragments.bary`` and ``Fragments.depth`` (once per layer).

The soft rasterizer (``soft.py``) reuses pass 1 with a wider :class:`Coverage`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import torch

from .. import frame_pool
from .._validate import (
    all_finite,
    check_frame_memory,
    check_has_data,
    check_resolution,
    check_tensor,
)
from ..numerics import floor_div_exact, take_columns, to_compute
from .binning import (
    BOX_XMAX,
    BOX_XMIN,
    BOX_YMAX,
    BOX_YMIN,
    DZDX,
    DZDY,
    EDGE_A,
    EDGE_B,
    EDGE_C,
    EDGE_MIN,
    REF_X,
    REF_Y,
    REF_Z,
    Records,
    TriangleSetup,
    bin_triangles,
    block_depth,
    block_edge,
    block_edges,
    depth_planes,
    plane_lower_bound,
    setup_triangles,
    sort_by_block,
    tested_boxes,
)
from .clip import ScreenTriangles, clip_and_project, outcodes, project

DEFAULT_TILE = 16
DEFAULT_MEMORY_BUDGET = 96 * 2**20  # bytes of temporaries per chunk of pixel candidates
_BYTES_PER_CANDIDATE = 64  # E, masks and depth (10 B) + ~7 int64 temporaries if covered
#: Resolve key of a pixel (or layer) that nothing covers: larger than every real key.
EMPTY_KEY = torch.iinfo(torch.int64).max
#: Peak bytes per pixel of a frame whose pixels are all covered: rasterize + interpolate of
#: 3 channels, measured 264-314 B (full-screen quad at 2048² and 1024²,
#: docs/benchmarks.md); the up-front memory check assumes this.
BYTES_PER_PIXEL = 320


class Fragments:
    """Per-pixel visibility of one ``rasterize`` call (channels last).

    face_id: (B, H, W) int64 index into faces, -1 where nothing is covered
    bary:    (B, H, W, 3) perspective-correct barycentrics of the visible face, 0 where empty;
             differentiable with respect to clip_pos
    depth:   (B, H, W) NDC z of the visible surface, +inf where empty; differentiable
    bary_dx, bary_dy: (B, H, W, 3) derivatives of ``bary`` per pixel step (x = one column
             right, y = one row down); only with ``rasterize(..., derivatives=True)``
    mask:    (B, 1, H, W) float coverage (image layout)
    layers:  the K depth layers of ``rasterize(..., layers=K)``, nearest first, each a
             Fragments of these shapes; ``layers[0]`` is this object (K = 1: ``(self,)``)
    silhouettes: (B, G, H, W) bool, with ``rasterize(..., groups=...)`` (else None): whether
             any face of group g covers the pixel, nothing occluding it

    Packed form (what ``interpolate`` uses; N = covered pixels): ``pixels`` (N,) flat index
    b*H*W + i*W + j, ``items`` (N,) batch item, ``corners`` (3, N) vertex ids of the visible
    face, ``bary_packed`` (N, 3), ``depth_packed`` (N,), and with derivatives
    ``bary_dx_packed`` / ``bary_dy_packed`` (N, 3). The full (B, H, W, ...) tensors are
    built on first access.

    Face rows (what the per-pixel passes gather from; M = visible (item, face) pairs):
    ``rows`` (N,) the row of each covered pixel, ``row_face`` (M,) face index and
    ``row_item`` (M,) batch item of each row, ``faces`` (F, 3) the faces rasterized.
    ``corners`` and ``front_facing`` (N,) bool (counter-clockwise in NDC) are gathered from
    them, and ``depth_packed`` evaluated, on first access.
    """

    def __init__(self, face_id, pixels, items, corners, bary_packed, depth_packed,
                 bary_dx_packed=None, bary_dy_packed=None, *, faces=None, rows=None,
                 row_face=None, row_item=None, row_front=None, depth_fn=None):
        self.face_id = face_id
        self.pixels = pixels
        self._items = items
        self._corners = corners
        self.bary_packed = bary_packed
        self._depth_packed = depth_packed
        self._depth_fn = depth_fn
        self.bary_dx_packed = bary_dx_packed
        self.bary_dy_packed = bary_dy_packed
        self.faces = faces
        self.rows = rows
        self.row_face = row_face
        self.row_item = row_item
        self._row_front = row_front
        self._front_facing: torch.Tensor | None = None
        self.deeper: tuple[Fragments, ...] = ()  # layers 1 .. K-1 (no reference cycle)
        self.silhouettes: torch.Tensor | None = None
        self._cache: dict[str, torch.Tensor] = {}
        self._dtype = bary_packed.dtype

    @property
    def corners(self) -> torch.Tensor:
        """(3, N) int64 vertex ids of each covered pixel's face (gathered on first use)."""
        if self._corners is None:
            face = self.row_face.index_select(0, self.rows)
            self._corners = self.faces.index_select(0, face).T.contiguous()
        return self._corners

    @property
    def depth_packed(self) -> torch.Tensor:
        """(N,) NDC depth in [-1, 1] of the covered pixels (computed on first use by
        ``rasterize``'s fragments, differentiable as if computed there)."""
        if self._depth_packed is None and self._depth_fn is not None:
            self._depth_packed = self._depth_fn()
            self._depth_fn = None
        return self._depth_packed

    @depth_packed.setter
    def depth_packed(self, value: torch.Tensor) -> None:
        self._depth_packed = value

    @property
    def items(self) -> torch.Tensor:
        """(N,) int64 batch item of each covered pixel (gathered on first use)."""
        if self._items is None:
            self._items = self.row_item.index_select(0, self.rows)
        return self._items

    @property
    def front_facing(self) -> torch.Tensor | None:
        """(N,) bool: the pixel's face is counter-clockwise in NDC (seen from the front)."""
        if self._front_facing is None and self._row_front is not None:
            self._front_facing = self._row_front.index_select(0, self.rows)
        return self._front_facing

    @front_facing.setter
    def front_facing(self, value: torch.Tensor | None) -> None:
        self._front_facing = value

    @property
    def layers(self) -> tuple[Fragments, ...]:
        """The depth layers, nearest first: ``(self, *deeper)``."""
        return (self, *self.deeper)

    def _unpack(self, name: str, packed: torch.Tensor | None, fill: float):
        if packed is None:
            return None
        if name not in self._cache:
            b, h, w = self.face_id.shape
            full = packed.new_full((b * h * w, *packed.shape[1:]), fill)
            self._cache[name] = full.index_copy_(0, self.pixels, packed).view(
                b, h, w, *packed.shape[1:])
        return self._cache[name]

    @property
    def bary(self) -> torch.Tensor:
        return self._unpack("bary", self.bary_packed, 0.0)

    @property
    def depth(self) -> torch.Tensor:
        return self._unpack("depth", self.depth_packed, float("inf"))

    @property
    def bary_dx(self) -> torch.Tensor | None:
        return self._unpack("bary_dx", self.bary_dx_packed, 0.0)

    @property
    def bary_dy(self) -> torch.Tensor | None:
        return self._unpack("bary_dy", self.bary_dy_packed, 0.0)

    @property
    def mask(self) -> torch.Tensor:
        return (self.face_id >= 0).unsqueeze(1).to(self._dtype)

    def release_interpolation(self) -> None:
        """Drop what only interpolation reads (memory, once every attribute is
        interpolated): the packed barycentrics and their derivatives, the corners, items and
        face rows of the covered pixels, and their unpacked frames. ``face_id``, ``pixels``,
        ``depth`` / ``depth_packed``, ``mask`` and ``silhouettes`` stay; interpolating
        afterwards raises."""
        self.depth_packed  # noqa: B018 - evaluated now: its closure holds the rows and table
        self.bary_packed = self.bary_dx_packed = self.bary_dy_packed = None
        self._corners = self._items = self.rows = None
        self.row_face = self.row_item = self._row_front = None
        for name in ("bary", "bary_dx", "bary_dy"):
            self._cache.pop(name, None)


def rasterize(
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    resolution: tuple[int, int] | int,
    cull_backfaces: bool | torch.Tensor = False,
    face_ranges: torch.Tensor | None = None,
    *,
    derivatives: bool = False,
    layers: int = 1,
    select: Callable[[torch.Tensor], torch.Tensor] | None = None,
    groups: torch.Tensor | None = None,
    num_groups: int | None = None,
    tile: int = DEFAULT_TILE,
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
) -> Fragments:
    """Rasterize triangles into per-pixel visibility.

    Coverage follows a top-left fill rule (no double hits or cracks on shared edges);
    nearest depth wins and exact ties go to the lower face index; triangles crossing the
    near plane are clipped.

    Args:
        clip_pos: (B, V, 4) float clip-space positions (OpenGL: visible iff w > 0 and
            -w <= x, y, z <= w; NDC +x right, +y up).
        faces: (F, 3) int64 vertex indices shared by the batch; counter-clockwise (in NDC)
            = front facing.
        resolution: (H, W) or an int for a square image. Pixel (row i, col j) samples NDC
            x = 2(j + 0.5)/W - 1, y = 1 - 2(i + 0.5)/H (row 0 is the top).
        cull_backfaces: drop clockwise (back-facing) triangles: all of them (True), or those
            flagged in an (F,) bool tensor (e.g. faces of single-sided materials).
        face_ranges: optional (B, 2) int64 [start, end): batch item b rasterizes only
            faces[start:end] (packed batches of different meshes, see ``mesh.pack_meshes``).
        derivatives: also return screen-space derivatives of the barycentrics (for
            mip-mapping through ``interpolate(..., derivatives=True)``), in every layer.
        layers: K >= 1, the number of depth layers (depth peeling). Layer 0 is the nearest
            surface (the result is unchanged by K); layer k holds, per pixel, the fragment
            whose resolve key (depth, then face index) is the smallest one strictly greater
            than layer k - 1's: the k-th nearest distinct face covering the pixel. Exact
            depth ties are ordered by face index; a face covering a pixel counts once.
        select: optional ``select(face_id) -> keep``: given the ``(B, H, W)`` int64 face ids
            of the nearest surface (-1 empty), a ``(B, H, W)`` bool of the pixels whose
            barycentrics (and depth, derivatives) are wanted; the others come out empty
            (``face_id`` -1). The barycentric pass then costs the kept pixels only (edge
            antialiasing keeps the sub-samples of a few pixels of a large raster).
            ``layers`` must be 1.
        groups: optional (F,) int64 group of each face in ``[-1, num_groups)`` (-1: none),
            e.g. the object of each face: ``frags.silhouettes`` (B, G, H, W) bool then
            holds each group's silhouette as if the group were drawn alone, exactly
            ``rasterize_coverage`` of its faces (amodal masks), from the same candidates
            as the visible surface (no second raster).
        num_groups: G (default: the largest group + 1).
        tile: tile size in pixels of the binning of large triangles (and the largest block
            of small ones).
        memory_budget: bytes of temporaries per chunk; peak memory is about this plus the
            frame buffers (K times those of one layer), whatever the triangle sizes.

    Returns:
        :class:`Fragments` of the nearest layer. ``frags.layers`` is the tuple of the K
        layers' Fragments, nearest first (``frags.layers[0] is frags``), each with the same
        shapes and full differentiable ``bary`` / ``depth``: ``face_id`` (B, H, W), -1 where
        the pixel has fewer than k + 1 surfaces (there ``bary`` is 0 and ``depth`` +inf).
        All K layers are resolved in one binning pass (:func:`insert_layers`).

    Example:
        >>> clip = torch.tensor([[[-1.0, -1, 0.5, 1], [3, -1, 0.5, 1], [-1, 3, 0.5, 1],
        ...                       [-1, -1, -0.5, 1], [0.5, -1, -0.5, 1], [-1, 0.5, -0.5, 1]]])
        >>> faces = torch.tensor([[0, 1, 2], [3, 4, 5]])  # 0: whole screen, 1: nearer corner
        >>> front, back = rasterize(clip, faces, (2, 2), layers=2).layers
        >>> front.face_id, back.face_id
        (tensor([[[0, 0],
                 [1, 0]]]), tensor([[[-1, -1],
                 [ 0, -1]]]))
    """
    clip_pos, faces, (h, w), face_ranges = check_inputs(clip_pos, faces, resolution,
                                                         face_ranges)
    cull_backfaces = check_options(clip_pos, faces, cull_backfaces, tile)
    layers = check_layers(layers)
    # half precision: barycentrics and their backward (1 / sum(l), per-pixel products)
    # overflow float16; evaluate in float32, gradients back to clip_pos saturated
    clip_pos = to_compute(clip_pos)
    if select is not None and layers != 1:
        raise ValueError(f"select: needs layers=1, got layers={layers}")
    b = clip_pos.shape[0]
    observe, silhouettes = None, None
    if groups is not None:
        silhouettes, observe = _silhouette_observer(groups, num_groups, faces.shape[0],
                                                    (b, h, w), clip_pos.device)
    keys = resolve_keys(clip_pos, faces, (h, w), cull_backfaces, face_ranges, int(tile),
                        memory_budget, BYTES_PER_PIXEL * layers, layers=layers,
                        observe=observe)
    if select is not None:  # drop the pixels not selected before the barycentric pass
        nearest = keys[0].view(b, h, w)
        keep = select((nearest << 32) >> 32)  # the face ids (-1 for EMPTY_KEY)
        check_tensor("select(face_id) result", keep, (b, h, w))
        if keep.dtype != torch.bool:
            raise TypeError(f"select(face_id) result: expected a bool tensor, got {keep.dtype}")
        nearest.masked_fill_(~keep, EMPTY_KEY)
    frags = [_fragments_from_keys(clip_pos, faces, k, (b, h, w), derivatives) for k in keys]
    frags[0].deeper = tuple(frags[1:])
    if silhouettes is not None:  # (B, G + 1, H, W): the last group collects face group -1
        frags[0].silhouettes = silhouettes[:, :-1].contiguous()  # a view at batch 1
    return frags[0]


def _silhouette_observer(groups: torch.Tensor, num_groups: int | None, n_faces: int,
                         shape: tuple[int, int, int], device: torch.device):
    """The ``(B, G + 1, H, W)`` bool masks of ``rasterize(groups=...)`` and the
    ``observe(pixel, key)`` that marks every candidate (pixel, face) in its face's group."""
    check_tensor("groups", groups, (n_faces,), integer=True)
    groups = groups.to(device=device, dtype=torch.int64)
    lo, hi = (int(v) for v in torch.aminmax(groups)) if n_faces else (-1, -1)
    if num_groups is not None and (isinstance(num_groups, bool) or int(num_groups) < 0):
        raise ValueError(f"num_groups: expected an int >= 0, got {num_groups!r}")
    g = hi + 1 if num_groups is None else int(num_groups)
    if lo < -1 or hi >= g:
        raise ValueError(f"groups: expected values in [-1, {g}) (num_groups={num_groups}), "
                         f"got [{lo}, {hi}]")
    b, h, w = shape
    hw = h * w
    masks = torch.zeros(b, g + 1, h, w, dtype=torch.bool, device=device)
    # row of each face in (G + 1) * H * W: group -1 writes into the spare last group
    offset = torch.where(groups < 0, g, groups) * hw
    flat = masks.view(-1)

    def observe(pixel: torch.Tensor, key: torch.Tensor) -> None:
        at = offset.index_select(0, key & 0x7FFFFFFF)
        if b > 1:  # pixel = item * H * W + p: the item's block of G + 1 masks
            at += torch.div(pixel, hw, rounding_mode="floor") * (g * hw)
        flat.index_fill_(0, at.add_(pixel), True)

    return masks, observe


def rasterize_depth(
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    resolution: tuple[int, int] | int,
    cull_backfaces: bool | torch.Tensor = False,
    face_ranges: torch.Tensor | None = None,
    *,
    tile: int = DEFAULT_TILE,
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
    out: torch.Tensor | None = None,
) -> torch.Tensor:
    """Depth-only rasterization (shadow maps, depth pre-passes): the visibility half of
    :func:`rasterize` without the barycentric pass, so no gradients.

    Views of more than :data:`DEPTH_BAND_PIXELS` pixels are resolved in bands of rows
    (:func:`resolve_keys` ``rows=``; identical values), so the int64 resolve keys never
    take more than a band (a 4096² shadow-map face: 16 MB instead of 128 MB). Batches of
    smaller views take one pass (each band repeats the triangle setup; callers bound the
    batch by memory).

    Args:
        clip_pos, faces, resolution, cull_backfaces, face_ranges, tile, memory_budget: as
            in :func:`rasterize` (same coverage rule, clipping and depth resolve).
        out: optional ``(B, H, W)`` float32 tensor to write the result into (e.g. the
            shadow maps themselves: no frame-sized temporary).

    Returns:
        ``(B, H, W)`` float32 NDC z of the nearest surface, clamped to [-1, 1], ``+inf``
        where nothing is covered; the same coverage and winners as :func:`rasterize`. The
        value is the resolve's depth plane (within ~1e-6 of ``rasterize(...).depth``, which
        is recomputed differentiably).

    Example:
        >>> clip = torch.tensor([[[-1.0, -1, 0.5, 1], [3, -1, 0.5, 1], [-1, 3, 0.5, 1],
        ...                       [-1, -1, -0.5, 1], [0.5, -1, -0.5, 1], [-1, 0.5, -0.5, 1]]])
        >>> rasterize_depth(clip, torch.tensor([[0, 1, 2], [3, 4, 5]]), (2, 2))
        tensor([[[ 0.5000,  0.5000],
                 [-0.5000,  0.5000]]])
    """
    clip_pos, faces, (h, w), face_ranges = check_inputs(clip_pos, faces, resolution,
                                                         face_ranges)
    cull_backfaces = check_options(clip_pos, faces, cull_backfaces, tile)
    b = clip_pos.shape[0]
    if out is None:
        check_frame_memory(f"resolution ({h}, {w}) at batch {b}", b * h * w, 4,
                           clip_pos.device)
        out = torch.empty((b, h, w), dtype=torch.float32, device=clip_pos.device)
    else:
        check_tensor("out", out, (b, h, w))
        if out.dtype != torch.float32 or out.device != clip_pos.device:
            raise TypeError(f"out: expected a float32 tensor on {clip_pos.device}, got "
                            f"{out.dtype} on {out.device}")
    band = h  # one pass unless one view is large (batches of small maps: one pass each)
    if h * w > DEPTH_BAND_PIXELS:
        band = max(int(tile), DEPTH_BAND_PIXELS // max(1, b * w) // int(tile) * int(tile))
    for y0 in range(0, h, band):
        y1 = min(h, y0 + band)
        rows = None if (y0, y1) == (0, h) else (y0, y1)
        keys = resolve_keys(clip_pos, faces, (h, w), cull_backfaces, face_ranges, int(tile),
                            memory_budget, _DEPTH_BYTES_PER_PIXEL, rows=rows)
        out[:, y0:y1] = key_depth(keys[0]).view(b, y1 - y0, w)
    return out


def rasterize_coverage(
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    resolution: tuple[int, int] | int,
    cull_backfaces: bool | torch.Tensor = False,
    face_ranges: torch.Tensor | None = None,
    *,
    tile: int = DEFAULT_TILE,
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
) -> torch.Tensor:
    """Which pixels any triangle covers: the visibility pass without depths or barycentrics
    (silhouette masks, e.g. each object's amodal mask).

    Args:
        clip_pos, faces, resolution, cull_backfaces, face_ranges, tile, memory_budget: as
            in :func:`rasterize`.

    Returns:
        ``(B, H, W)`` bool, exactly ``rasterize(...).face_id >= 0`` (the same coverage rule
        and clipping), without converting a depth.

    Example:
        >>> clip = torch.tensor([[[-1.0, -1, 0.5, 1], [3, -1, 0.5, 1], [-1, 3, 0.5, 1]]])
        >>> rasterize_coverage(clip, torch.tensor([[0, 1, 2]]), (2, 2)).tolist()
        [[[True, True], [True, True]]]
    """
    keys = _nearest_keys(clip_pos, faces, resolution, cull_backfaces, face_ranges, tile,
                         memory_budget)
    return keys != EMPTY_KEY


def _nearest_keys(clip_pos, faces, resolution, cull_backfaces, face_ranges, tile,
                  memory_budget) -> torch.Tensor:
    """``(B, H, W)`` int64 nearest resolve key per pixel (``EMPTY_KEY`` where empty): the
    checked visibility pass of :func:`rasterize_depth` and :func:`rasterize_coverage`."""
    clip_pos, faces, (h, w), face_ranges = check_inputs(clip_pos, faces, resolution,
                                                         face_ranges)
    cull_backfaces = check_options(clip_pos, faces, cull_backfaces, tile)
    keys = resolve_keys(clip_pos, faces, (h, w), cull_backfaces, face_ranges, int(tile),
                        memory_budget, _DEPTH_BYTES_PER_PIXEL)
    return keys[0].view(clip_pos.shape[0], h, w)


#: Peak bytes per pixel of rasterize_depth beyond the chunk budget: the int64 key and the
#: float32 result.
_DEPTH_BYTES_PER_PIXEL = 16
#: rasterize_depth resolves views of more pixels than this in bands of whole tile rows,
#: each with its own int64 keys (at most 2**21 keys with the batch: 16 MB).
DEPTH_BAND_PIXELS = 2**21


#: Most depth layers of one rasterize call (each layer is one more pass over the candidates
#: and one more set of frame buffers; depth peeling deeper than this is not a rasterizer job).
MAX_LAYERS: int = 64


def check_layers(layers: int, name: str = "layers") -> int:
    """``layers`` as an int in ``[1, MAX_LAYERS]`` (an integral float such as 2.0 is taken;
    bools, NaN, inf and huge counts are not), or a ValueError naming the argument ``name``."""
    ok = isinstance(layers, (int, float)) and not isinstance(layers, bool) and (
        math.isfinite(layers) and int(layers) == layers and 1 <= layers <= MAX_LAYERS)
    if not ok:
        raise ValueError(f"{name}: expected an int in [1, {MAX_LAYERS}], got {layers!r}")
    return int(layers)


def check_options(clip_pos, faces, cull_backfaces, tile):
    """Checked ``tile`` and ``cull_backfaces`` (moved to clip_pos's device)."""
    if int(tile) < 1:
        raise ValueError(f"tile: expected a positive int, got {tile}")
    if isinstance(cull_backfaces, torch.Tensor):
        check_tensor("cull_backfaces", cull_backfaces, (faces.shape[0],))
        if cull_backfaces.dtype != torch.bool:
            raise TypeError(f"cull_backfaces: expected a bool or an (F,) bool tensor, got "
                            f"{cull_backfaces.dtype}")
        cull_backfaces = cull_backfaces.to(clip_pos.device)
    return cull_backfaces


class Coverage:
    """Which (pixel centre, triangle) pairs enter the depth resolve of :func:`resolve_keys`.

    The default is the exact coverage of :func:`rasterize` (top-left rule). A subclass may
    widen it (as :mod:`torchraster.raster.soft` does): boxes and tiles are grown by
    ``margin`` pixels, ``setup`` may append rows to the per-triangle table, ``cover``
    returns a chunk's candidates, and ``bytes_per_candidate`` sizes the chunks.
    """

    margin: float = 0.0
    bytes_per_candidate: int = _BYTES_PER_CANDIDATE

    def setup(self, screen: ScreenTriangles) -> TriangleSetup:
        """The per-triangle table of a chunk of screen triangles."""
        return setup_triangles(screen)

    def cover(self, setup: TriangleSetup, rec: Records, resolution: tuple[int, int]
              ) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(pixel (M,), key (M,)) of a chunk of records, or None (see :func:`covered_keys`)."""
        return covered_keys(setup, rec, resolution)


def resolve_keys(clip_pos, faces, resolution, cull_backfaces, face_ranges, tile,
                 memory_budget, bytes_per_pixel, *, layers: int = 1,
                 coverage: Coverage | None = None, observe=None,
                 rows: tuple[int, int] | None = None) -> torch.Tensor:
    """The no-grad visibility pass: ``(K, B*H*W)`` int64 keys (depth bits << 32 | face),
    the K smallest distinct ones per pixel in increasing order, ``EMPTY_KEY`` where there
    are fewer. Arguments as in :func:`rasterize` (checked); ``bytes_per_pixel`` is the
    frame memory the caller will need per pixel (checked up front); ``observe(pixel, key)``,
    if given, sees every covered candidate (occlusion culling is then off).

    ``rows=(y0, y1)``: only the band of image rows ``y0 <= i < y1`` (keys ``(K, B*(y1-y0)*W)``,
    the same values as those rows of the whole frame): triangle boxes are clipped to the
    band before binning, so the frame's work is split, not repeated, across bands."""
    coverage = coverage or Coverage()
    h, w = resolution
    b = clip_pos.shape[0]
    y0, y1 = (0, h) if rows is None else rows
    check_frame_memory(f"resolution ({h}, {w}) at batch {b}",
                       b * (h if rows is None else y1 - y0 + 2 * tile) * w, bytes_per_pixel,
                       clip_pos.device)
    max_candidates = max(1024, int(memory_budget) // coverage.bytes_per_candidate)
    band = None if rows is None else _Band(y0, y1, h, w, b, tile)
    keys = frame_pool.empty((layers, b * (h if band is None else band.rows) * w), torch.int64,
                            clip_pos.device).fill_(EMPTY_KEY)
    # Occlusion culling: front faces first, then back faces that a conservative depth
    # test against the tiles resolved so far cannot prove hidden. Exact: a skipped
    # triangle's keys are all larger than the keys already in its pixels.
    cull_hidden = (layers == 1 and type(coverage) is Coverage and OCCLUSION_CULLING
                   and observe is None and band is None)
    with torch.no_grad():
        # Visibility runs in float32 (float64 for float64 input), whatever the input dtype.
        pos = clip_pos.detach()
        if pos.dtype != torch.float64:
            pos = pos.float()
        codes = outcodes(pos)
        screen_t = project(pos, (h, w)).view(-1, 3).T.contiguous()
        faces_t = faces.T.contiguous()
        for batch_ids, face_ids in _triangle_chunks(b, faces.shape[0], face_ranges, pos.device,
                                                    max_candidates // 8):
            screen = clip_and_project(pos, screen_t, codes, faces_t, face_ids, batch_ids,
                                      (h, w), cull_backfaces, margin=coverage.margin)
            if band is not None:
                band.clip_boxes(screen)
            front = screen.area < 0
            if not (cull_hidden and screen.valid is not None
                    and _back_candidates(screen, front) >= OCCLUSION_MIN_WORK):
                _rasterize_group(screen, None, coverage, keys, (h, w), tile, max_candidates,
                                 observe, band)
                continue
            _rasterize_group(screen, (screen.valid & front).nonzero().squeeze(1), coverage,
                             keys, (h, w), tile, max_candidates)
            back = _visible_subset(screen, (screen.valid & ~front).nonzero().squeeze(1),
                                   keys[0], (b, h, w), tile)
            _rasterize_group(screen, back, coverage, keys, (h, w), tile, max_candidates)
    return keys if band is None else band.inner(keys)


#: Skip back-facing triangles that a conservative hierarchical depth test proves hidden
#: behind the front faces already resolved (:func:`resolve_keys`); results are identical
#: either way (a switch for tests and benchmarks).
OCCLUSION_CULLING = True
#: Pixels per side of the finest tiles of the occlusion test (a power of two); larger
#: tested boxes start from tiles of about their mean size (:func:`_visible_subset`).
HIZ_TILE = 4
#: Occlusion culling runs only when the valid back faces' work (:func:`_back_candidates`)
#: reaches this: below, the second binning pass and the tile maxima cost more than they
#: save. Measured in turns (both settings in one process, 15 turns each, with the 4-pixel
#: tile maxima): spheres at batch 1 of 5k faces at 256² (3.4k back faces, 95k back
#: centres) 22 % slower with; 20k at 256² (13k, 96k) even; 80k at 256² (50k, 96k) 15 %
#: faster with; 5k at 512² and 1024² (3.4k faces; 382k and 1.5M centres) within 3 %.
OCCLUSION_MIN_WORK = 2**19
#: Weight of one back-facing triangle in that work, in pixel centres (its clipping, setup
#: and binning, which culling saves, cost more than the centres of its box).
OCCLUSION_TRIANGLE_WORK = 32


def _back_candidates(screen: ScreenTriangles, front: torch.Tensor) -> int:
    """Work of the valid back-facing triangles of ``screen``: the pixel centres in their
    boxes plus :data:`OCCLUSION_TRIANGLE_WORK` per triangle."""
    box = screen.box
    size = ((box[BOX_XMAX] - box[BOX_XMIN] + 1) * (box[BOX_YMAX] - box[BOX_YMIN] + 1)
            + OCCLUSION_TRIANGLE_WORK)
    return int(size.masked_fill_(front | ~screen.valid, 0).sum())


class _Band:
    """A band of image rows ``y0 <= i < y1`` of a ``(B, H, W)`` frame (:func:`resolve_keys`).

    Triangle boxes are clipped to the band; their blocks (at most ``tile`` rows, aligned
    to the tile grid or to the clipped box) can still reach up to ``tile`` rows past it, so
    the band's keys have ``tile`` spare rows above and below that take those candidates
    (one subtraction a chunk instead of a compaction) and are dropped at the end.
    """

    def __init__(self, y0: int, y1: int, h: int, w: int, b: int, tile: int) -> None:
        if not 0 <= y0 < y1 <= h:
            raise ValueError(f"rows: expected 0 <= y0 < y1 <= H={h}, got ({y0}, {y1})")
        self.y0, self.y1, self.h, self.w, self.b, self.margin = y0, y1, h, w, b, tile
        self.rows = y1 - y0 + 2 * tile  # rows of the keys buffer (spare rows included)

    def clip_boxes(self, screen: ScreenTriangles) -> None:
        """Clip the pixel boxes to the band; triangles outside it become invalid."""
        box = screen.box
        box[BOX_YMIN].clamp_(min=self.y0)
        box[BOX_YMAX].clamp_(max=self.y1 - 1)
        inside = box[BOX_YMIN] <= box[BOX_YMAX]
        screen.valid = inside if screen.valid is None else screen.valid & inside

    def take(self, pixel: torch.Tensor, key: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor]:
        """Frame pixel indices ``b*H*W + i*W + j`` -> the keys buffer's."""
        first = (self.y0 - self.margin) * self.w  # the buffer's row 0 in the frame
        local = pixel - first
        if self.b > 1:
            item = torch.div(pixel, self.h * self.w, rounding_mode="floor")
            local.add_(item.mul_(self.rows * self.w - self.h * self.w))
        return local, key

    def inner(self, keys: torch.Tensor) -> torch.Tensor:
        """``(K, B*rows*W)`` buffer keys -> ``(K, B*(y1-y0)*W)`` keys of the band."""
        k, m = keys.shape[0], self.margin
        return keys.view(k, self.b, self.rows, self.w)[:, :, m:self.rows - m].reshape(k, -1)


def _rasterize_group(screen, select, coverage, keys, resolution, tile, max_candidates,
                     observe=None, band: _Band | None = None):
    """Bin, test and resolve the screen triangles ``select`` (None: the valid ones) into
    ``keys`` (in place), showing every candidate to ``observe(pixel, key)`` if given; with
    ``band``, only its rows (``keys`` holds the band)."""
    screen, runs, n_small = sort_by_block(screen, resolution, tile, select)
    if len(screen) == 0:
        return
    setup = coverage.setup(screen)
    if type(coverage) is Coverage and RAGGED_RUN_CANDIDATES > 0:
        # Runs of few candidates: one ragged pass for all of them (fewer, longer ops).
        few = [r for r in runs if r[0] * r[1] * r[3] < RAGGED_RUN_CANDIDATES]
        if len(few) > 1 and sum(r[0] * r[1] * r[3] for r in few) < 2**24:
            runs = [r for r in runs if r[0] * r[1] * r[3] >= RAGGED_RUN_CANDIDATES]
            for found in ragged_keys(setup, few, resolution, max_candidates):
                if observe is not None:
                    observe(*found)
                insert_layers(keys, *(found if band is None else band.take(*found)))
    for records in bin_triangles(setup, runs, n_small, resolution, tile, max_candidates,
                                 margin=coverage.margin):
        found = coverage.cover(setup, records, resolution)
        if found is not None:
            if observe is not None:
                observe(*found)
            insert_layers(keys, *(found if band is None else band.take(*found)))


#: Runs of small triangles (one block shape) with fewer candidates than this are tested
#: together in one ragged pass (:func:`ragged_keys`) instead of one broadcast pass per
#: shape: per-op overhead dominates such runs. 0 disables the ragged pass.
RAGGED_RUN_CANDIDATES = 8192


def ragged_keys(setup: TriangleSetup, runs: list[tuple[int, int, int, int]],
                resolution: tuple[int, int], max_candidates: int
                ) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """Test the small-triangle runs of several block shapes in one ragged candidate list
    (each triangle's kh x kw block, row-major, one after the other).

    Same blocks, edge and depth float ops as :func:`covered_keys` (coefficients gathered per
    candidate instead of broadcast), so the keys are bit-identical.

    Args:
        setup: the per-triangle table, in :func:`~torchraster.raster.binning.sort_by_block`
            order.
        runs: (kh, kw, start, count) runs of that order, holding fewer than 2**24 candidates
            in all (candidate indices are exact in float32).
        resolution: (H, W).
        max_candidates: candidates per chunk (a triangle is never split).

    Returns:
        An iterator over chunks: (pixel (M,), key (M,)) int64 flat pixel indices and
        depth-resolve keys of the covered candidates (chunks with none are skipped).
    """
    h, w = resolution
    dev = setup.box.device
    spec = torch.tensor(runs, dtype=torch.int64, device=dev)  # (n_runs, 4)
    n_runs = spec.shape[0]
    lengths = spec[:, 3]
    run_of = torch.repeat_interleave(torch.arange(n_runs, device=dev), lengths)
    first = torch.cumsum(lengths, 0) - lengths
    tri = (torch.arange(run_of.numel(), device=dev) - first.index_select(0, run_of)
           + spec[:, 2].index_select(0, run_of))
    kh, kw = spec[:, 0].index_select(0, run_of), spec[:, 1].index_select(0, run_of)
    x0 = setup.box[BOX_XMIN].index_select(0, tri).clamp_(max=w - kw)  # as in bin_triangles
    y0 = setup.box[BOX_YMIN].index_select(0, tri).clamp_(max=h - kh)
    cand = kh * kw
    cum = torch.cumsum(cand, 0)
    total = int(cum[-1])
    marks = torch.arange(max_candidates, max(max_candidates, total), max_candidates,
                         device=dev)
    cuts = (torch.searchsorted(cum, marks, right=True)).tolist()
    bounds = sorted({0, tri.numel(), *[c for c in cuts if 0 < c < tri.numel()]})
    dt = setup.coef.dtype
    # Per-triangle rows gathered once per candidate (one component-major gather): edge A,
    # B, C, threshold, block origin x0, y0, first candidate, kw (as floats: exact, pixel
    # coordinates and candidate indices are below 2**24).
    first_cand = cum - cand
    table = torch.cat([setup.coef[:EDGE_MIN.stop].index_select(1, tri),
                       torch.stack([x0, y0, first_cand, kw]).to(dt)])  # (16, R)
    for s0, s1 in zip(bounds[:-1], bounds[1:], strict=False):
        sl = slice(s0, s1)
        counts = cand[sl]
        c0 = int(first_cand[s0])
        n = int(cum[s1 - 1]) - c0
        rec = torch.repeat_interleave(torch.arange(s0, s1, device=dev), counts,
                                      output_size=n)  # candidate -> record
        g = table.index_select(1, rec)  # (16, n)
        local = torch.arange(c0, c0 + n, dtype=dt, device=dev).sub_(g[14])
        ly = local.div(g[15]).floor_()  # exact: integers below 2**24
        px = local.sub_(ly * g[15]).add_(g[12])  # x0 + local x
        py = ly.add_(g[13])  # y0 + local y
        # the three edges at once, as block_edge: A x + (B y + C) >= threshold
        edge = torch.ge((g[EDGE_B] * py).add_(g[EDGE_C]).add_(g[EDGE_A] * px), g[EDGE_MIN])
        flat = edge[0].logical_and_(edge[1]).logical_and_(edge[2]).nonzero().squeeze(1)
        if flat.numel() == 0:
            continue
        t = tri.index_select(0, rec.index_select(0, flat))
        px, py = px.index_select(0, flat), py.index_select(0, flat)
        dzdx, dzdy, rx, ry, rz = (setup.coef[k].index_select(0, t)
                                  for k in (DZDX, DZDY, REF_X, REF_Y, REF_Z))
        depth = torch.add(rz.add_(dzdy.mul_(py - ry)), dzdx.mul_(px - rx))
        pixel = (setup.batch.index_select(0, t) * (h * w) + py.long() * w + px.long())
        yield pixel, depth_key(depth.clamp_(-1.0, 1.0)) | setup.key_lo.index_select(0, t)


def _visible_subset(screen: ScreenTriangles, idx: torch.Tensor, keys: torch.Tensor,
                    shape: tuple[int, int, int], tile: int) -> torch.Tensor:
    """The triangles of ``idx`` (M,) that may still win a pixel: those whose lower bound of
    the depth over the pixel centres binning will test
    (:func:`~torchraster.raster.binning.plane_lower_bound` over
    :func:`~torchraster.raster.binning.tested_boxes`) is not above the largest depth of the
    keys so far (``keys`` (B*H*W,)) in the tiles those centres touch: the tile maxima of
    :func:`_tile_maxima` at the finest level whose tiles are larger than the box's side - 1
    (the box then touches at most 2 x 2 of them: its corners' tiles)."""
    if idx.numel() == 0:
        return idx
    b, h, w = shape
    items = screen.batch.index_select(0, idx)
    lo, hi = (int(v) for v in torch.aminmax(items))  # a chunk's items are few: only theirs
    box = tested_boxes(take_columns(screen.box, idx), (h, w), tile)
    extent = torch.maximum(box[BOX_XMAX] - box[BOX_XMIN], box[BOX_YMAX] - box[BOX_YMIN])
    # finest tiles: about the boxes' mean size (finer ones would cost more to build than
    # they cull), at least HIZ_TILE
    mean = int(extent.sum()) // extent.numel()
    finest = max(HIZ_TILE, 1 << max(0, mean.bit_length() - 1))
    maxima, by_extent = _tile_maxima(keys.view(b, h, w)[lo:hi + 1], finest)
    x, y, z = screen.pos.view(9, -1).index_select(1, idx).view(3, 3, -1)
    bound = plane_lower_bound(depth_planes(x, y, z), box).clamp_(max=1.0)  # keys clamp too
    largest = _box_maxima(maxima, by_extent, box, extent, items - lo if hi > lo else None)
    return idx[~(bound > largest)]  # NaN bounds stay (conservative)


def _box_maxima(maxima: torch.Tensor, by_extent: tuple[torch.Tensor, ...], box: torch.Tensor,
                extent: torch.Tensor, items: torch.Tensor | None) -> torch.Tensor:
    """(N,) the largest depth of :func:`_tile_maxima` over the tiles each box touches:
    ``box`` (4, N) int64 inclusive pixel boxes, ``extent`` (N,) their larger side - 1,
    ``items`` (N,) their item among the maps' (None: all the first)."""
    shift, width, per_item, offset = (t.index_select(0, extent) for t in by_extent)
    if items is not None:
        offset = offset.addcmul_(items, per_item)
    top = (box[BOX_YMIN] >> shift).mul_(width).add_(offset)
    bottom = (box[BOX_YMAX] >> shift).mul_(width).add_(offset)
    left, right = box[BOX_XMIN] >> shift, box[BOX_XMAX] >> shift
    return torch.maximum(
        torch.maximum(maxima.index_select(0, top + left), maxima.index_select(0, top + right)),
        torch.maximum(maxima.index_select(0, bottom + left),
                      maxima.index_select(0, bottom + right)))


def _tile_maxima(keys: torch.Tensor, tile: int
                 ) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
    """Tile maxima of ``(B, H, W)`` resolve keys for the occlusion test.

    Level l has tiles of side ``tile * 2**l`` (up to one tile holding the frame) and holds
    the largest depth (:func:`key_depth`: +inf where a pixel is empty) of each tile. Pixels
    past the frame's edge count as -inf (no tested centre is there).

    Returns:
        maxima: the levels' ``(B, Hl, Wl)`` float32 maps, flattened and concatenated.
        by_extent: four ``(max(H, W),)`` int64 tables indexed by a box's side - 1: for the
            finest level whose tiles are larger than that (so the box touches at most 2 x 2
            tiles), the level's shift ``log2(tile) + l``, width ``Wl``, per-item size
            ``Hl * Wl`` and offset in ``maxima``.
    """
    b, h, w = keys.shape
    rows, cols = -(-h // tile), -(-w // tile)
    low = int(depth_key(torch.tensor(float("-inf"), device=keys.device)))  # below every key
    if rows * tile != h or cols * tile != w:
        keys = torch.nn.functional.pad(keys, (0, cols * tile - w, 0, rows * tile - h),
                                       value=low)
    # two reductions over contiguous runs: 4x faster than one over both tile axes
    level = key_depth(keys.reshape(b, rows * tile, cols, tile).amax(-1)
                      .view(b, rows, tile, cols).amax(2))
    maps = [level]
    while tile << (len(maps) - 1) < max(h, w):
        r, c = level.shape[1:]
        level = torch.nn.functional.pad(level, (0, c % 2, 0, r % 2), value=float("-inf"))
        level = level.view(b, (r + 1) // 2, 2, (c + 1) // 2, 2).amax((2, 4))
        maps.append(level)
    extent = torch.arange(max(h, w), device=keys.device)  # box side - 1
    lvl = torch.zeros_like(extent)
    for k in range(len(maps) - 1):
        lvl += extent > (tile << k)
    meta = torch.tensor([[tile.bit_length() - 1 + k, m.shape[2], m.shape[1] * m.shape[2], 0]
                         for k, m in enumerate(maps)], device=keys.device)
    meta[1:, 3] = torch.tensor([m.numel() for m in maps[:-1]], device=keys.device).cumsum(0)
    return (torch.cat([m.reshape(-1) for m in maps]),
            tuple(meta[:, i].index_select(0, lvl) for i in range(4)))


def check_inputs(clip_pos, faces, resolution, face_ranges):
    """Checked inputs of :func:`rasterize`: (clip_pos, faces (int64 on clip_pos's device),
    (H, W), face_ranges or None), or an error naming the bad argument."""
    h, w = check_resolution(resolution)
    check_has_data("clip_pos", check_tensor("clip_pos", clip_pos, ("B", "V", 4), floating=True))
    check_has_data("faces", check_tensor("faces", faces, ("F", 3), integer=True))
    if clip_pos.shape[0] == 0:
        raise ValueError("clip_pos: batch size must be at least 1")
    faces = faces.to(device=clip_pos.device, dtype=torch.int64)
    n_vert = clip_pos.shape[1]
    lo, hi = (int(v) for v in torch.aminmax(faces)) if faces.numel() else (0, -1)
    if lo < 0 or hi >= n_vert:
        raise ValueError(
            f"faces: vertex indices must be in [0, {n_vert}) for clip_pos with V={n_vert}; "
            f"got range [{lo}, {hi}]")
    if clip_pos.numel() and not all_finite(clip_pos):
        bad = int((~torch.isfinite(clip_pos)).any(-1).sum())
        raise ValueError(f"clip_pos: {bad} vertex position(s) contain NaN/Inf")
    if faces.shape[0] >= 2**31:
        raise ValueError("faces: at most 2**31 - 1 faces are supported")
    if face_ranges is not None:
        check_tensor("face_ranges", face_ranges, (clip_pos.shape[0], 2), integer=True)
        face_ranges = face_ranges.to(device=clip_pos.device, dtype=torch.int64)
        if bool(((face_ranges[:, 0] < 0) | (face_ranges[:, 1] > faces.shape[0])
                 | (face_ranges[:, 0] > face_ranges[:, 1])).any()):
            raise ValueError(
                f"face_ranges: expected 0 <= start <= end <= F={faces.shape[0]} per row, got "
                f"{face_ranges.tolist()}")
    return clip_pos, faces, (h, w), face_ranges


def _triangle_chunks(b: int, n_faces: int, face_ranges: torch.Tensor | None,
                     device: torch.device, per_chunk: int):
    """Yield (batch ids, face ids) of at most ``per_chunk`` (item, face) pairs, whole items
    where they fit (an item's back faces are tested for occlusion against all of its front
    faces); an item of more than ``per_chunk`` faces is split."""
    if face_ranges is None:
        starts = torch.zeros(b, dtype=torch.int64, device=device)
        counts = torch.full((b,), n_faces, dtype=torch.int64, device=device)
    else:
        starts, counts = face_ranges[:, 0], face_ranges[:, 1] - face_ranges[:, 0]
    offsets = torch.cumsum(counts, 0) - counts
    cuts, end, fill = [0], 0, 0  # chunk boundaries; pairs so far; pairs in the open chunk
    for count in counts.tolist():
        if fill and fill + count > per_chunk:
            cuts.append(end)
            fill = 0
        end += count
        fill += count
        while fill > per_chunk:
            cuts.append(end - fill + per_chunk)
            fill -= per_chunk
    if end > cuts[-1]:
        cuts.append(end)
    items = torch.arange(b, device=device)
    first_face = starts - offsets  # face id = pair index + this, per item
    for k0, k1 in zip(cuts[:-1], cuts[1:], strict=False):
        # each item's pairs in [k0, k1): runs of batch ids (no search per pair)
        taken = (torch.minimum(offsets + counts, torch.tensor(k1, device=device))
                 - offsets.clamp(min=k0)).clamp_(min=0)
        batch_ids = torch.repeat_interleave(items, taken, output_size=k1 - k0)
        face_ids = torch.repeat_interleave(first_face, taken, output_size=k1 - k0)
        yield batch_ids, face_ids.add_(torch.arange(k0, k1, device=device))


def depth_key(z: torch.Tensor) -> torch.Tensor:
    """The high half of a depth-resolve key: the float32 bits of depth ``z`` (any shape) as
    an order-preserving signed integer (negatives' magnitude flipped), shifted left by 32
    (OR a face index < 2**31 into the low half)."""
    bits = z.to(torch.float32).view(torch.int32)
    bits = bits ^ ((bits >> 31) & 0x7FFFFFFF)  # signed-int order now equals float order
    return bits.to(torch.int64) << 32


def key_depth(keys: torch.Tensor) -> torch.Tensor:
    """The float32 depth of int64 keys (any shape): the inverse of :func:`depth_key`; +inf
    for ``EMPTY_KEY``."""
    # in chunks of 2**20 keys: the only full-size buffer is the result (a 4096² shadow map
    # view: 64 MB, no int64 / int32 / bool temporaries of its size)
    flat = keys.reshape(-1)
    out = torch.empty(flat.shape, dtype=torch.float32, device=keys.device)
    step = 2**20
    for k in range(0, flat.numel(), step):
        part = flat[k:k + step]
        bits = (part >> 32).to(torch.int32)
        bits = bits ^ ((bits >> 31) & 0x7FFFFFFF)  # inverse of depth_key's flip
        out[k:k + step] = bits.view(torch.float32).masked_fill_(part == EMPTY_KEY,
                                                                float("inf"))
    return out.view(keys.shape)


#: Chunks of at most this many candidates test the three edges in one broadcast
#: (:func:`~torchraster.raster.binning.block_edges`: fewer launches, which dominate small
#: chunks); larger ones one edge at a time (3x smaller temporaries: 5k faces at 1024²,
#: batch 8, was 6 % slower fused).
FUSED_EDGE_CANDIDATES = 2**16


def covered_keys(setup: TriangleSetup, rec: Records, resolution: tuple[int, int]
                 ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Test a chunk of kh x kw pixel blocks: the covered centres' flat pixel indices (M,)
    and depth-resolve keys (M,) (see :func:`depth_key`), or None if nothing is covered.

    Candidates are laid out (kh, kw, R) with the R records innermost, so every broadcast op
    runs long contiguous inner loops however small the blocks are.
    """
    coef = rec.take(setup.coef)  # (COEF_ROWS, R)
    px, py = record_centres(rec, coef.dtype)
    if rec.full:  # every centre is covered: keys in the record layout, no search
        h, w = resolution
        local = (torch.arange(rec.kh, device=px.device)[:, None] * w
                 + torch.arange(rec.kw, device=px.device)).view(-1, 1)
        base = rec.take(setup.batch) * (h * w) + rec.y0 * w + rec.x0
        face = rec.take(setup.key_lo).expand(rec.kh * rec.kw, -1).reshape(-1)
        depth = block_depth(coef, px, py).view(-1)
        return (local + base).view(-1), depth_key(depth.clamp_(-1.0, 1.0)) | face
    if rec.kh * rec.kw * px.shape[1] <= FUSED_EDGE_CANDIDATES:  # few: fewer launches
        edge = torch.ge(block_edges(coef, px, py), coef[EDGE_MIN][:, None, None, :])
        inside = edge[0].logical_and_(edge[1]).logical_and_(edge[2])
    else:  # many: one edge at a time keeps the temporaries in cache
        inside = None
        for e in range(3):
            edge = torch.ge(block_edge(coef, e, px, py), coef[EDGE_MIN.start + e])
            inside = edge if inside is None else inside.logical_and_(edge)
    flat, pixel, r = record_pixels(setup, rec, inside, resolution)
    if flat.numel() == 0:
        return None
    depth = block_depth(coef, px, py).view(-1).index_select(0, flat)
    return pixel, depth_key(depth.clamp_(-1.0, 1.0)) | rec.take(setup.key_lo).index_select(0, r)


def record_centres(rec: Records, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-centre coordinates of a chunk of records: px (kw, R) and py (kh, R)."""
    device = rec.x0.device
    px = rec.x0.to(dtype) + torch.arange(rec.kw, dtype=dtype, device=device)[:, None]
    py = rec.y0.to(dtype) + torch.arange(rec.kh, dtype=dtype, device=device)[:, None]
    return px, py


def record_pixels(setup: TriangleSetup, rec: Records, hits: torch.Tensor,
                  resolution: tuple[int, int]
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The True candidates of ``hits`` (kh, kw, R) (a chunk of records' candidates):
    their flat candidate index local * R + r (M,), flat frame pixel index b*H*W + y*W + x
    (M,) and record index r (M,)."""
    h, w = resolution
    n_rec = rec.x0.numel()
    # A 2-D nonzero yields (local, r) directly: cheaper than dividing the flat index.
    local, r = hits.view(-1, n_rec).nonzero().unbind(1)
    offsets = (torch.arange(rec.kh, device=hits.device)[:, None] * w
               + torch.arange(rec.kw, device=hits.device)).view(-1)
    base = rec.take(setup.batch) * (h * w) + rec.y0 * w + rec.x0
    flat = torch.add(r, local, alpha=n_rec)
    return flat, base.index_select(0, r) + offsets.index_select(0, local), r


def insert_layers(layers: torch.Tensor, pixel: torch.Tensor, key: torch.Tensor) -> None:
    """Merge candidates into per-pixel sorted lists of the K smallest distinct keys.

    Args:
        layers: ``(K, P)`` int64, updated in place: row k holds, per pixel, the k-th smallest
            distinct key seen so far (``EMPTY_KEY`` when there are fewer than k + 1).
        pixel: ``(M,)`` int64 pixel index of each candidate.
        key: ``(M,)`` int64 candidate keys (repeats are allowed and count once).

    Round k scatters the remaining candidates into row k with ``amin``; the winners leave,
    the keys they displaced from row k move on to row k + 1, and candidates equal to the
    row's key (duplicates) are dropped. The result is the set of the K smallest distinct
    keys, whatever the order in which chunks arrive: as deterministic as the single resolve.
    Work is one scatter per candidate and round it survives (K = 1: exactly one scatter).
    """
    k = layers.shape[0]
    if k == 1:
        layers[0].scatter_reduce_(0, pixel, key, reduce="amin")
        return
    keep = (key < layers[k - 1].index_select(0, pixel)).nonzero().squeeze(1)
    pixel, key = pixel.index_select(0, keep), key.index_select(0, keep)  # others cannot enter
    for row in layers:
        if key.numel() == 0:
            break
        old = row.index_select(0, pixel)
        row.scatter_reduce_(0, pixel, key, reduce="amin")
        new = row.index_select(0, pixel)
        # key > new: still waiting for a later row; key == new != old: the winner, whose
        # displaced old key moves on instead; key == new == old: a duplicate, dropped.
        moved = (key == new) & (old != new) & (old != EMPTY_KEY)
        keep = ((key > new) | moved).nonzero().squeeze(1)
        pixel = pixel.index_select(0, keep)
        key = torch.where(moved, old, key).index_select(0, keep)


#: Covered pixels evaluated per step of the per-pixel pass: its ~20 temporaries per pixel
#: then stay in the CPU's cache (measured 3-4x faster than whole-frame ops at 512², batch 8)
#: while each op is still long enough for torch's intra-op threads.
PIXEL_CHUNK = 2**16


def _fragments_from_keys(clip_pos, faces, keys, shape, derivatives) -> Fragments:
    """Decode face ids and recompute differentiable barycentrics and depth.

    1. Decode: the covered pixels, their faces, and one table row per visible (item, face)
       pair (``Fragments.rows``), with one of the face's covered pixels as its reference.
    2. Per face (:func:`face_tables`): the barycentric numerators l_i and the NDC depth as
       affine functions of the pixel's offset (column, row) from that reference, built with
       ordinary autograd ops from ``clip_pos``.
    3. Per pixel (:class:`_PixelPass`): gather the face's row, evaluate
       ``l = L + A du + B dv``, ``bary = l / sum(l)``, ``depth = D + Dx du + Dy dv`` in
       cache-sized chunks; its backward is the closed-form derivative (no autograd graph
       per pixel).
    """
    b, h, w = shape
    n_faces = faces.shape[0]
    dev = keys.device
    pixels = frame_pool.flatnonzero(keys != EMPTY_KEY)
    n = pixels.numel()
    # keys (this call's buffer) becomes face_id in place: its pages are already mapped. The
    # low half sign-extended is the face (< 2**31), and -1 for EMPTY_KEY (low half all
    # ones): two in-place shifts, a third of the time of a mask and a masked fill.
    face_id = keys.bitwise_left_shift_(32).bitwise_right_shift_(32)

    # Visible (item, face) pairs, a table row each (item by item: the pixels of an item are
    # one contiguous run), and one reference pixel per row.
    rows = frame_pool.empty((n,), torch.int64, dev)
    starts = torch.searchsorted(pixels, torch.arange(b + 1, device=dev) * (h * w)).tolist()
    visible = torch.zeros(n_faces, dtype=torch.bool, device=dev)
    row_face, row_item, count = [], [], 0
    for item in range(b):
        s0, s1 = starts[item], starts[item + 1]
        if s0 == s1:
            continue
        f = face_id.index_select(0, pixels[s0:s1])  # per item: a smaller fresh buffer
        visible.index_fill_(0, f, True)
        vis = visible.nonzero().squeeze(1)
        index = torch.cumsum(visible, 0, dtype=torch.int64 if n_faces >= 2**31 else torch.int32)
        torch.add(index.index_select(0, f), count - 1, out=rows[s0:s1])
        visible.index_fill_(0, vis, False)
        row_face.append(vis)
        row_item.append(torch.full_like(vis, item))
        count += vis.numel()
    row_face = torch.cat(row_face) if row_face else pixels.new_zeros(0)
    row_item = torch.cat(row_item) if row_item else pixels.new_zeros(0)
    ref = torch.full((count,), b * h * w, dtype=torch.int64, device=dev)
    ref.scatter_reduce_(0, rows, pixels, "amin")  # the face's first covered pixel
    clip_t = clip_pos.permute(2, 0, 1).reshape(4, -1)
    vert_ids = faces.index_select(0, row_face).T + row_item * clip_pos.shape[1]
    verts = clip_t.index_select(1, vert_ids.reshape(-1)).view(4, 3, -1)  # (4, 3, M)
    ref_cr = torch.stack(_pixel_coords(ref, h, w))  # (2, M) column, row
    table, front = face_tables(verts, ref_cr, (h, w))  # (FACE_TABLE_ROWS, M)
    ref_f = ref_cr.to(table.dtype)
    outs = _PixelPass.apply(table, ref_f, rows, pixels, (h, w), derivatives, False)
    grad_mode = torch.is_grad_enabled()

    def depth() -> torch.Tensor:  # evaluated on first use, in the grad mode of rasterize
        with torch.set_grad_enabled(grad_mode):
            return _PixelPass.apply(table, ref_f, rows, pixels, (h, w), False, True)[0]

    frags = Fragments(face_id.view(b, h, w), pixels, None, None, outs[0].T, None,
                      faces=faces, rows=rows, row_face=row_face, row_item=row_item,
                      row_front=front, depth_fn=depth)
    if derivatives:
        frags.bary_dx_packed, frags.bary_dy_packed = outs[1].T, outs[2].T
    return frags


def _pixel_coords(pixels: torch.Tensor, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(column j, row i), each int64 of ``pixels``' shape, of flat pixel indices
    b*H*W + i*W + j (shifts and masks for power-of-two sizes, else exact float division)."""
    if w & (w - 1) == 0 and h & (h - 1) == 0:
        shift = w.bit_length() - 1
        return pixels & (w - 1), (pixels >> shift) & (h - 1)
    rows_all = floor_div_exact(pixels, w)
    return pixels - rows_all * w, rows_all - floor_div_exact(rows_all, h) * h


class _PixelPass(torch.autograd.Function):
    """Per-pixel evaluation of the face tables (see :func:`face_tables`).

    Forward (no autograd bookkeeping, in chunks of :data:`PIXEL_CHUNK` pixels): with
    du = column - reference column, dv = row - reference row of the pixel's face row,
    ``l = L + A du + B dv``, ``S = sum(l)`` (1 where 0), ``bary = l / S``, and with
    derivatives ``bary_dx = (A - bary sum(A)) / S``, ``bary_dy = (B - bary sum(B)) / S``;
    or (``depth=True``) only ``depth = D + Dx du + Dy dv`` (a separate, lazy pass: most
    callers never read it). Backward: the closed-form derivative with respect to the table,
    accumulated per row with ``index_add_`` (deterministic on CPU).

    Inputs: table (FACE_TABLE_ROWS, M), ref (2, M) reference column and row (float), rows
    (N,) int64 table row per pixel, pixels (N,) int64 flat pixel index, resolution (H, W),
    derivatives (bool), depth (bool). Outputs: bary (3, N) and with derivatives bary_dx,
    bary_dy (3, N); or depth (N,).
    """

    @staticmethod
    def forward(ctx, table, ref, rows, pixels, resolution, derivatives, depth):
        n, dt = rows.numel(), table.dtype
        keep = ctx.needs_input_grad[0]
        ctx.depth = depth
        used = slice(FT_D, FT_DY + 1) if depth else slice(0, FT_B.stop)
        sub = table[used]
        def new(*shape: int) -> torch.Tensor:  # per-pixel: reused pages (frame_pool)
            return frame_pool.empty(shape, table.dtype, table.device)

        out = new(n) if depth else new(3, n)
        ddx = new(3, n) if derivatives else None
        ddy = new(3, n) if derivatives else None
        uv = new(2, n) if keep else None
        inv_s = new(n) if keep and not depth else None
        c = min(n, PIXEL_CHUNK)
        g = table.new_empty(sub.shape[0] * c)  # flat: every chunk's (rows, m) view is
        gr = table.new_empty(2 * c)  # contiguous (take_columns' fast float32 gather)
        inv_buf = table.new_empty(c)
        for sl in pixel_slices(n):
            m = sl.stop - sl.start
            r = rows[sl]
            gather = take_columns(sub, r, g[:sub.shape[0] * m].view(-1, m))
            ref_g = take_columns(ref, r, gr[:2 * m].view(2, m))
            col, row = _pixel_coords(pixels[sl], *resolution)
            du = col.to(dt).sub_(ref_g[0])
            dv = row.to(dt).sub_(ref_g[1])
            if keep:
                uv[0, sl], uv[1, sl] = du, dv
            if depth:  # rows D, Dx, Dy; clamped: the plane equation's float rounding can
                # pass the far plane by ~1e-5 (scripts/stress.py); gradient straight through
                torch.addcmul(gather[0], gather[1], du, out=out[sl]).addcmul_(
                    gather[2], dv).clamp_(-1.0, 1.0)
                continue
            lam = torch.addcmul(gather[FT_L], gather[FT_A], du).addcmul_(gather[FT_B], dv)
            inv = torch.sum(lam, 0, out=inv_buf[:m])
            inv.masked_fill_(inv == 0, 1.0).reciprocal_()
            torch.mul(lam, inv, out=out[:, sl])
            if derivatives:
                bs = out[:, sl]
                for dest, rows_ab in ((ddx, FT_A), (ddy, FT_B)):
                    torch.addcmul(gather[rows_ab], bs, gather[rows_ab].sum(0), value=-1.0,
                                  out=dest[:, sl]).mul_(inv)
            if keep:
                inv_s[sl] = inv
        outs = (out,) + ((ddx, ddy) if derivatives else ())
        if keep:
            ctx.save_for_backward(table, rows, uv, inv_s, *outs)
        ctx.set_materialize_grads(False)
        return outs

    @staticmethod
    def backward(ctx, g_out, g_ddx=None, g_ddy=None):
        table, rows, uv, inv_s, bary, *dd = ctx.saved_tensors
        grad = torch.zeros_like(table)
        if g_ddx is None and g_ddy is None:
            dd = []
        for sl in pixel_slices(rows.numel()):
            r, du, dv = rows[sl], uv[0, sl], uv[1, sl]
            rows_grad = []
            if ctx.depth:
                if g_out is not None:
                    gz = g_out[sl]
                    rows_grad = [(FT_D, gz), (FT_DX, gz * du), (FT_DY, gz * dv)]
            else:
                rows_grad = _bary_row_grads(table, r, du, dv, inv_s[sl], bary[:, sl],
                                            None if g_out is None else g_out[:, sl],
                                            [None if gd is None else gd[:, sl]
                                             for gd in (g_ddx, g_ddy)] if dd else [],
                                            [d[:, sl] for d in dd])
            for dest, src in rows_grad:
                grad[dest].index_add_(grad[dest].dim() - 1, r, src)
        return grad, None, None, None, None, None, None


def _bary_row_grads(table, r, du, dv, inv, b, gb, g_dd, dd):
    """Per-pixel gradients of the rows L, A, B of :class:`_PixelPass` (bary mode) for one
    chunk: ``[(rows, (3, m)), ...]``. gb: grad of bary (3, m) or None; g_dd: grads of
    bary_dx, bary_dy (each (3, m) or None; [] without derivatives); dd: their values."""
    contrib = {}
    gl_extra = None
    if g_dd:
        g = table.index_select(1, r)
        for gd, d, rows_ab in zip(g_dd, dd, (FT_A, FT_B), strict=True):
            if gd is None:
                continue
            # d_i = (X_i - b_i sum(X)) / S
            contrib[rows_ab.start] = (gd - (gd * b).sum(0)) * inv
            gb_d = -gd * (g[rows_ab].sum(0) * inv)
            gb = gb_d if gb is None else gb + gb_d
            gs = -(gd * d).sum(0) * inv
            gl_extra = gs if gl_extra is None else gl_extra + gs
    if gb is None and gl_extra is None:
        return []
    gl = torch.zeros_like(b) if gb is None else (gb - (gb * b).sum(0)) * inv
    if gl_extra is not None:
        gl = gl + gl_extra
    ga, gbb = gl * du, gl * dv
    if FT_A.start in contrib:
        ga = ga + contrib[FT_A.start]
    if FT_B.start in contrib:
        gbb = gbb + contrib[FT_B.start]
    return [(FT_L, gl), (FT_A, ga), (FT_B, gbb)]


def pixel_slices(n: int) -> list[slice]:
    return [slice(i, min(n, i + PIXEL_CHUNK)) for i in range(0, n, PIXEL_CHUNK)]


def _cross_rows(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(3, N) rows i = a_j b_k - b_j a_k with (i, j, k) cyclic (the 2-D cross products)."""
    return torch.stack([a[1] * b[2] - b[1] * a[2], a[2] * b[0] - b[2] * a[0],
                        a[0] * b[1] - b[0] * a[1]])


# Rows of the face_tables table, defined once: barycentric numerators l_i = L_i + A_i du +
# B_i dv and NDC depth D + Dx du + Dy dv at an offset (du, dv) in pixels from the reference.
FT_L, FT_A, FT_B = slice(0, 3), slice(3, 6), slice(6, 9)
FT_D, FT_DX, FT_DY = 9, 10, 11
FACE_TABLE_ROWS = 12


def face_tables(verts: torch.Tensor, ref: torch.Tensor, resolution: tuple[int, int]):
    """Per-triangle affine tables of perspective-correct barycentrics and depth.

    Args:
        verts: (4, 3, M) clip-space triangles, component-major ([x|y|z|w][vertex][tri]).
        ref: (2, M) int64 reference pixel (column, row) per triangle (one of its covered
            pixels).
        resolution: (H, W).

    With homogeneous 2-D vertices v_i = (x_i, y_i, w_i) and a pixel ray p = (x, y, 1), the
    unnormalised perspective-correct barycentrics are l_i = p . (v_j x v_k) (Olano & Greer
    1997, "Triangle scan conversion using 2D homogeneous coordinates"); b = l / sum(l), and
    NDC depth = sum(l z) / sum(l w), where sum(l w) = det M is constant over the triangle.
    No divide by w, so this holds for triangles crossing the near plane too. Both are affine
    in p; for float accuracy they are written around the reference pixel (x0, y0): the
    frame is sheared so that it is the origin (x'_i = x_i - x0 w_i, y'_i = y_i - y0 w_i;
    determinant 1, l unchanged), so L_i = l_i(p0) = x'_j y'_k - y'_j x'_k multiplies small,
    local numbers, and the per-pixel offsets (du, dv) are exact small integers. Each
    triangle is first scaled to max |component| = 1 (b and z are invariant), so products
    neither under- nor overflow. Depth is z_ndc0 + sum_i (l_i w_i / det) (z_ndc_i - z_ndc0)
    where every w_i > 1e-3 (differences of nearby depths keep their precision), else the
    plain ratio sum(l z) / det.

    Returns:
        table (FACE_TABLE_ROWS, M): rows L (FT_L), A = dl/d column (FT_A), B = dl/d row
        (FT_B), depth D at the reference and its steps Dx, Dy (FT_D, FT_DX, FT_DY),
        differentiable with respect to ``verts``; front (M,) bool: counter-clockwise in NDC
        (det M > 0).
    """
    h, w_px = resolution
    flat = verts.detach().reshape(12, -1)
    scale = torch.maximum(flat.amax(0), flat.amin(0).neg_()).clamp_(
        min=torch.finfo(verts.dtype).tiny)
    x, y, z, w = verts / scale  # each (3, M)
    x0 = (2 * ref[0] + 1).to(x.dtype).mul_(1.0 / w_px).sub_(1.0)
    y0 = (2 * ref[1] + 1).to(x.dtype).mul_(-1.0 / h).add_(1.0)
    xs, ys = x - x0 * w, y - y0 * w
    lam = _cross_rows(xs, ys)  # l_i at the reference
    # d l_i / d x_ndc = y'_j w_k - w_j y'_k, d l_i / d y_ndc = w_j x'_k - x'_j w_k; one column
    # right is d x_ndc = 2 / W, one row down d y_ndc = -2 / H.
    step_u = _cross_rows(ys, w) * (2.0 / w_px)
    step_v = _cross_rows(w, xs) * (-2.0 / h)
    det = (lam * w).sum(0)
    with torch.no_grad():
        front = det > 0
        usable = (w > 1e-3).all(0)
    det = _nonzero_or_one(det)
    z_ndc = z / torch.where(usable, w, torch.ones_like(w))
    dz = torch.stack([z_ndc[1] - z_ndc[0], z_ndc[2] - z_ndc[0]])
    # Depth weights: usable faces z_ndc0 + sum_{i=1,2} l_i w_i dz_i / det, else sum l_i z_i / det
    wz = torch.where(usable, torch.cat([torch.zeros_like(w[:1]), w[1:] * dz]), z) / det
    base = torch.where(usable, z_ndc[0], torch.zeros_like(z_ndc[0]))
    depth = torch.stack([base + (lam * wz).sum(0), (step_u * wz).sum(0),
                         (step_v * wz).sum(0)])
    return torch.cat([lam, step_u, step_v, depth]), front


def _nonzero_or_one(t: torch.Tensor) -> torch.Tensor:
    """``t`` with exact zeros replaced by 1: a safe denominator with finite gradients."""
    return torch.where(t == 0, torch.ones_like(t), t)
