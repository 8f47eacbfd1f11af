"""Cross-check :func:`torchraster.testing.reference_area.area_light_radiance` against Mitsuba 3.

Measures how closely our float64 brute-force area-light reference agrees with Mitsuba 3's
path tracer (direct light only) on a diffuse floor lit by one area light, offline:

* scene (metres, y up): a 4 m x 4 m Lambert floor (albedo 0.5, normal +y) at y = 0, centred
  at the origin; one one-sided area light of radiance 5 (RGB) centred at (0.3, 1.2, 0.1),
  normal ``normalize(0.2, -1, 0.1)`` (facing down, tilted): a 0.8 m x 0.5 m ``rectangle`` or
  a ``disk`` of radius 0.3 m; optionally a 0.4 m cube centred at (0, 0.5, 0) as an occluder;
* Mitsuba: orthographic camera at y = 0.9 m (below the light, so the light's back does not
  hide the floor; above the cube) looking straight down, 64 x 64 pixels covering
  x, z in [-2, 2], ``path`` integrator with ``max_depth = 2`` (direct light only),
  ``hide_emitters``, ``stratified`` sampler, ``hdrfilm`` with a ``box`` filter (a pixel is the
  average over its footprint);
* ours: the Lambert part only. Our reference always adds a dielectric specular (f0 = 0.04)
  at metallic 0, so it is run at albedo 0.5 and at albedo 0 (metallic 0, roughness 1) and
  the difference ``0.5 / pi * integral * Le`` is compared. Each pixel is the mean over a
  ``SUB x SUB`` grid of floor points inside its footprint; the floor point of each film
  position is taken from Mitsuba's own ``sensor.sample_ray`` (no pixel-convention guessing).
  In the cube run the cube's 12 triangles are the casters and the pixels that see the
  cube's top (not the floor) are excluded.

Light geometry: Mitsuba's rectangle / disk is ``[-1, 1]^2`` / the unit disc in its local
xy plane with normal +z, emitting towards +z. Its ``to_world`` is the matrix with columns
``(u, v, n, position)``, ``n = normalize(u x v)``, so the shape is exactly
``position + s u + t v`` and the emitting normal is ``u x v``, as in our convention.

Metrics (per run, over the compared pixels, on the mean of RGB):
``rel L1 = sum |mitsuba - ours| / sum ours``, ``max abs / max = max |mitsuba - ours| / max
ours``, ``bias = sum mitsuba / sum ours - 1`` (averages the Monte Carlo noise away: a
convention error shows up here). The Monte Carlo noise is measured by two Mitsuba renders
of the rectangle scene with different seeds (same metrics, one against the other; the
noise of one render against the truth is that divided by sqrt(2)).

Run (Mitsuba lives in its own venv, the project environment is untouched)::

    python3 -m venv /tmp/mi_check/venv
    /tmp/mi_check/venv/bin/pip install mitsuba==3.6.4 drjit==1.0.5 numpy
    python scripts/mitsuba_area_check.py [--spp 4096] [--samples 2304] [--sub 4]
        [--python /tmp/mi_check/venv/bin/python] [--out /tmp/mi_check]

The Mitsuba part runs in a subprocess (the venv's python on an inline script that writes
``.npy`` files to ``--out``); the reference runs in this process. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torchraster.testing.reference_area import area_light_radiance

CENTRE = (0.3, 1.2, 0.1)
NORMAL = (0.2, -1.0, 0.1)
RECT_HALF = (0.4, 0.25)
DISC_RADIUS = 0.3
RADIANCE = 5.0
ALBEDO = 0.5
CUBE_CENTRE = (0.0, 0.5, 0.0)
CUBE_HALF = 0.2
RES = 64
HALF_FLOOR = 2.0
#: Camera height: between the cube's top (0.7 m) and the light's lowest point (~1.1 m), so
#: the camera does not see the back of the light (it would hide the floor under it).
CAMERA_Y = 0.9

MITSUBA_SCRIPT = r'''
import json, sys, time
import numpy as np
import drjit as dr
import mitsuba as mi

cfg = json.loads(sys.argv[1])
mi.set_variant(cfg["variant"])
dr.set_thread_count(cfg["threads"])
out = cfg["out"]
T = mi.ScalarTransform4f


def light_to_world(c, u, v):
    n = np.cross(u, v)
    n = n / np.linalg.norm(n)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = u, v, n, c
    return T(m.tolist())


def scene_dict(shape, u, v, cube, seed_unused=0):
    res, half = cfg["res"], cfg["half_floor"]
    d = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 2, "hide_emitters": True},
        "sensor": {
            "type": "orthographic",
            "to_world": T().look_at(origin=[0, cfg["camera_y"], 0], target=[0, 0, 0], up=[0, 0, 1])
            @ T().scale([half, half, 1]),
            "film": {"type": "hdrfilm", "width": res, "height": res,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "stratified", "sample_count": cfg["spp"]},
        },
        # columns (2,0,0), (0,0,-2), (0,1,0): [-1,1]^2 -> x,z in [-2,2] at y = 0, normal +y
        "floor": {"type": "rectangle",
                  "to_world": T([[half, 0, 0, 0], [0, 0, 1, 0], [0, -half, 0, 0],
                                 [0, 0, 0, 1]]),
                  "bsdf": {"type": "diffuse",
                           "reflectance": {"type": "rgb", "value": [cfg["albedo"]] * 3}}},
        "light": {"type": shape, "to_world": light_to_world(cfg["centre"], u, v),
                  "emitter": {"type": "area",
                              "radiance": {"type": "rgb", "value": [cfg["radiance"]] * 3}}},
    }
    if cube:
        h = cfg["cube_half"]
        d["cube"] = {"type": "cube",
                     "to_world": T().translate(cfg["cube_centre"]) @ T().scale([h, h, h]),
                     "bsdf": {"type": "diffuse"}}
    return d


runs = {
    "rect": ("rectangle", cfg["rect_u"], cfg["rect_v"], False, 1),
    "rect_seed2": ("rectangle", cfg["rect_u"], cfg["rect_v"], False, 2),
    "rect_cube": ("rectangle", cfg["rect_u"], cfg["rect_v"], True, 1),
    "disc": ("disk", cfg["disc_u"], cfg["disc_v"], False, 1),
}
times = {}
scene = None
for name, (shape, u, v, cube, seed) in runs.items():
    scene = mi.load_dict(scene_dict(shape, np.array(u), np.array(v), cube))
    t0 = time.time()
    img = np.array(mi.render(scene, seed=seed), dtype=np.float64)
    times[name] = time.time() - t0
    np.save(f"{out}/mi_{name}.npy", img)

# floor point of each film position (x = column, y = row, in [0, 1]) from the sensor itself
sensor = scene.sensors()[0]
res, sub = cfg["res"], cfg["sub"]
f = (np.arange(res * sub) + 0.5) / (res * sub)
fy, fx = np.meshgrid(f, f, indexing="ij")
pts = np.zeros((res * sub, res * sub, 3))
if cfg["variant"].startswith("scalar"):
    for i in range(res * sub):
        for j in range(res * sub):
            ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(fx[i, j], fy[i, j]),
                                       mi.Point2f(0.5, 0.5))
            o, d = np.array(ray.o), np.array(ray.d)
            pts[i, j] = o - o[1] / d[1] * d
else:
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(fx.ravel(), fy.ravel()),
                               mi.Point2f(0.5, 0.5))
    o, d = np.array(ray.o).T, np.array(ray.d).T
    if o.shape[0] != fx.size:
        o, d = o.T, d.T
    pts = (o - (o[:, 1:2] / d[:, 1:2]) * d).reshape(res * sub, res * sub, 3)
np.save(f"{out}/floor_points.npy", pts)
json.dump({"version": mi.__version__, "drjit": dr.__version__, "times": times},
          open(f"{out}/mi_info.json", "w"))
'''


def light_axes(half_u: float, half_v: float) -> tuple[np.ndarray, np.ndarray]:
    """Half-extent vectors ``u``, ``v`` with ``normalize(u x v) = normalize(NORMAL)``."""
    n = np.array(NORMAL) / np.linalg.norm(NORMAL)
    a = np.array([1.0, 0.0, 0.0]) - n[0] * n
    a /= np.linalg.norm(a)
    b = np.cross(n, a)  # a x (n x a) = n
    return half_u * a, half_v * b


def cube_mesh() -> tuple[torch.Tensor, torch.Tensor]:
    """The occluder's 12 triangles ``(positions (8, 3), faces (12, 3))``."""
    c = np.array(CUBE_CENTRE)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    pos = c + CUBE_HALF * corners
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4),
             (1, 5, 7, 3)]
    faces = [f for q in quads for f in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))]
    return torch.tensor(pos, dtype=torch.float64), torch.tensor(faces, dtype=torch.int64)


