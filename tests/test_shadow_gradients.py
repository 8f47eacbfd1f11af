"""Shadow gradients against finite differences of a converged reference (issue 21, item 5).

A shadow map rendered without gradients is piecewise constant in every parameter, so
``gradcheck`` (a tiny step at one map position) checks the derivative of a map glued to
the light, not of the image the renderer converges to. The reference here is the
visibility averaged over sub-texel jitters of the map grid (the same filter, the map
shifted by a uniform offset in [-0.5, 0.5)² texels), which is smooth: central finite
differences of its mean against the mean of the analytic derivatives over the same
jitters. Which filter x parameter cells are trustworthy: docs/benchmarks.md
("shadow-gradients", scripts/bench_shadow_grads.py) and docs/design.md.
"""

from __future__ import annotations

import math

import pytest
import torch

import torchraster as tr
from torchraster.shading import shadows
from torchraster.shading.shadows import (
    ShadowSettings,
    directional_views,
    local_views,
    render_shadow_maps,
    shadow_visibility,
)

F64 = torch.float64
SIZE = 32
# a flat square caster 0.5 m over the floor (2 triangles, parallel to it), turned 25
# degrees so that its edges do not run along texel rows
_C, _S = math.cos(math.radians(25)), math.sin(math.radians(25))
CASTER = torch.tensor([[x * _C + z * _S, 0.5, 0.05 - x * _S + z * _C]
                       for x, z in ((-0.25, -0.25), (0.25, -0.25), (0.25, 0.25), (-0.25, 0.25))],
                      dtype=F64)
FACES = torch.tensor([[0, 2, 1], [0, 3, 2]])
_XS = torch.linspace(-0.8, 0.8, 33, dtype=F64)
GX, GZ = torch.meshgrid(_XS, _XS, indexing="ij")
#: fixed weights of the floor receivers (a ramp: a rigid shift of them changes J)
WEIGHTS = (1.5 + 0.8 * GX - 0.5 * GZ).flatten()
CAM = (tr.camera.look_at([0.0, 2.5, 3.0], [0.0, 0.2, 0.0]).to(F64),
       tr.camera.perspective(50.0, 1.0, 0.1).to(F64))


def receivers() -> tuple[torch.Tensor, torch.Tensor]:
    p = torch.stack([GX.flatten(), torch.zeros(GX.numel(), dtype=F64), GZ.flatten()])
    n = torch.zeros_like(p)
    n[1] = 1
    return p[None, :, None], n[None, :, None]


def objective(kind: str, filt: str, light, verts, p, jitter) -> torch.Tensor:
    """Weighted mean visibility of the floor receivers with the map grid shifted by
    ``jitter`` texels."""
    st = ShadowSettings(map_size=SIZE, filter=filt, pcf_taps=8, pcf_radius=1.5)
    with torch.no_grad():
        bounds = torch.stack([verts.amin(0), verts.amax(0)])[None]
    if kind == "point":
        g = local_views("point", light.view(1, 1, 3), None, None, st, bounds)
    else:
        g = directional_views(light.view(1, 1, 3), st, bounds, *CAM,
                              receiver_bounds=torch.tensor([[[-1.0, 0, -1.0], [1.0, 1, 1.0]]],
                                                           dtype=F64))
    off = torch.zeros_like(g.proj)
    jx, jy = jitter
    if g.perspective:
        off[..., 0, 2], off[..., 1, 2] = -2 * jx / SIZE, 2 * jy / SIZE
    else:
        off[..., 0, 3], off[..., 1, 3] = 2 * jx / SIZE, -2 * jy / SIZE
    g.proj = g.proj + off
    render_shadow_maps([g], verts, FACES)
    recv = torch.ones(1, 1, *p.shape[2:], dtype=torch.bool)
    vis = shadow_visibility(g, p, receivers()[1], recv, CAM[0]).flatten()
    return (WEIGHTS * vis).sum() / WEIGHTS.sum()


