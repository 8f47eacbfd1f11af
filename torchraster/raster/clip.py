"""Homogeneous clipping, culling and projection of triangles to screen space.

Input triangles are clip-space vertex triples; output are screen-space triangles ready for
binning. A triangle is

* **culled** when all three vertices lie outside one clip plane (e.g. all behind the
  camera), when it is degenerate (zero area on screen), back-facing (if asked), or covers
  no pixel centre;
* **passed through** when all its vertices lie inside every plane (the common case);
* **clipped** (Sutherland-Hodgman in homogeneous space, then fanned back into triangles)
  otherwise. The planes are near (z >= -w), far (z <= w) and a guard band |x|, |y| <= G w
  a few viewports wide, which keeps screen coordinates small enough for float32 edge
  functions. Sub-triangles keep the id of their original face: barycentrics are later
  recomputed from the original face, so clipping only has to get coverage right.

Screen coordinates are pixel units with pixel (row i, col j) centred at (x, y) = (j, i):
x = (x_ndc + 1) W / 2 - 1/2 and y = (1 - y_ndc) H / 2 - 1/2, so y points down.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..numerics import take_columns

GUARD_BAND = 8.0  # clip |x|, |y| to GUARD_BAND * w: triangles stay within ~8 viewports
MAX_POLY = 9  #: a triangle clipped by the 6 planes has at most 3 + 6 vertices


@dataclass
class ScreenTriangles:
    """Screen-space triangles, component-major so every row is one contiguous vector.

    pos:   (3, 3, N) [x | y | z][vertex][triangle]: pixel x, pixel y (pixel centres at
           integers, y down) and NDC z
    area:  (N,) twice the signed pixel-space area (negative = front facing)
    box:   (4, N) int64 inclusive pixel box xmin, xmax, ymin, ymax, clamped to the image
    face:  (N,) int64 original face index
    batch: (N,) int64 batch item
    valid: (N,) bool, False for culled triangles (None: all valid)
    """

    pos: torch.Tensor
    area: torch.Tensor
    box: torch.Tensor
    face: torch.Tensor
    batch: torch.Tensor
    valid: torch.Tensor | None = None

    def __len__(self) -> int:
        return self.face.shape[0]


# Clip planes p with p . (x, y, z, w) >= 0 inside: near, far, then the guard band.
_PLANES = (
    (0, 0, 1, 1), (0, 0, -1, 1),
    (-1, 0, 0, GUARD_BAND), (1, 0, 0, GUARD_BAND), (0, -1, 0, GUARD_BAND), (0, 1, 0, GUARD_BAND),
)


def _plane_dist(v: torch.Tensor, plane: tuple[float, ...]) -> torch.Tensor:
    """Signed distance of (..., 4) points to a plane, in a fixed order of float ops.

    Elementwise ops round exactly, so a vertex shared by two triangles gets bitwise the same
    distance in both (a matmul could reorder the sum between rows).
    """
    return v[..., 0] * plane[0] + v[..., 1] * plane[1] + v[..., 2] * plane[2] + v[..., 3] * plane[3]


def outcodes(clip_pos: torch.Tensor) -> torch.Tensor:
    """Bit i set where a vertex lies outside clip plane i. (..., 4) -> (...,) uint8."""
    x, y, z, w = clip_pos.unbind(-1)
    gw = GUARD_BAND * w
    code = (z < -w).to(torch.uint8)
    code |= (z > w).to(torch.uint8) << 1
    code |= (x > gw).to(torch.uint8) << 2
    code |= (x < -gw).to(torch.uint8) << 3
    code |= (y > gw).to(torch.uint8) << 4
    code |= (y < -gw).to(torch.uint8) << 5
    return code


def project(clip_pos: torch.Tensor, resolution: tuple[int, int]) -> torch.Tensor:
    """(..., 4) clip-space points -> (..., 3) pixel x, pixel y (down) and NDC z."""
    h, w = resolution
    inv_w = 1.0 / clip_pos[..., 3]
    x = (clip_pos[..., 0] * inv_w + 1) * (w / 2) - 0.5
    y = (1 - clip_pos[..., 1] * inv_w) * (h / 2) - 0.5
    return torch.stack([x, y, clip_pos[..., 2] * inv_w], dim=-1)


def clip_and_project(
    clip_pos: torch.Tensor,
    screen_t: torch.Tensor,
    codes: torch.Tensor,
    faces_t: torch.Tensor,
    face: torch.Tensor,
    batch: torch.Tensor,
    resolution: tuple[int, int],
    cull_backfaces: bool | torch.Tensor,
    margin: float = 0.0,
) -> ScreenTriangles:
    """Clip, cull and project the triangles (batch[n], faces[face[n]]).

    clip_pos: (B, V, 4) clip-space vertices; screen_t: (3, B*V) their projections (:func:`project`),
    component-major and contiguous (``project(clip_pos).view(-1, 3).T.contiguous()``);
    codes: (B, V) their :func:`outcodes`; faces_t: (3, F) contiguous vertex ids, vertex-major
    (``faces.T.contiguous()``); face, batch: (N,) int64. Front faces are counter-clockwise
    in NDC (y up). cull_backfaces: drop back faces, for every face (bool) or per face ((F,)
    bool tensor). margin: grow every pixel box by this many pixels (soft coverage reaches
    beyond the triangle). Returns :class:`ScreenTriangles`.
    """
    n_vert = codes.shape[1]
    # Global vertex ids (item * V + vertex) of every corner, vertex-major (3, N): every
    # gather below reads and writes whole rows (no transposing copies).
    corners = take_columns(faces_t, face).add_(batch * n_vert)
    c = codes.view(-1).index_select(0, corners.view(-1)).view(3, -1)
    any_out = c[0] | c[1] | c[2]
    all_out = c[0] & c[1] & c[2]
    inside = any_out == 0
    needs_clip = (any_out != 0) & (all_out == 0)

    sel = inside.nonzero().squeeze(1)
    pos = take_columns(screen_t, take_columns(corners, sel).view(-1)).view(3, 3, -1)
    face_out, batch_out = face.index_select(0, sel), batch.index_select(0, sel)
    if bool(needs_clip.any()):
        sel = needs_clip.nonzero().squeeze(1)
        ids = take_columns(corners, sel).T.reshape(-1)  # triangle-major
        ctri = clip_pos.reshape(-1, 4).index_select(0, ids)
        ctri, cidx = _clip_polygons(ctri.view(-1, 3, 4))
        pos = torch.cat([pos, project(ctri, resolution).permute(2, 1, 0)], dim=2)
        face_out = torch.cat([face_out, face[sel][cidx]])
        batch_out = torch.cat([batch_out, batch[sel][cidx]])

    h, w = resolution
    x, y = pos[0], pos[1]
    # Twice the signed area in pixel space (y down): negative = CCW in NDC = front facing.
    area = (x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0])
    ok = torch.isfinite(area) & (area != 0)
    if isinstance(cull_backfaces, torch.Tensor):  # per face: single-sided materials
        ok &= (area < 0) | ~cull_backfaces.index_select(0, face_out)
    elif cull_backfaces:
        ok &= area < 0
    # Pixel boxes; cull triangles whose box holds no pixel centre (tiny or off-screen).
    xmin, xmax, ymin, ymax = x.amin(0), x.amax(0), y.amin(0), y.amax(0)
    # Grown by the rounding of the edge functions (box_slack): a centre that float32 edges
    # put inside a triangle is in its box, so a shared edge never loses a centre to both
    # of its triangles' boxes.
    grow = box_slack(torch.maximum(torch.maximum(xmin.abs(), xmax.abs()),
                                   torch.maximum(ymin.abs(), ymax.abs()))).add_(margin)
    xmin, xmax, ymin, ymax = xmin - grow, xmax + grow, ymin - grow, ymax + grow
    xmin = torch.ceil(xmin.clamp_(min=0))
    xmax = torch.floor(xmax.clamp_(max=w - 1))
    ymin = torch.ceil(ymin.clamp_(min=0))
    ymax = torch.floor(ymax.clamp_(max=h - 1))
    ok &= (xmin <= xmax) & (ymin <= ymax)
    # Culled triangles stay in the arrays, flagged: binning drops them in the same gather
    # that orders the others by block shape (one permutation instead of two).
    box = torch.stack([xmin, xmax, ymin, ymax]).nan_to_num_(0.0).long()
    return ScreenTriangles(pos=pos, area=area, box=box, face=face_out, batch=batch_out,
                           valid=ok)


def box_slack(extent: torch.Tensor) -> torch.Tensor:
    """How far (pixels) float rounding can move a triangle's edges (binning's
    A x + (B y + C), with C through an endpoint) given the largest vertex coordinate
    magnitude ``extent`` (N,): C and the evaluation round terms up to (|A| + |B|) extent,
    about 3 eps (|A| + |B|) extent in all, i.e. 4.3 eps extent pixels of distance, plus eps
    extent for the rounded edge direction; 8 eps (extent + 1) bounds both."""
    return (extent + 1).mul_(8 * torch.finfo(extent.dtype).eps)


def _lex_less(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Lexicographic a < b over the last dimension."""
    diff = b - a
    nonzero = diff != 0
    first = nonzero.to(torch.uint8).argmax(dim=-1, keepdim=True)
    return (diff.gather(-1, first).squeeze(-1) > 0) & nonzero.any(dim=-1)


