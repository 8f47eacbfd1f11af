"""Object identity and label channels: instance, semantic, object_coords (NOCS), distance,
amodal; RenderScene.from_objects; supersampled labels; errors.

References are independent of the engine: the float64 brute-force rasterizer
(torchraster.testing.reference_raster) with face -> object maps built here in numpy,
analytic ray-plane intersections, and torch.autograd.gradcheck."""

import math

import numpy as np
import pytest
import torch
import trimesh

import torchraster as tr
from torchraster.io import Scene
from torchraster.mesh import Mesh
from torchraster.scene import as_render_scene, nocs_coords
from torchraster.testing.reference_raster import (
    look_at_matrix,
    perspective_matrix,
    reference_rasterize,
    to_clip,
)

F64 = torch.float64
EYE = torch.tensor([0.3, 1.2, 4.0], dtype=F64)
ALL = ["instance", "semantic", "object_coords", "distance", "amodal", "face_id"]


def _camera(h: int, w: int, fov: float = 50.0):
    view = look_at_matrix(EYE, torch.tensor([0.0, 0.0, 0.0], dtype=F64),
                          torch.tensor([0.0, 1.0, 0.0], dtype=F64))
    proj = perspective_matrix(fov, w / h, 0.1, 50.0)
    return view, proj


def _rotation(axis: str, degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    i, j = {"x": (1, 2), "y": (0, 2), "z": (0, 1)}[axis]
    m = np.eye(4)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


def _objects():
    """Three overlapping boxes (model space) with their model -> world matrices (numpy) and
    categories; box 2 sits behind box 1 and is partly hidden by it."""
    meshes, mats = [], []
    for size, axis, deg, t in (((1.0, 1.0, 1.0), "y", 30.0, (-0.5, 0.0, 0.5)),
                               ((1.6, 0.8, 0.6), "x", 20.0, (0.2, 0.1, -0.8)),
                               ((0.6, 1.4, 0.6), "z", -15.0, (1.1, 0.2, 0.0))):
        box = trimesh.creation.box(size)
        meshes.append(Mesh(torch.tensor(box.vertices, dtype=F64),
                           torch.tensor(box.faces, dtype=torch.int64)))
        m = _rotation(axis, deg)
        m[:3, 3] = t
        mats.append(m)
    return meshes, np.stack(mats), [3, 7, 3]


def _world_numpy(meshes, mats):
    """World positions and faces of the merged objects, and the object id of each face,
    built here in numpy (independent of from_objects)."""
    pos, faces, obj, offset = [], [], [], 0
    for k, (mesh, m) in enumerate(zip(meshes, mats, strict=True)):
        v = mesh.positions.numpy()
        pos.append(v @ m[:3, :3].T + m[:3, 3])
        faces.append(mesh.faces.numpy() + offset)
        obj.append(np.full(mesh.faces.shape[0], k + 1))
        offset += v.shape[0]
    return np.concatenate(pos), np.concatenate(faces), np.concatenate(obj)


def _reference_face_id(pos: np.ndarray, faces: np.ndarray, h: int, w: int) -> np.ndarray:
    view, proj = _camera(h, w)
    clip = to_clip(torch.tensor(pos), proj @ view)[None]
    return reference_rasterize(clip, torch.tensor(faces), (h, w)).face_id[0].numpy()


def _render(scene, h: int, w: int, channels, supersample: int = 1, **kwargs):
    view, proj = _camera(h, w)
    renderer = tr.Renderer((h, w),
                           shading="unlit",
                           **kwargs,
                           raster=tr.RasterSettings(supersample=supersample))
    return renderer(scene, view, proj, channels=channels)


# ------------------------------------------------------------------------ RenderScene
def test_nocs_coords_of_a_box_are_its_normalised_corners():
    corners = torch.tensor([[x, y, z] for x in (-1.0, 3.0) for y in (0.0, 2.0)
                            for z in (5.0, 5.5)], dtype=F64)
    out = nocs_coords(corners)
    diag = math.sqrt(4**2 + 2**2 + 0.5**2)
    expected = (corners - torch.tensor([1.0, 1.0, 5.25], dtype=F64)) / diag + 0.5
    torch.testing.assert_close(out, expected, rtol=0, atol=1e-15)
    assert float(out.min()) >= 0 and float(out.max()) <= 1
    # the longest extent spans 4 / diag of the unit range, centred on 0.5
    assert math.isclose(float(out[:, 0].max() - out[:, 0].min()), 4 / diag, abs_tol=1e-15)
    assert torch.equal(nocs_coords(torch.ones(3, 3)), torch.full((3, 3), 0.5))


def test_from_objects_merges_meshes_with_identity():
    meshes, mats, cats = _objects()
    mats[2] = mats[2] @ np.diag([-1.0, 1.0, 1.0, 1.0])  # a mirror: faces must be re-wound
    scene = tr.RenderScene.from_objects(meshes, torch.tensor(mats), cats)
    pos, faces, obj = _world_numpy(meshes, mats)
    np.testing.assert_allclose(scene.positions.numpy(), pos, atol=1e-12)
    assert np.array_equal(scene.face_object.numpy(), obj)
    assert scene.object_category.tolist() == [0, *cats] and scene.num_objects == 3
    counts = [m.num_faces for m in meshes]
    ends = np.cumsum(counts)
    assert scene.object_face_ranges().tolist() == [[int(e - c), int(e)] for e, c in
                                                   zip(ends, counts, strict=True)]
    # mirrored object: same triangles, opposite index order, so still counter-clockwise
    lo, hi = ends[1], ends[2]
    assert np.array_equal(scene.faces[lo:hi].numpy(), faces[lo:hi][:, [0, 2, 1]])
    assert np.array_equal(scene.faces[:lo].numpy(), faces[:lo])
    # NOCS from model space: unchanged by the transforms
    start = meshes[0].num_vertices
    torch.testing.assert_close(scene.object_coords[start:start + meshes[1].num_vertices],
                               nocs_coords(meshes[1].positions))
    moved = scene.to("cpu")
    assert torch.equal(moved.face_object, scene.face_object)
    assert torch.equal(moved.object_coords, scene.object_coords)


def test_from_objects_transforms_normals_by_the_inverse_transpose():
    tri = Mesh(torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=F64),
               torch.tensor([[0, 1, 2]]),
               normals=torch.tensor([[1.0, 1.0, 0.0]] * 3, dtype=F64) / math.sqrt(2))
    m = np.diag([3.0, 1.0, 1.0, 1.0]) @ _rotation("z", 10.0)
    scene = tr.RenderScene.from_objects([tri], torch.tensor(m)[None])
    n = np.linalg.inv(m[:3, :3]).T @ (np.array([1.0, 1.0, 0.0]) / math.sqrt(2))
    np.testing.assert_allclose(scene.normals[0].numpy(), n / np.linalg.norm(n), atol=1e-12)
    assert scene.object_category is None and scene.face_object.tolist() == [1]


