"""Depth resolved in bands of rows (``resolve_keys(rows=...)``, ``rasterize_depth``'s bands
for large frames) gives exactly the keys of the whole frame."""

from __future__ import annotations

import importlib

import pytest
import torch
import trimesh

import torchraster as tr
from torchraster.raster import rasterize_depth

raster = importlib.import_module("torchraster.raster.rasterize")


def _scene(b: int = 3):
    """Clip positions (b, V, 4): a subdivided sphere (small triangles), a large floor quad
    crossing the near plane in some views (large triangles) and a sliver."""
    s = trimesh.creation.icosphere(subdivisions=3, radius=0.8)
    verts = torch.tensor(s.vertices, dtype=torch.float32)
    faces = torch.tensor(s.faces, dtype=torch.int64)
    floor = torch.tensor([[-6.0, -0.8, -6], [6, -0.8, -6], [6, -0.8, 6], [-6, -0.8, 6],
                          [-1.5, 0.9, 0.0], [1.5, 0.9, 0.01], [1.5, 0.905, 0.0]])
    n = verts.shape[0]
    faces = torch.cat([faces, torch.tensor([[n, n + 2, n + 1], [n, n + 3, n + 2],
                                            [n + 4, n + 5, n + 6]])])
    verts = torch.cat([verts, floor])
    view = tr.camera.orbit(torch.tensor([10.0, 120.0, 250.0][:b]),
                           torch.tensor([25.0, 5.0, 60.0][:b]), torch.tensor([3.0, 2.5, 4.0][:b]))
    return tr.camera.transform_points(verts, tr.camera.perspective(60.0, 1.3, 0.5) @ view), faces


@pytest.mark.parametrize("rows", [(0, 16), (16, 48), (5, 37), (40, 61), (0, 61)])
def test_band_keys_equal_the_whole_frames_rows(rows):
    clip, faces = _scene()
    h, w = 61, 77
    ranges = torch.tensor([[0, faces.shape[0]], [0, 1280], [1280, faces.shape[0]]])
    for cull in (False, True):
        for fr in (None, ranges):
            args = (clip, faces, (h, w), cull, fr, 16, 2**20, 16)
            whole = raster.resolve_keys(*args)[0].view(3, h, w)
            band = raster.resolve_keys(*args, rows=rows)[0].view(3, rows[1] - rows[0], w)
            assert torch.equal(band, whole[:, rows[0]:rows[1]]), (cull, fr is None)
    assert (whole != raster.EMPTY_KEY).sum() > 1000


def test_rasterize_depth_in_bands_is_the_unbanded_depth(monkeypatch):
    clip, faces = _scene()
    whole = rasterize_depth(clip, faces, (61, 77))
    for pixels in (3 * 77 * 16, 3 * 77 * 20, 1):  # bands of 16 rows (and the 16-row floor)
        monkeypatch.setattr(raster, "DEPTH_BAND_PIXELS", pixels)
        out = torch.full((3, 61, 77), 7.0)
        got = rasterize_depth(clip, faces, (61, 77), out=out)
        assert got is out and torch.equal(got, whole)
    assert torch.isfinite(whole).sum() > 1000


def test_rasterize_depth_out_is_checked():
    clip, faces = _scene()
    with pytest.raises(ValueError, match="out"):
        rasterize_depth(clip, faces, (8, 8), out=torch.empty(3, 8, 9))
    with pytest.raises(TypeError, match="out"):
        rasterize_depth(clip, faces, (8, 8), out=torch.empty(3, 8, 8, dtype=torch.float64))
    with pytest.raises(ValueError, match="rows"):
        raster.resolve_keys(clip, faces, (8, 8), False, None, 16, 2**20, 16, rows=(4, 9))
