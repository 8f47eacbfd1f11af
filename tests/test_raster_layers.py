"""rasterize(..., layers=K): depth peeling against an independent float64 K-nearest brute force.

The reference below tests every pixel centre against every face (2-D homogeneous edge
functions, top-left rule, w > 0 and -1 <= z <= 1, as in the contract), sorts all hits of a
pixel by (depth, face index) and keeps the first K: layer k of the engine must be the k-th
entry. Disagreements are only allowed where float rounding decides: a pixel centre within
ref.EDGE_TOL_PX of a boundary of a face involved, or two faces within ref.DEPTH_TIE_TOL in depth.
"""

from __future__ import annotations

import pytest
import torch
import trimesh

import torchraster as tr

try:
    from torchraster.testing import reference_raster as ref
except ImportError:  # the reference's former home, tests/reference_raster.py
    import reference_raster as ref  # type: ignore[no-redef]


def k_nearest_reference(clip_pos: torch.Tensor, faces: torch.Tensor, resolution, k: int,
                        cull_backfaces: bool = False):
    """float64 brute force: face ids (K, B, H, W) (-1 past the last hit) and depths (K, B,
    H, W) (+inf there) of the K nearest faces of every pixel, ordered by (depth, face)."""
    h, w = resolution
    clip = clip_pos.detach().double().cpu()
    pix = ref.pixel_centres(h, w)  # (P, 2)
    ids, depths = [], []
    for b in range(clip.shape[0]):
        tri = clip[b][faces]  # (F, 3, 4)
        coef, det = ref.edge_coefficients(tri)  # (F, 3, 3), (F,)
        e = (coef[:, None, :, 0] * pix[None, :, None, 0] + coef[:, None, :, 1]
             * pix[None, :, None, 1] + coef[:, None, :, 2])  # (F, P, 3)
        s = torch.sign(det)[:, None, None]
        nx, ny = s[:, :, 0] * coef[..., 0], s[:, :, 0] * coef[..., 1]  # inward normals
        top_left = ((nx > 0) | ((nx == 0) & (ny < 0)))[:, None, :]
        inside = ((s * e > 0) | ((e == 0) & top_left)).all(-1)
        inside &= det[:, None] * e.sum(-1) > 0  # w > 0, det != 0
        if cull_backfaces:
            inside &= (det > 0)[:, None]
        safe = torch.where(det == 0, torch.ones_like(det), det)
        z = (e * tri[:, None, :, 2]).sum(-1) / safe[:, None]
        inside &= (z >= -1) & (z <= 1)
        z = torch.where(inside, z, torch.full_like(z, float("inf")))  # (F, P)
        z_sorted, order = torch.sort(z, dim=0, stable=True)  # ties: lower face first
        face = torch.where(torch.isinf(z_sorted), -1, order)
        pad = max(0, k - face.shape[0])
        face = torch.cat([face, face.new_full((pad, face.shape[1]), -1)])[:k]
        z_sorted = torch.cat([z_sorted, z_sorted.new_full((pad, z_sorted.shape[1]),
                                                          float("inf"))])[:k]
        ids.append(face.view(k, h, w))
        depths.append(z_sorted.view(k, h, w))
    return torch.stack(ids, 1), torch.stack(depths, 1)


def _unexplained(frags, ref_ids, clip, faces, resolution) -> list:
    """Pixels whose engine layer list differs from the reference for no rounding reason."""
    h, w = resolution
    eng = torch.stack([layer.face_id for layer in frags.layers]).cpu()  # (K, B, H, W)
    differ = (eng != ref_ids).any(0)
    pix = ref.pixel_centres(h, w)
    clip64 = clip.detach().double().cpu()
    bad = []
    for b, i, j in differ.nonzero().tolist():
        p = pix[i * w + j][None]
        involved = sorted({int(f) for f in torch.cat([eng[:, b, i, j], ref_ids[:, b, i, j]])
                           if f >= 0})
        ft = torch.tensor(involved)
        near_edge = ref.boundary_distance_px(clip64[b], faces, ft, p.expand(len(involved), 2),
                                         (h, w)) < ref.EDGE_TOL_PX
        if bool(near_edge.any()):
            continue
        tri = clip64[b][faces[ft]]
        coef, det = ref.edge_coefficients(tri)
        e = coef[..., 0] * p[:, None, 0] + coef[..., 1] * p[:, None, 1] + coef[..., 2]
        z = ((e * tri[..., 2]).sum(-1) / det).sort().values
        if z.numel() > 1 and bool(((z[1:] - z[:-1]).abs() < ref.DEPTH_TIE_TOL).any()):
            continue
        bad.append((b, i, j, eng[:, b, i, j].tolist(), ref_ids[:, b, i, j].tolist()))
    return bad


