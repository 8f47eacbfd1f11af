"""Exposure, tone curves and the sRGB output encoding.

All curves act per channel on linear HDR values (negative inputs are clamped to 0 first)
and return display-referred linear values in [0, 1]; :class:`EncodeSRGB` then applies the
sRGB transfer function through ``kornia.color.linear_rgb_to_rgb``.

Curves (x = exposed linear value):
- ``linear``: clamp(x, 0, 1).
- ``reinhard``: x / (1 + x)  (Reinhard et al. 2002, "Photographic Tone Reproduction", eq. 3).
- ``reinhard_extended``: x (1 + x / w^2) / (1 + x), w = white point mapped to 1 (eq. 4),
  clamped to 1 above w.
- ``aces``: Narkowicz 2015 "ACES Filmic Tone Mapping Curve" fit of the ACES RRT+ODT,
  x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14), clamped to [0, 1]. As published, without
  the 0.6 pre-exposure Narkowicz mentions (use ``ev = log2(0.6)`` for that look).
- ``hable``: Hable 2010 "Uncharted 2: HDR Lighting" filmic curve
  f(x) = (x (A x + C B) + D E) / (x (A x + B) + D F) - E / F with A=0.15, B=0.50, C=0.10,
  D=0.20, E=0.02, F=0.30, output f(2 x) / f(W), W = 11.2 (his exposure bias 2).
"""

from __future__ import annotations

import torch
from torch import nn

from ..numerics import compute_dtype, finish_low_precision
from .blur import check_image, per_sample

CURVES = ("linear", "reinhard", "reinhard_extended", "aces", "hable")

# Hable 2010 (Uncharted 2) constants, from the talk's shader listing.
_HABLE = dict(A=0.15, B=0.50, C=0.10, D=0.20, E=0.02, F=0.30)
HABLE_WHITE = 11.2
HABLE_EXPOSURE_BIAS = 2.0


def _hable_partial(x: torch.Tensor) -> torch.Tensor:
    a, b, c, d, e, f = (_HABLE[k] for k in "ABCDEF")
    return (x * (a * x + c * b) + d * e) / (x * (a * x + b) + d * f) - e / f


def tone_curve(x: torch.Tensor, curve: str = "aces", white: float = 4.0) -> torch.Tensor:
    """Apply tone ``curve`` per channel: (B, C, H, W) linear HDR -> (B, C, H, W) in [0, 1].

    ``white``: white point (linear units) for ``reinhard_extended`` only, > 0.
    Half-precision inputs are computed in float32 and cast back.
    """
    x = check_image("x", x)
    if curve not in CURVES:
        raise ValueError(f"curve: expected one of {CURVES}, got {curve!r}")
    if curve == "reinhard_extended" and not white > 0:
        raise ValueError(f"white: expected a positive white point, got {white}")
    out_dtype = x.dtype
    x = x.to(compute_dtype(x)).clamp(min=0.0)
    if curve == "linear":
        y = x.clamp(max=1.0)
    elif curve == "reinhard":
        y = x / (1.0 + x)
    elif curve == "reinhard_extended":
        # written as x/(1+x) * (1 + x/w^2) so no x^2 term can overflow before the clamp
        y = (x / (1.0 + x) * (1.0 + x / (white * white))).clamp(max=1.0)
    elif curve == "aces":
        # divide numerator and denominator by (1 + x)^2 -> no overflow of x^2 for huge x
        s = x / (1.0 + x)
        t = 1.0 / (1.0 + x)
        num = s * (2.51 * s + 0.03 * t)
        den = s * (2.43 * s + 0.59 * t) + 0.14 * t * t
        y = (num / den).clamp(0.0, 1.0)
    else:  # hable
        # f is bounded: f(x) -> 1 - E/F for x -> inf, computed via u = 1/(1+x) for large x
        xb = HABLE_EXPOSURE_BIAS * x
        s, t = xb / (1.0 + xb), 1.0 / (1.0 + xb)
        a, b, c, d, e, f = (_HABLE[k] for k in "ABCDEF")
        num = s * (a * s + c * b * t) + d * e * t * t
        den = s * (a * s + b * t) + d * f * t * t
        white_scale = 1.0 / float(_hable_partial(torch.tensor(HABLE_WHITE, dtype=torch.float64)))
        y = ((num / den - e / f) * white_scale).clamp(0.0, 1.0)
    return finish_low_precision(y, out_dtype)


class Exposure(nn.Module):
    """Multiply linear HDR by ``2 ** ev`` (ev in stops; float or per-sample ``(B,)``)."""

    def __init__(self, ev: float | torch.Tensor = 0.0, enabled: bool = True):
        super().__init__()
        self.ev, self.enabled = ev, enabled

    def forward(self, x: torch.Tensor, ev: float | torch.Tensor | None = None) -> torch.Tensor:
        """(B, C, H, W) -> (B, C, H, W) scaled by 2**ev; ``ev`` overrides ``self.ev``.

        Returns ``x`` itself when disabled.
        """
        if not self.enabled:
            return x
        x = check_image("x", x)
        ev_t = per_sample("ev", self.ev if ev is None else ev, x.to(compute_dtype(x)))
        return finish_low_precision(x.to(ev_t.dtype) * torch.exp2(ev_t), x.dtype)


class ToneMap(nn.Module):
    """Tone curve module (see :func:`tone_curve`); identity when ``enabled=False``."""

    def __init__(self, curve: str = "aces", white: float = 4.0, enabled: bool = True):
        super().__init__()
        if curve not in CURVES:
            raise ValueError(f"curve: expected one of {CURVES}, got {curve!r}")
        self.curve, self.white, self.enabled = curve, float(white), enabled

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) linear HDR -> (B, C, H, W) display-linear in [0, 1]."""
        if not self.enabled:
            return x
        return tone_curve(x, self.curve, self.white)


def encode_srgb(x: torch.Tensor) -> torch.Tensor:
    """Display-linear (B, 3, H, W) -> sRGB-encoded (B, 3, H, W) in [0, 1].

    Clamps to [0, 1], then kornia's exact piecewise sRGB transfer function
    (``kornia.color.linear_rgb_to_rgb``: 12.92 x below 0.0031308, else 1.055 x^(1/2.4) - 0.055).
    """
    from kornia.color import linear_rgb_to_rgb  # lazy: `import torchraster` skips kornia

    x = check_image("x", x, 3)
    out_dtype = x.dtype
    y = linear_rgb_to_rgb(x.to(compute_dtype(x)).clamp(0.0, 1.0))
    return finish_low_precision(y, out_dtype)


class EncodeSRGB(nn.Module):
    """Module form of :func:`encode_srgb`; identity when ``enabled=False``."""

    def __init__(self, enabled: bool = True):
        super().__init__()
        self.enabled = enabled

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) display-linear -> (B, 3, H, W) sRGB."""
        if not self.enabled:
            return x
        return encode_srgb(x)
