"""Point tracks (TAP-Vid style) of a rendered video: where surface points go, frame by frame.

For every video (the frames of one camera of one scene: records sharing ``config``,
``object`` and ``camera``), ``n_points`` query pixels are drawn among the covered pixels of
its first frame (from ``rng_for(seed, key)``). Each query pixel's surface point is known
exactly from the frame's files: its instance id (``instance.npy``) and its object
coordinates (``object_coords.npy``, NOCS), turned back into the object's model frame with
the record's model box. At every frame it is moved by that object's ``object_to_world`` and
projected with the frame's camera (records only); it is *occluded* where it leaves the
image, goes behind the camera, or another surface is in front of it (the frame's
``instance.npy`` at that pixel is another object, or ``depth.npy`` is more than 1 %
nearer: :func:`torchraster.labels.keypoint_visibility`, the keypoints' test).

Writes ``exports/tracks/<video>.npz`` with (TAP-Vid's layout):

* ``tracks`` ``(N, T, 2)`` float32 pixel positions, x right, y down, pixel centres at
  integers + 0.5 (TAP-Vid's raster convention, as the query pixel (row i, col j) is at
  (j + 0.5, i + 0.5)); ``points`` the same divided by (W, H) (TAP-Vid's [0, 1] coordinates);
* ``occluded`` ``(N, T)`` bool;
* ``query_points`` ``(N, 3)`` float32 ``(t, y, x)`` of each query (t = 0, "first" mode);
* ``instance`` ``(N,)`` int32 the object of each point; ``keys`` the T view keys.
"""

from __future__ import annotations

import io
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from ..labels import keypoint_visibility, project
from ..pipeline import atomic_write
from ..randomize import rng_for
from .common import (
    EXPORTS,
    ExportError,
    field,
    file_path,
    load,
    read_depth,
    read_instance,
    resolution,
    view_name,
)
from .wds import sample_key


def videos(records: list[dict]) -> dict[str, list[dict]]:
    """Records grouped into videos (same config, object and camera), each in frame order."""
    groups: dict[str, list[dict]] = defaultdict(list)
    for r in records:
        name = "/".join(str(r.get(k, "")) for k in ("config", "object", "camera"))
        groups[name].append(r)
    return {k: sorted(v, key=lambda r: int(r.get("frame", 0))) for k, v in groups.items()}


def _model_points(out_dir: Path, first: dict, n_points: int, seed: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Query pixels of the first frame: (rows, cols), instance ids and model-space points."""
    inst = read_instance(out_dir, first)
    nocs = np.load(file_path(out_dir, first, "object_coords.npy")).astype(np.float64)
    h, w = resolution(first)
    if nocs.shape != (3, h, w):
        raise ExportError(f"view {view_name(first)}: object_coords.npy: expected shape "
                          f"(3, {h}, {w}), got {nocs.shape}")
    rows, cols = np.nonzero(inst > 0)
    if len(rows) == 0:
        raise ExportError(f"view {view_name(first)}: no covered pixel to track")
    g = rng_for(seed, first["key"])
    pick = g.choice(len(rows), size=min(n_points, len(rows)), replace=False)
    pick.sort()
    rows, cols = rows[pick], cols[pick]
    ids = inst[rows, cols]
    boxes = {o["instance_id"]: o["box3d"] for o in field(first, "objects")}
    model = np.empty((len(ids), 3))
    for k, (i, j, obj) in enumerate(zip(rows, cols, ids, strict=True)):
        box = boxes.get(int(obj))
        if box is None:
            raise ExportError(f"view {view_name(first)}: no object record for instance {obj}")
        center, size = np.array(box["center_model"]), np.array(box["size_model"])
        diag = np.linalg.norm(size) or 1.0  # NOCS: (p - c) / |diagonal| + 0.5
        model[k] = (nocs[:, i, j] - 0.5) * diag + center
    return np.stack([rows, cols], 1), ids, model


def track_video(out_dir: Path, frames: list[dict], n_points: int, seed: int) -> dict:
    """The arrays of one video (see the module docstring)."""
    (rc, ids, model) = _model_points(out_dir, frames[0], n_points, seed)
    h, w = resolution(frames[0])
    n, t = len(ids), len(frames)
    tracks = np.zeros((n, t, 2), np.float32)
    occluded = np.ones((n, t), bool)
    for f, rec in enumerate(frames):
        poses = {o["instance_id"]: np.array(o["object_to_world"]) for o in field(rec, "objects")}
        k = field(rec, "opencv", "K")
        w2c = torch.tensor(field(rec, "opencv", "world_to_camera"), dtype=torch.float64)
        inst = torch.from_numpy(read_instance(out_dir, rec))
        depth = torch.from_numpy(read_depth(out_dir, rec))
        for obj in np.unique(ids):
            sel = ids == obj
            m = poses.get(int(obj))
            if m is None:
                raise ExportError(f"view {view_name(rec)}: no object record for instance {obj}")
            world = torch.from_numpy(model[sel] @ m[:3, :3].T + m[:3, 3])
            cam, pix = project(world, w2c, torch.tensor(k, dtype=torch.float64))
            seen = keypoint_visibility(pix, cam[:, 2], int(obj), inst, depth)
            tracks[sel, f] = (pix.nan_to_num(-1.0) + 0.5).numpy()  # pixel centres at +0.5
            occluded[sel, f] = ~seen.numpy()
    query = np.stack([np.zeros(n), rc[:, 0] + 0.5, rc[:, 1] + 0.5], 1).astype(np.float32)
    return {"tracks": tracks, "points": tracks / np.array([w, h], np.float32),
            "occluded": occluded, "query_points": query, "instance": ids.astype(np.int32),
            "keys": np.array([r["key"] for r in frames])}


def write_tracks(out_dir: str | Path, records: list[dict] | None = None,
                 n_points: int = 256, seed: int = 0) -> list[Path]:
    """Write ``exports/tracks/<video>.npz`` for every video of the records (atomically);
    returns the paths.

    Args:
        out_dir: the rendered dataset folder; its views need ``instance``,
            ``object_coords`` and ``depth`` (npy) and their records' ``objects`` and
            ``opencv`` camera.
        records: its manifest records (default: ``read_manifest(out_dir)``).
        n_points: query points per video (fewer if fewer pixels are covered).
        seed: the query points' seed.

    Raises:
        ExportError: a missing field or file, named.
    """
    out_dir, records = load(out_dir, records)
    if not isinstance(n_points, int) or isinstance(n_points, bool) or n_points < 1:
        raise ExportError(f"n_points: expected an int >= 1, got {n_points!r}")
    written = []
    for name, frames in videos(records).items():
        arrays = track_video(out_dir, frames, n_points, seed)
        path = out_dir / EXPORTS / "tracks" / f"{sample_key(name)}.npz"
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        data = buf.getvalue()
        atomic_write(path, lambda p, data=data: Path(p).write_bytes(data))
        written.append(path)
    return written


__all__ = ["track_video", "videos", "write_tracks"]