def test_io_scene_instances_become_objects():
    meshes, mats, _ = _objects()
    loaded = Scene([meshes[0], meshes[1], meshes[0]], torch.tensor(mats),
                   ["a", "b", "c"])
    scene = as_render_scene(loaded)
    _, _, obj = _world_numpy([meshes[0], meshes[1], meshes[0]], mats)
    assert np.array_equal(scene.face_object.numpy(), obj)
    assert scene.object_category is None
    nv = meshes[0].num_vertices
    torch.testing.assert_close(scene.object_coords[-nv:], nocs_coords(meshes[0].positions))


# ------------------------------------------------------------------ instance / semantic
def test_instance_and_semantic_match_the_reference_rasterizer():
    h, w = 36, 44
    meshes, mats, cats = _objects()
    scene = tr.RenderScene.from_objects(meshes, torch.tensor(mats), cats)
    out = _render(scene, h, w, ["instance", "semantic", "face_id"])
    pos, faces, obj = _world_numpy(meshes, mats)
    fid = _reference_face_id(pos, faces, h, w)
    obj_ref = np.where(fid >= 0, np.concatenate([[0], obj])[fid + 1], 0)
    cat_ref = np.array([0, *cats])[obj_ref]
    inst = out.gbuffer["instance"][0, 0].numpy()
    assert out.gbuffer["instance"].dtype == torch.int64
    assert set(np.unique(obj_ref)) == {0, 1, 2, 3}  # every object is seen
    assert np.array_equal(inst, obj_ref)
    assert np.array_equal(out.gbuffer["semantic"][0, 0].numpy(), cat_ref)
    assert np.array_equal(out.gbuffer["face_id"][0, 0].numpy(), fid)