def _sphere_clip(subdiv: int = 3, dtype=torch.float64):
    mesh = trimesh.creation.icosphere(subdivisions=subdiv)
    verts = torch.tensor(mesh.vertices, dtype=torch.float64)
    faces = torch.tensor(mesh.faces, dtype=torch.int64)
    view = ref.look_at_matrix(torch.tensor([0.4, 0.3, 3.0]), torch.zeros(3),
                              torch.tensor([0, 1.0, 0]))
    clip = ref.to_clip(verts, ref.perspective_matrix(45.0, 1.0, 0.1, 10.0) @ view)[None]
    return clip.to(dtype), faces


# ------------------------------------------------------------------ layer 0 and the API


def test_layer_zero_is_rasterize_bitwise():
    gen = torch.Generator().manual_seed(1)
    clip, faces, _ = ref.random_soup(gen, 2, 120)
    clip = clip.float()
    plain = tr.rasterize(clip, faces, (40, 48))
    frags = tr.rasterize(clip, faces, (40, 48), layers=4)
    assert len(frags.layers) == 4 and frags.layers[0] is frags
    assert plain.layers == (plain,)
    for name in ("face_id", "bary", "depth"):
        assert torch.equal(getattr(plain, name), getattr(frags, name)), name


@pytest.mark.parametrize("bad", [0, -1, 1.5, True])
def test_layers_must_be_a_positive_int(bad):
    clip = torch.tensor([[[-1, -1, 0, 1], [1, -1, 0, 1], [0, 1, 0, 1.0]]])
    with pytest.raises(ValueError, match="layers"):
        tr.rasterize(clip, torch.tensor([[0, 1, 2]]), 8, layers=bad)


def test_more_layers_than_surfaces_are_empty():
    clip = torch.tensor([[[-1, -1, 0, 1], [1, -1, 0, 1], [0, 1, 0, 1.0]]], requires_grad=True)
    frags = tr.rasterize(clip, torch.tensor([[0, 1, 2]]), (8, 8), layers=3, derivatives=True)
    assert (frags.face_id >= 0).any()
    for layer in frags.layers[1:]:
        assert layer.face_id.shape == (1, 8, 8) and (layer.face_id == -1).all()
        assert torch.isinf(layer.depth).all() and (layer.bary == 0).all()
        assert layer.bary.shape == (1, 8, 8, 3) and layer.mask.sum() == 0
        assert (layer.bary_dx == 0).all()
        assert tr.interpolate(torch.ones(3, 2), layer, torch.tensor([[0, 1, 2]])).sum() == 0
    (frags.layers[0].bary.sum() + frags.layers[2].bary.sum()).backward()  # empty layers: ok
    assert torch.isfinite(clip.grad).all()


# ------------------------------------------------------------------ against the brute force


def test_duplicates_get_one_layer_each_in_face_order():
    """The same triangle listed three times (rotated vertices) plus one nearer triangle: the
    exact depth ties are ordered by face index, and every copy is its own layer."""
    v = torch.tensor([[-0.9, -0.8, 0.2, 1], [0.8, -0.9, 0.2, 1], [0.1, 0.9, 0.6, 1],
                      [-0.5, -0.5, -0.3, 1], [0.5, -0.5, -0.3, 1], [0, 0.5, -0.3, 1]])
    faces = torch.tensor([[1, 2, 0], [3, 4, 5], [0, 1, 2], [2, 0, 1]])
    frags = tr.rasterize(v[None], faces, (32, 32), layers=5)
    ref_ids, _ = k_nearest_reference(v[None], faces, (32, 32), 5)
    assert _unexplained(frags, ref_ids, v[None], faces, (32, 32)) == []
    inner = frags.face_id[0] == 1  # the nearer triangle
    stack = torch.stack([layer.face_id[0] for layer in frags.layers])
    assert inner.any()
    assert (stack[:, inner] == torch.tensor([1, 0, 2, 3, -1])[:, None]).all()
    only = (frags.face_id[0] == 0)
    assert only.any() and (stack[:, only] == torch.tensor([0, 2, 3, -1, -1])[:, None]).all()
    # the copies' depths and barycentrics agree (same plane, same pixel)
    assert torch.allclose(frags.layers[1].depth[0][inner], frags.layers[2].depth[0][inner])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_soups_match_k_nearest_reference(seed):
    gen = torch.Generator().manual_seed(seed)
    clip, faces, _ = ref.random_soup(gen, 2, 60)
    res, k = (36, 44), 4
    frags = tr.rasterize(clip, faces, res, layers=k)  # float64 visibility
    ref_ids, ref_depth = k_nearest_reference(clip, faces, res, k)
    eng = torch.stack([layer.face_id for layer in frags.layers])
    assert (ref_ids[1] >= 0).sum() > 50  # the soup really has several layers
    assert (eng == ref_ids).all(0).double().mean() > 0.995
    assert _unexplained(frags, ref_ids, clip, faces, res) == []
    for layer, ids, z in zip(frags.layers, ref_ids, ref_depth, strict=True):
        agree = (layer.face_id == ids) & (ids >= 0)
        assert torch.allclose(layer.depth[agree], z[agree], atol=1e-9)


