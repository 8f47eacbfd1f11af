"""MipAtlas lookups save only their inputs for backward (issue 23, memory).

References are independent: a float64 trilinear lookup written with grid_sample per level
on the unpadded pyramid (the documented convention), float64 gradcheck, and the bytes
autograd saves (``saved_tensors_hooks``) against the inputs' own bytes.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from torchraster.mip import build_mip_pyramid, compute_lod
from torchraster.mip_atlas import MipAtlas

D64 = torch.float64


def _inputs(n: int, size: int, dtype=D64, seed: int = 0, lod_range=(0.2, 2.8)):
    """uv anywhere (wrap), derivatives giving lods in ``lod_range`` (random directions)."""
    g = torch.Generator().manual_seed(seed)
    uv = torch.rand(2, n, generator=g, dtype=D64) * 3.0 - 1.0
    lod = torch.rand(n, generator=g, dtype=D64) * (lod_range[1] - lod_range[0]) + lod_range[0]
    ang = torch.rand(2, n, generator=g, dtype=D64) * 6.283
    r = 2.0**lod / size
    dx = torch.stack((ang[0].cos(), ang[0].sin())) * r  # |dx * size| = 2**lod
    dy = torch.stack((ang[1].cos(), ang[1].sin())) * r * (0.3 + 0.6 * torch.rand(n, generator=g))
    return uv.to(dtype), dx.to(dtype), dy.to(dtype)


def _reference(tex: torch.Tensor, uv, dx, dy) -> torch.Tensor:
    """Trilinear by definition: per level, grid_sample (wrap via a 3x3 tiling of the level,
    align_corners=False texel centres) of the box pyramid, lerped by the lod's fraction."""
    levels = build_mip_pyramid(tex[None])
    lod = compute_lod(dx[None, :, None], dy[None, :, None], tuple(tex.shape[-2:]))[0, 0, 0]
    lod = lod.clamp(0, len(levels) - 1)
    out = torch.zeros(tex.shape[0], uv.shape[1], dtype=tex.dtype)
    u, v = uv[0] - uv[0].floor(), uv[1] - uv[1].floor()
    for k, lev in enumerate(levels):
        wk = (1 - (lod - k).abs()).clamp_min(0)
        tiled = lev.repeat(1, 1, 3, 3)  # the level repeated: wrap addressing around [0, 1]
        grid = torch.stack(((u + 1) / 3 * 2 - 1, (2 - v) / 3 * 2 - 1), -1)[None, None]
        s = F.grid_sample(tiled, grid, mode="bilinear", align_corners=False)[0, :, 0]
        out = out + s * wk
    return out


def test_values_match_definition() -> None:
    tex = torch.rand(3, 16, 8, dtype=D64)
    uv, dx, dy = _inputs(500, 16, lod_range=(-1.0, 5.0))
    out = MipAtlas([tex[:2], tex[2:]]).sample(uv, dx, dy)
    torch.testing.assert_close(out, _reference(tex, uv, dx, dy))


@pytest.mark.parametrize("wrt", ["all", "uv", "dx", "tex"])
def test_gradcheck_textures_uv_and_derivatives(wrt: str) -> None:
    g = torch.Generator().manual_seed(1)
    tex = torch.rand(2, 8, 8, dtype=D64, generator=g).requires_grad_(wrt in ("all", "tex"))
    tex2 = torch.rand(1, 8, 8, dtype=D64, generator=g).requires_grad_(wrt == "all")
    uv, dx, dy = _inputs(12, 8, seed=1)
    uv.requires_grad_(wrt in ("all", "uv"))
    dx.requires_grad_(wrt in ("all", "dx"))
    dy.requires_grad_(wrt == "all")

    def f(a, b, uv, dx, dy):
        return MipAtlas([a, b], address=("wrap", "mirror")).sample(uv, dx, dy, lod_bias=0.1)

    assert torch.autograd.gradcheck(f, (tex, tex2, uv, dx, dy))


