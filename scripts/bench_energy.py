"""Energy compensation for every light type, and IBL specular beyond the split sum.

Writes the sections ``energy`` and ``ibl-specular`` of docs/benchmarks.md and the
pictures ``docs/images/energy_compensation.png`` and ``docs/images/ibl_specular.png``.

* energy: white furnaces (a lossless material under uniform light must reflect 1) for
  punctual light (a hemisphere of directional lights on a half-vector quadrature), ambient
  light and IBL, with and without ``multiscatter``; the run-time overhead of the energy
  terms on a full frame.
* ibl-specular: the specular of a white metal (f0 = 1, single scattering) on the sun-lit
  venice_sunset_1k map (roughness 0.3 / 0.6 / 0.8) and pedestrian_overpass_1k (0.3 / 0.6)
  at 64 random (n, v) pairs, against a brute-force float64 sum of the GGX lobe
  ``D G F (n.l) / (4 n.l n.v)`` over every texel of the full map: split sum (dominant
  direction, fitted lobe, with and without sun extraction), per-pixel filtered importance
  sampling with N samples, and the brute force itself (its time from the reference run);
  the split of the split sum's error into chain error and lobe-shape error; the time of
  ``shade_ibl`` before / after the one-call chain lookup and ``mask=``.

Usage: python scripts/bench_energy.py [--quick] [--no-images]
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from benchmd import markdown_table, median_time, update_section
from skimage import io as skio

from torchraster.config import lights_from_config
from torchraster.gbuffer import GBuffer
from torchraster.hdr_io import read_hdr
from torchraster.shading import Lights, shade
from torchraster.shading.ibl import Environment, dfg_lut, lookup_dfg, shade_ibl
from torchraster.shading.lights import DirectionalLights, PointLights
from torchraster.testing.assets import data_dir
from torchraster.testing.reference_brdf import furnace_hemisphere, heitz_v, walter_ggx
from torchraster.texture import latlong_directions, latlong_solid_angles

ROOT = Path(__file__).resolve().parent.parent
IMAGES = ROOT / "docs" / "images"
ENVMAPS = data_dir() / "envmaps"
F64 = torch.float64
THETAS = (0.0, 0.5, 1.0, 1.4)


# ------------------------------------------------------------------------------ energy


def view_gbuffer(theta: float, metallic: float, rough: float) -> tuple[GBuffer, torch.Tensor]:
    """One white pixel (normal +z at the origin) and its camera at distance 10 along v."""
    one = torch.ones(1, 1, 1, 1, dtype=F64)
    gb = GBuffer(position=torch.zeros(1, 3, 1, 1, dtype=F64),
                 normal=torch.tensor([0.0, 0.0, 1.0], dtype=F64).view(1, 3, 1, 1),
                 albedo=torch.ones(1, 3, 1, 1, dtype=F64), metallic=metallic * one,
                 roughness=rough * one)
    v = torch.tensor([[math.sin(theta), 0.0, math.cos(theta)]], dtype=F64)
    return gb, 10.0 * v


def hemisphere_lights(theta_v: float, n_theta: int = 200, n_phi: int = 64) -> Lights:
    """Directional lights of unit radiance on a half-vector quadrature of the hemisphere
    (dw_l = 4 (v.h) dw_h, graded towards the normal): the rendered sum is the
    directional albedo of the BRDF the punctual path evaluates."""
    l, w = furnace_hemisphere(theta_v, n_theta, n_phi)
    return Lights(directional=DirectionalLights(
        direction=-l[None], color=torch.ones(1, l.shape[0], 3, dtype=F64), intensity=w[None]))


def furnace(kind: str, metallic: float, rough: float, multiscatter: bool) -> float:
    """Mean over THETAS of the reflected radiance under uniform unit radiance."""
    vals = []
    white_env = Environment(torch.ones(3, 32, 64, dtype=F64), specular_size=8,
                            specular_levels=5, specular_samples=16)
    ambient = lights_from_config([{"type": "ambient", "color": [1.0, 1.0, 1.0]}], dtype=F64)
    for theta in THETAS:
        gb, eye = view_gbuffer(theta, metallic, rough)
        if kind == "punctual":
            out = shade(gb, camera_position=eye, lights=hemisphere_lights(theta),
                        multiscatter=multiscatter)
        elif kind == "ambient":
            out = shade(gb, camera_position=eye, lights=ambient, multiscatter=multiscatter)
        else:
            out = shade_ibl(gb.normal, eye.view(1, 3, 1, 1), gb.albedo, gb.metallic,
                            gb.roughness, None, white_env, multiscatter=multiscatter)
        vals.append(float(out.mean()))
    return sum(vals) / len(vals)


def sphere_gbuffer(res: int, metallic: float, rough: float, albedo=(1.0, 0.78, 0.34)):
    """Analytic unit sphere seen along -z from (0, 0, 10) (orthographic-like)."""
    c = (torch.arange(res, dtype=torch.float32) + 0.5) / res * 2 - 1
    y, x = -c.view(-1, 1).expand(res, res), c.view(1, -1).expand(res, res)
    r2 = x * x + y * y
    mask = (r2 < 1)[None, None]
    n = torch.stack((x, y, torch.sqrt((1 - r2).clamp_min(0))), 0)[None] * mask
    one = torch.ones(1, 1, res, res)
    return GBuffer(position=n.clone(), normal=n, albedo=torch.tensor(albedo).view(1, 3, 1, 1)
                   * torch.ones(1, 3, res, res), metallic=metallic * one,
                   roughness=rough * one, mask=mask.float())


def to_srgb(x: torch.Tensor) -> np.ndarray:
    x = x.clamp(0, 1)
    x = torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-8) ** (1 / 2.4) - 0.055)
    return (x[0].permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)


def energy_images() -> None:
    """Gold spheres under one point light, roughness 0.2 .. 1: single scattering (top)
    and compensated (bottom)."""
    res = 128
    lights = Lights(point=PointLights(position=torch.tensor([[[4.0, 4.0, 10.0]]]),
                                      color=torch.ones(1, 1, 3), intensity=torch.tensor(
                                          [[300.0]])))
    rows = []
    for ms in (False, True):
        tiles = []
        for rough in (0.2, 0.4, 0.6, 0.8, 1.0):
            gb = sphere_gbuffer(res, 1.0, rough)
            tiles.append(shade(gb, camera_position=torch.tensor([[0.0, 0.0, 10.0]]),
                               lights=lights, multiscatter=ms))
        rows.append(torch.cat(tiles, -1))
    img = to_srgb(torch.cat(rows, -2))
    IMAGES.mkdir(parents=True, exist_ok=True)
    skio.imsave(IMAGES / "energy_compensation.png", img, check_contrast=False)


def bench_energy(quick: bool, images: bool) -> str:
    roughs = [0.0, 0.25, 0.5, 0.75, 1.0] if not quick else [0.5, 1.0]
    rows = []
    for kind in ("punctual", "ambient", "ibl"):
        for r in roughs:
            vals = [furnace(kind, m, r, ms) for m in (1.0, 0.0) for ms in (True, False)]
            rows.append([kind, r] + [100 * (x - 1) for x in vals])
    table = markdown_table(
        ["light", "roughness", "white metal, compensated (%)", "white metal, single (%)",
         "white dielectric, compensated (%)", "white dielectric, single (%)"], rows)
    worst = max(max(abs(r[2]), abs(r[4])) for r in rows)
    metal_loss, diel_gain = -min(r[3] for r in rows), max(r[5] for r in rows)
    print(table)

    # run-time overhead on a full frame (512x512 sphere, 4 point lights / ambient / IBL)
    torch.set_num_threads(1)
    res = 256 if quick else 512
    gb = sphere_gbuffer(res, 0.5, 0.6)
    eye = torch.tensor([[0.0, 0.0, 10.0]])
    g = torch.Generator().manual_seed(0)
    pts = Lights(point=PointLights(position=torch.randn(1, 4, 3, generator=g) * 3 + torch.tensor(
        [0.0, 0.0, 4.0]), color=torch.ones(1, 4, 3), intensity=torch.full((1, 4), 50.0)))
    amb = Lights(ambient=torch.rand(1, 9, 3, generator=g) * 0.2)
    env = Environment(torch.rand(3, 64, 128, generator=g) + 0.5)
    n = gb.normal
    v = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand_as(n)
    cases = {
        "4 point lights": lambda ms: shade(gb, camera_position=eye, lights=pts, multiscatter=ms),
        "ambient (SH)": lambda ms: shade(gb, camera_position=eye, lights=amb, multiscatter=ms),
        "IBL (split sum)": lambda ms: shade_ibl(n, v, gb.albedo, gb.metallic, gb.roughness,
                                                None, env, multiscatter=ms),
    }
    trows = []
    with torch.no_grad():
        for name, fn in cases.items():
            t_on = median_time(lambda fn=fn: fn(True), 3 if quick else 7)
            t_off = median_time(lambda fn=fn: fn(False), 3 if quick else 7)
            trows.append([name, 1e3 * t_off, 1e3 * t_on, t_on / t_off])
    ttable = markdown_table(["pass", "multiscatter=False (ms)", "multiscatter=True (ms)",
                             "ratio"], trows)
    print(ttable)
    torch.set_num_threads(torch.get_num_threads())
    if images:
        energy_images()
    return (
        "## Energy compensation (multiscatter) for every light type\n\n"
        "White furnace: a white material (metal: f0 = 1; dielectric: albedo 1 under a 4 % "
        "specular coat) under uniform unit radiance must reflect exactly 1. Punctual = "
        f"{len(hemisphere_lights(0.0).directional.intensity[0])} directional lights on a "
        "half-vector quadrature of the hemisphere (the sum is the directional albedo of the "
        "BRDF the light pass evaluates); ambient = constant SH radiance; IBL = a uniform "
        f"environment. Signed error of the mean over view angles {list(THETAS)} rad.\n\n"
        + table + "\n\n"
        f"With compensation every light type is within {worst:.2g} % of 1; without it a "
        f"rough white metal loses up to {metal_loss:.0f} % (mean over the view angles; "
        f"grazing views lose most) and a white dielectric reflects up to {diel_gain:.1f} % "
        "too much (Lambert plus an uncoupled specular). The ambient and IBL furnaces are "
        "exact by construction (the same table gives the lobe's albedo and its "
        "compensation); the punctual row is the independent check (quadrature of the "
        "BRDF against the table), as is the Monte-Carlo test in tests/test_energy.py. "
        "Picture: docs/images/energy_compensation.png (gold, roughness 0.2 .. 1, one point "
        "light; top single scattering, bottom compensated).\n\n"
        f"Run time on a {res}x{res} frame (sphere, covered pixels shaded; 1 thread, median; "
        f"load average {os.getloadavg()[0]:.1f} on the 2 cores during the run: times are "
        "noisy, compare the ratios):\n\n" + ttable + "\n\n"
        "`multiscatter=True` stays the default of `shade`, `shade_ibl` and `Renderer`: "
        "the overhead is one DFG lookup a pixel.\n"
    )


# ------------------------------------------------------------------------ ibl-specular


def brute_specular(env: torch.Tensor, n: torch.Tensor, v: torch.Tensor, rough: float
                   ) -> tuple[torch.Tensor, float]:
    """Sum over every texel of L D G F (n.l) / (4 n.l n.v) dw, F = 1 (f0 = 1), reference
    GGX / Smith forms: (K, 3) and seconds per pixel."""
    he, we = env.shape[-2:]
    d = latlong_directions(he, we, dtype=F64).reshape(3, -1)
    dw = latlong_solid_angles(he, we, dtype=F64).expand(he, we).reshape(-1)
    lsrc = env.reshape(3, -1).to(F64)
    a = rough**2
    out = []
    t0 = time.perf_counter()
    for ni, vi in zip(n, v, strict=True):
        nl = ni @ d
        h = F.normalize(d + vi[:, None], dim=0)
        nh = (ni @ h).clamp(1e-9, 1.0)
        f = walter_ggx(nh, a) * heitz_v((ni @ vi).clamp_min(1e-4), nl.clamp_min(1e-9), a)
        out.append(lsrc @ torch.where(nl > 0, f * nl * dw, 0.0))
    return torch.stack(out), (time.perf_counter() - t0) / n.shape[0]


def cpu_median(fn, repeats: int) -> float:
    """Median CPU time (s) of this thread over ``repeats`` calls after one warm-up (less
    sensitive than wall time to other jobs on the shared machine)."""
    fn()
    times = []
    for _ in range(repeats):
        t = time.thread_time()
        fn()
        times.append(time.thread_time() - t)
    return float(np.median(times))


def random_pairs(k: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """k (normal, view) pairs, n.v spread over (0, 1]: (k, 3) each, float64."""
    g = torch.Generator().manual_seed(seed)
    n = F.normalize(torch.randn(k, 3, generator=g, dtype=F64), dim=1)
    v = F.normalize(torch.randn(k, 3, generator=g, dtype=F64), dim=1)
    v = torch.where((n * v).sum(1, keepdim=True) < 0, -v, v)
    return n, F.normalize(v + 0.3 * n, dim=1)


def kernel_mean(env: torch.Tensor, dirs: torch.Tensor, rough: float) -> torch.Tensor:
    """The prefiltered chain's kernel summed exactly over every texel: the GGX-weighted mean
    ``sum L D(c.h) (c.l)^+ dw / sum D (c.l)^+ dw`` (n = v = c) around each of ``dirs``
    ``(K, 3)`` -> ``(K, 3)`` float64 (what a perfect chain returns)."""
    he, we = env.shape[-2:]
    d = latlong_directions(he, we, dtype=F64).reshape(3, -1)
    dw = latlong_solid_angles(he, we, dtype=F64).expand(he, we).reshape(-1)
    lsrc, a2 = env.reshape(3, -1).to(F64), max(rough, 0.045) ** 4
    out = []
    for c in dirs:
        cl = c @ d
        nh2 = ((1.0 + cl) * 0.5).clamp_min(0.0)
        w = cl.clamp_min(0.0) * dw / (nh2 * (a2 - 1.0) + 1.0) ** 2  # D up to a constant
        out.append(lsrc @ w / w.sum())
    return torch.stack(out)


IBL_ROUGHS = (0.2, 0.3, 0.45, 0.6, 0.8, 1.0)
SECOND_MAP, SECOND_ROUGHS = "pedestrian_overpass_1k.hdr", (0.3, 0.6)
SUN_LEVEL = 10.0
BEFORE_REV = "623d366"  # torchraster/shading/ibl.py before the one-call lookup and mask


def bench_ibl_specular(quick: bool, images: bool) -> str:
    path, path2 = ENVMAPS / "venice_sunset_1k.hdr", ENVMAPS / SECOND_MAP
    if not path.exists() or not path2.exists():
        return "## IBL specular\n\n(skipped: the 1k Poly Haven maps are not present)\n"
    torch.set_num_threads(1)
    maps = {"venice": read_hdr(path), "overpass": read_hdr(path2)}
    k = 16 if quick else 64
    n, v = random_pairs(k)
    cases = [("venice", r) for r in IBL_ROUGHS] + [("overpass", r) for r in SECOND_ROUGHS]
    refs, per_pixel = {}, []
    for name, r in cases:
        refs[name, r], t = brute_specular(maps[name], n, v, r)
        per_pixel.append(t)
        print(f"reference {name} r = {r}: {t * 1e3:.0f} ms a pixel")
    envs: dict[tuple, Environment] = {}
    builds: dict[tuple, float] = {}  # (table knobs) -> seconds to build venice's table

    def environment(name: str, sun: float | None, table: tuple = (8, 8, 16)) -> Environment:
        if (name, sun, table) not in envs:
            env = Environment(maps[name], sun_threshold=sun, table_levels=table[0],
                              table_views=table[1], table_azimuths=table[2])
            env.specular_chain  # noqa: B018 - built once, outside the timings
            env.mip_chain  # noqa: B018
            t = time.perf_counter()
            env.lobe_table_atlas  # noqa: B018
            builds.setdefault((name, sun, table), time.perf_counter() - t)
            envs[name, sun, table] = env
        return envs[name, sun, table]

    nn, vv = n.T.reshape(1, 3, 1, k).float(), v.T.reshape(1, 3, 1, k).float()
    one = torch.ones(1, 1, 1, k)

    def spec(name: str, r: float, sun: float | None, classic: bool, table: tuple = (8, 8, 16),
             **kw) -> torch.Tensor:
        env = environment(name, sun, table)
        if classic:  # the split sum read at the reflection vector (before the dominant dir.)
            nv = (nn * vv).sum(1, keepdim=True)
            a, b = lookup_dfg(dfg_lut(16, 32), nv.clamp(1e-4, 1.0), r * one)
            return (env.specular(2 * nv * nn - vv, r * one) * (a + b))[0, :, 0].T.double()
        out = shade_ibl(nn, vv, torch.ones(1, 3, 1, k), one, r * one, None, env,
                        multiscatter=False, **kw)
        return out[0, :, 0].T.double()

    # time per megapixel on a 128x128 frame of random normals and views, roughness 0.6
    res = 128
    g = torch.Generator().manual_seed(1)
    fn = F.normalize(torch.randn(1, 3, res, res, generator=g), dim=1)
    fv = F.normalize(fn + torch.randn(1, 3, res, res, generator=g) * 0.5, dim=1)
    ones = torch.ones(1, 1, res, res)
    sun = SUN_LEVEL
    methods = [("split sum at r (before)", None, {"classic": True}),
               ("split sum, dominant direction (specular=split_sum)", None,
                {"specular": "split_sum"}),
               ("split sum, fitted lobe (specular=fitted)", None, {"specular": "fitted"}),
               ("lobe table (specular=table, default: 8 levels, 8 views, 16 azimuths)", None,
                {"specular": "table"}),
               ("lobe table, 6 levels, 6 views, 12 azimuths", None,
                {"specular": "table", "table": (6, 6, 12)}),
               ("lobe table, 10 levels, 10 views, 24 azimuths", None,
                {"specular": "table", "table": (10, 10, 24)}),
               (f"split sum + sun (sun_threshold={sun:g})", sun, {"specular": "split_sum"}),
               (f"fitted + sun (sun_threshold={sun:g})", sun, {"specular": "fitted"}),
               (f"table + sun (sun_threshold={sun:g})", sun, {"specular": "table"})] + [
        (f"importance N = {s}", None, {"specular": "importance", "importance_samples": s})
        for s in (4, 8, 16, 32, 64)] + [
        (f"importance N = {s} + sun", sun, {"specular": "importance", "importance_samples": s})
        for s in (16, 64)]
    rows, base = [], None
    with torch.no_grad():
        for label, sun_level, kw in methods:
            cl = kw.pop("classic", False)
            errs = [100 * float(((spec(m, r, sun_level, cl, **kw) - refs[m, r]).abs()
                                 / refs[m, r]).mean()) for m, r in cases]
            nv = len(IBL_ROUGHS)
            venice_mean = sum(errs[:nv]) / nv
            if cl:  # the same cost as the split sum: one chain lookup a pixel
                rows.append([label, "as the split sum", "1", "-"] + errs[:nv] + [venice_mean]
                            + errs[nv:])
                continue
            table = kw.pop("table", (8, 8, 16))
            env = environment("venice", sun_level, table)
            t = cpu_median(lambda kw=kw, env=env: shade_ibl(
                fn, fv, ones.expand(1, 3, res, res), ones, 0.6 * ones, None, env, **kw),
                3 if quick else 7)
            base = t if base is None else base
            build = (f"{builds['venice', sun_level, table]:.2f}"
                     if kw.get("specular") == "table" else "-")
            rows.append([label, 1e3 * t / (res * res / 1e6), f"{t / base:.2f}", build]
                        + errs[:nv] + [venice_mean] + errs[nv:])
            print(rows[-1])
    brute_ms = 1e3 * sum(per_pixel) / len(per_pixel) * 1e6
    rows.append(["brute force (reference, float64, every texel)", brute_ms,
                 f"{brute_ms / rows[1][1]:.3g}", "-"] + [0.0] * (len(cases) + 1))
    table = markdown_table(
        ["specular", "ms per megapixel", "x split sum", "table build (s)"]
        + [f"venice r = {r} (%)" for r in IBL_ROUGHS] + ["venice mean (%)"]
        + [f"overpass r = {r} (%)" for r in SECOND_ROUGHS], rows)
    print(table)
    tab_row = next(r for r in rows if r[0].startswith("lobe table (specular=table"))
    tab_err = dict(zip(IBL_ROUGHS, tab_row[4:4 + len(IBL_ROUGHS)], strict=True))
    diag = ibl_error_sources(maps["venice"], n, v, refs, environment("venice", None))
    print(diag)
    speed = ibl_speed(maps["venice"], 3 if quick else 9)
    print(speed)
    torch.set_num_threads(torch.get_num_threads())
    if images:
        ibl_images(maps["venice"])
    return (
        "## IBL specular: split sum, lobe table, sun extraction, importance sampling "
        "(venice_sunset_1k, "
        "pedestrian_overpass_1k)\n\n"
        f"Mean relative error of the specular of a white metal (f0 = 1, single scattering) "
        f"at {k} random (n, v) pairs (n.v spread over (0, 1]) against the brute-force "
        "integral of the GGX lobe over all 1024x512 texels (float64), on venice_sunset_1k "
        "(sunset; its sun carries ~3 % of the power) and pedestrian_overpass_1k (a clear "
        "sun with ~55 % of the power), both Poly Haven maps (CC0) at 1k, not shipped with "
        "the repository (without them the script skips this section). 2 % mean error is "
        "~40 dB. Time = `shade_ibl` (diffuse + specular) on a "
        f"{res}x{res} frame of random normals and views on venice, roughness 0.6, CPU time "
        "of 1 thread, median of 7, per megapixel; the prefiltered chain / mip pyramid / sun "
        "are built once per map and excluded. Brute force: the reference's own time a "
        f"pixel. Load average {os.getloadavg()[0]:.1f} during the run.\n\n"
        + table + "\n\n"
        "**Where the split sum's error comes from** (venice; the chain read at "
        "the same direction and roughness, compared with the chain's own kernel `D(c.h) "
        "(c.l)` summed exactly over every texel, and that exact kernel with the true lobe; "
        "per n.v range, mean % over the pairs in it):\n\n" + diag + "\n\n"
        "At roughness 0.3 the prefiltered chain itself is ~1 % (it was 2.9 % until "
        "2026-11-26, when the levels that have a grid of their own, the mid roughnesses, "
        "became exact quadratures, row-wise circular correlations by FFT "
        "(`_prefilter_rows`), instead of 32 importance samples a texel; the sharper levels "
        "are still importance-sampled). The total barely moved (venice 4.8 -> 4.7 %) and "
        "rose on overpass without sun extraction (17 -> 20 %): the chain's error had partly "
        "cancelled the lobe's; with the sun extracted it fell (7.6 -> 7.1 %). At 0.6 the "
        "chain is exact to 0.5 % and the whole error is the lobe shape: one isotropic "
        "`n = v` kernel, wherever it is centred and however wide, cannot follow the true "
        "lobe, which is stretched in the plane of incidence and cut by the horizon. It grows "
        "towards grazing views. Routes measured in scratch experiments and not kept (r = "
        "0.6, 64 pairs): a fit of 1 or 4 chain kernels (weights, directions in and out of "
        "the plane of incidence, one width) to each pair's true lobe by L1 (100 Adam steps, "
        "then decreasing slowly) left 27 % (one kernel) and 16 % (four) of the lobe's mass "
        "unmatched, so neither a "
        "(roughness, n.v) correction table nor a few taps of the chain can reach 2 %; "
        "sampling the lobe with filtered lookups of the GGX chain (the chain roughness from "
        "the sample's solid angle) instead of the box mips was no better than `importance` "
        "at any N (venice, N = 32: r = 0.6 8.3-11.9 % against 8.3 %, r = 0.3 4.1 % against "
        "3.0 %); the fitted split sum as a control variate for importance sampling (the "
        "samples estimate only lobe minus chain kernel) was no better either (venice r = "
        "0.6, N = 64: 5.6 % against 5.3 %; with the sun extracted 5.2 % against 4.7 %). The "
        "sun's texels are the other source: on pedestrian_overpass the split sum's error is "
        "mostly the sun. `Environment(sun_threshold=10)` splits it off "
        "(`extract_sun`: the texels within 0.1 rad of the brightest one that exceed 10x "
        "the mean radiance give their excess to one directional light, shaded per pixel "
        "with the exact GGX BRDF; chain and mips hold the residual): overpass error drops "
        "2-4x for every method, venice a little. It stays opt-in because `Environment."
        "specular` then reads the residual only (its other caller, SSR's miss fallback, "
        "would need the sun term added). Pole handling was not isolated on its own: the "
        "chain-vs-exact-kernel row bounds all the chain's resolution, quadrature and "
        "lat-long layout (poles included) contribute, ~1 % at 0.3 and 0.5 % at 0.6. Lobe "
        "shape and the split sum's separability are one error here (the kernel's mean "
        "radiance times the DFG albedo is exact whenever the kernel equals the normalised "
        "lobe): hence the table below, which tabulates the true lobe itself.\n\n"
        "**What reaches 40 dB: the lobe table, now the default** (`specular=\"table\"`, "
        "`torchraster/shading/ibl_table.py`). Instead of approximating the lobe by one "
        "isotropic kernel, it tabulates the exact single-scattering lobe `D V (n.l)`'s mean "
        "radiance per map: for the reflection direction R at the texel centres of a "
        "lat-long grid (`max(24, 4.4 / r^2)` rows), 8 nodes of acos(n.v) over [0, pi/2], 16 "
        "azimuths of the normal about R (measured in R's lat-long frame) and 8 roughness "
        "levels from 0.3 to 1. The yaw symmetry of the lat-long layout makes each output "
        "row a sum of circular correlations along the rows (real FFTs), and mirrored "
        "azimuths are conjugate transforms, so a map's table is built in ~0.5 s (column "
        "`table build`, 1 thread, venice 1k; built once per map and process, like the "
        "chain) and holds ~35 MB. A lookup is 8 bilinear points of one `grid_sample` "
        "(2 levels x 2 view nodes x 2 azimuths). Below roughness 0.3 it is the split sum "
        "plus the table's correction at 0.3, fading to the plain split sum at 0.2 (venice "
        "r = 0.25: 2.8 % against 3.8 % for the split sum alone). "
        f"Venice: {tab_err[0.3]:.2f} % at r = 0.3 and {tab_err[0.6]:.2f} % at r = 0.6 "
        f"(goal 2 %), {min(tab_err[r] for r in IBL_ROUGHS if r >= 0.3):.2f}-"
        f"{max(tab_err[r] for r in IBL_ROUGHS if r >= 0.3):.2f} % over 0.3-1. What is left "
        "is the interpolation between nodes (worst at grazing views and midway between "
        "levels) and the grid's resolution; the richer knob row shows the trade. On "
        "overpass the table still carries the sun's quantisation to the level's texels "
        "(a sun smaller than a texel of a 24-row grid); with `sun_threshold` the sun is "
        "exact and the table holds the residual. Time: on this benchmark's frame of "
        "random normals (every pixel reads a different part of the 35 MB atlas: cache "
        "misses) the table costs the `x split sum` column; on a rendered sphere (table "
        "below) it is ~1.5x the split sum's `shade_ibl` at one roughness and ~2x with "
        "per-pixel roughness U(0, 1) (the pixels below 0.3 also read the chain twice). "
        "The default's cost beside its accuracy: gradients w.r.t. the radiance work (the "
        "build is differentiable, linear in the map) but rebuild the table per "
        "optimisation step (~1 s); inverse rendering of the environment itself may prefer "
        "`specular=\"split_sum\"`. Importance sampling converges as ~1/sqrt(N) and stays "
        "tens of times the split sum's cost (its per-sample cost is a lat-long lookup of "
        "two mip levels; the 4x budget at N = 64 is out of reach for per-pixel sampling "
        "on the CPU); the table reaches lower error than N = 64 at ~2x.\n"
        "\n**Speed** (`shade_ibl`, 256x256, a sphere covering 60 % of "
        "the frame, roughness 0.45 (or uniform in [0, 1]), metallic 0.5, venice; CPU time "
        "of 1 thread, median of interleaved runs). `Environment.specular` reads the two "
        "chain levels around the lod as two points of one `grid_sample` over an atlas of "
        "the chain; `shade_ibl(mask=)` shades only the covered pixels (packed per batch "
        "item); before = torchraster/shading/ibl.py at "
        f"{BEFORE_REV} (the split sum with importance-sampled mid-roughness levels; the "
        "difference column of the split-sum rows is the chain's exact quadratures, up to "
        "~5 %, that of the table rows the table's change of the image):\n\n"
        + speed + "\n"
    )


def ibl_error_sources(env_t: torch.Tensor, n: torch.Tensor, v: torch.Tensor, refs: dict,
                      env: Environment) -> str:
    """Table: the split sum's error split into chain error and lobe-shape error."""
    from torchraster.shading.ibl import dominant_direction

    k = n.shape[0]
    nv = (n * v).sum(1)
    bins = ((0.0, 0.4), (0.4, 0.7), (0.7, 1.01))
    rows = []
    for r in (0.3, 0.6):
        rr = 2 * nv[:, None] * n - v
        one = torch.full((1, 1, 1, k), r, dtype=F64)
        dd = dominant_direction(n.T.reshape(1, 3, 1, k), rr.T.reshape(1, 3, 1, k), one)
        dd = dd[0, :, 0].T
        a, b = lookup_dfg(dfg_lut(16, 32), nv.view(1, 1, 1, k).float().clamp(1e-4, 1.0),
                          one.float())
        e = (a + b)[0, 0, 0].double()[:, None]
        exact = kernel_mean(env_t, dd, r) * e
        chain = env.specular(dd.T.reshape(1, 3, 1, k).float(), one.float())[0, :, 0].T
        chain = chain.double() * e
        ref = refs["venice", r]
        parts = [((chain - ref).abs() / ref).mean(1), ((chain - exact).abs() / exact).mean(1),
                 ((exact - ref).abs() / ref).mean(1)]
        for label, p in zip(("total (split sum)", "chain vs exact kernel",
                             "exact kernel vs true lobe"), parts, strict=True):
            rows.append([f"r = {r}", label, 100 * float(p.mean())]
                        + [100 * float(p[(nv >= lo) & (nv < hi)].mean()) for lo, hi in bins])
    counts = [int(((nv >= lo) & (nv < hi)).sum()) for lo, hi in bins]
    return markdown_table(["roughness", "part", "all (%)"]
                          + [f"n.v {lo}-{min(hi, 1.0)} ({c}) (%)"
                             for (lo, hi), c in zip(bins, counts, strict=True)], rows)


