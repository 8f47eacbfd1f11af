"""Run time against error for the rasterizer's and renderer's own knobs.

* tile size and memory budget of the binning rasterizer: the image must not change (error
  0 by construction: face ids and barycentrics are compared bit for bit with the default);
  only time and peak memory move.
* supersampling of the Renderer (anti-aliasing): error against a 8x supersampled render
  of the same view (mean absolute error of the display-encoded colour, in % of the mean).
* the frame pool (``frame_pool.POOL_BYTES``) on and off: rasterize + interpolate timed in
  turns in one process (each timed call preceded by an untimed one of the same setting, so
  the pool holds the previous call's released buffers, as in a loop); images compared bit
  for bit. Its own section (``--only frame-pool`` runs just it).

    python scripts/bench_knobs.py [--quick] [--only frame-pool]
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import time

import torch
import trimesh
from benchmd import markdown_table, median_time, update_section

import torchraster as tr
from torchraster import frame_pool

raster_mod = importlib.import_module("torchraster.raster.rasterize")


def _sphere_clip(subdiv: int, batch: int):
    mesh = trimesh.creation.icosphere(subdivisions=subdiv)
    verts = torch.tensor(mesh.vertices, dtype=torch.float32)
    faces = torch.tensor(mesh.faces, dtype=torch.int64)
    view = tr.camera.orbit(torch.linspace(0, 315, batch), torch.full((batch,), 20.0),
                           torch.full((batch,), 3.0))
    return tr.camera.transform_points(verts, tr.camera.perspective(45.0, 1.0, 0.1) @ view), faces


def tile_and_budget(repeats: int) -> str:
    rows = []
    for name, subdiv, res, batch in (("80k faces, 512², batch 8", 6, 512, 8),
                                     ("5k faces, 1024², batch 2", 4, 1024, 2)):
        clip, faces = _sphere_clip(subdiv, batch)
        ref = tr.rasterize(clip, faces, (res, res))
        for tile in (8, 16, 32, 64):
            for budget_mb in (16, 96, 384):
                kw = dict(tile=tile, memory_budget=budget_mb * 2**20)
                out = tr.rasterize(clip, faces, (res, res), **kw)
                same = torch.equal(out.face_id, ref.face_id) and torch.equal(out.bary, ref.bary)
                t = median_time(lambda kw=kw, c=clip, f=faces, r=res: tr.rasterize(
                    c, f, (r, r), **kw), repeats)
                default = (tile == raster_mod.DEFAULT_TILE
                           and budget_mb * 2**20 == raster_mod.DEFAULT_MEMORY_BUDGET)
                rows.append([name, tile, budget_mb, t * 1e3, "0 (identical)" if same else
                             "DIFFERS", "default" if default else ""])
                print(rows[-1], flush=True)
    return markdown_table(["scene", "tile px", "memory budget MB", "rasterize ms", "error",
                           ""], rows)


def supersampling(repeats: int, size: int) -> str:
    scene = tr.RenderScene.from_mesh(tr.load_spot(max_texture_size=512))
    view = tr.camera.orbit(120.0, 15.0, 2.2, [0.0, 0.05, 0.0])
    proj = tr.camera.perspective(45.0, 1.0, 0.1)

    def render(s: int) -> torch.Tensor:
        with torch.no_grad():
            out = tr.Renderer((size, size),
                              shading="headlight",
                              raster=tr.RasterSettings(supersample=s))(scene, view, proj)
        return out.image.clamp(0, 1) ** (1 / 2.2)

    ref = render(8)
    rows = []
    for s in (1, 2, 3, 4, 6):
        err = float((render(s) - ref).abs().mean() / ref.mean()) * 100
        t = median_time(lambda s=s: render(s), repeats)
        rows.append([s, t * 1e3, err])
        print(rows[-1], flush=True)
    return markdown_table(["supersample", "render ms", "mean abs error vs 8x (%)"], rows)


def frame_pool_on_off(turns: int) -> str:
    rows = []
    for name, subdiv, res, batch in (("5k faces, 1024², batch 8", 4, 1024, 8),
                                     ("80k faces, 1024², batch 8", 6, 1024, 8),
                                     ("80k faces, 512², batch 8", 6, 512, 8)):
        clip, faces = _sphere_clip(subdiv, batch)
        normals = clip[..., :3].contiguous()

        def draw(clip=clip, faces=faces, normals=normals, res=res) -> torch.Tensor:
            with torch.no_grad():
                return tr.interpolate(normals, tr.rasterize(clip, faces, (res, res)), faces)

        default = frame_pool.POOL_BYTES
        times: dict[int, list[float]] = {default: [], 0: []}
        images = {}
        for turn in range(turns):
            for setting in (default, 0) if turn % 2 == 0 else (0, default):
                frame_pool.POOL_BYTES = setting
                draw()  # the previous call's buffers, released (pooled when on)
                start = time.perf_counter()
                image = draw()
                times[setting].append(time.perf_counter() - start)
                images[setting] = image
                del image
        frame_pool.POOL_BYTES = default
        frame_pool.clear()
        ratio = statistics.median(a / b for a, b in zip(times[default], times[0], strict=True))
        same = torch.equal(images[default], images[0])
        rows.append([name, statistics.median(times[0]) * 1e3,
                     statistics.median(times[default]) * 1e3, ratio,
                     "0 (identical)" if same else "DIFFERS"])
        print(rows[-1], flush=True)
    return markdown_table(["scene", "pool off ms", "pool on ms", "on / off (median of turns)",
                           "error"], rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--only", choices=["frame-pool"], help="run only this part")
    args = ap.parse_args()
    repeats = 2 if args.quick else 5
    pool = (
        "## Frame pool: rasterize + interpolate with `frame_pool` on and off\n\n"
        "`torchraster.frame_pool` keeps released frame buffers of 32 MB and up for the next "
        "call (`POOL_BYTES`, default 1 GiB; 0 = off). Timed in turns in one process, each "
        "timed call after an untimed one of the same setting (so the pool holds the previous "
        "call's buffers, as in a loop); the images are compared bit for bit. Frames whose "
        "buffers are all below 32 MB (512², batch 8) are not pooled: that row runs the same "
        "code both ways, so its ratio shows the noise of the measurement.\n\n"
        f"{frame_pool_on_off(4 if args.quick else 12)}\n")
    if args.only == "frame-pool":
        if args.quick:
            print(pool)
        else:
            update_section("knobs-frame-pool", pool,
                           command="python scripts/bench_knobs.py --only frame-pool")
        return
    tiles = tile_and_budget(repeats)
    ss = supersampling(repeats, 128 if args.quick else 256)
    body = (
        "## Rasterizer and renderer knobs: run time against error\n\n"
        "Tile size and memory budget only move time and memory: every setting gives the "
        "same face ids and barycentrics bit for bit (the error column checks it).\n\n"
        f"{tiles}\n\nSupersampling (anti-aliasing) of `Renderer`, Spot with its texture, "
        "headlight shading; error = mean absolute difference of the gamma-encoded colour "
        "against an 8x supersampled render, in % of its mean. Default: 1 (off) for training "
        "(differentiable, cheapest); the quickstart config uses 2.\n\n"
        f"{ss}\n"
    )
    if not args.quick:
        update_section("knobs", body)
        update_section("knobs-frame-pool", pool,
                       command="python scripts/bench_knobs.py --only frame-pool")
    else:
        print(body)


if __name__ == "__main__":
    main()
