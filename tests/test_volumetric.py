"""Volumetric fog and light shafts (torchraster.shading.volumetric) against independent
references: numeric quadratures of the optical depth and of the phase function, a
brute-force float64 march with numerically integrated transmittance
(torchraster.testing.reference_fog), and a light shaft through a hole checked against the
analytic visibility of the hole."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

import torchraster as tr
from torchraster.renderer import camera_position, view_rays
from torchraster.shading.lights import sh_basis
from torchraster.shading.volumetric import (
    Fog,
    ambient_inscatter,
    apply_fog,
    fog_terms,
    fog_transmittance,
    hg_phase,
    interleaved_gradient_noise,
    light_optical_depth,
    light_source,
    light_transmittance,
    march_inscatter,
    optical_depth,
)
from torchraster.testing import reference_fog as ref

F64 = torch.float64


def _density(a: float, b: float, y0: float):
    return lambda y: a * torch.exp(-b * (y - y0))


# ------------------------------------------------------------------ closed forms


@pytest.mark.parametrize("b", [0.0, 0.3, 2.0])
@pytest.mark.parametrize("oy", [-1.0, 0.5, 3.0])
def test_optical_depth_matches_quadrature(b: float, oy: float):
    fog = Fog(density=0.4, height_falloff=b, base_height=0.5)
    dy = torch.tensor([-1.0, -0.6, -1e-7, 0.0, 1e-9, 0.2, 0.9, 1.0], dtype=F64).view(1, 1, 1, -1)
    s = torch.tensor([0.0, 0.01, 1.0, 7.5], dtype=F64).view(1, 1, -1, 1).expand(1, 1, 4, 8)
    o = torch.full((1, 1, 1, 1), oy, dtype=F64)
    got = optical_depth(o, dy, s, fog)
    want = ref.optical_depth_quadrature(o, dy, s, _density(0.4, b, 0.5), steps=20000)
    torch.testing.assert_close(got, want, rtol=1e-7, atol=1e-12)


def test_infinite_rays():
    """An infinite ray climbing out of height fog has tau = rho_o / (b v_y); any other is
    opaque (or empty where the density is 0)."""
    fog = Fog(density=0.4, height_falloff=0.5, base_height=0.0)
    o = torch.ones(1, 1, 1, 1, dtype=F64)
    dy = torch.tensor([0.5, 0.0, -0.5], dtype=F64).view(1, 1, 1, 3)
    tau = optical_depth(o, dy, torch.full_like(dy, math.inf), fog)
    long = ref.optical_depth_quadrature(o, dy[..., :1], torch.full_like(dy[..., :1], 200.0),
                                        _density(0.4, 0.5, 0.0), steps=200000)
    torch.testing.assert_close(tau[..., :1], long, rtol=1e-6, atol=0)
    assert torch.isinf(tau[..., 1:]).all()
    zero = optical_depth(o, dy, torch.full_like(dy, math.inf), Fog(density=0.0))
    assert (zero == 0).all()


def test_hg_phase_normalised_and_isotropic():
    # integral over the sphere = 2 pi integral_{-1}^{1} p(mu) dmu (Simpson, many nodes)
    mu = torch.linspace(-1, 1, 200001, dtype=F64)
    w = torch.ones_like(mu)
    w[1:-1:2], w[2:-1:2] = 4, 2
    for g in (-0.9, -0.3, 0.0, 0.5, 0.9, 0.99):
        p = hg_phase(mu, g)
        total = 2 * math.pi * float((p * w).sum() * (mu[1] - mu[0]) / 3)
        # (g = 0.99 peaks at 4e4 / sr: the uniform quadrature itself is off by 5e-5 there)
        assert abs(total - 1) < (1e-4 if abs(g) > 0.95 else 1e-6), (g, total)
        torch.testing.assert_close(p, ref.hg_phase_reference(mu, g))
        if g > 0:
            assert float(p[-1]) > float(p[0])  # forward scattering
    torch.testing.assert_close(hg_phase(mu, 0.0), torch.full_like(mu, 1 / (4 * math.pi)))


def test_ambient_inscatter_is_the_hg_convolution():
    """Funk-Hecke (SH band l scaled by g^l) against a quadrature over the sphere of the SH
    radiance times the phase."""
    sh = torch.randn(1, 9, 3, dtype=F64) * 0.3
    sh[:, 0] += 1.0
    n_t, n_p = 400, 800
    theta = (torch.arange(n_t, dtype=F64) + 0.5) * math.pi / n_t
    phi = (torch.arange(n_p, dtype=F64) + 0.5) * 2 * math.pi / n_p
    th, ph = torch.meshgrid(theta, phi, indexing="ij")
    w = torch.stack([torch.sin(th) * torch.cos(ph), torch.sin(th) * torch.sin(ph),
                     torch.cos(th)])  # (3, T, P)
    d_omega = torch.sin(th) * (math.pi / n_t) * (2 * math.pi / n_p)
    radiance = torch.einsum("khw,kc->chw", sh_basis(w), sh[0])  # (3, T, P)
    views = torch.nn.functional.normalize(torch.randn(3, 5, dtype=F64), dim=0)
    for g in (0.0, 0.4, -0.7):
        got = ambient_inscatter(sh, views.view(1, 3, 1, 5), g)[0, :, 0]  # (3, 5)
        for k in range(5):
            p = hg_phase(torch.einsum("c,chw->hw", views[:, k], w), g)
            want = (radiance * p * d_omega).sum((-2, -1)).clamp_min(0)
            torch.testing.assert_close(got[:, k], want, rtol=2e-3, atol=1e-4)
    const = torch.zeros(1, 9, 3, dtype=F64)
    const[:, 0] = 0.7 / 0.28209479177387814  # constant radiance 0.7
    torch.testing.assert_close(ambient_inscatter(const, views.view(1, 3, 1, 5), 0.8),
                               torch.full((1, 3, 1, 5), 0.7, dtype=F64))


# ------------------------------------------------------------------------- march


def _point_light(dtype=F64) -> tr.Lights:
    return tr.Lights(point=tr.PointLights(
        position=torch.tensor([[[0.3, 1.5, 0.0]]], dtype=dtype),
        color=torch.tensor([[[1.0, 0.8, 0.6]]], dtype=dtype),
        intensity=torch.tensor([[5.0]], dtype=dtype)))


def _rays(h: int, w: int, dtype=F64) -> torch.Tensor:
    g = torch.Generator().manual_seed(3)
    return torch.nn.functional.normalize(torch.randn(1, 3, h, w, generator=g, dtype=dtype),
                                         dim=1)


def test_constant_source_is_exact_at_any_step_count():
    fog = Fog(density=0.5, height_falloff=0.8, base_height=0.2, color=(0.9, 0.5, 0.2))
    eye = torch.tensor([[0.0, 1.0, 3.0]], dtype=F64)
    rays = _rays(4, 5)
    end = torch.full((1, 1, 4, 5), 4.0, dtype=F64)
    start = torch.zeros_like(end)
    one = torch.ones(1, 3, 4, 5, dtype=F64)
    want = fog.param("color", rays) * (1 - fog_transmittance(eye[:, 1, None, None, None],
                                                              rays[:, 1:2], end, fog))
    for steps in (1, 3, 17):
        got = march_inscatter(eye, rays, start, end, fog, lambda p, v: one, steps=steps)
        torch.testing.assert_close(got, want * one)


@pytest.mark.parametrize("jitter", [False, True])
def test_march_converges_to_brute_force(jitter: bool):
    fog = Fog(density=0.3, height_falloff=0.7, base_height=0.5, color=(0.9, 0.8, 0.7),
              anisotropy=0.4)
    eye = torch.tensor([[0.0, 1.0, 4.0]], dtype=F64)
    rays = _rays(6, 6)
    src = light_source(_point_light(), rays, 0.4)
    start = torch.full((1, 1, 6, 6), 0.5, dtype=F64)
    end = torch.full((1, 1, 6, 6), 6.0, dtype=F64)
    want = ref.march_reference(eye, rays, start, end, _density(0.3, 0.7, 0.5),
                               torch.tensor([0.9, 0.8, 0.7]), src, steps=1024)
    errs = []
    for steps in (4, 16, 64, 256):
        got = march_inscatter(eye, rays, start, end, fog, src, steps=steps, jitter=jitter)
        errs.append(float((got - want).abs().mean() / want.abs().mean()))
    assert errs[-1] < (2e-3 if jitter else 1e-4), errs
    assert errs[-1] < errs[1] < errs[0], errs


def test_noise_is_deterministic_and_spread():
    a = interleaved_gradient_noise(32, 32)
    assert torch.equal(a, interleaved_gradient_noise(32, 32))
    assert not torch.equal(a, interleaved_gradient_noise(32, 32, seed=1))
    assert 0 <= float(a.min()) and float(a.max()) < 1
    assert abs(float(a.mean()) - 0.5) < 0.02
    hist = torch.histc(a, bins=8, min=0, max=1)
    assert float(hist.min()) > 0.7 * 32 * 32 / 8


# ------------------------------------------------------------------- light shafts

HOLE, PLANE_Y, EXTENT = 0.4, 2.0, 4.0
SUN_DIR = (0.3, -1.0, 0.0)


def _plate_with_hole() -> tr.RenderScene:
    """A square plate (y = 2, +-4 m) with a square hole (+-0.4 m) in the middle."""
    h, e, y = HOLE, EXTENT, PLANE_Y
    quads = [(-e, -e, e, -h), (-e, h, e, e), (-e, -h, -h, h), (h, -h, e, h)]  # x0 z0 x1 z1
    pos, faces = [], []
    for x0, z0, x1, z1 in quads:
        k = len(pos)
        pos += [(x0, y, z0), (x0, y, z1), (x1, y, z1), (x1, y, z0)]
        faces += [(k, k + 1, k + 2), (k, k + 2, k + 3)]
    return tr.RenderScene.from_mesh(tr.Mesh(torch.tensor(pos), torch.tensor(faces)))


def _hole_visibility(p: torch.Tensor) -> torch.Tensor:
    """Analytic sun visibility ``(B, 1, H, W)`` of points ``(B, 3, H, W)``."""
    d = torch.tensor(SUN_DIR, dtype=p.dtype).view(1, 3, 1, 1)
    t = (PLANE_Y - p[:, 1:2]) / (-d[:, 1:2])  # along -d up to the plate
    q = p - d * t
    inside_hole = (q[:, 0:1].abs() < HOLE) & (q[:, 2:3].abs() < HOLE)
    off_plate = (q[:, 0:1].abs() > EXTENT) | (q[:, 2:3].abs() > EXTENT)
    return ((p[:, 1:2] >= PLANE_Y) | inside_hole | off_plate).to(p.dtype)


def test_light_shaft_only_under_the_hole():
    """A sun above a plate with a hole: the fog is lit only in the column under the hole,
    as the analytic visibility says (the march through the shadow map against a brute-force
    march with exact visibility)."""
    size, g = 32, 0.3
    # (homogeneous fog absorbs the sun on its way in: the shaft's geometry is tested without
    # the light path, which has its own tests below)
    fog = Fog(density=0.2, anisotropy=g, steps=64, jitter=False, blur=0.0, max_distance=5.0,
              light_transmittance=False)
    view = tr.camera.look_at([0.0, 1.0, 3.5], [0.0, 1.3, 0.0])
    proj = tr.camera.perspective(50.0, 1.0, 0.1)
    sun = tr.DirectionalLights(direction=torch.tensor([[SUN_DIR]]),
                               color=torch.ones(1, 1, 3), intensity=torch.tensor([[2.0]]),
                               cast_shadows=torch.tensor([[True]]),
                               shadow=tr.shading.shadows.ShadowSettings(map_size=512))
    lights = tr.Lights(directional=sun)
    scene = _plate_with_hole()
    out = tr.Renderer(size, fog=fog)(scene, view, proj, lights, channels={"position"})
    assert any(s.startswith("fog march 64 steps: directional[0] shadowed") for s in out.plan)
    # reference: the same rays, distances and light, exact visibility, 1024 steps
    v64, p64 = view.reshape(-1, 4, 4).double(), proj.reshape(-1, 4, 4).double()
    eye, rays = camera_position(v64), view_rays(v64, p64, (size, size))
    dist = (out.gbuffer["position"].double() - eye[:, :, None, None]).norm(dim=1, keepdim=True)
    dist = torch.where(out.alpha > 0, dist, torch.full_like(dist, 5.0))
    l_dir = -torch.nn.functional.normalize(torch.tensor(SUN_DIR, dtype=F64), dim=0)
    phase = ref.hg_phase_reference((rays * l_dir.view(1, 3, 1, 1)).sum(1, keepdim=True), g)

    def source(p, valid):
        return 2.0 * phase * _hole_visibility(p) * torch.ones_like(p)

    want = ref.march_reference(eye, rays, torch.zeros_like(dist), dist, _density(0.2, 0, 0),
                               torch.ones(3), source, steps=1024)
    plain = tr.Renderer(size)(scene, view, proj, lights).image.double()  # the plate's shading
    got = out.image.double() - torch.exp(-0.2 * dist) * plain
    lit = want[:, 1] > 0.02 * float(want.max())
    near_lit = torch.nn.functional.max_pool2d(lit[:, None].double(), 5, 1, 2)[:, 0] > 0
    assert 0.05 < float(lit.double().mean()) < 0.5  # a shaft, not everything or nothing
    assert float(got[:, 1][~near_lit].abs().max()) < 0.01 * float(want.max())
    assert float(got[:, 1][lit].mean()) > 0.5 * float(want[:, 1][lit].mean())
    rel = float((got - want).abs().mean() / want.abs().mean())
    assert rel < 0.1, rel


# ---------------------------------------------------------------- gradients, stress


def test_gradcheck_density_colour_anisotropy():
    eye = torch.tensor([[0.0, 1.0, 3.0]], dtype=F64)
    rays = _rays(2, 3)
    dist = torch.tensor([[[[2.0, 3.0, math.inf], [1.0, 5.0, 0.5]]]], dtype=F64)
    image = torch.rand(1, 3, 2, 3, dtype=F64)
    lights = _point_light()
    lights.ambient = tr.sh_from_color(torch.tensor([[0.2, 0.3, 0.4]], dtype=F64))
    lights.directional = tr.DirectionalLights(direction=torch.tensor([[[0.2, -1.0, 0.1]]],
                                                                      dtype=F64),
                                              color=torch.ones(1, 1, 3, dtype=F64),
                                              intensity=torch.tensor([[1.5]], dtype=F64))

    def f(density, color, g, falloff):
        fog = Fog(density=density, color=color, anisotropy=g, height_falloff=falloff,
                  base_height=0.3, steps=4, blur=1.0, max_distance=20.0)
        return apply_fog(image, dist, eye, rays, fog, lights)

    args = (torch.tensor(0.3, dtype=F64, requires_grad=True),
            torch.tensor([0.9, 0.7, 0.5], dtype=F64, requires_grad=True),
            torch.tensor(0.4, dtype=F64, requires_grad=True),
            torch.tensor(0.6, dtype=F64, requires_grad=True))
    assert torch.autograd.gradcheck(f, args)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_stress_inputs_stay_finite(dtype):
    """Empty frames (all sky, infinite), camera in dense fog, horizontal and grazing rays,
    huge distances, steep height falloff: finite values and gradients."""
    h, w = 4, 6
    rays = _rays(h, w, dtype)
    rays[:, :, 0, :] = torch.tensor([1.0, 0.0, 0.0], dtype=dtype).view(1, 3, 1)  # horizontal
    rays[:, :, 1, :] = torch.nn.functional.normalize(torch.tensor(
        [1.0, 1e-7, 0.0], dtype=dtype), dim=0).view(1, 3, 1)  # grazing
    lights = _point_light(dtype)
    lights.ambient = tr.sh_from_color(torch.tensor([[0.2, 0.3, 0.4]], dtype=dtype))
    cases = [(math.inf, 0.1, 0.0), (math.inf, 0.1, 0.5), (1e30, 50.0, 3.0),
             (1e3, 1e3, 0.0), (2.0, 1e-30, 1e4), (1e6, 0.2, 100.0)]
    for dist_value, density, falloff in cases:
        for eye_y in (-50.0, 1.0, 80.0):
            d = torch.tensor(density, dtype=dtype, requires_grad=True)
            b = torch.tensor(falloff, dtype=dtype, requires_grad=True)
            fog = Fog(density=d, height_falloff=b, steps=4, blur=1.0)
            eye = torch.tensor([[0.0, eye_y, 0.0]], dtype=dtype)
            dist = torch.full((1, 1, h, w), dist_value, dtype=dtype)
            image = torch.ones(1, 3, h, w, dtype=dtype, requires_grad=True)
            out = apply_fog(image, dist, eye, rays, fog, lights)
            assert torch.isfinite(out).all(), (dist_value, density, falloff, eye_y)
            out.sum().backward()
            for t in (d, b, image):
                assert torch.isfinite(t.grad).all(), (dist_value, density, falloff, eye_y)


def test_horizontal_limit_is_continuous():
    fog = Fog(density=0.3, height_falloff=5.0)
    o = torch.ones(1, 1, 1, 1, dtype=F64)
    dy = torch.tensor([0.0, 1e-12, 1e-9, 1e-6, 1e-5, 2e-5], dtype=F64).view(1, 1, 1, -1)
    s = torch.full_like(dy, 3.0)
    want = ref.optical_depth_quadrature(o, dy, s, _density(0.3, 5.0, 0.0), steps=4000)
    torch.testing.assert_close(optical_depth(o, dy, s, fog), want, rtol=1e-7, atol=0)


def test_renderer_empty_and_all_sky_frames():
    """A frame that sees nothing (the scene behind the camera) and fog with lights that
    cast: finite, and the fog of an infinite sky in homogeneous fog is opaque in-scatter."""
    scene = _plate_with_hole()
    view = tr.camera.look_at([0.0, 1.0, 10.0], [0.0, 1.0, 20.0])
    proj = tr.camera.perspective(40.0, 1.0, 0.1)
    sun = tr.DirectionalLights(direction=torch.tensor([[SUN_DIR]]), color=torch.ones(1, 1, 3),
                               intensity=torch.tensor([[2.0]]),
                               cast_shadows=torch.tensor([[True]]))
    amb = tr.sh_from_color(torch.tensor([[0.1, 0.1, 0.1]]))
    for fog in (Fog(density=0.2), Fog(density=0.2, height_falloff=1.0), Fog(density=1e4)):
        out = tr.Renderer(8, fog=fog)(scene, view, proj, tr.Lights(ambient=amb, directional=sun))
        assert (out.alpha == 0).all() and torch.isfinite(out.image).all()
        if fog.height_falloff == 0:  # opaque fog: ambient + the sun's in-scattering
            assert float(out.image.min()) > 0.1


# ------------------------------------------------------------------------ planner


def test_plan_skips_fog_unless_asked_and_reports_it():
    scene = _plate_with_hole()
    sun = tr.DirectionalLights(direction=torch.tensor([[SUN_DIR]]), color=torch.ones(1, 1, 3),
                               intensity=torch.tensor([[2.0]]))
    lights = tr.Lights(directional=sun, point=_point_light(torch.float32).point)
    plan = tr.Renderer(8).plan(scene, lights)
    assert plan.fog == () and not any("fog" in s for s in plan)
    plan = tr.Renderer(8, fog=Fog(steps=8)).plan(scene, lights)
    assert "position" in plan.channels
    assert plan.fog == ("fog analytic (directional[0])", "fog march 8 steps jittered: point[0]",
                        "fog blur 1 px", "fog light path: directional[0], point[0]")
    plan = tr.Renderer(8, fog=Fog(steps=8, light_transmittance=False)).plan(scene, lights)
    assert not any("light path" in s for s in plan.fog)
    assert all(s in plan for s in plan.fog)
    # shadow maps are rendered for the shafts even when no face receives shadows
    sun.cast_shadows = torch.tensor([[True]])
    scene.receive_shadows = torch.zeros(scene.faces.shape[0], dtype=torch.bool)
    assert tr.Renderer(8).plan(scene, lights).shadow_lights == ()
    plan = tr.Renderer(8, fog=Fog(blur=0.0)).plan(scene, lights)
    assert plan.shadow_lights and plan.fog[1].endswith("directional[0] shadowed, point[0]")
    assert len(plan.fog) == 3
    only_ambient = tr.Renderer(8, fog=Fog()).plan(scene, tr.Lights(ambient=tr.sh_from_color(
        torch.ones(1, 3))))
    assert only_ambient.fog == ("fog analytic (ambient)",)


def test_bad_fog_arguments_name_the_field():
    for kwargs, name in (({"density": -1.0}, "density"), ({"anisotropy": 1.0}, "anisotropy"),
                         ({"color": (1, 2)}, "color"), ({"steps": 0}, "steps"),
                         ({"blur": -1}, "blur"), ({"max_distance": 0}, "max_distance"),
                         ({"height_falloff": math.nan}, "height_falloff"),
                         ({"jitter": 1}, "jitter"), ({"seed": -1}, "seed")):
        with pytest.raises(ValueError, match=f"Fog.{name}"):
            Fog(**kwargs)
    with pytest.raises(TypeError, match="fog"):
        tr.Renderer(8, fog={"density": 1.0})
    with pytest.raises(ValueError, match="distance"):
        fog_terms(-torch.ones(1, 1, 2, 2), torch.zeros(1, 3), _rays(2, 2, torch.float32), Fog())


def test_blur_keeps_depth_edges_and_flat_regions():
    from torchraster.shading.volumetric import depth_aware_blur

    x = torch.zeros(1, 3, 12, 12, dtype=F64)
    x[..., :6] = 1.0 + 0.2 * torch.rand(1, 3, 12, 6, dtype=F64)  # noisy near region
    dist = torch.full((1, 1, 12, 12), 10.0, dtype=F64)
    dist[..., :6] = 1.0
    out = depth_aware_blur(x, dist, 2.0)
    assert float(out[..., 6:].abs().max()) < 1e-12  # nothing crosses the depth edge
    assert float(out[..., :6].std()) < 0.5 * float(x[..., :6].std())  # the noise is smoothed
    torch.testing.assert_close(depth_aware_blur(torch.ones_like(x), dist, 2.0), torch.ones_like(x))
    assert torch.equal(depth_aware_blur(x, dist, 0.0), x)


def test_renderer_fog_gradients_reach_fog_and_lights():
    scene = _plate_with_hole()
    view = tr.camera.look_at([0.0, 1.0, 3.5], [0.0, 1.3, 0.0])
    proj = tr.camera.perspective(50.0, 1.0, 0.1)
    density = torch.tensor(0.2, requires_grad=True)
    intensity = torch.tensor([[2.0]], requires_grad=True)
    sun = tr.DirectionalLights(direction=torch.tensor([[SUN_DIR]]), color=torch.ones(1, 1, 3),
                               intensity=intensity, cast_shadows=torch.tensor([[True]]))
    falloff = torch.tensor(0.5, requires_grad=True)
    out = tr.Renderer(8, fog=Fog(density=density, height_falloff=falloff, steps=4))(
        scene, view, proj, tr.Lights(directional=sun))
    out.image.sum().backward()
    for t in (density, falloff, intensity):
        assert torch.isfinite(t.grad).all() and float(t.grad.abs().sum()) > 0


def test_the_shipped_fog_config_renders():
    """configs/fog.yaml (small): the window room from box primitives, with light shafts."""
    from pathlib import Path

    cfg = tr.load_config(Path(__file__).resolve().parents[1] / "configs" / "fog.yaml")
    tr.config.check_config(cfg)
    cfg.render.resolution = 16
    (view,) = tr.render_config(cfg)
    assert any(s.startswith("fog march 16 steps jittered: directional[0] shadowed")
               for s in view.plan)
    assert bool(torch.isfinite(view.images["color"]).all())


# ----------------------------------------------------------- light path (issue 21)


def _sun(direction, intensity=2.0, dtype=F64, grad=False) -> tr.DirectionalLights:
    d = torch.tensor([[direction]], dtype=dtype, requires_grad=grad)
    return tr.DirectionalLights(direction=d, color=torch.ones(1, 1, 3, dtype=dtype),
                                intensity=torch.tensor([[intensity]], dtype=dtype))


def _bulb(position, intensity=5.0, dtype=F64, grad=False) -> tr.PointLights:
    p = torch.tensor([[position]], dtype=dtype, requires_grad=grad)
    return tr.PointLights(position=p, color=torch.ones(1, 1, 3, dtype=dtype),
                          intensity=torch.tensor([[intensity]], dtype=dtype))


def _points(dtype=F64) -> torch.Tensor:
    g = torch.Generator().manual_seed(5)
    p = torch.rand(1, 3, 3, 4, generator=g, dtype=dtype) * 4 - 2
    p[:, 1] = torch.linspace(-1.0, 2.5, 12, dtype=dtype).view(3, 4)
    return p


SUNS = [(0.3, -1.0, 0.2), (1.0, -0.1, 0.0), (0.2, -0.01, 1.0), (1.0, 0.0, 0.0),
        (0.5, 0.4, 0.0), (0.0, 1.0, 0.0)]  # climbing, grazing, horizon, below the horizon
BULBS = [(0.3, 2.0, -0.5), (1.0, -1.5, 0.0), (4.0, 0.7, 1.0), (0.0, 0.5, 0.0)]


@pytest.mark.parametrize("b", [0.0, 0.6, 3.0])
def test_light_transmittance_matches_quadrature(b: float):
    """Closed-form light-path optical depth against the midpoint rule: directional lights
    (the ray up to far = 80 / (b l_y), where the fog has thinned out by e^-80) and point
    lights (the segment), for homogeneous and height fog; the sun at or below the horizon
    (and any sun in homogeneous fog) is opaque."""
    fog = Fog(density=0.4, height_falloff=b, base_height=0.5)
    dens = _density(0.4, b, 0.5)
    p = _points()
    for sun in SUNS:
        got = light_optical_depth(p, "directional", _sun(sun), fog)[:, 0]
        l_y = -sun[1] / math.sqrt(sum(c * c for c in sun))
        if b == 0 or l_y <= 0:
            assert torch.isinf(got).all(), (b, sun)
            assert (light_transmittance(p, "directional", _sun(sun), fog) == 0).all()
            continue
        want = ref.light_optical_depth_reference(p, dens, direction=sun, far=80 / (b * l_y),
                                                 steps=40000)
        torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-12)
    for bulb in BULBS:
        got = light_optical_depth(p, "point", _bulb(bulb), fog)[:, 0]
        want = ref.light_optical_depth_reference(p, dens, position=bulb, steps=20000)
        torch.testing.assert_close(got, want, rtol=1e-7, atol=1e-12)
        spot = tr.SpotLights(position=torch.tensor([[bulb]], dtype=F64),
                             direction=torch.tensor([[[0.0, -1.0, 0.0]]], dtype=F64),
                             color=torch.ones(1, 1, 3, dtype=F64),
                             intensity=torch.ones(1, 1, dtype=F64))
        torch.testing.assert_close(light_optical_depth(p, "spot", spot, fog)[:, 0], got)


def test_light_transmittance_homogeneous_and_flat_limits_are_exact():
    """Homogeneous fog: T = exp(-a d) along any segment; a horizontal segment in height fog:
    T = exp(-rho(y) d); a point at the light: T = 1."""
    p = _points()
    bulb = (0.7, 1.1, -0.4)
    d = (torch.tensor(bulb, dtype=F64).view(1, 3, 1, 1) - p).norm(dim=1, keepdim=True)
    got = light_transmittance(p, "point", _bulb(bulb), Fog(density=0.35))[:, 0]
    torch.testing.assert_close(got, torch.exp(-0.35 * d), rtol=1e-14, atol=0)
    flat = p.clone()
    flat[:, 1] = 1.1  # the light's height
    fog = Fog(density=0.35, height_falloff=1.7, base_height=0.2)
    d = (torch.tensor(bulb, dtype=F64).view(1, 3, 1, 1) - flat).norm(dim=1, keepdim=True)
    want = torch.exp(-0.35 * math.exp(-1.7 * 0.9) * d)
    torch.testing.assert_close(light_transmittance(flat, "point", _bulb(bulb), fog)[:, 0], want,
                               rtol=1e-14, atol=0)
    at = torch.tensor(bulb, dtype=F64).view(1, 3, 1, 1)
    assert float(light_transmittance(at, "point", _bulb(bulb), fog)) == 1.0
    # switched off: 1 everywhere
    off = Fog(density=0.35, light_transmittance=False)
    assert (light_transmittance(p, "directional", _sun(SUNS[0]), off) == 1).all()


def _view_cases():
    """Eye at y = 1, rays with v_y below / equal to / above the sun's l_y (= 0.6), level,
    and the distances: finite, and infinite (the sky) for climbing and level rays."""
    vy = [-0.8, -0.3, 0.0, 0.3, 0.6, 0.6, 0.9, 0.3, 0.0, 0.95, -0.5]
    dist = [6.0, 3.0, 5.0, 8.0, 4.0, 0.0, 10.0, math.inf, math.inf, math.inf, math.inf]
    rays = torch.tensor([[math.sqrt(1 - y * y), y, 0.0] for y in vy], dtype=F64).T
    return rays.reshape(1, 3, 1, -1), torch.tensor(dist, dtype=F64).view(1, 1, 1, -1)


def test_directional_inscatter_is_the_integral_along_the_view_ray():
    """The closed-form in-scattering of an unshadowed sun dimmed on its way in, against the
    brute-force march of the sun's source with a numerically integrated light path (infinite
    view rays marched up to where the fog has thinned out, or become opaque)."""
    a, b, y0, g = 0.3, 0.7, 0.5, 0.4
    sun = (0.0, -0.6, 0.8)  # l_y = 0.6
    fog = Fog(density=a, height_falloff=b, base_height=y0, anisotropy=g, color=(0.9, 0.8, 0.7),
              steps=4)
    eye = torch.tensor([[0.0, 1.0, 0.0]], dtype=F64)
    rays, dist = _view_cases()
    lights = tr.Lights(directional=_sun(sun))
    got = fog_terms(dist, eye, rays, fog, lights).analytic
    dens = _density(a, b, y0)
    # brute force: truncate infinite rays where the rest is below 1e-12 of the integral
    vy = rays[:, 1:2]
    rho_eye = a * math.exp(-b * (1.0 - y0))
    # (climbing: e^-40 of the density left; level: tau = 40; falling: tau > 100 by 15 m)
    far = torch.where(vy > 0, 40 / (b * vy.clamp_min(1e-9)), torch.full_like(vy, 40 / rho_eye))
    far = torch.where(vy < 0, torch.full_like(vy, 15.0), far)
    end = torch.where(torch.isinf(dist), far, dist)
    src = ref.punctual_source_reference(rays, g, torch.full((3,), 2.0), dens, direction=sun,
                                        far=40 / (b * 0.6), steps=3000)
    want = ref.march_reference(eye, rays, torch.zeros_like(end), end, dens,
                               torch.tensor([0.9, 0.8, 0.7]), src, steps=3000)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-12)
    # the same rays without the light path: 1 - T_v of the undimmed source
    off = fog_terms(dist, eye, rays, dataclasses.replace(fog, light_transmittance=False),
                    lights).analytic
    src_off = ref.punctual_source_reference(rays, g, torch.full((3,), 2.0), dens,
                                            direction=sun, dimmed=False)
    want_off = ref.march_reference(eye, rays, torch.zeros_like(end), end, dens,
                                   torch.tensor([0.9, 0.8, 0.7]), src_off, steps=4000)
    torch.testing.assert_close(off, want_off, rtol=1e-5, atol=1e-12)
    assert bool((off > got).all() | (dist == 0).any())  # dimming only removes light


def test_sun_in_homogeneous_fog_or_below_the_horizon_adds_nothing():
    eye = torch.tensor([[0.0, 1.0, 0.0]], dtype=F64)
    rays, dist = _view_cases()
    for fog, sun in ((Fog(density=0.3), SUNS[0]),
                     (Fog(density=0.3, height_falloff=0.5), (1.0, 0.2, 0.0)),
                     (Fog(density=0.3, height_falloff=0.5), (1.0, 0.0, 0.0))):
        t = fog_terms(dist, eye, rays, fog, tr.Lights(directional=_sun(sun)))
        assert (t.analytic == 0).all() and torch.isfinite(t.transmittance).all()


@pytest.mark.parametrize("jitter", [False, True])
def test_march_with_light_path_converges_to_brute_force(jitter: bool):
    """Point light dimmed on the way to every fog sample: the engine's march against the
    brute-force march whose source integrates each sample's light path numerically."""
    a, b, y0, g = 0.3, 0.7, 0.5, 0.4
    fog = Fog(density=a, height_falloff=b, base_height=y0, color=(0.9, 0.8, 0.7), anisotropy=g)
    eye = torch.tensor([[0.0, 1.0, 4.0]], dtype=F64)
    rays = _rays(5, 5)
    light = (0.3, 1.5, 0.0)
    src = light_source(tr.Lights(point=_bulb(light)), rays, g, fog=fog)
    start = torch.full((1, 1, 5, 5), 0.5, dtype=F64)
    end = torch.full((1, 1, 5, 5), 6.0, dtype=F64)
    want = ref.march_reference(eye, rays, start, end, _density(a, b, y0),
                               torch.tensor([0.9, 0.8, 0.7]),
                               ref.punctual_source_reference(rays, g, torch.full((3,), 5.0),
                                                             _density(a, b, y0),
                                                             position=light, steps=512),
                               steps=1024)
    got = march_inscatter(eye, rays, start, end, fog, src, steps=256, jitter=jitter)
    rel = float((got - want).abs().mean() / want.abs().mean())
    assert rel < (2e-3 if jitter else 1e-4), rel
    undimmed = march_inscatter(eye, rays, start, end, fog, light_source(
        tr.Lights(point=_bulb(light)), rays, g), steps=256, jitter=jitter)
    assert float((undimmed - want).abs().mean() / want.abs().mean()) > 0.05  # it matters


