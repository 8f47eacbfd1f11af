"""Shadow maps: run time against error, measured against the ray-traced reference.

The reference is :mod:`torchraster.testing.raytrace` (float64 Möller-Trumbore from the
G-buffer positions, hard or area lights); the engine's shadow factor is the ratio of a render
with shadows to one without (``raytrace.render_shadow_factor``).

* map size 256-4096 (default filter), each light type: 1 - IoU of the shadow mask, acne and
  peter-panning rates (``raytrace.mask_stats``: band of 2 px left out);
* cascades 1-4 of a directional light over a 100 m field of spheres, low camera;
* PCF taps 1-64, PCSS, VSM blur sigmas: mean absolute error of the visibility against the
  ray-traced area light (a disc of radius 0.15 m / a 4 degree sun) and against the hard
  (point) reference;
* depth / slope / normal biases: IoU on the sphere and acne on a plane lit at 5 degrees;
* the shadow pass against the main pass for 1, 4, 16 point / spot lights, batch 1 and 4,
  over the sphere scene and a typical view (a floor with objects, lights above it, a camera
  looking down at it), with the culled views (the default) and with every view rendered.

Time of the shadow pass = median of renders with shadows minus median of renders without
(the main pass), measured interleaved in this run, ``torch.no_grad``.

    python scripts/bench_shadows.py [--quick] [--pictures-only] [--cost-only]
"""

from __future__ import annotations

import argparse
import math
import re
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from benchmd import markdown_table, update_section
from PIL import Image, ImageDraw

import torchraster as tr
from torchraster.shading import shadows
from torchraster.shading.shadows import ShadowSettings, directional_views
from torchraster.testing import raytrace as rt

IMAGES = Path(__file__).resolve().parent.parent / "docs" / "images"
KINDS = tuple(rt.LIGHTS)
#: Area lights of the soft references: disc radius (m) / sun angular diameter (degrees).
LIGHT_SIZE = {"directional": 4.0, "spot": 0.15, "point": 0.15}
MATERIAL = tr.Material(metallic_factor=0.0, roughness_factor=0.8)
# the defaults' error bounds: shadow masks within half a percent of the ray tracer's, PCF
# within 0.005 of 64 taps, soft shadows within 0.05 of the area light (shadow region)
IOU_OK, TAPS_OK, SOFT_OK = 0.995, 0.005, 0.05
DEFAULT = ShadowSettings()


def camera(eye=(0.0, 2.5, 4.0), target=(0.0, 0.3, 0.0), fov: float = 45.0):
    return tr.camera.look_at(list(eye), list(target)), tr.camera.perspective(fov, 1.0, 0.1)


sphere_scene = rt.sphere_on_plane


def field_scene():
    """14 spheres 2-40 m ahead of a low camera over a 100 m plane (cascades)."""
    return rt.field_of_spheres(14)


FIELD_CAMERA = camera(*rt.FIELD_CAMERA)
FIELD_SUN = rt.FIELD_SUN


def culled_shadow_time(scene, lights, view, proj, res: int, repeats: int
                       ) -> tuple[float, float, float, float, float, str]:
    """(maps with culled views, maps of every view, shadow pass with culled views, shadow
    pass rendering every view, main pass) seconds of CPU time and the views rendered with
    culling ("k of n"). The shadow pass is timed inside the render (the renderer's maps
    and lookup steps, ``_shadow_maps`` and ``_shadow_hook``; the maps alone: the first),
    the main pass is a render without shadows; the three are
    interleaved (culling off: ``shadows.CULL_VIEWS = False``) and each is the fastest of
    ``repeats`` (the other jobs of a shared machine only add time). Every call renders
    its maps (no ``ShadowMapCache``: as when the scene or the lights move; a cache would
    keep the maps of this static scene across the repeats)."""
    with_s, without = tr.Renderer(res), tr.Renderer(res, shadows=False)
    with_s.shadow_cache = None
    spent = {"maps": 0.0, "lookup": 0.0}

    def timed(fn, part: str):
        def run(*args, **kwargs):
            t = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[part] += time.process_time() - t
        return run

    with_s._shadow_maps = timed(with_s._shadow_maps, "maps")
    with_s._shadow_hook = timed(with_s._shadow_hook, "lookup")
    times: dict[str, list[tuple[float, float]]] = {"culled": [], "all": [], "main": []}
    steps: tuple[str, ...] = ()

    def run(which: str) -> None:
        nonlocal steps
        shadows.CULL_VIEWS = which != "all"
        spent.update(maps=0.0, lookup=0.0)
        try:
            t = time.process_time()
            out = (without if which == "main" else with_s)(scene, view, proj, lights)
            total = time.process_time() - t
        finally:
            shadows.CULL_VIEWS = True
        times[which].append((spent["maps"], spent["maps"] + spent["lookup"]) if which != "main"
                            else (total, total))
        if which == "culled":
            steps = out.plan.shadow_maps

    with torch.no_grad():
        for which in times:  # warm-up
            run(which)
        for k in times.values():
            k.clear()
        for _ in range(repeats):
            for which in times:
                run(which)
    counts = [s.rsplit(", ", 1)[1].removesuffix(" rendered") for s in steps
              if s.endswith("rendered")]
    best = {k: (min(m for m, _ in v), min(p for _, p in v)) for k, v in times.items()}
    return (best["culled"][0], best["all"][0], best["culled"][1], best["all"][1],
            best["main"][1], "; ".join(counts))


