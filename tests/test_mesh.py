"""Mesh record, normals, tangents, transforms and packing against independent references."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from torchraster.material import Material
from torchraster.mesh import (
    NORMAL_EPS,
    Mesh,
    face_normals,
    flat,
    pack_meshes,
    transform_normals,
    transform_points,
    transform_tangents,
    vertex_normals,
    vertex_tangents,
)


def icosphere(subdivisions: int = 3, dtype: torch.dtype = torch.float64):
    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    return torch.tensor(s.vertices, dtype=dtype), torch.tensor(s.faces, dtype=torch.int64)


def grid_plane(n: int = 5, dtype: torch.dtype = torch.float64):
    """(n*n) vertices on z = 0 in [0, 1]^2, CCW faces (normal +z)."""
    xs = torch.linspace(0, 1, n, dtype=dtype)
    y, x = torch.meshgrid(xs, xs, indexing="ij")
    pos = torch.stack([x.reshape(-1), y.reshape(-1), torch.zeros(n * n, dtype=dtype)], -1)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            faces += [[a, b, d], [a, d, c]]
    return pos, torch.tensor(faces, dtype=torch.int64)


# ------------------------------------------------------------------------------ Mesh record
def test_mesh_validation_errors() -> None:
    pos, faces = grid_plane(3, torch.float32)
    Mesh(pos, faces)  # ok
    with pytest.raises(ValueError, match="positions"):
        Mesh(pos[:, :2], faces)
    with pytest.raises(ValueError, match="faces"):
        Mesh(pos, faces[:, :2])
    with pytest.raises(ValueError, match=r"faces: vertex indices must be in \[0, 9\)"):
        Mesh(pos, faces + 5)
    with pytest.raises(ValueError, match="faces"):
        Mesh(pos, faces - 1)
    with pytest.raises(TypeError, match="faces"):
        Mesh(pos, faces.float())
    bad = pos.clone()
    bad[2, 1] = float("nan")
    with pytest.raises(ValueError, match="positions: contains 1 NaN"):
        Mesh(bad, faces)
    with pytest.raises(ValueError, match="normals"):
        Mesh(pos, faces, normals=pos[:-1])
    with pytest.raises(ValueError, match="normals: expected dtype"):
        Mesh(pos, faces, normals=pos.double())
    with pytest.raises(ValueError, match="uvs"):
        Mesh(pos, faces, uvs=pos)
    with pytest.raises(ValueError, match="tangents"):
        Mesh(pos, faces, tangents=pos)
    with pytest.raises(TypeError, match="material"):
        Mesh(pos, faces, material="red")
    with pytest.raises(TypeError, match="positions"):
        Mesh(pos.numpy(), faces)
    assert Mesh(pos, faces.int()).faces.dtype == torch.int64


def test_mesh_to_dtype() -> None:
    pos, faces = grid_plane(3, torch.float32)
    m = Mesh(pos, faces, normals=vertex_normals(pos, faces), uvs=pos[:, :2],
             material=Material(base_color_texture=torch.zeros(3, 2, 2, dtype=torch.uint8)))
    m64 = m.to(dtype=torch.float64)
    assert m64.positions.dtype == m64.normals.dtype == m64.uvs.dtype == torch.float64
    assert m64.faces.dtype == torch.int64
    assert m64.material.base_color_texture.dtype == torch.uint8
    assert torch.equal(m64.positions.float(), m.positions)
    with pytest.raises(ValueError, match="dtype"):
        m.to(dtype=torch.int32)


# ------------------------------------------------------------------------------- normals
def test_face_normals_ccw_and_batched() -> None:
    pos = torch.tensor([[0.0, 0, 0], [2, 0, 0], [0, 3, 0], [0, 0, 5]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 1], [0, 3, 1]])
    n = face_normals(pos, faces)
    assert n.shape == (3, 3)
    torch.testing.assert_close(n, torch.tensor([[0.0, 0, 1], [0, 0, -1], [0, 1, 0]]))
    nb = face_normals(torch.stack([pos, -pos]), faces)
    assert nb.shape == (2, 3, 3)
    torch.testing.assert_close(nb[1], n)  # point reflection keeps cross products


def test_smooth_normals_of_icosphere_are_radial() -> None:
    """Area weighting is first-order accurate: the error halves per subdivision and is
    < 1e-3 at 327k faces (at icosphere(3), 1280 faces, it is 1.2e-2 at the vertices with
    the most irregular one-ring)."""
    errors = {}
    for sub in (3, 4, 7):
        pos, faces = icosphere(sub, torch.float32)
        n = vertex_normals(pos, faces)
        radial = pos / pos.norm(dim=-1, keepdim=True)
        errors[sub] = float((n - radial).norm(dim=-1).max())
        torch.testing.assert_close(n.norm(dim=-1), torch.ones(len(pos)))
    assert errors[7] < 1e-3
    assert 1.8 < errors[3] / errors[4] < 2.2


def test_vertex_normals_match_brute_force_area_weighting() -> None:
    g = torch.Generator().manual_seed(1)
    pos = torch.randn(12, 3, generator=g, dtype=torch.float64)
    faces = torch.randint(0, 12, (30, 3), generator=g)
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                  & (faces[:, 0] != faces[:, 2])]
    p, f = pos.numpy(), faces.numpy()
    ref = np.zeros_like(p)
    for a, b, c in f:  # each corner gets 2 * area * unit normal = cross product
        cr = np.cross(p[b] - p[a], p[c] - p[a])
        ref[a] += cr
        ref[b] += cr
        ref[c] += cr
    lens = np.linalg.norm(ref, axis=1, keepdims=True)
    used = lens[:, 0] > 0
    ref[used] /= lens[used]
    got = vertex_normals(pos, faces).numpy()
    np.testing.assert_allclose(got, ref, atol=1e-12)


def test_vertex_normals_gradcheck_float64() -> None:
    pos, faces = icosphere(0)
    pos = (pos + 0.1 * torch.randn_like(pos)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: vertex_normals(p, faces), (pos,))
    batch = torch.stack([pos.detach(), 2 * pos.detach()]).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: face_normals(p, faces), (batch,))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_degenerate_faces_give_zero_normals_and_finite_grads(dtype: torch.dtype) -> None:
    pos = torch.tensor(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 2, 2], [2, 2, 2], [5, 5, 5], [9, 9, 9],
         [0, 0, 0], [1e-9, 0, 0], [0, 1e-9, 0]], dtype=dtype, requires_grad=True)
    # face 1: two coincident vertices; face 2: collinear; face 3: 1e-9 sized (|n|^2 = 1e-36);
    # vertex 6 is used only by the collinear face
    faces = torch.tensor([[0, 1, 2], [3, 4, 0], [3, 5, 6], [7, 8, 9]])
    vn = vertex_normals(pos, faces)
    fn = face_normals(pos, faces)
    assert torch.isfinite(vn).all() and torch.isfinite(fn).all()
    assert torch.equal(fn[1:], torch.zeros(3, 3, dtype=dtype))
    assert torch.equal(vn[6], torch.zeros(3, dtype=dtype))
    (vn.sum() + fn.sum() + (vn * torch.randn_like(vn)).sum()).backward()
    assert torch.isfinite(pos.grad).all()


def test_small_but_valid_faces_keep_their_normal() -> None:
    """NORMAL_EPS only removes faces far below any realistic scale (1e-6 edges are fine)."""
    s = 1e-6
    pos = torch.tensor([[0, 0, 0], [s, 0, 0], [0, s, 0]], dtype=torch.float32)
    assert s**4 > NORMAL_EPS
    torch.testing.assert_close(face_normals(pos, torch.tensor([[0, 1, 2]]))[0],
                               torch.tensor([0.0, 0, 1]))


def test_flat_unwelds_with_face_normals() -> None:
    pos, faces = icosphere(1, torch.float32)
    m = Mesh(pos, faces, normals=vertex_normals(pos, faces), uvs=pos[:, :2].contiguous())
    fm = flat(m)
    assert fm.num_vertices == 3 * m.num_faces and fm.num_faces == m.num_faces
    torch.testing.assert_close(fm.positions[fm.faces], pos[faces])
    torch.testing.assert_close(fm.uvs[fm.faces], m.uvs[faces])
    fn = face_normals(pos, faces)
    torch.testing.assert_close(fm.normals[fm.faces[:, 1]], fn)
    torch.testing.assert_close(face_normals(fm.positions, fm.faces), fn)


# ------------------------------------------------------------------------------ tangents
def _rotation(seed: int) -> torch.Tensor:
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(seed),
                                       dtype=torch.float64))
    return q * torch.sign(torch.linalg.det(q))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_tangents_on_uv_mapped_plane_are_analytic(seed: int) -> None:
    """uv = A (x, y) + c on a rotated plane: T = R [A^-1 e_u, 0], w = sign(det A)."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(2, 2, generator=g, dtype=torch.float64)
    if seed == 1:
        a[0] = -a[0]  # include a mirrored mapping
    pos, faces = grid_plane(4)
    uvs = pos[:, :2] @ a.T + torch.randn(2, generator=g, dtype=torch.float64)
    r = _rotation(seed)
    pos3 = pos @ r.T
    normal = r[:, 2].expand(len(pos), 3)
    t = vertex_tangents(pos3, uvs, normal, faces)
    ainv = torch.linalg.inv(a)
    t_ref = torch.cat([ainv[:, 0], torch.zeros(1, dtype=torch.float64)]) @ r.T
    t_ref = t_ref / t_ref.norm()
    torch.testing.assert_close(t[:, :3], t_ref.expand_as(t[:, :3]), atol=1e-10, rtol=0)
    w = torch.sign(torch.linalg.det(a))
    assert torch.all(t[:, 3] == w)
    # the bitangent cross(N, T) * w points along dP/dv
    b = torch.linalg.cross(normal, t[:, :3], dim=-1) * t[:, 3:]
    dpdv = torch.cat([ainv[:, 1], torch.zeros(1, dtype=torch.float64)]) @ r.T
    assert torch.all(b @ dpdv > 0)


