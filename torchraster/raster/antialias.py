"""Analytic antialiasing: gradients of visibility at silhouette and occlusion edges.

``rasterize`` decides visibility without gradients: ``Fragments.face_id`` and the coverage
mask are piecewise constant in the vertex positions, so a loss on a silhouette alone has no
gradient. :func:`antialias` (after Laine et al. 2020, "Modular Primitives for
High-Performance Differentiable Rendering", Sec. 3.4, implemented from the paper's text)
blends the colours of horizontally or vertically adjacent pixels whose visible faces differ,
by where the occluding silhouette edge crosses the segment between the two pixel centres.
The crossing moves continuously with the vertices, so the blended image has gradients with
respect to ``clip_pos`` there.

1. *no grad*, over the packed pixel pairs with differing face ids, a chunk at a time
   (``memory_budget``): the segment between the two pixel centres is walked over the mesh
   (edge adjacency from one sort of the edges, :func:`antialias_topology`), from the face
   visible at one pixel across internal edges to the first silhouette edge (boundary,
   non-manifold, or a fold: both faces on the same side of the edge as seen from the eye;
   this does not depend on the winding); the nearer of the two pixels' walks that found
   one gives the occluder's edge.
2. *differentiable*, on the blending pairs only: the crossing ``t`` in [0, 1] (from the
   occluder's pixel centre) is recomputed from the edge's clip-space endpoints with 2-D
   homogeneous line coordinates (no divide by w, valid for edges crossing the near plane),
   and the pixel on the far side of the midpoint takes ``|t - 1/2|`` (times the pair
   direction's share of the edge) of the other pixel's colour.
"""

from __future__ import annotations

import torch

from .._validate import all_finite, check_tensor
from ..numerics import compute_dtype, finish_low_precision, floor_div_exact
from .rasterize import DEFAULT_MEMORY_BUDGET, Fragments

#: Bytes of no-grad temporaries per pixel pair in a walk step (~130 float32 values over
#: the three edges, ~20 int64 indices and masks); doubled for float64 clip positions.
_BYTES_PER_PAIR = 1024


def antialias_topology(faces: torch.Tensor) -> torch.Tensor:
    """Edge adjacency of a mesh for :func:`antialias`, built with one sort of its edges.

    Edge ``k`` of face ``f`` runs from ``faces[f, k]`` to ``faces[f, (k + 1) % 3]``; its
    *slot* is ``3 f + k``.

    Args:
        faces: int vertex indices of the triangles.

    Returns:
        int64 ``across``: ``across[f, k]`` is the slot ``3 g + l`` of the same edge in the
        one other face ``g`` that shares it, or -1 where the edge is a boundary (one face)
        or non-manifold (three or more faces). Pass it as ``antialias(..., topology=...)``
        to reuse it across calls with the same faces.

    Shape:
        - faces: :math:`(F, 3)`.
        - Output: :math:`(F, 3)`.

    Example:
        >>> antialias_topology(torch.tensor([[0, 1, 2], [2, 1, 3]])).tolist()
        [[-1, 3, -1], [1, -1, -1]]
    """
    check_tensor("faces", faces, ("F", 3), integer=True)
    faces = faces.to(torch.int64)
    n = faces.shape[0] * 3
    if n == 0:
        return faces.clone()
    start, end = faces.reshape(-1), faces.roll(-1, 1).reshape(-1)
    n_vert = int(faces.max()) + 1
    key = torch.minimum(start, end) * n_vert + torch.maximum(start, end)
    key, order = torch.sort(key, stable=True)
    _, inverse, counts = torch.unique_consecutive(key, return_inverse=True, return_counts=True)
    pos = torch.arange(n, device=faces.device)
    next_same = torch.zeros(n, dtype=torch.bool, device=faces.device)
    next_same[:-1] = key[1:] == key[:-1]
    partner = torch.where(next_same, pos + 1, pos - 1).clamp_(0, n - 1)
    across = torch.where(counts.index_select(0, inverse) == 2, order.index_select(0, partner),
                         torch.full_like(key, -1))
    return torch.empty_like(across).index_copy_(0, order, across).view(-1, 3)


