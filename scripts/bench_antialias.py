"""Antialias benchmark: run time of ``antialias`` relative to ``rasterize``.

For an icosphere (5,120 faces) and Spot (5,856 faces) seen by cameras orbiting them, at
256^2 and 512^2, batch 1 and 4, in one process: the median time of

* ``rasterize`` (forward, no grad) and ``antialias`` (forward, no grad, on an RGB + alpha
  image from ``interpolate``, edge adjacency included), and their ratio;
* forward + backward of ``rasterize -> interpolate -> sum`` against
  ``rasterize -> interpolate -> antialias -> sum``, gradients to clip positions and vertex
  colours (the time antialiasing adds to a training step);

with the number of pixel pairs whose face ids differ and of those that blend. The
measurements of one row are interleaved (round-robin), so load changes on the machine hit
them alike.

    python scripts/bench_antialias.py            # the table, written to docs/benchmarks.md
    python scripts/bench_antialias.py --repeats 3 --no-write
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parent))

import torchraster as tr  # noqa: E402
from torchraster.raster import antialias_topology  # noqa: E402


def scene(name: str, batch: int):
    """Clip positions (B, V, 4), faces (F, 3) and vertex colours (V, 4) (RGB + alpha)."""
    if name == "icosphere":
        ico = trimesh.creation.icosphere(subdivisions=4)
        verts = torch.tensor(ico.vertices, dtype=torch.float32)
        faces = torch.tensor(ico.faces, dtype=torch.int64)
        distance = 3.0
    else:
        mesh = tr.load_spot()
        verts, faces, distance = mesh.positions, mesh.faces, 2.4
    view = tr.camera.orbit(torch.linspace(20, 290, batch), torch.full((batch,), 20.0),
                           torch.full((batch,), distance))
    clip = tr.camera.transform_points(verts, tr.camera.perspective(45.0, 1.0, 0.1) @ view)
    colors = torch.cat([verts * 0.5 + 0.5, torch.ones_like(verts[:, :1])], 1)
    return clip.reshape(batch, -1, 4).contiguous(), faces, colors


def measure(name: str, res: int, batch: int, repeats: int) -> dict:
    clip, faces, colors = scene(name, batch)
    size = (res, res)

    def raster():
        with torch.no_grad():
            return tr.rasterize(clip, faces, size)

    frags = raster()
    image = tr.interpolate(colors, frags, faces)

    def aa():
        with torch.no_grad():
            return tr.antialias(image, frags, clip, faces)

    def step(with_aa: bool):
        def run():
            c = clip.clone().requires_grad_(True)
            col = colors.clone().requires_grad_(True)
            fr = tr.rasterize(c, faces, size)
            img = tr.interpolate(col, fr, faces)
            if with_aa:
                img = tr.antialias(img, fr, c, faces)
            img.sum().backward()
        return run

    fns = {"raster": raster, "aa": aa, "train": step(False), "train_aa": step(True),
           "topology": lambda: antialias_topology(faces)}
    for fn in fns.values():  # warm-up
        fn()
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for key, fn in fns.items():
            t = time.perf_counter()
            fn()
            times[key].append(time.perf_counter() - t)
    out = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    ids = frags.face_id
    out["pairs"] = int((ids[:, :, 1:] != ids[:, :, :-1]).sum() + (ids[:, 1:] != ids[:, :-1]).sum())
    blended = aa()
    out["changed"] = int(((blended - image).abs().sum(1) > 0).sum())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args()
    from benchmd import markdown_table, update_section

    rows = []
    header = ["mesh", "resolution", "batch", "pairs", "changed px", "rasterize ms",
              "antialias ms", "antialias / rasterize", "train step ms", "+ antialias ms",
              "step ratio", "topology ms"]
    print(" | ".join(header))
    for name in ("icosphere", "spot"):
        for res in (256, 512):
            for batch in (1, 4):
                r = measure(name, res, batch, args.repeats)
                row = [name, f"{res}²", batch, r["pairs"], r["changed"], r["raster"], r["aa"],
                       r["aa"] / r["raster"], r["train"], r["train_aa"],
                       r["train_aa"] / r["train"], r["topology"]]
                rows.append(row)
                print(" | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row),
                      flush=True)
    body = (
        "## Antialiasing: `antialias` against `rasterize`\n\n"
        "Analytic antialiasing (`tr.antialias`, gradients at silhouettes and occlusion "
        "edges) of an RGB + alpha image from `interpolate`; icosphere (5,120 faces) and "
        "Spot (5,856 faces), cameras orbiting at distance 3.0 / 2.4 (fov 45°). *pairs*: "
        "4-neighbour pixel pairs whose face ids differ (the work of the walk), *changed "
        "px*: pixels the blend changed. *rasterize ms* / *antialias ms*: forward, no grad "
        "(antialias including its edge-adjacency sort, *topology ms*, which "
        "`antialias(..., topology=antialias_topology(faces))` saves across calls). "
        "*train step*: rasterize -> interpolate -> sum, forward + backward to clip "
        "positions and colours; *+ antialias*: the same with antialias before the sum. "
        f"Medians of {args.repeats} interleaved repeats after a warm-up, one process.\n\n"
        + markdown_table(header, rows)
    )
    if not args.no_write:
        update_section("antialias", body)
        print("wrote docs/benchmarks.md section 'antialias'")


if __name__ == "__main__":
    main()
