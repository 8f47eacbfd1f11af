"""Bloom on linear HDR: soft-knee bright pass, 13-tap downsample pyramid, tent upsample.

Following Jimenez 2014, "Next Generation Post Processing in Call of Duty: Advanced
Warfare" (SIGGRAPH course): the bright pass is downsampled level by level with the 13-tap
filter (five overlapping 2x2 boxes read by 13 bilinear taps; centre box weight 0.5, four
corner boxes 0.125 each), the first level as a "Karis average" (Karis 2013: texels weighted by
1 / (1 + luma), against fireflies). Each level is blurred by a Gaussian of ``radius`` level
pixels, then the levels are upsampled (bilinear x2 followed by the 3x3 tent [1 2 1]/4) and
added from the coarsest up. The result is added to the input:
``out = x + intensity * bloom / levels`` (every level carries the bright energy once, so
dividing by ``levels`` makes ``bloom / levels`` an average of blurs).

Variance bookkeeping (per axis, full-resolution pixels): a 13-tap step from level k-1 to
k adds 1.75 * 4^(k-1), a bilinear-x2 + tent step back adds (0.75 + 0.5) * 4^(k-1), the
blur adds radius^2 * 4^l. So level l approximates a Gaussian of
sigma_l^2 = (4^l - 1) + radius^2 * 4^l  (tested against brute-force Gaussians).

The soft knee (as in Unity's post-processing stack) ramps the bright pass in quadratically
over [threshold - k, threshold + k], k = knee * threshold:
w = max(min(max(b - threshold + k, 0), 2k)^2 / (4k), b - threshold) / max(b, BRIGHT_FLOOR),
b = max over channels.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ..numerics import compute_dtype, finish_low_precision
from .blur import (
    check_image,
    gaussian_blur,
    per_sample,
    separable_filter,
)

#: Brightness floor of the bright-pass division (linear units): below it the contribution
#: factor's denominator is clamped, so black and denormal pixels stay finite.
BRIGHT_FLOOR = 1e-5
#: Smallest knee half-width (linear units), avoids 0/0 for threshold = 0 or knee = 0.
KNEE_FLOOR = 1e-5

# 13 taps: (dy, dx) in source texels from the output centre; and the 5 boxes (tap names).
_TAPS = {
    "a": (-2, -2), "b": (-2, 0), "c": (-2, 2), "d": (0, -2), "e": (0, 0), "f": (0, 2),
    "g": (2, -2), "h": (2, 0), "i": (2, 2), "j": (-1, -1), "k": (-1, 1), "l": (1, -1),
    "m": (1, 1),
}
_BOXES = (("jklm", 0.5), ("abde", 0.125), ("bcef", 0.125), ("degh", 0.125), ("efhi", 0.125))


def bright_pass(x: torch.Tensor, threshold: float = 1.0, knee: float = 0.5) -> torch.Tensor:
    """Soft-knee bright pass: (B, C, H, W) linear HDR -> (B, C, H, W) (see module doc)."""
    x = check_image("x", x)
    if not threshold >= 0 or not knee >= 0:
        raise ValueError(f"threshold, knee: expected >= 0, got {threshold}, {knee}")
    x = x.clamp(min=0.0)
    b = x.amax(dim=1, keepdim=True)
    k = max(threshold * knee, KNEE_FLOOR)
    soft = (b - threshold + k).clamp(0.0, 2.0 * k) ** 2 / (4.0 * k)
    w = torch.maximum(soft, b - threshold) / b.clamp(min=BRIGHT_FLOOR)
    return x * w


def _luma(x: torch.Tensor) -> torch.Tensor:
    if x.shape[1] == 3:
        w = torch.tensor((0.2126, 0.7152, 0.0722), device=x.device, dtype=x.dtype)
        return (x * w.reshape(1, 3, 1, 1)).sum(dim=1, keepdim=True)
    return x.mean(dim=1, keepdim=True)


def downsample13(x: torch.Tensor, karis: bool = False) -> torch.Tensor:
    """13-tap downsample (Jimenez 2014): (B, C, H, W) -> (B, C, ceil(H/2), ceil(W/2)).

    Clamp-to-edge borders. ``karis=True`` is Karis's luminance-weighted average: every
    source texel is weighted by 1 / (1 + luma) and the filter is renormalized by the
    filtered weights (a lone firefly then counts about as much as one texel of value 1;
    a flat image is unchanged). Jimenez applies the weights per 2x2 box instead, which
    leaves a firefly that lies in all five boxes of an output texel unsuppressed.
    """
    if karis:
        w = 1.0 / (1.0 + _luma(x).clamp(min=0.0))
        return downsample13(x * w) / downsample13(w)
    h, w = x.shape[-2:]
    ho, wo = (h + 1) // 2, (w + 1) // 2
    xp = F.pad(x, (2, 2 + w % 2, 2, 2 + h % 2), mode="replicate")
    box = F.avg_pool2d(xp, 2, stride=1)  # box[r, s] = mean of texels (r..r+1, s..s+1)
    taps = {
        n: box[..., dy + 2 : dy + 2 + 2 * ho - 1 : 2, dx + 2 : dx + 2 + 2 * wo - 1 : 2]
        for n, (dy, dx) in _TAPS.items()
    }
    return sum(sum(taps[t] for t in names) * (0.25 * wt) for names, wt in _BOXES)


def upsample_tent(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinear upsample to ``size`` (H, W), then the 3x3 tent [1 2 1]/4 x [1 2 1]/4."""
    up = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
    tent = torch.tensor((0.25, 0.5, 0.25), device=x.device, dtype=x.dtype)
    return separable_filter(up, tent, tent, "replicate")