def ibl_speed(env_t: torch.Tensor, repeats: int) -> str:
    """Table: shade_ibl before (BEFORE_REV's ibl.py) and after, with and without mask."""
    import importlib.util
    import subprocess
    import tempfile

    src = subprocess.run(["git", "show", f"{BEFORE_REV}:torchraster/shading/ibl.py"],
                         cwd=ROOT, capture_output=True, text=True, check=True).stdout
    with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as f:
        f.write(src)
    spec_ = importlib.util.spec_from_file_location("ibl_before", f.name)
    old = importlib.util.module_from_spec(spec_)
    spec_.loader.exec_module(old)
    res = 256
    y, x = torch.meshgrid(torch.linspace(-1, 1, res), torch.linspace(-1, 1, res),
                          indexing="ij")
    mask = ((x * x + y * y) < 0.77)[None, None]
    nrm = torch.stack((x, y, torch.sqrt((1 - x * x - y * y).clamp_min(0)))) [None] * mask
    view = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(1, 3, res, res)
    alb, met, rough = (torch.full((1, c, res, res), val) * mask
                       for c, val in ((3, 0.7), (1, 0.5), (1, 0.45)))
    e_old, e_new = old.Environment(env_t), Environment(env_t)
    e_new.lobe_table_atlas  # noqa: B018 - built once, outside the timings
    mixed = torch.rand(1, 1, res, res, generator=torch.Generator().manual_seed(0)) * mask

    def new(specular: str, rough_map: torch.Tensor, masked: bool = True):  # noqa: ANN202
        return lambda: shade_ibl(nrm, view, alb, met, rough_map, None, e_new,
                                 specular=specular, mask=mask.float() if masked else None)

    calls = {
        "before": lambda: old.shade_ibl(nrm, view, alb, met, rough, None, e_old),
        "split sum, whole frame": new("split_sum", rough, masked=False),
        "split sum, mask=": new("split_sum", rough),
        "table (default), mask=": new("table", rough),
        "split sum, mask=, roughness U(0, 1)": new("split_sum", mixed),
        "table (default), mask=, roughness U(0, 1)": new("table", mixed),
    }
    times: dict[str, list[float]] = {key: [] for key in calls}
    with torch.no_grad():
        want = calls["before"]() * mask
        diffs = {key: float(((fn() * mask - want).abs() / want.abs().clamp_min(1e-3)).max())
                 if "U(0, 1)" not in key else "-" for key, fn in calls.items()}
        for _ in range(repeats):  # interleaved
            for key, fn in calls.items():
                t = time.thread_time()
                fn()
                times[key].append(time.thread_time() - t)
    t0 = float(np.median(times["before"]))
    rows = [[key, 1e3 * float(np.median(ts)), f"{float(np.median(ts)) / t0:.2f}", diffs[key]]
            for key, ts in times.items()]
    return markdown_table(["shade_ibl", "ms", "x before", "max rel. diff vs before "
                           "(covered pixels)"], rows)


