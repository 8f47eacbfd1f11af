"""Shading models: how a surface turns light from one direction into outgoing radiance.

Every model has the same signature, so the lighting pass can take one by name
(:data:`MODELS`, :func:`get_model`) or any user callable with this contract::

    model(n, v, l, surface) -> radiance factor

* ``n``: unit shading normal, ``v``: unit direction to the viewer, ``l``: unit direction
  to the light. xyz on dim -3: ``(B, 3, H, W)``, or ``(B, L, 3, H, W)`` with one slice per
  light (the lighting pass calls models with ``n, v`` of shape ``(B, 1, 3, H, W)`` and
  ``l`` of shape ``(B, L, 3, H, W)``); shapes broadcast.
* ``surface``: a :class:`Surface` whose tensors broadcast against the vectors, e.g.
  albedo ``(B, 3, H, W)`` (or ``(B, 1, 3, H, W)`` in the lighting pass).
* returns ``(B, 3, H, W)`` (resp. ``(B, L, 3, H, W)``): outgoing radiance per unit
  irradiance arriving perpendicular to the light direction, i.e. ``BRDF * max(n.l, 0)``
  for physically based models. Multiply by the light's illuminance (lux) at the point to
  get radiance. It must be 0 (or whatever the model wants) for light from below.

Only ``cook_torrance`` is physically based (and the default); the others are classic
artistic models, kept cheap and finite-gradient everywhere.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from torchraster.numerics import diffuse_color, dot, safe_normalize, specular_f0
from torchraster.shading.brdf import MIN_ROUGHNESS
from torchraster.shading.brdf import (
    cook_torrance as _cook_torrance_brdf,
)

#: Number of diffuse bands of the toon model.
TOON_BANDS: int = 3

#: Threshold on the normalised Blinn-Phong lobe (relative to its peak) above which the toon
#: model shows its hard highlight.
TOON_SPECULAR_THRESHOLD: float = 0.5

#: Brightness of the toon highlight relative to a fully lit white diffuse surface.
TOON_SPECULAR: float = 0.6


@dataclass(frozen=True)
class Surface:
    """Per-pixel material inputs of a shading model (metallic-roughness, glTF semantics).

    Attributes:
        albedo: base colour, linear RGB in [0, 1], ``(..., 3, H, W)``.
        metallic: in [0, 1], ``(..., 1, H, W)``.
        roughness: perceptual roughness in [0, 1], ``(..., 1, H, W)``.
    """

    albedo: torch.Tensor
    metallic: torch.Tensor
    roughness: torch.Tensor


ShadingModel = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, Surface], torch.Tensor]


def _blinn_phong_exponent(roughness: torch.Tensor) -> torch.Tensor:
    """Blinn-Phong exponent matching GGX alpha: ``s = 2 / alpha^2 - 2`` (Walter et al. 2007)."""
    r = roughness.clamp(MIN_ROUGHNESS, 1.0)
    a2 = (r * r) ** 2
    return 2.0 / a2 - 2.0


def _safe_pow(base: torch.Tensor, exponent: torch.Tensor) -> torch.Tensor:
    """``base ** exponent`` for base in [0, 1], 0 where base <= 0, with finite gradients."""
    ok = base > 0
    safe = torch.where(ok, base, 1.0)
    return torch.where(ok, torch.exp(exponent * torch.log(safe)), 0.0)


def _blinn_phong_lobe(n: torch.Tensor, v: torch.Tensor, l: torch.Tensor, roughness):
    """Normalised Blinn-Phong lobe ``(s + 8) / (8 pi) (n.h)^s`` (Akenine-Moller et al., RTR)."""
    s = _blinn_phong_exponent(roughness)
    n_dot_h = dot(n, safe_normalize(v + l)).clamp(0.0, 1.0)
    return (s + 8.0) / (8.0 * math.pi) * _safe_pow(n_dot_h, s), n_dot_h, s


def cook_torrance(n: torch.Tensor, v: torch.Tensor, l: torch.Tensor, surface: Surface):
    """GGX / Smith height-correlated / Schlick specular + Lambert diffuse (the default).

    See :func:`torchraster.shading.brdf.cook_torrance`; returns ``BRDF * max(n.l, 0)``.
    """
    return _cook_torrance_brdf(n, v, l, surface.albedo, surface.metallic, surface.roughness)


def blinn_phong(n: torch.Tensor, v: torch.Tensor, l: torch.Tensor, surface: Surface):
    """Energy-normalised Blinn-Phong: ``(kd / pi + f0 (s+8)/(8 pi) (n.h)^s) max(n.l, 0)``.

    ``kd = (1 - metallic) albedo``, ``f0 = mix(0.04, albedo, metallic)`` and the exponent
    ``s = 2 / alpha^2 - 2`` follows from the roughness, so highlights roughly match GGX.
    No Fresnel or visibility term.
    """
    lobe, _, _ = _blinn_phong_lobe(n, v, l, surface.roughness)
    f = (
        diffuse_color(surface.albedo, surface.metallic) / math.pi
        + specular_f0(surface.albedo, surface.metallic) * lobe
    )
    return f * dot(n, l).clamp(0.0, 1.0)


def half_lambert(n: torch.Tensor, v: torch.Tensor, l: torch.Tensor, surface: Surface):
    """Valve's half-Lambert wrap diffuse: ``albedo / pi * (0.5 n.l + 0.5)^2``.

    Lights the back side softly (non-zero for n.l > -1), no specular; metallic is ignored.
    Not energy conserving (integrates to 4/3 of Lambert over the hemisphere).
    """
    del v
    wrap = 0.5 * dot(n, l) + 0.5
    return surface.albedo / math.pi * wrap.clamp(0.0, 1.0) ** 2


def toon(n: torch.Tensor, v: torch.Tensor, l: torch.Tensor, surface: Surface):
    """Cel shading: diffuse quantised into TOON_BANDS bands plus a hard specular spot.

    ``diffuse = kd / pi * ceil(TOON_BANDS * max(n.l, 0)) / TOON_BANDS``; the highlight
    ``TOON_SPECULAR * mix(1, albedo, metallic) / pi`` where the Blinn-Phong lobe of the same
    roughness exceeds TOON_SPECULAR_THRESHOLD of its peak (a white spot on dielectrics, a
    tinted one on metals). Piecewise constant in the angles: gradients flow to the colours
    only.
    """
    n_dot_l = dot(n, l).clamp(0.0, 1.0)
    bands = torch.ceil(n_dot_l * TOON_BANDS) / TOON_BANDS
    _, n_dot_h, s = _blinn_phong_lobe(n, v, l, surface.roughness)
    # (n.h)^s > t  <=>  n.h > t^(1/s): the threshold angle, free of overflow for large s.
    cutoff = math.log(TOON_SPECULAR_THRESHOLD) / s
    hit = (n_dot_h > torch.exp(cutoff)) & (n_dot_l > 0)
    tint = 1.0 + (surface.albedo - 1.0) * surface.metallic
    spec = torch.where(hit, TOON_SPECULAR * tint, 0.0)
    return (diffuse_color(surface.albedo, surface.metallic) * bands + spec) / math.pi


#: Built-in shading models by name.
MODELS: dict[str, ShadingModel] = {
    "cook_torrance": cook_torrance,
    "blinn_phong": blinn_phong,
    "half_lambert": half_lambert,
    "toon": toon,
}


def get_model(model: str | ShadingModel) -> ShadingModel:
    """Return the shading model named ``model`` (a key of :data:`MODELS`) or the callable."""
    if callable(model):
        return model
    if isinstance(model, str) and model in MODELS:
        return MODELS[model]
    raise ValueError(
        f"model: expected one of {sorted(MODELS)} or a callable "
        f"model(n, v, l, surface) -> radiance factor, got {model!r}"
    )
