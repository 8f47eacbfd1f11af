"""Linearly transformed cosines (LTC) for polygonal area lights, fitted to this renderer's
GGX specular lobe (Heitz, Dupuy, Hill and Neubelt 2016, "Real-time polygonal-light shading
with linearly transformed cosines", ACM TOG 35(4)).

An LTC is the clamped cosine ``D_o(w) = max(w.z, 0) / pi`` pushed through a 3x3 matrix M:
``D(w) = D_o(M^-1 w / |M^-1 w|) |det M^-1| / |M^-1 w|^3`` (Heitz et al. 2016, eq. 1). Its
integral over a polygon P is the cosine integral over the polygon ``M^-1 P``, which has a
closed form (:func:`polygon_form_factor`), so a polygonal light costs one edge term per
vertex. The specular of a light of uniform radiance L is
``L * ltc_integral(p, ltc_inverse(r, n.v)) * (f0 A + B)``, with (A, B) the split-sum DFG
terms of :func:`torchraster.shading.ibl.dfg_lut`: the LTC carries the lobe's shape
(normalised to integrate to 1), ``A + B`` its integral over the hemisphere.

The fitted lobe (``scripts/fit_ltc.py``) is the specular of
:func:`~torchraster.shading.lighting.cook_torrance_lights` without Fresnel,
``rho(l) = D(h) V(l, v) (n.l)``: GGX D with ``alpha = r^2``,
perceptual roughness r clamped to ``[MIN_ROUGHNESS, 1]``, height-correlated Smith V with
n.v and n.l floored at ``MIN_COS``.

Local frame (:func:`local_frame`): rows (t1, t2, n), n = +z, the view direction in the xz
plane with x >= 0, ``v = (sin theta_v, 0, cos theta_v)``.

Table (``assets/ltc/ggx_ltc.npy``, float32, shape ``(4, R, C)``, R = C = 32): channel k
holds entry k of ``(a, b, c, d)`` of the inverse matrix

    M^-1 = [[a, 0, b],
            [0, c, 0],
            [d, 0, 1]]

(normalised so that its bottom-right entry is 1; an LTC does not change when M is
scaled); row i is perceptual roughness ``r = (s0 + (1 - s0) i / (R - 1))^2`` with
``s0 = sqrt(MIN_ROUGHNESS)`` (:func:`table_roughness`: uniform in sqrt(r), from
MIN_ROUGHNESS to 1: rows 0.011 apart at MIN_ROUGHNESS, ~3x denser than uniform steps of
r, between which a narrow lobe moved by more than its width), column j is
``u = j / (C - 1)`` with ``n.v = 1 - u^2`` (Heitz's ``sqrt(1 - cos theta_v)`` axis: denser
towards grazing angles). Nodes at both ends; looked up bilinearly.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import torch

from torchraster.numerics import compute_dtype, finish_low_precision
from torchraster.shading.brdf import MIN_ROUGHNESS

#: The fitted table; written by ``scripts/fit_ltc.py``.
TABLE_PATH: Path = Path(__file__).resolve().parent.parent / "assets" / "ltc" / "ggx_ltc.npy"

#: Below this, the column axis ``u = sqrt(1 - n.v)`` continues linearly (``u = s /
#: sqrt(SQRT_LINEAR)``, s = 1 - n.v, continuous at the switch): u(0) = 0 exactly and the
#: gradient with respect to n.v stays finite (at most ``0.5 / sqrt(SQRT_LINEAR)`` per unit
#: of u) at normal incidence; u moves by at most ``sqrt(SQRT_LINEAR) / 4`` (0.8 % of a cell).
SQRT_LINEAR: float = 1e-6


def table_roughness(rows: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Perceptual roughness of the table's rows ``(rows,)``: uniform in sqrt(r) from
    MIN_ROUGHNESS to 1 (the inverse of :func:`roughness_rows`).

    Example:
        >>> [round(r, 4) for r in table_roughness(4).tolist()]
        [0.045, 0.2254, 0.5437, 1.0]
    """
    s0 = math.sqrt(MIN_ROUGHNESS)
    return (s0 + (1.0 - s0) * torch.linspace(0.0, 1.0, rows, dtype=dtype)) ** 2


