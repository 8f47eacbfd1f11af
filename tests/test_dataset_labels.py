"""The dataset pipeline end to end (issue 20): YAML config -> ``torchraster render`` /
``render_dataset`` -> label files, manifest records and exports, each checked against an
independent reference: the face -> object map counted from the config's primitives and
mesh file, boxes and pixel counts from numpy, keyframes interpolated by hand, flow from a
float64 reprojection of the written depth, pycocotools / webdataset reading the exports,
and resume / error behaviour through the command line."""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from skimage import io as skio

from torchraster import manifest
from torchraster.cli import main

REPO = Path(__file__).resolve().parents[1]
ENV = (REPO / "torchraster" / "assets" / "envmaps" / "venice_sunset_256.hdr").as_posix()
#: Fields of a record that differ between runs (when, where, how long).
VOLATILE = {"timings", "finished_at", "rank", "host", "config_file"}

# ------------------------------------------------------------------------------ scenes
#: Floor, an animated cube (translation linear in time, 0 -> 90 degrees of yaw), a ball
#: turning about x by quaternion keys and growing, and a cone from a mesh file without a
#: category; 3 frames at 2 fps (t = 0, 0.5, 1), one static camera.
MAIN = """\
categories: [ground, cube, ball]
frames: {count: 3, fps: 2}
scene:
  objects:
    - {name: floor, primitive: plane, size: 5, category: ground}
    - name: cube
      primitive: box
      size: 0.8
      category: cube
      keypoints: [[0, 0, 0.4], [0, 0, -0.4]]
      animation:
        keys:
          - {time: 0, translate: [-0.5, 0.45, 0], rotate_deg: [0, 0, 0]}
          - {time: 1, translate: [0.5, 0.45, 0], rotate_deg: [0, 90, 0]}
    - name: ball
      primitive: sphere
      size: 0.6
      category: ball
      transform: {translate: [1.1, 0.35, 0.7]}
      animation:
        keys:
          - {time: 0, rotation: [1, 0, 0, 0], scale: 1}
          - {time: 1, rotation: [0.7071067811865476, 0.7071067811865476, 0, 0], scale: 2}
    - {name: cone, mesh: cone.obj, transform: {translate: [-1.3, 0.3, -0.6]}}
cameras:
  - name: cam
    look_at: {eye: [0, 2, 4], target: [0, 0.3, 0]}
render:
  resolution: 40
lights:
  - {type: directional, direction: [-1, -1, -1]}
outputs:
  channels: [color, depth, face_id, instance, semantic, amodal]
  formats: [png, npy]
  exports: [coco, nerf, webdataset]
  previews: true
"""

#: A static scene seen by a camera orbiting at 20 degrees per second, 4 fps: flow is camera
#: motion only. BOP export (every object has a category).
ORBIT = """\
categories: [ground, cube, ball]
frames: {count: 3, fps: 4}
scene:
  objects:
    - {name: floor, primitive: plane, size: 5, category: ground}
    - {name: cube, primitive: box, size: 0.8, category: cube,
       transform: {translate: [-0.3, 0.4, 0], rotate_deg: [0, 30, 0]}}
    - {name: ball, primitive: sphere, size: 0.6, category: ball,
       transform: {translate: [0.5, 0.3, 0.7]}}
cameras:
  - name: orbit
    orbit: {azimuth_deg: 10, elevation_deg: 25, distance: 4, target: [0, 0.3, 0],
            degrees_per_second: 20}
render:
  resolution: 32
lights:
  - {type: directional, direction: [-1, -1, -1]}
outputs:
  channels: [color, depth, face_id, instance, amodal, flow_forward, flow_forward_valid]
  formats: [png, npy]
  exports: [bop]
"""

#: A cube translating along x (0.25 per frame) in front of a static camera whose x axis is
#: the world's: every visible point moves fx * 0.25 / Z pixels right.
SLIDE = """\
frames: {count: 3, fps: 4}
scene:
  objects:
    - name: cube
      primitive: box
      size: 0.8
      animation:
        keys:
          - {time: 0, translate: [-0.5, 0, 0], rotate_deg: [0, 20, 0]}
          - {time: 1, translate: [0.5, 0, 0], rotate_deg: [0, 20, 0]}
cameras:
  - name: cam
    look_at: {eye: [0, 0.8, 3.5], target: [0, 0, 0]}
render:
  resolution: 32
  shading: unlit
outputs:
  channels: [depth, face_id, instance, flow_forward, flow_forward_valid, flow_backward,
             motion]
  formats: [npy]
"""