def reference(points: np.ndarray, u: np.ndarray, v: np.ndarray, disc: bool, casters,
              samples: int, sub: int) -> np.ndarray:
    """Lambert part ``(res, res)`` (mean of RGB) averaged over each pixel's sub-grid."""
    x = torch.tensor(points.reshape(-1, 3), dtype=torch.float64)
    count = x.shape[0]
    pts = torch.cat([x, x])
    normals = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand_as(pts)
    albedo = torch.zeros(2 * count, 3, dtype=torch.float64)
    albedo[:count] = ALBEDO
    zeros = torch.zeros(2 * count, dtype=torch.float64)
    out = area_light_radiance(pts, normals, (0.0, 10.0, 0.0), albedo, zeros, zeros + 1.0,
                              position=CENTRE, u=u, v=v, radiance=(RADIANCE,) * 3,
                              disc=disc, casters=casters, samples=samples)
    lam = (out[:count] - out[count:]).mean(-1).numpy()
    n = points.shape[0] // sub
    return lam.reshape(n, sub, n, sub).mean(axis=(1, 3))


def metrics(mi_img: np.ndarray, ours: np.ndarray, mask: np.ndarray) -> tuple[float, ...]:
    a, b = mi_img[mask], ours[mask]
    return (np.abs(a - b).sum() / b.sum(), np.abs(a - b).max() / b.max(),
            a.sum() / b.sum() - 1.0)