def test_tangents_axis_aligned_plane() -> None:
    pos, faces = grid_plane(3)
    nrm = torch.tensor([0.0, 0, 1], dtype=torch.float64).expand(len(pos), 3)
    t = vertex_tangents(pos, pos[:, :2], nrm, faces)
    torch.testing.assert_close(t, torch.tensor([1.0, 0, 0, 1], dtype=torch.float64)
                               .expand_as(t))
    mirrored = pos[:, :2] * torch.tensor([-1.0, 1.0], dtype=torch.float64)
    t = vertex_tangents(pos, mirrored, nrm, faces)
    torch.testing.assert_close(t, torch.tensor([-1.0, 0, 0, -1], dtype=torch.float64)
                               .expand_as(t))


def test_tangents_with_degenerate_uvs_are_finite_unit_and_perpendicular() -> None:
    pos, faces = icosphere(1)
    nrm = vertex_normals(pos, faces)
    uvs = torch.zeros(len(pos), 2, dtype=torch.float64, requires_grad=True)
    p = pos.clone().requires_grad_(True)
    t = vertex_tangents(p, uvs, nrm, faces)
    assert torch.isfinite(t).all()
    torch.testing.assert_close(t[:, :3].norm(dim=-1), torch.ones(len(pos), dtype=torch.float64))
    assert (t[:, :3] * nrm).sum(-1).abs().max() < 1e-12
    t.sum().backward()
    assert torch.isfinite(p.grad).all() and torch.isfinite(uvs.grad).all()


