"""Dataset exports (COCO, BOP, NeRF, WebDataset) of a hand-made dataset folder, read back
with each format's own reader / formula and compared with the hand-made channels and
camera matrices (independent of the renderer)."""

import json
import math
import sys
import tarfile

import numpy as np
import pytest
import torch
from skimage import io as skio

from torchraster import camera, export, manifest

H, W = 12, 16
CATEGORIES = ["cup", "box", "ball"]
KEYS = ["scene_a/cam0", "scene_a/cam1", "scene_a/cam2", "scene_b/cam0"]


def _translation(x, y, z, scale=1.0):
    m = np.eye(4) * scale
    m[3, 3] = 1.0
    m[:3, 3] = [x, y, z]
    return m


def _rot_y(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


def _maps(shift):
    """Instance map (H, W) and amodal silhouettes (4, H, W) of one view: object 1 a box,
    object 2 two disjoint pieces, object 3 entirely behind object 1, object 4 at the top."""
    inst = np.zeros((H, W), np.int64)
    amodal = np.zeros((4, H, W), bool)
    amodal[0, 2:7, 3 + shift:9 + shift] = True
    amodal[1, 8:12, 1:15] = True
    amodal[2, 3:6, 4 + shift:8 + shift] = True
    amodal[3, 0:2, 10:16] = True
    inst[amodal[3]] = 4
    inst[8:11, 1:4] = 2
    inst[8:12, 12:15] = 2
    inst[amodal[0]] = 1  # object 1 in front of object 3
    return inst, amodal


def _bbox(mask):
    ys, xs = np.nonzero(mask)
    return None if len(xs) == 0 else [int(xs.min()), int(ys.min()), int(xs.max()) + 1,
                                      int(ys.max()) + 1]


@pytest.fixture
def dataset(tmp_path):
    """A folder with 4 views (3 of config scene_a, 1 of scene_b) and its manifest."""
    rng = np.random.default_rng(0)
    records = []
    o2w = [_translation(0.1, 0.0, -0.2) @ _rot_y(30), _translation(-0.3, 0.1, 0.0),
           _translation(0.1, 0.0, -0.4) @ _rot_y(-50), _translation(0.2, 0.3, 0.1, 2.0)]
    for i, key in enumerate(KEYS):
        folder = tmp_path / key
        folder.mkdir(parents=True)
        inst, amodal = _maps(i % 3)
        depth = np.where(inst > 0, 1.5 + 0.1 * i, 0.0).astype(np.float32)[None]
        if i == 2:
            depth[0, 0, 0] = 9.0  # 9000 mm: needs depth_scale 1 mm in a 16-bit PNG
            inst[0, 0] = 4
        skio.imsave(folder / "color.png", rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
                    check_contrast=False)
        files = {"color.png": f"{key}/color.png", "amodal.npy": f"{key}/amodal.npy",
                 "depth.npy": f"{key}/depth.npy"}
        if i == 1:  # the 16-bit PNG instead of the .npy
            skio.imsave(folder / "instance.png", inst.astype(np.uint16), check_contrast=False)
            files["instance.png"] = f"{key}/instance.png"
        else:
            np.save(folder / "instance.npy", inst.astype(np.int32)[None])
            files["instance.npy"] = f"{key}/instance.npy"
        np.save(folder / "amodal.npy", amodal.astype(np.uint8))
        np.save(folder / "depth.npy", depth)
        eye = torch.tensor([0.4 * i - 0.5, 0.6, 3.0], dtype=torch.float64)
        view = camera.look_at(eye, [0.0, 0.1, 0.0])[0]
        proj = camera.from_intrinsics(20.0, 18.0, 7.6, 5.3, W, H, 0.1).double()[0]
        objects = []
        for k, (name, cat) in enumerate([("mug", 1), ("crate", 2), ("mug_2", 1),
                                         ("ball", 3)]):
            vis, full = inst == k + 1, amodal[k]
            objects.append({"instance_id": k + 1, "name": name, "category": CATEGORIES[cat - 1],
                            "category_id": cat, "object_to_world": o2w[k].tolist(),
                            "bbox_visible": _bbox(vis), "bbox_amodal": _bbox(full),
                            "pixels": int(vis.sum()), "pixels_amodal": int(full.sum())})
        record = {"key": key, "config": key.split("/")[0], "resolution": [H, W], "frame": i,
                  "time": i / 24, "categories": CATEGORIES, "objects": objects,
                  "files": files, "finished_at": 1000.0 + i}
        record.update(manifest.camera_matrices(view, proj, (H, W)))
        records.append(record)
    (tmp_path / manifest.MANIFEST).write_text("".join(json.dumps(r) + "\n" for r in records))
    return tmp_path, records


def _instance(root, record):
    files = record["files"]
    if "instance.npy" in files:
        return np.load(root / files["instance.npy"])[0].astype(np.int64)
    return skio.imread(root / files["instance.png"]).astype(np.int64)


# ------------------------------------------------------------------------------ COCO

def test_coco_loads_and_rles_give_back_the_instance_channel(dataset):
    from pycocotools import mask as mask_util
    from pycocotools.coco import COCO

    root, records = dataset
    (path,) = export.write_coco(root)
    assert path == root / "exports" / "coco" / "instances.json"
    coco = COCO(str(path))
    assert [c["name"] for c in coco.loadCats(coco.getCatIds())] == CATEGORIES
    assert sorted(coco.getImgIds()) == [1, 2, 3, 4]
    for image_id, record in enumerate(records, start=1):
        img = coco.loadImgs(image_id)[0]
        assert (img["height"], img["width"]) == (H, W)
        assert (root / img["file_name"]).is_file()
        inst = _instance(root, record)
        painted = np.zeros_like(inst)
        anns = coco.loadAnns(coco.getAnnIds(imgIds=image_id))
        assert sorted(a["instance_id"] for a in anns) == [1, 2, 4]  # 3 is hidden
        for ann in anns:
            assert isinstance(ann["segmentation"]["counts"], str) and ann["iscrowd"] == 0
            m = mask_util.decode(ann["segmentation"]).astype(bool)
            np.testing.assert_array_equal(m, coco.annToMask(ann).astype(bool))
            assert not painted[m].any()  # instances do not overlap
            painted[m] = ann["instance_id"]
            obj = record["objects"][ann["instance_id"] - 1]
            assert ann["category_id"] == obj["category_id"]
            assert ann["area"] == obj["pixels"]
            x0, y0, x1, y1 = obj["bbox_visible"]
            assert ann["bbox"] == [x0, y0, x1 - x0, y1 - y0]
        np.testing.assert_array_equal(painted, inst)
    # the split object is one annotation covering both pieces
    crate = [a for a in coco.loadAnns(coco.getAnnIds(imgIds=1)) if a["instance_id"] == 2][0]
    assert crate["area"] == 3 * 3 + 4 * 3 and crate["bbox"] == [1, 8, 14, 4]


def test_coco_without_pycocotools_names_the_extra(dataset, monkeypatch):
    monkeypatch.setitem(sys.modules, "pycocotools", None)
    monkeypatch.setitem(sys.modules, "pycocotools.mask", None)
    with pytest.raises(ImportError, match=r"pycocotools.*torchraster\[datasets\]"):
        export.write_coco(dataset[0])


def test_errors_name_the_missing_file_or_field(dataset, tmp_path_factory):
    root, records = dataset
    with pytest.raises(export.ExportError, match="manifest.jsonl: no manifest"):
        export.write_coco(tmp_path_factory.mktemp("empty"))
    bad = [dict(r) for r in records]
    del bad[1]["objects"]
    with pytest.raises(export.ExportError, match=r"'scene_a/cam1'.*no field 'objects'"):
        export.write_coco(root, bad)
    (root / records[2]["files"]["amodal.npy"]).unlink()
    with pytest.raises(export.ExportError, match=r"scene_a/cam2/amodal.npy: file missing"):
        export.write_bop(root)
    bad = [dict(r, opencv=dict(r["opencv"], K=None)) for r in records]
    with pytest.raises(export.ExportError, match="orthographic"):
        export.write_nerf(root, bad)


# ------------------------------------------------------------------------------ BOP

def _pixel_gl(record, p_world):
    """Where the renderer's OpenGL matrices put a world point: continuous pixel (u, v),
    pixel centres at integers (contract: column j samples NDC x = 2(j + 0.5)/W - 1)."""
    gl = record["opengl"]
    clip = np.array(gl["projection"]) @ np.array(gl["world_to_view"]) @ np.append(p_world, 1)
    return np.array([(clip[0] / clip[3] + 1) * W / 2 - 0.5, (1 - clip[1] / clip[3]) * H / 2 - 0.5])


def test_bop_reads_back_as_our_cameras_and_poses(dataset):
    root, records = dataset
    export.write_bop(root)
    bop = root / "exports" / "bop"
    assert json.loads((bop / "obj_ids.json").read_text()) == {"1": "cup", "2": "box",
                                                               "3": "ball"}
    scenes = {"000001": records[:3], "000002": records[3:]}
    model_point = np.array([0.05, -0.02, 0.03])
    for scene, views in scenes.items():
        folder = bop / scene
        cams = json.loads((folder / "scene_camera.json").read_text())
        gts = json.loads((folder / "scene_gt.json").read_text())
        infos = json.loads((folder / "scene_gt_info.json").read_text())
        assert json.loads((folder / "scene_views.json").read_text()) == {
            str(i): r["key"] for i, r in enumerate(views)}
        for im_id, record in enumerate(views):
            cam = cams[str(im_id)]
            k = np.array(cam["cam_K"]).reshape(3, 3)
            np.testing.assert_allclose(k, record["opencv"]["K"], atol=1e-12)
            w2c = np.eye(4)
            w2c[:3, :3] = np.reshape(cam["cam_R_w2c"], (3, 3))
            w2c[:3, 3] = np.array(cam["cam_t_w2c"]) / 1000
            np.testing.assert_allclose(w2c, record["opencv"]["world_to_camera"], atol=1e-12)
            inst = _instance(root, record)
            for gt_id, (gt, info) in enumerate(zip(gts[str(im_id)], infos[str(im_id)],
                                                   strict=True)):
                obj = record["objects"][gt_id]
                assert gt["obj_id"] == obj["category_id"]
                rot = np.reshape(gt["cam_R_m2c"], (3, 3))
                np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
                scale = np.array(gt.get("model_scale", [1.0, 1.0, 1.0]))
                m2c = np.eye(4)
                m2c[:3, :3] = rot * scale
                m2c[:3, 3] = np.array(gt["cam_t_m2c"]) / 1000
                np.testing.assert_allclose(np.linalg.inv(w2c) @ m2c, obj["object_to_world"],
                                           atol=1e-12)
                # BOP's projection of a model point (mm) lands where our renderer puts it
                p_cam = rot @ (scale * model_point * 1000) + np.array(gt["cam_t_m2c"])
                uv = (k @ p_cam)[:2] / (k @ p_cam)[2]
                p_world = (np.array(obj["object_to_world"]) @ np.append(model_point, 1))[:3]
                np.testing.assert_allclose(uv, _pixel_gl(record, p_world), atol=1e-9)
                # masks and counts
                stem = f"{im_id:06d}_{gt_id:06d}.png"
                visib = skio.imread(folder / "mask_visib" / stem)
                full = skio.imread(folder / "mask" / stem)
                np.testing.assert_array_equal(visib > 0, inst == obj["instance_id"])
                assert set(np.unique(visib)) <= {0, 255}
                amodal = np.load(root / record["files"]["amodal.npy"])[gt_id].astype(bool)
                np.testing.assert_array_equal(full > 0, amodal)
                n_vis, n_all = int((inst == obj["instance_id"]).sum()), int(amodal.sum())
                assert (info["px_count_visib"], info["px_count_all"]) == (n_vis, n_all)
                assert info["visib_fract"] == pytest.approx(n_vis / n_all)
                if n_vis == 0:  # bop_toolkit: both boxes -1 when nothing is visible
                    assert info["bbox_visib"] == info["bbox_obj"] == [-1, -1, -1, -1]
                else:
                    x0, y0, x1, y1 = _bbox(inst == obj["instance_id"])
                    assert info["bbox_visib"] == [x0, y0, x1 - 1 - x0, y1 - 1 - y0]
            # depth: 16-bit PNG, mm = value * depth_scale, 0 where empty
            depth = np.load(root / record["files"]["depth.npy"])[0].astype(np.float64) * 1000
            png = skio.imread(folder / "depth" / f"{im_id:06d}.png")
            assert png.dtype == np.uint16
            assert cam["depth_scale"] == (1.0 if record["key"] == "scene_a/cam2" else 0.1)
            np.testing.assert_allclose(png * cam["depth_scale"], depth,
                                       atol=cam["depth_scale"] / 2 + 1e-9)
            assert ((png == 0) == (depth == 0)).all()
            rgb = (folder / "rgb" / f"{im_id:06d}.png").read_bytes()
            assert rgb == (root / record["files"]["color.png"]).read_bytes()
    # the hidden mug: zero visible pixels, a full silhouette
    info = json.loads((bop / "000001" / "scene_gt_info.json").read_text())["0"][2]
    assert info["px_count_visib"] == 0 and info["px_count_all"] == 12
    assert info["visib_fract"] == 0.0
    # the scaled ball carries its scale
    gt = json.loads((bop / "000001" / "scene_gt.json").read_text())["0"][3]
    np.testing.assert_allclose(gt["model_scale"], [2.0, 2.0, 2.0])


def test_bop_obj_ids_by_name_and_fixed_depth_scale(dataset):
    root, records = dataset
    export.write_bop(root, obj_ids="name", depth_scale=1.0)
    bop = root / "exports" / "bop"
    assert json.loads((bop / "obj_ids.json").read_text()) == {
        "1": "mug", "2": "crate", "3": "mug_2", "4": "ball"}
    gts = json.loads((bop / "000002" / "scene_gt.json").read_text())["0"]
    assert [g["obj_id"] for g in gts] == [1, 2, 3, 4]
    cams = json.loads((bop / "000001" / "scene_camera.json").read_text())
    assert {c["depth_scale"] for c in cams.values()} == {1.0}
    with pytest.raises(export.ExportError, match="does not fit a 16-bit PNG"):
        export.write_bop(root, depth_scale=0.1)
    with pytest.raises(ValueError, match="obj_ids"):
        export.write_bop(root, obj_ids="model")


# ------------------------------------------------------------------------------ NeRF

def test_nerf_transforms_round_trip_and_project(dataset):
    root, records = dataset
    (path,) = export.write_nerf(root)
    data = json.loads(path.read_text())
    assert (data["w"], data["h"]) == (W, H)
    assert data["camera_angle_x"] == pytest.approx(2 * math.atan(W / (2 * 20.0)))
    assert len(data["frames"]) == len(records)
    p_world = np.array([0.1, 0.2, -0.1])
    for frame, record in zip(data["frames"], records, strict=True):
        assert (path.parent / frame["file_path"]).resolve() == (
            root / record["files"]["color.png"]).resolve()
        c2w = np.array(frame["transform_matrix"])
        np.testing.assert_allclose(c2w, record["opengl"]["view_to_world"], atol=0)
        assert frame["time"] == pytest.approx(record["time"])
        # NeRF's camera: x right, y up, looking down -z; the ray of pixel centre (x, y)
        # (x = column + 0.5) has direction ((x - cx)/fl_x, -(y - cy)/fl_y, -1)
        cam = np.linalg.inv(c2w) @ np.append(p_world, 1)
        x = data["fl_x"] * cam[0] / -cam[2] + data["cx"]
        y = -data["fl_y"] * cam[1] / -cam[2] + data["cy"]
        np.testing.assert_allclose(np.array([x, y]) - 0.5, _pixel_gl(record, p_world),
                                   atol=1e-9)
        # and back: our camera from the NeRF matrix is the record's world -> view
        w2v = camera.convert(torch.tensor(c2w), "nerf", "opengl", "camera_to_world")
        np.testing.assert_allclose(np.linalg.inv(w2v.numpy()),
                                   record["opengl"]["world_to_view"], atol=1e-12)
    assert "fl_x" not in data["frames"][0]  # shared intrinsics stay at the top


def test_nerf_per_frame_intrinsics_when_views_differ(dataset):
    root, records = dataset
    records[3]["opencv"]["K"][0][0] = 25.0
    data = json.loads(export.write_nerf(root, records)[0].read_text())
    assert data["frames"][3]["fl_x"] == 25.0 and data["frames"][0]["fl_x"] == 20.0


# ------------------------------------------------------------------------------ WebDataset

def test_webdataset_shards_read_back(dataset):
    import webdataset as wds

    root, records = dataset
    shards = export.write_webdataset(root, shard_size=3)
    assert [p.name for p in shards] == ["shard-000000.tar", "shard-000001.tar"]
    samples = list(wds.WebDataset([str(p) for p in shards], shardshuffle=False))
    assert [s["__key__"] for s in samples] == [export.sample_key(k) for k in KEYS]
    assert export.sample_key("scene_a/cam0") == "scene_a_cam0"
    for sample, record in zip(samples, records, strict=True):
        assert json.loads(sample["json"]) == record
        assert set(sample) - {"__key__", "__url__", "__local_path__", "json"} == set(
            record["files"])
        for name, rel in record["files"].items():
            assert sample[name] == (root / rel).read_bytes()


def test_webdataset_resumes_and_rewrites_only_changed_shards(dataset):
    root, records = dataset
    shards = export.write_webdataset(root, shard_size=3)
    before = [p.stat().st_mtime_ns for p in shards]
    data = [p.read_bytes() for p in shards]
    assert export.write_webdataset(root, shard_size=3) == shards
    assert [p.stat().st_mtime_ns for p in shards] == before  # nothing rewritten
    records[3]["finished_at"] = 2000.0  # view 3 re-rendered: only its shard changes
    export.write_webdataset(root, records, shard_size=3)
    assert shards[0].stat().st_mtime_ns == before[0]
    assert shards[1].read_bytes() != data[1]
    with tarfile.open(shards[1]) as tar:
        assert json.loads(tar.extractfile("scene_b_cam0.json").read())["finished_at"] == 2000.0
    # a truncated shard (killed copy) is rewritten; stale shards past the count go
    shards[0].write_bytes(data[0][:1000])
    assert export.write_webdataset(root, records[:2], shard_size=3) == shards[:1]
    assert not shards[1].exists()
    with tarfile.open(shards[0]) as tar:
        assert len(tar.getmembers()) == 2 * (len(records[0]["files"]) + 1)
    # equal inputs give equal bytes
    again = export.write_webdataset(root, records[:2], shard_size=3)[0].read_bytes()
    assert again == shards[0].read_bytes()


def test_webdataset_keys_stay_unique(dataset):
    root, records = dataset
    twins = [dict(records[0], key="a/b"), dict(records[1], key="a_b"), dict(records[2],
                                                                            key="a.b")]
    (shard,) = export.write_webdataset(root, twins)
    with tarfile.open(shard) as tar:
        keys = [m.name.split(".")[0] for m in tar.getmembers() if m.name.endswith(".json")]
    assert keys == ["a_b", "a_b_1", "a_b_2"]
    with pytest.raises(ValueError, match="shard_size"):
        export.write_webdataset(root, shard_size=0)