def main() -> None:
    torch.set_num_threads(1)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--python", default="/tmp/mi_check/venv/bin/python")
    ap.add_argument("--out", default="/tmp/mi_check")
    ap.add_argument("--variant", default="scalar_rgb")
    ap.add_argument("--spp", type=int, default=4096)
    ap.add_argument("--samples", type=int, default=48 * 48)
    ap.add_argument("--sub", type=int, default=4)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--skip-render", action="store_true", help="reuse the .npy files")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ru, rv = light_axes(*RECT_HALF)
    du, dv = light_axes(DISC_RADIUS, DISC_RADIUS)
    cfg = {"variant": args.variant, "threads": args.threads, "out": str(out), "res": RES,
           "half_floor": HALF_FLOOR, "camera_y": CAMERA_Y, "spp": args.spp, "sub": args.sub,
           "albedo": ALBEDO,
           "radiance": RADIANCE, "centre": list(CENTRE), "cube_centre": list(CUBE_CENTRE),
           "cube_half": CUBE_HALF, "rect_u": ru.tolist(), "rect_v": rv.tolist(),
           "disc_u": du.tolist(), "disc_v": dv.tolist()}
    for lu, lv in ((ru, rv), (du, dv)):
        low = min(CENTRE[1] + a * lu[1] + b * lv[1] for a in (-1, 1) for b in (-1, 1))
        assert CUBE_CENTRE[1] + CUBE_HALF < CAMERA_Y < low, (CAMERA_Y, low)
    t0 = time.time()
    if not args.skip_render:
        subprocess.run([args.python, "-c", MITSUBA_SCRIPT, json.dumps(cfg)], check=True)
    t_mi = time.time() - t0
    info = json.loads((out / "mi_info.json").read_text())
    pts = np.load(out / "floor_points.npy")
    # sanity: the sensor's footprint is the expected axis-aligned grid
    span = pts[..., [0, 2]].reshape(-1, 2)
    print(f"floor points: x [{span[:, 0].min():.4f}, {span[:, 0].max():.4f}], "
          f"z [{span[:, 1].min():.4f}, {span[:, 1].max():.4f}], |y| max "
          f"{np.abs(pts[..., 1]).max():.2e}; pixel (0,0) centre "
          f"{pts[:args.sub, :args.sub].reshape(-1, 3).mean(0).round(4).tolist()}",
          file=sys.stderr)
    img = {k: np.load(out / f"mi_{k}.npy").mean(-1)
           for k in ("rect", "rect_seed2", "rect_cube", "disc")}
    # pixels that see the cube's top instead of the floor (footprint overlaps it + margin)
    centres = pts.reshape(RES, args.sub, RES, args.sub, 3).mean(axis=(1, 3))
    pix = 2 * HALF_FLOOR / RES
    lim = CUBE_HALF + pix
    cube_mask = ~((np.abs(centres[..., 0] - CUBE_CENTRE[0]) < lim)
                  & (np.abs(centres[..., 2] - CUBE_CENTRE[2]) < lim))
    full = np.ones((RES, RES), bool)
    t1 = time.time()
    ours = {
        "rect": reference(pts, ru, rv, False, None,
                          args.samples, args.sub),
        "rect_cube": reference(pts, ru, rv, False, cube_mesh(), args.samples, args.sub),
        "disc": reference(pts, du, dv, True, None, args.samples, args.sub),
    }
    t_ref = time.time() - t1
    np.savez(out / "ours.npz", **ours)
    rows = [
        ("rectangle, unoccluded", metrics(img["rect"], ours["rect"], full)),
        ("rectangle + cube occluder", metrics(img["rect_cube"], ours["rect_cube"], cube_mask)),
        ("disc, unoccluded", metrics(img["disc"], ours["disc"], full)),
        ("MC noise: rect seed 1 vs seed 2", metrics(img["rect"], img["rect_seed2"], full)),
    ]
    print(f"Mitsuba {info['version']} (drjit {info['drjit']}, {args.variant}, "
          f"{args.threads} thread(s)), {args.spp} spp stratified, {RES}x{RES} px; ours: "
          f"{math.ceil(math.sqrt(args.samples)) ** 2} light samples, {args.sub}x{args.sub} "
          f"points per pixel. Mitsuba {t_mi:.0f} s "
          f"({', '.join(f'{k} {v:.1f}' for k, v in info['times'].items())}), "
          f"reference {t_ref:.0f} s. Cube run: {int((~cube_mask).sum())} px excluded.\n")
    print("| run | rel L1 (sum abs diff / sum ours) | max abs diff / max | bias (sum ratio - 1) |")
    print("|---|---|---|---|")
    for name, (l1, mx, bias) in rows:
        print(f"| {name} | {l1:.2%} | {mx:.2%} | {bias:+.3%} |")


if __name__ == "__main__":
    main()
