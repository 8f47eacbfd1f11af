"""Screen-space reflections: error against march steps and resolution, and time per frame.

Scene: a textured quad standing above a mirror floor (metallic 1, roughness 0), unlit, so
the reflected radiance is view-independent. Reference: the quad rendered with the camera
mirrored through the floor plane (what a perfect mirror shows). Error: mean over the floor
pixels the reference covers of max_c |SSR reflection - reference| (a miss counts as its
whole reference colour, so lost hits and wrong colours both count); "hit" is the fraction
of those pixels SSR reports a hit for (they are at most 1 px off at silhouettes and miss
where the reflected rays leave the frame). Time: the SSR module alone (median), and as a
fraction of the G-buffer render; "steps run" is the march iterations actually run and
"ray-steps" the march's work (rays stepped, summed over the iterations).

    python scripts/bench_ssr.py            # table -> docs/benchmarks.md, section ssr
    python scripts/bench_ssr.py --baseline HEAD   # also time the committed ssr.py
    python scripts/bench_ssr.py --picture  # docs/images/ssr_floor.png
"""

from __future__ import annotations

import argparse
import inspect
import os
import statistics
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmd import markdown_table, update_section  # noqa: E402

import torchraster as tr  # noqa: E402
from torchraster.camera import look_at, perspective  # noqa: E402
from torchraster.post import SSR, EncodeSRGB, ToneMap  # noqa: E402
from torchraster.post import ssr as ssr_module  # noqa: E402
from torchraster.post.ssao import camera_intrinsics  # noqa: E402
from torchraster.shading.surface import Surface  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
CHANNELS = ["depth", "normal", "roughness", "metallic", "albedo", "mask"]


