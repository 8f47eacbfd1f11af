"""Volumetric fog and light shafts (torchraster.shading.volumetric) against independent
references: numeric quadratures of the optical depth and of the phase function, a
brute-force float64 march with numerically integrated transmittance
(torchraster.testing.reference_fog), and a light shaft through a hole checked against the
analytic visibility of the hole."""

from __future__ import annotations

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
    light_source,
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
    fog = Fog(density=0.2, anisotropy=g, steps=64, jitter=False, blur=0.0, max_distance=5.0)
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
                        "fog blur 1 px")
    assert all(s in plan for s in plan.fog)
    # shadow maps are rendered for the shafts even when no face receives shadows
    sun.cast_shadows = torch.tensor([[True]])
    scene.receive_shadows = torch.zeros(scene.faces.shape[0], dtype=torch.bool)
    assert tr.Renderer(8).plan(scene, lights).shadow_lights == ()
    plan = tr.Renderer(8, fog=Fog(blur=0.0)).plan(scene, lights)
    assert plan.shadow_lights and plan.fog[1].endswith("directional[0] shadowed, point[0]")
    assert len(plan.fog) == 2
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
    out = tr.Renderer(8, fog=Fog(density=density, steps=4))(scene, view, proj,
                                                            tr.Lights(directional=sun))
    out.image.sum().backward()
    for t in (density, intensity):
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