# ---------------------------------------------------------------------------- transforms
def test_transform_points_matches_numpy_and_broadcasts() -> None:
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(7, 3, generator=g, dtype=torch.float64)
    m = torch.randn(2, 4, 4, generator=g, dtype=torch.float64)
    out = transform_points(pts, m)
    assert out.shape == (2, 7, 4)
    ref = np.einsum("bij,vj->bvi", m.numpy(), np.c_[pts.numpy(), np.ones(7)])
    np.testing.assert_allclose(out.numpy(), ref, atol=1e-12)
    out1 = transform_points(pts.expand(2, 7, 3), m[0])
    np.testing.assert_allclose(out1[1].numpy(), ref[0], atol=1e-12)
    with pytest.raises(ValueError, match="batch sizes differ"):
        transform_points(torch.randn(3, 7, 3, dtype=torch.float64), m)
    with pytest.raises(ValueError, match="matrix"):
        transform_points(pts, m[:, :3])
    with pytest.raises(ValueError, match="dtype"):
        transform_points(pts.float(), m)


@pytest.mark.parametrize("mirror", [False, True])
def test_transform_normals_match_transformed_geometry(mirror: bool) -> None:
    """Face normals of the transformed mesh equal the transformed face normals (affine M,
    non-uniform scale + shear; a mirror also re-winds the faces)."""
    pos, faces = icosphere(1)
    g = torch.Generator().manual_seed(3)
    m = torch.eye(4, dtype=torch.float64)
    m[:3, :3] = torch.diag(torch.tensor([3.0, 0.5, 1.0], dtype=torch.float64)) @ _rotation(5)
    m[0, 1] = 0.7
    m[:3, 3] = torch.randn(3, generator=g, dtype=torch.float64)
    if mirror:
        m[:3, :3] = m[:3, :3] @ torch.diag(torch.tensor([-1.0, 1, 1], dtype=torch.float64))
        faces_t = faces[:, [0, 2, 1]]
    else:
        faces_t = faces
    world = transform_points(pos, m)[:, :3]
    ref = face_normals(world, faces_t)
    got = transform_normals(face_normals(pos, faces), m)
    torch.testing.assert_close(got, ref, atol=1e-12, rtol=0)