LIGHT = {"point": (0.1, 1.5, 0.05), "directional": (0.3, -1.0, 0.15)}


def stratified(n: int) -> list[tuple[float, float]]:
    """n x n sub-texel offsets on a regular grid (the map content is periodic in the
    offset with period one texel: a grid integrates it far better than random draws)."""
    t = [(k + 0.5) / n - 0.5 for k in range(n)]
    return [(x, y) for x in t for y in t]


def derivatives(kind: str, filt: str, param: str, u, h: float, jitters: int = 4):
    """(analytic, reference, spread) of the directional derivative along ``u``, averaged
    over ``jitters``² offsets; spread: standard error of their difference as if the
    offsets were independent draws (an overestimate for a grid)."""
    u = torch.tensor(u, dtype=F64)
    u = u / u.norm()
    light = torch.tensor(LIGHT[kind], dtype=F64)
    p, _ = receivers()
    an, fd = [], []
    for jit in stratified(jitters):

        def f(t, jit=jit):
            lt = light + t * u if param == "light" else light
            pt = p + t * u.view(1, 3, 1, 1) if param == "receivers" else p
            vt = CASTER + t * u if param == "casters" else CASTER
            return objective(kind, filt, lt, vt, pt, jit)

        t0 = torch.zeros((), dtype=F64, requires_grad=True)
        out = f(t0)
        an.append(float(torch.autograd.grad(out, t0)[0]) if out.requires_grad else 0.0)
        with torch.no_grad():
            fd.append(float((f(torch.tensor(h, dtype=F64)) - f(torch.tensor(-h, dtype=F64)))
                            / (2 * h)))
    a, r = torch.tensor(an, dtype=F64), torch.tensor(fd, dtype=F64)
    return float(a.mean()), float(r.mean()), float((a - r).std() / math.sqrt(a.numel()))


@pytest.mark.parametrize("kind, u, h", [("point", (0.0, 1.0, 0.0), 0.02),
                                        ("point", (0.7, 0.2, -0.4), 0.02),
                                        ("directional", (0.6, 0.0, -0.5), 0.02)])
def test_pcf_light_gradient_matches_converged_reference(kind, u, h):
    """PCF w.r.t. the light position / direction: the shadow edges move with the light
    too (``_blocker_motion``); without that term the gradient has the wrong sign here."""
    a, r, se = derivatives(kind, "pcf", "light", u, h, jitters=6)
    assert abs(r) > 2 * se, (a, r, se)  # a clear reference
    assert abs(a - r) <= 0.2 * abs(r), (a, r, se)  # measured: 1-10 %
    keep = shadows._blocker_motion
    shadows._blocker_motion = lambda maps, sel, view, proj, tx, ty, *rest: (tx, ty)
    try:
        glued, _, _ = derivatives(kind, "pcf", "light", u, h, jitters=4)
    finally:
        shadows._blocker_motion = keep
    assert abs(glued - r) > 0.5 * abs(r), (glued, r)  # the test can fail


@pytest.mark.parametrize("filt", ["pcf", "pcss"])
def test_pcf_caster_vertex_gradient_matches_converged_reference(filt):
    """PCF / PCSS w.r.t. caster vertices: each tap's blocker texel remembers its caster
    face, and the blocker point follows the face's vertices (fixed barycentrics)."""
    # along the floor (PCSS: a caster moving up or down changes the penumbra width, which
    # carries no gradient: measured -53 % vertically; PCF -12 %)
    a, r, se = derivatives("point", filt, "casters", (1.0, 0.0, -0.6), 0.02, jitters=5)
    assert abs(r) > 4 * se, (a, r, se)
    assert abs(a - r) <= 0.15 * abs(r), (a, r, se)  # measured 1-5 %


