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
* :func:`light_optical_depth_reference`: the optical depth from points to a light by the
  midpoint rule: along the segment to a point light, or along the ray towards a directional
  light up to a finite ``far`` (the caller picks it beyond where the fog has thinned out).
* :func:`punctual_source_reference`: the in-scattering source of one light at fog samples,
  ``p_HG(l . v) E T_l`` with ``E = color I`` (directional) or ``color I / d^2`` (point) and
  ``T_l`` from :func:`light_optical_depth_reference`.
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


def light_optical_depth_reference(points: torch.Tensor,
                                  density: Callable[[torch.Tensor], torch.Tensor], *,
                                  direction: tuple[float, float, float] | None = None,
                                  position: tuple[float, float, float] | None = None,
                                  far: float = 1e3, steps: int = 20000) -> torch.Tensor:
    """Optical depth ``(B, 1, H, W)`` from points ``(B, 3, H, W)`` to one light.

    Give ``position`` (point light: the segment to it) or ``direction`` (directional light:
    the ray towards ``-direction`` up to ``far`` m). Midpoint rule on ``steps`` samples.
    """
    p = points.to(F64)
    if (direction is None) == (position is None):
        raise ValueError("give exactly one of direction, position")
    if position is not None:
        d = torch.tensor(position, dtype=F64).view(1, 3, 1, 1) - p
        length = d.norm(dim=1, keepdim=True)
        dir_y = torch.where(length > 0, d[:, 1:2] / length.clamp_min(1e-300), 0.0)
    else:
        l = -torch.tensor(direction, dtype=F64)
        dir_y = torch.full_like(p[:, 1:2], float(l[1] / l.norm()))
        length = torch.full_like(dir_y, far)
    return optical_depth_quadrature(p[:, 1:2], dir_y, length, density, steps=steps)


def punctual_source_reference(rays: torch.Tensor, g: float, color_intensity: torch.Tensor,
                              density: Callable[[torch.Tensor], torch.Tensor], *,
                              direction: tuple[float, float, float] | None = None,
                              position: tuple[float, float, float] | None = None,
                              far: float = 1e3, steps: int = 2048, dimmed: bool = True
                              ) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """``source(p, valid) -> (B, 3, H, W)``: ``p_HG(l . v) E T_l`` of one light (no range
    window, no cone, no shadows) at fog samples ``p``, for :func:`march_reference`.

    Args:
        rays: ``(B, 3, H, W)`` unit view directions.
        g: HG anisotropy.
        color_intensity: ``(3,)`` colour times intensity (lux, or candela for a point light).
        density: ``sigma_t(y)``.
        direction / position: the light (as in :func:`light_optical_depth_reference`).
        far, steps: the light-path quadrature.
        dimmed: False: ``T_l = 1``.
    """
    ci = color_intensity.to(F64).view(1, 3, 1, 1)
    v = rays.to(F64)

    def source(p: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        p = p.to(F64)
        if position is not None:
            d = torch.tensor(position, dtype=F64).view(1, 3, 1, 1) - p
            d2 = (d * d).sum(1, keepdim=True)
            l, e = d / d2.sqrt(), ci / d2
        else:
            l = -torch.tensor(direction, dtype=F64)
            l = (l / l.norm()).view(1, 3, 1, 1)
            e = ci
        cos = (l * v).sum(1, keepdim=True)
        t = torch.ones_like(cos)
        if dimmed:
            t = torch.exp(-light_optical_depth_reference(
                p, density, direction=direction, position=position, far=far, steps=steps))
        return hg_phase_reference(cos, g) * e * t

    return source