def antialias(
    color: torch.Tensor,
    frags: Fragments,
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    *,
    topology: torch.Tensor | None = None,
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
) -> torch.Tensor:
    """Antialias silhouette and occlusion edges analytically, with gradients to geometry.

    Every pair of 4-neighbour pixels with different ``frags.face_id`` is a potential
    visibility edge. From each pixel ``o`` of the pair that shows a face, the segment from
    its centre to the centre of the other pixel ``n`` is walked over the mesh: through the
    edge where it leaves the current face into the neighbouring face, as long as that edge
    is internal, until it crosses a *silhouette* edge (a boundary or non-manifold edge, or
    one whose two faces lie on the same side of it as seen from the eye: a fold, where the
    surface turns away), at the fraction ``t`` in [0, 1] of the segment. The walk ends
    without a silhouette when it enters the face visible at ``n`` (both pixels show one
    connected surface: internal edges never blend; pairs whose two faces share an edge that
    is not a fold are not walked at all), reaches ``n``'s centre, or has crossed
    ``MAX_WALK`` faces. The *occluder* side is the walk that found a silhouette, or if
    both did, the one from the face of smaller ``frags.depth`` (at its own pixel). The pair
    then *blends* unless the crossing lies behind the near plane or beyond the far plane,
    or the edge is parallel to the pair.

    A blending pair gives the weight ``w = s |t - 1/2|`` to its *target*: ``n`` if
    ``t > 1/2`` (the occluder covers part of ``n``'s footprint) else ``o`` (the occluder
    misses part of its own); the *source* is the other pixel of the pair. ``s`` is the
    pair axis's share of the edge (:data:`ORIENTATION_POWER`): with the edge's normal
    ``(n_x, n_y)`` in pixel units, ``s = n_x^4 / (n_x^4 + n_y^4)`` for horizontal pairs
    and ``n_y^4 / (n_x^4 + n_y^4)`` for vertical ones, so the two directions together
    count every straight edge once. Then, per batch item and pixel ``x``::

        out[:, x] = color[:, x] + sum_r w_r (color[:, src_r] - color[:, x]) / max(1, sum_r w_r)

    over the blending pairs ``r`` whose target is ``x`` (at most four, each ``w_r <= 1/2``;
    the normalisation only acts on sub-pixel features blended from three or four sides, and
    keeps every output a convex combination of ``x`` and its neighbours: an alpha or
    coverage channel stays in [0, 1]). Pixels in no blending pair keep their value exactly.

    ``t`` and ``s`` are differentiable functions of the edge's clip-space endpoints
    (x, y, w), so the output is differentiable with respect to ``clip_pos`` (through them)
    and ``color``. Which pairs blend (face ids, depths, the walk) carries no gradient: the
    output is piecewise smooth in ``clip_pos``. Antialias a coverage ``frags.mask`` (or
    an alpha channel) the same way to get a differentiable coverage: it is just another
    channel. Nothing divides by w: edges crossing the near plane or with a vertex at
    w = 0 give finite values and gradients. Only what the two pixel centres see is known:
    a second silhouette between them (a thin horn tip, a fold in front of a farther part
    of the surface) is missed.

    Args:
        color: the shaded image to antialias (any channels: colour, alpha, coverage,
            features), e.g. ``interpolate(...)`` or the output of a shading pass.
        frags: the :class:`Fragments` of ``rasterize(clip_pos, faces, (H, W))``.
        clip_pos: the clip-space positions that were rasterized (the gradient target); a
            batch of 1 is shared by all items.
        faces: int vertex indices of the triangles that were rasterized, shared by the
            batch (as in :func:`rasterize`; counter-clockwise = front facing, though
            silhouettes do not depend on the winding).
        topology: optional ``antialias_topology(faces)``, to skip rebuilding the edge
            adjacency (one sort of the 3F edges) on every call.
        memory_budget: bytes of temporaries per chunk of pixel pairs (as in
            :func:`rasterize`); results do not depend on it.

    Returns:
        The antialiased image, ``color``'s shape and dtype (float16 / bfloat16 are blended
        in float32).

    Shape:
        - color: :math:`(B, C, H, W)`.
        - frags.face_id: :math:`(B, H, W)`.
        - clip_pos: :math:`(B, V, 4)` or :math:`(1, V, 4)`.
        - faces: :math:`(F, 3)`.
        - topology: :math:`(F, 3)`.
        - Output: :math:`(B, C, H, W)`.

    Example:
        >>> from torchraster.raster import interpolate, rasterize
        >>> clip = torch.tensor([[[-0.5, -0.5, 0, 1], [0.5, -0.5, 0, 1], [0, 0.6, 0, 1]]],
        ...                     requires_grad=True)
        >>> faces = torch.tensor([[0, 1, 2]])
        >>> frags = rasterize(clip, faces, (8, 8))
        >>> rgb = interpolate(torch.eye(3), frags, faces)
        >>> rgba = antialias(torch.cat([rgb, frags.mask], 1), frags, clip, faces)
        >>> rgba[:, 3].unique().numel() > 2  # fractional coverage along the edges
        True
        >>> rgba[:, 3].sum().backward()  # e.g. a silhouette loss: gradients reach clip
        >>> bool(clip.grad.abs().sum() > 0)
        True
    """
    color, fid, clip_pos, faces, topology = _check_inputs(color, frags, clip_pos, faces,
                                                          topology)
    b, _, h, w = color.shape
    if clip_pos.dtype != torch.float64:
        clip_pos = clip_pos.float()
    per_chunk = max(256, int(memory_budget) // (_BYTES_PER_PAIR * clip_pos.element_size() // 4))
    depth: list[torch.Tensor] = []  # frags.depth, built only if two walks both hit

    def depth_at(pix: torch.Tensor) -> torch.Tensor:
        if not depth:
            depth.append(frags.depth.detach().reshape(-1))
        return depth[0].index_select(0, pix)

    records = []
    with torch.no_grad():
        ids = fid.reshape(-1)
        clip_t = clip_pos.detach().permute(2, 0, 1).reshape(4, -1)  # (4, B*V) rows
        firsts, axes = [], []
        for axis in (0, 1):  # 0: horizontal pairs (x, x + 1), 1: vertical (x, x + W)
            diff = torch.zeros((b, h, w), dtype=torch.bool, device=fid.device)
            if axis == 0:
                diff[:, :, :-1] = fid[:, :, 1:] != fid[:, :, :-1]
            else:
                diff[:, :-1] = fid[:, 1:] != fid[:, :-1]
            firsts.append(diff.view(-1).nonzero().squeeze(1))
            axes.append(torch.full_like(firsts[-1], axis))
            del diff
        first, axes = torch.cat(firsts), torch.cat(axes)  # both axes walk together
        for k0 in range(0, first.numel(), per_chunk):
            p, axis = first[k0:k0 + per_chunk], axes[k0:k0 + per_chunk]
            records.append(_pick_pairs(clip_t, clip_pos.shape, faces, topology, ids, depth_at,
                                       p, p + torch.where(axis == 0, 1, w), axis, (h, w)))
    if records:
        o, n, item, face, edge, axis, past_mid = (torch.cat(v)
                                                  for v in zip(*records, strict=True))
    else:
        o = n = item = face = edge = axis = torch.zeros(0, dtype=torch.int64,
                                                        device=fid.device)
        past_mid = torch.zeros(0, dtype=torch.bool, device=fid.device)
    t, share = _crossing(clip_pos, faces, o, n, item, face, edge, axis, (h, w))
    weight = torch.where(past_mid, t - 0.5, 0.5 - t).clamp_min(0) * share
    return _blend(color, torch.where(past_mid, n, o), torch.where(past_mid, o, n), weight)


def _blend(color: torch.Tensor, target: torch.Tensor, source: torch.Tensor,
           weight: torch.Tensor) -> torch.Tensor:
    """``out[x] = color[x] + sum_r w_r (color[src_r] - color[x]) / max(1, sum_r w_r)`` over
    the records ``r`` with target ``x`` (flat pixel indices b*H*W + i*W + j); only the
    targets are touched."""
    b, c, h, w = color.shape
    dtype = color.dtype
    col = color.to(compute_dtype(color)).reshape(b, c, h * w)
    out = col.clone()
    if target.numel():
        weight = weight.to(col.dtype)
        uniq, inv = torch.unique(target, return_inverse=True)

        def pixels(pix):
            item = floor_div_exact(pix, h * w)
            return item, pix - item * (h * w)

        (ti, tp), (si, sp), (ui, up) = pixels(target), pixels(source), pixels(uniq)
        delta = weight[:, None] * (col[si, :, sp] - col[ti, :, tp])  # (R, C)
        total = weight.new_zeros(uniq.shape).index_add(0, inv, weight)
        delta = delta.new_zeros((uniq.numel(), c)).index_add(0, inv, delta)
        out[ui, :, up] = col[ui, :, up] + delta / total.clamp_min(1.0)[:, None]
    return finish_low_precision(out.view(b, c, h, w), dtype)


def _check_inputs(color, frags, clip_pos, faces, topology):
    if not hasattr(frags, "face_id") or not hasattr(frags, "depth"):
        raise TypeError(f"frags: expected Fragments from rasterize, got {type(frags).__name__}")
    fid = frags.face_id
    check_tensor("color", color, ("B", "C", "H", "W"), floating=True)
    check_tensor("frags.face_id", fid, ("B", "H", "W"), integer=True)
    b, h, w = fid.shape
    if (color.shape[0], *color.shape[2:]) != (b, h, w):
        raise ValueError(f"frags: fragments of (B, H, W) = {(b, h, w)} do not match color "
                         f"{tuple(color.shape)} (B, C, H, W); rasterize at the colour's "
                         "resolution and batch size")
    check_tensor("clip_pos", clip_pos, (None, "V", 4), floating=True)
    check_tensor("faces", faces, ("F", 3), integer=True)
    if clip_pos.shape[0] not in (1, b):
        raise ValueError(f"clip_pos: batch size {clip_pos.shape[0]} does not match the "
                         f"fragments' batch size {b} (use 1 to share positions)")
    faces = faces.to(device=clip_pos.device, dtype=torch.int64)
    n_vert, n_faces = clip_pos.shape[1], faces.shape[0]
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= n_vert):
        raise ValueError(f"faces: vertex indices must be in [0, {n_vert}) for clip_pos with "
                         f"V={n_vert}; got range [{int(faces.min())}, {int(faces.max())}]")
    if fid.numel() and int(fid.max()) >= n_faces:
        raise ValueError(f"frags: face id {int(fid.max())} out of range for F={n_faces} faces "
                         "(were the fragments rasterized from these faces?)")
    if clip_pos.numel() and not all_finite(clip_pos):
        raise ValueError("clip_pos: contains NaN/Inf")
    if topology is None:
        topology = antialias_topology(faces)
    else:
        check_tensor("topology", topology, (n_faces, 3), integer=True)
        topology = topology.to(device=clip_pos.device, dtype=torch.int64)
    return color, fid.to(clip_pos.device), clip_pos, faces, topology