def _floor(size: float = 6.0) -> tr.RenderScene:
    pos = torch.tensor([(-size, 0.0, -size), (-size, 0.0, size), (size, 0.0, size),
                        (size, 0.0, -size)])
    return tr.RenderScene.from_mesh(tr.Mesh(pos, torch.tensor([(0, 1, 2), (0, 2, 3)])))


@pytest.mark.parametrize("kind", ["directional", "point"])
def test_surface_lighting_is_dimmed_by_the_light_path(kind: str):
    """A floor lit through height fog that scatters nothing (colour 0): the fogged image
    with the light path over the one without is the light's transmittance from each floor
    point, against the midpoint quadrature at the same points."""
    a, b, y0 = 0.25, 0.4, 0.0
    view = tr.camera.look_at([0.0, 2.0, 4.0], [0.0, 0.0, 0.0])
    proj = tr.camera.perspective(60.0, 1.0, 0.1)
    sun, bulb = (0.4, -0.7, -0.3), (0.5, 2.5, -0.5)
    lights = tr.Lights(directional=_sun(sun, dtype=torch.float32)) if kind == "directional" \
        else tr.Lights(point=_bulb(bulb, dtype=torch.float32))
    fog = Fog(density=a, height_falloff=b, base_height=y0, color=(0.0, 0.0, 0.0))
    on = tr.Renderer(16, fog=fog)(_floor(), view, proj, lights, channels={"position"})
    off = tr.Renderer(16, fog=dataclasses.replace(fog, light_transmittance=False))(
        _floor(), view, proj, lights)
    assert on.plan.fog[-1] == f"fog light path: {kind}[0]"
    lit = (on.alpha[:, 0] > 0) & (off.image[:, 1] > 1e-4)
    assert float(lit.double().mean()) > 0.5
    ratio = (on.image / off.image.clamp_min(1e-12))[:, 1][lit].double()
    p = on.gbuffer["position"].double()
    if kind == "directional":
        l_y = 0.7 / math.sqrt(0.4**2 + 0.7**2 + 0.3**2)
        tau = ref.light_optical_depth_reference(p, _density(a, b, y0), direction=sun,
                                                far=80 / (b * l_y))
    else:
        tau = ref.light_optical_depth_reference(p, _density(a, b, y0), position=bulb)
    torch.testing.assert_close(ratio, torch.exp(-tau)[:, 0][lit], rtol=2e-5, atol=0)
    assert float(ratio.max()) < 0.9  # the fog did dim it


