"""Anisotropic texture filtering: N trilinear probes along the major axis of the footprint.

A pixel's footprint in the texture is the parallelogram spanned by the screen-space UV
derivatives ``J_x = duv/dx`` and ``J_y = duv/dy`` (in texels). Trilinear filtering covers it
with one square of side ``P_max = max(|J_x|, |J_y|)`` (the OpenGL lod), which over-blurs a
steep surface along the short side. The GPU approximation (the OpenGL extension
EXT_texture_filter_anisotropic, its change to section 3.8.5, "Texture Minification"; core
since OpenGL 4.6) instead takes

    P_max = max(|J_x|, |J_y|),  P_min = min(|J_x|, |J_y|)
    N     = min(ceil(P_max / max(P_min, 1)), max_anisotropy)
    lod   = log2(P_max / N)

and averages N trilinear lookups at that (finer) lod, spaced along the longer derivative
vector. ``P_min`` is floored at one texel (ours, measured): a probe is never finer than
level 0, so a magnified footprint takes one probe like trilinear instead of being blurred
by more. Here the probes sit at the centres of N equal parts of that vector
(``uv + ((i + 1/2) / N - 1/2) J_major``, i = 0..N-1), so they tile the footprint like a box
filter; with N = 1 this is exactly trilinear filtering.

Vectorised without waste: only the N probes of each pixel are looked up (pixel indices
repeated N times, one batched trilinear lookup, summed back with ``index_add``), so the cost
is proportional to the mean N, not to ``max_anisotropy`` (measured in docs/benchmarks.md,
section quality-texture, against evaluating ``max_anisotropy`` probes everywhere).

Differentiable w.r.t. the texture, the UVs and the UV derivatives (through the probe
positions and the lod); N is an integer decision and carries no gradient.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from .mip import LOD_RHO2_FLOOR, sample_levels

__all__ = ["MAX_TEXTURE_ANISOTROPY", "check_max_anisotropy", "anisotropic_footprint",
           "sample_anisotropic", "sample_anisotropic_dense"]

#: Largest accepted ``max_anisotropy`` (the usual GPU limit is 16).
MAX_TEXTURE_ANISOTROPY: int = 64

#: ``P_max / P_min`` is rounded up after subtracting this, so footprints that are isotropic
#: up to float noise take one probe (and equal trilinear filtering).
_RATIO_TOL: float = 1e-4


def check_max_anisotropy(value: object) -> int:
    """``max_anisotropy`` as an int in ``[1, MAX_TEXTURE_ANISOTROPY]``, else a ValueError
    naming it."""
    top = MAX_TEXTURE_ANISOTROPY
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= top:
        raise ValueError(f"max_anisotropy: expected an int in [1, {top}], "
                         f"got {value!r}")
    return value


def anisotropic_footprint(
    duv_dx: torch.Tensor,
    duv_dy: torch.Tensor,
    size: tuple[int, int],
    max_anisotropy: int = 16,
    lod_bias: float | torch.Tensor = 0.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Probe count, probe lod and major axis of each pixel's texture footprint.

    Args:
        duv_dx, duv_dy: UV derivatives per pixel step right / down (UV units / pixel).
        size: ``(Ht, Wt)`` of mip level 0 (u is scaled by Wt, v by Ht).
        max_anisotropy: largest number of probes N.
        lod_bias: added to the probe lod.

    Returns:
        ``(n, lod, axis)``: the probe count (int64, in ``[1, max_anisotropy]``), the
        unclamped lod of each probe and the major axis in UV units (the longer of
        ``duv_dx`` and ``duv_dy``; probes span it from -1/2 to +1/2).

    Shape:
        - duv_dx, duv_dy: ``(B, 2, H, W)``
        - n, lod: ``(B, 1, H, W)``; axis: ``(B, 2, H, W)``
    """
    check_max_anisotropy(max_anisotropy)
    ht, wt = size
    scale = duv_dx.new_tensor([wt, ht]).view(1, 2, 1, 1)
    rx = ((duv_dx * scale) ** 2).sum(1, keepdim=True)
    ry = ((duv_dy * scale) ** 2).sum(1, keepdim=True)
    x_major = rx >= ry
    rho2_max = torch.maximum(rx, ry).clamp_min(LOD_RHO2_FLOOR)
    # probes no finer than a texel: a bilinear probe of level 0 already spans one, so a
    # magnified footprint takes one probe (as trilinear) instead of blurring with more
    rho2_min = torch.minimum(rx, ry).detach().clamp_min(1.0)
    ratio = torch.sqrt(rho2_max.detach() / rho2_min)
    n = torch.ceil(ratio - _RATIO_TOL).clamp(1, max_anisotropy)
    lod = 0.5 * torch.log2(rho2_max) - torch.log2(n) + lod_bias
    axis = torch.where(x_major, duv_dx, duv_dy)
    return n.long(), lod, axis