def shadow_time(scene, lights, view, proj, res: int, repeats: int) -> tuple[float, float]:
    """(shadow pass, main pass) seconds of CPU time: medians of interleaved renders with /
    without shadows (process CPU time: robust to the other jobs of a shared machine)."""
    with_s, without = tr.Renderer(res), tr.Renderer(res, shadows=False)
    on, off = [], []
    with torch.no_grad():
        with_s(scene, view, proj, lights)  # warm-up
        without(scene, view, proj, lights)
        for _ in range(repeats):
            t = time.process_time()
            with_s(scene, view, proj, lights)
            on.append(time.process_time() - t)
            t = time.process_time()
            without(scene, view, proj, lights)
            off.append(time.process_time() - t)
    main = statistics.median(off)
    return max(statistics.median(on) - main, 0.0), main


class Bench:
    """Scenes, references and timing of one run."""

    def __init__(self, res: int, soft_res: int, samples: int, repeats: int) -> None:
        self.res, self.soft_res, self.repeats = res, soft_res, repeats
        self.positions, self.faces, self.cast = sphere_scene()
        self.scene = tr.RenderScene(self.positions, self.faces, materials=[MATERIAL],
                                    cast_shadows=self.cast)
        self.view, self.proj = camera()
        self.hard, self.soft = {}, {}
        t = time.perf_counter()
        for kind in KINDS:
            lights = rt.make_lights(kind, ShadowSettings(filter="hard"))
            shot = self.shot(lights, res)
            self.hard[kind] = rt.reference_for(shot, lights, self.positions,
                                               self.faces[self.cast])
            shot = self.shot(lights, soft_res)
            size = LIGHT_SIZE[kind]
            area = rt.reference_for(shot, lights, self.positions, self.faces[self.cast],
                                    samples=samples, **({"angle": size} if kind == "directional"
                                                        else {"radius": size}))
            hard = rt.reference_for(shot, lights, self.positions, self.faces[self.cast])
            self.soft[kind] = (area, hard, shot.valid)
        print(f"references: {time.perf_counter() - t:.1f} s", flush=True)

    def shot(self, lights, res: int) -> rt.Shot:
        return rt.render_shadow_factor(self.positions, self.faces, self.cast, lights,
                                       self.view, self.proj, res=res)

    def timed(self, lights, res: int | None = None, repeats: int | None = None):
        return shadow_time(self.scene, lights, self.view, self.proj, res or self.res,
                           repeats or self.repeats)

    def hard_row(self, kind: str, st: ShadowSettings, repeats: int | None = None) -> list:
        lights = rt.make_lights(kind, st)
        shot = self.shot(lights, self.res)
        stats = rt.mask_stats(shot.vis, self.hard[kind], shot.valid)
        t, main = self.timed(lights, repeats=repeats)
        return [t * 1e3, main * 1e3, 1 - stats["iou"], stats["acne"], stats["peter"]]

    def soft_row(self, kind: str, st: ShadowSettings, versus: torch.Tensor | None = None
                 ) -> list:
        area, hard, valid = self.soft[kind]
        shot = self.shot(rt.make_lights(kind, st), self.soft_res)
        vis = shot.vis.double()
        region = ((area < 0.999) | (vis < 0.999))[valid]
        err = (vis - area).abs()[valid]
        row = [float(err.mean()), float(err[region].mean()),
               float((vis - hard).abs()[valid].mean())]
        if versus is not None:
            near = ((vis < 0.999) | (versus < 0.999)) & valid
            row.append(float((vis - versus).abs()[near].mean()))
        t, _ = self.timed(rt.make_lights(kind, st))
        return [t * 1e3] + row