def test_gradcheck_light_path():
    """Light-path transmittance (surface hook) and the fogged image (analytic sun, marched
    point light, both dimmed) w.r.t. fog density and falloff, sun direction and light
    position."""
    from torchraster.shading.volumetric import surface_light_hook

    p = _points()[..., :2, :3]
    eye = torch.tensor([[0.0, 1.0, 3.0]], dtype=F64)
    rays = _rays(2, 3)
    dist = torch.tensor([[[[2.0, 3.0, math.inf], [1.0, 5.0, 0.5]]]], dtype=F64)
    image = torch.rand(1, 3, 2, 3, dtype=F64)

    def f(density, falloff, direction, position):
        lights = tr.Lights(directional=tr.DirectionalLights(
            direction=direction.view(1, 1, 3), color=torch.ones(1, 1, 3, dtype=F64),
            intensity=torch.tensor([[1.5]], dtype=F64)), point=tr.PointLights(
            position=position.view(1, 1, 3), color=torch.ones(1, 1, 3, dtype=F64),
            intensity=torch.tensor([[4.0]], dtype=F64)))
        fog = Fog(density=density, height_falloff=falloff, base_height=0.3, anisotropy=0.3,
                  steps=3, blur=0.0, max_distance=30.0)
        hook = surface_light_hook(fog, lights, p)
        return (hook("directional", slice(0, 1)), hook("point", slice(0, 1)),
                apply_fog(image, dist, eye, rays, fog, lights))

    args = (torch.tensor(0.3, dtype=F64, requires_grad=True),
            torch.tensor(0.6, dtype=F64, requires_grad=True),
            torch.tensor([0.2, -1.0, 0.1], dtype=F64, requires_grad=True),
            torch.tensor([0.4, 1.8, -0.2], dtype=F64, requires_grad=True))
    assert torch.autograd.gradcheck(f, args)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_light_path_extremes_stay_finite(dtype):
    """Zero, tiny and huge falloff, dense fog, the sun below / at / just above the horizon,
    lights inside the fog, under the base height and at a fog sample: finite values and
    gradients (a documented limit: such a sun is absorbed, T = 0)."""
    h, w = 3, 4
    rays = _rays(h, w, dtype)
    rays[:, :, 0, :] = torch.tensor([1.0, 0.0, 0.0], dtype=dtype).view(1, 3, 1)
    image = torch.ones(1, 3, h, w, dtype=dtype)
    for density, falloff in ((0.3, 0.0), (0.3, 1e-7), (0.3, 1e3), (1e4, 50.0), (1e-30, 1.0)):
        for sun in ((0.3, -1.0, 0.0), (1.0, 0.0, 0.0), (1.0, 1e-6, 0.0), (1.0, -1e-7, 0.0),
                    (0.0, 1.0, 0.0)):
            for bulb in ((0.0, 1.0, 0.0), (0.0, -30.0, 1.0), (0.5, 1.2, 2.0)):
                d = torch.tensor(density, dtype=dtype, requires_grad=True)
                b = torch.tensor(falloff, dtype=dtype, requires_grad=True)
                sd = torch.tensor([[sun]], dtype=dtype, requires_grad=True)
                pos = torch.tensor([[bulb]], dtype=dtype, requires_grad=True)
                lights = tr.Lights(
                    directional=tr.DirectionalLights(direction=sd, color=torch.ones(
                        1, 1, 3, dtype=dtype), intensity=torch.ones(1, 1, dtype=dtype)),
                    point=tr.PointLights(position=pos, color=torch.ones(1, 1, 3, dtype=dtype),
                                         intensity=torch.ones(1, 1, dtype=dtype)))
                fog = Fog(density=d, height_falloff=b, steps=3, blur=1.0)
                eye = torch.tensor([[0.0, 1.0, 0.0]], dtype=dtype)
                dist = torch.full((1, 1, h, w), math.inf, dtype=dtype)
                dist[..., 1, :] = 2.0
                out = apply_fog(image, dist, eye, rays, fog, lights)
                from torchraster.shading.volumetric import surface_light_hook

                hook = surface_light_hook(fog, lights, eye[:, :, None, None] + rays * 2.0)
                t = hook("directional", slice(0, 1)).sum() + hook("point", slice(0, 1)).sum()
                assert torch.isfinite(out).all() and torch.isfinite(t), (density, falloff, sun)
                (out.sum() + t).backward()
                for x in (d, b, sd, pos):
                    assert torch.isfinite(x.grad).all(), (density, falloff, sun, bulb)


