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
import torch.nn.functional as F
from torch.autograd.function import once_differentiable

from .numerics import LOW_PRECISION, compute_dtype, finish_low_precision, grid_sample
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


#: Points a chunk of :meth:`MipAtlas.sample`'s forward evaluates at once: its temporaries
#: (level weights, grid, taps; ~60 B a point) stay bounded (issue 23, memory).
LOOKUP_CHUNK: int = 2**18


def _taps(uv: torch.Tensor, duv_dx: torch.Tensor, duv_dy: torch.Tensor, table: torch.Tensor,
          size: tuple[int, int], address: tuple[str, str], lod_bias: float,
          atlas_size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """The two taps of N trilinear lookups: the weight ``frac`` ``(N,)`` of the upper level
    (the lower one has ``1 - frac``) and the ``(1, 1, 2N, 2)`` ``grid_sample`` grid
    (align_corners=True) of the lower-level taps, then the upper-level ones; in
    :func:`compute_dtype` of ``uv`` (float32 for half precision)."""
    dt = compute_dtype(uv)
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
    ha, wa = atlas_size
    scale = grid.new_tensor([2.0 / (wa - 1), 2.0 / (ha - 1)])
    return frac, (grid * scale - 1.0)[None, None]  # (1, 1, 2N, 2), align_corners=True


class _TrilinearLookup(torch.autograd.Function):
    """The lookup of :meth:`MipAtlas.sample`: ``(C, N)``, the lerp by ``frac`` of the
    bilinear taps of two levels (one ``grid_sample`` call). Saves only its inputs for
    backward, which recomputes the taps (the per-tap indices, weights and texels otherwise
    kept by autograd, ~49 B a pixel at 512², issue 23) and applies the derivatives of
    ``torch.lerp`` and ``grid_sample`` itself. Double backward is not supported."""

    @staticmethod
    def forward(ctx, atlas, uv, duv_dx, duv_dy, table, size, address, lod_bias):
        ctx.save_for_backward(atlas, uv, duv_dx, duv_dy, table)
        ctx.args = (size, address, lod_bias)
        n = uv.shape[1]
        dt = compute_dtype(uv, atlas)  # float32 for half-precision lookups
        tex = atlas.to(dt)
        out = uv.new_empty(atlas.shape[1], n)
        for i in range(0, n, LOOKUP_CHUNK):  # bounded temporaries (the points are independent)
            j = min(i + LOOKUP_CHUNK, n)
            frac, grid = _taps(uv[:, i:j].to(dt), duv_dx[:, i:j].to(dt), duv_dy[:, i:j].to(dt),
                               table, size, address, lod_bias, tuple(atlas.shape[-2:]))
            s = grid_sample(tex, grid, mode="bilinear", padding_mode="border",
                            align_corners=True)[0, :, 0]  # (C, 2m)
            m = j - i
            out[:, i:j] = finish_low_precision(torch.lerp(s[:, :m], s[:, m:], frac[None]),
                                               uv.dtype)
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        atlas, uv, duv_dx, duv_dy, table = ctx.saved_tensors
        need_atlas = ctx.needs_input_grad[0]
        needs = ctx.needs_input_grad[1:4]
        n = uv.shape[1]
        tex = atlas.detach().to(compute_dtype(uv, atlas))
        result = [t.new_empty(t.shape) if nd else None
                  for t, nd in zip((uv, duv_dx, duv_dy), needs, strict=True)]
        # the points are independent: their part of backward in chunks (bounded
        # temporaries); the atlas gradient sums over every point, so with it one chunk
        # (the same sums in the same order as one call)
        step = n if need_atlas else LOOKUP_CHUNK
        grad_atlas = None
        for i in range(0, max(n, 1), max(step, 1)):
            cut = slice(i, min(i + step, n))
            ga, parts = _lookup_backward(tex, uv[:, cut], duv_dx[:, cut], duv_dy[:, cut],
                                         grad[:, cut], table, ctx.args, need_atlas, needs)
            if ga is not None:
                grad_atlas = finish_low_precision(ga, atlas.dtype)
            for dest, part in zip(result, parts, strict=True):
                if dest is not None and part is not None:
                    dest[:, cut] = part
                elif dest is not None:
                    dest[:, cut] = 0.0
        return (grad_atlas, *result, None, None, None, None)


def _lookup_backward(tex, uv, duv_dx, duv_dy, grad, table, args, need_atlas, needs):
    """:class:`_TrilinearLookup`'s backward at some points: (the atlas gradient or None,
    [d uv, d duv_dx, d duv_dy] each ``(2, m)`` or None)."""
    need_uv, need_dx, need_dy = needs
    n = uv.shape[1]
    dt = tex.dtype
    leaves = [t.detach().to(dt).requires_grad_(nd) for t, nd in zip(
        (uv, duv_dx, duv_dy), needs, strict=True)]
    with torch.enable_grad():  # the per-point part only: coordinates and level weights
        frac, grid = _taps(*leaves, table, *args, tuple(tex.shape[-2:]))
    grid0, w1 = grid.detach(), frac.detach()[None]
    grad = grad.to(dt)
    s = None
    if need_dx or need_dy or uv.dtype in LOW_PRECISION:
        s = F.grid_sample(tex, grid0, mode="bilinear", padding_mode="border",
                          align_corners=True)[0, :, 0]  # (C, 2N)
    if uv.dtype in LOW_PRECISION:  # finish_low_precision's clamp passes grads inside
        big = torch.finfo(uv.dtype).max
        out = torch.lerp(s[:, :n], s[:, n:], w1)
        grad = grad * ((out >= -big) & (out <= big))
        del out
    outs, grads_out = [], []
    if need_dx or need_dy:  # d lerp(a, b, w) / dw = b - a
        outs.append(frac)
        grads_out.append((grad * (s[:, n:] - s[:, :n])).sum(0))
    del s
    grad_atlas = None
    if need_atlas or need_uv:  # d lerp / da = 1 - w, d lerp / db = w
        g = torch.cat((grad * (1.0 - w1), grad * w1), 1)[None, :, None]  # (1, C, 1, 2N)
        # grid_sample's own backward: interpolation 0 = bilinear, padding 1 = border
        ga, gg = torch.ops.aten.grid_sampler_2d_backward(
            g, tex, grid0, 0, 1, True, [need_atlas, need_uv])
        del g
        if need_atlas:
            grad_atlas = ga
        if need_uv:
            outs.append(grid)
            grads_out.append(gg)
    wrt = [t for t in leaves if t.requires_grad]
    grads = iter(torch.autograd.grad(outs, wrt, grads_out, allow_unused=True) if wrt else ())
    result = [next(grads) if t.requires_grad else None for t in leaves]
    return grad_atlas, [g if g is None else finish_low_precision(g, t.dtype) for g, t in zip(
        result, (uv, duv_dx, duv_dy), strict=True)]
