"""What every exporter shares: the records, the channel files they name, atomic writes.

A record names its files relative to the output folder (``record["files"]``, see
:mod:`torchraster.manifest`); every reader here checks the file is named, exists and has
the view's resolution, and raises :class:`ExportError` naming the view and the file or
field otherwise.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from ..manifest import MANIFEST, read_manifest
from ..pipeline import atomic_write
from ..pipeline import write_png as pipeline_write_png

#: Where the exporters write, relative to the output folder.
EXPORTS = Path("exports")
#: The optional extra that installs the exporters' packages.
EXTRA_HINT = "pip install 'torchraster[datasets]'"


class ExportError(ValueError):
    """A dataset folder or record that cannot be exported (names the file or field)."""


def load(out_dir: str | Path, records: list[dict] | None) -> tuple[Path, list[dict]]:
    """The output folder as a Path and its records (``records`` or its manifest's).

    Raises:
        ExportError: no records (a missing or empty manifest).
    """
    out_dir = Path(out_dir)
    if records is None:
        if not (out_dir / MANIFEST).is_file():
            raise ExportError(f"{out_dir / MANIFEST}: no manifest (render the dataset first, "
                              "or pass records=)")
        records = read_manifest(out_dir)
    records = list(records)
    if not records:
        raise ExportError(f"{out_dir / MANIFEST}: no records to export")
    return out_dir, records


def view_name(record: dict) -> str:
    """How errors name a view: its key."""
    return repr(record.get("key", "<record without a key>"))


def field(record: dict, *names: str):
    """``record[names[0]][names[1]]...``, or an :class:`ExportError` naming the field."""
    value = record
    for i, name in enumerate(names):
        if not isinstance(value, dict) or value.get(name) is None:
            path = ".".join(names[: i + 1])
            raise ExportError(f"view {view_name(record)}: the record has no field {path!r}")
        value = value[name]
    return value


def resolution(record: dict) -> tuple[int, int]:
    """The record's ``(H, W)``."""
    res = field(record, "resolution")
    if not (isinstance(res, list | tuple) and len(res) == 2):
        raise ExportError(f"view {view_name(record)}: resolution: expected [H, W], got {res!r}")
    return int(res[0]), int(res[1])


def has_file(record: dict, name: str) -> bool:
    """Whether the record names a channel file ``name`` (e.g. ``"depth.npy"``)."""
    return isinstance(record.get("files"), dict) and name in record["files"]


def file_path(out_dir: Path, record: dict, name: str) -> Path:
    """The path of channel file ``name`` of a view (checked to exist)."""
    rel = field(record, "files").get(name)
    if rel is None:
        raise ExportError(f"view {view_name(record)}: the record names no {name!r} file "
                          f"(files: {sorted(record['files'])})")
    path = out_dir / rel
    if not path.is_file():
        raise ExportError(f"view {view_name(record)}: {path}: file missing")
    return path


def _plane(record: dict, name: str, arr: np.ndarray) -> np.ndarray:
    """``arr`` as (H, W), checked against the record's resolution."""
    h, w = resolution(record)
    if arr.ndim == 3 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.shape != (h, w):
        raise ExportError(f"view {view_name(record)}: {name}: expected shape ({h}, {w}) or "
                          f"(1, {h}, {w}), got {arr.shape}")
    return arr


def read_instance(out_dir: Path, record: dict) -> np.ndarray:
    """The view's instance ids ``(H, W)`` int64 (0 = background), from ``instance.npy``
    or else the 16-bit ``instance.png``."""
    if has_file(record, "instance.npy"):
        arr = np.load(file_path(out_dir, record, "instance.npy"))
        name = "instance.npy"
    elif has_file(record, "instance.png"):
        from skimage import io as skio

        arr = skio.imread(file_path(out_dir, record, "instance.png"))
        name = "instance.png"
    else:
        raise ExportError(f"view {view_name(record)}: the record names no 'instance.npy' or "
                          "'instance.png' file (render with the instance channel)")
    if arr.dtype.kind not in "iu":
        raise ExportError(f"view {view_name(record)}: {name}: expected integer ids, "
                          f"got {arr.dtype}")
    return _plane(record, name, arr).astype(np.int64)


def read_amodal(out_dir: Path, record: dict, count: int) -> np.ndarray:
    """The view's unoccluded silhouettes ``(N, H, W)`` bool from ``amodal.npy`` (plane k
    is instance id k + 1); ``count`` = the largest instance id needed."""
    arr = np.load(file_path(out_dir, record, "amodal.npy"))
    h, w = resolution(record)
    if arr.ndim != 3 or arr.shape[1:] != (h, w) or arr.shape[0] < count:
        raise ExportError(f"view {view_name(record)}: amodal.npy: expected shape "
                          f"({count}, {h}, {w}) (one plane per object), got {arr.shape}")
    return arr.astype(bool)


def read_depth(out_dir: Path, record: dict) -> np.ndarray:
    """The view's depth ``(H, W)`` float64 (metres along the view axis); empty pixels
    (0, negative or not finite) are 0."""
    arr = _plane(record, "depth.npy", np.load(file_path(out_dir, record, "depth.npy")))
    arr = arr.astype(np.float64)
    return np.where(np.isfinite(arr) & (arr > 0), arr, 0.0)


def objects(record: dict) -> list[dict]:
    """The record's objects, each checked to have an integer ``instance_id`` >= 1."""
    objs = field(record, "objects")
    for i, obj in enumerate(objs):
        iid = obj.get("instance_id") if isinstance(obj, dict) else None
        if not isinstance(iid, int) or iid < 1:
            raise ExportError(f"view {view_name(record)}: objects[{i}].instance_id: expected "
                              f"an int >= 1, got {iid!r}")
    return objs


def write_json(path: Path, data) -> Path:
    """Write ``data`` as JSON, atomically."""
    text = json.dumps(data, indent=1)

    def write(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)

    atomic_write(path, write)
    return path


def write_png(path: Path, image: np.ndarray) -> Path:
    """Write a uint8 / uint16 image as PNG, atomically (:func:`pipeline.write_png`)."""
    pipeline_write_png(path, image)
    return path


def copy_file(src: Path, dst: Path) -> Path:
    """Copy ``src`` to ``dst``, atomically."""
    atomic_write(dst, lambda tmp: shutil.copyfile(src, tmp))
    return dst


def mask_bbox(mask: np.ndarray) -> list[int] | None:
    """``[x0, y0, x1, y1]`` of a (H, W) mask in pixel-edge coordinates (x1 = max col + 1),
    None when empty."""
    rows, cols = np.any(mask, axis=1), np.any(mask, axis=0)
    if not rows.any():
        return None
    y = np.flatnonzero(rows)
    x = np.flatnonzero(cols)
    return [int(x[0]), int(y[0]), int(x[-1]) + 1, int(y[-1]) + 1]
