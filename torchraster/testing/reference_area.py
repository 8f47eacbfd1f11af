"""Independent float64 brute-force reference for rectangle and disc area lights.

Shares no code with the engine (imports only :mod:`torchraster.testing.raytrace` for shadow
rays and :mod:`torchraster.testing.reference_brdf` for GGX / Smith): the outgoing radiance
of the single-scattering Cook-Torrance BRDF lit by one area light of constant radiance
``Le`` is integrated over the light's surface ``A``::

    L_o(x) = int_A f(l) Le vis(x, y) max(n.l, 0) |n_L.l| / |y - x|^2 dA(y),
    l = (y - x) / |y - x|,
    f(l) = kd / pi + D(n.h) V(n.v, n.l) F(v.h),   h = normalize(l + v),

with ``kd = (1 - metallic) albedo``, ``f0 = 0.04 (1 - metallic) + albedo metallic``, GGX
``D`` (:func:`~torchraster.testing.reference_brdf.walter_ggx`), height-correlated Smith
``V = G2 / (4 n.l n.v)`` (:func:`~torchraster.testing.reference_brdf.heitz_v`), Schlick
``F = f0 + (1 - f0)(1 - v.h)^5``, ``alpha = clamp(roughness, 0.045, 1)^2``; ``n.v`` is
floored at :data:`MIN_COS` (a view at or below the horizon). A plain Lambert diffuse term
(no ``1 - F`` factor), no multiple-scattering compensation.

Light convention (that of the engine's ``AreaLights``): centre ``position``, half-extent
vectors ``u``, ``v``; a rectangle (parallelogram) is ``position + s u + t v``,
``s, t in [-1, 1]`` (area ``4 |u x v|``), a disc (ellipse) the same with ``s^2 + t^2 <= 1``
(area ``pi |u x v|``). The emitting normal is ``n_L = normalize(u x v)``; a one-sided light
lights ``x`` from ``y`` only when ``(x - y).n_L > 0``, a two-sided one from both sides.

Quadrature: a midpoint rule on a ``k x k`` grid of ``(s, t)`` cells, ``k =
ceil(sqrt(samples))``, the same nodes for every receiver, each node weighted by its cell's
exact area ``area / k^2``. A rectangle's nodes are the cell centres; a disc maps the grid
through Shirley & Chiu's equal-area concentric map and puts each node at the area centroid
of its cell's image (the mean of the map over an 8 x 8 sub-grid: the image of the cell
centre is off the centroid by O(h^2) where the map bends, near the disc's centre and its
diagonals; measured 10x less accurate for a highlight at the disc's centre, 1-2x elsewhere).
The error falls as ``1 / k^2 = 1 / samples`` for a smooth integrand; a discontinuity inside
the light (a shadow edge, the receiver's horizon or the one-sided plane crossing the light)
adds an O(1 / k) error. Measured on a glossy metal (a 1 m x 1 m light, or the disc inscribed
in it, 1.5 m above a plane of 36 receivers seen from an eye 3.6 m away, the light
subtending ~30 degrees; max relative error of the receivers brighter than 10 % of the
brightest, against ``k = 512``; the worst receivers see the highlight at the light's
edge)::

    k (samples = k^2)       r = 0.1   r = 0.15  r = 0.2   r = 0.3   r = 0.5
    16   rectangle          2.4e-1    8.2e-3    2.3e-2    2.9e-3    9.2e-4
         disc               1.3e-1    3.3e-3    3.1e-2    5.1e-3    9.5e-4
    32   rectangle          1.7e-2    1.6e-4    5.7e-3    7.1e-4    2.3e-4
         disc               1.1e-2    1.3e-3    7.8e-3    1.3e-3    2.4e-4
    64   rectangle          5.1e-5    3.8e-5    1.4e-3    1.8e-4    5.7e-5
         disc               1.4e-3    4.3e-4    1.9e-3    3.1e-4    5.9e-5
    80   rectangle                              8.9e-4    1.1e-4
         disc                                   1.2e-3    2.0e-4
    128  rectangle          2.1e-6    9.0e-6    3.3e-4    4.2e-5    1.3e-5
         disc               5.0e-4    1.1e-4    4.6e-4    7.4e-5    1.4e-5

(below r = 0.2 only 3 receivers catch the highlight, hence the erratic columns). A rule of
thumb from these: relative error ~ ``0.03 (theta / alpha)^2`` with ``theta`` the angle a
cell subtends (the light's angular size / k) and ``alpha = roughness^2`` the lobe width.
The default :data:`SAMPLES` (``80^2``) is accurate to ~1e-3 at roughness >= 0.2 for
lights up to ~30 degrees across (larger lights: scale k with the angle). Near-specular
highlights (roughness < ~0.15) of small lights need many more samples: the lobe narrows
as ``alpha = roughness^2`` and must span several cells. Cost: ~0.3 us per point-sample
unshadowed (one thread), i.e. ~2 ms per receiver at the default.

Shadow rays (``casters``) go from ``x + eps n`` to each sample ``y`` with ``t`` up to the
distance minus ``eps`` (so a light included among the casters does not shadow itself),
through :func:`~torchraster.testing.raytrace.occluded`; only samples that contribute are
traced. Work is done ``max_rays`` point-samples at a time.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from torchraster.testing.raytrace import RAY_EPSILON, occluded, ray_origins
from torchraster.testing.reference_brdf import heitz_v, walter_ggx

F64 = torch.float64

#: Default light samples per receiver point (an 80 x 80 grid).
SAMPLES: int = 80 * 80
#: Sub-grid per cell side used to place a disc's nodes at the cells' area centroids.
DISC_SUBGRID: int = 8
#: Floor of ``n.v`` (a view direction at or below the surface's horizon).
MIN_COS: float = 1e-4
#: Floor and ceiling of the perceptual roughness.
MIN_ROUGHNESS: float = 0.045

Vec = torch.Tensor | Sequence[float]


def _vec(x: Vec, device: torch.device | None = None) -> torch.Tensor:
    return torch.as_tensor(x, dtype=F64, device=device).reshape(3)


def light_area(u: Vec, v: Vec, disc: bool = False) -> float:
    """Area of a light with half-extents ``u``, ``v`` ``(3,)``: ``4 |u x v|`` (rectangle)
    or ``pi |u x v|`` (disc)."""
    cross = torch.linalg.cross(_vec(u), _vec(v)).norm().item()
    return (math.pi if disc else 4.0) * cross


def _concentric(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Shirley & Chiu's equal-area concentric map of ``[-1, 1]^2`` onto the unit disc (its
    Jacobian is the constant pi / 4): points ``(..., 2)`` for coordinates ``a``, ``b``."""
    first = a.abs() > b.abs()
    r = torch.where(first, a, b)
    safe_a = torch.where(a == 0, torch.ones_like(a), a)
    safe_b = torch.where(b == 0, torch.ones_like(b), b)
    phi = torch.where(first, (math.pi / 4) * b / safe_a, math.pi / 2 - (math.pi / 4) * a / safe_b)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi)], -1)


