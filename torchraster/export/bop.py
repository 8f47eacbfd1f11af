"""BOP format export of a rendered dataset (``exports/bop/<scene_id:06d>/``).

Follows the BOP toolkit's dataset layout (bop_toolkit ``docs/bop_datasets_format.md``): per
scene ``scene_camera.json`` (``cam_K`` row-major, ``depth_scale``, ``cam_R_w2c``,
``cam_t_w2c`` in mm), ``scene_gt.json`` (``cam_R_m2c``, ``cam_t_m2c`` in mm, ``obj_id``),
``scene_gt_info.json`` (``bbox_obj``, ``bbox_visib`` as ``[x, y, w, h]`` with
w = max col - min col as ``bop_toolkit.misc.calc_2d_bbox``, ``[-1] * 4`` when nothing is
visible; ``px_count_all``, ``px_count_valid``, ``px_count_visib``, ``visib_fract``),
``rgb/``, ``depth/`` (16-bit PNG: depth in mm = value * depth_scale, 0 = none),
``mask/`` (unoccluded silhouette) and ``mask_visib/`` PNGs ``{im_id:06d}_{gt_id:06d}.png``.

Our choices: one scene per config (record ``config``), numbered from 1 in order of first
appearance; image ids count the scene's views from 0 (``scene_views.json`` maps them to
view keys); ``gt_id`` is the object's position in the record's ``objects``; poses use
the OpenCV camera frame (x right, y down, z forward) as BOP does. ``obj_id`` is the
category id (``obj_ids="category"``) or a number per distinct object name (``"name"``);
``exports/bop/obj_ids.json`` maps ids to names. BOP models are in mm: a model for this
export is the object's mesh times ``mm_per_unit``; an object scaled in the scene gets
``model_scale`` (per model axis) in ``scene_gt`` and the unit rotation in ``cam_R_m2c``.
``bbox_obj`` / ``px_count_all`` are the silhouette inside the image (the toolkit renders
a larger canvas for truncated objects).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .common import (
    EXPORTS,
    ExportError,
    copy_file,
    field,
    file_path,
    load,
    mask_bbox,
    objects,
    read_amodal,
    read_depth,
    read_instance,
    view_name,
    write_json,
    write_png,
)

#: depth_scale values (mm per PNG unit) tried in order when none is given.
DEPTH_SCALES = (0.1, 1.0, 10.0, 100.0)


def _bop_bbox(mask: np.ndarray) -> list[int]:
    box = mask_bbox(mask)
    if box is None:
        return [-1, -1, -1, -1]
    return [box[0], box[1], box[2] - 1 - box[0], box[3] - 1 - box[1]]


def _matrix(record: dict, *names: str) -> np.ndarray:
    m = np.asarray(field(record, *names), dtype=np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise ExportError(f"view {view_name(record)}: {'.'.join(names)}: expected a finite "
                          f"4x4 matrix, got shape {m.shape}")
    return m


def model_to_camera(record: dict, obj: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An object's pose in the OpenCV camera frame: rotation ``(3, 3)``, translation ``(3,)``
    (world units) and scale per model axis ``(3,)`` (``M = [R diag(s) | t]``).

    Raises:
        ExportError: a sheared / mirrored transform, which no rigid pose + scale holds.
    """
    w2c = _matrix(record, "opencv", "world_to_camera")
    o2w = np.asarray(obj.get("object_to_world"), dtype=np.float64)
    if o2w.shape != (4, 4):
        raise ExportError(f"view {view_name(record)}: object {obj['instance_id']}: "
                          "object_to_world: expected a 4x4 matrix")
    m = w2c @ o2w
    scale = np.linalg.norm(m[:3, :3], axis=0)
    rot = m[:3, :3] / scale
    if not (np.allclose(rot.T @ rot, np.eye(3), atol=1e-5) and np.linalg.det(rot) > 0):
        raise ExportError(f"view {view_name(record)}: object {obj['instance_id']}: "
                          "object_to_world is sheared or mirrored; BOP poses are rotations")
    return rot, m[:3, 3], scale


def _depth_scale(depth_mm: np.ndarray, chosen: float | None, record: dict) -> float:
    top = float(depth_mm.max(initial=0.0))
    if chosen is not None:
        if top / chosen > 65535:
            raise ExportError(f"view {view_name(record)}: depth {top:.1f} mm does not fit a "
                              f"16-bit PNG at depth_scale={chosen} mm")
        return chosen
    for scale in DEPTH_SCALES:
        if top / scale <= 65535:
            return scale
    raise ExportError(f"view {view_name(record)}: depth {top:.1f} mm exceeds 16 bits at "
                      f"depth_scale={DEPTH_SCALES[-1]} mm; pass depth_scale=")


def _obj_ids(records: list[dict], mode: str) -> dict[str, int]:
    """Object name (or category name) -> BOP obj_id."""
    ids: dict[str, int] = {}
    for r in records:
        names = r.get("categories") or []
        for obj in objects(r):
            if mode == "category":
                cat = int(obj.get("category_id") or 0)
                if cat < 1:
                    raise ExportError(f"view {view_name(r)}: object {obj['instance_id']} has "
                                      "no category; use obj_ids='name'")
                label = names[cat - 1] if cat <= len(names) else f"category {cat}"
                ids.setdefault(label, cat)
            else:
                label = obj.get("name") or f"instance {obj['instance_id']}"
                ids.setdefault(label, len(ids) + 1)
    return ids


