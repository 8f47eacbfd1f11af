"""COCO instance annotations of a rendered dataset (``exports/coco/instances.json``).

Format (cocodataset.org/#format-data): ``images`` (id, file_name, width, height),
``annotations`` (id, image_id, category_id, segmentation, area, bbox ``[x, y, w, h]``,
iscrowd) and ``categories`` (id, name). Each visible instance of a known category is one
annotation whose segmentation is the compressed RLE (``pycocotools.mask.encode``, counts as
str) of its visible pixels, read from the exact instance channel; ``bbox`` and ``area`` are
the mask's (pixel-edge coordinates: x = min col, w = max col + 1 - x). Instances with no
visible pixel or no category (id 0) get no annotation. ``file_name`` is the colour image
relative to the output folder (use the output folder as the image root).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .common import (
    EXPORTS,
    EXTRA_HINT,
    ExportError,
    field,
    load,
    objects,
    read_instance,
    resolution,
    view_name,
    write_json,
)


def _mask_api():
    try:
        from pycocotools import mask as mask_util
    except ImportError:
        raise ImportError(f"write_coco needs pycocotools ({EXTRA_HINT})") from None
    return mask_util


def categories(records: list[dict]) -> list[str]:
    """The category names shared by every record (category id i + 1 = names[i]).

    Raises:
        ExportError: a record without ``categories``, or records that disagree.
    """
    names = None
    for r in records:
        got = field(r, "categories")
        if names is None:
            names = list(got)
        elif list(got) != names:
            raise ExportError(f"view {view_name(r)}: categories {got} differ from the first "
                              f"view's {names}: one category list per export")
    return names or []


def coco_dataset(out_dir: str | Path, records: list[dict] | None = None,
                 image_file: str = "color.png") -> dict:
    """The COCO instances dictionary of a dataset folder (see the module docstring).

    Args:
        out_dir: the rendered dataset folder.
        records: its manifest records (default: ``read_manifest(out_dir)``).
        image_file: the record file used as each image.
    """
    mask_util = _mask_api()
    out_dir, records = load(out_dir, records)
    names = categories(records)
    images, annotations = [], []
    for image_id, record in enumerate(records, start=1):
        h, w = resolution(record)
        rel = field(record, "files").get(image_file)
        if rel is None:
            raise ExportError(f"view {view_name(record)}: the record names no {image_file!r} "
                              "file")
        images.append({"id": image_id, "file_name": rel, "width": w, "height": h,
                       "view_key": record.get("key")})
        instance = read_instance(out_dir, record)
        for obj in objects(record):
            cat = int(obj.get("category_id") or 0)
            if cat == 0:
                continue
            if not 1 <= cat <= len(names):
                raise ExportError(f"view {view_name(record)}: object {obj['instance_id']}: "
                                  f"category_id {cat} is not in categories (1..{len(names)})")
            mask = instance == obj["instance_id"]
            if not mask.any():
                continue
            rle = mask_util.encode(np.asfortranarray(mask.astype(np.uint8)))
            rle["counts"] = rle["counts"].decode("ascii")
            annotations.append({
                "id": len(annotations) + 1, "image_id": image_id, "category_id": cat,
                "segmentation": rle, "area": float(mask_util.area(rle)),
                "bbox": [float(v) for v in mask_util.toBbox(rle)], "iscrowd": 0,
                "instance_id": obj["instance_id"]})
    return {"info": {"description": "torchraster dataset export"}, "images": images,
            "annotations": annotations,
            "categories": [{"id": i + 1, "name": n} for i, n in enumerate(names)]}


def write_coco(out_dir: str | Path, records: list[dict] | None = None,
               image_file: str = "color.png") -> list[Path]:
    """Write ``<out_dir>/exports/coco/instances.json`` (atomically); returns its path.

    Args:
        out_dir: the rendered dataset folder.
        records: its manifest records (default: ``read_manifest(out_dir)``).
        image_file: the record file used as each image.

    Raises:
        ImportError: pycocotools is missing (the ``datasets`` extra).
        ExportError: a missing record field or channel file, named.
    """
    data = coco_dataset(out_dir, records, image_file)
    return [write_json(Path(out_dir) / EXPORTS / "coco" / "instances.json", data)]
