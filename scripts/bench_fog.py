"""Volumetric fog: run time against error of the light-shaft march, against a brute-force
many-step float64 march.

Scene: a closed room (4 x 2.5 x 4 m) lit only through a window with a cross-shaped frame
by a low sun that casts shadows, plus a spot light on the ceiling (shadowed); homogeneous
fog with a little height falloff, forward scattering (g = 0.5). The reference is
:func:`torchraster.testing.reference_fog.march_reference` (512 midpoint steps, float64,
numerically integrated transmittance) with the engine's light source (the shadow-map lookup
of a fog sample: what is measured is the march, not the shadow maps). Rows: steps 4-64,
without jitter (midpoints), with jitter, with jitter and the depth-aware blur; the error is
the mean absolute error of the in-scattered radiance relative to its mean (over the
image), and the time the whole fog pass (``apply_fog``), median of repeats.

    python scripts/bench_fog.py [--quick] [--picture] [--light-path]

``--light-path`` writes section ``fog-light-path``: an open floor under height fog lit by a
sun and a point light, the whole linear image with the light path (``Fog(light_transmittance
=True)``) and without against a float64 brute-force reference whose light paths are
numerically integrated (surfaces and every fog sample), the frame time of both, and what
the in-scattering of an environment map and of an emissive panel would add (their share of
the image when left out).

``--picture`` renders docs/images/fog_godrays.png (god rays through the window).
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from pathlib import Path

import numpy as np
import torch
import trimesh
from benchmd import markdown_table, update_section
from PIL import Image

import torchraster as tr
from torchraster.renderer import camera_position, view_rays
from torchraster.shading.volumetric import (
    Fog,
    ambient_inscatter,
    apply_fog,
    depth_aware_blur,
    fog_terms,
    light_source,
    marched_lights,
)
from torchraster.testing import reference_fog

IMAGES = Path(__file__).resolve().parent.parent / "docs" / "images"
SUN = (1.0, -0.55, 0.35)
FOG = dict(density=0.12, height_falloff=0.15, base_height=0.0, color=(1.0, 0.97, 0.92),
           anisotropy=0.5)


def room() -> tr.RenderScene:
    """A closed box room; the -x wall has a window (1.6 x 1.2 m) split by a cross."""
    t = 0.1  # wall thickness
    parts = [((4 + 2 * t, t, 4 + 2 * t), (0, -t / 2, 0)),  # floor
             ((4 + 2 * t, t, 4 + 2 * t), (0, 2.5 + t / 2, 0)),  # ceiling
             ((t, 2.5, 4), (2 + t / 2, 1.25, 0)),  # +x wall
             ((4, 2.5, t), (0, 1.25, -2 - t / 2)), ((4, 2.5, t), (0, 1.25, 2 + t / 2))]
    # -x wall around the window y in [0.9, 2.1], z in [-1.0, 0.6], frame bars 0.08 m
    x = -2 - t / 2
    parts += [((t, 0.9, 4), (x, 0.45, 0)), ((t, 0.4, 4), (x, 2.3, 0)),
              ((t, 1.2, 1.0), (x, 1.5, -1.5)), ((t, 1.2, 1.4), (x, 1.5, 1.3)),
              ((t, 1.2, 0.08), (x, 1.5, -0.2)), ((t, 0.08, 1.6), (x, 1.5, -0.2))]
    boxes = []
    for ext, centre in parts:
        b = trimesh.creation.box(extents=ext)
        b.apply_translation(centre)
        b.unmerge_vertices()
        boxes.append(b)
    m = trimesh.util.concatenate(boxes)
    pos = torch.tensor(np.asarray(m.vertices), dtype=torch.float32)
    faces = torch.tensor(np.asarray(m.faces), dtype=torch.int64)
    normals = torch.zeros_like(pos)
    normals[faces.flatten()] = torch.tensor(np.asarray(m.face_normals),
                                            dtype=torch.float32).repeat_interleave(3, 0)
    mat = tr.Material(base_color_factor=(0.75, 0.72, 0.68, 1.0), roughness_factor=0.9)
    return tr.RenderScene.from_mesh(tr.Mesh(pos, faces, normals=normals, material=mat))


def lights(map_size: int = 1024, spot: bool = True) -> tr.Lights:
    from torchraster.shading.shadows import ShadowSettings

    st = ShadowSettings(map_size=map_size)
    sun = tr.DirectionalLights(direction=torch.tensor([[SUN]]),
                               color=torch.tensor([[[1.0, 0.9, 0.75]]]),
                               intensity=torch.tensor([[6.0]]),
                               cast_shadows=torch.tensor([[True]]), shadow=st)
    sp = None
    if spot:
        sp = tr.SpotLights(position=torch.tensor([[[0.2, 2.45, -1.3]]]),
                           direction=torch.tensor([[[0.0, -1.0, 0.0]]]),
                           color=torch.tensor([[[0.5, 0.7, 1.0]]]),
                           intensity=torch.tensor([[3.0]]),
                           inner_cone_angle=torch.tensor([[0.25]]),
                           outer_cone_angle=torch.tensor([[0.45]]),
                           cast_shadows=torch.tensor([[True]]), shadow=st)
    return tr.Lights(ambient=tr.sh_from_color(torch.tensor([[0.03, 0.03, 0.035]])),
                     directional=sun, spot=sp)


def camera(size: int):
    view = tr.camera.look_at([1.8, 1.1, 1.85], [-1.2, 0.9, -0.9])
    proj = tr.camera.perspective(70.0, 1.0, 0.05)
    return view.reshape(-1, 4, 4), proj.reshape(-1, 4, 4)


def to_png(img: torch.Tensor, path: Path, ev: float = 0.0) -> None:
    x = img[0].permute(1, 2, 0).clamp_min(0) * 2**ev
    x = x / (1 + x)  # Reinhard
    x = torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-8) ** (1 / 2.4) - 0.055)
    Image.fromarray((x.clamp(0, 1) * 255 + 0.5).byte().numpy()).save(path, optimize=True)


def picture(size: int = 384) -> None:
    scene, lt = room(), lights()
    view, proj = camera(size)
    sky = (0.45, 0.6, 0.9)
    left = tr.Renderer(size, background=sky)(scene, view, proj, lt).image
    right = tr.Renderer(size, background=sky, fog=Fog(**FOG))(scene, view, proj, lt).image
    both = torch.cat([left, torch.ones_like(left[..., :4]), right], -1)
    IMAGES.mkdir(parents=True, exist_ok=True)
    to_png(both, IMAGES / "fog_godrays.png", ev=1.0)
    print("wrote", IMAGES / "fog_godrays.png")


def cpu_median(fn, repeats: int) -> float:
    """Median process CPU time (s) of ``fn`` on one thread, after a warm-up call: on a
    machine shared with other jobs, wall time measures the others' load too."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        fn()
        times = []
        for _ in range(repeats):
            t0 = time.process_time()
            fn()
            times.append(time.process_time() - t0)
        return statistics.median(times)
    finally:
        torch.set_num_threads(n)


