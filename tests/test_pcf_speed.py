"""The padded PCF lookup (``_pcf_padded``) against a plain per-tap bilinear filter of the
depth comparisons, in either memory layout of its taps, and its gradient against
``gradcheck`` and against the general lookup's (``_pcf``)."""

from __future__ import annotations

import pytest
import torch

from torchraster.shading.shadows import _pcf, _pcf_padded

F64 = torch.float64


def _reference(maps, sel, tx, ty, z, size):
    """Mean over taps of the bilinear weights of the 4 texels around each tap that pass
    ``z <= depth`` (outside the map: lit), one (receiver, light, tap) at a time."""
    out = torch.zeros(tx.shape[:2], dtype=F64)
    z = z.expand_as(tx)
    for p in range(tx.shape[0]):
        for li in range(tx.shape[1]):
            m = maps[sel[p, li]].view(size, size)
            acc = 0.0
            for t in range(tx.shape[2]):
                x, y = float(tx[p, li, t]), float(ty[p, li, t])
                x0, y0 = int(torch.floor(torch.tensor(x))), int(torch.floor(torch.tensor(y)))
                fx, fy = x - x0, y - y0
                for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                                  (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
                    xi, yi = x0 + dx, y0 + dy
                    inside = 0 <= xi < size and 0 <= yi < size
                    acc += w * (not inside or float(z[p, li, t]) <= float(m[yi, xi]))
            out[p, li] = acc / tx.shape[2]
    return out


def _inputs(taps: int, seed: int, dtype=F64, n: int = 60, size: int = 12, maps: int = 3):
    g = torch.Generator().manual_seed(seed)
    depth = torch.rand(maps, size * size, generator=g, dtype=dtype)
    depth[:, ::7] = float("inf")  # texels where nothing was drawn
    sel = torch.randint(0, maps, (n, 2), generator=g)
    tx = torch.rand(n, 2, taps, generator=g, dtype=dtype) * (size + 6) - 3  # some outside
    ty = torch.rand(n, 2, taps, generator=g, dtype=dtype) * (size + 6) - 3
    tx[:4], ty[4:8] = 1e9, -1e9  # far outside
    tx[8:12] = torch.randint(-2, size + 2, (4, 2, taps), generator=g).to(dtype)  # on texels,
    ty[10:14] = torch.tensor([-1.0, -0.5, size - 1.0, size - 0.5])[:, None, None]  # the edges
    z = torch.rand(n, 2, taps, generator=g, dtype=dtype)
    return depth, sel, tx, ty, z, size


def _taps_leading(t: torch.Tensor) -> torch.Tensor:
    """``t`` ``(P, Ls, T)`` stored as ``(T, P, Ls)`` (as _visibility_of_view makes taps)."""
    return t.movedim(-1, 0).contiguous().movedim(0, -1)


@pytest.mark.parametrize("taps", [1, 3, 4, 8])
@pytest.mark.parametrize("per_tap_z", [True, False])
def test_padded_pcf_equals_a_plain_bilinear_filter(taps, per_tap_z):
    maps, sel, tx, ty, z, size = _inputs(taps, seed=taps)
    if not per_tap_z:
        z = z[..., :1]
    got = _pcf_padded(maps, sel, tx, ty, z, size)
    torch.testing.assert_close(got, _reference(maps, sel, tx, ty, z, size), rtol=0, atol=1e-12)
    # the same bits as the general lookup, and in either layout of the taps
    assert torch.equal(got, _pcf(maps, sel, tx, ty, z, size))
    leading = _pcf_padded(maps, sel, _taps_leading(tx), _taps_leading(ty), _taps_leading(z),
                          size)
    assert torch.equal(leading, got)


def test_padded_pcf_float32_maps_float64_taps():
    maps, sel, tx, ty, z, size = _inputs(4, seed=5)
    maps = maps.float()
    assert torch.equal(_pcf_padded(maps, sel, tx, ty, z, size), _pcf(maps, sel, tx, ty, z, size))


def test_padded_pcf_gradcheck():
    maps, sel, tx, ty, z, size = _inputs(4, seed=11, n=20)
    # away from texel boundaries, where the filter is not differentiable
    tx = (torch.floor(tx) + (tx - torch.floor(tx)).clamp(0.05, 0.95))[12:].requires_grad_()
    ty = (torch.floor(ty) + (ty - torch.floor(ty)).clamp(0.05, 0.95))[12:].requires_grad_()
    sel, z = sel[12:], z[12:]
    assert torch.autograd.gradcheck(
        lambda x, y: _pcf_padded(maps, sel, _taps_leading(x), _taps_leading(y), z, size),
        (tx, ty))


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("taps", [3, 8])
def test_padded_pcf_gradient_equals_the_general_lookups(dtype, taps):
    maps, sel, tx0, ty0, z, size = _inputs(taps, seed=3, dtype=dtype, n=200)
    w = torch.rand(tx0.shape[:2], generator=torch.Generator().manual_seed(1), dtype=dtype)
    grads = []
    for fn, layout in ((_pcf, lambda t: t), (_pcf_padded, _taps_leading)):
        tx, ty = tx0.clone().requires_grad_(), ty0.clone().requires_grad_()
        out = fn(maps, sel, layout(tx), layout(ty), z, size)
        grads.append(torch.autograd.grad((out * w).sum(), (tx, ty)))
    assert all(torch.equal(a, b) for a, b in zip(*grads, strict=True))
    assert float(grads[0][0].abs().sum()) > 0
