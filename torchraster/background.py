"""Background images: any picture fitted to the frame and composited under the scene.

    bg = load_background("studio.jpg")                 # (3, h, w) linear RGB
    img = fit_background(bg, (H, W), fit="contain")    # (1, 3, H, W)
    renderer = Renderer((H, W), background=BackgroundSettings(image=bg, fit="cover"))

Fits keep the aspect ratio (except ``stretch``) and centre the image: ``cover`` scales it
to fill the frame and crops the overflow, ``contain`` scales it to fit inside and fills the
bars with the background colour (letterbox / pillarbox), ``stretch`` scales each axis to the
frame. Frame pixel centre ``(j + 0.5, i + 0.5)`` maps to the source point
``x = (j + 0.5 - W / 2) / s_x + w / 2`` (likewise y) and is sampled bilinearly; images
shrunk by 2x or more are first box-filtered by the integer part of the factor (so fine
detail averages instead of aliasing). Bar pixels take the background colour weighted by the
part of the pixel outside the image (exact box coverage), so bar edges are antialiased.
Differentiable with respect to the image (bilinear weights).

The renderer composites the fitted image where the scene lets light through:
``image = radiance + transmittance * background`` (transmittance ``1 - alpha``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F

from ._validate import check_resolution, check_tensor

#: Ways to fit an image to the frame.
FITS = ("cover", "contain", "stretch")
#: File suffixes read as linear HDR radiance (:func:`torchraster.hdr_io.read_hdr`); any
#: other image is read as 8-bit sRGB and decoded to linear.
HDR_SUFFIXES = (".hdr", ".pic", ".exr")


def load_background(path: str | Path) -> torch.Tensor:
    """Read a background image as linear RGB.

    Args:
        path: a PNG / JPEG / ... file (sRGB, decoded to linear with the IEC 61966-2-1
            transfer function; alpha dropped) or a ``.hdr`` / ``.exr`` file (linear
            radiance, as is).

    Returns:
        ``(3, h, w)`` float32, row 0 = top of the image.

    Raises:
        FileNotFoundError: naming the file.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: file not found")
    if p.suffix.lower() in HDR_SUFFIXES:
        from .hdr_io import read_hdr

        return read_hdr(p)
    from kornia.color import rgb_to_linear_rgb

    from .io import load_texture

    codes = load_texture(p, alpha=False)
    return rgb_to_linear_rgb(codes.to(torch.float32) / 255.0)


def fit_scale(source: tuple[int, int], frame: tuple[int, int], fit: str) -> tuple[float, float]:
    """Scale factors ``(s_y, s_x)`` from source pixels ``(h, w)`` to frame pixels ``(H, W)``."""
    (h, w), (hh, ww) = source, frame
    if fit == "stretch":
        return hh / h, ww / w
    s = max(hh / h, ww / w) if fit == "cover" else min(hh / h, ww / w)
    return s, s


def _axis(n_frame: int, n_source: int, scale: float, pool: int, like: torch.Tensor
          ) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised sample coordinates (grid_sample, align_corners=False) along one axis of
    a source pooled by ``pool``, and each frame pixel's coverage by the image."""
    j = torch.arange(n_frame, dtype=like.dtype, device=like.device)
    x = (j + 0.5 - n_frame / 2) / scale + n_source / 2  # source pixels
    pooled = math.ceil(n_source / pool)
    grid = 2 * (x / pool) / pooled - 1
    lo, hi = n_frame / 2 - n_source * scale / 2, n_frame / 2 + n_source * scale / 2
    cover = (torch.minimum(j + 1, j.new_tensor(hi)) - torch.maximum(j, j.new_tensor(lo)))
    return grid, cover.clamp(0.0, 1.0)


def fit_background(
    image: torch.Tensor,
    resolution: tuple[int, int] | int,
    fit: str = "cover",
    fill: Sequence[float] | torch.Tensor = (0.0, 0.0, 0.0),
) -> torch.Tensor:
    """Fit an image to a frame (see the module docstring for the geometry).

    Args:
        image: ``(3, h, w)`` or ``(B, 3, h, w)`` linear RGB.
        resolution: ``(H, W)`` of the frame, or an int for a square.
        fit: ``"cover"``, ``"contain"`` or ``"stretch"``.
        fill: linear RGB of the bars ``contain`` leaves (3 floats or a ``(3,)`` tensor).

    Returns:
        ``(B, 3, H, W)`` (B = 1 for an unbatched image), in the image's dtype.

    Example:
        >>> fit_background(torch.rand(3, 40, 80), (32, 32), "contain").shape
        torch.Size([1, 3, 32, 32])
    """
    if fit not in FITS:
        raise ValueError(f"fit: expected one of {FITS}, got {fit!r}")
    if isinstance(image, torch.Tensor) and image.dim() == 3:
        image = image[None]
    check_tensor("image", image, ("B", 3, "h", "w"), floating=True, finite=True)
    hh, ww = check_resolution(resolution)
    h, w = image.shape[-2:]
    sy, sx = fit_scale((h, w), (hh, ww), fit)
    ky, kx = max(1, math.floor(1 / sy)), max(1, math.floor(1 / sx))
    src = image
    if ky > 1 or kx > 1:  # box prefilter: pad to whole blocks, then average
        src = F.pad(src, (0, -w % kx, 0, -h % ky), mode="replicate")
        src = F.avg_pool2d(src, (ky, kx))
    gy, cy = _axis(hh, h, sy, ky, image)
    gx, cx = _axis(ww, w, sx, kx, image)
    grid = torch.stack(torch.meshgrid(gy, gx, indexing="ij")[::-1], -1)  # (H, W, 2): x, y
    out = F.grid_sample(src, grid[None].expand(src.shape[0], hh, ww, 2), mode="bilinear",
                        padding_mode="border", align_corners=False)
    if fit == "contain":
        coverage = cy[:, None] * cx[None, :]  # (H, W)
        fill_t = torch.as_tensor(fill, dtype=out.dtype, device=out.device).view(1, 3, 1, 1)
        out = out * coverage + fill_t * (1 - coverage)
    return out


__all__ = ["FITS", "HDR_SUFFIXES", "fit_background", "fit_scale", "load_background"]
