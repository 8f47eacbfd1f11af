"""Dataset rendering speed: frames per second of configs/dataset_movi.yaml and the cost of
each label channel relative to the colour frame, with peak memory.

Three measurements, written to the section "dataset" of docs/benchmarks.md:

1. *Label cost* (in-process, no files): one randomised scene of the config rendered with
   ``outputs.channels: [color]`` and with ``[color, <label>]`` for each label channel, the
   variants timed in turns over the same frames (medians of the per-turn ratios): what a
   label adds to the frame.
2. *Labelled frame* (in-process, no files): the config's own channels, every frame of one
   scene, frames per second.
3. *Whole run* (``torchraster render`` in fresh processes, files, manifest and exports
   included): 1 process, and 2 ranks under ``torchrun``, frames per second of rendering
   (the run summary's ``render_seconds``) and peak RSS per process.

    python scripts/bench_dataset.py [--frames 12] [--turns 3] [--skip-runs]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from benchmd import markdown_table, update_section

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "configs" / "dataset_movi.yaml"
LABELS = ["depth", "normal", "instance", "semantic", "object_coords", "distance", "amodal",
          "flow_forward", "flow_backward", "motion"]


def _renderer(cfg, channels: list[str]):
    """The view renderer of the config's first scene with only ``channels`` written."""
    from torchraster import pipeline

    cfg = cfg.model_copy(update={"outputs": cfg.outputs.model_copy(update={
        "channels": channels, "exports": []})})
    plan = pipeline.plan_objects(cfg)[0]
    return pipeline.view_renderer(plan.config), plan.views


def label_costs(cfg, frames: int, turns: int) -> list[list[str]]:
    """Per label: median over turns of (time with the label) / (colour alone) - 1."""
    base, views = _renderer(cfg, ["color"])
    views = views[:frames]
    variants = {label: _renderer(cfg, ["color", label])[0] for label in LABELS}

    def run(render) -> float:
        t0 = time.perf_counter()
        for v in views:
            render(v.camera_config, v.folder, v.frame)
        return (time.perf_counter() - t0) / len(views)

    run(base)  # warm up: caches, first-call costs
    for r in variants.values():
        run(r)
    ratios: dict[str, list[float]] = {k: [] for k in LABELS}
    base_times = []
    for _ in range(turns):
        for label, render in variants.items():
            b = run(base)
            base_times.append(b)
            ratios[label].append(run(render) / b - 1)
    rows = [["color alone", f"{statistics.median(base_times) * 1e3:.0f} ms", "-"]]
    for label in LABELS:
        q = sorted(ratios[label])
        rows.append([label, "", f"{statistics.median(q) * 100:+.0f} % "
                                f"({q[0] * 100:+.0f} .. {q[-1] * 100:+.0f})"])
    return rows


def shadow_map_sizes(cfg, frames: int) -> list[list[str]]:
    """The sun's shadow-map size as a knob: the colour frame's time against its error
    (PSNR of the display image over every other frame of the first ``2 frames``, against
    the same frames with a 4096² map)."""

    results = {}
    for size in (4096, 2048, 1024, 768, 512, 384, 256):
        rz = cfg.randomize
        lights = rz.lights.model_copy(update={"shadows": rz.lights.shadows.model_copy(
            update={"map_size": size})})
        c = cfg.model_copy(update={"randomize": rz.model_copy(update={"lights": lights})})
        render, views = _renderer(c, ["color"])
        views = views[:2 * frames:2]
        render(views[0].camera_config, views[0].folder, views[0].frame)  # warm up
        t0 = time.perf_counter()
        images = [render(v.camera_config, v.folder, v.frame).images["color"] for v in views]
        results[size] = (torch.stack(images), (time.perf_counter() - t0) / len(views))
    ref, t_ref = results[4096]
    rows = []
    for size, (img, t) in results.items():
        mse = float(((img - ref) ** 2).mean())
        psnr = "reference" if size == 4096 else f"{10 * math.log10(1 / mse):.1f}"
        rows.append([f"{size}²", f"{t * 1e3:.0f} ms", f"{t / results[512][1]:.2f}", psnr])
    return rows


def png_levels(cfg, repeats: int = 5) -> list[list[str]]:
    """``outputs.png_compression`` as a knob: the time to write one labelled view's files
    (the config's channels, png + npy, previews) and the bytes of its PNGs, per zlib level
    (lossless at every level: the same pixels; medians of ``repeats`` writes)."""
    from torchraster import pipeline

    render, views = _renderer(cfg, list(cfg.outputs.channels))
    result = render(views[3].camera_config, views[3].folder, views[3].frame)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for level in (0, 1, 3, 6, 9):
            times, size = [], 0
            for r in range(repeats + 1):  # the first write warms the file system up
                t0 = time.perf_counter()
                files = pipeline.write_outputs(result, Path(tmp) / f"{level}-{r}",
                                               cfg.outputs.formats, cfg.outputs.previews, level)
                times.append(time.perf_counter() - t0)
                size = sum(f.stat().st_size for f in files if f.suffix == ".png")
            t = statistics.median(times[1:])
            rows.append([str(level), f"{t * 1e3:.0f} ms", f"{size / 1024:.0f} KiB"])
    return rows


