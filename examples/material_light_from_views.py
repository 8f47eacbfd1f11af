"""Recover a texture, the roughness and a point light from 8 views of a textured mesh.

Spot (shipped) is seen by ``--views`` cameras around it: its base-colour texture
(``--texture-size``, the true one downsampled to that size), roughness 0.35, metallic 0,
lit by a white point light at (1.5, 2.5, 2.0) of 12 cd and a known dim ambient light. The
targets are rendered at ``--target-supersample`` (4) times the resolution without
antialiasing (each pixel's true area average). Starting from a uniform grey texture,
roughness 0.8 and a light of 4 cd at (-1.5, 2.0, 1.0), Adam recovers

* the texture (``(3, T, T)`` linear RGB, through a sigmoid),
* the roughness (a scalar, through a sigmoid),
* the light's position (3) and intensity (through exp),

by minimising the mean squared difference of the sRGB-encoded renders of
``tr.Renderer(shading="pbr", raster=tr.RasterSettings(antialias=True, supersample=2))``.
The images are compared
with the PSNR of the sRGB-encoded image in [0, 1] over the pixels the object covers in the
target (background excluded, so the figure is not inflated by black pixels), also without
the silhouette's pixels ("interior"); the true parameters through the same renderer give
the best PSNR possible (the "ceiling", printed too). ``--holdout`` further views, never
optimised, check the recovered texture and light elsewhere (texels no training view sees
stay grey there).

    python examples/material_light_from_views.py            # 8 views, 128 px, 256^2 texture
    python examples/material_light_from_views.py --iterations 30 --resolution 32 \\
        --texture-size 16 --supersample 1
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

import torchraster as tr  # noqa: E402
from torchraster.post import encode_srgb  # noqa: E402

FOV_DEG = 40.0
DISTANCE = 2.8
TRUE_ROUGHNESS = 0.35
TRUE_LIGHT = (1.5, 2.5, 2.0)
TRUE_INTENSITY = 12.0
START_ROUGHNESS = 0.8
START_LIGHT = (-1.5, 2.0, 1.0)
START_INTENSITY = 4.0
AMBIENT = 0.08
ELEVATIONS = (30.0, -5.0)


def lights_of(position: torch.Tensor, intensity: torch.Tensor) -> tr.Lights:
    """One white point light (position ``(3,)``, intensity ``()``) and the known ambient."""
    return tr.Lights(
        ambient=tr.sh_from_color(torch.full((1, 3), AMBIENT)),
        point=tr.PointLights(position=position.view(1, 1, 3), color=torch.ones(1, 1, 3),
                             intensity=intensity.view(1, 1)))


def psnr(image: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR (dB) of sRGB-encoded images in [0, 1] over the pixels where ``mask`` > 0.

    Shape: image, target ``(B, 3, H, W)`` linear radiance; mask ``(B, 1, H, W)``.
    """
    a, b = encode_srgb(image), encode_srgb(target)
    m = (mask > 0).expand_as(a)
    mse = ((a - b) ** 2)[m].mean()
    return float(10 * torch.log10(1.0 / mse.clamp_min(1e-12)))


def interior(alpha: torch.Tensor) -> torch.Tensor:
    """Pixels whose 3x3 neighbourhood is fully covered (``(B, 1, H, W)`` float): the object
    without its silhouette's pixels."""
    return (-torch.nn.functional.max_pool2d(-alpha, 3, 1, 1) >= 1.0).float()


def logit(p: float) -> float:
    """Inverse of the sigmoid."""
    return math.log(p / (1 - p))


class Unknowns(torch.nn.Module):
    """What is recovered: texture and roughness (through sigmoids), light position and
    intensity (through exp)."""

    def __init__(self, texture_size: int) -> None:
        super().__init__()
        self.texture = torch.nn.Parameter(torch.zeros(3, texture_size, texture_size))
        self.roughness = torch.nn.Parameter(torch.tensor(logit(START_ROUGHNESS)))
        self.light = torch.nn.Parameter(torch.tensor(START_LIGHT))
        self.log_intensity = torch.nn.Parameter(torch.tensor(math.log(START_INTENSITY)))

    def material(self, base: tr.Material) -> tr.Material:
        """``base`` with the current texture and roughness."""
        return replace(base, base_color_texture=torch.sigmoid(self.texture),
                       roughness_factor=torch.sigmoid(self.roughness))

    def lights(self) -> tr.Lights:
        """The current light."""
        return lights_of(self.light, self.log_intensity.exp())