@pytest.mark.parametrize("kind, param, u, jitters", [
    ("directional", "light", (0.6, 0.0, -0.5), 4),
    pytest.param("point", "light", (0.7, 0.2, -0.4), 6, marks=pytest.mark.slow),
    pytest.param("point", "casters", (0.5, -0.2, 0.4), 6, marks=pytest.mark.slow)])
def test_vsm_light_and_caster_gradients_match_converged_reference(kind, param, u, jitters):
    """VSM maps are rendered differentiably, their moments antialiased (silhouettes moving
    across texels): light pose and caster vertices get the edges' motion (measured within
    7-13 % here; the point-light references need 36 offsets to settle)."""
    a, r, se = derivatives(kind, "vsm", param, u, 0.02, jitters=jitters)
    assert abs(r) > 2 * se, (a, r, se)
    assert abs(a - r) <= 0.25 * abs(r), (a, r, se)


@pytest.mark.parametrize("kind, filt", [("point", "pcf"), ("directional", "pcf"),
                                        ("point", "vsm"), ("directional", "vsm"),
                                        ("directional", "pcss")])
def test_receiver_position_gradient_matches_converged_reference(kind, filt):
    """Receivers moving in any direction; PCSS only under a sun and along the floor: its
    penumbra width (blocker search) carries no gradient, so a receiver moving away from
    the caster (or from a point light) misses the penumbra's change (measured here: -38 %
    vertically under the sun, +73 % along the floor under the point light)."""
    u = (0.6, 0.0, -0.5) if filt == "pcss" else (0.4, 0.6, -0.5)
    a, r, se = derivatives(kind, filt, "receivers", u, 0.02, jitters=3)
    assert abs(r) > 6 * se, (a, r, se)
    assert abs(a - r) <= 0.1 * abs(r), (a, r, se)


def test_hard_filter_has_no_visibility_gradient():
    """Documented: ``"hard"`` is a step; its visibility carries no gradient."""
    light = torch.tensor(LIGHT["point"], dtype=F64, requires_grad=True)
    p, _ = receivers()
    out = objective("point", "hard", light, CASTER, p, (0.0, 0.0))
    assert not out.requires_grad


@pytest.mark.parametrize("filt", ["hard", "pcf", "pcss", "vsm"])
def test_light_intensity_gradient_is_exact(filt):
    """The visibility multiplies the illuminance: the image is linear in the intensity,
    so the analytic derivative equals a finite difference of any step."""
    floor = torch.tensor([[-1.5, 0, -1.5], [1.5, 0, -1.5], [1.5, 0, 1.5], [-1.5, 0, 1.5]],
                         dtype=F64)
    pos = torch.cat([CASTER, floor])
    faces = torch.cat([FACES, torch.tensor([[4, 6, 5], [4, 7, 6]])])
    cast = torch.tensor([True, True, False, False])
    scene = tr.RenderScene(pos, faces, materials=[tr.Material(roughness_factor=0.8)],
                           cast_shadows=cast)
    st = ShadowSettings(map_size=SIZE, filter=filt)
    renderer = tr.Renderer(16, shadows=st)
    w = torch.rand(1, 3, 16, 16, dtype=F64, generator=torch.Generator().manual_seed(1))

    def f(i):
        lights = tr.Lights(point=tr.PointLights(
            position=torch.tensor([[LIGHT["point"]]], dtype=F64),
            color=torch.ones(1, 1, 3, dtype=F64), intensity=i.view(1, 1),
            cast_shadows=torch.ones(1, 1, dtype=torch.bool), shadow=st))
        return (renderer(scene, *CAM, lights).image * w).sum()

    i0 = torch.tensor(5.0, dtype=F64, requires_grad=True)
    a = float(torch.autograd.grad(f(i0), i0)[0])
    with torch.no_grad():
        ref = float((f(i0 + 1.0) - f(i0 - 1.0)) / 2.0)
    assert ref > 0
    assert a == pytest.approx(ref, rel=1e-9)
