"""interpolate returns one type; interpolate_with_derivatives adds exact screen derivatives,
checked against central differences of the independent float64 reference barycentrics."""

from __future__ import annotations

import pytest
import torch

import torchraster as tr
from torchraster.testing.reference_raster import (
    face_bary_depth,
    look_at_matrix,
    perspective_matrix,
    pixel_centres,
    to_clip,
)

RES = (24, 20)  # (H, W): not square, so row and column steps differ


def _scene(dtype: torch.dtype = torch.float64):
    """Two tilted triangles in perspective (one partly behind the other), own float64
    camera maths; returns clip (1, V, 4), faces (F, 3), attrs (V, 2)."""
    g = torch.Generator().manual_seed(7)
    verts = torch.tensor([[-1.2, -1.0, 0.3], [1.1, -0.8, -0.6], [0.1, 1.2, 0.2],
                          [-0.5, -0.3, 0.9], [0.9, 0.1, 0.4], [-0.2, 0.8, 0.6]],
                         dtype=torch.float64)
    mat = perspective_matrix(50.0, RES[1] / RES[0], 0.1, 20.0) @ look_at_matrix(
        torch.tensor([0.4, 0.3, 3.0]), torch.zeros(3), torch.tensor([0.0, 1.0, 0.0]))
    clip = to_clip(verts, mat)[None].to(dtype)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    attrs = torch.randn(6, 2, generator=g, dtype=torch.float64).to(dtype)
    return clip, faces, attrs


def test_interpolate_always_returns_one_tensor():
    clip, faces, attrs = _scene()
    frags = tr.rasterize(clip, faces, RES, derivatives=True)
    img = tr.interpolate(attrs, frags, faces)
    assert isinstance(img, torch.Tensor) and img.shape == (1, 2, *RES)
    with pytest.raises(TypeError):
        tr.interpolate(attrs, frags, faces, derivatives=True)  # the old tuple-returning flag


def test_derivatives_match_central_differences_of_the_reference():
    clip, faces, attrs = _scene()
    frags = tr.rasterize(clip, faces, RES, derivatives=True)
    out = tr.interpolate_with_derivatives(attrs, frags, faces)
    assert isinstance(out, tr.raster.Interpolated)
    value, ddx, ddy = out
    assert value.shape == ddx.shape == ddy.shape == (1, 2, *RES)
    torch.testing.assert_close(value, tr.interpolate(attrs, frags, faces), rtol=0, atol=0)

    h, w = RES
    fid = frags.face_id[0].reshape(-1)
    hit = fid >= 0
    assert hit.sum() > 100
    pix = pixel_centres(h, w)[hit]
    face = fid[hit]
    step = 1e-3  # pixels
    dx = torch.tensor([2.0 * step / w, 0.0], dtype=torch.float64)  # one column right
    dy = torch.tensor([0.0, -2.0 * step / h], dtype=torch.float64)  # one row down

    def attr_at(points: torch.Tensor) -> torch.Tensor:
        bary, _ = face_bary_depth(clip[0], faces, face, points)
        return (bary[..., None] * attrs[faces[face]]).sum(1).T  # (C, N)

    ref_dx = (attr_at(pix + dx) - attr_at(pix - dx)) / (2 * step)
    ref_dy = (attr_at(pix + dy) - attr_at(pix - dy)) / (2 * step)
    got_dx = ddx[0].reshape(2, -1)[:, hit]
    got_dy = ddy[0].reshape(2, -1)[:, hit]
    scale = max(ref_dx.abs().max(), ref_dy.abs().max())
    torch.testing.assert_close(got_dx, ref_dx, rtol=0, atol=1e-6 * scale)
    torch.testing.assert_close(got_dy, ref_dy, rtol=0, atol=1e-6 * scale)
    empty = ~hit.view(1, 1, h, w)
    assert (ddx * empty == 0).all() and (ddy * empty == 0).all()


def test_derivatives_need_derivative_fragments_and_are_differentiable():
    clip, faces, attrs = _scene()
    with pytest.raises(ValueError, match="derivatives=True"):
        tr.interpolate_with_derivatives(attrs, tr.rasterize(clip, faces, RES), faces)
    attrs = attrs.clone().requires_grad_(True)
    frags = tr.rasterize(clip, faces, RES, derivatives=True)
    value, ddx, ddy = tr.interpolate_with_derivatives(attrs, frags, faces)
    (value.sum() + ddx.sum() + ddy.sum()).backward()
    assert attrs.grad is not None and torch.isfinite(attrs.grad).all()
