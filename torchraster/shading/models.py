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

import functools
import inspect
import math
from collections.abc import Callable

import torch

from torchraster.numerics import diffuse_color, dot, safe_normalize, specular_f0
from torchraster.shading.brdf import MIN_ROUGHNESS
from torchraster.shading.brdf import (
    cook_torrance as _cook_torrance_brdf,
)
from torchraster.shading.surface import Surface

#: Number of diffuse bands of the toon model.
TOON_BANDS: int = 3

#: Threshold on the normalised Blinn-Phong lobe (relative to its peak) above which the toon
#: model shows its hard highlight.
TOON_SPECULAR_THRESHOLD: float = 0.5

#: Brightness of the toon highlight relative to a fully lit white diffuse surface.
TOON_SPECULAR: float = 0.6

#: Default ``rim_width`` of the toon model: the rim covers ``n.v < TOON_RIM_WIDTH``.
TOON_RIM_WIDTH: float = 0.3


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


def toon(n: torch.Tensor, v: torch.Tensor, l: torch.Tensor, surface: Surface, *,
         bands: int = TOON_BANDS, rim: float = 0.0, rim_width: float = TOON_RIM_WIDTH):
    """Cel shading: diffuse quantised into ``bands`` bands, a hard specular spot and an
    optional rim light.

    ``diffuse = kd / pi * ceil(bands * max(n.l, 0)) / bands``; the highlight
    ``TOON_SPECULAR * mix(1, albedo, metallic) / pi`` where the Blinn-Phong lobe of the same
    roughness exceeds TOON_SPECULAR_THRESHOLD of its peak (a white spot on dielectrics, a
    tinted one on metals); the rim ``rim / pi`` (white) on the lit side (n.l > 0) where the
    surface turns away from the viewer, ``n.v < rim_width`` (the classic toon rim, e.g.
    Roystan's toon shader, thresholded). Piecewise constant in the angles: gradients flow
    to the colours only.

    Args:
        n, v, l, surface: as every model (module docstring).
        bands: number of diffuse levels above black, an int >= 1.
        rim: brightness of the rim relative to a fully lit white diffuse surface, >= 0
            (0: no rim).
        rim_width: the rim covers ``n.v < rim_width``, in [0, 1].

    Returns:
        ``BRDF-like factor * cosine``, shaped like the broadcast of the inputs.
    """
    if isinstance(bands, bool) or not isinstance(bands, int) or bands < 1:
        raise ValueError(f"bands: expected an int >= 1, got {bands!r}")
    if not (isinstance(rim, (int, float)) and math.isfinite(rim) and rim >= 0):
        raise ValueError(f"rim: expected a finite float >= 0, got {rim!r}")
    if not (isinstance(rim_width, (int, float)) and 0.0 <= rim_width <= 1.0):
        raise ValueError(f"rim_width: expected a float in [0, 1], got {rim_width!r}")
    n_dot_l = dot(n, l).clamp(0.0, 1.0)
    level = torch.ceil(n_dot_l * bands) / bands
    _, n_dot_h, s = _blinn_phong_lobe(n, v, l, surface.roughness)
    # (n.h)^s > t  <=>  n.h > t^(1/s): the threshold angle, free of overflow for large s.
    cutoff = math.log(TOON_SPECULAR_THRESHOLD) / s
    hit = (n_dot_h > torch.exp(cutoff)) & (n_dot_l > 0)
    tint = 1.0 + (surface.albedo - 1.0) * surface.metallic
    spec = torch.where(hit, TOON_SPECULAR * tint, 0.0)
    out = diffuse_color(surface.albedo, surface.metallic) * level + spec
    if rim > 0:
        out = out + torch.where((dot(n, v) < rim_width) & (n_dot_l > 0), float(rim), 0.0)
    return out / math.pi


#: Built-in shading models by name.
MODELS: dict[str, ShadingModel] = {
    "cook_torrance": cook_torrance,
    "blinn_phong": blinn_phong,
    "half_lambert": half_lambert,
    "toon": toon,
}


def get_model(model: str | ShadingModel, **options: object) -> ShadingModel:
    """Return the shading model named ``model`` (a key of :data:`MODELS`) or the callable.

    Args:
        model: a name of :data:`MODELS` or a callable ``model(n, v, l, surface)``.
        options: keyword parameters of a named model (e.g. ``toon``'s ``bands``, ``rim``,
            ``rim_width``), bound here; a name the model does not take raises a ValueError
            naming it and the model's parameters.
    """
    if callable(model) and not options:
        return model
    if isinstance(model, str) and model in MODELS:
        fn = MODELS[model]
        if not options:
            return fn
        params = model_options(model)
        unknown = sorted(set(options) - set(params))
        if unknown:
            raise ValueError(f"shading options {unknown}: not parameters of model {model!r}; "
                             f"it takes {sorted(params) or 'none'}")
        fn(*_probe(), **options)  # validate the values now (errors name the option)
        return functools.partial(fn, **options)
    if callable(model):
        raise ValueError("options: only named models take options; bind them into the "
                         f"callable instead, got {sorted(options)}")
    raise ValueError(
        f"model: expected one of {sorted(MODELS)} or a callable "
        f"model(n, v, l, surface) -> radiance factor, got {model!r}"
    )


def model_options(model: str) -> dict[str, object]:
    """``{parameter: default}`` of the keyword options of the named model (``{}`` for models
    without options), e.g. ``{"bands": 3, "rim": 0.0, "rim_width": 0.3}`` for ``"toon"``."""
    fn = get_model(model)
    return {p.name: p.default for p in inspect.signature(fn).parameters.values()
            if p.kind is inspect.Parameter.KEYWORD_ONLY}


def _probe() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, Surface]:
    """One tiny valid input of a model (to check option values up front)."""
    z = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
    one = torch.ones(1, 1, 1, 1)
    return z, z, z, Surface(albedo=torch.ones(1, 3, 1, 1), metallic=one * 0, roughness=one)