def test_transform_normals_singular_matrix_is_finite() -> None:
    n = torch.tensor([[0.0, 0, 1], [1, 0, 0]], requires_grad=True)
    m = torch.diag(torch.tensor([1.0, 1.0, 0.0, 1.0])).requires_grad_(True)
    out = transform_normals(n, m)
    assert torch.isfinite(out).all()
    out.sum().backward()
    assert torch.isfinite(n.grad).all() and torch.isfinite(m.grad).all()


@pytest.mark.parametrize("mirror", [False, True])
def test_transform_tangents_match_recomputed_frames(mirror: bool) -> None:
    pos, faces = grid_plane(4)
    uvs = pos[:, :2] @ torch.tensor([[1.0, 0.3], [-0.2, 0.8]], dtype=torch.float64).T
    nrm = vertex_normals(pos, faces)
    tan = vertex_tangents(pos, uvs, nrm, faces)
    m = torch.eye(4, dtype=torch.float64)
    m[:3, :3] = _rotation(7) @ torch.diag(torch.tensor([2.0, 0.5, 1.5], dtype=torch.float64))
    faces_t = faces
    if mirror:
        m[:3, :3] = m[:3, :3] @ torch.diag(torch.tensor([1.0, -1, 1], dtype=torch.float64))
        faces_t = faces[:, [0, 2, 1]]
    world = transform_points(pos, m)[:, :3]
    nrm_w = transform_normals(nrm, m)
    torch.testing.assert_close(nrm_w, vertex_normals(world, faces_t))
    ref = vertex_tangents(world, uvs, nrm_w, faces_t)
    got = transform_tangents(tan, m)
    assert torch.equal(got[:, 3], ref[:, 3])
    # for non-uniform scale the transformed tangent is not orthogonalised: compare after
    # Gram-Schmidt against the transformed normal
    t = got[:, :3] - nrm_w * (nrm_w * got[:, :3]).sum(-1, keepdim=True)
    torch.testing.assert_close(t / t.norm(dim=-1, keepdim=True), ref[:, :3])