def map_sizes(b: Bench, sizes) -> tuple[str, dict]:
    rows, ok = [], {}
    for size in sizes:
        for kind in KINDS:
            st = ShadowSettings(map_size=size)
            row = b.hard_row(kind, st, repeats=1 if size >= 4096 else None)
            ok.setdefault(size, []).append(row[2] <= 1 - IOU_OK)
            rows.append([size, kind] + row)
            print(rows[-1], flush=True)
    table = markdown_table(["map", "light", "shadow pass ms", "main pass ms", "1 - IoU",
                            "acne", "peter-panning"], rows)
    return table, ok


def cascades(b: Bench, sizes) -> str:
    positions, faces, cast = field_scene()
    scene = tr.RenderScene(positions, faces, materials=[MATERIAL], cast_shadows=cast)
    view, proj = FIELD_CAMERA
    lights = rt.make_lights("directional", ShadowSettings(filter="hard"), direction=FIELD_SUN)
    shot = rt.render_shadow_factor(positions, faces, cast, lights, view, proj, res=b.res)
    ref = rt.reference_for(shot, lights, positions, faces[cast])
    rows = []
    for size in sizes:
        for count in (1, 2, 3, 4):
            st = ShadowSettings(map_size=size, cascades=count)
            lights = rt.make_lights("directional", st, direction=FIELD_SUN)
            shot = rt.render_shadow_factor(positions, faces, cast, lights, view, proj,
                                           res=b.res)
            stats = rt.mask_stats(shot.vis, ref, shot.valid)
            t, main = shadow_time(scene, lights, view, proj, b.res, b.repeats)
            rows.append([size, count, t * 1e3, main * 1e3, 1 - stats["iou"], stats["acne"],
                         stats["peter"], "; ".join(shot.plan.shadow_maps)])
            print(rows[-1], flush=True)
    return markdown_table(["map", "cascades", "shadow pass ms", "main pass ms", "1 - IoU",
                           "acne", "peter-panning", "plan"], rows)


def soft(b: Bench, taps, blurs) -> tuple[str, list]:
    rows, picks = [], []
    header = ["light", "filter", "shadow pass ms", "MAE vs area", "MAE vs area, shadow region",
              "MAE vs hard", "MAE vs 64 taps, shadow region"]
    for kind in KINDS:
        best_vis = b.shot(rt.make_lights(kind, ShadowSettings(pcf_taps=64)),
                          b.soft_res).vis.double()
        for n in taps:
            row = b.soft_row(kind, ShadowSettings(pcf_taps=n), versus=best_vis)
            rows.append([kind, f"pcf {n} taps"] + row)
            picks.append((kind, "pcf", n, row))
            print(rows[-1], flush=True)
        st = ShadowSettings(filter="pcss", light_size=LIGHT_SIZE[kind])
        row = b.soft_row(kind, st)
        rows.append([kind, f"pcss (light size {LIGHT_SIZE[kind]})"] + row + [""])
        picks.append((kind, "pcss", 16, row))
        print(rows[-1], flush=True)
        for sigma in blurs:
            row = b.soft_row(kind, ShadowSettings(filter="vsm", vsm_blur=sigma))
            rows.append([kind, f"vsm blur {sigma}"] + row + [""])
            picks.append((kind, "vsm", sigma, row))
            print(rows[-1], flush=True)
    return markdown_table(header, rows), picks


BIASES = ((1.0, 1.0, 1.0), (1.0, 1.0, 0.5), (1.0, 1.0, 0.0), (1.0, 2.0, 0.0), (1.0, 3.0, 0.0),
          (2.0, 2.0, 1.0), (2.0, 2.0, 0.5))