def test_labels_follow_the_first_opaque_layer_of_cutouts():
    meshes, mats, cats = _objects()
    front = tr.Material(base_color_factor=torch.tensor([1.0, 1.0, 1.0, 0.2]),
                        alpha_mode="MASK", alpha_cutoff=0.5)
    cut = Mesh(meshes[0].positions, meshes[0].faces, material=front)
    h, w = 36, 44
    out = _render(tr.RenderScene.from_objects([cut, *meshes[1:]], torch.tensor(mats), cats),
                  h, w, ["instance", "distance"])
    pos, faces, obj = _world_numpy(meshes[1:], mats[1:])  # object 1 is cut out entirely
    fid = _reference_face_id(pos, faces, h, w)
    assert np.array_equal(out.gbuffer["instance"][0, 0].numpy(),
                          np.where(fid >= 0, obj[fid] + 1, 0))
    assert bool(((out.gbuffer["distance"] > 0) == (out.gbuffer["instance"] > 0)).all())


# --------------------------------------------------------------- object_coords, distance
def _plane_scene(dtype=F64):
    """A 4 x 2 quad (model z = 0) tilted, its centre at the world origin (the view's
    target); returns the scene, its model -> world matrix and model-space corners."""
    corners = torch.tensor([[0.0, 0, 0], [4, 0, 0], [4, 2, 0], [0, 2, 0]], dtype=dtype)
    quad = Mesh(corners, torch.tensor([[0, 1, 2], [0, 2, 3]]))
    m = _rotation("x", -35.0) @ _rotation("y", 20.0)
    m[:3, 3] = -m[:3, :3] @ np.array([2.0, 1.0, 0.0])
    return tr.RenderScene.from_objects([quad], torch.tensor(m, dtype=dtype)[None]), m, corners


def _ray_plane(h: int, w: int, m: np.ndarray, fov: float = 50.0):
    """Per pixel centre: the float64 world hit of the eye ray with the quad's plane, its
    model-space point, and whether it lies inside the 4 x 2 quad."""
    view, _ = _camera(h, w, fov)
    view = view.numpy()
    t = math.tan(math.radians(fov) / 2)
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    x = (2 * (jj + 0.5) / w - 1) * t * w / h
    y = (1 - 2 * (ii + 0.5) / h) * t
    d_view = np.stack([x, y, -np.ones_like(x)], -1)
    d = d_view @ view[:3, :3]  # R^T d for row vectors
    eye = EYE.numpy()
    normal, origin = m[:3, 2], m[:3, 3]
    s = ((origin - eye) @ normal) / (d @ normal)
    hit = eye + s[..., None] * d
    model = (hit - m[:3, 3]) @ m[:3, :3]  # R^T (hit - t)
    inside = ((model[..., 0] > 1e-6) & (model[..., 0] < 4 - 1e-6) & (model[..., 1] > 1e-6)
              & (model[..., 1] < 2 - 1e-6) & (s > 0))
    return hit, model, inside