def frame_inputs(size: int):
    """What the renderer hands the fog pass: lit image, distance, rays, shadow maps."""
    scene, lt = room(), lights()
    view, proj = camera(size)
    r = tr.Renderer(size)
    out = r(scene, view, proj, lt, channels={"position"})
    plan = r.plan(scene, lt)
    eye = camera_position(view)
    rays = view_rays(view, proj, (size, size))
    dist = (out.gbuffer["position"] - eye[:, :, None, None]).norm(dim=1, keepdim=True)
    dist = torch.where(out.alpha > 0, dist, torch.full_like(dist, math.inf))
    groups, lights_b = r._shadow_maps(plan, scene, view, proj, lt, 1, None)
    bounds = torch.stack([scene.positions.amin(0), scene.positions.amax(0)])[None]
    return out.image, dist, eye, rays, lights_b, groups, view, bounds


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--picture", action="store_true")
    ap.add_argument("--light-path", action="store_true")
    args = ap.parse_args()
    if args.picture:
        picture()
        return
    if args.light_path:
        light_path(args.quick)
        return
    torch.set_grad_enabled(False)
    size = 48 if args.quick else 96
    image, dist, eye, rays, lt, groups, view, bounds = frame_inputs(size)
    fog = Fog(**FOG)
    # the reference: the marched lights' in-scattering, brute force
    terms = fog_terms(dist, eye, rays, fog, lt, groups, view, bounds)
    d64 = dist.double()
    start = torch.zeros_like(d64)
    # the engine marches up to the farthest corner of the scene's box (and the spot light)
    # from the eye: the sky seen through the window too
    spot = lt.spot.position[0].double()
    lo = torch.minimum(bounds[0, 0].double(), spot.amin(0))
    hi = torch.maximum(bounds[0, 1].double(), spot.amax(0))
    far = torch.maximum((lo - eye[0].double()).abs(), (hi - eye[0].double()).abs()).norm()
    end = torch.minimum(d64, far)
    a, b, y0 = FOG["density"], FOG["height_falloff"], FOG["base_height"]
    src = light_source(lt.to(dtype=torch.float64), rays.double(), FOG["anisotropy"],
                       groups, view.double(), marched_lights(lt, groups), fog)
    ref = reference_fog.march_reference(eye.double(), rays.double(), start, end,
                                        lambda y: a * torch.exp(-b * (y - y0)),
                                        torch.tensor(FOG["color"]), src,
                                        steps=256 if args.quick else 512)
    scale = float(ref.abs().mean())
    rows = []
    repeats = 3
    for steps in (4, 8, 16, 32, 64):
        for jitter, blur in ((False, 0.0), (True, 0.0), (True, 1.0), (True, 2.0)):
            f = Fog(**FOG, steps=steps, jitter=jitter, blur=blur)
            t = fog_terms(dist, eye, rays, f, lt, groups, view, bounds)
            marched = depth_aware_blur(t.marched, dist, blur)
            err = float((marched.double() - ref).abs().mean()) / scale
            sec = cpu_median(lambda f=f: apply_fog(image, dist, eye, rays, f, lt, groups, view,
                                                   bounds), repeats)
            rows.append([steps, "yes" if jitter else "no", f"{blur:g}", err, sec * 1e3])
            print(rows[-1], flush=True)
    analytic_share = float(terms.analytic.abs().mean()) / (
        float(terms.analytic.abs().mean()) + scale)
    table = markdown_table(["steps", "jitter", "blur (px)", "rel. mean abs error",
                            "fog pass (CPU ms)"], rows)
    default = next(r for r in rows if r[:3] == [Fog().steps, "yes" if Fog().jitter else "no",
                                                f"{Fog().blur:g}"])
    body = (f"### Fog\n\nLight shafts in a {size}x{size} frame of the window room "
            "(`scripts/bench_fog.py`): sun with a 1024 shadow map through a window with a "
            "cross-shaped frame and a shadowed spot light, fog density "
            f"{FOG['density']}/m, g = {FOG['anisotropy']}. Error: mean absolute difference of "
            "the marched in-scattering from a 512-step float64 brute-force march "
            "(`testing/reference_fog.py`, numerically integrated transmittance, the same "
            "shadow-map lookups), relative to its mean. The analytic part (ambient, "
            f"{analytic_share:.0%} of the in-scattered light here) is exact and not in the "
            "error. Time: the whole fog pass (`apply_fog`, no grad), median process CPU time "
            f"of {repeats} on one thread (the machine is shared with other jobs, so wall time "
            f"would measure their load). Defaults ({default[0]} steps, jitter, {default[2]} px "
            f"blur): error {default[3]:.3f}, {default[4]:.0f} ms.\n\n" + table)
    print(body)
    if not args.quick:
        update_section("fog", body)