def _pixel_ndc(pix: torch.Tensor, resolution: tuple[int, int], dtype: torch.dtype):
    """NDC centre (x, y) of flat pixel indices b*H*W + i*W + j."""
    h, w = resolution
    rows_all = floor_div_exact(pix, w)  # b * H + i
    col, row = pix - rows_all * w, rows_all - floor_div_exact(rows_all, h) * h
    x = (2 * col + 1).to(dtype) * (1.0 / w) - 1.0
    y = 1.0 - (2 * row + 1).to(dtype) * (1.0 / h)
    return x, y


def _scaled(v: torch.Tensor) -> torch.Tensor:
    """Clip-space points (4, ...) divided by max |x, y, w| (a positive factor, without
    gradient: lines, crossings and every sign below are invariant to it), so that products
    neither under- nor overflow."""
    s = torch.maximum(torch.maximum(v[0].abs(), v[1].abs()), v[3].abs())
    return v / s.detach().clamp_min(torch.finfo(v.dtype).tiny)


def _sheared(v: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor):
    """(x - x0 w, y - y0 w, w) of scaled points (4, ...): the 2-D homogeneous frame whose
    origin is the NDC point (x0, y0) (a shear of determinant 1: lines and sides are
    preserved, and products of nearby points stay small and accurate)."""
    return v[0] - x0 * v[3], v[1] - y0 * v[3], v[3]


