"""Independent float64 references for the BRDF terms (share no code with torchraster).

The GGX distribution in Walter et al. 2007's tangent form, the height-correlated Smith
visibility of Heitz 2014 written with the Lambda function, and a hemisphere quadrature of
any BRDF (the directional albedo), used by ``tests/test_brdf.py`` and
``tests/test_lighting.py``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

F64 = torch.float64


def walter_ggx(mu: torch.Tensor, alpha: float) -> torch.Tensor:
    """GGX normal distribution, Walter et al. 2007 form.

    Args:
        mu: cosine between the normal and the half vector, ``0 < mu <= 1``.
        alpha: GGX width (``roughness ** 2``).

    Returns:
        ``alpha**2 / (pi cos**4 (alpha**2 + tan**2)**2)``, the shape of ``mu``.
    """
    a2 = alpha * alpha
    tan2 = (1 - mu * mu) / (mu * mu)
    return a2 / (math.pi * mu**4 * (a2 + tan2) ** 2)


def heitz_v(nv: torch.Tensor, nl: torch.Tensor, alpha: float) -> torch.Tensor:
    """Height-correlated Smith visibility ``G2 / (4 nv nl)``, ``G2 = 1 / (1 + Lambda(v) +
    Lambda(l))`` (Heitz 2014), for cosines in ``(0, 1]``; the broadcast shape of the inputs."""

    def lam(mu: torch.Tensor) -> torch.Tensor:
        tan2 = (1 - mu * mu) / (mu * mu)
        return 0.5 * (-1 + torch.sqrt(1 + alpha * alpha * tan2))

    return 1.0 / (1.0 + lam(nv) + lam(nl)) / (4 * nv * nl)


def directional_albedo(
    brdf_cos: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
    theta_v: float,
    n_theta: int = 600,
    n_phi: int = 96,
) -> float:
    """Integral over the hemisphere of ``l`` of BRDF times ``max(n.l, 0)``, by quadrature.

    The integral is taken over the half vector (``l = reflect(v, h)``, ``dw_l = 4 (v.h)
    dw_h``) on a grid graded towards the pole, where a sharp GGX lobe lives.

    Args:
        brdf_cos: ``f(n, v, l)`` -> BRDF times ``max(n.l, 0)`` for the unit normal ``n`` and
            view direction ``v``, each ``(1, 3, 1, 1)``, and light directions ``l``
            ``(1, 3, n_theta, n_phi)``; returns ``n_theta * n_phi`` values (e.g.
            ``(1, 1, n_theta, n_phi)``).
        theta_v: angle between the view direction and the normal (radians).
        n_theta, n_phi: quadrature points in the half vector's polar and azimuth angles.

    Returns:
        The directional albedo (1 for a white, lossless BRDF).
    """
    s = torch.linspace(0, 1, n_theta, dtype=F64)
    th = 0.5 * math.pi * s**3  # graded grid: dense near the pole
    ph = torch.linspace(0, 2 * math.pi, n_phi + 1, dtype=F64)[:-1]
    t, p = torch.meshgrid(th, ph, indexing="ij")
    h = torch.stack([t.sin() * p.cos(), t.sin() * p.sin(), t.cos()])  # (3, nt, np)
    v = torch.tensor([math.sin(theta_v), 0.0, math.cos(theta_v)], dtype=F64).view(3, 1, 1)
    vh = (v * h).sum(0, keepdim=True)
    l = 2 * vh * h - v
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64).view(3, 1, 1)
    f = brdf_cos(n[None], v[None], l[None]).to(F64).reshape(n_theta, n_phi)
    f = torch.where((vh[0] > 0) & (l[2] > 0), f * 4 * vh[0], torch.zeros_like(f))
    inner = f.mean(dim=1) * 2 * math.pi  # uniform in phi
    return torch.trapezoid(inner * th.sin(), th).item()


def furnace_hemisphere(theta_v: float, n_theta: int = 160, n_phi: int = 48
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """A quadrature of the light hemisphere around the normal +z for the view at polar angle
    ``theta_v`` (in the x-z plane), parametrised by the half vector (graded towards the
    normal, dw_l = 4 (v.h) dw_h): with radiance 1 from every node, ``sum_k f(l_k) cos_k
    weight_k`` is the directional albedo of a BRDF f (a white furnace of punctual lights).

    Returns:
        ``(l, weight)``: unit light directions ``(K, 3)`` and solid-angle weights ``(K,)``,
        float64, only the nodes above the surface with a positive weight.
    """
    th = 0.5 * math.pi * torch.linspace(0, 1, n_theta, dtype=torch.float64) ** 3
    tw = torch.zeros(n_theta, dtype=torch.float64)  # trapezoid weights of the graded nodes
    tw[1:] += 0.5 * (th[1:] - th[:-1])
    tw[:-1] += 0.5 * (th[1:] - th[:-1])
    ph = (torch.arange(n_phi, dtype=torch.float64) + 0.5) * (2 * math.pi / n_phi)
    t, p = torch.meshgrid(th, ph, indexing="ij")
    h = torch.stack([t.sin() * p.cos(), t.sin() * p.sin(), t.cos()], -1).reshape(-1, 3)
    v = torch.tensor([math.sin(theta_v), 0.0, math.cos(theta_v)], dtype=torch.float64)
    vh = h @ v
    l = 2 * vh[:, None] * h - v
    w = (tw[:, None] * th.sin()[:, None] * (2 * math.pi / n_phi)).expand(-1, n_phi)
    w = (w.reshape(-1) * 4 * vh).clamp_min(0)
    keep = (w > 0) & (l[:, 2] > 0)
    return l[keep], w[keep]