def roughness_rows(roughness: torch.Tensor, rows: int) -> torch.Tensor:
    """Fractional row ``(...)`` of perceptual roughness ``roughness`` ``(...)`` (clamped to
    [MIN_ROUGHNESS, 1]) in a table of ``rows`` rows (:func:`table_roughness`)."""
    s0 = math.sqrt(MIN_ROUGHNESS)
    s = roughness.clamp(MIN_ROUGHNESS, 1.0).sqrt()
    return (s - s0) * ((rows - 1) / (1.0 - s0))


@functools.cache
def _load_table(path: Path, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    if not path.is_file():
        raise FileNotFoundError(
            f"LTC table {path} is missing: run `python scripts/fit_ltc.py` to fit it"
        )
    table = np.load(path)
    if table.ndim != 3 or table.shape[0] != 4 or min(table.shape[1:]) < 2:
        raise ValueError(f"LTC table {path}: expected shape (4, R, C), got {table.shape}")
    return torch.from_numpy(table).to(device=device, dtype=dtype)


def ltc_table(
    device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """The fitted table ``(4, R, C)``: entries (a, b, c, d) of M^-1 per (roughness, u)
    node (layout in the module docstring). Loaded once per device and dtype and cached:
    do not modify it in place.

    Example:
        >>> ltc_table().shape
        torch.Size([4, 32, 32])
    """
    return _load_table(TABLE_PATH, torch.device(device or "cpu"), dtype)


def ltc_coefficients(roughness: torch.Tensor, n_dot_v: torch.Tensor) -> torch.Tensor:
    """The entries ``(a, b, c, d)`` of the fitted M^-1 (see :func:`ltc_inverse`), bilinear
    in the table, differentiable with respect to both inputs.

    Args:
        roughness: perceptual roughness, clamped to [MIN_ROUGHNESS, 1] (the shading's
            own clamp), any shape broadcastable with ``n_dot_v``.
        n_dot_v: cosine of the view angle, clamped to [0, 1].

    Returns:
        ``(4, ...)``, ``...`` the broadcast shape of the inputs, in their compute dtype
        (float16 / bfloat16 inputs: float32).
    """
    dt = compute_dtype(roughness, n_dot_v)
    r, nv = torch.broadcast_tensors(roughness.to(dt), n_dot_v.to(dt))
    table = ltc_table(r.device, dt)
    rows, cols = table.shape[1:]
    x = roughness_rows(r, rows)
    s = 1.0 - nv.clamp(0.0, 1.0)
    big = s > SQRT_LINEAR
    u = torch.where(big, torch.sqrt(torch.where(big, s, 1.0)), s / math.sqrt(SQRT_LINEAR))
    y = u * (cols - 1)
    i = x.detach().floor().clamp(0, rows - 2).long()
    j = y.detach().floor().clamp(0, cols - 2).long()
    fx, fy = x - i, y - j  # weights carry the gradients
    flat = table.reshape(4, -1)
    first = (i * cols + j).reshape(-1)

    def node(offset: int) -> torch.Tensor:  # the four entries at node (i, j) + offset
        return flat.index_select(1, first + offset).view(4, *i.shape)

    return ((node(0) * (1 - fy) + node(1) * fy) * (1 - fx)
            + (node(cols) * (1 - fy) + node(cols + 1) * fy) * fx)


def ltc_inverse(roughness: torch.Tensor, n_dot_v: torch.Tensor) -> torch.Tensor:
    """The fitted inverse LTC matrix M^-1 in the local frame (n = z, v in the xz plane),
    bilinear in the table, differentiable with respect to both inputs.

    Args:
        roughness, n_dot_v: as in :func:`ltc_coefficients`.

    Returns:
        ``(..., 3, 3)`` M^-1 = ``[[a, 0, b], [0, c, 0], [d, 0, 1]]``, ``...`` the broadcast
        shape of the inputs, in their promoted dtype (float16 / bfloat16: looked up in
        float32 and cast back).

    Example:
        >>> m = ltc_inverse(torch.tensor([0.5]), torch.tensor([1.0]))
        >>> m.shape, round(m[0, 1, 0].item(), 6), m[0, 2, 2].item()
        (torch.Size([1, 3, 3]), 0.0, 1.0)
    """
    out = torch.promote_types(roughness.dtype, n_dot_v.dtype)
    a, b, c, d = ltc_coefficients(roughness, n_dot_v).unbind(0)
    zero, one = torch.zeros_like(a), torch.ones_like(a)
    m_inv = torch.stack((a, zero, b, zero, c, zero, d, zero, one), -1)
    return finish_low_precision(m_inv.unflatten(-1, (3, 3)), out)


def _unit(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor
          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The components of ``(x, y, z) / |(x, y, z)|``, 0 (zero gradient) for vectors whose
    squared length underflows (scale-free, unlike the default threshold of
    ``safe_normalize``)."""
    n2 = x * x + y * y + z * z
    ok = n2 > torch.finfo(n2.dtype).tiny
    inv = torch.rsqrt(torch.where(ok, n2, torch.ones_like(n2))) * ok
    return x * inv, y * inv, z * inv


def _edge_integral(a: tuple[torch.Tensor, ...], b: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """``theta * normalize(b x a).z`` for the edges from the unit vectors ``a`` to ``b``
    (each a tuple of the x, y, z component tensors; 0 vectors allowed), theta the angle
    between them: one term of the vector form factor (Lambert; Baum, Rushmeier and Winget
    1989, eq. 7; Arvo 1995). ``theta / sin(theta) = atan2(|b x a|, a.b) / |b x a|``
    (accurate at every angle; the full cross product keeps short, distant edges exact)
    with its limits where ``|b x a|`` vanishes: 1 for a degenerate edge (a = b: the term
    is exactly 0) and 0 when the shading point lies on the edge (a = -b) or a vertex
    (a = 0)."""
    ax, ay, az = a
    bx, by, bz = b
    cx, cy, cz = by * az - bz * ay, bz * ax - bx * az, bx * ay - by * ax
    sin2 = cx * cx + cy * cy + cz * cz
    cos = ax * bx + ay * by + az * bz
    ok = sin2 > torch.finfo(sin2.dtype).eps ** 2
    sin = torch.sqrt(torch.where(ok, sin2, torch.ones_like(sin2)))
    theta_over_sin = torch.where(ok, torch.atan2(sin, cos) / sin, (cos > 0).to(cos.dtype))
    return theta_over_sin * cz


def form_factor_components(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, dim: int = -1
                           ) -> torch.Tensor:
    """:func:`polygon_form_factor` of polygons given as component tensors: ``x``, ``y``,
    ``z`` of one shape, the K vertices along ``dim`` (every op then runs on long contiguous
    rows, e.g. ``(K, N)`` for N polygons with ``dim=0``). Returns that shape without
    ``dim``, in the inputs' dtype (compute in float32 or wider). Only the polygons that
    cross the horizon are clipped (gathered, then put back)."""
    a = _unit(x, y, z)  # each vertex as a direction, once
    b = tuple(t.roll(-1, dims=dim) for t in a)  # edge i runs from vertex i to vertex i + 1
    above_a = a[2] >= 0
    whole = torch.where(above_a, _edge_integral(a, b), 0.0).sum(dim) * (0.5 / math.pi)
    crossing = (above_a != (b[2] >= 0)).any(dim)
    if not bool(crossing.any()):  # no polygon crosses the horizon: nothing to clip
        return whole
    shape = whole.shape
    idx = crossing.reshape(-1).nonzero().squeeze(1)

    def take(t: torch.Tensor) -> torch.Tensor:  # (K, n) columns of the crossing polygons
        return t.movedim(dim, 0).reshape(t.shape[dim], -1).index_select(1, idx)

    clipped = _clipped(tuple(take(t) for t in a), tuple(take(t) for t in b))
    return whole.reshape(-1).index_copy(0, idx, clipped).view(shape)


def _clipped(a: tuple[torch.Tensor, ...], b: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """The form factor ``(n,)`` of polygons crossing the horizon: unit vertices ``a`` and
    their successors ``b`` (components, each ``(K, n)``)."""
    above_a, above_b = a[2] >= 0, b[2] >= 0
    crosses = above_a != above_b
    # where an edge crosses the horizon z = 0: the same direction on the chord between the
    # unit vectors as on the edge itself (both lie in the plane of the edge and the origin)
    t = a[2] / torch.where(crosses, a[2] - b[2], torch.ones_like(a[2])) * crosses
    h = _unit(a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), torch.zeros_like(a[2]))
    start = tuple(torch.where(above_a, p, q) for p, q in zip(a, h, strict=True))
    end = tuple(torch.where(above_b, p, q) for p, q in zip(b, h, strict=True))
    edges = torch.where(above_a | above_b, _edge_integral(start, end), 0.0).sum(0)
    # a convex polygon crosses the horizon at most once each way: the masked sums pick
    # the exit and entry points
    leaving, entering = above_a & ~above_b, ~above_a & above_b
    exit_point = tuple((q * leaving).sum(0) for q in h)
    entry_point = tuple((q * entering).sum(0) for q in h)
    return (edges + _edge_integral(exit_point, entry_point)) * (0.5 / math.pi)


def polygon_form_factor(p: torch.Tensor) -> torch.Tensor:
    """Cosine-weighted solid angle of a convex polygon above the horizon, over pi.

    ``F = integral over {w in P, w.z >= 0} of w.z dw / pi``, exact: the polygon is
    clipped to the horizon z = 0 (the clamped parts of its edges plus one edge along the
    horizon from the exit to the entry point; fixed shapes, per-edge masks) and the
    clipped polygon's integral is the edge sum ``1 / (2 pi) sum_i theta_i
    normalize(p_{i+1} x p_i).z`` (Lambert's formula; Baum, Rushmeier and Winget 1989,
    "Improving radiosity solutions through the use of analytically determined
    form-factors", eq. 7). A polygon covering the whole upper hemisphere gives 1.
    :func:`form_factor_components` is the same on component tensors.

    Sign: F > 0 when the vertices run counter-clockwise as seen from the shading point
    (the origin), i.e. when the polygon's right-hand normal
    ``(p1 - p0) x (p2 - p1)`` points towards the origin (the light's front face is
    seen); reversing the vertex order negates F. A one-sided light uses ``max(F, 0)``, a
    two-sided one ``|F|``.

    Vertices may repeat (a degenerate edge contributes exactly 0: pad polygons to a common
    K by repeating a vertex); a polygon entirely below the horizon gives exactly 0; a
    shading point in the polygon's plane, on an edge or on a vertex gives finite values
    and gradients.

    Args:
        p: ``(..., K, 3)`` vertices, K >= 3, relative to the shading point in a frame whose
            z axis is the surface normal (not normalised; any scale).

    Returns:
        ``(...)`` F, dimensionless, in [-1, 1].

    Example:
        >>> square = torch.tensor([[1.0, 1, 1], [-1, 1, 1], [-1, -1, 1], [1, -1, 1]])
        >>> round(polygon_form_factor(square.flip(0)).item(), 4)  # seen counter-clockwise
        0.5541
        >>> round(polygon_form_factor(square).item(), 4)  # its back face
        -0.5541
    """
    q = p.to(compute_dtype(p))
    return finish_low_precision(form_factor_components(q[..., 0], q[..., 1], q[..., 2]),
                                p.dtype)


def ltc_integral(p: torch.Tensor, m_inv: torch.Tensor) -> torch.Tensor:
    """Integral of the LTC ``M`` over a polygon: the cosine integral over the transformed
    polygon ``M^-1 p`` (Heitz et al. 2016, section 3.3; the edge formula normalises, so
    the vertices need not be). Same sign convention as :func:`polygon_form_factor` (M^-1
    from :func:`ltc_inverse` has a positive determinant, so it keeps the orientation).

    Args:
        p: ``(..., K, 3)`` vertices relative to the shading point in the local frame of
            :func:`local_frame`.
        m_inv: ``(..., 3, 3)`` M^-1 (:func:`ltc_inverse`), broadcastable with ``p``'s
            leading dims.

    Returns:
        ``(...)`` the LTC's integral over the polygon (its normalised shading integral:
        multiply by the lobe's norm, ``f0 A + B``).

    Example:
        >>> square = torch.tensor([[1.0, 1, 1], [1, -1, 1], [-1, -1, 1], [-1, 1, 1]])
        >>> round(ltc_integral(square, torch.eye(3)).item(), 4)  # M = I: the cosine lobe
        0.5541
    """
    dt = compute_dtype(p, m_inv)
    q = p.to(dt) @ m_inv.to(dt).transpose(-1, -2)  # rows: M^-1 p_k
    return finish_low_precision(polygon_form_factor(q), torch.promote_types(p.dtype, m_inv.dtype))


def _any_tangent(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A unit vector orthogonal to the unit vector ``(x, y, z)`` (component tensors),
    branch-free and smooth away from z = 0 (Duff, Burgess, Christensen, Hery, Kensler,
    Liani and Villemin 2017, "Building an orthonormal basis, revisited", listing 3)."""
    sign = torch.where(z >= 0, 1.0, -1.0).to(z.dtype)
    k = -1.0 / (sign + z)
    return 1.0 + sign * x * x * k, sign * x * y * k, -sign * x


def frame_rows(n: tuple[torch.Tensor, ...], v: tuple[torch.Tensor, ...]
               ) -> tuple[tuple[torch.Tensor, ...], ...]:
    """:func:`local_frame` on component tensors: ``n``, ``v`` the (x, y, z) components
    (broadcastable tensors); returns the rows ``(t1, t2, n)``, each a tuple of its x, y, z
    components."""
    nx, ny, nz = _unit(*n)
    vx, vy, vz = v
    nv = nx * vx + ny * vy + nz * vz
    w = (vx - nx * nv, vy - ny * nv, vz - nz * nv)
    nw = nx * w[0] + ny * w[1] + nz * w[2]
    w = (w[0] - nx * nw, w[1] - ny * nw, w[2] - nz * nw)  # twice: orthogonal to rounding
    sq = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    fi = torch.finfo(sq.dtype)  # |w| < sqrt(eps) |v|: v within ~3e-4 rad (float32) of n
    ok = sq > ((vx * vx + vy * vy + vz * vz) * fi.eps).clamp_min(fi.tiny)
    inv = torch.rsqrt(torch.where(ok, sq, torch.ones_like(sq)))
    t1 = tuple(torch.where(ok, c * inv, t) for c, t in zip(w, _any_tangent(nx, ny, nz),
                                                            strict=True))
    t2 = (ny * t1[2] - nz * t1[1], nz * t1[0] - nx * t1[2], nx * t1[1] - ny * t1[0])
    return t1, t2, (nx, ny, nz)


def local_frame(n: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """The shading frame of the LTC: rows (t1, t2, n), ``t1 = normalize(v - n (n.v))``,
    ``t2 = n x t1`` (right-handed: a rotation, so polygon orientations are kept), so that
    ``p_local = frame @ p_world`` puts the normal on +z and v in the xz plane with x >= 0.
    When v is parallel to n, t1 is any tangent (the lobe is then rotationally symmetric);
    values and gradients stay finite. :func:`frame_rows` is the same on components.

    Args:
        n: ``(..., 3)`` surface normal (normalised here; a zero normal gives a singular,
            finite frame).
        v: ``(..., 3)`` direction to the eye (any length), broadcastable with ``n``.

    Returns:
        ``(..., 3, 3)`` rotation, the broadcast shape of the inputs.

    Example:
        >>> f = local_frame(torch.tensor([0.0, 1.0, 0.0]), torch.tensor([0.0, 1.0, 1.0]))
        >>> (f @ torch.tensor([0.0, 1.0, 1.0])).tolist()
        [1.0, 0.0, 1.0]
    """
    dt = compute_dtype(n, v)
    n, v = torch.broadcast_tensors(n.to(dt), v.to(dt))
    rows = frame_rows(n.unbind(-1), v.unbind(-1))
    return torch.stack([torch.stack(row, -1) for row in rows], -2)