def labelled_frame(cfg, frames: int, threads: list[int], turns: int = 3
                   ) -> dict[int, float]:
    """Seconds per frame of the config's own channels, no files, per torch thread count:
    the counts take turns over the same frames (``turns`` each; medians)."""
    render, views = _renderer(cfg, list(cfg.outputs.channels))
    views = views[:frames]
    times: dict[int, list[float]] = {n: [] for n in threads}
    for turn in range(turns + 1):
        for n in threads:
            torch.set_num_threads(n)
            t0 = time.perf_counter()
            for v in views:
                render(v.camera_config, v.folder, v.frame)
            if turn:  # the first turn warms up
                times[n].append((time.perf_counter() - t0) / len(views))
    torch.set_num_threads(max(threads))
    return {n: statistics.median(t) for n, t in times.items()}


RUN = """
import json, resource, sys, time, torch
from pathlib import Path
import torchraster as tr
from torchraster.distributed import DatasetConfig, render_dataset
cfg = tr.load_config(sys.argv[1])
rz = cfg.randomize.model_copy(update={"scenes": int(sys.argv[3])})
cfg = cfg.model_copy(update={"randomize": rz})
s = render_dataset([DatasetConfig(Path(sys.argv[1]), "movi", cfg)], sys.argv[2], progress=False)
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
import os
if int(os.environ.get("RANK", "0")) == 0:
    views = [json.loads(line) for f in Path(sys.argv[2]).glob("**/manifest*.jsonl")
             for line in open(f)]
    timings = [v["timings"] for v in views if "timings" in v]
    print(json.dumps({"written": s.written, "render_s": s.render_seconds, "peak_mb": peak,
                      "timings": timings}))
else:
    print(json.dumps({"peak_mb": peak}), file=sys.stderr)
"""


