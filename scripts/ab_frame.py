"""In-process A/B timing of whole ``Renderer`` frames: this checkout against an older one.

Like ``ab_raster.py`` (rasterizer) and ``ab_shadows.py`` (shadow lookups), for the whole
forward pass: both codes are imported into one process (the older one renamed), render the
same inputs in alternating order, and the table gives the medians and the median of the
per-turn time ratios, with whether the images are bit-identical (else their largest
difference).

    git archive HEAD torchraster | tar -x -C /tmp/before    # the code to compare against
    python scripts/ab_frame.py /tmp/before --turns 7

Rows ("--rows"): "<res> <batch> <what>" with what ``plain`` (one point light) or
``+``-joined tokens: ``env`` (an environment, the default lobe-table specular), ``shadow``
(the point lights cast 1024² cube maps), ``4`` (four point lights instead of one),
``ssao`` (the default ``SSAO()``), ``fog`` (``Fog(density=0.2)``: 16 march steps), or a
shading model other than pbr (``blinn_phong``, ``half_lambert``, ``toon``); ``shadow4`` is
``shadow+4``. Frame: Spot (5856 faces, its 1024² texture) from orbit views, as
``bench_memory.py``.
"""

from __future__ import annotations

import argparse
import importlib
import math
import statistics
import time
from pathlib import Path

import torch
from ab_raster import load_renamed
from benchmd import markdown_table, update_section

import torchraster as after

ROWS = ("512 8 plain", "512 8 env", "512 1 shadow", "512 1 shadow4", "512 4 env+shadow")


def _sky(h: int = 64) -> torch.Tensor:
    """A procedural ``(1, 3, h, 2h)`` sky (no data files)."""
    theta = torch.linspace(0, math.pi, h)[:, None]
    return torch.stack([0.4 + 0.6 * theta.cos().clamp_min(0), 0.5 + 0.3 * theta.sin(),
                        0.8 + 0.0 * theta], 0).expand(3, h, 2 * h).contiguous()[None]


def _inputs(module, res: int, batch: int, what: str):
    """(renderer, args) of a row built with ``module``'s classes."""
    mesh = module.load_spot()
    scene = module.RenderScene.from_mesh(mesh)
    view = module.camera.orbit(torch.arange(batch) * (360.0 / 8), 15.0, 2.2)
    proj = module.camera.perspective(45.0, 1.0, 0.1)
    tokens = set(what.replace("shadow4", "shadow+4").split("+"))
    n = 4 if "4" in tokens else 1
    ang = torch.arange(n) * (2 * math.pi / n)
    pos = torch.stack([2.0 * torch.cos(ang), 2.0 + 0 * ang, 3.0 * torch.sin(ang) + 1.0], -1)
    shadow = "shadow" in tokens
    settings = module.shading.shadows.ShadowSettings(map_size=1024) if shadow else None
    point = module.PointLights(position=pos[None], color=torch.ones(1, n, 3),
                               intensity=torch.full((1, n), 20.0 / n),
                               cast_shadows=torch.full((1, n), shadow), shadow=settings)
    env = module.Environment(_sky()) if "env" in tokens else None
    models = tokens & {"blinn_phong", "half_lambert", "toon"}
    post = importlib.import_module(module.__name__ + ".post")
    volumetric = importlib.import_module(module.__name__ + ".shading.volumetric")
    renderer = module.Renderer(res, shading=models.pop() if models else "pbr",
                               ssao=post.SSAO() if "ssao" in tokens else None,
                               fog=volumetric.Fog(density=0.2) if "fog" in tokens else None)
    renderer.shadow_cache = None  # every frame draws its maps (moving lights or scene)
    return renderer, (scene, view, proj, module.Lights(point=point), env)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path, help="directory holding the older torchraster/")
    ap.add_argument("--rows", nargs="+", default=list(ROWS))
    ap.add_argument("--turns", type=int, default=7)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--section", default=None,
                    help="write the table to this docs/benchmarks.md section")
    ap.add_argument("--title", default="Whole frames: before / after")
    ap.add_argument("--note", default="", help="text under the table (what changed)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    before = load_renamed(args.before, "torchraster_before")
    rows = []
    for text in args.rows:
        res, batch, what = text.split()
        runs = {m: _inputs(m, int(res), int(batch), what) for m in (before, after)}
        times: dict[object, list[float]] = {before: [], after: []}
        images = {}
        with torch.no_grad():
            for module, (renderer, inputs) in runs.items():  # warm-up
                images[module] = renderer(*inputs).image
            for turn in range(args.turns):
                for module in (before, after) if turn % 2 == 0 else (after, before):
                    renderer, inputs = runs[module]
                    t = time.perf_counter()
                    renderer(*inputs)
                    times[module].append(time.perf_counter() - t)
        diff = float((images[before] - images[after]).abs().max())
        ratios = [b / a for b, a in zip(times[before], times[after], strict=True)]
        rows.append([f"{res}²", int(batch), what, statistics.median(times[before]) * 1e3,
                     statistics.median(times[after]) * 1e3, statistics.median(ratios),
                     f"{min(ratios):.2f}-{max(ratios):.2f}",
                     "yes" if diff == 0 else f"no ({diff:.2g})"])
        print(rows[-1], flush=True)
    table = markdown_table(["frame", "batch", "scene", "before ms", "after ms",
                            "before / after (median of turns)", "per-turn range",
                            "bit-identical image"], rows)
    print(table)
    if args.section:
        method = " ".join(__doc__.split("\n\n")[1].split())
        update_section(args.section, f"## {args.title}\n\n{method}\n\n{table}\n\n{args.note}")


if __name__ == "__main__":
    main()