def _cone(folder: Path) -> Path:
    path = folder / "cone.obj"
    trimesh.creation.cone(radius=0.3, height=0.6, sections=8).export(path)
    return path


def _render(out: Path, *configs: Path, extra: tuple[str, ...] = ()) -> int:
    return main(["render", *map(str, configs), "--out", str(out), *extra])


def _records(out: Path) -> dict[str, dict]:
    return {r["key"]: r for r in manifest.read_manifest(out)}


def _npy(out: Path, record: dict, name: str) -> np.ndarray:
    return np.load(out / record["files"][name])


@pytest.fixture(scope="module")
def main_run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("main")
    _cone(root)
    (root / "main.yaml").write_text(MAIN)
    assert _render(root / "out", root / "main.yaml") == 0
    return root


@pytest.fixture(scope="module")
def orbit_run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("orbit")
    (root / "orbit.yaml").write_text(ORBIT)
    assert _render(root / "out", root / "orbit.yaml") == 0
    return root / "out"


@pytest.fixture(scope="module")
def slide_run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("slide")
    (root / "slide.yaml").write_text(SLIDE)
    assert _render(root / "out", root / "slide.yaml") == 0
    return root / "out"


# ------------------------------------------------------------------ 1. ids from the faces
def _obj_triangles(path: Path) -> int:
    """Faces of an OBJ file counted from its text (triangulated: one 'f' line each)."""
    return sum(1 for line in path.read_text().splitlines() if line.startswith("f "))


def test_instance_and_semantic_follow_the_visible_face(main_run):
    out = main_run / "out"
    records = _records(out)
    assert sorted(records) == ["main/00000", "main/00001", "main/00002"]
    # faces per scene entry, in scene order: the plane is 2 triangles, the box 12, the
    # sphere an icosphere of 3 subdivisions (20 * 4^3), the cone its OBJ file's
    counts = [2, 12, 20 * 4 ** 3, _obj_triangles(main_run / "cone.obj")]
    face_to_object = np.concatenate([np.full(n, i + 1) for i, n in enumerate(counts)])
    category_of = np.array([0, 1, 2, 3, 0])  # background, ground, cube, ball, cone (none)
    seen = set()
    for r in records.values():
        face = _npy(out, r, "face_id.npy")[0].astype(np.int64)
        assert face.max() < face_to_object.size
        expected = np.where(face >= 0, face_to_object[np.maximum(face, 0)], 0)
        instance = _npy(out, r, "instance.npy")[0]
        semantic = _npy(out, r, "semantic.npy")[0]
        assert instance.dtype == np.int32 and semantic.dtype == np.int32
        np.testing.assert_array_equal(instance, expected)
        np.testing.assert_array_equal(semantic, category_of[expected])
        for name, ids in (("instance.png", instance), ("semantic.png", semantic)):
            png = skio.imread(out / r["files"][name])
            assert png.dtype == np.uint16
            np.testing.assert_array_equal(png, ids)
        seen |= set(np.unique(instance).tolist())
        assert r["categories"] == ["ground", "cube", "ball"]
        assert [(o["name"], o["category"], o["category_id"]) for o in r["objects"]] == [
            ("floor", "ground", 1), ("cube", "cube", 2), ("ball", "ball", 3), ("cone", None, 0)]
    assert seen == {0, 1, 2, 3, 4}  # every object seen somewhere: the test can fail


# --------------------------------------------------------------- 2. boxes and pixel counts
def _box(mask: np.ndarray) -> list[float] | None:
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if rows.size == 0:
        return None
    return [float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1)]


def test_record_boxes_and_counts_match_the_label_files(main_run):
    out = main_run / "out"
    occluded = 0
    for r in _records(out).values():
        instance = _npy(out, r, "instance.npy")[0]
        amodal = _npy(out, r, "amodal.npy")
        assert amodal.dtype == np.uint8 and amodal.shape == (4, 40, 40)
        assert set(np.unique(amodal).tolist()) <= {0, 1}
        for o in r["objects"]:
            k = o["instance_id"]
            visible, full = instance == k, amodal[k - 1].astype(bool)
            assert not (visible & ~full).any()  # visible is a subset of amodal
            assert o["pixels"] == int(visible.sum())
            assert o["bbox_visible"] == _box(visible)
            assert o["pixels_amodal"] == int(full.sum())
            assert o["bbox_amodal"] == _box(full)
            assert o["visible_fraction"] == pytest.approx(visible.sum() / full.sum())
            occluded += o["pixels"] < o["pixels_amodal"]
    assert occluded >= 3  # the floor behind the others, at least: fractions below 1 tested


