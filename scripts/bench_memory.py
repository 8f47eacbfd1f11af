"""Memory per pixel: peak resident memory of each renderer pass (issue 23).

Every row runs in a fresh subprocess: import torch and torchraster, load Spot, build the
cameras and lights, then read the resident set (``VmRSS``) as the baseline, reset the
process's high-water mark (``/proc/self/clear_refs``, 5) and run the measured call twice
(the second call sees what the first left behind: the frame pool, malloc's free lists).
One-time costs (the texture's mip pyramid, lookup tables, lazy imports) are paid by a
32² x 1 warm-up call before the baseline, so the rows give what a frame costs.
malloc's free memory is returned to the OS (``malloc_trim``) before the baseline. Peak =
``VmHWM - baseline``, divided by the pixels of the batch (B * H * W) and by the
covered pixels. The scene is the frame of issue 23: Spot (5856 faces, its 1024² base-colour
texture), 8 orbit views at distance 2.2 (fov 45°, elevation 15°, ~44 % of the pixels
covered), one point light (2, 2, 3), PBR, no shadows unless the row says so.

Rows (``KINDS``): ``rasterize`` (rasterize + interpolate normals), ``gbuffer`` (rasterize +
the pbr geometry pass), ``shade N`` (the lighting pass alone over a G-buffer computed before
the baseline), ``forward N`` (``Renderer`` under no_grad, N point lights), ``shadows S``
(forward, the light casting a cube map of S² texels a face), ``post`` (forward + bloom +
tone map), ``fwd+bwd`` (forward and backward of a loss on the image with gradients to
the vertex positions and the light intensity), ``shadows+bwd S`` (that forward and backward
with the light casting a cube map of S² texels a face).

The per-pass profile of the 512² x 8 pbr frame (forward, forward + backward, and forward
with the light casting a 1024² cube map; ``--no-breakdown`` skips it): each function
``Renderer.forward`` calls is wrapped, and for each call the table gives the resident memory
before it (above the baseline), its peak above that, what it leaves resident, and the bytes
autograd saves for backward inside it (``torch.autograd.graph.saved_tensors_hooks``,
distinct storages).

    python scripts/bench_memory.py --label before          # the grid + breakdown (~6 min)
    python scripts/bench_memory.py --label after           # the same, "after" in the doc
    python scripts/bench_memory.py --rows "forward 1 512 8" --no-doc
    python scripts/bench_memory.py --label after --merge --no-breakdown \
        --rows "shadows 1024 512 8" "shadows 2048 512 8" "shadows 4096 512 1" \
        --source "what changed"          # re-measure rows, keep the label's others

Results are kept per label in ``docs/bench_memory.json`` so the section shows both.
The machine is shared (2 cores): the measurement is memory, which other processes do not
change, but each row is a separate process, so rows are independent of each other.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import dataclasses
import functools
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "bench_memory.json"
KINDS = ("rasterize", "gbuffer", "shade", "forward", "shadows", "post", "fwd+bwd",
         "shadows+bwd")
#: (kind, parameter, resolution, batch) of the default run.
GRID = (
    [(k, 1, r, b) for k in ("rasterize", "forward", "fwd+bwd")
     for r in (256, 512, 1024) for b in (1, 8)]
    + [("gbuffer", 1, 512, 8)]
    + [("shade", n, 512, 8) for n in (1, 4, 16)]
    + [("forward", n, 512, 8) for n in (4, 16)]
    + [("fwd+bwd", n, 512, 8) for n in (4, 16)]
    + [("shadows", s, 512, 8) for s in (1024, 2048)]
    + [("shadows", 4096, 512, 1)]
    + [("post", 1, 512, 8)]
)


def _status(key: str) -> int:
    """A ``/proc/self/status`` field in bytes (VmRSS, VmHWM)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    raise KeyError(key)