LP_FOG = dict(density=0.08, height_falloff=0.25, base_height=0.0, color=(1.0, 1.0, 1.0),
              anisotropy=0.3)
LP_SUN, LP_BULB = (0.5, -0.6, 0.4), (1.0, 1.5, -4.0)


def light_path(quick: bool) -> None:
    """Section fog-light-path (module docstring)."""
    torch.set_grad_enabled(False)
    size = 32 if quick else 64
    steps = 256 if quick else 1024
    f64 = torch.float64
    e = 1000.0
    floor = tr.Mesh(torch.tensor([(-e, 0.0, -e), (-e, 0.0, e), (e, 0.0, e), (e, 0.0, -e)]),
                    torch.tensor([(0, 1, 2), (0, 2, 3)]),
                    material=tr.Material(base_color_factor=(0.6, 0.6, 0.6, 1.0),
                                         roughness_factor=0.8))
    scene = tr.RenderScene.from_mesh(floor)
    view = tr.camera.look_at([0.0, 1.6, 6.0], [0.0, 1.0, -4.0]).reshape(1, 4, 4)
    proj = tr.camera.perspective(70.0, 1.0, 0.05).reshape(1, 4, 4)
    ones = torch.ones(1, 1, 3)
    sun = tr.DirectionalLights(direction=torch.tensor([[LP_SUN]]), color=ones,
                               intensity=torch.tensor([[5.0]]))
    bulb = tr.PointLights(position=torch.tensor([[LP_BULB]]), color=ones,
                          intensity=torch.tensor([[20.0]]))
    amb = tr.sh_from_color(torch.tensor([[0.05, 0.05, 0.05]]))
    fog_on = Fog(**LP_FOG, steps=16)
    fog_off = Fog(**LP_FOG, steps=16, light_transmittance=False)
    every = tr.Lights(ambient=amb, directional=sun, point=bulb)
    images, times = {}, {}
    for name, fog in (("on", fog_on), ("off", fog_off)):
        r = tr.Renderer(size, fog=fog)
        out = r(scene, view, proj, every, channels={"position"})
        images[name] = out.image.double()
        times[name] = cpu_median(lambda r=r: r(scene, view, proj, every), 3)
    times["no fog"] = cpu_median(lambda: tr.Renderer(size)(scene, view, proj, every), 3)
    # the reference: surfaces lit per light (the engine's shading, no fog) times the
    # numerically integrated light path; view-ray transmittance and in-scattering by the
    # brute-force march with numerically integrated light paths at every sample
    a, b, y0, g = (LP_FOG[k] for k in ("density", "height_falloff", "base_height",
                                         "anisotropy"))
    dens = lambda y: a * torch.exp(-b * (y - y0))  # noqa: E731
    eye, rays = camera_position(view).double(), view_rays(view, proj, (size, size)).double()
    pos = out.gbuffer["position"].double()
    covered = out.alpha.double() > 0
    plain = {k: tr.Renderer(size)(scene, view, proj, lt).image.double() for k, lt in (
        ("amb", tr.Lights(ambient=amb)), ("sun", tr.Lights(directional=sun)),
        ("bulb", tr.Lights(point=bulb)))}
    l_y = 0.6 / math.sqrt(sum(c * c for c in LP_SUN))
    t_sun = torch.exp(-reference_fog.light_optical_depth_reference(
        pos, dens, direction=LP_SUN, far=40 / (b * l_y), steps=4000))
    t_bulb = torch.exp(-reference_fog.light_optical_depth_reference(pos, dens,
                                                                    position=LP_BULB))
    surface = plain["amb"] + plain["sun"] * t_sun + plain["bulb"] * t_bulb
    dist = (pos - eye[:, :, None, None]).norm(dim=1, keepdim=True)
    vy = rays[:, 1:2]
    sky_end = torch.where(vy > 0, (40 / (b * vy.clamp_min(1e-9))).clamp_max(300.0),
                          torch.full_like(vy, 300.0))
    end = torch.where(covered, dist, sky_end)
    tau_v = reference_fog.optical_depth_quadrature(eye[:, 1, None, None, None], vy, end, dens,
                                                   steps=4000)
    srcs = [reference_fog.punctual_source_reference(rays, g, torch.full((3,), 5.0), dens,
                                                    direction=LP_SUN, far=40 / (b * l_y),
                                                    steps=256),
            reference_fog.punctual_source_reference(rays, g, torch.full((3,), 20.0), dens,
                                                    position=LP_BULB, steps=128)]
    amb_in = ambient_inscatter(amb.double(), rays, g)

    def source(p, valid, dimmed=True):
        return amb_in + sum(s(p, valid) for s in srcs)

    inscatter = reference_fog.march_reference(eye, rays, torch.zeros_like(end), end, dens,
                                              torch.ones(3), source, steps=steps)
    ref = torch.exp(-tau_v) * surface * covered + inscatter
    rows = []
    for name in ("on", "off"):
        err = images[name] - ref
        rel = float(err.abs().mean() / ref.abs().mean())
        bias = float(err.mean() / ref.mean())
        sky = ~covered.expand_as(err)
        rel_sky = float(err[sky].abs().mean() / ref[sky].abs().mean())
        rel_floor = float(err[~sky].abs().mean() / ref[~sky].abs().mean())
        rows.append([f"light path {name}", rel, bias, rel_floor, rel_sky, times[name] * 1e3])
    rows.append(["no fog (frame only)", "", "", "", "", times["no fog"] * 1e3])
    # what an environment map and an emissive panel would add (left out: the error)
    from torchraster.shading.ibl import Environment
    from torchraster.texture import latlong_directions
    d = latlong_directions(32, 64, dtype=f64)
    sky_map = (0.3 + 0.5 * d[:, 1:2].clamp_min(0)) * torch.tensor([0.6, 0.8, 1.0],
                                                                     dtype=f64).view(1, 3, 1, 1)
    env = Environment(sky_map[0])
    env_terms = fog_terms(torch.where(covered, dist, torch.full_like(dist, math.inf)), eye, rays,
                          Fog(**LP_FOG), None, (), None, None, env)
    env_share = float(env_terms.analytic.mean() / (ref.mean() + env_terms.analytic.mean()))
    t0 = time.process_time()
    fog_terms(dist, eye, rays, Fog(**LP_FOG), None, (), None, None, env)
    env_ms = (time.process_time() - t0) * 1e3
    # a 1 x 1 m panel of 5 nits facing +z at x in [-0.5, 0.5], y in [0, 1], z = -2, as
    # 8 x 8 Lambertian emitters (intensity L A cos / 64) with numerically integrated paths
    panel = []
    for i in range(8):
        for j in range(8):
            c = (-0.5 + (i + 0.5) / 8, (j + 0.5) / 8, -2.0)
            panel.append(c)

    def panel_source(p, valid):
        total = torch.zeros_like(p)
        for c in panel:
            to = p - torch.tensor(c, dtype=f64).view(1, 3, 1, 1)
            cos = (to[:, 2:3] / to.norm(dim=1, keepdim=True)).clamp_min(0)
            ci = torch.full((3,), 5.0 / 64, dtype=f64)
            s = reference_fog.punctual_source_reference(rays, g, ci, dens, position=c,
                                                        steps=32)
            total = total + s(p, valid) * cos
        return total

    panel_end = end.clamp_max(30.0)
    emissive = reference_fog.march_reference(eye, rays, torch.zeros_like(end), panel_end, dens,
                                             torch.ones(3), panel_source,
                                             steps=max(64, steps // 8))
    em_share = float(emissive.mean() / (ref.mean() + emissive.mean()))
    em_max = float((emissive / (ref + emissive)).max())
    table = markdown_table(["fog", "rel. mean abs error", "bias (mean)", "floor pixels",
                            "sky pixels", "frame (CPU ms)"], rows)
    body = (f"### Fog light path\n\nAn open floor (diffuse, 0.6) under height fog (density "
            f"{a}/m at y = 0, falloff {b}/m, g = {g}) lit by a sun (5 lux, l_y = {l_y:.2f}), "
            f"a point light (20 cd at 1.5 m) and a little ambient light, {size}x{size}, "
            "camera 1.6 m above the floor looking to the horizon (`scripts/bench_fog.py "
            "--light-path`). Reference: the engine's unfogged shading of each light times "
            "its light-path transmittance integrated by the midpoint rule, then a "
            f"{steps}-step float64 march of the view ray whose every sample integrates the "
            "path to each light numerically (`testing/reference_fog.py`: "
            "`light_optical_depth_reference`, `punctual_source_reference`); sky rays end "
            "where the fog has thinned out (at most 300 m). Error: mean absolute "
            "difference of the linear image relative to the reference's mean (bias: mean "
            "difference over mean). Time: the whole frame (`Renderer`, 16 fog steps, no "
            "grad), median process CPU time of 3 on one thread.\n\n" + table +
            "\n\nLeft out (measured on the same frame): an environment map (a blue sky "
            "gradient, 0.3-0.8 nits) lighting the fog would add "
            f"{env_share:.1%} of the image; it is now in-scattered through its 9 SH "
            f"coefficients like the ambient light ({env_ms:.1f} ms a frame, "
            "`fog_terms(environment=...)`, on in the renderer when the scene has an "
            "environment). A 1 x 1 m emissive panel of 5 nits on the floor 8 m ahead "
            f"(8 x 8 Lambertian emitters, brute force) adds {em_share:.2%} of the image on "
            f"average and at most {em_max:.1%} of a pixel: not modelled (emissive "
            "surfaces would need to be gathered as lights).")
    print(body)
    if not quick:
        update_section("fog-light-path", body)


if __name__ == "__main__":
    main()
