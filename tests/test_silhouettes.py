"""``rasterize(groups=...)``: each face group's silhouette from the main raster's candidates.

Reference: ``rasterize_coverage`` of the group's faces alone (a separate raster per group
and item), which is what the amodal masks used to be."""

from __future__ import annotations

import pytest
import torch
import trimesh

import torchraster as tr
from torchraster.raster import rasterize_coverage

RES = (27, 34)


def _scene():
    """Clip positions (3, V, 4) of 4 overlapping spheres (one around the near plane in the
    last view), faces (F, 3) and the (F,) group of each face (sphere k -> group k, the last
    sphere's faces in no group), 3 views."""
    verts, faces, groups = [], [], []
    offset = 0
    for k, centre in enumerate([(0.0, 0.0, 0.0), (0.4, 0.2, 0.8), (-0.6, -0.3, -0.9),
                                (0.2, 0.5, 2.6)]):
        s = trimesh.creation.icosphere(subdivisions=1, radius=0.5 + 0.1 * k)
        verts.append(torch.tensor(s.vertices, dtype=torch.float32) + torch.tensor(centre))
        faces.append(torch.tensor(s.faces, dtype=torch.int64) + offset)
        groups.append(torch.full((len(s.faces),), k if k < 3 else -1))
        offset += len(s.vertices)
    view = tr.camera.orbit(torch.tensor([0.0, 60.0, 10.0]), torch.tensor([10.0, 25.0, 5.0]),
                           torch.tensor([4.0, 5.0, 3.0]))
    clip = tr.camera.transform_points(torch.cat(verts), tr.camera.perspective(55.0, 1.2, 0.3)
                                      @ view)
    return clip, torch.cat(faces), torch.cat(groups)


def _reference(clip, faces, groups, num_groups, cull, face_ranges):
    """(B, G, H, W): group g of item b rasterized alone (its faces within the item's range)."""
    b = clip.shape[0]
    out = torch.zeros(b, num_groups, *RES, dtype=torch.bool)
    index = torch.arange(faces.shape[0])
    for i in range(b):
        lo, hi = (0, faces.shape[0]) if face_ranges is None else face_ranges[i].tolist()
        for g in range(num_groups):
            pick = ((groups == g) & (index >= lo) & (index < hi)).nonzero().flatten()
            if pick.numel() == 0:
                continue
            c = cull if isinstance(cull, bool) else cull[pick]
            out[i, g] = rasterize_coverage(clip[i:i + 1], faces[pick], RES, c)[0]
    return out


@pytest.mark.parametrize("layers", [1, 2])
def test_silhouettes_equal_each_group_rasterized_alone(layers):
    clip, faces, groups = _scene()
    single = torch.zeros(faces.shape[0], dtype=torch.bool)
    single[::3] = True
    ranges = torch.tensor([[0, faces.shape[0]], [60, 300], [0, 130]])
    for cull in (False, True, single):
        for fr in (None, ranges):
            frags = tr.rasterize(clip, faces, RES, cull_backfaces=cull, face_ranges=fr,
                                 layers=layers, groups=groups, num_groups=4)
            got = frags.silhouettes
            assert got.shape == (3, 4, *RES) and got.dtype == torch.bool
            assert got.is_contiguous()
            assert torch.equal(got, _reference(clip, faces, groups, 4, cull, fr))
            assert not got[:, 3].any()  # a group with no faces
            plain = tr.rasterize(clip, faces, RES, cull_backfaces=cull, face_ranges=fr,
                                 layers=layers)
            for a, b in zip(frags.layers, plain.layers, strict=True):  # visibility unchanged
                assert torch.equal(a.face_id, b.face_id) and torch.equal(a.bary, b.bary)
    assert got[:, :3].any((2, 3)).sum() >= 6
    assert tr.rasterize(clip, faces, RES).silhouettes is None


def test_hidden_back_faces_count_with_occlusion_culling_forced(monkeypatch):
    """Occlusion culling drops back faces hidden behind front faces from the depth resolve;
    a silhouette must still see them: a lone back-facing triangle (group 1) behind a
    screen-filling quad (group 0)."""
    import importlib

    raster = importlib.import_module("torchraster.raster.rasterize")
    monkeypatch.setattr(raster, "OCCLUSION_MIN_WORK", 0)
    clip = torch.tensor([[[-2.0, -2, 0, 1], [2, -2, 0, 1], [2, 2, 0, 1], [-2, 2, 0, 1],
                          [-0.5, -0.5, 0.5, 1], [0.0, 0.5, 0.5, 1], [0.5, -0.5, 0.5, 1]]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [4, 5, 6]])  # the last one clockwise
    frags = tr.rasterize(clip, faces, (16, 16), groups=torch.tensor([0, 0, 1]))
    assert (frags.face_id < 2).all()  # the quad hides it
    want = rasterize_coverage(clip, faces[2:], (16, 16))[0]
    assert want.sum() > 10 and torch.equal(frags.silhouettes[0, 1], want)


def test_groups_bad_input_is_named():
    clip, faces, groups = _scene()
    with pytest.raises(ValueError, match="groups"):
        tr.rasterize(clip, faces, RES, groups=groups[:-1])
    with pytest.raises(ValueError, match=r"groups: expected values in \[-1, 2\)"):
        tr.rasterize(clip, faces, RES, groups=groups, num_groups=2)
    with pytest.raises(ValueError, match="groups"):
        tr.rasterize(clip, faces, RES, groups=groups - 2)
    with pytest.raises(TypeError, match="groups"):
        tr.rasterize(clip, faces, RES, groups=groups.float())
    with pytest.raises(ValueError, match="num_groups"):
        tr.rasterize(clip, faces, RES, groups=groups.clamp(max=-1), num_groups=-1)
