"""The README's dataset picture: one frame of configs/dataset_movi.yaml as colour, instance
ids, optical flow (colour wheel), object coordinates (NOCS) and the colour frame with each
object's visible 2D box and projected 3D box, all from the frame's files and record.

    python scripts/make_dataset_pictures.py [--scene 0] [--frame 8]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from skimage import draw
from skimage import io as skio

import torchraster as tr
from torchraster import pipeline

ROOT = Path(__file__).resolve().parent.parent
#: Box edges as pairs of corner indices (torchraster.labels.CORNER_SIGNS order).
EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]


def _u8(img: torch.Tensor) -> np.ndarray:
    return (img.clamp(0, 1).permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)


def boxes_overlay(color: np.ndarray, objects: list[dict]) -> np.ndarray:
    """The colour frame with each visible object's 2D box (white) and 3D box (its id's
    preview colour)."""
    out = color.copy()
    h, w = out.shape[:2]
    for o in objects:
        if o["bbox_visible"] is None or o["category"] in (None, "floor"):
            continue
        hue = pipeline.id_preview(torch.tensor([[[o["instance_id"]]]]))[:, 0, 0]
        rgb = (hue.numpy() * 255).astype(np.uint8)
        corners = o["box3d"]["corners_pixels"]
        if corners is not None:
            for a, b in EDGES:
                (x0, y0), (x1, y1) = corners[a], corners[b]
                rr, cc = draw.line(int(round(y0)), int(round(x0)), int(round(y1)),
                                   int(round(x1)))
                keep = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
                out[rr[keep], cc[keep]] = rgb
        x0, y0, x1, y1 = (int(v) for v in o["bbox_visible"])
        out[y0, x0:x1] = out[y1 - 1, x0:x1] = 255  # pixel-edge box: last row / column is -1
        out[y0:y1, x0] = out[y0:y1, x1 - 1] = 255
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", type=int, default=0)
    ap.add_argument("--frame", type=int, default=8)
    ap.add_argument("--out", default=str(ROOT / "docs" / "images" / "dataset_movi.png"))
    args = ap.parse_args()
    cfg = tr.load_config(ROOT / "configs" / "dataset_movi.yaml")
    plan = pipeline.plan_objects(cfg)[args.scene]
    render = pipeline.view_renderer(plan.config)
    view = next(v for v in plan.views if v.frame == args.frame)
    r = render(view.camera_config, view.folder, view.frame)
    color = _u8(r.images["color"])
    tiles = [color, _u8(pipeline.id_preview(r.images["instance"])),
             _u8(pipeline.flow_to_color(r.images["flow_forward"]) * r.mask),
             _u8(r.images["object_coords"] * r.mask), boxes_overlay(color, r.objects)]
    gap = np.full((color.shape[0], 4, 3), 255, np.uint8)
    row = np.concatenate([x for t in tiles for x in (t, gap)][:-1], 1)
    skio.imsave(args.out, row, check_contrast=False)
    print(args.out)


if __name__ == "__main__":
    main()