def test_random_soup_float32_and_chunking():
    """float32 visibility with a tiny memory budget (many chunks arrive in arbitrary depth
    order): same layers as one big chunk, and the brute force agrees."""
    gen = torch.Generator().manual_seed(5)
    clip, faces, _ = ref.random_soup(gen, 1, 80)
    clip = clip.float()
    res = (40, 40)
    big = tr.rasterize(clip, faces, res, layers=6)
    small = tr.rasterize(clip, faces, res, layers=6, memory_budget=1, tile=4)
    for a, b in zip(big.layers, small.layers, strict=True):
        assert torch.equal(a.face_id, b.face_id) and torch.equal(a.depth, b.depth)
    ref_ids, _ = k_nearest_reference(clip, faces, res, 6)
    assert _unexplained(big, ref_ids, clip, faces, res) == []


def test_closed_sphere_front_then_back():
    clip, faces = _sphere_clip()
    frags = tr.rasterize(clip, faces, (64, 64), layers=3)
    front, back, third = frags.layers
    covered = front.face_id >= 0
    assert covered.sum() > 500
    assert torch.equal(covered, back.face_id >= 0)  # watertight: every ray enters and leaves
    assert (third.face_id == -1).all()
    assert front.front_facing.all() and not back.front_facing.any()
    assert (back.depth[covered] > front.depth[covered]).all()
    ref_ids, _ = k_nearest_reference(clip, faces, (64, 64), 3)
    assert _unexplained(frags, ref_ids, clip, faces, (64, 64)) == []
    culled = tr.rasterize(clip, faces, (64, 64), cull_backfaces=True, layers=2)
    assert torch.equal(culled.face_id, front.face_id) and (culled.layers[1].face_id < 0).all()


def test_batch_face_ranges_and_derivatives_per_layer():
    clip, faces = _sphere_clip(2)
    f = faces.shape[0]
    clip2 = torch.cat([clip, clip * torch.tensor([1.0, 1.0, 1.0, 1.3])])
    ranges = torch.tensor([[0, f], [0, f // 2]])
    frags = tr.rasterize(clip2, faces, (32, 32), face_ranges=ranges, layers=2,
                         derivatives=True)
    for k, layer in enumerate(frags.layers):
        for b in range(2):
            one = tr.rasterize(clip2[b:b + 1], faces[: ranges[b, 1]], (32, 32), layers=2,
                               derivatives=True).layers[k]
            assert torch.equal(layer.face_id[b:b + 1], one.face_id)
            assert torch.allclose(layer.bary[b:b + 1], one.bary)
            assert torch.allclose(layer.bary_dx[b:b + 1], one.bary_dx)


def test_back_layer_is_differentiable():
    """gradcheck of the second layer's barycentrics and depth w.r.t. clip positions."""
    clip = torch.tensor([[[-0.9, -0.8, 0.1, 1.0], [0.8, -0.7, 0.2, 1.1], [0.0, 0.9, 0.3, 0.9],
                          [-0.6, -0.6, -0.2, 1.0], [0.7, -0.5, -0.3, 1.2],
                          [0.1, 0.8, -0.1, 1.0]]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    frags = tr.rasterize(clip, faces, (8, 8), layers=2)
    assert (frags.layers[1].face_id == 0).sum() > 10

    def f(c):
        back = tr.rasterize(c, faces, (8, 8), layers=2).layers[1]
        return back.bary, torch.where(back.face_id >= 0, back.depth, 0.0)

    assert torch.autograd.gradcheck(f, (clip.clone().requires_grad_(True),))


def test_layers_on_device_name_their_factories(device, dtype):
    from test_device import _FactoriesWithoutDevice

    clip, faces = _sphere_clip(2, dtype)
    clip, faces = clip.to(device), faces.to(device)
    mode = _FactoriesWithoutDevice()
    with mode:
        frags = tr.rasterize(clip, faces, (32, 32), layers=3, derivatives=True)
        back = frags.layers[1]
        _ = back.bary, back.depth, back.bary_dx
    assert not mode.found, sorted(mode.found)
    assert back.face_id.device.type == torch.device(device).type and back.bary.dtype == dtype
    assert (back.face_id >= 0).sum() > 100
