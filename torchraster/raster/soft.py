"""Soft rasterization: coverage probabilities from signed screen distances (SoftRas).

The hard rasterizer's coverage is a step function of the vertex positions, so a pixel
outside a silhouette gets no gradient. Soft rasterization (Liu et al. 2019, "Soft
Rasterizer: A Differentiable Renderer for Image-based 3D Reasoning"; PyTorch3D's
``blur_radius`` + ``softmax_rgb_blend``) replaces it with a probability that decays with the
pixel's distance to the triangle, and blends the K nearest faces of every pixel:

* :func:`soft_rasterize` keeps, per pixel, the K nearest faces (by depth) among those whose
  coverage probability ``sigmoid(d / sigma)`` is at least ``min_prob`` (``d``: signed
  distance in pixels from the pixel centre to the face's screen triangle, positive inside),
  and returns differentiable distances, probabilities, barycentrics and depths;
* :func:`soft_blend` turns per-face colours into an RGBA image with SoftRas's aggregation
  (softmax over normalised inverse depth, weighted by the probabilities, plus background),
  and :meth:`SoftFragments.silhouette` is ``1 - prod(1 - prob)``.

Visibility follows the engine's two passes. The no-grad pass is the hard rasterizer's
binning and key resolve with a wider coverage (:class:`SoftCoverage`): boxes and tiles are
grown by the cut-off distance, each candidate's exact distance to its (clipped) screen
triangle is tested, and its key is the depth of the triangle's nearest point; the K
smallest keys per pixel are kept by :func:`~torchraster.raster.rasterize.insert_layers`.
The differentiable pass then recomputes, from the clip-space positions, each kept face's
signed distance, nearest point, perspective-correct barycentrics of that point and its
depth (faces crossing a clip plane are clipped differentiably first), in chunks
under activation checkpointing, so memory stays bounded by the (B, H, W, K) outputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch.utils.checkpoint import checkpoint

from ..numerics import floor_div_exact
from .binning import (
    COEF_ROWS,
    DZDX,
    DZDY,
    EDGE_A,
    EDGE_B,
    EDGE_MIN,
    Records,
    TriangleSetup,
    block_depth,
    block_edge,
    setup_triangles,
)
from .clip import MAX_POLY, ScreenTriangles, clip_polygons, outcodes
from .rasterize import (
    DEFAULT_MEMORY_BUDGET,
    Coverage,
    check_inputs,
    check_layers,
    check_options,
    depth_key,
    record_centres,
    record_pixels,
    resolve_keys,
)

# Rows appended to TriangleSetup.coef by SoftCoverage (3 rows each: one per edge e).
SOFT_TX = slice(COEF_ROWS, COEF_ROWS + 3)  #: T_e(p) = tx x + (ty y + tc): position along
SOFT_TY = slice(COEF_ROWS + 3, COEF_ROWS + 6)  #: the edge, 0 at one end and 1 at the other
SOFT_TC = slice(COEF_ROWS + 6, COEF_ROWS + 9)
SOFT_LEN2 = slice(COEF_ROWS + 9, COEF_ROWS + 12)  #: squared edge length (px^2)
SOFT_INV_LEN2 = slice(COEF_ROWS + 12, COEF_ROWS + 15)  #: its inverse (0 for length 0)
SOFT_DZN = slice(COEF_ROWS + 15, COEF_ROWS + 18)  #: depth change per unit E towards the line
SOFT_DZT = slice(COEF_ROWS + 18, COEF_ROWS + 21)  #: depth change per unit T along the edge
SOFT_COEF_ROWS = COEF_ROWS + 21

#: Default smallest kept coverage probability: faces farther than the matching distance
#: (9.2 sigma for the linear profile) are not candidates of a pixel.
DEFAULT_MIN_PROB = 1e-4
_SOFT_BYTES_PER_CANDIDATE = 96  # ~9 float32 temporaries of the distance test + masks
_SOFT_BYTES_PER_SLOT = 160  # keys, ids, dist/prob/bary/depth and their gradients per slot
_SLOT_BYTES = 2048  # float temporaries of the differentiable pass per slot (chunk sizing)


@dataclass
class SoftFragments:
    """The K nearest faces of every pixel within the soft coverage radius (channels last).

    face_id: (B, H, W, K) int64, -1 for empty slots; nearest first (by the depth of the
             face's nearest point to the pixel centre, ties by face index).
    dist:    (B, H, W, K) signed distance in pixels from the pixel centre to the face's
             visible screen polygon, positive inside; -inf in empty slots. Differentiable.
    prob:    (B, H, W, K) coverage probability sigmoid(dist / sigma) (squared profile:
             sigmoid(sign(dist) dist^2 / sigma)); 0 in empty slots. Differentiable.
    bary:    (B, H, W, K, 3) perspective-correct barycentrics of the face's point nearest to
             the pixel centre (the pixel's own point inside the face); 0 in empty slots.
    depth:   (B, H, W, K) NDC z of that point, +inf in empty slots. Differentiable.
    sigma, squared: the profile that made ``prob``.
    """

    face_id: torch.Tensor
    dist: torch.Tensor
    prob: torch.Tensor
    bary: torch.Tensor
    depth: torch.Tensor
    sigma: float
    squared: bool

    def silhouette(self) -> torch.Tensor:
        """Soft silhouette ``1 - prod_k (1 - prob_k)``: (B, 1, H, W)."""
        return (1.0 - torch.prod(1.0 - self.prob, dim=-1)).unsqueeze(1)

    def interpolate(self, vertex_attrs: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
        """Per-slot attributes: (B, V, C) or (V, C) vertex attributes interpolated with
        ``bary`` -> (B, H, W, K, C), 0 in empty slots; differentiable in both."""
        b, h, w, k = self.face_id.shape
        if vertex_attrs.dim() == 2:
            vertex_attrs = vertex_attrs[None]
        vertex_attrs = vertex_attrs.expand(b, -1, -1)
        n_vert, c = vertex_attrs.shape[1:]
        faces = faces.to(device=self.face_id.device, dtype=torch.int64)
        fid = self.face_id.clamp(min=0).view(b, -1)  # (B, H*W*K)
        corners = faces.index_select(0, fid.reshape(-1)).view(b, -1, 3)
        corners = corners + (torch.arange(b, device=fid.device) * n_vert)[:, None, None]
        attrs = vertex_attrs.reshape(-1, c).index_select(0, corners.reshape(-1))
        attrs = attrs.view(b, h, w, k, 3, c).to(self.bary.dtype)
        return (self.bary[..., None] * attrs).sum(-2)


def soft_rasterize(
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    resolution: tuple[int, int] | int,
    *,
    sigma: float = 1.0,
    k: int = 8,
    squared: bool = False,
    min_prob: float = DEFAULT_MIN_PROB,
    cull_backfaces: bool | torch.Tensor = False,
    face_ranges: torch.Tensor | None = None,
    tile: int | None = None,
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
) -> SoftFragments:
    """Soft rasterization: the K nearest faces within the sigma-neighbourhood of each pixel.

    Args:
        clip_pos: (B, V, 4) float clip-space positions, as in :func:`rasterize`.
        faces: (F, 3) int64 vertex indices shared by the batch.
        resolution: (H, W) or an int; pixel centres as in :func:`rasterize`.
        sigma: width of the coverage profile in pixels (``squared``: in square pixels).
            ``prob = sigmoid(d / sigma)`` with d the signed distance in pixels (positive
            inside); sigma -> 0 gives the hard coverage. PyTorch3D's / SoftRas's sigma (NDC
            units squared, ``squared=True``) is ``sigma_ndc * (min(H, W) / 2) ** 2`` here.
        k: faces kept per pixel (the K nearest by depth).
        squared: use SoftRas's profile ``sigmoid(sign(d) d^2 / sigma)`` (zero gradient at
            the edge itself, faster decay) instead of ``sigmoid(d / sigma)``.
        min_prob: faces whose probability at a pixel is below this are not candidates there:
            the cut-off distance is ``sigma * log(1 / min_prob - 1)`` (``squared``: the
            square root of that), 9.2 sigma by default.
        cull_backfaces, face_ranges: as in :func:`rasterize`.
        tile: binning tile in pixels; default: 16, or larger for wide cut-offs.
        memory_budget: bytes of temporaries per chunk (both passes).

    Returns:
        :class:`SoftFragments` with (B, H, W, K) face ids, signed distances, probabilities,
        depths and (B, H, W, K, 3) barycentrics, differentiable with respect to clip_pos.

    Example:
        >>> clip = torch.tensor([[[-0.5, -0.5, 0, 1], [0.5, -0.5, 0, 1], [0, 0.5, 0, 1]]])
        >>> faces = torch.tensor([[0, 1, 2]])
        >>> sf = soft_rasterize(clip, faces, (8, 8), sigma=0.5, k=2)
        >>> rgba = soft_blend(sf.interpolate(torch.eye(3), faces), sf)
        >>> rgba.shape, bool((rgba[:, 3] > 0).all())  # coverage (and gradients) outside too
        (torch.Size([1, 4, 8, 8]), True)
    """
    clip_pos, faces, (h, w), face_ranges = check_inputs(clip_pos, faces, resolution,
                                                         face_ranges)
    k = check_layers(k, "k")
    if not (isinstance(sigma, (int, float)) and math.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma: expected a positive finite float, got {sigma!r}")
    if not 0.0 < min_prob < 0.5:
        raise ValueError(f"min_prob: expected a float in (0, 0.5), got {min_prob!r}")
    logit = math.log(1.0 / min_prob - 1.0)
    cutoff = math.sqrt(sigma * logit) if squared else sigma * logit
    if tile is None:
        tile = 16 if cutoff <= 4 else 32
    cull_backfaces = check_options(clip_pos, faces, cull_backfaces, tile)
    b = clip_pos.shape[0]
    keys = resolve_keys(clip_pos, faces, (h, w), cull_backfaces, face_ranges, int(tile),
                        memory_budget, _SOFT_BYTES_PER_SLOT * k, layers=k,
                        coverage=SoftCoverage(cutoff))
    face_id, dist, bary, depth = _soft_pass(clip_pos, faces, keys, (b, h, w), memory_budget)
    valid = face_id >= 0
    d = torch.where(valid, dist, 0.0)  # no inf in the graph: finite gradients
    prob = torch.where(valid, torch.sigmoid((d * d.abs() if squared else d) / sigma), 0.0)
    return SoftFragments(face_id, dist, prob, bary, depth, sigma, squared)


def soft_blend(
    colors: torch.Tensor,
    frags: SoftFragments,
    *,
    gamma: float = 1e-4,
    background: torch.Tensor | float | None = None,
    eps: float = 1e-10,
) -> torch.Tensor:
    """SoftRas aggregation of per-slot colours into an RGBA image.

    With p_k the slots' probabilities and z_k = (1 - NDC z_k) / 2 their normalised inverse
    depth (1 at the near plane, 0 at the far plane; NDC z is affine in 1 / view depth):
    ``w_k = p_k exp(z_k / gamma) / (sum_j p_j exp(z_j / gamma) + exp(eps / gamma))`` and
    ``rgb = sum_k w_k c_k + w_bg background`` (w_bg the last term's share); alpha is the
    silhouette ``1 - prod_k (1 - p_k)``. gamma -> 0 keeps only the nearest face.

    Args:
        colors: (B, H, W, K, C) colour of every slot (e.g. ``frags.interpolate(...)``).
        frags: from :func:`soft_rasterize`.
        gamma: depth temperature (smaller: sharper occlusion).
        background: None (0), a float, a (C,) colour or a (B, C, H, W) image.
        eps: the background's depth offset, as in SoftRas / PyTorch3D (also floors its
            weight so a denominator is never 0).

    Returns:
        (B, C + 1, H, W): blended colour channels then alpha; differentiable with respect
        to colors and, through the probabilities and depths, clip positions.
    """
    if gamma <= 0:
        raise ValueError(f"gamma: expected a positive float, got {gamma!r}")
    b, h, w, k = frags.face_id.shape
    if colors.dim() != 5 or tuple(colors.shape[:4]) != (b, h, w, k):
        raise ValueError(f"colors: expected shape ({b}, {h}, {w}, {k}, C), got "
                         f"{tuple(colors.shape)}")
    valid = frags.face_id >= 0
    z = torch.where(valid, (1.0 - frags.depth.clamp(-1.0, 1.0)) * 0.5, 0.0)
    # Stabiliser: the ratio is invariant to the shift, so it carries no gradient.
    top = z.detach().amax(-1, keepdim=True).clamp(min=eps)
    num = frags.prob * torch.exp((z - top) / gamma)
    bg = torch.exp((eps - top) / gamma).clamp(min=eps)
    den = num.sum(-1, keepdim=True) + bg  # (B, H, W, 1)
    rgb = (num[..., None] * colors).sum(-2)  # (B, H, W, C)
    c = colors.shape[-1]
    if background is not None:
        bgc = torch.as_tensor(background, dtype=colors.dtype, device=colors.device)
        if bgc.dim() == 4:
            bgc = bgc.permute(0, 2, 3, 1)
        elif bgc.dim() not in (0, 1):
            raise ValueError(f"background: expected a float, a ({c},) colour or a "
                             f"(B, {c}, H, W) image, got shape {tuple(bgc.shape)}")
        rgb = rgb + bg * bgc
    rgb = rgb / den
    alpha = 1.0 - torch.prod(1.0 - frags.prob, dim=-1, keepdim=True)
    return torch.cat([rgb, alpha], -1).permute(0, 3, 1, 2)


class SoftCoverage(Coverage):
    """Candidates of the soft visibility pass: every pixel centre within ``cutoff`` pixels of
    a screen triangle (exact Euclidean distance; centres inside by the top-left rule),
    keyed by the depth of the triangle's point nearest to it."""

    bytes_per_candidate = _SOFT_BYTES_PER_CANDIDATE

    def __init__(self, cutoff: float):
        self.margin = float(cutoff)
        self.cutoff2 = float(cutoff) ** 2

    def setup(self, screen: ScreenTriangles) -> TriangleSetup:
        """The hard table plus the SOFT_* rows of every edge."""
        base = setup_triangles(screen)
        x, y = screen.pos[0], screen.pos[1]  # (3, N): vertex rows
        ax, ay = torch.cat([x[1:], x[:1]]), torch.cat([y[1:], y[:1]])  # edge e: vertex e+1
        ux = torch.cat([x[2:], x[:2]]) - ax  # ... to vertex e+2
        uy = torch.cat([y[2:], y[:2]]) - ay
        len2 = ux * ux + uy * uy
        inv = torch.where(len2 > 0, 1.0 / torch.where(len2 > 0, len2, 1.0), 0.0)
        coef = base.coef
        gx, gy = coef[DZDX], coef[DZDY]
        rows = [ux * inv, uy * inv, -(ux * ax + uy * ay) * inv, len2, inv,
                (gx * coef[EDGE_A] + gy * coef[EDGE_B]) * inv, gx * ux + gy * uy]
        base.coef = torch.cat([coef, *rows])
        return base

    def cover(self, setup: TriangleSetup, rec: Records, resolution: tuple[int, int]
              ) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Pixels within the cut-off, keyed by the depth of the nearest point."""
        coef = rec.take(setup.coef)  # (SOFT_COEF_ROWS, R)
        px, py = record_centres(rec, coef.dtype)
        emin = coef[EDGE_MIN]
        tx, ty, tc = coef[SOFT_TX], coef[SOFT_TY], coef[SOFT_TC]
        len2, inv, dzn, dzt = coef[SOFT_LEN2], coef[SOFT_INV_LEN2], coef[SOFT_DZN], coef[SOFT_DZT]
        inside = best = shift = None
        for e in range(3):
            edge = block_edge(coef, e, px, py)
            covered = edge >= emin[e]
            inside = covered if inside is None else inside.logical_and_(covered)
            t = torch.add((ty[e] * py + tc[e])[:, None, :], (tx[e] * px)[None, :, :])
            dt = t.clamp(0.0, 1.0).sub_(t)  # along the edge from the line's foot to the segment
            d2 = edge * edge * inv[e] + dt * dt * len2[e]  # squared distance to the segment
            dz = dt * dzt[e] - edge * dzn[e]  # depth from the pixel to that nearest point
            if best is None:
                best, shift = d2, dz
            else:
                closer = d2 < best
                best = torch.where(closer, d2, best)
                shift = torch.where(closer, dz, shift)
        flat, pixel, r = record_pixels(setup, rec, inside | (best <= self.cutoff2),
                                       resolution)
        if flat.numel() == 0:
            return None
        depth = block_depth(coef, px, py).view(-1).index_select(0, flat)
        shift = torch.where(inside, 0.0, shift).view(-1).index_select(0, flat)
        key = depth_key((depth + shift).clamp_(-1.0, 1.0))
        return pixel, key | rec.take(setup.key_lo).index_select(0, r)


def _soft_pass(clip_pos, faces, keys, shape, memory_budget):
    """Differentiable pass over the kept slots: face ids (B, H, W, K) and the dist (B, H,
    W, K), bary (B, H, W, K, 3) and depth (B, H, W, K) of every slot."""
    b, h, w = shape
    k, n_pix = keys.shape
    dtype = clip_pos.dtype
    face_kp = (keys << 32) >> 32  # (K, P) low half sign-extended: -1 for EMPTY_KEY
    face_kp = _drop_repeated_faces(face_kp, clip_pos, faces)
    face_id = face_kp.T.contiguous()  # (P, K)
    slot = (face_id >= 0).view(-1).nonzero().squeeze(1)  # p * K + k
    n = slot.numel()
    pixel = floor_div_exact(slot, k)
    face = face_id.view(-1).index_select(0, slot)
    item = floor_div_exact(pixel, h * w)
    rem = pixel - item * (h * w)
    row = floor_div_exact(rem, w)
    col = rem - row * w
    vert = faces.index_select(0, face) + (item * clip_pos.shape[1])[:, None]  # (N, 3)
    px = torch.stack([col, row], -1).to(dtype)  # (N, 2) pixel centres
    flat_clip = clip_pos.reshape(-1, 4)
    chunk = max(1024, int(memory_budget) // _SLOT_BYTES)
    outs = []
    for s in range(0, n, chunk):
        args = (flat_clip, vert[s:s + chunk], px[s:s + chunk], (h, w))
        if torch.is_grad_enabled() and clip_pos.requires_grad and n > chunk:
            outs.append(checkpoint(_slot_geometry, *args, use_reentrant=False))
        else:
            outs.append(_slot_geometry(*args))
    d, bc, z = (torch.cat(parts) for parts in zip(*outs, strict=True)) if outs else (
        clip_pos.new_zeros(0), clip_pos.new_zeros(0, 3), clip_pos.new_zeros(0))
    dist = clip_pos.new_full((n_pix * k,), float("-inf")).index_copy(0, slot, d)
    depth = clip_pos.new_full((n_pix * k,), float("inf")).index_copy(0, slot, z)
    bary = clip_pos.new_zeros((n_pix * k, 3)).index_copy(0, slot, bc)
    return (face_id.view(b, h, w, k), dist.view(b, h, w, k), bary.view(b, h, w, k, 3),
            depth.view(b, h, w, k))


def _drop_repeated_faces(face_kp: torch.Tensor, clip_pos: torch.Tensor,
                         faces: torch.Tensor) -> torch.Tensor:
    """A clipped face is several screen triangles in the visibility pass and may hold more
    than one slot of a pixel: keep its first (nearest) slot only, and move the freed slots
    to the end. (K, P) -> (K, P)."""
    k = face_kp.shape[0]
    if k == 1:
        return face_kp
    with torch.no_grad():
        codes = outcodes(clip_pos.detach().reshape(-1, 4)).view(clip_pos.shape[:2])
        clipped = (codes.index_select(1, faces.reshape(-1)).view(-1, faces.shape[0], 3)
                   != 0).any(-1).any(0)  # (F,) clipped in some batch item
        if not bool(clipped.any()):
            return face_kp
        hit = clipped.index_select(0, face_kp.clamp(min=0).view(-1)).view(face_kp.shape)
        cols = ((face_kp >= 0) & hit).any(0).nonzero().squeeze(1)
        sub = face_kp.index_select(1, cols)  # (K, P'): pixels with a clipped face
        same = (sub[:, None, :] == sub[None, :, :]) & (sub[None, :, :] >= 0)  # (K, K, P')
        earlier = torch.ones(k, k, dtype=torch.bool, device=sub.device).tril(-1)
        repeated = (same & earlier[:, :, None]).any(1)
        sub = torch.where(repeated, -1, sub)
        holes_last = torch.sort((sub < 0).to(torch.uint8), dim=0, stable=True).indices
        return face_kp.index_copy(1, cols, sub.gather(0, holes_last))


def _slot_geometry(flat_clip: torch.Tensor, vert: torch.Tensor, px: torch.Tensor,
                   resolution: tuple[int, int]):
    """Signed distance (N,), barycentrics (N, 3) and NDC depth (N,) of the nearest point
    of each slot's face (clip-space vertices ``flat_clip[vert]``, (N, 3)) to pixel centre
    ``px`` (N, 2) (pixel units, y down)."""
    h, w = resolution
    tri = flat_clip.index_select(0, vert.reshape(-1)).view(-1, 3, 4)  # (N, 3, 4)
    with torch.no_grad():
        crosses = (outcodes(tri.detach()) != 0).any(-1)  # (N,): clip before projecting
    dist = torch.empty_like(px[:, 0])
    near = torch.empty_like(px)
    whole = (~crosses).nonzero().squeeze(1)
    parts = [(whole, tri.index_select(0, whole), None)]
    if bool(crosses.any()):
        cut = crosses.nonzero().squeeze(1)
        poly, count = _clipped_polygons(tri.index_select(0, cut))
        parts.append((cut, poly, count))
    for idx, poly, count in parts:
        if idx.numel() == 0:
            continue
        screen = _to_pixels(poly, (h, w))
        d, q = _polygon_distance(screen, px.index_select(0, idx))
        if count is not None:  # clipped away entirely (rounding): no coverage
            d = torch.where(count >= 3, d, torch.full_like(d, -1e30))
        dist = dist.index_copy(0, idx, d)
        near = near.index_copy(0, idx, q)
    bary, depth = _point_bary_depth(tri, near, (h, w))
    return dist, bary, depth


def _to_pixels(poly: torch.Tensor, resolution: tuple[int, int]) -> torch.Tensor:
    """(N, P, 4) clip-space points with w >= 0 -> (N, P, 2) pixel x, y (y down)."""
    h, w = resolution
    cw = poly[..., 3].clamp(min=torch.finfo(poly.dtype).tiny)
    x = (poly[..., 0] / cw + 1.0) * (w / 2) - 0.5
    y = (1.0 - poly[..., 1] / cw) * (h / 2) - 0.5
    return torch.stack([x, y], -1)


def _clipped_polygons(tri: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(M, 3, 4) triangles clipped differentiably as in the visibility pass
    (:func:`~torchraster.raster.clip.clip_polygons`: near, far, guard band), unused slots
    repeating the last vertex (zero-length edges): (M, MAX_POLY, 4) polygons and (M,)
    counts. Inside near and far, w >= 0, and the guard band keeps projections finite."""
    poly, count = clip_polygons(tri)
    slots = torch.arange(MAX_POLY, device=tri.device)
    fill = torch.minimum(slots[None, :], (count - 1).clamp(min=0)[:, None])
    return poly.gather(1, fill[:, :, None].expand(-1, -1, 4)), count


def _polygon_distance(poly: torch.Tensor, p: torch.Tensor):
    """Signed distance (N,) in pixels from points p (N, 2) to convex polygons (N, P, 2)
    (positive inside) and the polygon's point nearest to p (N, 2) (p itself inside).

    Inside: the smallest distance to an edge line (smooth). Outside: the smallest distance
    to an edge segment, through a square root floored at 1e-24 px^2 (finite gradients)."""
    a = poly
    ab = torch.roll(poly, -1, dims=1) - a  # (N, P, 2)
    ap = p[:, None, :] - a
    cross = ab[..., 0] * ap[..., 1] - ab[..., 1] * ap[..., 0]  # (N, P)
    area = (a[..., 0] * torch.roll(a[..., 1], -1, 1) - torch.roll(a[..., 0], -1, 1)
            * a[..., 1]).sum(1)
    orient = torch.sign(area).detach()[:, None]
    len2 = (ab * ab).sum(-1)
    has_len = len2 > 0
    safe_len2 = torch.where(has_len, len2, torch.ones_like(len2))
    inward = cross * orient
    inside = ((inward >= 0).all(1) & (area != 0)).detach()
    line = torch.where(has_len, inward / safe_len2.sqrt(), torch.full_like(len2, math.inf))
    d_in = line.min(1).values
    t = torch.where(has_len, (ap * ab).sum(-1) / safe_len2, torch.zeros_like(len2))
    t = t.clamp(0.0, 1.0)
    foot = a + t[..., None] * ab  # (N, P, 2) nearest point of each edge
    off = p[:, None, :] - foot
    d2 = (off * off).sum(-1)
    best = d2.detach().argmin(1, keepdim=True)
    d2_min = d2.gather(1, best).squeeze(1)
    d_out = torch.sqrt(d2_min.clamp(min=1e-24))
    q = foot.gather(1, best[..., None].expand(-1, -1, 2)).squeeze(1)
    dist = torch.where(inside, torch.where(torch.isfinite(d_in), d_in, 0.0), -d_out)
    q = torch.where(inside[:, None], p, q)
    return dist, q


def _point_bary_depth(tri: torch.Tensor, q: torch.Tensor, resolution: tuple[int, int]):
    """Perspective-correct barycentrics (N, 3) (clamped to the face) and NDC depth (N,) of
    the points of clip-space triangles (N, 3, 4) seen through pixel positions q (N, 2).

    2-D homogeneous edge functions (as in :func:`~torchraster.raster.rasterize.face_tables`):
    each triangle is scaled to max |component| = 1 and sheared so that q is the origin."""
    h, w = resolution
    qx = (2.0 * q[:, 0] + 1.0) / w - 1.0
    qy = 1.0 - (2.0 * q[:, 1] + 1.0) / h
    scale = tri.detach().abs().flatten(1).amax(1).clamp(min=torch.finfo(tri.dtype).tiny)
    v = tri / scale[:, None, None]
    x, y, z, cw = v.unbind(-1)  # (N, 3) each
    xs, ys = x - qx[:, None] * cw, y - qy[:, None] * cw
    lam = torch.stack([xs[:, 1] * ys[:, 2] - ys[:, 1] * xs[:, 2],
                       xs[:, 2] * ys[:, 0] - ys[:, 2] * xs[:, 0],
                       xs[:, 0] * ys[:, 1] - ys[:, 0] * xs[:, 1]], -1)  # (N, 3)
    total = lam.sum(-1, keepdim=True)
    total = torch.where(total == 0, torch.ones_like(total), total)
    bary = (lam / total).clamp(min=0.0)
    norm = bary.sum(-1, keepdim=True)
    bary = bary / torch.where(norm == 0, torch.ones_like(norm), norm)
    den = (bary * cw).sum(-1)
    depth = (bary * z).sum(-1) / torch.where(den == 0, torch.ones_like(den), den)
    return bary, depth