def run(args: argparse.Namespace) -> dict:
    """Run the optimisation; returns the history, the recovered values and the pictures."""
    common.setup(args)
    spot = tr.load_spot(max_texture_size=args.texture_size)
    true_texture = spot.material.texture("base_color")
    true_material = replace(spot.material, base_color_texture=true_texture,
                            roughness_factor=TRUE_ROUGHNESS, metallic_factor=0.0)
    geometry = replace(spot, material=None)
    centre = (spot.positions.min(0).values + spot.positions.max(0).values) / 2
    views = common.ring_views(args.views, DISTANCE, ELEVATIONS, target=centre)
    holdout = common.ring_views(args.holdout, DISTANCE, ELEVATIONS, target=centre,
                                offset_deg=180.0 / max(1, args.views))
    proj = tr.camera.perspective(FOV_DEG, 1.0, 0.1)
    renderer = tr.Renderer(args.resolution,
                           shading="pbr",
                           raster=tr.RasterSettings(antialias=True, supersample=args.supersample))
    true_lights = lights_of(torch.tensor(TRUE_LIGHT), torch.tensor(TRUE_INTENSITY))

    def render(material: tr.Material, lights: tr.Lights, cams: torch.Tensor,
               with_renderer: tr.Renderer = renderer) -> tr.RenderOutput:
        return with_renderer(replace(geometry, material=material), cams, proj, lights)

    reference = renderer
    if args.target_supersample > 1:
        reference = tr.Renderer(args.resolution,
                                shading="pbr",
                                raster=tr.RasterSettings(supersample=args.target_supersample))
    with torch.no_grad():
        target = render(true_material, true_lights, views, reference)
        target_holdout = (render(true_material, true_lights, holdout, reference)
                          if args.holdout else None)
        # the best any parameters can do: the true ones through the optimised renderer
        ceiling = psnr(render(true_material, true_lights, views).image, target.image,
                       target.alpha)
    target_srgb = encode_srgb(target.image)

    unknowns = Unknowns(args.texture_size)
    opt = torch.optim.Adam([
        {"params": [unknowns.texture], "lr": args.lr_texture},
        {"params": [unknowns.roughness, unknowns.light, unknowns.log_intensity],
         "lr": args.lr_light},
    ])
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.iterations, eta_min=0.0)
    with torch.no_grad():
        start = render(unknowns.material(true_material), unknowns.lights(), views)
    initial = psnr(start.image, target.image, target.alpha)
    inner = interior(target.alpha)
    table = common.Table(["PSNR dB", "PSNR interior", "roughness", "light err", "intensity"],
                         args.log_every, args.quiet)
    for it in range(args.iterations):
        table.tick()
        out = render(unknowns.material(true_material), unknowns.lights(), views)
        loss = ((encode_srgb(out.image) - target_srgb) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        table.tock()
        with torch.no_grad():
            light_err = float((unknowns.light - torch.tensor(TRUE_LIGHT)).norm())
            table.record(it, [psnr(out.image, target.image, target.alpha),
                              psnr(out.image, target.image, inner),
                              float(torch.sigmoid(unknowns.roughness)), light_err,
                              float(unknowns.log_intensity.exp())],
                         last=it == args.iterations - 1)
    with torch.no_grad():
        material = unknowns.material(true_material)
        final = render(material, unknowns.lights(), views)
        result = {
            "history": table.history, "initial": initial, "ceiling": ceiling,
            "final": psnr(final.image, target.image, target.alpha),
            "final_interior": psnr(final.image, target.image, inner),
            "roughness": float(torch.sigmoid(unknowns.roughness)),
            "light": unknowns.light.detach().tolist(),
            "intensity": float(unknowns.log_intensity.exp()),
            "centre": centre.tolist(),
        }
        if args.holdout:
            held = render(material, unknowns.lights(), holdout)
            result["holdout"] = psnr(held.image, target_holdout.image, target_holdout.alpha)
        if args.out is not None or args.picture is not None:
            panels = []
            rows = [0, args.views // 2] if args.views > 1 else [0]
            for label, out in (("start", start), ("target", target), ("result", final)):
                panels.append((label, common.stack_rows(
                    [common.to_uint8(out.image[i].clamp(0, 1)) for i in rows])))
            size = args.resolution
            textures = [torch.nn.functional.interpolate(t[None], size=(size, size),
                                                        mode="area")[0]
                        for t in (true_texture, material.base_color_texture)]
            panels.append(("texture: true / recovered",
                           common.stack_rows([common.to_uint8(t) for t in textures])))
            result["panels"] = panels
    return result


def parser() -> argparse.ArgumentParser:
    """The command line."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    common.add_common_args(p, iterations=200, resolution=128, views=8,
                           out="out/inverse_material")
    p.add_argument("--texture-size", type=int, default=256,
                   help="side of the true and the recovered texture (default 256)")
    p.add_argument("--holdout", type=int, default=4,
                   help="views never optimised, for a held-out PSNR (default 4; 0: none)")
    p.add_argument("--supersample", type=int, default=2,
                   help="supersampling of the optimised renderer, on top of antialiasing "
                        "(default 2; 1 is 4x cheaper, its ceiling is ~34 dB at 128 px)")
    p.add_argument("--target-supersample", type=int, default=4,
                   help="render the targets at this supersampling without antialiasing "
                        "(default 4; 1: the targets come from the optimised renderer itself)")
    p.add_argument("--lr-texture", type=float, default=0.1,
                   help="Adam learning rate of the texture logits (default 0.1)")
    p.add_argument("--lr-light", type=float, default=0.1,
                   help="Adam learning rate of roughness, light position and log intensity")
    return p


def main(argv: list[str] | None = None) -> dict:
    """Parse ``argv``, run, write the pictures (and the benchmark section)."""
    args = parser().parse_args(argv)
    result = run(args)
    return common.finish(args, result, "material.png", summary(result), "inverse-material",
                         lambda: benchmark_body(args, result))


def light_errors(result: dict) -> tuple[float, float]:
    """What the images pin down about the light: the angle (degrees) between the recovered
    and the true direction to it from the object's centre, and the relative error (%) of
    the illuminance it gives there (intensity / distance^2). A farther, brighter light
    lights the object almost alike, so position and intensity alone are less telling."""
    centre = np.asarray(result["centre"])
    true, found = np.asarray(TRUE_LIGHT) - centre, np.asarray(result["light"]) - centre
    cos = true @ found / (np.linalg.norm(true) * np.linalg.norm(found))
    angle = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    lux = result["intensity"] / (found @ found)
    true_lux = TRUE_INTENSITY / (true @ true)
    return angle, float((lux / true_lux - 1) * 100)


def summary(result: dict) -> str:
    """PSNR before / after and the recovered parameters against the true ones."""
    light = ", ".join(f"{v:.2f}" for v in result["light"])
    true_light = ", ".join(f"{v:g}" for v in TRUE_LIGHT)
    text = (f"PSNR {result['initial']:.2f} -> {result['final']:.2f} dB over the object's "
            f"pixels of the training views ({result['final_interior']:.2f} dB without the "
            f"silhouette pixels; the true parameters score {result['ceiling']:.2f} dB "
            "through the same renderer)")
    if "holdout" in result:
        text += f", {result['holdout']:.2f} dB on held-out views"
    angle, lux = light_errors(result)
    return text + (
        f"; roughness {result['roughness']:.3f} (true {TRUE_ROUGHNESS}), light at ({light}) "
        f"(true {true_light}), {result['intensity']:.2f} cd (true {TRUE_INTENSITY:g}): its "
        f"direction from the object's centre is off by {angle:.1f}°, the illuminance it "
        f"gives there by {lux:+.1f} %; {result['history'].ms_per_iteration:.0f} ms/iteration")


def benchmark_body(args: argparse.Namespace, result: dict) -> str:
    """The docs/benchmarks.md section of this run."""
    hist = result["history"]
    rows = [[i, *hist.rows[i], hist.seconds[i] * 1e3] for i in common.checkpoints(len(hist.rows))]
    light_err = float(np.linalg.norm(np.subtract(result["light"], TRUE_LIGHT)))
    rows.append(["final", result["final"], result["final_interior"], result["roughness"],
                 light_err, result["intensity"], ""])
    aa = "antialias=True" + (f", supersample={args.supersample}" if args.supersample > 1
                             else "")
    target = (f"{args.target_supersample}x supersampled without antialiasing"
              if args.target_supersample > 1 else "by the optimised renderer itself")
    return (
        f"### Texture, roughness and light from views (Spot, {args.views} views, "
        f"{args.resolution}², {args.texture_size}² texture, {args.iterations} iterations)"
        "\n\n"
        "Recovered at once: the base-colour texture, the roughness and a point light's "
        "position and intensity (a dim ambient light is known), by Adam on the squared "
        f"difference of sRGB-encoded renders (`shading=\"pbr\"`, `{aa}`); targets rendered "
        f"{target}. PSNR of the sRGB-encoded image over the pixels the object covers "
        "(background excluded), and over the covered pixels whose 3x3 neighbourhood is "
        "covered (\"interior\"). Step i: the render of that step, before its update; "
        "final: after the last.\n\n"
        + common.markdown_table(["step", "PSNR (dB)", "PSNR interior (dB)",
                                 f"roughness (true {TRUE_ROUGHNESS})",
                                 "light position error (m)",
                                 f"intensity (cd, true {TRUE_INTENSITY:g})",
                                 "ms / iteration"], rows)
        + "\n\n" + summary(result) + " (target ≥ 35 dB).\n\n"
        "![start / target / result, true and recovered texture](images/inverse_material.png)"
    )


if __name__ == "__main__":
    main()