def test_gradients_match_definition() -> None:
    """Against autograd through the reference on a 64² texture (float64)."""
    tex = torch.rand(3, 64, 64, dtype=D64, requires_grad=True)
    uv, dx, dy = (t.requires_grad_() for t in _inputs(2000, 64, seed=2, lod_range=(0.1, 5.9)))
    w = torch.randn(3, 2000, dtype=D64)
    got = torch.autograd.grad((MipAtlas([tex]).sample(uv, dx, dy) * w).sum(), (tex, uv, dx, dy))
    ref = torch.autograd.grad((_reference(tex, uv, dx, dy) * w).sum(), (tex, uv, dx, dy))
    for a, b in zip(got, ref, strict=True):
        torch.testing.assert_close(a, b)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
def test_saves_only_the_inputs(dtype: torch.dtype) -> None:
    """Autograd keeps uv, its derivatives, the atlas and the level table: no per-tap
    indices, weights or texels (those cost ~10 floats a lookup)."""
    tex = torch.rand(4, 64, 64, requires_grad=True)
    atlas = MipAtlas([tex[:3], tex[3:]])
    n = 4096
    uv, dx, dy = (t.requires_grad_() for t in _inputs(n, 64, dtype=dtype, seed=3))
    saved = []
    with torch.autograd.graph.saved_tensors_hooks(lambda t: saved.append(t) or t, lambda t: t):
        out = atlas.sample(uv, dx, dy)
    per_lookup = [t for t in saved if t.numel() >= n and t is not atlas.atlas]
    assert sum(t.numel() for t in per_lookup) <= 6 * n, [tuple(t.shape) for t in per_lookup]
    assert all(t.data_ptr() in (uv.data_ptr(), dx.data_ptr(), dy.data_ptr())
               for t in per_lookup)
    out.float().square().sum().backward()  # still differentiable, gradients in input dtypes
    assert uv.grad.dtype == dtype and tex.grad.dtype == torch.float32
    assert torch.isfinite(tex.grad).all() and tex.grad.abs().sum() > 0


def test_only_needed_gradients_and_no_grad_mode() -> None:
    tex = torch.rand(3, 32, 32, requires_grad=True)
    uv, dx, dy = _inputs(300, 32, dtype=torch.float32, seed=4)
    uv.requires_grad_()
    atlas = MipAtlas([tex])
    out = atlas.sample(uv, dx, dy)
    out.sum().backward()
    assert uv.grad is not None and dx.grad is None and tex.grad is not None
    with torch.no_grad():
        assert not atlas.sample(uv, dx, dy).requires_grad
    assert torch.equal(atlas.sample(uv, dx, dy).detach(), out.detach())


def test_half_precision_saturation_blocks_gradient() -> None:
    """float16 lookups saturate to the finite range (finish_low_precision): no gradient
    reaches the texels of a saturated channel, as for the clamp it is."""
    tex = torch.cat((torch.full((1, 16, 16), 7e4), torch.rand(1, 16, 16))).requires_grad_()
    uv, dx, dy = _inputs(64, 16, dtype=torch.float16, seed=5)
    out = MipAtlas([tex]).sample(uv, dx, dy)
    assert out.dtype == torch.float16 and bool((out[0] == 65504).all())
    out.float().sum().backward()
    assert bool((tex.grad[0] == 0).all()) and tex.grad[1].sum() > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
def test_backward_in_chunks_is_bit_identical(monkeypatch, dtype: torch.dtype) -> None:
    # the per-point part of backward runs in chunks of LOOKUP_CHUNK points; with a texture
    # that takes gradients it stays one chunk (the atlas gradient sums over every point)
    from torchraster import mip_atlas

    g = torch.Generator().manual_seed(5)
    for tex_grad in (False, True):
        tex = torch.rand(3, 16, 16, generator=g).requires_grad_(tex_grad)
        uv, dx, dy = (t.to(dtype).requires_grad_(True) for t in _inputs(500, 16, seed=2))
        w = torch.randn(3, 500, generator=g)
        wrt = (uv, dx, dy) + ((tex,) if tex_grad else ())

        def grads(chunk: int, tex=tex, uv=uv, dx=dx, dy=dy, w=w, wrt=wrt):
            monkeypatch.setattr(mip_atlas, "LOOKUP_CHUNK", chunk)
            out = MipAtlas([tex]).sample(uv, dx, dy)
            return torch.autograd.grad((out.float() * w).sum(), wrt)

        whole, chunked = grads(2**18), grads(37)
        for a, b in zip(whole, chunked, strict=True):
            assert a.dtype == b.dtype and torch.equal(a, b)
        assert all(bool(torch.isfinite(a).all()) for a in whole)