# ---------------------------------------------------------------- 3. keyframed poses
def _rot_y(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_x(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _pose(rotation: np.ndarray, translation, scale: float = 1.0) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rotation * scale
    m[:3, 3] = translation
    return m


def test_object_to_world_is_the_hand_interpolated_keyframes(main_run):
    records = _records(main_run / "out")
    for frame in range(3):
        r = records[f"main/{frame:05d}"]
        t = frame / 2
        assert r["frame"] == frame and r["time"] == pytest.approx(t)
        floor, cube, ball, cone = (np.array(o["object_to_world"]) for o in r["objects"])
        # translation linear in time, yaw slerped 0 -> 90 degrees (45 halfway)
        np.testing.assert_allclose(cube, _pose(_rot_y(90 * t), [-0.5 + t, 0.45, 0]),
                                   atol=1e-6)
        # quaternion keys: 0 -> 90 degrees about x, scale 1 -> 2, the transform's translation
        np.testing.assert_allclose(ball, _pose(_rot_x(90 * t), [1.1, 0.35, 0.7], 1 + t),
                                   atol=1e-6)
        np.testing.assert_allclose(floor, np.eye(4), atol=1e-7)
        np.testing.assert_allclose(cone, _pose(np.eye(3), [-1.3, 0.3, -0.6]), atol=1e-6)
        # the 3D box: the cube's model box (side 0.8) moved by the hand-made pose
        box = r["objects"][1]["box3d"]
        np.testing.assert_allclose(box["center_model"], [0, 0, 0], atol=1e-6)
        np.testing.assert_allclose(box["size_model"], [0.8] * 3, atol=1e-6)
        signs = np.array([[(k >> 2 & 1) * 2 - 1, (k >> 1 & 1) * 2 - 1, (k & 1) * 2 - 1]
                          for k in range(8)])
        pose = _pose(_rot_y(90 * t), [-0.5 + t, 0.45, 0])
        corners = signs * 0.4 @ pose[:3, :3].T + pose[:3, 3]
        np.testing.assert_allclose(box["corners_world"], corners, atol=1e-6)


# ------------------------------------------------------------------------------ 4. flow
def _k_w2c(record: dict) -> tuple[np.ndarray, np.ndarray]:
    return (np.array(record["opencv"]["K"], dtype=np.float64),
            np.array(record["opencv"]["world_to_camera"], dtype=np.float64))


def _reproject(depth: np.ndarray, rec0: dict, rec1: dict, moved=(0.0, 0.0, 0.0)
               ) -> tuple[np.ndarray, np.ndarray]:
    """Float64 reprojection of every pixel's surface point (OpenCV pixel centres at
    integers, depth along the view axis) from rec0's camera into rec1's, the point moved
    by ``moved`` (world) in between: returns the other frame's pixel (2, H, W) and depth
    (H, W)."""
    k0, w2c0 = _k_w2c(rec0)
    k1, w2c1 = _k_w2c(rec1)
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(k0).T
    cam0 = rays * depth[..., None].astype(np.float64)
    world = (cam0 - w2c0[:3, 3]) @ w2c0[:3, :3] + np.asarray(moved)  # rigid inverse
    cam1 = world @ w2c1[:3, :3].T + w2c1[:3, 3]
    pix = cam1 @ k1.T
    return np.stack([pix[..., 0] / pix[..., 2], pix[..., 1] / pix[..., 2]]), cam1[..., 2]


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    h, w = img.shape
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = x - x0, y - y0
    return (img[y0, x0] * (1 - fx) * (1 - fy) + img[y0, x0 + 1] * fx * (1 - fy)
            + img[y0 + 1, x0] * (1 - fx) * fy + img[y0 + 1, x0 + 1] * fx * fy)


def _lands_on_its_surface(pix: np.ndarray, z: np.ndarray, src: dict, dst: dict,
                          same_face: bool = True) -> np.ndarray:
    """Pixels whose point lands inside the other frame (1 px margin) on its own object
    (the 4 pixels around the landing point), within 1 % of the other frame's depth there
    (bilinear), and (``same_face``) whose nearest pixel centre there and its 8 neighbours
    show the same face: clearly visible in the other frame. ``src`` / ``dst``:
    ``{"instance", "face_id", "depth"}`` planes of the two frames."""
    h, w = dst["depth"].shape
    x, y = pix
    inside = (x >= 1) & (x <= w - 2) & (y >= 1) & (y <= h - 2) & (src["instance"] > 0)
    x, y = np.where(inside, x, 1.0), np.where(inside, y, 1.0)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    ok = inside.copy()
    for dy in (0, 1):
        for dx in (0, 1):
            ok &= dst["instance"][y0 + dy, x0 + dx] == src["instance"]
    ok &= np.abs(_bilinear(dst["depth"], x, y) - z) <= 0.01 * z
    if same_face:  # the nearest centre and its 8 neighbours: away from creases
        row, col = np.floor(y + 0.5).astype(int), np.floor(x + 0.5).astype(int)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                ok &= dst["face_id"][row + dy, col + dx] == src["face_id"]
    return ok


def _planes(out: Path, record: dict) -> dict:
    return {n: _npy(out, record, f"{n}.npy")[0] for n in ("instance", "face_id", "depth")}


def test_flow_of_a_moving_camera_is_the_reprojected_depth(orbit_run):
    records = _records(orbit_run)
    for f in range(2):
        r0, r1 = records[f"orbit/{f:05d}"], records[f"orbit/{f + 1:05d}"]
        # the camera did turn: 5 degrees a frame
        assert not np.allclose(_k_w2c(r0)[1], _k_w2c(r1)[1], atol=1e-3)
        depth = _npy(orbit_run, r0, "depth.npy")[0]
        ids = _npy(orbit_run, r0, "instance.npy")[0]
        covered = ids > 0
        assert covered.mean() > 0.5
        pix, z = _reproject(depth, r0, r1)
        u, v = np.meshgrid(np.arange(depth.shape[1]), np.arange(depth.shape[0]))
        ref = pix - np.stack([u, v])
        flow = _npy(orbit_run, r0, "flow_forward.npy")
        assert flow.shape == (2, 32, 32)
        np.testing.assert_allclose(flow[:, covered], ref[:, covered], atol=1e-3)
        assert np.abs(ref[:, covered]).max() > 0.5  # pixels do move
        valid = _npy(orbit_run, r0, "flow_forward_valid.npy")[0]
        seen = _lands_on_its_surface(pix, z, _planes(orbit_run, r0), _planes(orbit_run, r1))
        assert seen.sum() > 0.5 * covered.sum()
        assert (valid[seen] == 1).all()
        assert (valid[~covered] == 0).all()


def test_flow_of_a_translating_object_is_the_analytic_displacement(slide_run):
    records = _records(slide_run)
    dx = 0.25  # world units per frame, along the camera's x axis
    for f in range(3):
        r = records[f"slide/{f:05d}"]
        k, w2c = _k_w2c(r)
        np.testing.assert_allclose(w2c[0, :3], [1, 0, 0], atol=1e-7)  # camera x = world x
        fx, w = k[0, 0], r["resolution"][1]
        depth = _npy(slide_run, r, "depth.npy")[0].astype(np.float64)
        ids = _npy(slide_run, r, "instance.npy")[0]
        covered = ids > 0
        assert covered.sum() > 50
        shift = np.where(covered, fx * dx / np.where(covered, depth, 1.0), 0.0)
        forward = _npy(slide_run, r, "flow_forward.npy")
        np.testing.assert_allclose(forward[0], shift, atol=1e-3)
        np.testing.assert_allclose(forward[1], 0.0, atol=1e-3)
        # backward: the previous frame; before the first key the first key holds
        back_shift = -shift if f > 0 else 0.0 * shift
        backward = _npy(slide_run, r, "flow_backward.npy")
        np.testing.assert_allclose(backward[0], back_shift, atol=1e-3)
        np.testing.assert_allclose(backward[1], 0.0, atol=1e-3)
        # NDC motion vectors: current minus previous, x right, y up (2 / W per pixel)
        motion = _npy(slide_run, r, "motion.npy")
        np.testing.assert_allclose(motion[0], -back_shift * 2 / w, atol=1e-4)
        np.testing.assert_allclose(motion[1], 0.0, atol=1e-4)
        if f < 2:
            nxt = records[f"slide/{f + 1:05d}"]
            pix, z = _reproject(depth, r, nxt, (dx, 0, 0))
            seen = _lands_on_its_surface(pix, z, _planes(slide_run, r), _planes(slide_run, nxt))
            assert seen.sum() > 0.2 * covered.sum()  # small triangles: few away from edges
            assert (_npy(slide_run, r, "flow_forward_valid.npy")[0][seen] == 1).all()


def test_flow_validity_at_convex_creases(orbit_run):
    """Points on a grazing face whose nearest centre in the next frame sees the face beyond a
    convex crease (the cube's edges) are valid: the test allows for the point's own face's
    slope across its offset from that centre (motion.py's occlusion test)."""
    records = _records(orbit_run)
    r0, r1 = records["orbit/00000"], records["orbit/00001"]
    pix, z = _reproject(_npy(orbit_run, r0, "depth.npy")[0], r0, r1)
    seen = _lands_on_its_surface(pix, z, _planes(orbit_run, r0), _planes(orbit_run, r1),
                                 same_face=False)
    assert (_npy(orbit_run, r0, "flow_forward_valid.npy")[0][seen] == 1).all()


# --------------------------------------------------------------------------- 5. exports
@pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")  # pycocotools
def test_coco_export_decodes_to_the_instance_files(main_run):
    from pycocotools.coco import COCO

    out = main_run / "out"
    records = _records(out)
    coco = COCO(str(out / "exports" / "coco" / "instances.json"))
    assert [c["name"] for c in coco.loadCats(coco.getCatIds())] == ["ground", "cube", "ball"]
    assert len(coco.getImgIds()) == 3
    for image in coco.loadImgs(coco.getImgIds()):
        r = records[image["view_key"]]
        assert image["file_name"] == r["files"]["color.png"]
        assert (image["height"], image["width"]) == tuple(r["resolution"])
        rebuilt = np.zeros((image["height"], image["width"]), dtype=np.int64)
        by_id = {o["instance_id"]: o for o in r["objects"]}
        for ann in coco.loadAnns(coco.getAnnIds(imgIds=image["id"])):
            mask = coco.annToMask(ann).astype(bool)
            assert not (rebuilt[mask] > 0).any()  # instances never overlap
            rebuilt[mask] = ann["instance_id"]
            o = by_id[ann["instance_id"]]
            assert ann["category_id"] == o["category_id"] and ann["area"] == o["pixels"]
            x0, y0, x1, y1 = o["bbox_visible"]
            assert ann["bbox"] == [x0, y0, x1 - x0, y1 - y0]
        instance = _npy(out, r, "instance.npy")[0].astype(np.int64)
        expected = np.where(instance == 4, 0, instance)  # the cone has no category: no entry
        assert (instance == 4).any()
        np.testing.assert_array_equal(rebuilt, expected)


def test_nerf_export_holds_the_recorded_cameras(main_run):
    out = main_run / "out"
    records = _records(out)
    folder = out / "exports" / "nerf"
    data = json.loads((folder / "transforms.json").read_text())
    k = np.array(records["main/00000"]["opencv"]["K"])
    assert data["fl_x"] == pytest.approx(k[0, 0]) and data["cx"] == pytest.approx(k[0, 2] + 0.5)
    assert data["w"] == data["h"] == 40
    assert data["camera_angle_x"] == pytest.approx(math.radians(45))  # the default fov
    by_file = {r["files"]["color.png"]: r for r in records.values()}
    assert len(data["frames"]) == 3
    eye, target = np.array([0, 2, 4.0]), np.array([0, 0.3, 0])
    for frame in data["frames"]:
        rel = (folder / frame["file_path"]).resolve().relative_to(out.resolve()).as_posix()
        r = by_file[rel]
        c2w = np.array(frame["transform_matrix"])
        np.testing.assert_allclose(c2w, r["opengl"]["view_to_world"], atol=1e-12)
        # independent of the record: the camera sits at the eye and looks down -z at the target
        np.testing.assert_allclose(c2w[:3, 3], eye, atol=1e-5)
        forward = (target - eye) / np.linalg.norm(target - eye)
        np.testing.assert_allclose(-c2w[:3, 2], forward, atol=1e-5)
        assert frame["time"] == pytest.approx(r["time"])


def test_bop_export_poses_depth_and_masks(orbit_run):
    records = _records(orbit_run)
    scene = orbit_run / "exports" / "bop" / "000001"
    views = json.loads((scene / "scene_views.json").read_text())
    gt = json.loads((scene / "scene_gt.json").read_text())
    cams = json.loads((scene / "scene_camera.json").read_text())
    assert json.loads((orbit_run / "exports" / "bop" / "obj_ids.json").read_text()) == {
        "1": "ground", "2": "cube", "3": "ball"}
    assert sorted(views.values()) == sorted(records)
    # the cube's pose by hand: translate (-0.3, 0.4, 0), 30 degrees of yaw
    cube = _pose(_rot_y(30), [-0.3, 0.4, 0])
    for im_id, key in views.items():
        r = records[key]
        k, w2c = _k_w2c(r)
        np.testing.assert_allclose(np.reshape(cams[im_id]["cam_K"], (3, 3)), k, atol=1e-9)
        np.testing.assert_allclose(cams[im_id]["cam_t_w2c"], w2c[:3, 3] * 1000, atol=1e-6)
        for gt_id, (g, o) in enumerate(zip(gt[im_id], r["objects"], strict=True)):
            m2c = w2c @ np.array(o["object_to_world"])
            np.testing.assert_allclose(np.reshape(g["cam_R_m2c"], (3, 3)), m2c[:3, :3],
                                       atol=1e-9)
            np.testing.assert_allclose(g["cam_t_m2c"], m2c[:3, 3] * 1000, atol=1e-6)
            assert g["obj_id"] == o["category_id"] and "model_scale" not in g
            stem = f"{int(im_id):06d}_{gt_id:06d}.png"
            visible = _npy(orbit_run, r, "instance.npy")[0] == o["instance_id"]
            full = _npy(orbit_run, r, "amodal.npy")[o["instance_id"] - 1].astype(bool)
            np.testing.assert_array_equal(skio.imread(scene / "mask_visib" / stem),
                                          visible * 255)
            np.testing.assert_array_equal(skio.imread(scene / "mask" / stem), full * 255)
        m2c = w2c @ cube
        g = gt[im_id][1]
        np.testing.assert_allclose(np.reshape(g["cam_R_m2c"], (3, 3)), m2c[:3, :3], atol=1e-6)
        np.testing.assert_allclose(g["cam_t_m2c"], m2c[:3, 3] * 1000, atol=1e-3)
        depth_mm = _npy(orbit_run, r, "depth.npy")[0].astype(np.float64) * 1000
        png = skio.imread(scene / "depth" / f"{int(im_id):06d}.png").astype(np.float64)
        scale = cams[im_id]["depth_scale"]
        assert np.abs(png * scale - depth_mm).max() <= scale / 2 + 1e-3
        assert (png[depth_mm > 0] > 0).all()


def test_webdataset_shards_read_back(main_run):
    import webdataset as wds

    out = main_run / "out"
    records = _records(out)
    shards = sorted((out / "exports" / "webdataset").glob("shard-*.tar"))
    assert len(shards) == 1
    samples = list(wds.WebDataset([str(shards[0])], shardshuffle=False))
    assert [s["__key__"] for s in samples] == ["main_00000", "main_00001", "main_00002"]
    for s in samples:
        r = json.loads(s["json"])
        assert r == records[r["key"]]
        assert set(s) - {"__key__", "__url__", "__local_path__", "json"} == set(r["files"])
        for name, rel in r["files"].items():
            assert s[name] == (out / rel).read_bytes()


# ------------------------------------------------------------- 6. previews and keypoints
def test_previews_colour_each_id_alike(main_run):
    out = main_run / "out"
    colour_of: dict[int, tuple] = {}
    for r in _records(out).values():
        for channel in ("instance", "semantic"):
            rgb = skio.imread(out / r["files"][f"{channel}_preview.png"])
            ids = _npy(out, r, f"{channel}.npy")[0]
            assert rgb.shape == (40, 40, 3) and rgb.dtype == np.uint8
            assert (rgb[ids == 0] == 0).all()
            for i in np.unique(ids[ids > 0]):
                colours = np.unique(rgb[ids == i], axis=0)
                assert len(colours) == 1 and colours[0].any()
                if channel == "instance":  # one colour per id, in every view
                    assert colour_of.setdefault(int(i), tuple(colours[0])) == tuple(colours[0])
    assert len(set(colour_of.values())) == len(colour_of) == 4


def test_keypoints_are_projected_with_their_visibility(main_run):
    records = _records(main_run / "out")
    for frame in (0, 1):  # the front face turns 0 then 45 degrees: seen; the back never
        r = records[f"main/{frame:05d}"]
        kp = r["objects"][1]["keypoints"]
        np.testing.assert_allclose(kp["model"], [[0, 0, 0.4], [0, 0, -0.4]], atol=1e-7)
        assert kp["visible"] == [True, False]
        k, w2c = _k_w2c(r)
        pose = _pose(_rot_y(45 * frame), [-0.5 + frame / 2, 0.45, 0])
        world = np.array(kp["model"]) @ pose[:3, :3].T + pose[:3, 3]
        cam = world @ w2c[:3, :3].T + w2c[:3, 3]
        pix = cam @ k.T
        np.testing.assert_allclose(kp["pixels"], pix[:, :2] / pix[:, 2:], atol=1e-4)
        # the hidden one falls on the cube itself: the depth test, not the id, hides it
        ids = _npy(main_run / "out", r, "instance.npy")[0]
        u, v = np.floor(np.array(kp["pixels"][1]) + 0.5).astype(int)
        assert ids[v, u] == 2
    assert all("keypoints" not in o for o in records["main/00000"]["objects"][::2])


# ------------------------------------------------------------------------------ 7. resume
RESUME = f"""\
frames: {{count: 2, fps: 2}}
categories: [thing, other]
scene:
  objects:
    - name: cube
      primitive: box
      category: thing
      material: {{base_color: [0.8, 0.2, 0.2]}}
      animation:
        keys:
          - {{time: 0, translate: [0, 0, 0]}}
          - {{time: 1, translate: [0.3, 0, 0]}}
cameras:
  - look_at: {{eye: [0, 1, 3]}}
render: {{resolution: 16}}
lights:
  - {{type: point, position: [1, 2, 2], intensity: 10}}
environment: {{path: {ENV}, intensity: 1.0}}
outputs: {{channels: [color, instance, semantic], formats: [npy]}}
"""

#: One change of each kind; every one must re-render both views of its config.
CHANGES = {
    "material": ("base_color: [0.8, 0.2, 0.2]", "base_color: [0.2, 0.8, 0.2]"),
    "light": ("intensity: 10}", "intensity: 20}"),
    "animation": ("translate: [0.3, 0, 0]", "translate: [0.4, 0, 0]"),
    "category": ("category: thing", "category: other"),
    "fps": ("fps: 2}", "fps: 3}"),
    "environment": ("intensity: 1.0}", "intensity: 0.5}"),
}


def test_resume_skips_done_views_and_redoes_changed_configs(tmp_path, capsys):
    out = tmp_path / "out"
    base, other = tmp_path / "r.yaml", tmp_path / "s.yaml"
    base.write_text(RESUME)
    other.write_text(RESUME.replace("[0.8, 0.2, 0.2]", "[0.2, 0.2, 0.8]"))
    assert _render(out, base, other) == 0
    assert "4 view(s) written" in capsys.readouterr().err
    assert _render(out, base, other) == 0
    assert "0 view(s) written" in capsys.readouterr().err
    for kind, (old, new) in CHANGES.items():
        assert old in RESUME, kind
        folder = tmp_path / kind
        folder.mkdir()
        changed = folder / "r.yaml"  # the same config name: the same output folder
        changed.write_text(RESUME.replace(old, new, 1))
        before = {p: p.read_bytes() for p in (out / "r").rglob("*.npy")}
        assert _render(out, changed, other) == 0
        err = capsys.readouterr().err
        assert "2 view(s) written" in err and "2 already done" in err, (kind, err)
        after = {p: p.read_bytes() for p in (out / "r").rglob("*.npy")}
        assert after != before, kind  # the change shows in the files
        assert _render(out, changed, other) == 0  # and is done now
        assert "0 view(s) written" in capsys.readouterr().err, kind
        if kind == "category":
            r = _records(out)["r/00000"]
            assert r["objects"][0]["category"] == "other"
            assert (np.load(out / r["files"]["semantic.npy"]) == 2).any()
    assert len(_records(out)) == 4


# ------------------------------------------------------------------------ 8. bad input
GOOD = """\
scene:
  objects:
    - {primitive: box, category: cube}
render: {resolution: 16}
"""
ANIMATED = """\
scene:
  objects:
    - primitive: box
      animation:
        keys:
          - {time: 0.5, translate: [0, 0, 0]}
          - {time: TIME, translate: [1, 0, 0]}
"""

BAD = {
    "keys out of order": (ANIMATED.replace("TIME", "0.25"), 7,  # the key's own line
                          "scene.objects.0.animation.keys.1.time",
                          "0.25 comes before keys[0].time (0.5)"),
    "keys duplicated": (ANIMATED.replace("TIME", "0.5"), 7,
                        "scene.objects.0.animation.keys.1.time",
                        "0.5 duplicates keys[0].time (0.5)"),
    "no frames": (GOOD + "frames: {count: 0}\n", 5, "frames.count", "greater than or equal"),
    "too many frames": (GOOD + "frames: {count: 100001}\n", 5, "frames.count",
                        "less than or equal to 100000"),
    "flow with one frame": (GOOD + "outputs: {channels: [color, flow_forward, motion]}\n", 5,
                            "outputs.channels", "flow_forward, motion need another frame"),
    "unknown category": (GOOD + "categories: [ball]\n", 3, "scene.objects.0.category",
                         "unknown category 'cube'"),
    "duplicated category": (GOOD + "categories: [cube, ball, cube]\n", 5, "categories.2",
                            "'cube' is listed twice"),
    "export without channels": (GOOD + "outputs: {channels: [color], exports: [coco]}\n", 5,
                                "outputs.exports.0", "coco needs the channel(s) instance"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_dataset_input_is_one_named_error(tmp_path, capsys, case):
    text, line, key, message = BAD[case]
    bad, good = tmp_path / "bad.yaml", tmp_path / "good.yaml"
    bad.write_text(text)
    good.write_text(GOOD)
    # the run is checked before anything renders: nothing is written, not even the good one
    assert _render(tmp_path / "out", good, bad) == 2
    err = capsys.readouterr().err
    assert f"bad.yaml:{line}: {key}: " in err and message in err, err
    assert err.count("bad.yaml:") == 1 and "good.yaml" not in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()
    # the good config alone carries on
    assert _render(tmp_path / "out", good) == 0
    assert (tmp_path / "out" / "good" / "color.png").is_file()


def test_a_config_failing_at_render_time_fails_alone(tmp_path, capsys):
    """A config that loads but cannot build its scene (a broken mesh file) fails its own
    views; the other config of the run renders and gets its exports."""
    (tmp_path / "broken.obj").write_text("v 0 0 0\nf 1 2 3\n")  # a face with missing vertices
    broken = tmp_path / "broken.yaml"
    broken.write_text(GOOD.replace("{primitive: box, category: cube}",
                                   "{mesh: broken.obj, category: cube}")
                      + "frames: {count: 2}\n")
    good = tmp_path / "good.yaml"
    good.write_text(GOOD + "frames: {count: 2}\noutputs: {channels: [color, instance], "
                    "exports: [coco]}\n")
    assert _render(tmp_path / "out", broken, good) == 1
    err = capsys.readouterr().err
    assert "broken.yaml" in err and "2 view(s) written" in err and "2 failed" in err
    assert {r["config"] for r in manifest.read_manifest(tmp_path / "out")} == {"good"}
    coco = json.loads((tmp_path / "out" / "exports" / "coco" / "instances.json").read_text())
    assert len(coco["images"]) == 2 and len(coco["annotations"]) == 2


def test_bop_export_without_categories_is_refused_up_front(tmp_path, capsys):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(GOOD.replace(", category: cube", "") + "outputs: {channels: [color, "
                   "instance, amodal, depth], exports: [bop]}\n")
    code = _render(tmp_path / "out", cfg)
    err = capsys.readouterr().err
    assert code == 2 and "c.yaml:" in err and "bop export" in err, err
    assert "give this object a category" in err


# ---------------------------------------------------------------- 9. one rank or two
def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_two_ranks_write_the_same_animated_dataset_as_one(tmp_path):
    from test_dataset_render import _env, _torchrun

    config = tmp_path / "anim.yaml"
    config.write_text(RESUME.replace("count: 2", "count: 4").replace(
        "[color, instance, semantic]", "[color, depth, instance, amodal, flow_forward]")
        .replace("formats: [npy]", "formats: [png, npy], exports: [coco, nerf]"))
    one = tmp_path / "one"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the torchrun workers (OMP_NUM_THREADS=1)
    try:
        assert _render(one, config) == 0
    finally:
        torch.set_num_threads(threads)
    two = tmp_path / "two"
    res = subprocess.run(_torchrun(2, "render", str(config), "--out", str(two)), env=_env(),
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert _files(two / "anim") == _files(one / "anim")  # bit-identical PNG and NPY
    assert len(_files(one / "anim")) == 4 * 9

    def strip(out: Path) -> dict:
        return {k: {f: v for f, v in r.items() if f not in VOLATILE}
                for k, r in _records(out).items()}

    assert strip(two) == strip(one)
    assert {r["rank"] for r in manifest.read_manifest(two)} == {0, 1}
    assert _files(two / "exports") == _files(one / "exports")
    assert not [p for p in two.rglob("*") if ".trtmp-" in p.name]
    nerf = json.loads((one / "exports" / "nerf" / "transforms.json").read_text())
    assert [f["time"] for f in nerf["frames"]] == [0.0, 0.5, 1.0, 1.5]


def test_render_to_files_writes_one_folder_per_frame(tmp_path):
    import torchraster as tr

    cfg = tr.parse_config(ANIMATED.replace("TIME", "1.0") + "frames: {count: 2, fps: 1}\n"
                          "render: {resolution: 16}\noutputs: {channels: [depth], "
                          "formats: [npy]}\n")
    written = tr.render_to_files(cfg, tmp_path)
    assert sorted(p.relative_to(tmp_path).as_posix() for p in written) == [
        "00000/depth.npy", "00001/depth.npy"]  # frames never overwrite each other
    a, b = (np.load(tmp_path / f / "depth.npy") for f in ("00000", "00001"))
    assert not np.array_equal(a, b)  # the box moved between t = 0 and t = 1