def whole_run(ranks: int, scenes: int, src: str | None = None) -> dict:
    """``render_dataset`` of ``scenes`` scenes in fresh processes (``ranks`` under torchrun),
    of the torchraster in ``src`` (a checkout) if given."""
    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / "run.py"
        script.write_text(RUN)
        out = Path(tmp) / "out"
        # one process: torch's default threads (the batch command then leaves a core to its
        # writer thread, distributed.writer_core); ranks: the cores split between them
        env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
        env["GLOO_SOCKET_IFNAME"] = "lo"
        if src is not None:
            env["PYTHONPATH"] = src
        if ranks > 1:
            env["OMP_NUM_THREADS"] = str(max(1, (os.cpu_count() or 2) // ranks))
        if ranks == 1:
            cmd = [sys.executable, str(script)]
        else:
            cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", str(ranks),
                   "--rdzv-backend", "c10d", "--rdzv-endpoint", "127.0.0.1:0", str(script)]
        res = subprocess.run(cmd + [str(CONFIG), str(out), str(scenes)], env=env,
                             capture_output=True, text=True, check=True,
                             cwd=ROOT)
        result = json.loads(res.stdout.strip().splitlines()[-1])
        peaks = [result["peak_mb"]] + [json.loads(line)["peak_mb"] for line in
                                       res.stderr.splitlines() if line.startswith('{"peak_mb"')]
        result["peak_mb"] = max(peaks)
        return result


def spent_text(spent: dict[int, tuple[float, float, float]], in_process: float) -> str:
    """Where a whole run's view time goes (the manifest's per-view timings, this tree)."""
    if not spent:
        return ""
    rows = [[str(ranks), f"{first:.2f} s", f"{render * 1e3:.0f} ms", f"{write * 1e3:.0f} ms"]
            for ranks, (first, render, write) in sorted(spent.items())]
    return ("\n\nWhere a whole run's time goes (this tree; the manifest's per-view timings): "
            "the slowest view of a run is a process's first, which builds the environment's "
            "prefiltered specular chain and its lobe table (`specular: table`, the default "
            "since 2026-11-26; ~1.4 s and ~0.5 s for this map, once per map per process: a "
            "content cache); a steady view renders in the main thread while the previous "
            "view's files are written by the writer thread, which takes one of the two cores "
            f"(the same view in-process, 1 thread, no files: {in_process * 1e3:.0f} ms).\n\n"
            + markdown_table(["processes", "slowest view (first)", "view render (median)",
                              "view files (median, writer thread)"], rows))


def blender_text(python: str | None, frames: int, fps: float, threads: int) -> str:
    """The Blender anchor: measured now with ``python`` (a Python with ``bpy``) on the same
    kind of scene (scripts/blender_movi.py), or the figures quoted by issue 20."""
    if python is None:
        return ("Anchor (quoted from issue 20, measured on this kind of machine with Blender "
                "5.0.1 as a Python module, a MOVi-like scene of 8 objects, sun + HDR, 256², "
                "passes Combined, Depth, Normal, IndexOB, Vector, Cryptomatte): Cycles CPU "
                "0.75 / 1.58 / 5.10 s a frame at 1 / 16 / 64 samples, 0.14 s with persistent "
                "data at 1 sample (noisy); Workbench 0.029 s but colour and depth only. "
                "Blender's IndexOB is one sample at the pixel centre; its Vector pass blends "
                "over samples at edges. Not re-measured in this run (`--blender PYTHON`).\n")
    res = subprocess.run([python, str(ROOT / "scripts" / "blender_movi.py"),
                          "--frames", str(min(frames, 6))], capture_output=True, text=True,
                         check=True, cwd=ROOT)
    got = json.loads(res.stdout.strip().splitlines()[-1])
    names = {"cycles1": "Cycles CPU, 1 sample", "cycles1_persistent":
             "Cycles CPU, 1 sample, persistent data", "cycles16": "Cycles CPU, 16 samples",
             "cycles64": "Cycles CPU, 64 samples",
             "workbench": "Workbench (colour and depth only; no lighting of the HDR)"}
    rows = [[names[k], f"{got[k] * 1e3:.0f} ms", f"{1 / got[k]:.2f}", f"{got[k] * fps:.1f}x"]
            for k in names if k in got]
    print(markdown_table(["Blender " + got["bpy"], "per frame", "frames / s",
                          "Blender time / ours"], rows))
    return ("Blender, measured in this run (`scripts/blender_movi.py`: Blender "
            f"{got['bpy']} as a Python module, 2 threads; the same kind of scene: 8 objects from "
            "Spot, boxes and spheres on a floor, random Principled materials, sun + the same "
            "HDR, orbiting camera, objects moving, 256²; passes Combined, Depth, Normal, "
            "IndexOB, Vector, Cryptomatte written as multilayer EXR; median over "
            f"{min(frames, 6)} frames after a warm-up frame). *Blender time / ours* = Blender's "
            f"time a frame over our in-process labelled frame above ({threads} torch "
            f"thread{'s' * (threads > 1)}, the faster row). Blender's IndexOB is one "
            "sample at the pixel centre; its Vector pass blends over samples at edges.\n\n"
            + markdown_table(["Blender " + got["bpy"], "per frame", "frames / s",
                              "Blender time / ours"], rows) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=12, help="frames per in-process timing")
    ap.add_argument("--turns", type=int, default=3)
    ap.add_argument("--scenes", type=int, default=1, help="scenes of the whole runs")
    ap.add_argument("--skip-runs", action="store_true", help="no whole-run rows")
    ap.add_argument("--no-write", action="store_true", help="print only")
    ap.add_argument("--png-only", action="store_true",
                    help="only the PNG compression table (section dataset-png)")
    ap.add_argument("--before", metavar="SRC", help="a checkout of an earlier tree: its whole "
                    "runs alternate with this tree's (2 each, medians)")
    ap.add_argument("--blender", metavar="PYTHON", help="a Python with bpy: time Blender on "
                    "the same kind of scene in the same run (scripts/blender_movi.py)")
    args = ap.parse_args()
    import torchraster as tr

    torch.set_num_threads(os.cpu_count() or 1)
    cfg = tr.load_config(CONFIG)
    if args.png_only:
        rows = png_levels(cfg)
        table = markdown_table(["outputs.png_compression", "write a view (files)",
                                "PNG bytes a view"], rows)
        print(table)
        if not args.no_write:
            update_section("dataset-png", (
                "## Dataset: PNG compression level against write time\n\n"
                "`outputs.png_compression` (zlib level, 0-9; lossless at every level, so the "
                "trade is time against bytes, not error): one labelled view of "
                "`configs/dataset_movi.yaml` (its channels as png + npy, instance / semantic "
                "previews) written to a temporary folder, median of 5 writes after one. The "
                "npy files (~5 MB a view) do not depend on the level. Default: 1.\n\n" + table))
        return
    h, w = cfg.render.size
    costs = label_costs(cfg, args.frames, args.turns)
    cores = os.cpu_count() or 1
    frame_s = labelled_frame(cfg, args.frames, sorted({1, cores}))
    best = min(frame_s, key=frame_s.get)
    fps = 1 / frame_s[best]
    maps = shadow_map_sizes(cfg, min(args.frames, 6))
    print(markdown_table(["sun map", "colour frame", "time / 512²", "PSNR (dB)"], maps))
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(markdown_table(["channel", "colour frame", "added by the label"], costs))
    rows = [[f"in-process, labelled frame (no files), {n} torch thread{'s' * (n > 1)}", "1",
             f"{1 / sec:.2f}", f"{sec * 1e3:.0f} ms", f"{rss:.0f} MB (this process)"]
            for n, sec in frame_s.items()]
    before = ""
    spent: dict[int, tuple[float, float, float]] = {}  # ranks -> first, steady render, write
    if not args.skip_runs:
        trees = [("", None)]
        if args.before:
            commit = subprocess.run(["git", "-C", args.before, "log", "-1", "--format=%h"],
                                    capture_output=True, text=True).stdout.strip() or "?"
            trees = [(f" (before: {commit})", args.before), (" (this tree)", None)]
            before = (f"Whole runs of the tree at {commit} (before) and of this tree alternate, "
                      "two of each, medians. ")
        for ranks in (1, 2):
            found: dict[str, list[dict]] = {label: [] for label, _ in trees}
            for _ in range(2 if args.before else 1):
                for label, src in trees:
                    found[label].append(whole_run(ranks, args.scenes, src))
            for label, _ in trees:
                if label == trees[-1][0]:  # this tree: where a view's time goes
                    t = [v for r in found[label] for v in r.get("timings", [])]
                    if t:
                        spent[ranks] = (max(v["render_s"] for v in t),
                                        statistics.median(v["render_s"] for v in t),
                                        statistics.median(v["write_s"] for v in t))
                per = statistics.median(r["render_s"] / r["written"] for r in found[label])
                peak = max(r["peak_mb"] for r in found[label])
                rows.append([f"torchraster render, {args.scenes} scene(s), files + manifest + "
                             f"COCO{label}", str(ranks), f"{1 / per:.2f}",
                             f"{per * 1e3:.0f} ms", f"{peak:.0f} MB (largest rank)"])
    print(markdown_table(["how", "processes", "frames / s", "per frame", "peak RSS"], rows))
    body = (
        "## Dataset: frames per second and the cost of labels\n\n"
        f"`configs/dataset_movi.yaml` ({h}x{w}, 8 objects from Spot and primitives, floor, "
        "sun with a 512² PCF shadow map, HDR environment, pbr with energy compensation, "
        "24 frames of camera and object motion; channels colour, depth, normal, instance, "
        "semantic, object_coords, flow both ways with validity). Label cost: the first scene's "
        f"first {args.frames} frames rendered in-process without files, colour alone against "
        f"colour plus one label, in turns ({args.turns} turns; median and range of the "
        "ratios).\n\n" + markdown_table(["channel", "colour frame", "added by the label"], costs)
        + "\n\nThe sun's shadow-map size (the config's knob; colour frames, every other frame "
        "of the first 12, PSNR of the display image against a 4096² map): the config uses "
        "512²; the rows above it say what a larger map buys and what it costs.\n\n"
        + markdown_table(["sun map", "colour frame", "time / 512²", "PSNR (dB)"], maps)
        + "\n\nWhole labelled frames. In-process: the config's frames with 1 and with "
        f"{cores} torch threads in turns (3 turns after a warm-up, medians); at 256² most "
        "operations are too small to gain from a second thread, whose parallel regions cost "
        "more than they save. " + before + "Whole runs: one process uses torch's default "
        "threads (one fewer while its writer thread encodes files, `distributed.writer_core`); "
        "two ranks get one thread each. This machine's speed drifts by up to ~30 % within the "
        "hour (the same labelled frame has timed 88 ms and 116 ms on one day): compare rows "
        "within one run.\n\n"
        + markdown_table(["how", "processes", "frames / s", "per frame", "peak RSS"], rows)
        + spent_text(spent, frame_s[1]) + "\n\n" + blender_text(args.blender, args.frames, fps,
                                                                 best))
    if not args.no_write:
        command = None
        if args.blender or args.before:  # without this machine's paths
            names = {args.blender: "PYTHON", args.before: "SRC"}
            argv = [names.get(a, a) for a in sys.argv[1:]]
            command = "python " + " ".join([os.path.relpath(sys.argv[0]), *argv])
            if args.blender:
                command += " (PYTHON: a virtualenv with `pip install bpy==5.0.1`)"
            if args.before:
                command += " (SRC: a checkout of the earlier tree)"
        update_section("dataset", body, command)


if __name__ == "__main__":
    main()