def _clip_polygons(tri: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Clip (M, 3, 4) triangles against all planes (:func:`clip_polygons`), then fan them.

    Returns (K, 3, 4) triangles and their (K,) source index into ``tri``.
    """
    poly, count = clip_polygons(tri)
    # Fan triangulation (v0, v_k, v_k+1) for k = 1 .. count - 2.
    k = torch.arange(1, MAX_POLY - 1, device=tri.device)
    fan_ok = k[None, :] < (count[:, None] - 1)
    src, kk = fan_ok.nonzero(as_tuple=True)
    kk = kk + 1
    out = torch.stack([poly[src, 0], poly[src, kk], poly[src, kk + 1]], dim=1)
    return out, src


def clip_polygons(tri: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Sutherland-Hodgman clip of (M, 3, 4) clip-space triangles against all planes (near,
    far, guard band).

    Returns (M, MAX_POLY, 4) convex polygons (slots past the count are zero) and their (M,)
    vertex counts (< 3: nothing left). Intersections are computed with the edge's endpoints
    in a canonical (lexicographic) order, so an edge shared by two triangles is cut at
    bitwise the same point from either side. Differentiable with respect to ``tri``.
    """
    m = tri.shape[0]
    poly = tri.new_zeros(m, MAX_POLY, 4)
    poly[:, :3] = tri
    count = torch.full((m,), 3, dtype=torch.long, device=tri.device)
    slots = torch.arange(MAX_POLY, device=tri.device)
    for plane in _PLANES:
        valid = slots < count[:, None]
        nxt_idx = torch.where(slots + 1 < count[:, None], slots + 1, 0)
        nxt = poly.gather(1, nxt_idx[:, :, None].expand(-1, -1, 4))
        d_cur = _plane_dist(poly, plane)
        d_nxt = d_cur.gather(1, nxt_idx)
        in_cur, in_nxt = d_cur >= 0, d_nxt >= 0
        swap = _lex_less(nxt, poly)
        a = torch.where(swap[..., None], nxt, poly)
        b = torch.where(swap[..., None], poly, nxt)
        da = torch.where(swap, d_nxt, d_cur)
        db = torch.where(swap, d_cur, d_nxt)
        denom = da - db
        t = da / torch.where(denom == 0, torch.ones_like(denom), denom)
        cut = a + t[..., None] * (b - a)
        emit = torch.stack([valid & in_cur, valid & (in_cur != in_nxt)], dim=2)  # (M, S, 2)
        cand = torch.stack([poly, cut], dim=2)  # (M, S, 2, 4)
        emit = emit.reshape(m, -1)
        cand = cand.reshape(m, -1, 4)
        dest = torch.cumsum(emit, dim=1) - 1
        dest = torch.where(emit & (dest < MAX_POLY), dest, MAX_POLY)  # overflow slot
        new = tri.new_zeros(m, MAX_POLY + 1, 4)
        new.scatter_(1, dest[:, :, None].expand(-1, -1, 4), cand)
        poly = new[:, :MAX_POLY]
        count = emit.sum(dim=1).clamp(max=MAX_POLY)
    return poly, count