def grazing_acne(kind: str, st: ShadowSettings, elevation: float = 5.0) -> tuple[int, float]:
    """(pixels darker than 0.95, min visibility) of a casting + receiving plane lit at
    ``elevation`` degrees (``raytrace.grazing_plane_shot``)."""
    shot = rt.grazing_plane_shot(kind, elevation, st)
    vis = shot.vis[shot.valid]
    return int((vis < 0.95).sum()), float(vis.min())


def biases(b: Bench) -> tuple[str, list]:
    rows = []
    for bias, slope, normal in BIASES:
        for filt in ("hard", "pcf", "pcss"):
            ious, acne, worst, acne3 = [], 0, 1.0, 0
            for kind in KINDS:
                st = ShadowSettings(map_size=512, filter=filt, bias=bias, slope_bias=slope,
                                    normal_bias=normal, light_size=LIGHT_SIZE[kind])
                shot = b.shot(rt.make_lights(kind, st), b.res)
                ious.append(rt.mask_stats(shot.vis, b.hard[kind], shot.valid)["iou"])
                n, low = grazing_acne(kind, st)
                acne, worst = acne + n, min(worst, low)
                acne3 += grazing_acne(kind, st, 3.0)[0]
            rows.append([f"{bias} / {slope} / {normal}", filt] + [1 - x for x in ious]
                        + [acne, worst, acne3])
            print(rows[-1], flush=True)
    return markdown_table(["bias / slope / normal (texels)", "filter"]
                          + [f"1 - IoU {k}" for k in KINDS]
                          + ["acne px at 5 deg (all lights, < 0.95)",
                             "min visibility at 5 deg", "acne px at 3 deg"], rows), rows


def typical_scene():
    """A typical view: a 12 m floor with 7 spheres (0.3-0.6 m) and a camera 3 m high,
    6 m back, looking down at the middle; :func:`ground_scene` outputs and the camera."""
    gen = torch.Generator().manual_seed(2)
    casters = []
    for _ in range(7):
        r = 0.3 + 0.3 * float(torch.rand(1, generator=gen))
        x, z = (torch.rand(2, generator=gen) * 8 - 4).tolist()
        casters.append(rt.icosphere(r, (x, r, z)))
    return rt.ground_scene(casters, 12.0), camera((0.0, 3.0, 6.0), (0.0, 0.0, 0.0), 50.0)