def sample_anisotropic(
    levels: Sequence[torch.Tensor],
    uv: torch.Tensor,
    duv_dx: torch.Tensor,
    duv_dy: torch.Tensor,
    address: tuple[str, str],
    max_anisotropy: int = 16,
    lod_bias: float | torch.Tensor = 0.0,
    padded: Sequence[torch.Tensor] | None = None,
) -> torch.Tensor:
    """Average of N trilinear probes along the footprint's major axis (module docstring).

    Args:
        levels: mip levels, level 0 first, each ``(B or 1, C, h_k, w_k)`` (1 = shared).
        uv: texture coordinates; duv_dx, duv_dy: their derivatives (UV / pixel).
        address: ``(mode_u, mode_v)`` address modes.
        max_anisotropy: largest number of probes a pixel.
        lod_bias: added to the probe lod.
        padded: the levels padded for ``address`` (:class:`~torchraster.texture.MipTexture`
            keeps them), or None.

    Returns:
        The filtered texels.

    Shape:
        - uv, duv_dx, duv_dy: ``(B, 2, H, W)``
        - output: ``(B, C, H, W)``
    """
    n, lod, axis = anisotropic_footprint(duv_dx, duv_dy, tuple(levels[0].shape[-2:]),
                                         max_anisotropy, lod_bias)
    if n.numel() == 0 or int(n.max()) <= 1:  # isotropic everywhere: trilinear
        return sample_levels(levels, uv[:, 0], uv[:, 1], lod, address, padded)
    b, _, h, w = uv.shape
    c = levels[0].shape[1]
    items = 1 if levels[0].shape[0] == 1 else b  # a shared texture: the batch is one item
    npix = b * h * w // items

    def flat(t: torch.Tensor) -> torch.Tensor:  # (B, K, H, W) -> (K, items * npix)
        return t.transpose(0, 1).reshape(t.shape[1], -1)

    counts = flat(n)[0]
    # one column per probe: its pixel and its index i within the pixel
    pix = torch.repeat_interleave(counts)
    first = torch.cumsum(counts, 0) - counts
    probe = torch.arange(pix.numel(), device=uv.device) - first.index_select(0, pix)
    nf = counts.index_select(0, pix).to(uv.dtype)
    t = (probe.to(uv.dtype) + 0.5) / nf - 0.5
    pos = flat(uv).index_select(1, pix) + t * flat(axis).index_select(1, pix)  # (2, M)
    probes = torch.cat((pos, flat(lod).index_select(1, pix)), 0)  # (3, M): u, v, lod
    per_item = counts.view(items, npix).sum(1)
    width = int(per_item.max())
    dest = None
    if items > 1:  # item k's probes go to row k, padded to the longest item (weight 0)
        item = torch.div(pix, npix, rounding_mode="floor")
        start = (torch.cumsum(per_item, 0) - per_item - item.new_tensor(
            range(0, items * width, width))).index_select(0, item)
        dest = torch.arange(pix.numel(), device=uv.device) - start
        probes = probes.new_zeros(3, items * width).index_copy(1, dest, probes)
    probes = probes.view(3, items, 1, width)
    s = sample_levels(levels, probes[0], probes[1], probes[2, :, None], address, padded)
    s = s.transpose(0, 1).reshape(c, items * width)  # (C, items * width)
    if dest is not None:
        s = s.index_select(1, dest)
    out = uv.new_zeros(c, items * npix).index_add(1, pix, s / nf)
    return out.view(c, b, h, w).transpose(0, 1)


def sample_anisotropic_dense(
    levels: Sequence[torch.Tensor],
    uv: torch.Tensor,
    duv_dx: torch.Tensor,
    duv_dy: torch.Tensor,
    address: tuple[str, str],
    max_anisotropy: int = 16,
    lod_bias: float | torch.Tensor = 0.0,
    padded: Sequence[torch.Tensor] | None = None,
) -> torch.Tensor:
    """Same result as :func:`sample_anisotropic`, evaluating ``max_anisotropy`` probes at
    every pixel with zero weight for the unused ones (kept for the benchmark that measures
    the two vectorisations; shapes as there)."""
    n, lod, axis = anisotropic_footprint(duv_dx, duv_dy, tuple(levels[0].shape[-2:]),
                                         max_anisotropy, lod_bias)
    k = max_anisotropy
    b, _, h, w = uv.shape
    i = torch.arange(k, device=uv.device, dtype=uv.dtype)
    nf = n.to(uv.dtype)[..., None]  # (B, 1, H, W, 1)
    used = i < nf
    t = torch.where(used, (i + 0.5) / nf - 0.5, torch.zeros_like(nf))
    pos = (uv[..., None] + t * axis[..., None]).reshape(b, 2, h, w * k)
    lods = lod[..., None].expand(b, 1, h, w, k).reshape(b, 1, h, w * k)
    s = sample_levels(levels, pos[:, 0], pos[:, 1], lods, address, padded)
    weight = used.to(uv.dtype) / nf
    return (s.view(b, -1, h, w, k) * weight).sum(-1)
