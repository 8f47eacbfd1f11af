"""Benchmark the stylised shading models, the dissolve effect and background images in the
renderer: run time at 512x512 against pbr / the plain render, and the error of the
float32 render against the same render in float64 (the high-quality reference).

Scene: configs/shading_models.yaml (Spot on a ground plane, a sun and ambient light;
shadow maps off, so the rows time the shading and the effects, not the shadow pass).

Writes section ``shading-models`` of docs/benchmarks.md. Run from the repo root:

    python scripts/bench_models.py           # 512x512, 7 rounds (about four minutes on 2 cores)
    python scripts/bench_models.py --quick   # 128x128 smoke run, does not write the doc
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
from benchmd import markdown_table, median_time, update_section

import torchraster as tr
from torchraster.background import load_background
from torchraster.config import lights_from_config
from torchraster.dissolve import Dissolve
from torchraster.pipeline import build_camera, build_scene

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    size = 128 if args.quick else 512
    start = time.perf_counter()
    cfg = tr.load_config(ROOT / "configs" / "shading_models.yaml")
    scene = build_scene(cfg)
    view, proj = build_camera(cfg.cameras[0], scene.positions, (size, size))
    lights = lights_from_config(cfg.lights, 1)
    toon = cfg.render.toon.model_dump()
    sky = load_background(ROOT / "torchraster" / "assets" / "envmaps" / "venice_sunset_256.hdr")
    scene64 = tr.RenderScene(scene.positions.double(), scene.faces, scene.normals.double(),
                             scene.uvs.double(), None, scene.face_material, scene.materials)
    lights64 = lights.to(dtype=torch.float64)

    model_rows = [("pbr (Cook-Torrance)", {"shading": "pbr"})]
    model_rows += [(shading + (" (bands 3, rim)" if shading == "toon" else ""),
                    {"shading": tr.ShadingSettings(shading, toon if shading == "toon" else {})})
                   for shading in ("blinn_phong", "half_lambert", "toon")]
    effect_rows = [
        ("dissolve t=0.5 (4 depth layers)", {"dissolve": Dissolve(threshold=0.5)}),
        ("dissolve t=0.5, alpha_layers=1", {"dissolve": Dissolve(threshold=0.5),
                                            "raster": tr.RasterSettings(alpha_layers=1)}),
        ("background image, cover", {"background": tr.BackgroundSettings(image=sky)}),
        ("background image, contain", {"background": tr.BackgroundSettings(image=sky,
                                                                           fit="contain")})]
    renderers = {name: tr.Renderer(size, shadows=False, **kwargs)
                 for name, kwargs in model_rows + effect_rows}
    # rounds interleave the configurations, so load from other jobs spreads over all rows
    times: dict[str, list[float]] = {name: [] for name in renderers}
    cpu: dict[str, list[float]] = {name: [] for name in renderers}
    with torch.no_grad():
        for r in renderers.values():  # warm-up (caches, tables)
            r(scene, view, proj, lights)
        for _ in range(args.repeats):
            for name, r in renderers.items():
                c = time.process_time()
                times[name].append(median_time(lambda r=r: r(scene, view, proj, lights), 1,
                                               warmup=False))
                cpu[name].append(time.process_time() - c)
        errors = {}
        for name, r in renderers.items():
            img = r(scene, view, proj, lights).image.double()
            ref = r(scene64, view.double(), proj.double(), lights64).image
            errors[name] = (float((img - ref).abs().mean()), float((img - ref).abs().max()))
    med = {name: statistics.median(t) for name, t in times.items()}
    med_cpu = {name: statistics.median(t) for name, t in cpu.items()}
    pbr = med["pbr (Cook-Torrance)"]
    pbr_cpu = med_cpu["pbr (Cook-Torrance)"]
    for name in renderers:
        print(f"{name:34s} {med[name]:7.3f} s  x{med[name] / pbr:5.2f}  cpu "
              f"{med_cpu[name]:7.3f} s  x{med_cpu[name] / pbr_cpu:5.2f}  "
              f"mean err {errors[name][0]:.2e}")

    def table(rows: list, first: str, ratio: str) -> str:
        return markdown_table([first, "median (s)", ratio, "CPU (s)", f"CPU {ratio}",
                               "mean abs err vs float64", "max abs err"],
                              [[n, med[n], med[n] / pbr, med_cpu[n], med_cpu[n] / pbr_cpu,
                                *errors[n]] for n, _ in rows])

    table_models = table(model_rows, "shading", "x pbr")
    effects_table = table(effect_rows, "pbr +", "x plain pbr")
    elapsed = time.perf_counter() - start
    body = (
        f"## Shading models, dissolve, background image ({elapsed:.0f} s)\n\n"
        f"{size}x{size}, configs/shading_models.yaml (Spot on a ground plane, a sun and "
        "ambient light, shadow maps off), float32 and no autograd; medians of "
        f"{args.repeats} rounds, each round timing every row once (interleaved, so load "
        "from other jobs on the machine spreads over all rows); CPU is this process's CPU "
        "time (both threads), less sensitive to other jobs than wall time. The error "
        "columns compare "
        "the float32 render with the same render in float64 (linear radiance). The "
        "stylised models run the generic light loop (lights as a tensor dimension over the "
        "whole frame) where pbr has its fused pass over the covered pixels (with the "
        "energy-compensation terms).\n\n"
        f"{table_models}\n\nEffects on top of pbr. The dissolve rows include the depth "
        "layers it needs to show what is behind a discarded surface (`alpha_layers`, 4 by "
        "default: every layer gets a G-buffer, its noise is evaluated on its covered "
        "pixels); with one layer only the background shows through the holes. Max errors "
        "come from silhouette pixels (and, for dissolve, from pixels whose noise lies within "
        "float32 rounding of the threshold: kept in one precision, discarded in the "
        "other).\n\n"
        f"{effects_table}\n"
    )
    print(f"done in {elapsed:.0f} s")
    if not args.quick:
        update_section("shading-models", body)


if __name__ == "__main__":
    main()
