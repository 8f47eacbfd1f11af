"""Shadow gradients against finite differences of a converged reference (issue 21, item 5).

A shadow map is rendered without gradients and its texels are piecewise constant in every
parameter: finite differences with a tiny step at one map position see only what moves the
receiver in a map glued to the light (``gradcheck`` passes), not the shadow edges that the
map holds moving too, and a step that flips a texel gives a spike. The converged quantity
is the visibility averaged over sub-texel offsets of the map grid (the same filter, the map
shifted by a regular n x n grid of offsets in [-0.5, 0.5)² texels): smooth in every parameter, it
is what the image converges to as the map is refined relative to the shading. For each
filter x parameter the script compares the jitter average of the analytic directional
derivative with the jitter average of central finite differences (step ``h``) of

    J = weighted mean over receivers of visibility (weights: a ramp over the floor)

(``N`` receivers on the floor around a caster, float64, module level: ``local_views`` /
``directional_views`` -> ``render_shadow_maps`` -> ``shadow_visibility``). The light
intensity row goes through ``Renderer`` (the image is linear in it).

    python scripts/bench_shadow_grads.py            # ~5 min, writes "shadow-gradients"
    python scripts/bench_shadow_grads.py --jitters 3 --no-write
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torchraster as tr  # noqa: E402
from torchraster.shading import shadows  # noqa: E402
from torchraster.shading.shadows import (  # noqa: E402
    ShadowSettings,
    directional_views,
    local_views,
    render_shadow_maps,
    shadow_visibility,
)
from torchraster.testing import raytrace as rt  # noqa: E402

F64 = torch.float64
FILTERS = ("hard", "pcf", "pcss", "vsm")
#: (kind, parameter) rows; each is a directional derivative along a fixed unit vector.
PARAMS = (("point", "light position"), ("directional", "light direction"),
          ("point", "caster vertices"), ("point", "receiver positions"),
          ("directional", "caster vertices"), ("directional", "receiver positions"),
          ("point", "light intensity"))
SIZE = 64
GRID = 61  #: receivers per side of the floor grid
_XS = torch.linspace(-1.0, 1.0, GRID, dtype=F64)
#: Fixed weights of the receivers: a ramp over the floor (a rigid shift of them changes J).
WEIGHTS = (1.5 + 0.8 * _XS[:, None] - 0.5 * _XS[None, :]).flatten()
U_LIGHT = (0.6, 0.3, -0.5)
U_CASTER = (0.5, -0.2, 0.4)
U_RECEIVER = (0.4, 0.6, -0.5)


def unit(v) -> torch.Tensor:
    t = torch.tensor(v, dtype=F64)
    return t / t.norm()


def scene():
    """A low-poly sphere (radius 0.35 m, centre 0.6 m up) and floor receivers around its
    shadow: caster vertices ``(V, 3)``, faces, receivers ``(1, 3, 1, N)``, normals."""
    verts, faces = rt.icosphere(0.35, (0.0, 0.6, 0.0), subdivisions=2)
    gx, gz = torch.meshgrid(_XS, _XS, indexing="ij")
    p = torch.stack([gx.flatten(), torch.zeros(gx.numel(), dtype=F64), gz.flatten()])
    n = torch.zeros_like(p)
    n[1] = 1
    return verts, faces, p[None, :, None], n[None, :, None]


def settings(filt: str) -> ShadowSettings:
    return ShadowSettings(map_size=SIZE, filter=filt, pcf_taps=8, pcf_radius=1.5,
                          light_size=0.1 if filt == "pcss" else 0.5, max_penumbra=8)


def jittered(g, jx: float, jy: float):
    """Shift the map grid of views ``g`` by (jx, jy) texels (a sub-texel offset)."""
    size = g.settings.map_size
    off = torch.zeros_like(g.proj)
    if g.perspective:  # ndc += -P02 (w = -z)
        off[..., 0, 2], off[..., 1, 2] = -2 * jx / size, 2 * jy / size
    else:
        off[..., 0, 3], off[..., 1, 3] = 2 * jx / size, -2 * jy / size
    g.proj = g.proj + off
    return g


def objective(kind: str, st: ShadowSettings, light: torch.Tensor, verts: torch.Tensor,
              faces: torch.Tensor, p: torch.Tensor, n: torch.Tensor,
              jitter: tuple[float, float]) -> torch.Tensor:
    """Weighted mean visibility of the receivers (scalar) for one jitter of the grid."""
    with torch.no_grad():
        bounds = torch.stack([verts.amin(0), verts.amax(0)])[None]
    if kind == "point":
        g = local_views("point", light.view(1, 1, 3), None, None, st, bounds)
        cam = None
    else:
        cam_view, cam_proj = (m.to(F64) for m in (
            tr.camera.look_at([0.0, 2.5, 3.0], [0.0, 0.2, 0.0]),
            tr.camera.perspective(50.0, 1.0, 0.1)))
        g = directional_views(light.view(1, 1, 3), st, bounds, cam_view, cam_proj,
                              receiver_bounds=torch.tensor([[[-1.5, 0, -1.5], [1.5, 1, 1.5]]],
                                                           dtype=F64))
        cam = cam_view
    g = jittered(g, *jitter)
    render_shadow_maps([g], verts, faces)
    recv = torch.ones(1, 1, *p.shape[2:], dtype=torch.bool)
    vis = shadow_visibility(g, p, n, recv, cam).flatten()
    return (WEIGHTS * vis).sum() / WEIGHTS.sum()


def light_of(kind: str) -> torch.Tensor:
    return torch.tensor([0.3, 1.6, 0.2] if kind == "point" else [0.35, -1.0, 0.2], dtype=F64)


def measure(kind: str, param: str, filt: str, jitters: int, h: float) -> dict:
    """Averages over ``jitters`` x ``jitters`` sub-texel offsets (a regular grid: the map
    is periodic in the offset, one texel) of the analytic and the finite-difference
    directional derivative; ``se``: the standard error of their difference as if the
    offsets were independent draws (an overestimate for a grid)."""
    st = settings(filt)
    verts, faces, p, n = scene()
    light = light_of(kind)
    u = unit({"light position": U_LIGHT, "light direction": U_LIGHT,
              "caster vertices": U_CASTER, "receiver positions": U_RECEIVER}[param])
    an, fd, glued = [], [], []
    offsets = [(k + 0.5) / jitters - 0.5 for k in range(jitters)]
    for jit in [(x, y) for x in offsets for y in offsets]:

        def f(t: torch.Tensor, jit=jit) -> torch.Tensor:
            lt, vt, pt = light, verts, p
            if param.startswith("light"):
                lt = light + t * u
            elif param == "caster vertices":
                vt = verts + t * u
            else:
                pt = p + t * u.view(1, 3, 1, 1)
            return objective(kind, st, lt, vt, faces, pt, n, jit)

        t0 = torch.zeros((), dtype=F64, requires_grad=True)
        out = f(t0)
        grad = torch.autograd.grad(out, t0, allow_unused=True)[0] if out.requires_grad else None
        an.append(0.0 if grad is None else float(grad))
        if param.startswith("light") and filt in ("pcf", "pcss"):
            # the same without the blockers' motion (the map glued to the light)
            keep = shadows._blocker_motion
            shadows._blocker_motion = lambda maps, sel, view, proj, tx, ty, *rest: (tx, ty)
            try:
                glued.append(float(torch.autograd.grad(f(t0), t0)[0]))
            finally:
                shadows._blocker_motion = keep
        with torch.no_grad():
            fd.append(float((f(torch.tensor(h, dtype=F64)) - f(torch.tensor(-h, dtype=F64)))
                            / (2 * h)))
    a, r = torch.tensor(an, dtype=F64), torch.tensor(fd, dtype=F64)
    diff = a - r
    return {"analytic": float(a.mean()), "reference": float(r.mean()),
            "glued": sum(glued) / len(glued) if glued else None,
            "se": float(diff.std() / math.sqrt(diff.numel())) if jitters > 1 else float("nan")}


def intensity_row(filt: str) -> dict:
    """d(image . w)/d(light intensity) through Renderer: analytic vs central FD."""
    verts, faces, _, _ = scene()
    positions, faces, cast = rt.ground_scene([(verts, faces)], 3.0, dtype=F64)
    sc = tr.RenderScene(positions, faces, materials=[tr.Material(roughness_factor=0.8)],
                        cast_shadows=cast)
    st = settings(filt)
    view = tr.camera.look_at([0.0, 2.5, 3.0], [0.0, 0.2, 0.0]).to(F64)
    proj = tr.camera.perspective(50.0, 1.0, 0.1).to(F64)
    r = tr.Renderer(24, shadows=st)
    r.shadow_cache = None
    w = torch.rand(1, 3, 24, 24, dtype=F64, generator=torch.Generator().manual_seed(1))

    def f(i: torch.Tensor) -> torch.Tensor:
        lights = tr.Lights(point=tr.PointLights(
            position=light_of("point").view(1, 1, 3), color=torch.ones(1, 1, 3, dtype=F64),
            intensity=i.view(1, 1), cast_shadows=torch.ones(1, 1, dtype=torch.bool),
            shadow=st))
        return (r(sc, view, proj, lights).image * w).sum()

    i0 = torch.tensor(5.0, dtype=F64, requires_grad=True)
    a = float(torch.autograd.grad(f(i0), i0)[0])
    with torch.no_grad():
        ref = float((f(i0 + 0.1) - f(i0 - 0.1)) / 0.2)
    return {"analytic": a, "reference": ref, "se": 0.0, "glued": None}


def verdict(res: dict) -> str:
    a, r, se = res["analytic"], res["reference"], res["se"]
    if abs(r) <= 3 * se:
        return "reference ~0" if abs(a - r) <= 3 * se else "wrong (nonzero)"
    if a == 0:
        return "missing (zero)"
    rel = abs(a - r) / abs(r)
    if rel <= 0.1 or abs(a - r) <= 2 * se:
        return "trustworthy"
    if a * r < 0:
        return "wrong sign"
    return "approximate" if rel <= 0.25 else "biased"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jitters", type=int, default=8, help="n: n x n sub-texel offsets")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    t_start = time.time()
    rows = []
    for kind, param in PARAMS:
        for filt in FILTERS:
            if param == "light intensity":
                res = intensity_row(filt)
            else:
                # step: ~0.2 texel of motion at the casters (texel ~2.3 cm there)
                h = 0.01 if param != "light direction" else 0.008
                res = measure(kind, param, filt, args.jitters, h)
            v = verdict(res)
            rel = abs(res["analytic"] - res["reference"]) / max(abs(res["reference"]), 1e-300)
            glued = "" if res["glued"] is None else f"{res['glued']:.4g}"
            rows.append([f"{kind} light", param, filt, f"{res['analytic']:.4g}",
                         f"{res['reference']:.4g}", f"{res['se']:.2g}", f"{rel:.2f}", v,
                         glued])
            print(" | ".join(rows[-1]), flush=True)
    seconds = time.time() - t_start
    print(f"{seconds:.0f} s")
    if args.no_write:
        return
    from benchmd import markdown_table, update_section

    body = "\n".join([
        "## Shadow gradients (issue 21, item 5)", "",
        f"Analytic directional derivative of the mean shadow visibility of {41 * 41} floor "
        "receivers around a sphere caster (radius 0.35 m, 320 faces, 0.6 m up; point light "
        f"at (0.3, 1.6, 0.2), sun along (0.35, -1, 0.2)), {SIZE}² maps, float64, against "
        "the converged reference: central finite differences of the same quantity "
        f"averaged over {args.jitters}x{args.jitters} sub-texel offsets of the map grid "
        "(a regular grid of offsets in [-0.5, 0.5)² texels; each offset's "
        "analytic derivative is averaged the same way; `se` is the standard error of the "
        "mean of their difference). A map rendered without gradients is piecewise constant "
        "in every parameter; averaging over the grid's offset gives what the image "
        "converges to as the map is refined, and its derivative. Light intensity: through "
        "`Renderer` (24² image, the image is linear in it). Verdicts: `trustworthy` = "
        "within 10 % (or 2 se); `approximate` = right sign, within 25 %; `missing (zero)` = "
        "the analytic gradient is 0 where the reference is not; `biased` / `wrong sign` "
        "otherwise. The last column is the analytic derivative without the blockers' "
        "motion (`_blocker_motion`), i.e. before this fix. Settings: PCF 8 taps radius "
        "1.5, PCSS light size 0.1 m, VSM blur 1.5. See docs/design.md (\"Shadows\", "
        "Gradients).", "",
        markdown_table(["light", "parameter", "filter", "analytic", "reference", "se",
                        "rel. error", "verdict", "analytic, map glued to the light"], rows),
        "", f"Run time {seconds:.0f} s."])
    update_section("shadow-gradients", body)


if __name__ == "__main__":
    main()
