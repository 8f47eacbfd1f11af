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

import torch

from .._validate import check_frame_memory, check_resolution, check_tensor
from ..numerics import floor_div_exact
from .binning import (
    EDGE_MIN,
    Records,
    TriangleSetup,
    bin_triangles,
    block_depth,
    block_edge,
    setup_triangles,
    sort_by_block,
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

    Packed form (what ``interpolate`` uses; N = covered pixels): ``pixels`` (N,) flat index
    b*H*W + i*W + j, ``items`` (N,) batch item, ``corners`` (3, N) vertex ids of the visible
    face, ``bary_packed`` (N, 3), ``depth_packed`` (N,), and with derivatives
    ``bary_dx_packed`` / ``bary_dy_packed`` (N, 3). The full (B, H, W, ...) tensors are
    built on first access.
    """

    def __init__(self, face_id, pixels, items, corners, bary_packed, depth_packed,
                 bary_dx_packed=None, bary_dy_packed=None):
        self.face_id = face_id
        self.pixels = pixels
        self.items = items
        self.corners = corners
        self.bary_packed = bary_packed
        self.depth_packed = depth_packed
        self.bary_dx_packed = bary_dx_packed
        self.bary_dy_packed = bary_dy_packed
        self.front_facing: torch.Tensor | None = None  # (N,) bool, CCW in NDC
        self.deeper: tuple[Fragments, ...] = ()  # layers 1 .. K-1 (no reference cycle)
        self._cache: dict[str, torch.Tensor] = {}

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
            self._cache[name] = full.index_copy(0, self.pixels, packed).view(
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
        return (self.face_id >= 0).unsqueeze(1).to(self.bary_packed.dtype)


def rasterize(
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    resolution: tuple[int, int] | int,
    cull_backfaces: bool | torch.Tensor = False,
    face_ranges: torch.Tensor | None = None,
    *,
    derivatives: bool = False,
    layers: int = 1,
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
        >>> frags = rasterize(clip, faces, (256, 256), layers=2)
        >>> front, back = frags.layers  # e.g. the two sides of a closed mesh
    """
    clip_pos, faces, (h, w), face_ranges = check_inputs(clip_pos, faces, resolution,
                                                         face_ranges)
    cull_backfaces = check_options(clip_pos, faces, cull_backfaces, tile)
    layers = check_layers(layers)
    keys = resolve_keys(clip_pos, faces, (h, w), cull_backfaces, face_ranges, int(tile),
                        memory_budget, BYTES_PER_PIXEL * layers, layers=layers)
    b = clip_pos.shape[0]
    frags = [_fragments_from_keys(clip_pos, faces, k, (b, h, w), derivatives) for k in keys]
    frags[0].deeper = tuple(frags[1:])
    return frags[0]


def rasterize_depth(
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    resolution: tuple[int, int] | int,
    cull_backfaces: bool | torch.Tensor = False,
    face_ranges: torch.Tensor | None = None,
    *,
    tile: int = DEFAULT_TILE,
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
) -> torch.Tensor:
    """Depth-only rasterization (shadow maps, depth pre-passes): the visibility half of
    :func:`rasterize` without the barycentric pass, so no gradients.

    Args:
        clip_pos, faces, resolution, cull_backfaces, face_ranges, tile, memory_budget: as
            in :func:`rasterize` (same coverage rule, clipping and depth resolve).

    Returns:
        ``(B, H, W)`` float32 NDC z of the nearest surface, clamped to [-1, 1], ``+inf``
        where nothing is covered; the same coverage and winners as :func:`rasterize`. The
        value is the resolve's depth plane (within ~1e-6 of ``rasterize(...).depth``, which
        is recomputed differentiably).

    Example:
        >>> depth = rasterize_depth(clip, faces, (512, 512))  # (B, 512, 512)
    """
    clip_pos, faces, (h, w), face_ranges = check_inputs(clip_pos, faces, resolution,
                                                         face_ranges)
    cull_backfaces = check_options(clip_pos, faces, cull_backfaces, tile)
    keys = resolve_keys(clip_pos, faces, (h, w), cull_backfaces, face_ranges, int(tile),
                        memory_budget, _DEPTH_BYTES_PER_PIXEL)
    return key_depth(keys[0]).view(clip_pos.shape[0], h, w)


#: Peak bytes per pixel of rasterize_depth beyond the chunk budget: the int64 key and the
#: float32 result.
_DEPTH_BYTES_PER_PIXEL = 16


def check_layers(layers: int, name: str = "layers") -> int:
    """``layers`` as a positive int, or a ValueError naming the argument ``name``."""
    if isinstance(layers, bool) or not isinstance(layers, (int, float)) or (
            int(layers) != layers or layers < 1):
        raise ValueError(f"{name}: expected a positive int, got {layers!r}")
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
                 coverage: Coverage | None = None) -> torch.Tensor:
    """The no-grad visibility pass: ``(K, B*H*W)`` int64 keys (depth bits << 32 | face),
    the K smallest distinct ones per pixel in increasing order, ``EMPTY_KEY`` where there
    are fewer. Arguments as in :func:`rasterize` (checked); ``bytes_per_pixel`` is the
    frame memory the caller will need per pixel (checked up front)."""
    coverage = coverage or Coverage()
    h, w = resolution
    b = clip_pos.shape[0]
    check_frame_memory(f"resolution ({h}, {w}) at batch {b}", b * h * w, bytes_per_pixel,
                       clip_pos.device)
    max_candidates = max(1024, int(memory_budget) // coverage.bytes_per_candidate)
    keys = torch.full((layers, b * h * w), EMPTY_KEY, dtype=torch.int64,
                      device=clip_pos.device)
    with torch.no_grad():
        # Visibility runs in float32 (float64 for float64 input), whatever the input dtype.
        pos = clip_pos.detach()
        if pos.dtype != torch.float64:
            pos = pos.float()
        codes, screen_pos = outcodes(pos), project(pos, (h, w))
        for batch_ids, face_ids in _triangle_chunks(b, faces.shape[0], face_ranges, pos.device,
                                                    max_candidates // 8):
            screen = clip_and_project(pos, screen_pos, codes, faces, face_ids, batch_ids,
                                      (h, w), cull_backfaces, margin=coverage.margin)
            screen, runs, n_small = sort_by_block(screen, (h, w), tile)
            if len(screen) == 0:
                continue
            setup = coverage.setup(screen)
            for records in bin_triangles(setup, runs, n_small, (h, w), tile,
                                         max_candidates, margin=coverage.margin):
                found = coverage.cover(setup, records, (h, w))
                if found is not None:
                    insert_layers(keys, *found)
    return keys


def check_inputs(clip_pos, faces, resolution, face_ranges):
    """Checked inputs of :func:`rasterize`: (clip_pos, faces (int64 on clip_pos's device),
    (H, W), face_ranges or None), or an error naming the bad argument."""
    h, w = check_resolution(resolution)
    check_tensor("clip_pos", clip_pos, ("B", "V", 4), floating=True)
    check_tensor("faces", faces, ("F", 3), integer=True)
    if clip_pos.shape[0] == 0:
        raise ValueError("clip_pos: batch size must be at least 1")
    faces = faces.to(device=clip_pos.device, dtype=torch.int64)
    n_vert = clip_pos.shape[1]
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= n_vert):
        raise ValueError(
            f"faces: vertex indices must be in [0, {n_vert}) for clip_pos with V={n_vert}; "
            f"got range [{int(faces.min())}, {int(faces.max())}]")
    if not bool(torch.isfinite(clip_pos).all()):
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
    """Yield (batch ids, face ids) of at most ``per_chunk`` (item, face) pairs."""
    if face_ranges is None:
        starts = torch.zeros(b, dtype=torch.int64, device=device)
        counts = torch.full((b,), n_faces, dtype=torch.int64, device=device)
    else:
        starts, counts = face_ranges[:, 0], face_ranges[:, 1] - face_ranges[:, 0]
    offsets = torch.cumsum(counts, 0) - counts
    total = int(counts.sum())
    for k0 in range(0, total, per_chunk):
        k = torch.arange(k0, min(total, k0 + per_chunk), device=device)
        batch_ids = torch.searchsorted(offsets, k, right=True) - 1
        yield batch_ids, starts[batch_ids] + (k - offsets[batch_ids])


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
    bits = (keys >> 32).to(torch.int32)
    bits = bits ^ ((bits >> 31) & 0x7FFFFFFF)  # inverse of depth_key's flip
    depth = bits.view(torch.float32)
    return torch.where(keys == EMPTY_KEY, torch.full_like(depth, float("inf")), depth)


def covered_keys(setup: TriangleSetup, rec: Records, resolution: tuple[int, int]
                 ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Test a chunk of kh x kw pixel blocks: the covered centres' flat pixel indices (M,)
    and depth-resolve keys (M,) (see :func:`depth_key`), or None if nothing is covered.

    Candidates are laid out (kh, kw, R) with the R records innermost, so every broadcast op
    runs long contiguous inner loops however small the blocks are.
    """
    coef = rec.take(setup.coef)  # (COEF_ROWS, R)
    px, py = record_centres(rec, coef.dtype)
    inside = None
    for e in range(3):
        edge = block_edge(coef, e, px, py).ge_(coef[EDGE_MIN][e])
        inside = edge if inside is None else inside.logical_and_(edge)
    flat = inside.view(-1).nonzero().squeeze(1)
    if flat.numel() == 0:
        return None
    depth = block_depth(coef, px, py).view(-1).index_select(0, flat)
    pixel, r = record_pixels(setup, rec, flat, resolution)
    return pixel, depth_key(depth.clamp_(-1.0, 1.0)) | rec.take(setup.key_lo).index_select(0, r)


def record_centres(rec: Records, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-centre coordinates of a chunk of records: px (kw, R) and py (kh, R)."""
    device = rec.x0.device
    px = rec.x0.to(dtype) + torch.arange(rec.kw, dtype=dtype, device=device)[:, None]
    py = rec.y0.to(dtype) + torch.arange(rec.kh, dtype=dtype, device=device)[:, None]
    return px, py


def record_pixels(setup: TriangleSetup, rec: Records, flat: torch.Tensor,
                  resolution: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat frame pixel index b*H*W + y*W + x (M,) and record index r (M,) of candidates
    ``flat`` (M,) = local * R + r of a (kh, kw, R) candidate layout."""
    h, w = resolution
    n_rec = rec.x0.numel()
    local = floor_div_exact(flat, n_rec)
    r = flat - local * n_rec
    offsets = (torch.arange(rec.kh, device=flat.device)[:, None] * w
               + torch.arange(rec.kw, device=flat.device)).view(-1)
    base = rec.take(setup.batch) * (h * w) + rec.y0 * w + rec.x0
    return base.index_select(0, r) + offsets.index_select(0, local), r


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


_PIXELS_PER_PASS = 2**20  # batch items are decoded in groups of about this many pixels


def _fragments_from_keys(clip_pos, faces, keys, shape, derivatives) -> Fragments:
    """Decode face ids and recompute barycentrics and depth, a group of batch items at a
    time, so per-pixel temporaries stay near _PIXELS_PER_PASS pixels whatever the batch
    (time then grows linearly with the batch, and peak memory beyond the outputs does not).
    """
    b, h, w = shape
    per = max(1, _PIXELS_PER_PASS // (h * w))
    if b <= per:
        return _fragment_pass(clip_pos, faces, keys, shape, derivatives)
    parts = [_fragment_pass(clip_pos[i:i + per], faces, keys[i * h * w:(i + per) * h * w],
                            (min(per, b - i), h, w), derivatives) for i in range(0, b, per)]
    offsets = range(0, b, per)

    def cat(name, dim=0):
        values = [getattr(p, name) for p in parts]
        return None if values[0] is None else torch.cat(values, dim)

    frags = Fragments(
        torch.cat([p.face_id for p in parts]),
        torch.cat([p.pixels + i * h * w for p, i in zip(parts, offsets, strict=True)]),
        torch.cat([p.items + i for p, i in zip(parts, offsets, strict=True)]),
        cat("corners", 1), torch.cat([p.bary_packed.T for p in parts], 1).T,
        cat("depth_packed"))
    frags.front_facing = cat("front_facing")
    if derivatives:
        frags.bary_dx_packed = torch.cat([p.bary_dx_packed.T for p in parts], 1).T
        frags.bary_dy_packed = torch.cat([p.bary_dy_packed.T for p in parts], 1).T
    return frags


def _fragment_pass(clip_pos, faces, keys, shape, derivatives) -> Fragments:
    """Decode face ids and recompute differentiable barycentrics and depth.

    The per-pixel work is an affine evaluation: every visible (item, face) gets a small
    table (barycentric numerators at one of its pixels, their screen gradients, the depth
    numerator and denominator) from :func:`face_tables`, and each pixel evaluates it at its
    offset from that reference pixel.
    """
    b, h, w = shape
    n_faces = faces.shape[0]
    pixels = (keys != EMPTY_KEY).nonzero().squeeze(1)
    face = keys.index_select(0, pixels) & 0xFFFFFFFF
    face_id = torch.full((b * h * w,), -1, dtype=torch.int64, device=keys.device)
    face_id.index_copy_(0, pixels, face)
    rows_all = floor_div_exact(pixels, w)  # b * H + row
    items = floor_div_exact(rows_all, h)
    col = pixels - rows_all * w
    row = rows_all - items * h
    corners = faces.index_select(0, face).T.contiguous()  # (3, N) vertex ids, vertex-major
    dtype = clip_pos.dtype
    x_ndc = (2 * col + 1).to(dtype).mul_(1.0 / w).sub_(1.0)
    y_ndc = (2 * row + 1).to(dtype).mul_(-1.0 / h).add_(1.0)

    # Visible (item, face) pairs, a table row each, and one reference pixel per row.
    slot = items * n_faces + face
    visible = torch.zeros(b * n_faces, dtype=torch.bool, device=keys.device)
    visible.index_fill_(0, slot, True)
    vis = visible.nonzero().squeeze(1)
    row_of = (torch.cumsum(visible, 0) - 1).index_select(0, slot)  # (N,) table row per pixel
    ref = torch.full((vis.numel(),), pixels.numel(), dtype=torch.int64, device=keys.device)
    ref.scatter_reduce_(0, row_of, torch.arange(pixels.numel(), device=keys.device), "amin")
    vis_item, vis_face = vis // n_faces, vis % n_faces
    clip_t = clip_pos.permute(2, 0, 1).reshape(4, -1)
    vert_ids = faces.index_select(0, vis_face).T + vis_item * clip_pos.shape[1]
    verts = clip_t.index_select(1, vert_ids.reshape(-1)).view(4, 3, -1)  # (4, 3, n_vis)
    x0, y0 = x_ndc.index_select(0, ref), y_ndc.index_select(0, ref)
    table, z_clip, front = face_tables(verts, x0, y0)  # (FACE_TABLE_ROWS, n_vis)

    # Per pixel: shear the table's local vertices once more, by the offset from the
    # reference point (small numbers times small numbers: accurate even on slivers).
    t = table[:FT_USABLE].index_select(1, row_of)  # (12, N): the per-pixel rows
    xs, ys, wv, zv = t[FT_X], t[FT_Y], t[FT_W], t[FT_Z]  # zv: z_ndc0, dz_ndc1, dz_ndc2
    xs = xs - (x_ndc - x0.index_select(0, row_of)) * wv
    ys = ys - (y_ndc - y0.index_select(0, row_of)) * wv
    lam = _cross_rows(xs, ys)  # (3, N) barycentric numerators
    total = _nonzero_or_one(lam.sum(0))
    bary = lam / total
    lw = lam * wv
    den = _nonzero_or_one(lw.sum(0))
    # NDC depth sum(l z) / sum(l w), written as z_0 + sum_i beta_i (z_i - z_0) with the
    # screen-space weights beta_i = l_i w_i / sum(l w) and NDC z_i = z_i / w_i: differences
    # of nearby depths keep their precision (3e-8 instead of 2e-7 in float32 at z ~ 1).
    depth = zv[0] + (lw[1] * zv[1] + lw[2] * zv[2]) / den
    far_from_eye = table[FT_USABLE].index_select(0, row_of) > 0
    if not bool(far_from_eye.all()):  # faces with a vertex near / behind the eye plane
        ratio = (lam * z_clip.index_select(1, row_of)).sum(0) / den
        depth = torch.where(far_from_eye, depth, ratio)
    frags = Fragments(face_id.view(b, h, w), pixels, items, corners, bary.T, depth)
    frags.front_facing = front.index_select(0, row_of)
    if derivatives:
        # d l_i / d x_ndc = y'_j w_k - w_j y'_k, d l_i / d y_ndc = w_j x'_k - x'_j w_k;
        # d b_i = (d l_i - b_i d sum(l)) / sum(l); per pixel step: d/d(col) = (2 / W)
        # d/dx_ndc, d/d(row) = -(2 / H) d/dy_ndc
        gx, gy = _cross_rows(ys, wv), _cross_rows(wv, xs)
        frags.bary_dx_packed = ((gx - bary * gx.sum(0)) / total * (2.0 / w)).T
        frags.bary_dy_packed = ((gy - bary * gy.sum(0)) / total * (-2.0 / h)).T
    return frags


def _cross_rows(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(3, N) rows i = a_j b_k - b_j a_k with (i, j, k) cyclic (the 2-D cross products)."""
    return torch.stack([a[1] * b[2] - b[1] * a[2], a[2] * b[0] - b[2] * a[0],
                        a[0] * b[1] - b[0] * a[1]])


# Rows of the face_tables table, defined once (the per-pixel rows come first).
FT_X, FT_Y, FT_W = slice(0, 3), slice(3, 6), slice(6, 9)  #: sheared x', y' and w per vertex
FT_Z = slice(9, 12)  #: NDC z of vertex 0, then z_ndc_i - z_ndc_0 for i = 1, 2
FT_USABLE = 12  #: 1 where every w_i > 1e-3 (NDC z usable), else 0
FACE_TABLE_ROWS = 13


def face_tables(verts: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor):
    """Per-triangle local frames for perspective-correct barycentrics and depth.

    verts: (4, 3, n) clip-space triangles, component-major ([x|y|z|w][vertex][triangle]);
    x0, y0: (n,) an NDC reference point per triangle (one of its covered pixel centres).

    With homogeneous 2-D vertices v_i = (x_i, y_i, w_i) and a pixel ray p = (x, y, 1), the
    unnormalised perspective-correct barycentrics are l_i = p . (v_j x v_k) (Olano & Greer
    1997, "Triangle scan conversion using 2D homogeneous coordinates"); b = l / sum(l), and
    NDC depth = sum(l z) / sum(l w). No divide by w, so this holds for triangles crossing
    the near plane too. For float accuracy the frame is sheared so that the pixel is the
    origin (x'_i = x_i - x w_i, y'_i = y_i - y w_i; determinant 1, l unchanged): then
    l_i = x'_j y'_k - y'_j x'_k multiplies small, local numbers. The shear is split in two:
    to the triangle's reference point here, once per triangle, and by the pixel's offset
    from it per pixel. Each triangle is first scaled to max |component| = 1 (b and z are
    invariant), so products neither under- nor overflow.

    Returns table (FACE_TABLE_ROWS, n): rows x' (FT_X), y' (FT_Y), w (FT_W) of the scaled
    triangle sheared to the reference point, NDC z of vertex 0 and z_ndc_i - z_ndc_0 for
    i = 1, 2 (FT_Z), and (FT_USABLE) 1 where every w_i > 1e-3 (NDC z usable; the triangle
    is scaled to max |component| = 1, so |z / w| <= 1e3) else 0; z (3, n) the scaled
    clip z (for the plain ratio elsewhere); and front (n,) bool: counter-clockwise in NDC
    (det M > 0).
    """
    flat = verts.detach().reshape(12, -1)
    scale = torch.maximum(flat.amax(0), flat.amin(0).neg_()).clamp_(
        min=torch.finfo(verts.dtype).tiny)
    x, y, z, w = verts / scale  # each (3, n)
    xs, ys = x - x0 * w, y - y0 * w
    with torch.no_grad():
        front = (_cross_rows(xs, ys) * w).sum(0) > 0  # sum_i l_i w_i = det M
        usable = (w > 1e-3).all(0)
    z_ndc = z / torch.where(usable, w, torch.ones_like(w))
    z_rows = torch.stack([z_ndc[0], z_ndc[1] - z_ndc[0], z_ndc[2] - z_ndc[0]])
    z_rows = torch.where(usable, z_rows, torch.zeros_like(z_rows))
    return torch.cat([xs, ys, w, z_rows, usable[None].to(w.dtype)]), z, front


def _nonzero_or_one(t: torch.Tensor) -> torch.Tensor:
    """``t`` with exact zeros replaced by 1: a safe denominator with finite gradients."""
    return torch.where(t == 0, torch.ones_like(t), t)
