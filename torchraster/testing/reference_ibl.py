"""Independent float64 reference for image-based GGX specular (shares no code with torchraster).

``brute_ggx_specular`` integrates the single-scattering GGX lobe of a white conductor
(f0 = 1, so Fresnel = 1) against a lat-long environment::

    L_o(n, v) = int L(l) D(h) G2(v, l) / (4 (n.l)(n.v)) (n.l)^+ dl

as a midpoint sum over a grid ``k`` times finer than the map in each direction, the
radiance at each fine cell reconstructed bilinearly from the texels (wrap in longitude,
clamp in latitude: how the renderer reads the map) and each cell weighted by its exact
solid angle. ``k = 1`` is the plain sum over texels; a lobe narrower than a few texels
needs ``k > 1`` (:func:`supersampling`). Used by ``tests/test_ibl_accuracy.py`` and
``scripts/bench_energy.py`` (section ibl-specular).

Lat-long layout (that of the renderer's maps): row 0 is +y, ``theta = (i + 0.5) pi / H``
from +y; column j has azimuth ``phi = ((j + 0.5) / W - 0.5) 2 pi`` and direction
``(sin theta sin phi, cos theta, -sin theta cos phi)`` (the image centre looks along -z).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from torchraster.testing.reference_brdf import heitz_v, walter_ggx

F64 = torch.float64


def supersampling(height: int, roughness: float) -> int:
    """Sub-cells per texel side so that the lobe (half-width ~ 2 alpha in l) spans about
    16 fine cells: ``clamp(ceil(8 (pi / H) / alpha), 1, 8)``, ``alpha = roughness**2``."""
    alpha = max(roughness, 0.045) ** 2
    return int(min(8, max(1, math.ceil(8.0 * (math.pi / height) / alpha))))


def _fine_map(env: torch.Tensor, k: int) -> torch.Tensor:
    """``(3, k H, k W)``: the bilinear reconstruction of ``env`` ``(3, H, W)`` at the centres
    of a k-times finer grid (one wrapped column each side, rows clamped)."""
    if k == 1:
        return env
    padded = torch.cat((env[..., -1:], env, env[..., :1]), -1)[None]
    h, w = env.shape[-2:]
    up = F.interpolate(padded, size=(k * h, k * (w + 2)), mode="bilinear",
                       align_corners=False)[0]
    return up[..., k:k + k * w]


def _band(height: int, width: int, row0: int, rows: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Cell-centre directions ``(3, rows W)`` and exact cell solid angles ``(rows W,)`` of
    rows ``row0 .. row0 + rows - 1`` of an ``H x W`` lat-long grid."""
    i = torch.arange(row0, row0 + rows, dtype=F64)
    theta = (i + 0.5) * (math.pi / height)
    phi = ((torch.arange(width, dtype=F64) + 0.5) / width - 0.5) * (2.0 * math.pi)
    st, ct = theta.sin()[:, None], theta.cos()[:, None]
    d = torch.stack((st * phi.sin()[None], ct.expand(rows, width),
                     -st * phi.cos()[None]), 0).reshape(3, -1)
    edges = torch.cos(torch.arange(row0, row0 + rows + 1, dtype=F64) * (math.pi / height))
    dw = ((edges[:-1] - edges[1:]) * (2.0 * math.pi / width))[:, None].expand(rows, width)
    return d, dw.reshape(-1)


def brute_ggx_specular(env: torch.Tensor, n: torch.Tensor, v: torch.Tensor, roughness: float,
                       k: int | None = None) -> torch.Tensor:
    """Reflected radiance of a white GGX conductor (f0 = 1, single scattering).

    Args:
        env: ``(3, H, W)`` lat-long radiance (any float dtype; summed in float64).
        n, v: ``(K, 3)`` unit normals and unit directions towards the eye (n.v > 0).
        roughness: perceptual roughness (alpha = roughness**2, floored at 0.045**2).
        k: supersampling of the map (None: :func:`supersampling`).

    Returns:
        ``(K, 3)`` float64 radiance.
    """
    env = env.to(F64)
    h, w = env.shape[-2:]
    k = supersampling(h, roughness) if k is None else int(k)
    alpha = max(roughness, 0.045) ** 2
    n, v = n.to(F64), v.to(F64)
    nv = (n * v).sum(1).clamp(1e-4, 1.0)[:, None]  # (K, 1)
    out = torch.zeros(n.shape[0], 3, dtype=F64)
    band = max(1, 2**22 // (n.shape[0] * k * k * w))  # source rows a band: 4M (pair, cell)
    for r0 in range(0, h, band):  # the fine grid in bands of rows: bounded memory
        rows = env[:, max(r0 - 1, 0):min(r0 + band + 1, h)]  # one row of context each side
        lo = k * (r0 - max(r0 - 1, 0))
        lf = _fine_map(rows, k)[:, lo:lo + k * min(band, h - r0)].reshape(3, -1)
        d, dw = _band(k * h, k * w, k * r0, lf.shape[1] // (k * w))
        nl = n @ d  # (K, P)
        hv = d[None] + v[:, :, None]
        hv = hv / hv.norm(dim=1, keepdim=True).clamp_min(1e-300)
        nh = (n[:, :, None] * hv).sum(1).clamp(1e-12, 1.0)
        f = walter_ggx(nh, alpha) * heitz_v(nv, nl.clamp(1e-12, 1.0), alpha)
        out += torch.where(nl > 0, f * nl * dw, 0.0) @ lf.T
    return out