def _line(a, b):
    """The 2-D homogeneous line a x b through points a = (x, y, w), b: ``L . p = 0`` on
    it; (L0, L1) is its NDC normal and L2 its value at the frame's origin."""
    (xa, ya, wa), (xb, yb, wb) = a, b
    return ya * wb - wa * yb, wa * xb - xa * wb, xa * yb - ya * xb


def _crossing_t(line, dx: torch.Tensor, dy: torch.Tensor):
    """Fraction t along the segment from the frame's origin to (dx, dy) (NDC) where
    ``line`` crosses it, and the denominator (0: parallel, t then 0 and masked by the
    callers)."""
    par = line[0] * dx + line[1] * dy
    return -line[2] / torch.where(par == 0, torch.ones_like(par), par), par


def _dot(line, p) -> torch.Tensor:
    return line[0] * p[0] + line[1] * p[1] + line[2] * p[2]


def _step(o: torch.Tensor, n: torch.Tensor, axis: torch.Tensor,
          resolution: tuple[int, int], dtype: torch.dtype):
    """NDC offset (dx, dy) from the centre of pixel ``o`` to that of its neighbour ``n``:
    one column for axis 0, one row for axis 1 (rows grow downwards, NDC y upwards)."""
    h, w = resolution
    sign = torch.where(n > o, 1.0, -1.0).to(dtype)
    horizontal = axis == 0
    zero = torch.zeros_like(sign)
    return (torch.where(horizontal, sign * (2.0 / w), zero),
            torch.where(horizontal, zero, sign * (-2.0 / h)))


