"""Brute-force single-scattering reference for the fog of
:mod:`torchraster.shading.volumetric`: many-step float64 midpoint quadrature, with the
transmittance integrated numerically from the density (no closed form), so it shares no
formula with the engine. Imports torch only.

* :func:`optical_depth_quadrature`: ``integral_0^s sigma_t(o_y + t v_y) dt`` by the midpoint
  rule.
* :func:`march_reference`: ``integral_start^end T(t) sigma_s(t) S(t) dt`` by the midpoint rule
  on ``steps`` samples, ``T`` accumulated from the same samples (and a quadrature of the
  part before ``start``).
* :func:`hg_phase_reference`: the Henyey-Greenstein phase written out.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

F64 = torch.float64


def hg_phase_reference(cos_theta: torch.Tensor, g: float) -> torch.Tensor:
    """``(1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^1.5)`` in float64."""
    c = cos_theta.to(F64)
    return (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * c) ** 1.5)


def optical_depth_quadrature(origin_y: torch.Tensor, dir_y: torch.Tensor, length: torch.Tensor,
                             density: Callable[[torch.Tensor], torch.Tensor], steps: int = 4096
                             ) -> torch.Tensor:
    """Midpoint-rule optical depth of rays (any broadcastable shapes, finite ``length``)."""
    oy, dy, s = (x.to(F64)[..., None] for x in (origin_y, dir_y, length))
    total = torch.zeros(torch.broadcast_shapes(oy.shape, dy.shape, s.shape)[:-1], dtype=F64)
    chunk = 4096
    for k in range(0, steps, chunk):
        i = torch.arange(k, min(k + chunk, steps), dtype=F64)
        t = s * ((i + 0.5) / steps)
        total = total + (density(oy + dy * t) * (s / steps)).sum(-1)
    return total


def march_reference(eye: torch.Tensor, rays: torch.Tensor, start: torch.Tensor,
                    end: torch.Tensor, density: Callable[[torch.Tensor], torch.Tensor],
                    albedo: torch.Tensor,
                    source: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                    steps: int = 1024) -> torch.Tensor:
    """In-scattered radiance ``integral_start^end T(t) albedo sigma_t(t) S(t) dt``.

    Args:
        eye: ``(B, 3)``; rays: ``(B, 3, H, W)`` unit directions.
        start, end: ``(B, 1, H, W)`` finite distances (nothing where ``end <= start``).
        density: ``sigma_t(y)`` of heights (float64 tensors).
        albedo: ``(3,)`` single-scattering albedo.
        source: ``source(p, valid) -> (B, 3, H, W)`` radiance per unit scattering length.
        steps: midpoint samples.

    Returns:
        ``(B, 3, H, W)`` float64.
    """
    eye, rays, start, end = (x.to(F64) for x in (eye, rays, start, end))
    valid = end > start
    length = torch.where(valid, end - start, torch.zeros_like(end))
    oy, dy = eye[:, 1, None, None, None], rays[:, 1:2]
    tau = optical_depth_quadrature(oy, dy, start, density, steps=max(64, steps // 4))
    out = torch.zeros_like(rays)
    dt = length / steps
    for i in range(steps):
        t = start + length * ((i + 0.5) / steps)
        sigma = density(oy + dy * t)
        tau_mid = tau + sigma * dt / 2
        p = eye[:, :, None, None] + rays * t
        out = out + torch.exp(-tau_mid) * sigma * dt * source(p, valid).to(F64)
        tau = tau + sigma * dt
    return out * albedo.to(F64).view(1, 3, 1, 1) * valid
