"""NeRF / instant-ngp / nerfstudio camera file of a rendered dataset
(``exports/nerf/transforms.json``).

Format (the Blender synthetic scenes of NeRF, extended by instant-ngp and nerfstudio):
``camera_angle_x`` (horizontal field of view, radians), ``fl_x``, ``fl_y``, ``cx``, ``cy``,
``w``, ``h`` and ``frames``, each with ``file_path`` (relative to the JSON's folder) and
``transform_matrix``: camera-to-world in the OpenGL / Blender camera convention (x right,
y up, looking down -z), i.e. the record's ``opengl.view_to_world``. These tools cast the ray
of pixel column j through x = j + 0.5, so their ``cx`` is OpenCV's ``K[0, 2] + 0.5`` (same
for cy). When views differ in intrinsics or size, each frame also carries its own
``fl_x, fl_y, cx, cy, w, h`` (nerfstudio reads them per frame); a record with a ``time``
gives the frame's ``time`` in seconds.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from .common import EXPORTS, ExportError, field, file_path, load, resolution, view_name, write_json


def _intrinsics(record: dict) -> dict:
    k = field(record, "opencv").get("K")
    if k is None:
        raise ExportError(f"view {view_name(record)}: opencv.K is null (an orthographic "
                          "camera): NeRF needs a pinhole camera")
    k = np.asarray(k, dtype=np.float64)
    if k.shape != (3, 3) or k[0, 1] != 0:
        raise ExportError(f"view {view_name(record)}: opencv.K: expected a 3x3 matrix without "
                          "skew")
    h, w = resolution(record)
    return {"fl_x": float(k[0, 0]), "fl_y": float(k[1, 1]), "cx": float(k[0, 2]) + 0.5,
            "cy": float(k[1, 2]) + 0.5, "w": w, "h": h}


def write_nerf(out_dir: str | Path, records: list[dict] | None = None,
               image_file: str = "color.png") -> list[Path]:
    """Write ``<out_dir>/exports/nerf/transforms.json`` (atomically); returns its path.

    Args:
        out_dir: the rendered dataset folder (records need ``opencv.K``,
            ``opengl.view_to_world``, ``resolution`` and the image file).
        records: its manifest records (default: ``read_manifest(out_dir)``).
        image_file: the record file each frame points at.

    Raises:
        ExportError: a missing record field or file, named; an orthographic view.
    """
    out_dir, records = load(out_dir, records)
    path = out_dir / EXPORTS / "nerf" / "transforms.json"
    cams = [_intrinsics(r) for r in records]
    shared = all(c == cams[0] for c in cams)
    frames = []
    for r, cam in zip(records, cams, strict=True):
        c2w = np.asarray(field(r, "opengl", "view_to_world"), dtype=np.float64)
        if c2w.shape != (4, 4):
            raise ExportError(f"view {view_name(r)}: opengl.view_to_world: expected 4x4")
        image = file_path(out_dir, r, image_file)
        frame = {"file_path": Path(os.path.relpath(image, path.parent)).as_posix(),
                 "transform_matrix": c2w.tolist()}
        if not shared:
            frame.update(cam)
        if r.get("time") is not None:
            frame["time"] = float(r["time"])
        frames.append(frame)
    first = cams[0]
    data = {"camera_angle_x": 2 * math.atan(first["w"] / (2 * first["fl_x"])),
            "camera_angle_y": 2 * math.atan(first["h"] / (2 * first["fl_y"])),
            **first, "frames": frames}
    return [write_json(path, data)]