def test_object_coords_and_distance_are_the_analytic_visible_point():
    h, w = 15, 17  # odd: the centre pixel lies on the optical axis
    scene, m, _ = _plane_scene()
    out = _render(scene, h, w, ["object_coords", "distance", "depth"])
    hit, model, inside = _ray_plane(h, w, m)
    covered = out.gbuffer["distance"][0, 0].numpy() > 0
    assert inside.sum() > 50 and np.array_equal(covered, inside)
    nocs = (model - np.array([2.0, 1.0, 0.0])) / math.sqrt(20) + 0.5
    got = out.gbuffer["object_coords"][0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(got[inside], nocs[inside], atol=1e-10)
    assert not got[~inside].any()
    dist = np.linalg.norm(hit - EYE.numpy(), axis=-1)
    np.testing.assert_allclose(out.gbuffer["distance"][0, 0].numpy()[inside], dist[inside],
                               rtol=1e-10)
    c = (h // 2, w // 2)
    assert inside[c]
    assert math.isclose(float(out.gbuffer["distance"][0, 0][c]),
                        float(out.gbuffer["depth"][0, 0][c]), rel_tol=1e-12)
    off_axis = inside.copy()
    off_axis[c] = False
    assert bool((out.gbuffer["distance"][0, 0].numpy()[off_axis]
                 > out.gbuffer["depth"][0, 0].numpy()[off_axis]).all())


def test_distance_and_object_coords_gradcheck_wrt_positions():
    h, w = 5, 6
    scene, _, _ = _plane_scene()
    view, proj = _camera(h, w)
    renderer = tr.Renderer((h, w), shading="unlit")

    def labels(positions):
        s = tr.RenderScene(positions, scene.faces, face_object=scene.face_object,
                           object_coords=scene.object_coords)
        gb = renderer(s, view, proj, channels=["distance", "object_coords"]).gbuffer
        return gb["distance"], gb["object_coords"]

    pos = scene.positions.clone().requires_grad_(True)
    dist, coords = labels(pos)
    assert int((dist > 0).sum()) >= 10  # covered pixels away from the diagonal and the rim
    assert torch.autograd.gradcheck(labels, (pos,), eps=1e-6, atol=1e-6)


# ------------------------------------------------------------------------------ amodal
def test_amodal_is_each_object_rendered_alone():
    h, w = 36, 44
    meshes, mats, cats = _objects()
    scene = tr.RenderScene.from_objects(meshes, torch.tensor(mats), cats)
    out = _render(scene, h, w, ["amodal", "instance"])
    amodal, inst = out.gbuffer["amodal"][0], out.gbuffer["instance"][0, 0]
    assert amodal.shape == (3, h, w) and amodal.dtype == torch.bool
    assert "amodal 3 objects" in out.plan
    for k in range(3):
        pos, faces, _ = _world_numpy([meshes[k]], mats[k:k + 1])
        alone = _reference_face_id(pos, faces, h, w) >= 0
        assert np.array_equal(amodal[k].numpy(), alone), k
        visible = (inst == k + 1).numpy()
        assert not (visible & ~alone).any()  # visible is inside amodal
    hidden = int(amodal[1].sum()) - int((inst == 2).sum())
    assert hidden > 20  # box 2 is partly behind box 1


@pytest.mark.parametrize("case", ["spread", "off-screen and near plane"])
def test_amodal_equals_full_frame_rasters(case):
    """Each object's mask is exactly the object rasterized alone over the whole frame
    (``rasterize_depth`` per object, float32), for objects small and large, partly
    off-screen, wholly off-screen and around the eye, in a batch of views. (Rasterizing
    each object over its pixel box only, through a clip-space crop, was 1.7x cheaper at
    1024² but not exact: float rounding of the cropped coordinates flipped pixel centres on
    edges in 1 of 300 stress scenes.)"""
    from torchraster.raster import rasterize_depth

    g = torch.Generator().manual_seed(7)
    meshes, mats = [], []
    for k in range(7):
        sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.15 + 0.1 * k)
        meshes.append(Mesh(torch.tensor(sphere.vertices, dtype=torch.float32),
                           torch.tensor(sphere.faces, dtype=torch.int64)))
        m = np.eye(4)
        m[:3, 3] = (torch.rand(3, generator=g) * 4 - 2).numpy()
        mats.append(m)
    floor = trimesh.creation.box((20.0, 0.01, 20.0))
    meshes.append(Mesh(torch.tensor(floor.vertices, dtype=torch.float32),
                       torch.tensor(floor.faces, dtype=torch.int64)))
    mats.append(np.eye(4))
    if case != "spread":
        mats[0][:3, 3] = (30.0, 0.0, 0.0)  # outside every view
        mats[1][:3, 3] = (0.0, 0.5, 2.9)  # around the eye of the first view: w <= 0
    scene = tr.RenderScene.from_objects(meshes, torch.tensor(np.stack(mats),
                                                             dtype=torch.float32))
    h, w = 45, 61
    view = tr.camera.orbit(torch.tensor([0.0, 70.0]), torch.tensor([20.0, 35.0]),
                           torch.tensor([3.0, 5.0]))
    proj = tr.camera.perspective(60.0, w / h, 0.05)
    out = tr.Renderer((h, w), shading="unlit")(scene, view, proj, channels=["amodal"])
    amodal = out.gbuffer["amodal"]
    clip = tr.camera.transform_points(scene.positions, proj @ view)
    ranges = scene.object_face_ranges()
    for bi in range(2):
        for k in range(len(meshes)):
            alone = rasterize_depth(clip[bi:bi + 1], scene.faces, (h, w),
                                    face_ranges=ranges[k:k + 1])[0]
            assert torch.equal(amodal[bi, k], torch.isfinite(alone)), (bi, k)
    assert amodal.any((2, 3)).sum() >= 10


def test_amodal_per_batch_item_with_face_ranges():
    meshes, mats, cats = _objects()
    scene = tr.RenderScene.from_objects(meshes, torch.tensor(mats), cats)
    nf = [m.num_faces for m in meshes]
    scene.face_ranges = torch.tensor([[0, nf[0] + nf[1]], [nf[0], sum(nf)]])
    out = _render(scene, 20, 24, ["amodal", "instance"])
    amodal = out.gbuffer["amodal"]
    assert amodal.shape == (2, 3, 20, 24)
    assert not amodal[0, 2].any() and not amodal[1, 0].any()  # not drawn in that item
    assert amodal[0, 0].any() and amodal[1, 2].any()
    assert torch.equal(amodal[0, 1], amodal[1, 1])  # the same object, same camera


def test_labels_are_only_computed_when_requested():
    meshes, mats, cats = _objects()
    scene = tr.RenderScene.from_objects(meshes, torch.tensor(mats), cats)
    out = _render(scene, 8, 8, ["albedo"])
    assert not any(step.startswith("amodal") for step in out.plan)
    gbuffer = next(p for p in out.plan if p.startswith("gbuffer "))
    assert not {"instance", "semantic", "object_coords", "distance", "amodal"} & set(
        gbuffer.split(" ")[1].split(","))


# ------------------------------------------------------------------------ supersampling
@pytest.mark.parametrize("s", [2, 3])
def test_supersampled_labels_are_one_subsample_of_the_full_frame(s):
    h, w = 9, 11
    meshes, mats, cats = _objects()
    scene = tr.RenderScene.from_objects(meshes, torch.tensor(mats), cats)
    view, proj = _camera(h, w)
    small = tr.Renderer((h, w), shading="unlit", raster=tr.RasterSettings(supersample=s))(
        scene, view, proj, channels=ALL + ["albedo"]).gbuffer
    full = tr.Renderer((s * h, s * w), shading="unlit")(
        scene, view, proj, channels=ALL + ["albedo"]).gbuffer
    k = (s - 1) // 2
    for name in ALL:
        assert small[name].shape[-2:] == (h, w)
        assert torch.equal(small[name], full[name][:, :, k::s, k::s]), name
    torch.testing.assert_close(small["albedo"], torch.nn.functional.avg_pool2d(
        full["albedo"], s))  # material channels stay box-filtered


# --------------------------------------------------------------------------- bad input
def _box_scene(**fields):
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    return tr.RenderScene(torch.tensor(box.vertices, dtype=torch.float32),
                          torch.tensor(box.faces, dtype=torch.int64), **fields)


def test_missing_identity_fields_name_the_channel_and_field():
    nf = 12
    with pytest.raises(ValueError, match="'semantic' needs RenderScene.object_category"):
        _render(_box_scene(face_object=torch.ones(nf, dtype=torch.int64)), 8, 8, ["semantic"])
    for channel in ("instance", "amodal"):
        with pytest.raises(ValueError, match=f"'{channel}' needs RenderScene.face_object"):
            _render(_box_scene(), 8, 8, [channel])
    with pytest.raises(ValueError, match="'object_coords' needs RenderScene.object_coords"):
        _render(_box_scene(), 8, 8, ["object_coords"])


@pytest.mark.parametrize("fields, match", [
    ({"face_object": torch.ones(5, dtype=torch.int64)}, r"face_object: expected shape"),
    ({"face_object": torch.ones(12)}, "face_object: expected an integer"),
    ({"face_object": torch.zeros(12, dtype=torch.int64)}, r"face_object: object ids must be"),
    ({"face_object": torch.full((12,), 3), "object_category": torch.tensor([0, 1])},
     r"face_object: object ids must be in \[1, 1\]"),
    ({"face_object": torch.tensor([1] * 4 + [2] * 4 + [1] * 4)}, "contiguous"),
    ({"face_object": torch.ones(12, dtype=torch.int64), "object_category": torch.tensor([1, 1])},
     "object_category: expected"),
    ({"object_category": torch.tensor([0, 1])}, "object_category: needs face_object"),
    ({"object_coords": torch.zeros(3, 3)}, "object_coords: expected V = 8"),
])
def test_bad_identity_fields_are_rejected(fields, match):
    with pytest.raises((ValueError, TypeError), match=match):
        _box_scene(**fields)


def test_from_objects_rejects_bad_arguments():
    meshes, mats, _ = _objects()
    with pytest.raises(ValueError, match="categories: expected 3"):
        tr.RenderScene.from_objects(meshes, torch.tensor(mats), [1, 2])
    with pytest.raises(ValueError, match="object_to_world"):
        tr.RenderScene.from_objects(meshes, torch.tensor(mats[:2]))
    with pytest.raises(TypeError, match=r"meshes\[1\]"):
        tr.RenderScene.from_objects([meshes[0], "box"])
