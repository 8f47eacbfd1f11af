"""rasterize(select=...): the barycentric pass over the selected pixels only (edge
antialiasing's k x raster), against the plain rasterize and the float64 reference."""

from __future__ import annotations

import pytest
import torch

import torchraster as tr
from torchraster.testing.reference_raster import reference_rasterize


def _scene(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(1, 60, 2, generator=g, dtype=torch.float64) * 2.4 - 1.2
    z = torch.rand(1, 60, 1, generator=g, dtype=torch.float64) * 1.6 - 0.8
    w = 1 + torch.rand(1, 60, 1, generator=g, dtype=torch.float64)
    clip = torch.cat([xy * w, z * w, w], -1)
    faces = torch.randint(0, 60, (40, 3), generator=g)
    return clip, faces


def test_selected_pixels_equal_the_full_raster() -> None:
    clip, faces = _scene()
    res = (24, 32)
    full = tr.rasterize(clip, faces, res, derivatives=True)
    seen = []

    def select(face_id: torch.Tensor) -> torch.Tensor:
        seen.append(face_id.clone())
        keep = torch.zeros_like(face_id, dtype=torch.bool)
        keep[:, ::3, 1::2] = True
        return keep

    part = tr.rasterize(clip, faces, res, derivatives=True, select=select)
    assert torch.equal(seen[0], full.face_id)  # select sees the whole nearest surface
    keep = select(full.face_id)
    assert torch.equal(part.face_id, torch.where(keep, full.face_id, -1))
    ref = reference_rasterize(clip, faces, res)
    assert torch.equal(part.face_id[keep], ref.face_id[keep])
    sel = keep & (full.face_id >= 0)
    for name in ("bary", "depth", "bary_dx", "bary_dy"):
        a, b = getattr(part, name), getattr(full, name)
        m = sel[..., None].expand_as(a) if a.dim() == 4 else sel
        torch.testing.assert_close(a[m], b[m], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(part.bary[sel], ref.bary[sel], rtol=1e-9, atol=1e-9)


def test_select_is_checked() -> None:
    clip, faces = _scene(1)
    with pytest.raises(ValueError, match="select: needs layers=1"):
        tr.rasterize(clip, faces, 8, layers=2, select=lambda f: f >= 0)
    with pytest.raises(TypeError, match="select.*bool"):
        tr.rasterize(clip, faces, 8, select=lambda f: f)
    with pytest.raises(ValueError, match="select"):
        tr.rasterize(clip, faces, 8, select=lambda f: (f >= 0)[:, :4])


def test_selected_gradients_match() -> None:
    clip, faces = _scene(2)
    clip.requires_grad_(True)

    def keep_fn(f: torch.Tensor) -> torch.Tensor:  # every other column
        return torch.ones_like(f, dtype=torch.bool).index_fill_(2, torch.arange(0, 16, 2), False)

    a = tr.rasterize(clip, faces, 16, select=keep_fn)
    b = tr.rasterize(clip, faces, 16)
    keep = keep_fn(b.face_id) & (b.face_id >= 0)
    ga, = torch.autograd.grad((a.bary * keep[..., None]).sum(), clip)
    gb, = torch.autograd.grad((b.bary * keep[..., None]).sum(), clip)
    torch.testing.assert_close(ga, gb, rtol=1e-9, atol=1e-9)
