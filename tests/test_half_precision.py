"""The half-precision policy (numerics.compute_dtype): float16 / bfloat16 geometry is
evaluated in float32 and its gradients come back saturated, never Inf / NaN. Regressions
found by scripts/stress.py (kind "half", seed 20261125): vertex normals' cross-product
backward and the rasterizer's per-pixel barycentric backward overflowed float16."""

import pytest
import torch

import torchraster as tr


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_vertex_normals_backward_is_finite_and_matches_float32(dtype):
    g = torch.Generator().manual_seed(0)
    pos32 = torch.rand(200, 3, generator=g) * 0.05  # small faces: |cross| ~ 1e-4, so the
    faces = torch.randint(0, 200, (300, 3), generator=g)  # normalisation's gradient ~ 1e4 x
    weight = torch.randn(200, 3, generator=g) * 2000
    grads = []
    for dt in (dtype, torch.float32):
        pos = pos32.to(dt).float().to(dt).requires_grad_(True)
        (tr.vertex_normals(pos, faces).float() * weight).sum().backward()
        grads.append(pos.grad.float())
    assert torch.isfinite(grads[0]).all()
    # the same (half-rounded) positions: where float32's gradient fits the half range, the
    # half gradient is it up to half rounding of the incoming gradient; beyond, saturated
    big = torch.finfo(dtype).max
    fits = grads[1].abs() < big
    err = (grads[0] - grads[1])[fits].norm() / grads[1][fits].norm()
    assert err < 0.05
    assert (grads[0][~fits].abs() == big).all()


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_rasterize_half_evaluates_in_float32(dtype):
    # a long sliver and a big triangle: 1 / sum(l) and its derivative exceed float16
    clip = torch.tensor([[[-1.0, -1, 0, 1], [1, -0.999, 0, 1], [-1, -0.998, 0, 1],
                          [-0.9, -0.9, 0.5, 1e-2], [0.9, -0.9, 0.5, 1e-2],
                          [0, 0.9, 0.5, 1e-2]]], dtype=dtype).requires_grad_(True)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    frags = tr.rasterize(clip, faces, (64, 64))
    assert frags.bary.dtype == torch.float32
    (frags.bary * 1e4).sum().backward()
    assert clip.grad.dtype == dtype and torch.isfinite(clip.grad).all()