def _light_positions(scene_name: str, n: int) -> torch.Tensor:
    """``(n, 3)``: on a 1.2 m circle 1.8 m high over the sphere; over the typical view's
    floor, 2.5 m high on a jittered grid (one light: above the middle)."""
    if scene_name == "sphere":
        ang = torch.arange(n) * (2 * math.pi / n)
        return torch.stack([1.2 * torch.cos(ang), torch.full_like(ang, 1.8),
                            1.2 * torch.sin(ang)], -1)
    side = math.ceil(math.sqrt(n))
    k = torch.arange(n)
    grid = torch.stack([(k % side).float(), (k // side).float()], -1)
    xz = (grid + 0.5) / side * 8 - 4 if n > 1 else torch.zeros(1, 2)
    return torch.stack([xz[:, 0], torch.full((n,), 2.5), xz[:, 1]], -1)


def light_counts(counts, batches, res: int, repeats: int) -> tuple[str, list]:
    """Shadow pass against the main pass, point and spot lights, over the sphere scene and
    a typical view; culled views (the renderer's default) and every view."""
    (typ_pos, typ_faces, typ_cast), typ_camera = typical_scene()
    scenes = {"sphere": (sphere_scene(), camera()),
              "typical": ((typ_pos, typ_faces, typ_cast), typ_camera)}
    rows = []
    for scene_name, ((positions, faces, cast), (view, proj)) in scenes.items():
        scene = tr.RenderScene(positions, faces, materials=[MATERIAL], cast_shadows=cast)
        for kind in ("point", "spot"):
            for batch in batches:
                for n in counts:
                    lights = rt.make_lights(kind, ShadowSettings(map_size=512), count=n,
                                            batch=batch)
                    part = getattr(lights, kind)
                    part.position = _light_positions(scene_name, n).expand(batch, n, 3)
                    if kind == "spot":
                        part.direction = (-part.position if scene_name == "sphere" else
                                          torch.tensor([0.0, -1.0, 0.0]).expand(batch, n, 3))
                    maps, maps_all, t, t_all, main, views = culled_shadow_time(
                        scene, lights, view.expand(batch, 4, 4), proj, res,
                        repeats if n * batch < 16 else 2)
                    rows.append([scene_name, kind, batch, n, views, maps * 1e3,
                                 maps_all * 1e3, t * 1e3, t_all * 1e3, main * 1e3, t / main,
                                 t_all / main])
                    print(rows[-1], flush=True)
    return markdown_table(["scene", "light", "batch", "shadowed lights", "views rendered",
                           "maps ms", "every view: maps ms", "shadow pass ms",
                           "every view: shadow pass ms", "main pass ms", "shadow / main",
                           "every view: shadow / main"], rows), rows


def best_biases(bias_rows: list) -> tuple[str, float] | None:
    """The bias combination with no acne at 5 degrees for hard and PCF and the best
    worst-light IoU (ties: the least acne at 3 degrees): (label, worst 1 - IoU)."""
    by_combo: dict[str, list] = {}
    for r in bias_rows:
        if r[1] in ("hard", "pcf"):
            by_combo.setdefault(r[0], []).append(r)
    ranked = sorted((max(max(r[2:5]) for r in rs), sum(r[7] for r in rs), k)
                    for k, rs in by_combo.items() if all(r[5] == 0 for r in rs))
    return (ranked[0][2], ranked[0][0]) if ranked else None


def findings(bias_rows: list, count_rows: list) -> str:
    """What the tables say about the biases, PCSS and the cost (numbers of this run)."""
    row = {(r[0], r[1]): r for r in bias_rows}
    default = f"{DEFAULT.bias} / {DEFAULT.slope_bias} / {DEFAULT.normal_bias}"
    base = row[(default, "pcf")]
    best = best_biases(bias_rows)
    pcss = [r[6] for r in bias_rows if r[1] == "pcss"]
    lines = []
    if best:
        better = row[(best[0], "pcf")]
        lines.append(
            "* The hard-mask error is mostly the normal offset: it moves every lookup towards "
            "the light, so shadows shrink. 1 - IoU at 512², PCF, directional / spot / point: "
            f"{base[2]:.4f} / {base[3]:.4f} / {base[4]:.4f} with {default}; "
            f"{better[2]:.4f} / {better[3]:.4f} / {better[4]:.4f} with {best[0]}, whose "
            f"PCF has {better[5]} acne pixels at 5 degrees and {better[7]} at 3 (the default: "
            f"{base[5]} and {base[7]}).")
    lines.append(
        f"* PCSS on a tilted receiver that also casts (the plane at 5 degrees): minimum "
        f"visibility {min(pcss):.2f}-{max(pcss):.2f} over the bias rows: each filter and "
        "blocker-search tap compares against the receiver plane's depth at the tap "
        "(receiver-plane bias), so the receiver does not shadow itself.")
    lines.append("* PCF and VSM are hard-shadow filters: against an area light only PCSS stays "
                 f"within {SOFT_OK} shadow-region MAE.")
    lines.append(cost_finding(count_rows))
    return "\n".join(lines)


def cost_finding(count_rows: list) -> str:
    """The findings' line on the cost of the shadow pass (rows of :func:`light_counts`)."""
    ratios = [r[-2] for r in count_rows]
    every = [r[-1] for r in count_rows]
    typical = [(r[-1], r[-2]) for r in count_rows if r[0] == "typical" and r[1] == "point"]
    saved = [1 - r[5] / r[6] for r in count_rows if r[1] == "point" and r[6] > 0]
    return (
        f"* The shadow pass costs {min(ratios):.1f}-{max(ratios):.1f} times the main pass "
        f"(512² image, 512² maps, 1-16 lights, batch 1-4; {min(every):.1f}-{max(every):.1f} "
        "rendering every view): cube maps of point lights (6 views each) cost most. Only "
        "the cube faces some receiver can read are rendered (the G-buffer's surfaces, the "
        "fog's view rays, with edge antialiasing the scene's box; "
        "`shadows.cull_local_views`, the same image; single spot maps are always rendered)"
        + (f"; in the typical view (point lights 2.5 m over a floor the camera looks down "
           f"at) the point-light shadow pass falls from {min(a for a, _ in typical):.1f}-"
           f"{max(a for a, _ in typical):.1f} to {min(c for _, c in typical):.1f}-"
           f"{max(c for _, c in typical):.1f} times the main pass." if typical else ".")
        + (f" The point lights' maps take {min(saved):.0%}-{max(saved):.0%} less time; the "
           "lookups, which culling does not change, are most of the shadow pass here (and "
           "the noisiest part of these times)." if saved else ""))


def cost_section(table: str, res: int) -> str:
    """The subsection of the shadow pass's cost (Markdown, from its heading)."""
    return f"""### Shadow pass against the main pass ({res}² image, 512² maps, PCF)

Scenes: `sphere` is the sphere on the plane above with the lights on a 1.2 m circle 1.8 m
high (spots aimed at the sphere); `typical` a 12 m floor with 7 spheres seen from 3 m high
and 6 m back, looking down at the middle, the lights 2.5 m over the floor on a grid (spots
aimed straight down), whose faces away from the visible floor see nothing the camera
sees. Views rendered: cube faces (or spot maps) rendered of those of every item and light,
with culling (the default).
Every view: the same renders with culling off (`shadows.CULL_VIEWS = False`). Shadow pass:
CPU time of the renderer's shadow steps (maps and lookups: `_shadow_maps`, `_shadow_hook`)
inside the render; main pass: a render without shadows; interleaved, the fastest of the
repeats (2 from 16 light-items on). Every render draws its maps (no `ShadowMapCache`, as
when the scene or the lights move): culling saves maps only, not lookups.

{table}
"""


def replace_cost_section(table: str, rows: list, res: int) -> None:
    """Put a new cost subsection and findings line into docs/benchmarks.md's shadows
    section (the other tables keep those of their last full run)."""
    from benchmd import DOC  # noqa: PLC0415

    text = DOC.read_text()
    m = re.search(r"<!-- begin shadows -->\n(.*?)\n\nCommand: .*?<!-- end shadows -->", text,
                  re.S)
    if m is None:
        raise SystemExit("docs/benchmarks.md has no shadows section: run the full benchmark")
    body = m[1]
    body = re.sub(r"### Shadow pass against the main pass.*?(?=\n### )",
                  lambda _: cost_section(table, res).rstrip() + "\n", body, flags=re.S)
    body = re.sub(r"^\* The shadow pass costs.*$", lambda _: cost_finding(rows), body,
                  flags=re.M)
    update_section("shadows", body, "python scripts/bench_shadows.py (the cost tables: "
                   "python scripts/bench_shadows.py --cost-only)")


def pick_defaults(size_ok: dict, soft_picks: list, bias_rows: list) -> str:
    """The fastest settings within the stated errors (see the lines it returns)."""
    lines = []
    good = [s for s, oks in sorted(size_ok.items()) if all(oks)]
    lines.append(f"* map size: the smallest with IoU >= {IOU_OK} for all three lights (PCF, "
                 f"default biases): **{good[0]}** (default {DEFAULT.map_size})." if good else
                 f"* map size: no size reaches IoU >= {IOU_OK} for all three lights.")
    taps: dict[int, list[float]] = {}
    for _, filt, n, row in soft_picks:
        if filt == "pcf" and len(row) > 4:
            taps.setdefault(n, []).append(row[4])
    enough = [n for n in sorted(taps) if max(taps[n]) <= TAPS_OK]
    if enough:
        lines.append(f"* PCF taps: the fewest within {TAPS_OK} MAE (shadow region) of 64 taps for "
                     f"all lights: **{enough[0]}** (default {DEFAULT.pcf_taps}).")
    soft_ok = sorted({(f, n) for _, f, n, row in soft_picks
                      if all(r[2] <= SOFT_OK for k, f2, n2, r in soft_picks
                             if (f2, n2) == (f, n))})
    lines.append(f"* soft settings with shadow-region MAE <= {SOFT_OK} against the area light "
                 "for all lights: " + (", ".join(f"{f} {n}" for f, n in soft_ok) or "none")
                 + ".")
    best = best_biases(bias_rows)
    if best:
        lines.append(f"* biases (bias / slope / normal): of the combinations with no acne at 5 "
                     f"degrees (hard and PCF), the best worst-light IoU, then the least acne at "
                     f"3 degrees: **{best[0]}** (default {DEFAULT.bias} / {DEFAULT.slope_bias} "
                     f"/ {DEFAULT.normal_bias}); with it 512² maps already reach 1 - IoU "
                     f"{best[1]:.4f} (hard and PCF, all lights)"
                     + (f", within {1 - IOU_OK:g}: **512** would do." if best[1] <= 1 - IOU_OK
                        else "."))
    return "\n".join(lines)


# ------------------------------------------------------------------------------- pictures


def _label(img: np.ndarray, text: str) -> np.ndarray:
    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    draw.rectangle([0, 0, 7 * len(text) + 6, 14], fill=(0, 0, 0))
    draw.text((3, 1), text, fill=(255, 255, 255))
    return np.asarray(pil)


def _display(image: torch.Tensor) -> np.ndarray:
    """``(3, H, W)`` linear HDR -> ``(H, W, 3)`` uint8 (Reinhard-free clamp, gamma 2.2)."""
    x = image.detach().clamp(0, 1) ** (1 / 2.2)
    return (x.permute(1, 2, 0) * 255 + 0.5).byte().numpy()


def picture_filters(res: int = 200) -> None:
    """Rows: directional, spot, point; columns: hard, PCF, PCSS, VSM and the ray-traced
    area light (shadow factor times the unshadowed render)."""
    positions, faces, cast = sphere_scene()
    scene = tr.RenderScene(positions, faces, materials=[MATERIAL], cast_shadows=cast)
    view, proj = camera()
    rows = []
    for kind in KINDS:
        tiles = []
        size = LIGHT_SIZE[kind]
        for filt in ("hard", "pcf", "pcss", "vsm"):
            st = ShadowSettings(map_size=1024, filter=filt, light_size=size)
            with torch.no_grad():
                out = tr.Renderer(res)(scene, view, proj, rt.make_lights(kind, st))
            tiles.append(_label(_display(out.image[0]), f"{kind} {filt}"))
        lights = rt.make_lights(kind, ShadowSettings(filter="hard"))
        shot = rt.render_shadow_factor(positions, faces, cast, lights, view, proj, res=res,
                                       min_cos=-1.0)
        ref = rt.reference_for(shot, lights, positions, faces[cast], samples=64,
                               **({"angle": size} if kind == "directional" else {"radius": size}))
        with torch.no_grad():
            plain = tr.Renderer(res, shadows=False)(scene, view, proj, lights).image[0]
        tiles.append(_label(_display(plain * ref.float()), "ray-traced area light"))
        rows.append(np.concatenate(tiles, 1))
    Image.fromarray(np.concatenate(rows, 0)).save(IMAGES / "shadows_filters.png",
                                                  optimize=True)


CASCADE_COLOURS = torch.tensor([[1.0, 0.35, 0.3], [0.35, 1.0, 0.35], [0.35, 0.5, 1.0],
                                [1.0, 0.9, 0.3]])


def picture_cascades(res: int = 320) -> None:
    """Left: cascade index (colour) times the shaded render of the field; right: render."""
    positions, faces, cast = field_scene()
    scene = tr.RenderScene(positions, faces, materials=[MATERIAL], cast_shadows=cast)
    view, proj = FIELD_CAMERA
    st = ShadowSettings(map_size=1024, cascades=4)
    lights = rt.make_lights("directional", st, direction=FIELD_SUN)
    with torch.no_grad():
        out = tr.Renderer(res)(scene, view, proj, lights, channels={"position"})
    img = out.image[0]
    # the cascade a pixel reads: the first split end beyond its camera depth (as the engine)
    bounds = positions[faces[cast].unique()]
    bounds = torch.stack([bounds.amin(0), bounds.amax(0)])[None]
    g = directional_views(torch.tensor([[FIELD_SUN]]), st, bounds, view, proj)
    p = out.gbuffer["position"][0]
    depth = -(view[0, 2, :3] @ p.reshape(3, -1) + view[0, 2, 3]).view(res, res)
    idx = (depth[..., None] >= g.splits[0, 0, 1:]).sum(-1).clamp_max(3)
    colour = CASCADE_COLOURS[idx].permute(2, 0, 1) * out.alpha[0]
    lum = img.mean(0, keepdim=True).clamp(0, 1) ** (1 / 2.2)
    debug = (colour * (0.25 + 0.75 * lum)).clamp(0, 1)
    left = _label((debug.permute(1, 2, 0) * 255 + 0.5).byte().numpy(),
                  "cascade 1 red, 2 green, 3 blue, 4 yellow")
    right = _label(_display(img), "4 cascades 1024, PCF")
    Image.fromarray(np.concatenate([left, right], 1)).save(IMAGES / "shadows_cascades.png",
                                                           optimize=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sweep, no docs update")
    ap.add_argument("--pictures-only", action="store_true")
    ap.add_argument("--cost-only", action="store_true",
                    help="only the shadow pass / main pass table (culled views against every "
                         "view); replaces it in docs/benchmarks.md's shadows section")
    args = ap.parse_args()
    torch.manual_seed(0)
    torch.set_num_threads(1)  # CPU times of one thread: comparable on a shared machine
    if args.cost_only:
        res = 256 if args.quick else 512
        counts, batches = ((1, 4), (1,)) if args.quick else ((1, 4, 16), (1, 4))
        table, rows = light_counts(counts, batches, res, 1 if args.quick else 3)
        print(table + "\n\n" + cost_finding(rows))
        if not args.quick:
            replace_cost_section(table, rows, res)
        return
    start = time.perf_counter()
    if args.pictures_only or not args.quick:
        picture_filters()
        picture_cascades()
        print(f"pictures written to {IMAGES}", flush=True)
        if args.pictures_only:
            return
    if args.quick:
        b = Bench(res=128, soft_res=64, samples=16, repeats=1)
        sizes, taps, blurs, counts, batches = (512, 1024), (1, 16), (1.5,), (1, 4), (1,)
    else:
        b = Bench(res=256, soft_res=128, samples=64, repeats=3)
        sizes, taps, blurs = (256, 512, 1024, 2048, 4096), (1, 4, 16, 32, 64), (0.5, 1, 1.5, 3)
        counts, batches = (1, 4, 16), (1, 4)
    size_table, size_ok = map_sizes(b, sizes)
    cascade_table = cascades(b, (512, 1024) if not args.quick else (512,))
    soft_table, picks = soft(b, taps, blurs)
    bias_table, bias_rows = biases(b)
    count_table, count_rows = light_counts(counts, batches, 256 if args.quick else 512, b.repeats)
    verdict = pick_defaults(size_ok, picks, bias_rows)
    took = time.perf_counter() - start
    body = f"""## Shadows: run time against error ({took:.0f} s)

Reference: `torchraster.testing.raytrace`, float64 Möller-Trumbore rays from the G-buffer
positions (origin offset 1e-4 m along the normal) to the light: hard, or an area light
({LIGHT_SIZE['spot']} m disc for spot / point lights, a {LIGHT_SIZE['directional']} degree sun,
{b.soft_res}² pixels, 64 stratified rays per pixel). Scene: a 1 m sphere (1280 faces) on a
4 m plane that receives but does not cast, {b.res}² pixels, the lights of
`raytrace.LIGHTS`. Our shadow factor is the ratio of renders with / without shadows
(`raytrace.render_shadow_factor`; pixels with n.l > 0.1). Masks: visibility < 0.5; acne =
share of reference-lit pixels we shadow, peter-panning = share of reference-shadowed pixels we
light, both outside a 2 px band around the reference boundaries. Times: CPU time of one
thread (`torch.set_num_threads(1)`, `time.process_time`: other jobs shared the 2 cores while
this ran); shadow pass = median render with shadows minus median render without (the main
pass), {b.repeats} interleaved repeats after a warm-up.

### Map size (default filter: PCF {DEFAULT.pcf_taps} taps, radius {DEFAULT.pcf_radius})

{size_table}

### Cascades (directional light, 100 m field of 14 spheres, camera 1.7 m high)

{cascade_table}

### Soft filters (map 1024) against the area light

{soft_table}

### Biases (map 512): IoU on the sphere, acne on a casting plane lit at 5 and 3 degrees

{bias_table}

{cost_section(count_table, 256 if args.quick else 512)}
### Findings

{findings(bias_rows, count_rows)}

### Defaults: the fastest setting within the stated error

{verdict}
"""
    print(body)
    if not args.quick:
        update_section("shadows", body)


if __name__ == "__main__":
    main()