def _disc_nodes(k: int, device: torch.device | None = None, sub: int = DISC_SUBGRID
                ) -> torch.Tensor:
    """``(k^2, 2)`` area centroids of the images of a ``k x k`` grid of ``[-1, 1]^2`` under
    :func:`_concentric` (each cell's image has the area ``pi / k^2``): the mean of the map
    over a ``sub x sub`` midpoint sub-grid of the cell."""
    c = (torch.arange(k, dtype=F64, device=device) * (2.0 / k) - 1.0)
    a0, b0 = torch.meshgrid(c, c, indexing="ij")
    a0, b0 = a0.reshape(-1), b0.reshape(-1)
    acc = torch.zeros(k * k, 2, dtype=F64, device=device)
    for i in range(sub):
        for j in range(sub):
            acc += _concentric(a0 + (i + 0.5) * (2.0 / (k * sub)),
                               b0 + (j + 0.5) * (2.0 / (k * sub)))
    return acc / (sub * sub)


def light_samples(position: Vec, u: Vec, v: Vec, disc: bool = False, samples: int = SAMPLES,
                  device: torch.device | None = None
                  ) -> tuple[torch.Tensor, float, torch.Tensor]:
    """The quadrature nodes of a light.

    Args:
        position, u, v: ``(3,)`` centre and half-extent vectors.
        disc: ellipse (True) or parallelogram (False).
        samples: rounded up to ``k^2``, ``k = ceil(sqrt(samples))``.

    Returns:
        ``(y, dA, n_L)``: points ``(k^2, 3)`` float64 on the light, the area of each cell
        (all equal) and the unit emitting normal ``(3,)``.
    """
    p, a, b = (_vec(t, device) for t in (position, u, v))
    k = max(1, math.ceil(math.sqrt(samples)))
    if disc:
        st = _disc_nodes(k, device)
    else:
        c = (torch.arange(k, dtype=F64, device=device) + 0.5) * (2.0 / k) - 1.0
        s, t = torch.meshgrid(c, c, indexing="ij")
        st = torch.stack([s.reshape(-1), t.reshape(-1)], -1)
    y = p + st[:, :1] * a + st[:, 1:] * b
    normal = torch.linalg.cross(a, b)
    length = normal.norm()
    if not bool(length > 0):
        raise ValueError("reference_area: u and v are parallel or zero")
    return y, light_area(a, b, disc) / (k * k), normal / length