def quad_scene(mirror_view: bool = False):
    """Textured quad above a mirror floor (or, mirrored, the quad alone) and its camera."""
    uu, vv = torch.meshgrid(torch.linspace(0, 1, 64), torch.linspace(0, 1, 64), indexing="xy")
    tex = torch.stack([0.5 + 0.5 * torch.sin(19 * uu), 0.5 + 0.5 * torch.cos(13 * vv),
                       0.2 + 0.6 * (((uu * 8).floor() + (vv * 8).floor()) % 2)])
    quad = torch.tensor([[-0.9, 0.15, 0.0], [0.9, 0.15, 0.0], [0.9, 1.2, 0.0], [-0.9, 1.2, 0.0]])
    floor = torch.tensor([[-8.0, 0, -8], [-8, 0, 8], [8, 0, 8], [8, 0, -8]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    uvs = torch.tensor([[0.0, 0], [1, 0], [1, 1], [0, 1]] + [[0.0, 0]] * 4)
    normals = torch.tensor([[0.0, 0, 1]] * 4 + [[0.0, 1, 0]] * 4)
    mats = [tr.Material(base_color_texture=tex, roughness_factor=0.9),
            tr.Material(metallic_factor=1.0, roughness_factor=0.0)]
    positions, fm = torch.cat([quad, floor]), torch.tensor([0, 0, 1, 1])
    view = look_at([0.3, 0.9, 3.0], [0.0, 0.35, 0.0])
    if mirror_view:  # reflect the world through y = 0 before the camera; flip the winding
        positions, faces, uvs, normals = quad, faces[:2, [0, 2, 1]], uvs[:4], normals[:4]
        mats, fm = mats[:1], fm[:2]
        view = view @ torch.diag(torch.tensor([1.0, -1.0, 1.0, 1.0]))
    scene = tr.RenderScene(positions=positions, faces=faces, uvs=uvs, normals=normals,
                           materials=mats, face_material=fm)
    return scene, view, perspective(50.0, 1.0, 0.1, 50.0)


def baseline_module(rev: str):
    """``torchraster/post/ssr.py`` as it was at git revision ``rev``, imported as a module of
    the current package (its relative imports resolve to today's code)."""
    src = subprocess.run(["git", "show", f"{rev}:torchraster/post/ssr.py"], cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout
    mod = types.ModuleType("torchraster.post._ssr_baseline")
    mod.__package__ = "torchraster.post"
    exec(compile(src, f"{rev}:torchraster/post/ssr.py", "exec"), mod.__dict__)  # noqa: S102
    return mod


def measure(res: int, steps_list: list[int], repeats: int, baseline=None):  # noqa: ANN001
    """Rows: error, hit rate, march steps run, and median times of the G-buffer render,
    the baseline SSR (if any) and today's SSR, interleaved in one loop (same load). The
    G-buffer render does not depend on max_steps: its median is over all the rounds of
    the resolution (a steadier denominator on a shared machine)."""
    scene, view, proj = quad_scene()
    renderer = tr.Renderer(res, shading="unlit")
    out = renderer(scene, view, proj, channels=CHANNELS)
    g = out.gbuffer
    n_view = torch.einsum("ij,bjhw->bihw", view[0, :3, :3], g["normal"])
    ref_scene, ref_view, _ = quad_scene(mirror_view=True)
    ref = renderer(ref_scene, ref_view, proj)
    seen = (ref.alpha[0, 0] > 0) & (g["roughness"][0, 0] == 0)
    k = camera_intrinsics(proj, None, (1, res, res))
    rows, gbuffer_times = [], []
    for steps in steps_list:
        mods = {"after": ssr_module} | ({"before": baseline} if baseline else {})
        ssrs = {name: m.SSR(max_steps=steps, edge_fade=0.0) for name, m in mods.items()}

        def run(name: str, ssrs=ssrs):  # noqa: ANN001, ANN202
            module = ssrs[name]
            if "surface" in inspect.signature(module.forward).parameters:
                material = (Surface(albedo=g["albedo"], metallic=g["metallic"],
                                    roughness=g["roughness"]),)
            else:  # a revision before SSR took the surface by name
                material = (g["roughness"], g["metallic"], g["albedo"])
            return module(out.image, g["depth"], n_view, *material, projection=proj,
                          return_maps=True)

        jobs = {"gbuffer": lambda: renderer(scene, view, proj, channels=CHANNELS)}
        jobs |= {name: (lambda name=name: run(name)) for name in mods}
        times: dict[str, list[float]] = {name: [] for name in jobs}
        for rep in range(repeats + 1):  # the first round warms up
            for name, fn in jobs.items():
                t = time.perf_counter()
                fn()
                if rep:
                    times[name].append(time.perf_counter() - t)
        gbuffer_times += times.pop("gbuffer")
        t = {name: statistics.median(v) for name, v in times.items()}
        maps = run("after")
        same = "-"
        if baseline:  # share of pixels whose SSRMaps differ by more than 1e-4
            diff = torch.zeros_like(maps.confidence[:, 0], dtype=torch.bool)
            for a, b in zip(maps, run("before"), strict=True):
                diff |= (a - b).abs().amax(1) > 1e-4
            same = f"{100 * float(diff.float().mean()):.2f} %"
        stats: dict = {}
        ssr_module.trace_reflections(out.image, g["depth"], n_view, g["roughness"], k,
                                     max_steps=steps, stats=stats)
        refl = torch.where(maps.confidence > 0, maps.reflection, torch.zeros_like(
            maps.reflection))
        err = (refl[0] - ref.image[0]).abs().amax(0)[seen]
        hit = float((maps.confidence[0, 0] > 0)[seen].float().mean())
        rows.append((steps, float(err.mean()), f"{100 * hit:.1f} %", stats["steps"],
                     stats.get("ray_steps", "-"), t, same))
        print(res, rows[-1], flush=True)
    gb = statistics.median(gbuffer_times)
    table = []
    for steps, err, hit, run_steps, ray_steps, t, same in rows:
        row = [f"{res}x{res}", steps, err, hit, run_steps, ray_steps, gb * 1000]
        if baseline:
            row += [t["before"] * 1000, f"{t['before'] / gb:.2f}x"]
        row += [t["after"] * 1000, f"{t['after'] / gb:.2f}x", same]
        table.append(row)
    return table


def picture(path: Path) -> None:
    """The spot cow on a glossy metal floor under the venice sky, without / with SSR."""
    spot = tr.load_spot()
    rot = torch.tensor([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])  # side on to the camera
    p = spot.positions @ rot.T * 0.8 + torch.tensor([0.0, 0.59, 0.0])
    s = 30.0
    fp = torch.tensor([[-s, 0, -s], [-s, 0, s], [s, 0, s], [s, 0, -s]])
    scene = tr.RenderScene(
        positions=torch.cat([p, fp]),
        faces=torch.cat([spot.faces, torch.tensor([[0, 1, 2], [0, 2, 3]]) + p.shape[0]]),
        normals=torch.cat([spot.normals @ rot.T, torch.tensor([[0.0, 1, 0]]).expand(4, 3)]),
        uvs=torch.cat([spot.uvs, torch.zeros(4, 2)]),
        face_material=torch.cat([torch.zeros(spot.faces.shape[0], dtype=torch.int64),
                                 torch.ones(2, dtype=torch.int64)]),
        materials=[spot.material, tr.Material(base_color_factor=[0.35, 0.33, 0.3, 1.0],
                                              metallic_factor=1.0, roughness_factor=0.12)])
    env = tr.Environment(tr.read_hdr(ROOT / "torchraster/assets/envmaps/venice_sunset_256.hdr"),
                         yaw=2.0)
    lights = tr.Lights(directional=tr.DirectionalLights(
        direction=torch.tensor([[[-0.5, -1.0, -0.4]]]), color=torch.ones(1, 1, 3),
        intensity=torch.tensor([[3.0]])))
    view = look_at([0.2, 0.75, 3.3], [0.0, 0.42, 0.0])
    proj = perspective(40.0, 1.0, 0.1, 100.0)
    images = []
    for ssr in (None, SSR()):
        renderer = tr.Renderer(256, ssr=ssr, raster=tr.RasterSettings(supersample=2))
        images.append(renderer(scene, view, proj, lights=lights, environment=env).image)
    img = EncodeSRGB()(ToneMap()(torch.cat(images, 3)))[0]
    from skimage import io as skio

    path.parent.mkdir(parents=True, exist_ok=True)
    skio.imsave(path, (img.clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8))
    print(f"wrote {path} ({path.stat().st_size // 1024} KB)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--picture", action="store_true", help="write docs/images/ssr_floor.png")
    ap.add_argument("--quick", action="store_true", help="small sizes, no docs update")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--steps", type=int, nargs="+", default=[16, 32, 64, 4096],
                    help="max_steps values")
    ap.add_argument("--baseline", metavar="REV",
                    help="also time torchraster/post/ssr.py of this git revision (e.g. HEAD)")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads (1: steadier times on a shared machine)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.picture:
        picture(ROOT / "docs" / "images" / "ssr_floor.png")
        return
    t0 = time.perf_counter()
    baseline = baseline_module(args.baseline) if args.baseline else None
    sizes = [64, 128] if args.quick else [128, 256, 512]
    rows = [r for res in sizes for r in measure(res, args.steps, args.repeats, baseline)]
    head = ["resolution", "max_steps", "mean error", "hit", "steps run", "ray-steps",
            "G-buffer ms"]
    if baseline:
        head += [f"SSR ms ({args.baseline})", f"/ G-buffer ({args.baseline})"]
    head += ["SSR ms", "SSR / G-buffer", f"maps differ ({args.baseline})" if baseline
             else "maps differ"]
    table = markdown_table(head, rows)
    print(table)
    if args.quick:
        return
    before = (f" Columns marked `{args.baseline}` time the SSR module as it was at that "
              "git revision (loaded by the script, timed in the same loop; \"maps "
              "differ\": share of the pixels where its SSRMaps and today's differ by more "
              "than 1e-4)." if baseline else "")
    body = (f"## Screen-space reflections: error against march steps and resolution "
            f"({time.perf_counter() - t0:.0f} s)\n\n"
            "A textured quad above a mirror floor; reference: the quad rendered with the "
            "camera mirrored through the floor (`scripts/bench_ssr.py` docstring). Mean "
            "error: max-channel |reflection - reference| over the floor pixels the "
            "reference covers, a miss counting as the whole reference colour (texture "
            "values in [0, 1]). The rest of the error is the 1-pixel silhouette band and "
            "reflections leaving the frame, which SSR cannot know. \"steps run\": march "
            "iterations actually run (the march ends when every ray has hit or missed; "
            "`max_steps` is only a cap), \"ray-steps\" the rays stepped summed over them "
            "(the march's work). Times: medians of the unlit G-buffer render (over all the "
            "rounds of a resolution) and of the SSR module on that G-buffer, interleaved "
            "in one loop." + before +
            " Load average during the run: "
            f"{os.getloadavg()[0]:.1f} (times on a loaded machine are noisy; the error "
            "columns are deterministic).\n\n" + table)
    update_section("ssr", body)


if __name__ == "__main__":
    main()
