"""Separable Gaussian blur as two depthwise ``conv2d`` passes, plus shared post helpers.

Why not ``kornia.filters.gaussian_blur2d``: on CPU kornia 0.9 takes a fast sliced-
accumulation path only when the input does not require grad; with grad it falls back to
``filter2d_separable``, which is the same depthwise ``conv2d`` pair (groups=C, a 1xK then a
Kx1 pass) as here plus per-call checks. ``scripts/bench_post.py`` times forward+backward on
8x3x512x512 with the calls alternated: tied (kornia / conv2d = 0.99 for sigma 2 and 5 in
a paired run; docs/benchmarks.md). This module is kept for training use: never slower
with grad, identical output (``tests/test_post_blur.py`` checks it against kornia and a
brute-force 2-D convolution), and independent of kornia's internal dispatch.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .._validate import check_tensor
from ..numerics import compute_dtype, finish_low_precision

#: Truncate the Gaussian at this many sigmas (kernel radius = ceil(TRUNCATE * sigma)); the
#: tail beyond 3 sigma holds 0.27 % of the mass and the kernel is renormalized to sum to 1.
TRUNCATE = 3.0

#: Border modes accepted by the blur (``torch.nn.functional.pad`` names). ``replicate``
#: (clamp-to-edge, like a GPU sampler) works for any image size; ``reflect`` needs
#: H, W > radius.
BORDERS = ("replicate", "reflect", "constant", "circular")


def check_image(name: str, x: object, channels: int | None = None) -> torch.Tensor:
    """Validate a ``(B, C, H, W)`` floating image (``C == channels`` when given)."""
    return check_tensor(name, x, ("B", channels if channels else "C", "H", "W"), floating=True)


def per_sample(name: str, value: object, x: torch.Tensor) -> torch.Tensor:
    """A float, 0-d, ``(1,)`` or ``(B,)`` parameter as a ``(B, 1, 1, 1)`` tensor like ``x``.

    Keeps the autograd graph of a tensor ``value`` (so gradients reach e.g. an exposure or
    a focus distance). Raises ``TypeError``/``ValueError`` naming ``name`` otherwise.
    """
    b = x.shape[0]
    if isinstance(value, bool) or not isinstance(value, (int, float, torch.Tensor)):
        raise TypeError(f"{name}: expected a float or a (B,) tensor, got {type(value).__name__}")
    if isinstance(value, torch.Tensor):
        if not value.is_floating_point():
            value = value.to(x.dtype)
        if value.dim() > 1 or (value.dim() == 1 and value.shape[0] not in (1, b)):
            raise ValueError(
                f"{name}: expected a float or a tensor of shape ({b},), got {tuple(value.shape)}"
            )
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"{name}: must be finite")
        return value.to(device=x.device, dtype=x.dtype).reshape(-1, 1, 1, 1).expand(b, 1, 1, 1)
    if not math.isfinite(float(value)):
        raise ValueError(f"{name}: must be finite, got {value}")
    return torch.full((b, 1, 1, 1), float(value), device=x.device, dtype=x.dtype)


def gaussian_kernel1d(
    sigma: float, *, device: torch.device | None = None, dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """Normalized 1-D Gaussian taps ``(2r+1,)`` with ``r = ceil(TRUNCATE * sigma)``.

    ``sigma`` in pixels, > 0. Same sampling as kornia's ``get_gaussian_kernel1d`` (point
    samples of exp(-x^2 / 2 sigma^2) at integer offsets, renormalized).
    """
    if not sigma > 0:
        raise ValueError(f"sigma: expected a positive float, got {sigma}")
    r = max(1, math.ceil(TRUNCATE * sigma))
    t = torch.arange(-r, r + 1, device=device, dtype=dtype)
    k = torch.exp(-(t * t) / (2.0 * sigma * sigma))
    return k / k.sum()


def separable_filter(
    x: torch.Tensor, kx: torch.Tensor, ky: torch.Tensor, border: str = "replicate"
) -> torch.Tensor:
    """Correlate every channel of ``x`` (B, C, H, W) with ``kx`` along W, then ``ky`` along H.

    ``kx``, ``ky``: odd-length 1-D kernels. Depthwise ``conv2d`` (groups=C), "same" size.
    """
    c = x.shape[1]
    rx, ry = kx.shape[0] // 2, ky.shape[0] // 2
    wx = kx.to(x.dtype).reshape(1, 1, 1, -1).expand(c, 1, 1, -1)
    wy = ky.to(x.dtype).reshape(1, 1, -1, 1).expand(c, 1, -1, 1)
    x = F.conv2d(F.pad(x, (rx, rx, 0, 0), mode=border), wx, groups=c)
    return F.conv2d(F.pad(x, (0, 0, ry, ry), mode=border), wy, groups=c)


def gaussian_blur(x: torch.Tensor, sigma: float, border: str = "replicate") -> torch.Tensor:
    """Gaussian blur of ``x`` (B, C, H, W) with standard deviation ``sigma`` pixels.

    ``sigma <= 0`` returns ``x`` itself. Kernel radius ``ceil(3 sigma)``; ``border`` is a
    ``torch.nn.functional.pad`` mode (default clamp-to-edge). Output (B, C, H, W).
    """
    x = check_image("x", x)
    if border not in BORDERS:
        raise ValueError(f"border: expected one of {BORDERS}, got {border!r}")
    if sigma <= 0:
        return x
    k = gaussian_kernel1d(float(sigma), device=x.device, dtype=compute_dtype(x))
    return finish_low_precision(separable_filter(x.to(k.dtype), k, k, border), x.dtype)


class GaussianBlur(nn.Module):
    """``nn.Module`` wrapper of :func:`gaussian_blur` (identity when ``enabled=False``)."""

    def __init__(self, sigma: float = 1.0, border: str = "replicate", enabled: bool = True):
        super().__init__()
        self.sigma, self.border, self.enabled = float(sigma), border, enabled

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) -> (B, C, H, W) blurred; returns ``x`` itself when disabled."""
        if not self.enabled:
            return x
        return gaussian_blur(x, self.sigma, self.border)