def _reset_peak() -> None:
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def _trim() -> None:
    """Return malloc's free memory to the OS (glibc), so that buffers freed by the set-up
    are not reused by the measured call (which would hide part of its peak)."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


@functools.lru_cache(maxsize=1)
def _spot():
    """Spot, loaded once (its texture tensor, hence the renderer's texture cache entry, is
    shared by the warm-up and the measured call)."""
    import torchraster as tr

    return tr.load_spot()


def _scene(res: int, batch: int, lights: int, shadow: int = 0):
    """Spot, B orbit cameras, ``lights`` point lights (the first at (2, 2, 3))."""
    import torch

    import torchraster as tr
    from torchraster.shading.shadows import ShadowSettings

    mesh = _spot()
    scene = tr.RenderScene.from_mesh(mesh)
    view = tr.camera.orbit(torch.arange(batch) * (360.0 / 8), 15.0, 2.2)
    proj = tr.camera.perspective(45.0, 1.0, 0.1)
    ang = torch.arange(lights) * (2 * math.pi / max(lights, 1))
    pos = torch.stack([2.0 * torch.cos(ang) + 0.0 * ang, 2.0 + 0 * ang,
                       3.0 * torch.cos(ang) + 2.0 * torch.sin(ang)], -1)
    pos[0] = torch.tensor([2.0, 2.0, 3.0])
    point = tr.PointLights(position=pos[None], color=torch.ones(1, lights, 3),
                           intensity=torch.full((1, lights), 20.0 / lights),
                           cast_shadows=torch.full((1, lights), bool(shadow)),
                           shadow=ShadowSettings(map_size=shadow) if shadow else None)
    return mesh, scene, view, proj, tr.Lights(point=point)


def worker(spec: dict) -> dict:
    """Measure one row in this (fresh) process."""
    import torch

    import torchraster as tr
    from torchraster import frame_pool
    from torchraster.gbuffer import geometry_pass
    from torchraster.post import Bloom, PostChain, ToneMap

    kind, n = spec["kind"], spec["n"]
    torch.set_num_threads(spec.get("threads", 1))
    caches: dict = {}

    def make(res: int, b: int):
        """The measured call at (res, b), its set-up done (G-buffer of ``shade``)."""
        mesh, scene, view, proj, lights = _scene(res, b, n if kind in ("shade", "forward",
                                                                       "fwd+bwd") else 1,
                                                 shadow=n if kind.startswith("shadows") else 0)
        renderer = tr.Renderer((res, res), shading="pbr", **spec.get("renderer", {}))
        if caches:  # the warm-up's texture pyramids and shadow maps
            renderer.mip_cache, renderer.shadow_cache = caches["mip"], caches["shadow"]
        caches.update(mip=renderer.mip_cache, shadow=renderer.shadow_cache)
        clip = tr.camera.transform_points(mesh.positions, proj @ view)
        channels = {"position", "normal", "albedo", "metallic", "roughness", "ao", "emissive",
                    "mask"}
        gb = None
        if kind == "shade":
            with torch.no_grad():
                frags = tr.rasterize(clip, mesh.faces, (res, res), derivatives=True)
                gb = geometry_pass(frags, channels, positions=scene.positions, view=view,
                                   normals=scene.normals, uvs=scene.uvs,
                                   materials=scene.materials)
                del frags
        grad = kind in ("fwd+bwd", "shadows+bwd")
        positions = scene.positions.clone().requires_grad_(grad)
        intensity = lights.point.intensity.clone().requires_grad_(grad)
        post = PostChain(bloom=Bloom(), tonemap=ToneMap()) if kind == "post" else None

        def call():
            if kind == "rasterize":
                with torch.no_grad():
                    frags = tr.rasterize(clip, mesh.faces, (res, res))
                    return tr.interpolate(mesh.normals, frags, mesh.faces)
            if kind == "gbuffer":
                with torch.no_grad():
                    frags = tr.rasterize(clip, mesh.faces, (res, res), derivatives=True)
                    return geometry_pass(frags, channels, positions=scene.positions, view=view,
                                         normals=scene.normals, uvs=scene.uvs,
                                         materials=scene.materials)
            if kind == "shade":
                with torch.no_grad():
                    eye = tr.renderer.camera_position(view)
                    return tr.shade(gb, camera_position=eye, lights=lights)
            lit = tr.Lights(point=tr.PointLights(
                position=lights.point.position, color=lights.point.color, intensity=intensity,
                cast_shadows=lights.point.cast_shadows, shadow=lights.point.shadow))
            sc = dataclasses.replace(scene, positions=positions) if grad else scene
            ctx = contextlib.nullcontext() if grad else torch.no_grad()
            with ctx:
                out = renderer(sc, view, proj, lit)
                image = out.image
                if post is not None:
                    image = post(image)
                if grad:
                    image.square().mean().backward()
                    positions.grad = intensity.grad = None
                return out.alpha.mean().item()

        return call, clip, mesh

    # warm-up at 32² x 1: one-time costs (texture pyramids, lookup tables, lazy imports)
    # are built before the baseline, so the rows measure what a frame costs
    make(32, 1)[0]()
    res, b = spec["res"], spec["batch"]
    call, clip, mesh = make(res, b)
    _trim()
    base = _status("VmRSS")
    _reset_peak()
    t0 = time.perf_counter()
    for _ in range(spec.get("calls", 2)):
        result = call()
        del result
    seconds = (time.perf_counter() - t0) / spec.get("calls", 2)
    peak = _status("VmHWM") - base
    after = _status("VmRSS") - base
    with torch.no_grad():  # after the measurement: its buffers must not be reused by it
        covered = int((tr.rasterize(clip, mesh.faces, (res, res)).face_id >= 0).sum())
    return {**spec, "pixels": b * res * res, "covered": covered, "peak": peak,
            "after": after, "pooled": frame_pool.pooled_bytes(),
            "seconds": seconds}


# ----------------------------------------------------------------------------- breakdown

def breakdown(spec: dict) -> dict:
    """Per-pass memory of one forward (+ backward) of the 512² x 8 frame, in this process."""
    import torch

    import torchraster as tr
    import torchraster.renderer as rmod
    from torchraster import frame_pool

    res, b, backward = spec["res"], spec["batch"], spec["backward"]
    torch.set_num_threads(spec.get("threads", 1))
    mesh, scene, view, proj, lights = _scene(res, b, 1, shadow=spec.get("shadow", 0))
    renderer = tr.Renderer((res, res), shading="pbr")
    positions = scene.positions.clone().requires_grad_(backward)
    sc = dataclasses.replace(scene, positions=positions)
    small = tr.Renderer(32, shading="pbr")  # warm-up: texture pyramids, tables, imports
    small.mip_cache, small.shadow_cache = renderer.mip_cache, renderer.shadow_cache
    with contextlib.nullcontext() if backward else torch.no_grad():
        small(sc, view[:1], proj, lights).image.sum()
    rows: list[dict] = []
    stack: list[dict] = []
    seen: set[int] = set()

    def bump(hwm: int) -> None:
        for frame in stack:
            frame["peak"] = max(frame["peak"], hwm)

    @contextlib.contextmanager
    def measure(name: str):
        bump(_status("VmHWM"))
        before = _status("VmRSS")
        _reset_peak()
        frame = {"name": "  " * len(stack) + name, "before": before, "peak": before,
                 "saved": 0}
        stack.append(frame)
        rows.append(frame)
        try:
            yield
        finally:
            bump(_status("VmHWM"))
            stack.pop()
            frame["after"] = _status("VmRSS")

    def pack(t):
        st = t.untyped_storage()
        key = st.data_ptr()
        if stack and key not in seen and st.nbytes() > 0:
            seen.add(key)
            stack[-1]["saved"] += st.nbytes()
        return t

    def wrap(owner, attr, name):
        fn = getattr(owner, attr)

        def wrapped(*args, **kwargs):
            with measure(name):
                return fn(*args, **kwargs)

        setattr(owner, attr, wrapped)

    for attr, name in (("rasterize", "rasterize"), ("geometry_pass", "G-buffer"),
                       ("vertex_normals", "vertex normals"), ("shade", "lighting (shade)"),
                       ("antialias", "antialias"), ("transform_points", "transform")):
        wrap(rmod, attr, name)
    wrap(rmod.Renderer, "_shadow_maps", "shadow maps")
    wrap(rmod.Renderer, "_shadow_hook", "shadow lookup")
    wrap(rmod.Renderer, "_shade", "shade step (+ IBL, SSAO)")
    _trim()
    base = _status("VmRSS")
    _reset_peak()
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        with contextlib.nullcontext() if backward else torch.no_grad():
            with measure("forward (total)"):
                out = renderer(sc, view, proj, lights)
                loss = out.image.square().mean()
    if backward:
        with measure("backward"):
            loss.backward()
    del out, loss
    result = []
    for r in rows:
        result.append({"name": r["name"], "before": r["before"] - base,
                       "peak": r["peak"] - r["before"], "left": r["after"] - r["before"],
                       "saved": r["saved"]})
    return {**spec, "pixels": b * res * res, "rows": result,
            "pooled": frame_pool.pooled_bytes()}


# ----------------------------------------------------------------------------- driver

def _run(spec: dict, fn: str) -> dict:
    cmd = [sys.executable, __file__, "--worker", fn, json.dumps(spec)]
    src = spec.get("src") or str(ROOT)
    env = {**os.environ, "PYTHONPATH": src + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
    if proc.returncode != 0:
        return {**spec, "error": proc.stderr.strip().splitlines()[-1][:200]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _label(r: dict) -> str:
    kind, n = r["kind"], r["n"]
    if kind in ("shade", "forward", "fwd+bwd"):
        return f"{kind}, {n} light{'s' * (n > 1)}"
    if kind == "shadows+bwd":
        return f"fwd+bwd, cube map {n}²"
    if kind == "shadows":
        return f"forward, cube map {n}²" + (" †" if r.get("source") else "")
    return {"post": "forward + bloom + tone map"}.get(kind, kind)


def _grid_table(rows: list[dict]) -> str:
    from benchmd import markdown_table

    out = []
    for r in rows:
        if "error" in r:
            out.append([_label(r), f"{r['res']}²", r["batch"], "error", r["error"], "", ""])
            continue
        out.append([_label(r), f"{r['res']}²", r["batch"], f"{r['peak'] / 2**20:.0f}",
                    f"{r['peak'] / r['pixels']:.0f}", f"{r['peak'] / max(r['covered'], 1):.0f}",
                    f"{r['seconds']:.2f}"])
    return markdown_table(["row", "frame", "batch", "peak MB", "B/px", "B/covered px",
                           "s/call"], out)


def _breakdown_table(bd: dict) -> str:
    from benchmd import markdown_table

    px = bd["pixels"]
    out = [[r["name"].replace("  ", "&nbsp;&nbsp;"), f"{r['before'] / px:.0f}",
            f"{r['peak'] / px:.0f}", f"{r['left'] / px:.0f}", f"{r['saved'] / px:.0f}"]
           for r in bd["rows"]]
    return markdown_table(["pass (in call order)", "resident before (B/px)",
                           "peak above that (B/px)", "left resident (B/px)",
                           "saved for backward (B/px)"], out)


def write_doc(results: dict) -> None:
    sys.path.insert(0, str(Path(__file__).parent))
    from benchmd import update_section

    parts = ["## Memory per pixel (issue 23)", "",
             "Peak resident memory (`VmHWM`) above the process after imports and scene load, "
             "each row in a fresh process, two calls after a 32² x 1 warm-up (which builds "
             "the texture pyramid and tables first); the second call sees what the first "
             "left (the frame pool, malloc's free lists); B/px divides by B * H * W, B/covered px "
             "by the covered pixels (~44 % here). Frame: Spot (5856 faces, 1024² base-colour "
             "texture), orbit views at distance 2.2, fov 45°, one point light, PBR, no "
             "shadows unless stated; `fwd+bwd` takes gradients to the vertex positions and "
             "the light intensity. Goals of the issue: pbr forward <= 120 B/px and forward + "
             "backward <= 250 B/px at 512² x 8, flat in the number of lights. Memory does "
             "not depend on the load of the machine (shared, 2 cores); s/call does (noisy). "
             "The default run (grid + per-pass profiles) took 8 minutes on that machine."]
    for label in ("before", "after"):
        res = results.get(label)
        if not res:
            continue
        parts += ["", f"### {label}", "", res.get("source", ""), "", _grid_table(res["grid"])]
        later = list(dict.fromkeys(r["source"] for r in res["grid"] if r.get("source")))
        if later:
            parts += ["", "† measured later (`--merge`): " + "; ".join(later)]
        for bd in res.get("breakdown", []):
            what = "forward + backward" if bd["backward"] else "forward (no_grad)"
            shadow = f", the light casting a {bd['shadow']}² cube map" if bd.get("shadow") else ""
            parts += ["", f"Per pass, {what}, {bd['res']}² x {bd['batch']}{shadow} "
                      f"(frame pool holds {bd['pooled'] / 2**20:.0f} MB after):", "",
                      _breakdown_table(bd)]
    if results.get("notes"):
        parts += ["", results["notes"]]
    update_section("memory", "\n".join(parts), command="python scripts/bench_memory.py "
                   "--label before|after")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worker", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--label", choices=("before", "after"), default="after")
    ap.add_argument("--source", default="", help="what code ran (shown in the doc)")
    ap.add_argument("--rows", nargs="*", help='rows "kind n res batch", e.g. "forward 1 512 8"')
    ap.add_argument("--src", default="",
                    help="directory holding the torchraster package to measure (default: "
                         "this checkout), e.g. a copy of the code before a change")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-breakdown", action="store_true")
    ap.add_argument("--no-doc", action="store_true")
    ap.add_argument("--merge", action="store_true",
                    help="replace only the measured rows in the label's stored grid (and "
                         "the breakdowns only if measured); --source is kept per row")
    args = ap.parse_args()
    if args.worker:
        fn, spec = args.worker
        print(json.dumps((worker if fn == "worker" else breakdown)(json.loads(spec))))
        return
    grid = GRID if not args.rows else [
        (r.split()[0], int(r.split()[1]), int(r.split()[2]), int(r.split()[3]))
        for r in args.rows]
    t0 = time.time()
    rows = []
    for kind, n, res, b in grid:
        r = _run({"kind": kind, "n": n, "res": res, "batch": b, "src": args.src,
                  "threads": args.threads}, "worker")
        rows.append(r)
        if "error" in r:
            print(f"{kind} {n} {res} {b}: ERROR {r['error']}", flush=True)
        else:
            print(f"{_label(r):32s} {res:5d}² x{b}: {r['peak'] / 2**20:7.0f} MB "
                  f"{r['peak'] / r['pixels']:6.0f} B/px {r['peak'] / r['covered']:6.0f} "
                  f"B/covered  {r['seconds']:.2f} s  (pool {r['pooled'] / 2**20:.0f} MB)",
                  flush=True)
    bds = []
    if not args.no_breakdown:
        for backward, shadow in ((False, 0), (True, 0), (False, 1024)):
            bd = _run({"res": 512, "batch": 8, "backward": backward, "shadow": shadow,
                       "src": args.src, "threads": args.threads},
                      "breakdown")
            bds.append(bd)
            if "error" in bd:
                print("breakdown ERROR", bd["error"])
                continue
            print(f"breakdown backward={backward}")
            for r in bd["rows"]:
                px = bd["pixels"]
                print(f"  {r['name']:34s} before {r['before'] / px:6.0f} peak "
                      f"{r['peak'] / px:6.0f} left {r['left'] / px:6.0f} saved "
                      f"{r['saved'] / px:6.0f} B/px", flush=True)
    print(f"{time.time() - t0:.0f} s")
    if args.no_doc:
        return
    results = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    if args.merge and args.label in results:
        old = results[args.label]

        def key(r: dict) -> tuple:
            return r["kind"], r["n"], r["res"], r["batch"]

        fresh = {key(r): {**r, "source": args.source} for r in rows}
        grid = [fresh.pop(key(r), r) for r in old["grid"]] + list(fresh.values())
        results[args.label] = {**old, "grid": grid, "breakdown": [
            b for b in bds if "error" not in b] or old.get("breakdown", [])}
    else:
        results[args.label] = {"source": args.source, "grid": rows,
                               "breakdown": [b for b in bds if "error" not in b]}
    RESULTS.write_text(json.dumps(results, indent=1) + "\n")
    write_doc(results)


if __name__ == "__main__":
    main()
