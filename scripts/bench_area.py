"""Area lights: run time against error, against the float64 brute-force reference.

A stage (a 4 m floor, a box and a metal sphere) under one area light (a 0.8 x 0.5 m panel
or a disc of radius 0.3 m), rendered by ``tr.Renderer`` (pbr, single scattering: the
reference has none), and by :func:`torchraster.testing.reference_area.area_light_radiance`
at the renderer's own G-buffer (positions, normals, materials: the comparison is of the
lighting only), with ray-traced shadows. Rows:

* the knobs: shadow-map size and PCSS taps (from the light's centre with the light's own
  size) and :data:`~torchraster.shading.area.DISC_SIDES` (the polygon a disc is shaded as);
* the cost: ``Renderer`` forward and forward + backward with one area light against one
  point light (same frame), and the shading pass alone.

Writes section ``area`` of docs/benchmarks.md and ``docs/images/area_lights.png`` (ours,
reference, 8x difference).

    python scripts/bench_area.py [--res 160] [--samples 24] [--repeats 5]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh
from benchmd import markdown_table, median_time, update_section

import torchraster as tr
from torchraster.shading import area as area_module
from torchraster.testing import raytrace
from torchraster.testing.reference_area import area_light_radiance

F64 = torch.float64
ROOT = Path(__file__).resolve().parent.parent
EYE = (0.0, 2.6, 2.6)
TARGET = (0.0, 0.2, 0.0)
LIGHTS = {
    "rect": {"position": (0.4, 1.7, 0.3), "direction": (-0.25, -1.0, -0.1), "size": (0.8, 0.5),
             "disc": False},
    "disc": {"position": (0.4, 1.7, 0.3), "direction": (-0.25, -1.0, -0.1), "size": (0.6, 0.6),
             "disc": True},
}
RADIANCE = 6.0


def stage():
    """positions (V, 3), faces (F, 3), cast (F,), face_material (F,), materials."""
    box = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.35)
    casters = [(torch.tensor(box.vertices) + torch.tensor([-0.6, 0.25, 0.1]),
                torch.tensor(box.faces)),
               (torch.tensor(ball.vertices) + torch.tensor([0.45, 0.35, -0.35]),
                torch.tensor(ball.faces))]
    positions, faces, cast = raytrace.ground_scene(casters, 4.0)
    n_box, n_ball = len(box.faces), len(ball.faces)
    face_material = torch.cat([torch.zeros(n_box, dtype=torch.int64),
                               torch.ones(n_ball, dtype=torch.int64),
                               torch.full((2,), 2, dtype=torch.int64)])
    materials = [tr.Material(base_color_factor=(0.7, 0.3, 0.2, 1.0), metallic_factor=0.0,
                             roughness_factor=0.6),
                 tr.Material(base_color_factor=(0.95, 0.8, 0.5, 1.0), metallic_factor=1.0,
                             roughness_factor=0.35),
                 tr.Material(base_color_factor=(0.8, 0.8, 0.8, 1.0), metallic_factor=0.0,
                             roughness_factor=0.8)]
    return positions, faces, cast, face_material, materials


def area_lights(spec: dict, cast: bool, settings=None, dtype=torch.float32) -> tr.Lights:
    u, v = tr.area_light_axes(torch.tensor(spec["direction"]), torch.tensor(spec["size"][0]),
                              torch.tensor(spec["size"][1]))
    return tr.Lights(area=tr.AreaLights(
        position=torch.tensor(spec["position"], dtype=dtype).view(1, 1, 3),
        u=u.to(dtype).view(1, 1, 3), v=v.to(dtype).view(1, 1, 3),
        color=torch.ones(1, 1, 3, dtype=dtype), intensity=torch.full((1, 1), RADIANCE,
                                                                     dtype=dtype),
        disc=torch.tensor([[spec["disc"]]]), cast_shadows=torch.tensor([[cast]]),
        shadow=settings))


def camera(res: int):
    view = tr.camera.look_at(torch.tensor([EYE]), torch.tensor([TARGET]))
    return view, tr.camera.perspective(50.0, 1.0, 0.1)


def render(res: int, lights: tr.Lights, channels=()):
    positions, faces, cast, face_material, materials = stage()
    scene = tr.RenderScene(positions.float(), faces, face_material=face_material,
                           materials=materials, cast_shadows=cast)
    view, proj = camera(res)
    renderer = tr.Renderer(res, shading=tr.ShadingSettings("pbr", multiscatter=False))
    return renderer, scene, view, proj, renderer(scene, view, proj, lights, channels=channels)


def reference(out, spec: dict, samples: int, shadows: bool = True) -> torch.Tensor:
    """(3, H, W) float64 reference radiance at ``out``'s G-buffer (0 where empty), with
    ray-traced shadows of the box and the sphere (``shadows``) or none."""
    positions, faces, cast, _, _ = stage()
    g = out.gbuffer
    covered = (out.alpha[0, 0] > 0).reshape(-1)
    idx = covered.nonzero().squeeze(1)

    def take(name: str) -> torch.Tensor:
        t = g[name][0].double()
        return t.reshape(t.shape[0], -1)[:, idx].T

    u, v = tr.area_light_axes(torch.tensor(spec["direction"], dtype=F64),
                              torch.tensor(spec["size"][0], dtype=F64),
                              torch.tensor(spec["size"][1], dtype=F64))
    rad = area_light_radiance(
        take("position"), take("normal"), torch.tensor(EYE, dtype=F64), take("albedo"),
        take("metallic")[:, 0], take("roughness")[:, 0],
        position=torch.tensor(spec["position"], dtype=F64), u=u, v=v,
        radiance=torch.full((3,), RADIANCE, dtype=F64), disc=spec["disc"],
        casters=(positions, faces[cast]) if shadows else None, samples=samples)
    h, w = out.alpha.shape[-2:]
    img = torch.zeros(3, h * w, dtype=F64)
    img[:, idx] = rad.T
    return img.view(3, h, w)


def errors(ours: torch.Tensor, ref: torch.Tensor) -> tuple[float, float]:
    """(mean relative error |ours - ref| / mean ref over the image, PSNR dB with the
    reference's 99.5th percentile as peak)."""
    ours = ours.double()
    rel = float((ours - ref).abs().mean() / ref.abs().mean())
    peak = float(torch.quantile(ref.flatten(), 0.995))
    mse = float(((ours - ref) ** 2).mean())
    return rel, 10 * math.log10(peak * peak / max(mse, 1e-30))


def save_picture(ours: torch.Tensor, ref: torch.Tensor, path: Path) -> None:
    from skimage.io import imsave

    def tone(x: torch.Tensor) -> np.ndarray:
        x = 2.0 * x  # exposure
        x = (x / (1 + x)).clamp(0, 1) ** (1 / 2.2)
        return (x.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)

    diff = ((ours.double() - ref).abs() * 8).float()
    row = np.concatenate([tone(ours.float()), tone(ref.float()), tone(diff)], 1)
    path.parent.mkdir(parents=True, exist_ok=True)
    imsave(path, row, check_contrast=False)


def disc_polygon_rows() -> list[list[object]]:
    """The form factor of a disc (radius 1, facing -z) shaded as a k-gon of its area
    against the exact disc's (quadrature, 200² samples) at 200 receivers 0.05-3 radii
    below it (lateral offsets up to 1.5 radii, normals tilted at random): largest and mean
    |error| relative to the largest and mean form factor."""
    from torchraster.shading.ltc import form_factor_components, frame_rows
    from torchraster.testing.reference_area import form_factor_reference

    u, v = torch.tensor([1.0, 0, 0], dtype=F64), torch.tensor([0.0, -1, 0], dtype=F64)
    gen = torch.Generator().manual_seed(0)
    rows = []
    default_sides = area_module.DISC_SIDES
    for h in (0.05, 0.2, 0.5, 1.0, 3.0):
        n = 200
        pts = torch.cat([(torch.rand(n, 2, generator=gen, dtype=F64) * 2 - 1) * 1.5,
                         torch.full((n, 1), -h, dtype=F64)], 1)
        nrm = torch.tensor([0, 0, 1.0], dtype=F64) + 0.5 * torch.randn(n, 3, generator=gen,
                                                                       dtype=F64)
        nrm = nrm / nrm.norm(dim=1, keepdim=True)
        ref = form_factor_reference(pts, nrm, torch.zeros(3, dtype=F64), u, v, disc=True,
                                    samples=200 ** 2)
        frame = frame_rows(nrm.T.unbind(0), (nrm.T + 0.3).unbind(0))
        row: list[object] = [f"{h:g}"]
        for k in (8, 16, 32):
            area_module.DISC_SIDES = k
            try:
                lights = tr.AreaLights(position=torch.zeros(1, 1, 3, dtype=F64),
                                       u=u.view(1, 1, 3), v=v.view(1, 1, 3),
                                       color=torch.ones(1, 1, 3, dtype=F64),
                                       intensity=torch.ones(1, 1, dtype=F64),
                                       disc=torch.tensor([[True]]))
                corners = area_module.polygon_corners(lights, 0)[0]  # (k, 3)
            finally:
                area_module.DISC_SIDES = default_sides
            rel = corners[:, None, :] - pts[None]  # (k, n, 3)
            x, y, z = (r[0] * rel[..., 0] + r[1] * rel[..., 1] + r[2] * rel[..., 2]
                       for r in frame)
            err = (form_factor_components(x, y, z, dim=0) - ref).abs()
            row += [float(err.max() / ref.abs().max()), float(err.mean() / ref.abs().mean())]
        rows.append(row)
    return rows


def fog_source_rows() -> list[list[object]]:
    """What lights a fog sample, ``sum_lights p(l . v) E`` of an area light: ours (the
    exact solid angle, the Henyey-Greenstein phase towards the centre) against the
    quadrature of ``L p(l_s . v) cos_light dA / d^2`` over the light (400² cells), at 400
    random samples 0.1-3 m from the 0.8 x 0.5 m panel on its emitting side, random unit view
    directions: mean and largest relative error per anisotropy g."""
    from torchraster.shading.area import area_incidence
    from torchraster.shading.volumetric import hg_phase
    from torchraster.testing.reference_area import light_samples

    spec = LIGHTS["rect"]
    lights = area_lights(spec, cast=False, dtype=F64)
    part = lights.area
    gen = torch.Generator().manual_seed(0)
    n = 400
    normal = torch.linalg.cross(part.u[0, 0], part.v[0, 0])
    normal = normal / normal.norm()
    dirs = torch.randn(n, 3, generator=gen, dtype=F64)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    dirs = torch.where((dirs @ normal)[:, None] < 0, -dirs, dirs)  # the emitting side
    dist = 0.1 + 2.9 * torch.rand(n, 1, generator=gen, dtype=F64)
    pts = part.position[0, 0] + dirs * dist
    view = torch.randn(n, 3, generator=gen, dtype=F64)
    view = view / view.norm(dim=1, keepdim=True)
    y, d_a, n_l = light_samples(part.position[0, 0], part.u[0, 0], part.v[0, 0],
                                samples=400 ** 2)
    to = y[None] - pts[:, None]
    d2 = (to * to).sum(-1)
    cos_s = (to * view[:, None]).sum(-1) / d2.sqrt()
    w = (-(to * n_l).sum(-1) / d2.sqrt()).clamp_min(0) * d_a / d2
    l, e, mu = area_incidence(part, pts.T.reshape(1, 3, 1, n))
    l, e, mu = l[0, 0, :, 0].T, e[0, 0, 0, 0], mu[0, 0, 0, 0]
    to_centre = part.position[0, 0] - pts
    to_centre = to_centre / to_centre.norm(dim=1, keepdim=True)
    rows = []
    for g in (0.0, 0.3, 0.6, 0.9):
        ref = RADIANCE * (hg_phase(cos_s, g) * w).sum(1)
        row: list[object] = [f"{g:g}"]
        for ours in (hg_phase((to_centre * view).sum(1), g) * e,  # towards the centre
                     hg_phase((l * view).sum(1), g * mu) * e):  # mean direction, spread
            rel = (ours - ref).abs() / ref
            row += [float(rel.mean()), float(rel.max()),
                    float((ours - ref).abs().sum() / ref.sum())]
        rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--res", type=int, default=160)
    parser.add_argument("--samples", type=int, default=24 ** 2)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)
    res = args.res
    t0 = time.perf_counter()
    rows = []
    refs = {}
    channels = {"position", "normal", "albedo", "metallic", "roughness"}
    for name, spec in LIGHTS.items():
        with torch.no_grad():
            *_, out = render(res, area_lights(spec, cast=True), channels)
        refs[name] = reference(out, spec, args.samples)
        print(name, "reference done", f"{time.perf_counter() - t0:.0f} s", flush=True)
        knobs = [("shadows off (unshadowed image)", False, None, None)]
        if spec["disc"]:  # the polygon of the disc, against the unshadowed reference
            knobs += [(f"shadows off, disc as {k}-gon", False, None, k) for k in (8, 32)]
        knobs += [(f"shadow map {s}, PCSS {taps} taps{' (default)' * ((s, taps) == (1024, 16))}",
                   True, tr.ShadowSettings(map_size=s, filter="pcss", pcf_taps=taps), None)
                  for s, taps in ((256, 16), (512, 16), (1024, 4), (1024, 16), (1024, 32))]
        for label, cast, settings, sides in knobs:
            default_sides = area_module.DISC_SIDES
            if sides is not None:
                area_module.DISC_SIDES = sides
            try:
                lights = area_lights(spec, cast, settings)
                renderer, scene, view, proj, out = render(res, lights, channels)
                with torch.no_grad():
                    ms = 1e3 * median_time(lambda: renderer(scene, view, proj, lights),  # noqa: B023
                                           args.repeats)
                    image = renderer(scene, view, proj, lights).image[0]
            finally:
                area_module.DISC_SIDES = default_sides
            if not cast:  # against the unshadowed reference
                ref = reference(out, spec, args.samples, shadows=False)
            else:
                ref = refs[name]
            rel, psnr = errors(image, ref)
            rows.append([name, label, ms, 100 * rel, psnr])
            print(rows[-1], flush=True)
            if name == "rect" and label.endswith("(default)"):
                save_picture(image, ref, ROOT / "docs" / "images" / "area_lights.png")
    # cost against a point light of the same frame
    cost = []
    spec = LIGHTS["rect"]
    point = tr.Lights(point=tr.PointLights(
        position=torch.tensor(spec["position"]).view(1, 1, 3), color=torch.ones(1, 1, 3),
        intensity=torch.full((1, 1), RADIANCE * 0.4)))
    for size in (256, 512):
        for shadows in (False, True):
            row = [f"{size}²", "on" if shadows else "off"]
            for mode in ("fwd", "fwd+bwd"):
                pair = []
                for lights in (area_lights(spec, shadows, None), point):
                    if lights.point is not None:
                        lights.point.cast_shadows = torch.tensor([[shadows]])
                    positions, faces, cast, fm, mats = stage()
                    pos = positions.float().requires_grad_(mode == "fwd+bwd")
                    scene = tr.RenderScene(pos, faces, face_material=fm, materials=mats,
                                           cast_shadows=cast)
                    view, proj = camera(size)
                    renderer = tr.Renderer(size)

                    def run(renderer=renderer, scene=scene, view=view, proj=proj,
                            lights=lights, mode=mode, pos=pos):
                        if mode == "fwd":
                            with torch.no_grad():
                                renderer(scene, view, proj, lights)
                        else:
                            renderer(scene, view, proj, lights).image.sum().backward()
                            pos.grad = None

                    pair.append(run)
                turns = [[], []]
                for fn in pair:
                    fn()
                for _ in range(args.repeats):
                    for k, fn in enumerate(pair):
                        t = time.perf_counter()
                        fn()
                        turns[k].append(time.perf_counter() - t)
                a, p = statistics.median(turns[0]), statistics.median(turns[1])
                ratio = statistics.median(x / y for x, y in zip(*turns, strict=True))
                row += [1e3 * a, 1e3 * p, ratio]
            cost.append(row)
            print(row, flush=True)
    disc_rows = disc_polygon_rows()
    fog_rows = fog_source_rows()
    total = time.perf_counter() - t0
    body = (
        f"## Area lights: linearly transformed cosines and PCSS against the brute-force "
        f"reference ({total:.0f} s)\n\n"
        "A 4 m floor (dielectric, roughness 0.8), a box (roughness 0.6) and a metal sphere "
        f"(roughness 0.35) under one area light of radiance {RADIANCE:g}: a 0.8 x 0.5 m panel "
        "or a disc of radius 0.3 m, 1.5 m above, tilted. *Ours*: `tr.Renderer` pbr with energy "
        f"compensation off, {res}² pixels. *Reference*: "
        "`torchraster.testing.reference_area.area_light_radiance` at the renderer's own "
        f"G-buffer (so the lighting alone is compared): {args.samples} stratified samples "
        "over the light per pixel, exact GGX / Smith / Schlick and Lambert in float64, "
        "shadows by ray tracing against the box and the sphere. Error: mean |ours - ref| over "
        "mean ref, and PSNR with the reference's 99.5th percentile as the peak. Time: "
        f"median of {args.repeats} forward renders (no grad), 1 thread.\n\n"
        + markdown_table(["light", "setting", "ms / frame", "mean error %", "PSNR dB"], rows)
        + "\n\nWhat remains is the LTC's lobe shape (section ltc: a few % where the light "
        "holds the lobe, tens of % in its tails) and the PCSS penumbra, estimated from the "
        "light's centre with a disc of the light's area (a long panel's penumbra is "
        "isotropic here). ![ours, reference, 8x difference](images/area_lights.png)\n\n"
        "**The disc's polygon** (`DISC_SIDES`, default 16; the time of each is in the rows "
        "above): the form factor of a disc of radius 1 shaded as the k-gon of its area "
        "against the exact disc (quadrature) at 200 receivers h radii below it (lateral "
        "offsets up to 1.5 radii, normals tilted at random), |error| relative to the largest "
        "and to the mean form factor:\n\n"
        + markdown_table(["h / radius", "8: max", "8: mean", "16: max", "16: mean", "32: max",
                          "32: mean"], disc_rows)
        + "\n\n**Fog** (`Renderer(fog=...)`): a fog sample receives the light's radiance "
        "times the solid angle of its polygon from the sample's side (exact) and a "
        "Henyey-Greenstein phase (exact for g = 0). That source "
        "against the quadrature of the phase over the light (400² cells), at 400 samples "
        "0.1-3 m from the panel (random directions on its emitting side, random view "
        "directions):\n\n"
        + markdown_table(["g", "centre: mean rel. error", "centre: max", "centre: sum |error| "
                          "/ sum", "used: mean rel. error", "used: max",
                          "used: sum |error| / sum"], fog_rows)
        + "\n\n*centre*: the phase towards the light's centre; *used* (what the renderer "
        "does): towards its mean direction, with the anisotropy times the mean cosine of its "
        "directions about it (`area_incidence`)."
        + "\n\n**Cost against a point light** (the same stage and camera, `tr.Renderer` defaults "
        "(energy compensation on), one light; in turns in one process, median of the "
        "per-turn ratios; shadows: the area light's PCSS cube map against the point "
        "light's default PCF cube map):\n\n"
        + markdown_table(["frame", "shadows", "area fwd ms", "point fwd ms", "fwd ratio",
                          "area fwd+bwd ms", "point fwd+bwd ms", "fwd+bwd ratio"], cost)
        + "\n\nWith shadows, forward + backward costs 4-5x the point light's: the area "
        "light's 16-tap PCSS (a blocker search and the filter, with gradients to the light) "
        "against the point light's 4-tap PCF; `ShadowSettings(pcf_taps=4)` on the light "
        "trades that for the 4-tap row's error above.")
    update_section("area", body)
    print(body)


if __name__ == "__main__":
    sys.exit(main())