def _at(t: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """t[k[i], i] for a (3, N) per-edge or per-vertex tensor."""
    return t.gather(0, k[None]).squeeze(0)


#: How an edge is shared between horizontal and vertical pixel pairs: a pair across an
#: edge with pixel-unit normal (n_x, n_y) blends with the weight share |t - 1/2|, where the
#: share of horizontal pairs is n_x^p / (n_x^p + n_y^p) and that of vertical pairs the rest.
#: The shares sum to 1, so (in the mean over edge positions) every edge contributes its
#: exact coverage gradient for any p. p = inf is a hard switch at 45 degrees; edges of
#: finely tessellated silhouettes zig-zag around that switch, which biases it: the
#: translation moment (tests/test_antialias.py) of a 20k-face sphere at 64^2 is off by
#: -1.7 % with the switch, -1.0 % with p = 1, +-0.2 % with p = 2 and 4 (chosen: the
#: closest to the switch, whose coverage is exact for edges spanning a pixel).
ORIENTATION_POWER = 4

#: Faces a walk along one pixel segment may cross before it gives up (pixel segments cross a
#: few faces of meshes whose triangles are smaller than a pixel).
MAX_WALK = 16


def _scaled_xyw(v: torch.Tensor) -> torch.Tensor:
    """:func:`_scaled` of points given as (x, y, w) ``(3, ...)``."""
    return v / v.abs().amax(0).clamp_min(torch.finfo(v.dtype).tiny)


def _cross(a: torch.Tensor, b: torch.Tensor, nxt: torch.Tensor, prv: torch.Tensor
           ) -> torch.Tensor:
    """Cross products over dim 0 of stacked 2-D homogeneous points ``(3, ...)``: the
    lines through them, component for component the float operations of :func:`_line`.
    ``nxt``, ``prv``: the index tensors ``[1, 2, 0]`` and ``[2, 0, 1]`` (a roll by one,
    as a gather: ``roll`` concatenates two slices)."""
    return (a.index_select(0, nxt) * b.index_select(0, prv)
            - a.index_select(0, prv) * b.index_select(0, nxt))


def _dot3(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a . b`` over dim 0 of ``(3, ...)`` tensors, summed in :func:`_dot`'s order."""
    p = a * b
    return p[0] + p[1] + p[2]


def _walk(clip_t, faces, topology, vert_base, face, goal, o, n, axis, resolution):
    """No-grad: walk the segment from pixel ``o``'s centre to ``n``'s over the mesh,
    starting in ``face`` (visible at ``o``), across internal edges, up to the first
    silhouette edge.

    In each face the segment leaves through the one edge, other than its entry edge, that
    it crosses (the crossing point X = alpha a + beta b with alpha, beta >= 0: on the edge
    segment itself, in front of the eye, not just on its line). The walk stops at a
    silhouette edge (a boundary or non-manifold edge, or a fold: both faces on the same
    side of the edge as seen from the eye); without one when it enters ``goal`` (the face
    visible at ``n``: both pixels show one connected surface), when the crossing lies
    beyond ``n``'s centre, or after ``MAX_WALK`` faces. ``vert_base`` (N,): offset of each
    row's batch item in ``clip_t`` (4, B*V); ``axis`` (N,): 0 for horizontal pairs, 1 for
    vertical ones.

    Returns (hit, reached, face, edge, t, blend), each (N,): ``hit`` the segment reaches a
    silhouette edge, ``edge`` of ``face``, at fraction ``t``; ``reached`` the walk entered
    ``goal`` first; ``blend`` the hit is between the near and far planes and the edge is
    not parallel to the pair (``face``, ``edge``, ``t``, ``blend``: of the rows that hit).
    """
    dtype, device = clip_t.dtype, o.device
    count = o.numel()
    hit = torch.zeros(count, dtype=torch.bool, device=device)
    reached, blend = torch.zeros_like(hit), torch.zeros_like(hit)
    face, edge = face.clone(), torch.zeros_like(o)
    t_out = torch.zeros(count, dtype=dtype, device=device)
    x0, y0 = _pixel_ndc(o, resolution, dtype)
    dx, dy = _step(o, n, axis, resolution, dtype)
    # the walking rows, compacted as they finish: (x0, y0, 0, dx, dy) and (row, face,
    # vertex base, entry edge, goal); the entry edge is the one the walk came in through
    geo = torch.stack([x0, y0, torch.zeros_like(x0), dx, dy])
    state = torch.stack([torch.arange(count, device=device), face, vert_base,
                         torch.full_like(o, -1), goal])
    slots = torch.arange(3, device=device)[:, None]
    nxt, prv = torch.tensor([1, 2, 0], device=device), torch.tensor([2, 0, 1], device=device)
    xyw = clip_t.index_select(0, torch.tensor([0, 1, 3], device=device))  # z: not needed
    stops = []  # (row, face, edge) of each walk that reached a silhouette
    for _ in range(MAX_WALK):
        if state.shape[1] == 0:
            break
        rows, cur, base, entry, target = state
        corner = faces.index_select(0, cur).T  # (3, R)
        v = _scaled_xyw(xyw.index_select(1, (corner + base).reshape(-1)).view(3, 3, -1))
        a = v - geo[:3, None] * v[2]  # (3, 3, R): _sheared vertex k = start of edge k
        b = a.index_select(1, nxt)  # end of edge k
        line = _cross(a, b, nxt, prv)
        t, par = _crossing_t(line, geo[3], geo[4])
        x = torch.stack([t * geo[3], t * geo[4], torch.ones_like(t)])
        on = ((par != 0) & (t >= 0) & (_dot3(line, _cross(x, b, nxt, prv)) >= 0)  # alpha >= 0
              & (_dot3(line, _cross(a, x, nxt, prv)) >= 0) & (slots != entry))  # beta >= 0
        k = torch.where(on[0], 0, torch.where(on[1], 1, 2))  # the first crossed edge
        t = t.gather(0, k[None])[0]
        line = line.gather(1, k.expand(3, 1, -1))[:, 0]  # (3, R)
        slot = topology.view(-1).index_select(0, cur * 3 + k)  # 3 g + l across edge k
        nb_face = floor_div_exact(slot.clamp_min(0), 3)
        nb_edge = slot.clamp_min(0) - nb_face * 3
        nb_vert = faces.view(-1).index_select(0, nb_face * 3 + prv.index_select(0, nb_edge))
        nb = _scaled_xyw(xyw.index_select(1, nb_vert + base))
        nb = nb - geo[:3] * nb[2]
        opposite = a.gather(1, prv.index_select(0, k).expand(3, 1, -1))[:, 0]
        silhouette = (slot < 0) | (torch.sign(_dot3(line, nb))
                                   * torch.sign(_dot3(line, opposite)) > 0)
        crossed = on.any(0) & (t <= 1)  # before reaching n's centre
        stop = crossed & silhouette
        go = crossed & ~silhouette
        arrive = go & (nb_face == target)
        stops.append(torch.stack([rows, cur, k])[:, stop])
        reached.index_fill_(0, rows[arrive], True)
        keep = (go & ~arrive).nonzero().squeeze(1)
        state = torch.stack([rows, nb_face, base, nb_edge, target]).index_select(1, keep)
        geo = geo.index_select(1, keep)
    done, at, ki = torch.cat(stops, 1) if stops else torch.zeros(3, 0, dtype=o.dtype,
                                                                 device=device)
    if done.numel():  # the hits again, edge k only: t, the crossing and the depth range
        x0, y0, dx, dy = (c.index_select(0, done) for c in (x0, y0, dx, dy))
        corner = faces.index_select(0, at)  # (H, 3)
        ends = corner.gather(1, torch.stack([ki, (ki + 1) % 3], 1)).T  # (2, H)
        base = vert_base.index_select(0, done)
        v = _scaled(clip_t.index_select(1, (ends + base).reshape(-1)).view(4, 2, -1))
        a, b = _sheared(v[:, 0], x0, y0), _sheared(v[:, 1], x0, y0)
        line = _line(a, b)
        t, _ = _crossing_t(line, dx, dy)
        xx, xy = t * dx, t * dy
        al = _dot(line, _line((xx, xy, 1.0), b))
        be = _dot(line, _line(a, (xx, xy, 1.0)))
        (za, zb), (wa, wb) = v[2], v[3]
        near_ok = al * (za + wa) + be * (zb + wb) >= 0
        far_ok = al * (wa - za) + be * (wb - zb) >= 0
        nx, ny, _ = _line((v[0, 0], v[1, 0], wa), (v[0, 1], v[1, 1], wb))
        hit[done] = True
        face[done] = at
        edge[done] = ki
        t_out[done] = t
        across = torch.where(axis.index_select(0, done) == 0, nx != 0, ny != 0)  # not parallel
        blend[done] = near_ok & far_ok & across
    return hit, reached, face, edge, t_out, blend


def _internal(clip_t, faces, topology, vert_base, fp, fq):
    """(N,) bool: faces ``fp`` and ``fq`` share an edge that is not a fold (their other
    vertices lie on opposite sides of it, seen from the eye)."""
    slots = topology.index_select(0, fp.clamp_min(0))  # (N, 3)
    # edge k of fp is shared with fq when its slot across is 3 fq + l, l in {0, 1, 2}
    rel = slots - 3 * fq[:, None]
    across = (slots >= 0) & (rel >= 0) & (rel < 3)
    shared = across.any(1) & (fp >= 0)
    idx = shared.nonzero().squeeze(1)
    if idx.numel() == 0:
        return shared
    across, rel = across.index_select(0, idx), rel.index_select(0, idx)
    k = torch.where(across[:, 0], 0, torch.where(across[:, 1], 1, 2))
    corner = faces.index_select(0, fp.index_select(0, idx)).T  # (3, n)
    edge_q = rel.gather(1, k[:, None]).squeeze(1)  # the edge's index in fq
    other = faces.view(-1).index_select(0, 3 * fq.index_select(0, idx) + (edge_q + 2) % 3)
    base = vert_base.index_select(0, idx)
    ids = torch.stack([_at(corner, k), _at(corner, (k + 1) % 3), _at(corner, (k + 2) % 3),
                       other]) + base
    x, y, _, w = _scaled(clip_t.index_select(1, ids.reshape(-1)).view(4, 4, -1))
    line = _line((x[0], y[0], w[0]), (x[1], y[1], w[1]))
    sides = torch.sign(_dot(line, (x[2], y[2], w[2]))) * torch.sign(_dot(line, (x[3], y[3], w[3])))
    shared[idx] = sides < 0
    return shared


def _pick_pairs(clip_t, clip_shape, faces, topology, fid, depth_at, p, q, axis, resolution):
    """No-grad, one chunk of pairs (p, q) with different face ids: the blending records
    (o, n, item, face, edge, axis, past_mid) of the occluder of each pair (past_mid:
    the crossing is nearer to n's centre).

    Pairs whose faces share an edge that is not a fold are internal (most pairs of a mesh
    whose triangles are a few pixels wide) and skip the walks. The walk from q's face counts
    only where the walk from p's face did not reach q's face over internal edges (then
    both pixels show one connected surface and nothing blends)."""
    h, w = resolution
    item = floor_div_exact(p, h * w)
    vert_base = (item if clip_shape[0] > 1 else torch.zeros_like(item)) * clip_shape[1]
    fp, fq = fid.index_select(0, p), fid.index_select(0, q)
    m = p.numel()
    hit = torch.zeros(2 * m, dtype=torch.bool, device=p.device)
    blend = torch.zeros_like(hit)
    face, edge = torch.cat([fp, fq]), torch.zeros(2 * m, dtype=torch.int64, device=p.device)
    t = torch.zeros(2 * m, dtype=clip_t.dtype, device=p.device)
    # rows [0, m): walks from p towards q; rows [m, 2m): from q towards p
    o, n, goal = torch.cat([p, q]), torch.cat([q, p]), torch.cat([fq, fp])
    internal = _internal(clip_t, faces, topology, vert_base, fp, fq)
    # both sides walk at once (the walks are independent: one loop of steps instead of
    # two); a walk from q counts only where the walk from p did not reach q's face
    todo = (torch.cat([fp, fq]) >= 0) & ~torch.cat([internal, internal])
    todo = todo.nonzero().squeeze(1)
    if todo.numel():
        pair = todo - m * (todo >= m)
        r = _walk(clip_t, faces, topology, vert_base.index_select(0, pair),
                  face.index_select(0, todo), goal.index_select(0, todo),
                  o.index_select(0, todo), n.index_select(0, todo),
                  axis.index_select(0, pair), resolution)
        hit[todo], arrived, face[todo], edge[todo], t[todo], blend[todo] = r
        reached = torch.zeros(2 * m, dtype=torch.bool, device=p.device)
        reached[todo] = arrived
        hit[m:] &= ~reached[:m]
    hp, hq = hit[:m], hit[m:]
    use_p = hp & ~hq
    both = (hp & hq).nonzero().squeeze(1)
    if both.numel():  # two silhouettes: the nearer face's (its depth at its own pixel)
        use_p[both] = depth_at(p[both]) <= depth_at(q[both])
    use_q = hq & ~use_p
    sel = (torch.cat([use_p, use_q]) & blend).nonzero().squeeze(1)
    return (o[sel], n[sel], torch.cat([item, item])[sel], face[sel], edge[sel],
            torch.cat([axis, axis])[sel],
            t[sel] > 0.5)


def _crossing(clip_pos, faces, o, n, item, face, edge, axis, resolution):
    """Differentiable crossing fraction t (N,) of the chosen edges, from ``o`` to ``n`` (the
    same float operations as in :func:`_walk`, so the same values), and the pair axis's
    share (N,) of the edge (see :data:`ORIENTATION_POWER`)."""
    h, w = resolution
    if clip_pos.shape[0] == 1:
        item = torch.zeros_like(item)
    dtype = clip_pos.dtype
    x0, y0 = _pixel_ndc(o, resolution, dtype)
    dx, dy = _step(o, n, axis, resolution, dtype)
    corner = faces.index_select(0, face)
    ends = [_sheared(_scaled(clip_pos[item, corner.gather(1, k[:, None]).squeeze(1)].T),
                     x0, y0) for k in (edge, (edge + 1) % 3)]
    line = _line(*ends)
    t, _ = _crossing_t(line, dx, dy)
    # the normal in pixel units is (2 L0 / W, -2 L1 / H)
    nx, ny = (line[0] * (1.0 / w)).abs(), (line[1] * (1.0 / h)).abs()
    big = torch.maximum(nx, ny)
    big = torch.where(big == 0, torch.ones_like(big), big)  # 0 only for degenerate lines
    px, py = (nx / big) ** ORIENTATION_POWER, (ny / big) ** ORIENTATION_POWER
    total = px + py  # >= 1 unless degenerate
    share = torch.where(axis == 0, px, py) / torch.where(total == 0, torch.ones_like(total),
                                                         total)
    return t.clamp(0.0, 1.0), share