def test_environment_lights_the_fog():
    """An environment map's in-scattering (9 SH coefficients convolved with HG) against the
    brute-force sum over the map's texels of phase x radiance x solid angle, for a smooth
    (band-limited) map with a yaw and an intensity; times (1 - T_v)."""
    from torchraster.shading.ibl import Environment
    from torchraster.texture import latlong_directions, latlong_solid_angles

    he, we = 64, 128
    d = latlong_directions(he, we, dtype=F64)[0]
    radiance = torch.stack([1 + 0.5 * d[1] + 0.3 * d[0], 0.5 + 0.2 * d[2] * d[0],
                            0.8 - 0.3 * d[2]])
    env = Environment(radiance, yaw=0.7, intensity=1.5)
    fog = Fog(density=0.3, height_falloff=0.4, anisotropy=0.5, color=(0.9, 0.8, 0.7))
    eye = torch.tensor([[0.0, 1.0, 0.0]], dtype=F64)
    rays = _rays(2, 3)
    dist = torch.tensor([[[[2.0, 3.0, math.inf], [1.0, 5.0, 0.5]]]], dtype=F64)
    t = fog_terms(dist, eye, rays, fog, environment=env)
    omega = latlong_solid_angles(he, we, dtype=F64)
    c, s_ = math.cos(0.7), math.sin(0.7)
    world = torch.stack([c * d[0] + s_ * d[2], d[1], -s_ * d[0] + c * d[2]])  # yaw about +y
    want = torch.zeros_like(rays)
    for i in range(2):
        for j in range(3):
            p = ref.hg_phase_reference((world * rays[0, :, i, j].view(3, 1, 1)).sum(0), 0.5)
            want[0, :, i, j] = 1.5 * (radiance * p * omega).sum((-2, -1))
    want = want * torch.tensor([0.9, 0.8, 0.7], dtype=F64).view(1, 3, 1, 1) * (
        1 - t.transmittance)
    torch.testing.assert_close(t.analytic, want, rtol=2e-3, atol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_renderer_fog_in_half_precision(dtype):
    """Half-precision scenes are fogged in float32: finite image and gradients (the light
    path, the sun at the horizon, dense height fog)."""
    pos = _floor().positions.to(dtype).clone().requires_grad_()
    scene = tr.RenderScene.from_mesh(tr.Mesh(pos, torch.tensor([(0, 1, 2), (0, 2, 3)])))
    for sun, density, falloff in (((0.3, -1.0, 0.2), 0.3, 0.5), ((1.0, 0.0, 0.0), 50.0, 20.0)):
        sd = torch.tensor([[sun]], dtype=dtype, requires_grad=True)
        lights = tr.Lights(directional=tr.DirectionalLights(
            direction=sd, color=torch.ones(1, 1, 3, dtype=dtype),
            intensity=torch.full((1, 1), 3.0, dtype=dtype)), point=_bulb(
            (0.5, 1.0, 0.0), dtype=dtype))
        view = tr.camera.look_at([0.0, 2.0, 4.0], [0.0, 0.0, 0.0]).to(dtype)
        proj = tr.camera.perspective(60.0, 1.0, 0.1).to(dtype)
        fog = Fog(density=density, height_falloff=falloff, steps=3)
        out = tr.Renderer(12, fog=fog)(scene, view, proj, lights)
        assert out.image.dtype == dtype and torch.isfinite(out.image).all()
        out.image.float().sum().backward()
        assert torch.isfinite(pos.grad).all() and torch.isfinite(sd.grad).all()


def test_march_in_row_bands_equals_the_whole_frame(monkeypatch):
    """fog_terms marches bands of FOG_BAND_PIXELS pixels (cache-sized; not with shadow
    maps); bands of one row, with jitter (the pattern of each band's own rows), a sun, a
    point light with the light path and a batch of 2, give the whole frame's values and
    gradients."""
    from torchraster.shading import volumetric

    scene = _plate_with_hole()
    view = torch.cat([tr.camera.look_at([0.0, 1.0, 3.5], [0.0, 1.3, 0.0]).reshape(1, 4, 4),
                      tr.camera.look_at([0.5, 1.2, 3.0], [0.0, 1.0, 0.0]).reshape(1, 4, 4)])
    view = view.double()
    proj = tr.camera.perspective(50.0, 1.0, 0.1).double()
    outs, marches = [], []
    march = volumetric.march_inscatter

    def counted(*args, **kwargs):
        marches[-1] += 1
        return march(*args, **kwargs)

    monkeypatch.setattr(volumetric, "march_inscatter", counted)
    for band in (volumetric.FOG_BAND_PIXELS, 1):
        monkeypatch.setattr(volumetric, "FOG_BAND_PIXELS", band)
        marches.append(0)
        density = torch.tensor(0.3, dtype=F64, requires_grad=True)
        sun = tr.DirectionalLights(direction=torch.tensor([[SUN_DIR]], dtype=F64),
                                   color=torch.ones(1, 1, 3, dtype=F64),
                                   intensity=torch.tensor([[2.0]], dtype=F64))
        lights = tr.Lights(directional=sun, point=_bulb((0.3, 1.0, 0.5)))
        fog = Fog(density=density, height_falloff=0.3, anisotropy=0.4, steps=5, blur=0.0)
        out = tr.Renderer((9, 7), fog=fog)(scene, view, proj, lights)
        outs.append((out.image, *torch.autograd.grad(out.image.square().sum(), density)))
    assert marches == [1, 9] and float(outs[0][1].abs()) > 0  # one band a row of 9
    torch.testing.assert_close(outs[0][0], outs[1][0], rtol=1e-12, atol=1e-14)
    # the density's gradient sums over every pixel, in another order per band (the plate
    # is a float32 mesh: its G-buffer is float32)
    torch.testing.assert_close(outs[0][1], outs[1][1], rtol=1e-6, atol=0)
