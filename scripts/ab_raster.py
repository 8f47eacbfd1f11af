"""In-process A/B timing of rasterize + interpolate: this checkout against an older one.

On a shared machine, timings of separate processes drift by 10-20 % between runs, more than
most single changes are worth. This script imports both codes into one process (the older
one renamed), calls them in alternating order on the same inputs, checks that their images
agree, and prints the median of the per-turn time ratios. Use it to decide whether a change
is kept; quote the tables of ``bench_raster.py`` for absolute figures.

    git archive HEAD torchraster | tar -x -C /tmp/before    # the code to compare against
    python scripts/ab_raster.py /tmp/before "82k frame 512 8" "5k 256 1" --turns 24

Rows are "<faces> <resolution> <batch>" as in ``bench_raster.py --rows`` (faces 5k, 80k,
1.3M, or "82k frame" for the random frame-filling views). ``--grad`` adds a backward pass.
"""

from __future__ import annotations

import argparse
import atexit
import importlib
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from bench_raster import SUBDIV
from benchmd import markdown_table, update_section


def load_renamed(src: Path, name: str):
    """Import the ``torchraster`` package found in ``src`` under the module name ``name``."""
    root = Path(tempfile.mkdtemp(prefix="ab_raster_"))
    atexit.register(shutil.rmtree, root, True)
    shutil.copytree(src / "torchraster", root / name)
    for path in (root / name).rglob("*.py"):
        path.write_text(path.read_text().replace("torchraster", name))
    sys.path.insert(0, str(root))
    return importlib.import_module(name)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path, help="directory holding the older torchraster/")
    ap.add_argument("rows", nargs="+", help="rows such as '82k frame 512 8' or '5k 256 1'")
    ap.add_argument("--turns", type=int, default=16)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--grad", action="store_true", help="also backward (sum of squares)")
    ap.add_argument("--section", default=None,
                    help="write the table to this docs/benchmarks.md section")
    ap.add_argument("--title", default="Rasterizer: before / after", help="its heading")
    ap.add_argument("--note", default="", help="text under the table (what changed)")
    args = ap.parse_args()

    import torch
    import trimesh

    import torchraster as after

    before = load_renamed(args.before, "torchraster_before")
    torch.set_num_threads(args.threads)
    print("row | before ms | after ms | after / before (median of per-turn ratios)")
    rows = []
    for text in args.rows:
        *name, res, batch = text.split()
        name, res, batch = " ".join(name), int(res), int(batch)
        mesh = trimesh.creation.icosphere(subdivisions=SUBDIV["80k" if "frame" in name
                                                              else name])
        verts = torch.tensor(mesh.vertices, dtype=torch.float32)
        faces = torch.tensor(mesh.faces, dtype=torch.int64)
        if "frame" in name:  # as bench_raster.py: random views filling ~80 % of the frame
            g = torch.Generator().manual_seed(0)
            view = after.camera.orbit(torch.rand(batch, generator=g) * 360,
                                      torch.rand(batch, generator=g) * 140 - 70,
                                      torch.full((batch,), 2.6))
        else:
            view = after.camera.orbit(torch.linspace(0, 315, batch),
                                      torch.full((batch,), 20.0), torch.full((batch,), 3.0))
        clip = after.camera.transform_points(
            verts, after.camera.perspective(45.0, 1.0, 0.1) @ view)
        normals = verts.expand(batch, -1, -1).contiguous()

        def run(module, clip=clip, faces=faces, normals=normals, res=res):
            pos = clip.clone().requires_grad_(args.grad)
            image = module.interpolate(normals, module.rasterize(pos, faces, (res, res)), faces)
            if args.grad:
                image.square().sum().backward()
            return image.detach()

        # Same image up to pixels whose coverage moved with float rounding of an edge.
        differ = ((run(after) - run(before)).abs().amax(1) > 1e-4).float().mean().item()
        if differ > 1e-4:
            raise SystemExit(f"{text}: {differ:.1e} of the pixels differ: not the same image")
        times = {before: [], after: []}
        for turn in range(args.turns):
            for module in (before, after) if turn % 2 == 0 else (after, before):
                start = time.perf_counter()
                run(module)
                times[module].append(time.perf_counter() - start)
        ratios = [a / b for a, b in zip(times[after], times[before], strict=True)]
        ratio = statistics.median(ratios)
        print(f"{text} | {statistics.median(times[before]) * 1e3:.1f} | "
              f"{statistics.median(times[after]) * 1e3:.1f} | {ratio:.3f}", flush=True)
        rows.append([text, statistics.median(times[before]) * 1e3,
                     statistics.median(times[after]) * 1e3, ratio,
                     f"{min(ratios):.2f}-{max(ratios):.2f}"])
    if args.section:
        method = " ".join(__doc__.split("\n\n")[1].split())
        table = markdown_table(["row (faces, resolution, batch)", "before ms", "after ms",
                                "after / before (median of turns)", "per-turn range"], rows)
        update_section(args.section, f"## {args.title}\n\n{method} {args.turns} turns, "
                       f"{args.threads} torch threads{', with backward' if args.grad else ''}."
                       f"\n\n{table}\n\n{args.note}")


if __name__ == "__main__":
    main()
