"""Auto-exposure: metered scene luminance -> exposure in EV, with temporal adaptation.

Metering (Reinhard et al. 2002, "Photographic Tone Reproduction", eq. 1-2): the log-average
luminance L_avg = exp(mean(log(LUM_FLOOR + L))) with Rec. 709 luminance
L = 0.2126 R + 0.7152 G + 0.0722 B; the exposure that maps L_avg to the ``key`` (0.18,
"middle grey") is ev = log2(key / L_avg) + compensation, clamped to [min_ev, max_ev].

``metering="percentile"`` averages log-luminance only over the pixels between the
``percentile_low`` and ``percentile_high`` quantiles (the UE4-style histogram metering that
ignores the darkest and brightest pixels). It is evaluated exactly by sorting instead of
with a binned histogram - the limit of infinitely fine bins - and stays differentiable.

Temporal adaptation (image sequences): the adapted log2-luminance moves toward the metered
one by the factor 1 - exp(-rate * dt) per frame (exponential adaptation, ``rate`` in 1/s,
``dt`` in seconds), so the result does not depend on the frame rate. The state lives in
the buffer ``adapted_log2_lum`` (B,), detached between frames; :meth:`reset` clears it.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..numerics import compute_dtype, finish_low_precision
from .blur import check_image, per_sample

#: Rec. 709 / sRGB luminance weights.
REC709 = (0.2126, 0.7152, 0.0722)

#: Reinhard's delta: added to luminance before the log so black pixels (0) give a finite
#: log. 1e-6 is far below any pixel a display can show after exposure clamps of +-20 EV,
#: so it does not bias the mean for real scenes. Also a normal number in float32.
LUM_FLOOR = 1e-6

METERINGS = ("average", "percentile")


def luminance(x: torch.Tensor) -> torch.Tensor:
    """Rec. 709 relative luminance: (B, 3, H, W) linear RGB -> (B, 1, H, W)."""
    x = check_image("x", x, 3)
    w = torch.tensor(REC709, device=x.device, dtype=x.dtype).reshape(1, 3, 1, 1)
    return (x * w).sum(dim=1, keepdim=True)


def metered_log2_luminance(
    x: torch.Tensor,
    metering: str = "average",
    percentile_low: float = 0.1,
    percentile_high: float = 0.9,
) -> torch.Tensor:
    """Metered scene log2-luminance per sample: (B, 3, H, W) linear HDR -> (B,).

    ``average``: log2 of Reinhard's log-average luminance. ``percentile``: mean of
    log2(L + LUM_FLOOR) over pixels ranked in [percentile_low, percentile_high).
    """
    if metering not in METERINGS:
        raise ValueError(f"metering: expected one of {METERINGS}, got {metering!r}")
    if not 0.0 <= percentile_low < percentile_high <= 1.0:
        raise ValueError(
            "percentile_low, percentile_high: expected 0 <= low < high <= 1, "
            f"got {percentile_low}, {percentile_high}"
        )
    lum = luminance(x.to(compute_dtype(x))).clamp(min=0.0)
    logl = torch.log2(lum + LUM_FLOOR).flatten(1)  # (B, N)
    if metering == "average":
        return logl.mean(dim=1)
    n = logl.shape[1]
    lo = min(int(math.floor(percentile_low * n)), n - 1)
    hi = max(int(math.ceil(percentile_high * n)), lo + 1)
    return logl.sort(dim=1).values[:, lo:hi].mean(dim=1)


class AutoExposure(nn.Module):
    """Meter the scene, adapt over time, and expose: (B, 3, H, W) -> (B, 3, H, W).

    Args:
        key: target middle-grey value the metered luminance is mapped to (0.18).
        min_ev, max_ev: clamps on the resulting exposure (stops).
        compensation: extra exposure in EV added after metering (float or (B,)).
        metering: ``"average"`` or ``"percentile"`` (see module docstring).
        rate: adaptation speed in 1/s (time constant 1/rate); used when ``dt`` is given.
        enabled: ``False`` returns the input object itself.

    After each call ``last_ev`` holds the applied exposure (B,) in stops.
    """

    def __init__(
        self,
        key: float = 0.18,
        min_ev: float = -16.0,
        max_ev: float = 16.0,
        compensation: float | torch.Tensor = 0.0,
        metering: str = "average",
        percentile_low: float = 0.1,
        percentile_high: float = 0.9,
        rate: float = 1.5,
        enabled: bool = True,
    ):
        super().__init__()
        if not key > 0:
            raise ValueError(f"key: expected a positive float, got {key}")
        if not min_ev <= max_ev:
            raise ValueError(f"min_ev, max_ev: expected min_ev <= max_ev, got {min_ev}, {max_ev}")
        if not rate >= 0:
            raise ValueError(f"rate: expected a non-negative float (1/s), got {rate}")
        if metering not in METERINGS:
            raise ValueError(f"metering: expected one of {METERINGS}, got {metering!r}")
        self.key, self.min_ev, self.max_ev = float(key), float(min_ev), float(max_ev)
        self.compensation, self.metering = compensation, metering
        self.percentile_low, self.percentile_high = float(percentile_low), float(percentile_high)
        self.rate, self.enabled = float(rate), enabled
        self.register_buffer("adapted_log2_lum", torch.empty(0), persistent=False)
        self.last_ev: torch.Tensor | None = None

    def reset(self) -> None:
        """Forget the adaptation state: the next frame is metered without lag."""
        self.adapted_log2_lum = torch.empty(0, device=self.adapted_log2_lum.device)

    def target_ev(self, log2_lum: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """Exposure (B,) in stops that maps a scene of log2-luminance ``log2_lum`` to key."""
        comp = per_sample("compensation", self.compensation, x.to(log2_lum.dtype)).reshape(-1)
        ev = math.log2(self.key) - log2_lum + comp
        return ev.clamp(self.min_ev, self.max_ev)

    def forward(self, x: torch.Tensor, dt: float | torch.Tensor | None = None) -> torch.Tensor:
        """Expose ``x`` (B, 3, H, W) linear HDR by the metered, adapted EV.

        ``dt``: frame time in seconds (float or (B,)); ``None`` = no temporal adaptation
        (the state is still updated). The first frame after :meth:`reset` (or a batch size
        change) uses the metered value directly.
        """
        if not self.enabled:
            return x
        x = check_image("x", x, 3)
        xc = x.to(compute_dtype(x))
        measured = metered_log2_luminance(
            xc, self.metering, self.percentile_low, self.percentile_high
        )
        prev = self.adapted_log2_lum
        if dt is None or prev.shape != measured.shape:
            adapted = measured
        else:
            dt_t = per_sample("dt", dt, xc).reshape(-1)
            if bool((dt_t < 0).any()):
                raise ValueError("dt: frame time must be >= 0 seconds")
            alpha = 1.0 - torch.exp(-self.rate * dt_t)
            prev = prev.to(device=measured.device, dtype=measured.dtype)
            adapted = prev + (measured - prev) * alpha
        self.adapted_log2_lum = adapted.detach()
        ev = self.target_ev(adapted, xc)
        self.last_ev = ev.detach()
        return finish_low_precision(xc * torch.exp2(ev).reshape(-1, 1, 1, 1), x.dtype)