def ibl_images(env_t: torch.Tensor) -> None:
    """Rough (0.8) white-metal spheres on the map box-filtered to 256x128 (so the brute
    force is quick): split sum at r | split sum, dominant direction | importance N = 16 |
    N = 64 | lobe table (the default) | brute force."""
    small = F.adaptive_avg_pool2d(env_t[None], (128, 256))[0]
    env = Environment(small)
    res = 64
    gb = sphere_gbuffer(res, 1.0, 0.8, albedo=(1.0, 1.0, 1.0))
    v = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(1, 3, res, res)
    nv = (gb.normal * v).sum(1, keepdim=True)
    rough = gb.roughness
    a, b = lookup_dfg(dfg_lut(16, 32), nv.clamp(1e-4, 1.0), rough)
    tiles = [env.specular(2 * nv * gb.normal - v, rough) * (a + b)]
    for kw in ({"specular": "split_sum"}, {"specular": "importance", "importance_samples": 16},
               {"specular": "importance", "importance_samples": 64}, {"specular": "table"}):
        tiles.append(shade_ibl(gb.normal, v, gb.albedo, gb.metallic, rough, None, env,
                               multiscatter=False, **kw))
    m = gb.mask[0, 0] > 0
    nn = gb.normal[0].reshape(3, -1).T[m.reshape(-1)].double()
    ref, _ = brute_specular(small, nn, torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand_as(nn),
                            0.8)
    brute = torch.zeros(1, 3, res, res)
    brute[0][:, m] = ref.T.float()
    tiles.append(brute)
    errs = [float(((t[0][:, m] - brute[0][:, m]).abs() / brute[0][:, m]).mean()) * 100
            for t in tiles[:-1]]
    print("picture errors vs brute force (%):", [round(e, 1) for e in errs])
    img = torch.cat([t * gb.mask for t in tiles], -1)
    img = img / (1 + img)  # Reinhard
    skio.imsave(IMAGES / "ibl_specular.png", to_srgb(img * 1.6), check_contrast=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer cases (smoke test)")
    ap.add_argument("--no-images", action="store_true")
    ap.add_argument("--only", choices=("energy", "ibl-specular"), default=None)
    args = ap.parse_args()
    t0 = time.perf_counter()
    if args.only in (None, "energy"):
        body = bench_energy(args.quick, not args.no_images)
        if not args.quick:
            update_section("energy", body)
    if args.only in (None, "ibl-specular"):
        body = bench_ibl_specular(args.quick, not args.no_images)
        if not args.quick:
            update_section("ibl-specular", body)
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