def _integrate(points: torch.Tensor, normals: torch.Tensor, position: Vec, u: Vec, v: Vec,
               disc: bool, two_sided: bool, casters, samples: int, eps: float,
               max_rays: int, view: torch.Tensor | None = None,
               alpha: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """Sums over the light samples per point: ``w = sum g``, and with ``view`` / ``alpha``
    ``(N, 3)`` / ``(N,)`` also ``s1 = sum D V g``, ``s2 = sum D V (1 - v.h)^5 g``, where
    ``g = vis max(n.l, 0) |n_L.l| / d^2 dA`` (times the one-sided mask). ``(N,)`` each."""
    x_all = points.to(F64)
    n_all = normals.to(F64)
    n_all = n_all / n_all.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    dev = x_all.device
    y, da, n_l = light_samples(position, u, v, disc, samples, dev)
    n_s = y.shape[0]
    count = x_all.shape[0]
    w_sum = torch.zeros(count, dtype=F64, device=dev)
    s1_sum = torch.zeros_like(w_sum) if view is not None else None
    s2_sum = torch.zeros_like(w_sum) if view is not None else None
    per = max(1, max_rays // n_s)
    for k0 in range(0, count, per):
        sl = slice(k0, k0 + per)
        x, n = x_all[sl], n_all[sl]
        d = y[None] - x[:, None]  # (P, S, 3)
        d2 = (d * d).sum(-1)
        ok = d2 > 1e-300
        inv = torch.where(ok, d2, torch.ones_like(d2)).rsqrt()
        l = d * inv[..., None]
        nl = (l * n[:, None]).sum(-1)
        cos_light = l @ n_l  # < 0: the receiver is on the n_L side of the light
        ok = ok & (nl > 0) & (cos_light != 0)
        if not two_sided:
            ok = ok & (cos_light < 0)
        g = torch.where(ok, nl * cos_light.abs() * inv * inv * da, torch.zeros_like(nl))
        if casters is not None and bool(ok.any()):
            positions, faces = casters
            o = ray_origins(x, n, eps)
            pi, si = ok.nonzero(as_tuple=True)
            seg = y[si] - o[pi]
            length = seg.norm(dim=-1).clamp_min(1e-300)
            t_max = ((length - eps) / length).clamp_min(0.0)
            hit = occluded(o[pi], seg, t_max, positions, faces)
            g[pi[hit], si[hit]] = 0.0
        w_sum[sl] = g.sum(-1)
        if view is None:
            continue
        vo = view[sl]
        a = alpha[sl][:, None]
        nv = (vo * n).sum(-1, keepdim=True).clamp(MIN_COS, 1.0)  # (P, 1)
        hv = l + vo[:, None]
        hlen = hv.norm(dim=-1)
        okh = ok & (hlen > 1e-12)
        h = hv / torch.where(okh, hlen, torch.ones_like(hlen))[..., None]
        nh = (h * n[:, None]).sum(-1)
        vh = (h * vo[:, None]).sum(-1).clamp(0.0, 1.0)
        okh = okh & (nh > 0)
        dist = walter_ggx(torch.where(okh, nh, torch.ones_like(nh)), a)
        vis = heitz_v(nv, torch.where(okh, nl, torch.ones_like(nl)), a)
        s1 = torch.where(okh, dist * vis * g, torch.zeros_like(g))
        s1_sum[sl] = s1.sum(-1)
        s2_sum[sl] = (s1 * (1.0 - vh) ** 5).sum(-1)
    return w_sum, s1_sum, s2_sum


def area_light_radiance(points: torch.Tensor, normals: torch.Tensor, eye: Vec,
                        albedo: torch.Tensor, metallic: torch.Tensor, roughness: torch.Tensor,
                        *, position: Vec, u: Vec, v: Vec, radiance: Vec, disc: bool = False,
                        two_sided: bool = False,
                        casters: tuple[torch.Tensor, torch.Tensor] | None = None,
                        samples: int = SAMPLES, eps: float = RAY_EPSILON,
                        max_rays: int = 2**20) -> torch.Tensor:
    """Outgoing radiance of the single-scattering Cook-Torrance BRDF lit by one area light.

    Args:
        points: ``(N, 3)`` receiver positions; normals: ``(N, 3)`` their normals (need not
            be unit).
        eye: ``(3,)`` (or ``(N, 3)``) camera position; the view direction is
            ``normalize(eye - x)``.
        albedo: ``(N, 3)`` base colour; metallic, roughness: ``(N,)`` (roughness clamped to
            ``[0.045, 1]``, ``alpha = roughness^2``).
        position, u, v: ``(3,)`` the light's centre and half-extent vectors.
        radiance: ``(3,)`` emitted radiance (colour x intensity).
        disc: ellipse instead of parallelogram; two_sided: emit on both sides.
        casters: ``(positions (V, 3), faces (F, 3))`` shadow casters (the light itself is
            not one), or None: unoccluded.
        samples: light samples per point (rounded up to a square ``k^2``; see the module
            docstring for the accuracy: near-specular highlights, roughness < ~0.15, of
            small lights need many more).
        eps: shadow-ray origin offset along the normal (m).
        max_rays: point-samples evaluated at once (bounds memory).

    Returns:
        ``(N, 3)`` float64 outgoing radiance towards the eye.
    """
    x = points.to(F64)
    n = normals.to(F64)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    eye_t = torch.as_tensor(eye, dtype=F64, device=x.device).expand_as(x)
    view = eye_t - x
    view = view / view.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    base = albedo.to(F64).reshape(-1, 3)
    m = metallic.to(F64).reshape(-1, 1)
    r = roughness.to(F64).reshape(-1).clamp(MIN_ROUGHNESS, 1.0)
    w, s1, s2 = _integrate(x, n, position, u, v, disc, two_sided, casters, samples, eps,
                           max_rays, view=view, alpha=r * r)
    f0 = 0.04 * (1.0 - m) + base * m
    kd = (1.0 - m) * base
    le = torch.as_tensor(radiance, dtype=F64, device=x.device).reshape(1, 3)
    out = kd / math.pi * w[:, None] + f0 * s1[:, None] + (1.0 - f0) * s2[:, None]
    return out * le


def form_factor_reference(points: torch.Tensor, normals: torch.Tensor, position: Vec, u: Vec,
                          v: Vec, disc: bool = False, samples: int = SAMPLES, *,
                          two_sided: bool = False,
                          casters: tuple[torch.Tensor, torch.Tensor] | None = None,
                          eps: float = RAY_EPSILON, max_rays: int = 2**20) -> torch.Tensor:
    """Point-to-light form factor ``(1 / pi) int_A vis max(n.l, 0) |n_L.l| / d^2 dA``: the
    diffuse integral without albedo (a white Lambert receiver under a light of radiance 1
    returns exactly this).

    Args:
        points, normals: ``(N, 3)`` receivers; position, u, v: ``(3,)`` the light.
        disc, two_sided, casters, eps, max_rays: as in :func:`area_light_radiance`.
        samples: light samples per point (rounded up to a square).

    Returns:
        ``(N,)`` float64 in ``[0, 1]``.
    """
    w, _, _ = _integrate(points, normals, position, u, v, disc, two_sided, casters, samples,
                         eps, max_rays)
    return w / math.pi


__all__ = ["MIN_COS", "SAMPLES", "area_light_radiance", "form_factor_reference", "light_area",
           "light_samples"]


def rectangle_corners(centre, normal, half, roll: float = 0.0,
                      dtype: torch.dtype = F64) -> torch.Tensor:
    """``(4, 3)`` corners of a rectangle of half sizes ``half`` (2,) centred at ``centre``
    (3,) whose front face (the side its right-hand normal ``(p1 - p0) x (p2 - p1)`` points
    to) faces along ``normal`` (3,), turned by ``roll`` radians about it (test geometry)."""
    c, n = torch.tensor(centre, dtype=F64), torch.tensor(normal, dtype=F64)
    n = n / n.norm()
    helper = torch.tensor([0.0, 0, 1] if abs(n[2]) < 0.9 else [1.0, 0, 0], dtype=F64)
    e1 = torch.linalg.cross(helper, n)
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(n, e1)
    cr, sr = math.cos(roll), math.sin(roll)
    e1, e2 = (cr * e1 + sr * e2) * half[0], (cr * e2 - sr * e1) * half[1]
    return torch.stack((c - e1 - e2, c + e1 - e2, c + e1 + e2, c - e1 + e2)).to(dtype)