# -------------------------------------------------------------------------------- shapes
def test_outputs_keep_the_batching_of_the_inputs() -> None:
    """Unbatched in, unbatched out: (V, 3) -> (V, 3), never a surprise (1, V, 3); any batched
    input makes the result (B, ...), the others broadcasting. Values are the same either way."""
    pos, faces = icosphere(0)
    v, f = len(pos), len(faces)
    uvs = pos[:, :2].contiguous()
    nrm = vertex_normals(pos, faces)
    tan = vertex_tangents(pos, uvs, nrm, faces)
    m = torch.eye(4, dtype=torch.float64)
    m[:3, 3] = 1.0
    pos_b, uvs_b, nrm_b, tan_b, m_b = (t.expand(2, *t.shape) for t in (pos, uvs, nrm, tan, m))
    cases = [  # (function, unbatched args, batched args (any one batched), per-item shape)
        (face_normals, (pos, faces), [(pos_b, faces)], (f, 3)),
        (vertex_normals, (pos, faces), [(pos_b, faces)], (v, 3)),
        (vertex_tangents, (pos, uvs, nrm, faces),
         [(pos_b, uvs, nrm, faces), (pos, uvs_b, nrm, faces), (pos, uvs, nrm_b, faces)], (v, 4)),
        (transform_points, (pos, m), [(pos_b, m), (pos, m_b)], (v, 4)),
        (transform_normals, (nrm, m), [(nrm_b, m), (nrm, m_b)], (v, 3)),
        (transform_tangents, (tan, m), [(tan_b, m), (tan, m_b)], (v, 4)),
    ]
    for fn, args, batched_args, shape in cases:
        single = fn(*args)
        assert single.shape == shape, (fn.__name__, single.shape)
        for bargs in batched_args:
            out = fn(*bargs)
            assert out.shape == (2, *shape), (fn.__name__, out.shape)
            torch.testing.assert_close(out[1], single)
    assert flat(Mesh(pos.float(), faces, uvs=uvs.float(), tangents=tan.float())).normals.shape \
        == (3 * f, 3)


# ------------------------------------------------------------------------------- packing
def test_pack_meshes_ranges_and_global_indices() -> None:
    a_pos, a_f = icosphere(0, torch.float32)
    b_pos, b_f = grid_plane(3, torch.float32)
    ma = Mesh(a_pos, a_f, uvs=torch.zeros(len(a_pos), 2), material=Material(name="a"))
    mb = Mesh(b_pos, b_f, uvs=torch.ones(len(b_pos), 2))
    pk = pack_meshes([ma, mb, ma])
    assert pk.num_meshes == 3
    assert pk.positions.shape == (2 * len(a_pos) + len(b_pos), 3)
    assert pk.faces.shape == (2 * len(a_f) + len(b_f), 3)
    for i, m in enumerate([ma, mb, ma]):
        f0, f1 = pk.face_ranges[i].tolist()
        v0, v1 = pk.vertex_ranges[i].tolist()
        assert f1 - f0 == m.num_faces and v1 - v0 == m.num_vertices
        torch.testing.assert_close(pk.positions[pk.faces[f0:f1]], m.positions[m.faces])
        assert pk.faces[f0:f1].min() >= v0 and pk.faces[f0:f1].max() < v1
        assert torch.all(pk.face_mesh[f0:f1] == i)
    assert pk.normals is None and pk.uvs.shape == (len(pk.positions), 2)
    assert pk.materials[0].name == "a" and pk.materials[1] is None
    with pytest.raises(ValueError, match="meshes"):
        pack_meshes([])
    with pytest.raises(TypeError, match=r"meshes\[1\]"):
        pack_meshes([ma, "x"])
    with pytest.raises(ValueError, match=r"meshes\[1\]"):
        pack_meshes([ma, mb.to(dtype=torch.float64)])


def test_packed_meshes_render_like_separate_meshes() -> None:
    """The face_ranges convention end to end: item b of a packed batch rasterizes exactly
    what mesh b alone rasterizes."""
    import torchraster as tr
    from torchraster import camera

    a_pos, a_f = icosphere(1, torch.float32)
    b_pos, b_f = grid_plane(4, torch.float32)
    meshes = [Mesh(a_pos, a_f), Mesh(b_pos - 0.5, b_f)]
    pk = pack_meshes(meshes)
    mvp = camera.perspective(40.0, 1.0, 0.1, 10.0) @ camera.look_at([0.3, 0.4, 3.0], [0, 0, 0])
    clip = transform_points(pk.positions, mvp.expand(2, 4, 4))
    frags = tr.rasterize(clip, pk.faces, (32, 32), face_ranges=pk.face_ranges)
    for i, m in enumerate(meshes):
        alone = tr.rasterize(transform_points(m.positions, mvp), m.faces, (32, 32))
        start = int(pk.face_ranges[i, 0])
        expect = torch.where(alone.face_id >= 0, alone.face_id + start, alone.face_id)
        assert torch.equal(frags.face_id[i], expect[0])
        assert (alone.face_id >= 0).sum() > 20
