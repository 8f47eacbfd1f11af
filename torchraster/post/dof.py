"""Depth of field: thin-lens circle of confusion and a blend of a few Gaussian blur levels.

Circle of confusion (thin lens; e.g. Potmesil & Chakravarty 1981, or any optics text): for
an object at distance z with the lens focused at z_f, focal length f and aperture diameter
A = f / N, the blur-spot diameter on the sensor is

    c = A * f / (z_f - f) * (z - z_f) / z        (signed: c < 0 in front of the focus plane)

converted to pixels by ``c_mm / sensor_width_mm * W``. Depth and focus distance are in
metres (scene units), focal length and sensor width in millimetres.

Blur: kornia's Gaussian blur has no per-pixel sigma, so the image is blurred at ``levels``
fixed sigmas sigma_k = k / (levels - 1) * max_coc / 4 (level 0 = sharp; a disk of diameter
c has per-axis standard deviation c / 4) and every pixel blends the two levels bracketing
its own sigma |c| / 4 linearly. That is a per-pixel *gather*.

Layers (the usual near/far split of real-time DOF, e.g. Jimenez 2014, Sousa 2013):
- far/focus layer: blur levels of (x * w_far) normalized by the blurred w_far, where
  w_far = clamp(c / COC_RAMP_PX, 0, 1) is 0 for in-focus and near pixels. So a blurry
  background never gathers colour from a sharp foreground object: no halo around in-focus
  foreground objects. In-focus pixels (sigma 0) keep their own colour.
- near layer: near pixels (a = clamp(-c / COC_RAMP_PX, 0, 1)) must bleed over what lies
  behind them. Their CoC is dilated (max filter of radius max_coc / 2, then a Gaussian of
  half that radius), and every pixel gathers premultiplied near colour and near coverage
  alpha with that dilated sigma; out = near_premult + (1 - alpha) * far_layer.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .._validate import check_tensor
from ..numerics import compute_dtype, finish_low_precision
from .blur import check_image, gaussian_blur, per_sample

#: Depth floor (metres) before dividing by depth: 1 micrometre, far below any near plane.
DEPTH_FLOOR = 1e-6
#: Width (pixels of CoC diameter) of the ramps that classify a pixel as in focus / far /
#: near. Below one pixel of CoC a pixel counts as (partly) in focus.
COC_RAMP_PX = 1.0
#: Far-layer weights below this count as "nothing to gather": keep the sharp pixel.
WEIGHT_FLOOR = 1e-6


def circle_of_confusion(
    depth: torch.Tensor,
    focus_distance: float | torch.Tensor,
    focal_length_mm: float | torch.Tensor = 50.0,
    f_number: float | torch.Tensor = 2.8,
    sensor_width_mm: float = 36.0,
) -> torch.Tensor:
    """Signed thin-lens CoC diameter in pixels: depth (B, 1, H, W) metres -> (B, 1, H, W).

    Negative = near field (closer than the focus distance). Focus distance in metres,
    focal length and sensor width in mm; the per-sample parameters may be (B,) tensors.
    ``depth`` may hold +inf (empty pixels/sky: CoC of an object at infinity).
    """
    depth = check_tensor("depth", depth, ("B", 1, "H", "W"), floating=True)
    if bool(torch.isnan(depth).any()):
        raise ValueError("depth: contains NaN")
    if not sensor_width_mm > 0:
        raise ValueError(f"sensor_width_mm: expected > 0, got {sensor_width_mm}")
    zf = per_sample("focus_distance", focus_distance, depth)
    f = per_sample("focal_length_mm", focal_length_mm, depth) * 1e-3  # metres
    n = per_sample("f_number", f_number, depth)
    if bool((f <= 0).any()) or bool((n <= 0).any()):
        raise ValueError("focal_length_mm, f_number: expected > 0")
    if bool((zf <= f).any()):
        raise ValueError("focus_distance: must exceed the focal length (both as metres)")
    z = depth.clamp(min=DEPTH_FLOOR)
    c_m = (f / n) * f / (zf - f) * (1.0 - zf / z)  # sensor metres; (1 - zf/z) is inf-safe
    return c_m * (1e3 / sensor_width_mm * depth.shape[-1])


def _level_weights(sigma: torch.Tensor, sigmas: list[float]) -> list[torch.Tensor]:
    """Hat-function weights (linear interpolation in sigma) of every blur level."""
    t = sigma / sigmas[-1] * (len(sigmas) - 1)
    return [(1.0 - (t - k).abs()).clamp(min=0.0) for k in range(len(sigmas))]


def near_sigma(coc: torch.Tensor, max_coc: float) -> torch.Tensor:
    """Dilated, smoothed near-field blur sigma (px): signed CoC (B,1,H,W) -> (B,1,H,W).

    Max filter of radius ceil(max_coc / 2) (the largest blur radius) of the near sigma
    clamp(-c, 0, max_coc) / 4, then a Gaussian of sigma = radius / 2 (clamp-to-edge).
    """
    s = (-coc).clamp(0.0, max_coc) / 4.0
    r = max(1, math.ceil(max_coc / 2.0))
    s = F.max_pool2d(F.pad(s, (r, r, r, r), mode="replicate"), 2 * r + 1, stride=1)
    return gaussian_blur(s, r / 2.0)


def depth_of_field(
    x: torch.Tensor, coc: torch.Tensor, max_coc: float = 16.0, levels: int = 12
) -> torch.Tensor:
    """Blur ``x`` (B, C, H, W) by the signed CoC diameters ``coc`` (B, 1, H, W) in pixels.

    ``|coc|`` is clamped to ``max_coc``; ``levels`` (>= 2) blur levels are blended.
    Output (B, C, H, W). See the module docstring for the near/far layers.
    """
    c = x.shape[1]
    coc = coc.clamp(-max_coc, max_coc)
    sigmas = [k / (levels - 1) * max_coc / 4.0 for k in range(levels)]
    w_far = (coc / COC_RAMP_PX).clamp(0.0, 1.0)
    a_near = (-coc / COC_RAMP_PX).clamp(0.0, 1.0)
    stack = torch.cat([x * w_far, w_far, x * a_near, a_near], dim=1)
    wf = _level_weights(coc.abs() / 4.0, sigmas)
    wn = _level_weights(near_sigma(coc, max_coc), sigmas)
    far = wf[0] * x
    near = wn[0] * stack[:, c + 1 :]
    for k in range(1, levels):
        if not bool(((wf[k] > 0) | (wn[k] > 0)).any()):
            continue  # no pixel uses this blur level (its weights and their grads are 0)
        blurred = gaussian_blur(stack, sigmas[k])
        num, den = blurred[:, :c], blurred[:, c : c + 1]
        ok = den > WEIGHT_FLOOR
        far_k = torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), x)
        far = far + wf[k] * far_k
        near = near + wn[k] * blurred[:, c + 1 :]
    near_premult, alpha = near[:, :c], near[:, c:].clamp(0.0, 1.0)
    return near_premult + (1.0 - alpha) * far


class DepthOfField(nn.Module):
    """Thin-lens depth of field: (B, C, H, W) linear HDR + depth (B, 1, H, W) -> (B, C, H, W).

    Args:
        focus_distance: metres (float or (B,)).
        focal_length_mm, f_number: lens (float or (B,)); aperture diameter = f / N.
        sensor_width_mm: sensor width the image width maps to (36 = full frame).
        max_coc: largest CoC diameter in pixels (larger ones are clamped).
        levels: number of blur levels (>= 2); more = closer to a per-pixel Gaussian
            (default 12: the cheapest within 1 % mean error of the brute-force gather at
            max_coc 16 in scripts/bench_post.py).
        enabled: ``False`` returns the input object itself.
    """

    def __init__(
        self,
        focus_distance: float | torch.Tensor = 5.0,
        focal_length_mm: float | torch.Tensor = 50.0,
        f_number: float | torch.Tensor = 2.8,
        sensor_width_mm: float = 36.0,
        max_coc: float = 16.0,
        levels: int = 12,
        enabled: bool = True,
    ):
        super().__init__()
        if not max_coc > 0:
            raise ValueError(f"max_coc: expected > 0 pixels, got {max_coc}")
        if int(levels) < 2:
            raise ValueError(f"levels: expected an int >= 2, got {levels}")
        self.focus_distance, self.focal_length_mm, self.f_number = (
            focus_distance, focal_length_mm, f_number
        )
        self.sensor_width_mm, self.max_coc, self.levels = (
            float(sensor_width_mm), float(max_coc), int(levels)
        )
        self.enabled = enabled

    def forward(
        self,
        x: torch.Tensor,
        depth: torch.Tensor,
        focus_distance: float | torch.Tensor | None = None,
        f_number: float | torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Blur ``x`` by the CoC of ``depth`` (metres, +inf allowed); per-call overrides
        of ``focus_distance`` / ``f_number`` (float or (B,)). Identity when disabled."""
        if not self.enabled:
            return x
        x = check_image("x", x)
        depth = check_tensor("depth", depth, (x.shape[0], 1, x.shape[2], x.shape[3]), floating=True)
        dt = compute_dtype(x)
        coc = circle_of_confusion(
            depth.to(dt),
            self.focus_distance if focus_distance is None else focus_distance,
            self.focal_length_mm,
            self.f_number if f_number is None else f_number,
            self.sensor_width_mm,
        )
        out = depth_of_field(x.to(dt), coc, self.max_coc, self.levels)
        return finish_low_precision(out, x.dtype)
