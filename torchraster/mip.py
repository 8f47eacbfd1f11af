"""Mip pyramids and level sampling: the lookups that :mod:`torchraster.texture` (nearest,
bilinear, trilinear) and :mod:`torchraster.anisotropic` share (conventions: the
:mod:`torchraster.texture` docstring; both import this module, neither the other's
internals).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import torch
import torch.nn.functional as F

from torchraster._validate import check_tensor
from torchraster.numerics import grid_sample

ADDRESS_MODES = ("wrap", "clamp", "mirror")

#: Floor on the squared screen-space footprint ``rho**2`` (texels per pixel, squared) before
#: ``log2``: lod >= -20, far below level 0 where it is clamped anyway. Keeps the lod and its
#: gradient finite for zero UV derivatives (the clamp then gives a zero gradient).
LOD_RHO2_FLOOR: float = 2.0**-40


def mip_sizes(height: int, width: int) -> list[tuple[int, int]]:
    """Sizes of all mip levels: ``max(1, floor(size / 2**k))`` per axis until 1x1."""
    sizes = [(height, width)]
    while sizes[-1] != (1, 1):
        h, w = sizes[-1]
        sizes.append((max(1, h // 2), max(1, w // 2)))
    return sizes


def build_mip_pyramid(
    texture: torch.Tensor, *, pyramid: Literal["box", "gaussian"] = "box"
) -> list[torch.Tensor]:
    """Mip pyramid of a ``(B, C, Ht, Wt)`` texture, level 0 first, down to 1x1.

    ``pyramid="box"`` averages (``adaptive_avg_pool2d``); ``"gaussian"`` uses
    ``kornia.geometry.transform.pyrdown`` (Gaussian 5x5 blur then 2x decimation) while
    both sides are >= 2, and box for the last thin levels. Differentiable.
    """
    check_tensor("texture", texture, (None, None, "Ht", "Wt"), floating=True)
    if pyramid not in ("box", "gaussian"):
        raise ValueError(f"pyramid: expected 'box' or 'gaussian', got {pyramid!r}")
    sizes = mip_sizes(texture.shape[-2], texture.shape[-1])
    levels = [texture]
    for h, w in sizes[1:]:
        prev = levels[-1]
        if pyramid == "gaussian" and min(prev.shape[-2:]) >= 4:
            from kornia.geometry.transform import pyrdown

            nxt = pyrdown(prev, border_type="reflect")
            if nxt.shape[-2:] != (h, w):  # defensive: keep the OpenGL sizes
                nxt = F.adaptive_avg_pool2d(nxt, (h, w))
        else:
            nxt = F.adaptive_avg_pool2d(prev, (h, w))
        levels.append(nxt)
    return levels


def compute_lod(
    duv_dx: torch.Tensor,
    duv_dy: torch.Tensor,
    size: tuple[int, int],
    lod_bias: float | torch.Tensor = 0.0,
) -> torch.Tensor:
    """OpenGL level of detail ``log2(max(|duv_dx * size|, |duv_dy * size|)) + lod_bias``.

    Args:
        duv_dx, duv_dy: ``(B, 2, H, W)`` UV derivatives per pixel (UV units / pixel).
        size: ``(Ht, Wt)`` of mip level 0 in texels (u is scaled by Wt, v by Ht).
        lod_bias: added to the lod (float or tensor broadcastable to ``(B, 1, H, W)``).

    Returns:
        ``(B, 1, H, W)`` unclamped lod (level units).
    """
    ht, wt = size
    scale = duv_dx.new_tensor([wt, ht]).view(1, 2, 1, 1)
    rx = ((duv_dx * scale) ** 2).sum(1, keepdim=True)
    ry = ((duv_dy * scale) ** 2).sum(1, keepdim=True)
    rho2 = torch.maximum(rx, ry).clamp_min(LOD_RHO2_FLOOR)
    return 0.5 * torch.log2(rho2) + lod_bias


# ----------------------------------------------------------------------------- sampling


def address_pair(address: str | Sequence[str]) -> tuple[str, str]:
    """``(mode_u, mode_v)`` from one address mode or a pair of them (checked)."""
    pair = (address, address) if isinstance(address, str) else tuple(address)
    if len(pair) != 2 or any(a not in ADDRESS_MODES for a in pair):
        raise ValueError(
            f"address: expected one of {ADDRESS_MODES} or a (u, v) pair of them, got {address!r}"
        )
    return pair  # type: ignore[return-value]


def remap_address(t: torch.Tensor, mode: str) -> torch.Tensor:
    """Map a texture coordinate (any shape) into [0, 1] for the address mode ``"wrap"``,
    ``"mirror"`` or ``"clamp"`` (derivative +-1 or 0); same shape."""
    if mode == "wrap":
        return t - torch.floor(t)
    if mode == "mirror":  # triangle wave of period 2 (GL_MIRRORED_REPEAT)
        return 1.0 - (t - 2.0 * torch.floor(0.5 * t) - 1.0).abs()
    return t.clamp(0.0, 1.0)


def pad_texture(tex: torch.Tensor, mode_u: str, mode_v: str) -> torch.Tensor:
    """Pad a texture by one texel per side for :func:`sample_padded`.

    Args:
        tex: ``(B, C, h, w)`` texture.
        mode_u, mode_v: address mode per axis: ``"wrap"`` pads circularly, ``"clamp"`` /
            ``"mirror"`` copy the edge.

    Returns:
        ``(B, C, h + 2, w + 2)``.
    """
    tex = F.pad(tex, (1, 1, 0, 0), mode="circular" if mode_u == "wrap" else "replicate")
    return F.pad(tex, (0, 0, 1, 1), mode="circular" if mode_v == "wrap" else "replicate")


def sample_level(
    tex: torch.Tensor, u: torch.Tensor, v: torch.Tensor, mode: str, address: tuple[str, str]
) -> torch.Tensor:
    """Sample one level: tex ``(B, C, h, w)`` or ``(1, C, h, w)``, u, v ``(B, H, W)`` ->
    ``(B, C, H, W)``. A batch-1 texture is sampled once for all ``B * H`` rows."""
    return sample_padded(pad_texture(tex, *address), u, v, mode, address)


def sample_padded(
    padded: torch.Tensor, u: torch.Tensor, v: torch.Tensor, mode: str, address: tuple[str, str]
) -> torch.Tensor:
    """Bilinear / nearest lookups in a texture padded by :func:`pad_texture` (pad once,
    sample many times).

    Args:
        padded: ``(B, C, h + 2, w + 2)`` or ``(1, C, h + 2, w + 2)`` (shared by the batch).
        u, v: ``(B, H, W)`` texture coordinates (v = 0 at the bottom row, glTF flips
            handled by the loader).
        mode: ``"bilinear"`` or ``"nearest"``.
        address: ``(mode_u, mode_v)`` as given to :func:`pad_texture`.

    Returns:
        ``(B, C, H, W)``.
    """
    h, w = padded.shape[-2] - 2, padded.shape[-1] - 2
    b = u.shape[0]
    tex = padded
    x = remap_address(u, address[0]) * w - 0.5  # continuous texel index, centres at integers
    y = (1.0 - remap_address(v, address[1])) * h - 0.5
    grid = torch.stack((2.0 * (x + 1.0) / (w + 1) - 1.0, 2.0 * (y + 1.0) / (h + 1) - 1.0), -1)
    if tex.shape[0] == 1 and b > 1:
        flat = grid.reshape(1, b * grid.shape[1], grid.shape[2], 2)
        out = grid_sample(padded, flat, mode=mode, padding_mode="border", align_corners=True)
        return out.reshape(tex.shape[1], b, *grid.shape[1:3]).transpose(0, 1)
    if b == 1 and tex.shape[0] > 1:  # one set of coordinates for a batch of textures
        grid = grid.expand(tex.shape[0], -1, -1, -1)
    return grid_sample(padded, grid, mode=mode, padding_mode="border", align_corners=True)


def sample_levels(
    levels: Sequence[torch.Tensor],
    u: torch.Tensor,
    v: torch.Tensor,
    lod: torch.Tensor,
    address: tuple[str, str],
    padded: Sequence[torch.Tensor] | None = None,
) -> torch.Tensor:
    """Trilinear: hat-weighted sum of bilinear samples of the levels around ``lod``.

    Args:
        levels: mip levels, each ``(B or 1, C, h_k, w_k)``.
        u, v: ``(B, H, W)`` texture coordinates.
        lod: ``(B, 1, H, W)`` level of detail, clamped to ``[0, L - 1]``.
        address: ``(mode_u, mode_v)``.
        padded: the levels already padded by :func:`pad_texture` for ``address`` (e.g.
            kept by :class:`MipTexture`), or None to pad the levels used here.

    Returns:
        ``(B, C, H, W)``. Each level is sampled only at the pixels that give it a
    non-zero weight (gathered, then scattered back with ``index_add``), so the cost is
    two bilinear lookups a pixel however many levels the image spans.
    """
    top = len(levels) - 1
    lod = lod.clamp(0.0, float(top))
    b, h, w = u.shape
    c = levels[0].shape[1]
    shared = levels[0].shape[0] == 1
    uf = u.reshape(1, 1, -1) if shared else u.reshape(b, 1, -1)
    vf = v.reshape(1, 1, -1) if shared else v.reshape(b, 1, -1)
    lf = lod.reshape(1, -1) if shared else lod.reshape(b, -1)
    npix = lf.shape[1]
    out = lf.new_zeros(lf.shape[0], c, npix)
    if npix == 0:  # nothing to sample (e.g. no covered pixel in the frame)
        return out.reshape(c, b, h, w).transpose(0, 1) if shared else out.reshape(b, c, h, w)
    lo = int(math.floor(float(lod.detach().min())))
    hi = min(top, int(math.ceil(float(lod.detach().max()))))
    for k in range(lo, hi + 1):
        wk = (1.0 - (lf - k).abs()).clamp_min(0.0)  # (B', P)
        used = (wk > 0).any(0)
        if not bool(used.any()):
            continue
        tex = padded[k] if padded is not None else pad_texture(levels[k], *address)
        if bool(used.all()):
            s = sample_padded(tex, uf, vf, "bilinear", address)[:, :, 0]  # (B', C, P)
            out = out + s * wk[:, None]
            continue
        idx = used.nonzero().squeeze(1)
        s = sample_padded(tex, uf[..., idx], vf[..., idx], "bilinear", address)[:, :, 0]
        out = out.index_add(2, idx, s * wk[:, None, idx])
    if shared:
        return out.reshape(c, b, h, w).transpose(0, 1)
    return out.reshape(b, c, h, w)


__all__ = ["ADDRESS_MODES", "LOD_RHO2_FLOOR", "address_pair", "build_mip_pyramid", "compute_lod",
           "mip_sizes", "pad_texture", "remap_address", "sample_levels", "sample_padded"]
