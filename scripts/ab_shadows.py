"""In-process A/B timing of shadow lookups: this checkout against an older one.

Rows are scenes of ``bench_shadows.py``'s shadow-pass table (512² image, 512² maps, PCF, no
map cache: every render draws its maps). Both codes are imported into one process (the
older one renamed, as ``ab_raster.py`` does) and render the same inputs in alternating
order, turn by turn; each render reports the CPU time of the renderer's lookup step
(``Renderer._shadow_hook``: every light's visibility of every receiver; one torch thread).
The table gives the medians and the median of the per-turn ratios: on this shared machine
separate processes drifted by up to 1.5x between runs, more than the change measured.

    git worktree add /tmp/before <commit>
    python scripts/ab_shadows.py /tmp/before --turns 5

Rows: "<scene> <light> <lights> <batch>" (``--rows``), scene ``sphere`` or ``typical``.
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import time
from pathlib import Path

import bench_shadows as bs
import torch
from ab_raster import load_renamed
from benchmd import markdown_table, update_section

import torchraster as after

ROWS = ("sphere point 1 1", "sphere point 4 1", "sphere point 16 1", "sphere spot 16 1",
        "typical point 4 1", "typical point 16 1", "sphere point 16 4", "typical point 16 4")


def _inputs(module, scene_name: str, kind: str, n: int, batch: int):
    """(renderer, scene, view, proj, lights) of a row, built with ``module``'s classes."""
    if scene_name == "sphere":
        (positions, faces, cast), (view, proj) = bs.sphere_scene(), bs.camera()
    else:
        (positions, faces, cast), (view, proj) = bs.typical_scene()
    scene = module.RenderScene(positions, faces, cast_shadows=cast, materials=[
        module.Material(metallic_factor=0.0, roughness_factor=0.8)])
    settings = importlib.import_module(module.__name__ + ".shading.shadows").ShadowSettings(
        map_size=512)
    raytrace = importlib.import_module(module.__name__ + ".testing.raytrace")
    lights = raytrace.make_lights(kind, settings, count=n, batch=batch)
    part = getattr(lights, kind)
    part.position = bs._light_positions(scene_name, n).expand(batch, n, 3)
    if kind == "spot":
        part.direction = (-part.position if scene_name == "sphere"
                          else torch.tensor([0.0, -1.0, 0.0]).expand(batch, n, 3))
    renderer = module.Renderer(512)
    renderer.shadow_cache = None
    return renderer, scene, view.expand(batch, 4, 4), proj, lights


def _timed_lookup(renderer) -> list[float]:
    """Wrap the renderer's lookup step; the returned list accumulates its CPU seconds."""
    spent = [0.0]
    hook = renderer._shadow_hook

    def timed(*args, **kwargs):
        t = time.process_time()
        try:
            return hook(*args, **kwargs)
        finally:
            spent[0] += time.process_time() - t

    renderer._shadow_hook = timed
    return spent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path, help="directory holding the older torchraster/")
    ap.add_argument("--rows", nargs="+", default=list(ROWS))
    ap.add_argument("--turns", type=int, default=5)
    ap.add_argument("--section", default=None,
                    help="write the table to this docs/benchmarks.md section")
    ap.add_argument("--note", default="", help="text under the table (what changed)")
    ap.add_argument("--title", default="Shadow lookups: before / after",
                    help="the section's heading")
    args = ap.parse_args()
    torch.set_num_threads(1)
    before = load_renamed(args.before, "torchraster_before")
    rows = []
    for text in args.rows:
        scene_name, kind, n, batch = text.split()
        runs = {}
        for module in (before, after):
            renderer, *inputs = _inputs(module, scene_name, kind, int(n), int(batch))
            runs[module] = (renderer, inputs, _timed_lookup(renderer))
        times: dict[object, list[float]] = {before: [], after: []}
        images = {}
        with torch.no_grad():
            for module, (renderer, inputs, _) in runs.items():  # warm-up
                images[module] = renderer(*inputs).image
            for turn in range(args.turns):
                for module in (before, after) if turn % 2 == 0 else (after, before):
                    renderer, inputs, spent = runs[module]
                    spent[0] = 0.0
                    renderer(*inputs)
                    times[module].append(spent[0])
        same = torch.equal(images[before], images[after])
        ratios = [b / a for b, a in zip(times[before], times[after], strict=True)]
        rows.append([scene_name, kind, int(n), int(batch),
                     statistics.median(times[before]) * 1e3,
                     statistics.median(times[after]) * 1e3, statistics.median(ratios),
                     f"{min(ratios):.2f}-{max(ratios):.2f}", "yes" if same else "NO"])
        print(rows[-1], flush=True)
    table = markdown_table(["scene", "light", "lights", "batch", "before ms", "after ms",
                            "before / after (median of turns)", "per-turn range",
                            "bit-identical image"], rows)
    print(table)
    if args.section:
        method = " ".join(__doc__.split("\n\n")[1].split())
        update_section(args.section, f"## {args.title}\n\n{method}\n\n"
                       f"{table}\n\n{args.note}")


if __name__ == "__main__":
    main()
