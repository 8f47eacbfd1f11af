"""Pictures of the shading models and the dissolve effect, from the shipped configs.

    python scripts/make_models_pictures.py

* docs/images/shading_models_config.png: configs/shading_models.yaml rendered with
  ``render.shading`` = pbr (Cook-Torrance), blinn_phong, half_lambert and toon (the file's
  own line), side by side: one config line switches the model.
* docs/images/dissolve.png: configs/dissolve.yaml at thresholds 0.2, 0.45 and 0.7 (with its
  background image behind the holes).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

import torchraster as tr

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT / "docs" / "images"


def _render(cfg) -> np.ndarray:
    (view,) = tr.render_config(cfg)
    return (view.images["color"].clamp(0, 1).permute(1, 2, 0).numpy() * 255 + 0.5).astype(
        np.uint8)


def _strip(panels: list[np.ndarray], labels: list[str], path: Path) -> None:
    """Panels side by side with a label in each top-left corner, saved as PNG."""
    img = Image.fromarray(np.concatenate(panels, axis=1))
    draw = ImageDraw.Draw(img)
    w = panels[0].shape[1]
    for i, label in enumerate(labels):
        draw.rectangle([i * w + 4, 4, i * w + 8 + 6 * len(label), 18], fill=(0, 0, 0))
        draw.text((i * w + 6, 5), label, fill=(255, 255, 255))
    img.save(path, optimize=True)
    print(f"wrote {path} ({path.stat().st_size // 1024} KB)")


def shading_models() -> None:
    cfg = tr.load_config(ROOT / "configs" / "shading_models.yaml")
    toon = cfg.render.toon
    panels, labels = [], []
    for shading in ("pbr", "blinn_phong", "half_lambert", "toon"):
        cfg.render.shading = shading
        cfg.render.toon = toon if shading == "toon" else None
        panels.append(_render(cfg))
        labels.append("pbr (cook_torrance)" if shading == "pbr" else shading)
    _strip(panels, labels, IMAGES / "shading_models_config.png")


def dissolve() -> None:
    cfg = tr.load_config(ROOT / "configs" / "dissolve.yaml")
    panels, labels = [], []
    for t in (0.2, 0.45, 0.7):
        cfg.render.dissolve.threshold = t
        panels.append(_render(cfg))
        labels.append(f"threshold {t}")
    _strip(panels, labels, IMAGES / "dissolve.png")


if __name__ == "__main__":
    torch.set_num_threads(2)
    which = sys.argv[1:] or ["models", "dissolve"]
    if "models" in which:
        shading_models()
    if "dissolve" in which:
        dissolve()