def _obj_id(obj: dict, mode: str, ids: dict[str, int]) -> int:
    if mode == "category":
        return int(obj["category_id"])
    return ids[obj.get("name") or f"instance {obj['instance_id']}"]


def _flat(m: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(m).reshape(-1)]


def write_bop(out_dir: str | Path, records: list[dict] | None = None, *,
              depth_scale: float | None = None, mm_per_unit: float = 1000.0,
              obj_ids: str = "category", image_file: str = "color.png") -> list[Path]:
    """Write the dataset in the BOP format under ``<out_dir>/exports/bop`` (see the module
    docstring); every file atomically. Returns the written paths.

    Args:
        out_dir: the rendered dataset folder; its records need ``opencv.K``,
            ``opencv.world_to_camera``, ``objects`` (``instance_id``, ``object_to_world``,
            ``category_id`` or ``name``) and the files ``color.png``, ``instance.npy`` (or
            ``.png``), ``amodal.npy`` and ``depth.npy``.
        records: its manifest records (default: ``read_manifest(out_dir)``).
        depth_scale: mm per depth PNG unit; None picks per view the finest of
            :data:`DEPTH_SCALES` that holds the farthest depth.
        mm_per_unit: millimetres per world unit (1000: metres).
        obj_ids: ``"category"`` (obj_id = category id) or ``"name"``.
        image_file: the record file copied to ``rgb/``.

    Raises:
        ExportError: a missing record field or channel file, named; an orthographic view.
    """
    if obj_ids not in ("category", "name"):
        raise ValueError(f"obj_ids: expected 'category' or 'name', got {obj_ids!r}")
    if not (math.isfinite(mm_per_unit) and mm_per_unit > 0):
        raise ValueError(f"mm_per_unit: expected a positive number, got {mm_per_unit}")
    if depth_scale is not None and not (math.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f"depth_scale: expected a positive number of mm, got {depth_scale}")
    out_dir, records = load(out_dir, records)
    root = out_dir / EXPORTS / "bop"
    ids = _obj_ids(records, obj_ids)
    scenes: dict[str, list[dict]] = {}
    for r in records:
        scenes.setdefault(str(field(r, "config")), []).append(r)
    written = [write_json(root / "obj_ids.json", {str(v): k for k, v in ids.items()})]
    for scene_id, views in enumerate(scenes.values(), start=1):
        written += _write_scene(out_dir, root / f"{scene_id:06d}", views, depth_scale,
                                mm_per_unit, obj_ids, ids, image_file)
    return written


def _write_scene(out_dir: Path, folder: Path, views: Sequence[dict], depth_scale: float | None,
                 mm_per_unit: float, mode: str, ids: dict[str, int], image_file: str
                 ) -> list[Path]:
    cams, gts, infos, keys, written = {}, {}, {}, {}, []
    for im_id, r in enumerate(views):
        name = f"{im_id:06d}"
        k = field(r, "opencv").get("K")
        if k is None:
            raise ExportError(f"view {view_name(r)}: opencv.K is null (an orthographic "
                              "camera): BOP needs a pinhole camera")
        w2c = _matrix(r, "opencv", "world_to_camera")
        objs = objects(r)
        instance = read_instance(out_dir, r)
        amodal = read_amodal(out_dir, r, max((o["instance_id"] for o in objs), default=0))
        depth_mm = read_depth(out_dir, r) * mm_per_unit
        scale = _depth_scale(depth_mm, depth_scale, r)
        cams[str(im_id)] = {"cam_K": _flat(k), "depth_scale": scale,
                            "cam_R_w2c": _flat(w2c[:3, :3]),
                            "cam_t_w2c": _flat(w2c[:3, 3] * mm_per_unit)}
        keys[str(im_id)] = r.get("key")
        written.append(copy_file(file_path(out_dir, r, image_file), folder / "rgb" / f"{name}.png"))
        png = np.round(depth_mm / scale).astype(np.uint16)
        written.append(write_png(folder / "depth" / f"{name}.png", png))
        gts[str(im_id)], infos[str(im_id)] = [], []
        for gt_id, obj in enumerate(objs):
            rot, t, s = model_to_camera(r, obj)
            gt = {"cam_R_m2c": _flat(rot), "cam_t_m2c": _flat(t * mm_per_unit),
                  "obj_id": _obj_id(obj, mode, ids)}
            if not np.allclose(s, 1.0, rtol=0, atol=1e-6):
                gt["model_scale"] = _flat(s)
            gts[str(im_id)].append(gt)
            full = amodal[obj["instance_id"] - 1]
            visible = instance == obj["instance_id"]
            n_all, n_vis = int(full.sum()), int(visible.sum())
            infos[str(im_id)].append({
                "bbox_obj": _bop_bbox(full) if n_vis else [-1, -1, -1, -1],
                "bbox_visib": _bop_bbox(visible),
                "px_count_all": n_all, "px_count_valid": int((full & (depth_mm > 0)).sum()),
                "px_count_visib": n_vis, "visib_fract": n_vis / n_all if n_all else 0.0})
            stem = f"{name}_{gt_id:06d}.png"
            written.append(write_png(folder / "mask" / stem, full.astype(np.uint8) * 255))
            written.append(write_png(folder / "mask_visib" / stem,
                                     visible.astype(np.uint8) * 255))
    for fname, data in (("scene_camera.json", cams), ("scene_gt.json", gts),
                        ("scene_gt_info.json", infos), ("scene_views.json", keys)):
        written.append(write_json(folder / fname, data))
    return written