def max_levels(h: int, w: int) -> int:
    """Deepest pyramid level whose smaller side is still >= 2 pixels."""
    return max(1, int(math.floor(math.log2(max(2, min(h, w))))))


def bloom_levels(
    x: torch.Tensor, levels: int = 5, radius: float = 1.0, karis: bool = True
) -> torch.Tensor:
    """Pyramid blur of an (already bright-passed) image: (B, C, H, W) -> (B, C, H, W).

    Returns the upsampled sum over pyramid levels 1..levels (not divided by ``levels``);
    ``levels`` is capped at :func:`max_levels` for small images.
    """
    levels = min(int(levels), max_levels(*x.shape[-2:]))
    pyr = [x]
    for lvl in range(levels):
        pyr.append(downsample13(pyr[-1], karis=karis and lvl == 0))
    acc = None
    for lvl in range(levels, 0, -1):
        cur = gaussian_blur(pyr[lvl], radius) if radius > 0 else pyr[lvl]
        acc = cur if acc is None else cur + upsample_tent(acc, tuple(cur.shape[-2:]))
    return upsample_tent(acc, tuple(x.shape[-2:]))


class Bloom(nn.Module):
    """HDR bloom: (B, C, H, W) linear -> (B, C, H, W) linear, ``x + intensity * bloom``.

    Args:
        threshold: bright-pass threshold (linear units, >= 0).
        knee: soft-knee width as a fraction of ``threshold`` (0 = hard cut).
        intensity: strength of the added glow (float or per-sample (B,)).
        radius: Gaussian sigma applied at every pyramid level, in that level's pixels
            (default 1.5: the cheapest value within 1 % of the Gaussian-sum reference in
            scripts/bench_post.py; 0 = pure pyramid, ~5 % off).
        levels: number of pyramid levels (capped for small images); more = wider glow.
        karis: Karis average on the first downsample (firefly suppression).
        enabled: ``False`` returns the input object itself.
    """

    def __init__(
        self,
        threshold: float = 1.0,
        knee: float = 0.5,
        intensity: float | torch.Tensor = 0.05,
        radius: float = 1.5,
        levels: int = 5,
        karis: bool = True,
        enabled: bool = True,
    ):
        super().__init__()
        if not threshold >= 0 or not knee >= 0 or not radius >= 0:
            raise ValueError(
                f"threshold, knee, radius: expected >= 0, got {threshold}, {knee}, {radius}"
            )
        if int(levels) < 1:
            raise ValueError(f"levels: expected a positive int, got {levels}")
        self.threshold, self.knee, self.intensity = float(threshold), float(knee), intensity
        self.radius, self.levels = float(radius), int(levels)
        self.karis, self.enabled = karis, enabled

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) linear HDR -> (B, C, H, W) with bloom added (identity if disabled)."""
        if not self.enabled:
            return x
        x = check_image("x", x)
        xc = x.to(compute_dtype(x))
        intensity = per_sample("intensity", self.intensity, xc)
        levels = min(self.levels, max_levels(*x.shape[-2:]))
        bright = bright_pass(xc, self.threshold, self.knee)
        glow = bloom_levels(bright, levels, self.radius, self.karis)
        return finish_low_precision(xc + intensity * glow / levels, x.dtype)
