"""Mip atlas: every level of a texture's mip pyramid, padded, packed into one image.

Trilinear filtering with :class:`~torchraster.texture.MipTexture` samples each level the
image's level of detail spans in its own ``grid_sample`` call (gathering and scattering
the pixels that use it). With all levels side by side in one image, a pixel's two levels
are two points of one ``grid_sample`` call, whatever the spread of the level of detail;
and textures of the same size read with the same UVs (a glTF material's base colour,
metallic-roughness, normal, occlusion and emissive maps) are stacked as channels of one
atlas, so a material costs one lookup. The filtered values are those of
:func:`~torchraster.texture.sample_texture` with ``filter="trilinear"`` (same pyramid,
same padding, same bilinear weights; equal up to float rounding).

Layout: level 0, padded by one texel per side (:func:`~torchraster.texture.pad_texture`),
at the top left; levels 1, 2, ... (each padded) stacked top to bottom in a column to its
right. A bilinear lookup at texel coordinate ``x`` of a padded level reads columns
``floor(x)`` and ``floor(x) + 1`` only, inside the level's own block for every remapped
coordinate, so levels never bleed into each other.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch.autograd.function import once_differentiable

from .numerics import compute_dtype, finish_low_precision, grid_sample
from .texture import (
    address_pair,
    build_mip_pyramid,
    compute_lod,
    mip_sizes,
    pad_texture,
    remap_address,
)

__all__ = ["MipAtlas"]


class MipAtlas:
    """Textures of one size, stacked as channels, their pyramids packed in one padded image.

    Args:
        textures: ``(C_i, Ht, Wt)`` float textures of the same ``Ht x Wt`` (channels are
            concatenated in the given order).
        address: ``"wrap"``, ``"clamp"`` or ``"mirror"``, or a ``(u, v)`` pair.

    Attributes:
        atlas: ``(1, C, Ha, Wa)`` the packed, padded levels.
        channels: the channel count ``C_i`` of each input texture.
    """

    def __init__(self, textures: Sequence[torch.Tensor], *, address="wrap") -> None:
        if not textures:
            raise ValueError("textures: expected at least one texture")
        size = tuple(textures[0].shape[-2:])
        for i, t in enumerate(textures):
            if t.dim() != 3 or tuple(t.shape[-2:]) != size or not t.is_floating_point():
                raise ValueError(f"textures[{i}]: expected a float (C, {size[0]}, {size[1]}) "
                                 f"texture, got {t.dtype} {tuple(t.shape)}")
        self.address = address_pair(address)
        self.channels = [t.shape[0] for t in textures]
        # half-precision textures are stored in float32: the atlas coordinates need more
        # than float16's 11 bits (numerics' policy), and grid_sample's half backward crashes
        tex = torch.cat(list(textures), 0)[None]
        tex = tex.to(compute_dtype(tex))
        levels = [pad_texture(t, *self.address) for t in build_mip_pyramid(tex)]
        h0, w0 = levels[0].shape[-2:]
        col_w = max((t.shape[-1] for t in levels[1:]), default=0)
        height = max(h0, sum(t.shape[-2] for t in levels[1:]))
        atlas = tex.new_zeros(1, tex.shape[1], height, w0 + col_w)
        offsets = [(0, 0)]
        atlas[..., :h0, :w0] = levels[0]
        y = 0
        for t in levels[1:]:
            h, w = t.shape[-2:]
            atlas[..., y:y + h, w0:w0 + w] = t
            offsets.append((y, w0))
            y += h
        # channels last: the C values of a texel are adjacent, so a bilinear lookup touches
        # 4 cache lines instead of 4 C (grid_sample's CPU kernel follows the strides)
        self.atlas = atlas.contiguous(memory_format=torch.channels_last)
        self.size = size
        sizes = mip_sizes(*size)
        # per level: (row offset, column offset, height, width) of the unpadded level
        self._table = torch.tensor([[oy, ox, h, w] for (oy, ox), (h, w) in zip(
            offsets, sizes, strict=True)], dtype=tex.dtype, device=tex.device)

    @property
    def num_levels(self) -> int:
        """Number of mip levels (down to 1x1)."""
        return self._table.shape[0]

    @property
    def nbytes(self) -> int:
        """Bytes of the atlas."""
        return self.atlas.numel() * self.atlas.element_size()

    def sample(self, uv: torch.Tensor, duv_dx: torch.Tensor, duv_dy: torch.Tensor,
               lod_bias: float = 0.0) -> torch.Tensor:
        """Trilinear lookups at N points.

        Differentiable with respect to ``uv``, ``duv_dx``, ``duv_dy`` (through the level
        weights) and the textures (through :attr:`atlas`). Autograd keeps only the inputs:
        the backward recomputes the taps (issue 23, memory), so double backward is not
        supported.

        Args:
            uv: ``(2, N)`` texture coordinates (v up, as :mod:`torchraster.texture`).
            duv_dx, duv_dy: ``(2, N)`` their change per pixel step right / down.
            lod_bias: added to the level of detail.

        Returns:
            ``(C, N)`` filtered values, channels in the order of the textures.
        """
        n = uv.shape[1]
        c = self.atlas.shape[1]
        if n == 0:
            return uv.new_zeros(c, 0)
        return _TrilinearLookup.apply(self.atlas, uv, duv_dx, duv_dy, self._table, self.size,
                                      self.address, float(lod_bias))


def _lookup(atlas: torch.Tensor, uv: torch.Tensor, duv_dx: torch.Tensor, duv_dy: torch.Tensor,
            table: torch.Tensor, size: tuple[int, int], address: tuple[str, str],
            lod_bias: float) -> torch.Tensor:
    """The trilinear lookup of :meth:`MipAtlas.sample` (``(C, N)``), in plain tensor ops:
    run without autograd by the forward of :class:`_TrilinearLookup`, with it by the
    backward."""
    n = uv.shape[1]
    out_dtype = uv.dtype
    dt = compute_dtype(uv, atlas)  # float32 for half-precision lookups
    uv, duv_dx, duv_dy = uv.to(dt), duv_dx.to(dt), duv_dy.to(dt)
    lod = compute_lod(duv_dx[None, :, None], duv_dy[None, :, None], size,
                      lod_bias)[0, 0, 0]  # (N,)
    top = table.shape[0] - 1
    lod = lod.clamp(0.0, float(top))
    k0 = lod.detach().floor()
    frac = lod - k0  # the hat weights of levels k0 and k0 + 1: 1 - frac and frac
    k0 = k0.long()
    k1 = (k0 + 1).clamp_max(top)
    table = table.to(uv.dtype)
    u = remap_address(uv[0], address[0])
    v = 1.0 - remap_address(uv[1], address[1])
    points = []
    for k in (k0, k1):
        oy, ox, h, w = table[k].unbind(1)
        # texel centre coordinates in the padded level (+1: the pad), then the atlas
        points.append(torch.stack((ox + u * w + 0.5, oy + v * h + 0.5), -1))
    grid = torch.cat(points, 0)  # (2N, 2) atlas pixel coordinates
    ha, wa = atlas.shape[-2:]
    scale = grid.new_tensor([2.0 / (wa - 1), 2.0 / (ha - 1)])
    grid = (grid * scale - 1.0)[None, None]  # (1, 1, 2N, 2), align_corners=True
    s = grid_sample(atlas.to(dt), grid, mode="bilinear",
                    padding_mode="border", align_corners=True)[0, :, 0]  # (C, 2N)
    return finish_low_precision(torch.lerp(s[:, :n], s[:, n:], frac[None]), out_dtype)


class _TrilinearLookup(torch.autograd.Function):
    """:func:`_lookup` saving only its inputs for backward, which recomputes the taps
    (indices, weights, texels: ~49 B a covered pixel otherwise kept by autograd) and
    differentiates them. The gradients are those of :func:`_lookup` under autograd; double
    backward is not supported."""

    @staticmethod
    def forward(ctx, atlas, uv, duv_dx, duv_dy, table, size, address, lod_bias):
        ctx.save_for_backward(atlas, uv, duv_dx, duv_dy, table)
        ctx.args = (size, address, lod_bias)
        return _lookup(atlas, uv, duv_dx, duv_dy, table, size, address, lod_bias)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        saved = ctx.saved_tensors
        need = ctx.needs_input_grad[:4]
        inputs = [t.detach().requires_grad_(nd) for t, nd in zip(saved[:4], need, strict=True)]
        wrt = [t for t, nd in zip(inputs, need, strict=True) if nd]
        grads = iter(())
        if wrt:
            with torch.enable_grad():
                out = _lookup(*inputs, saved[4], *ctx.args)
                grads = iter(torch.autograd.grad(out, wrt, grad, allow_unused=True))
        result = [next(grads) if nd else None for nd in need]
        return (*result, None, None, None, None)
