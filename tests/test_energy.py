"""Energy compensation (shading/energy.py) for punctual, ambient and image-based light.

References are independent of the code under test: white furnaces (a lossless material
under uniform light reflects exactly the light it receives), a hemisphere quadrature of
the rendered BRDF built from many directional lights, and a float64 Monte-Carlo estimate
of the single-scattering albedo (GGX importance sampling with the Walter / Heitz forms of
``torchraster.testing.reference_brdf``) fed into the compensation model.
"""

from __future__ import annotations

import math

import pytest
import torch

from torchraster.config import lights_from_config
from torchraster.gbuffer import GBuffer
from torchraster.shading import Lights, shade
from torchraster.shading.energy import dfg_terms, energy_terms
from torchraster.shading.ibl import Environment, dfg_lut, shade_ibl
from torchraster.shading.lights import DirectionalLights
from torchraster.testing.reference_brdf import furnace_hemisphere, heitz_v, walter_ggx

F64 = torch.float64
THETAS = (0.0, 0.7, 1.3)  # view angles from the normal


def _view_pixels(thetas=THETAS, **material):
    """One pixel per view angle: normal +z at the origin, camera at distance 10 along v."""
    k = len(thetas)
    v = torch.tensor([[math.sin(t), 0.0, math.cos(t)] for t in thetas], dtype=F64)
    one = torch.ones(1, 1, 1, k, dtype=F64)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64).view(1, 3, 1, 1).expand(1, 3, 1, k)
    gb = GBuffer(position=torch.zeros(1, 3, 1, k, dtype=F64), normal=n,
                 albedo=material.get("albedo", 1.0) * torch.ones(1, 3, 1, k, dtype=F64),
                 metallic=material.get("metallic", 1.0) * one,
                 roughness=material.get("roughness", 0.5) * one)
    return gb, v


def _render_each_view(gb: GBuffer, v: torch.Tensor, lights_of, **kw) -> torch.Tensor:
    """Shade pixel k from camera direction v[k] (lights_of(k) -> Lights): (K, 3)."""
    out = []
    for k in range(v.shape[0]):
        sub = GBuffer(**{c: getattr(gb, c)[..., k:k + 1] for c in
                         ("position", "normal", "albedo", "metallic", "roughness")})
        out.append(shade(sub, camera_position=10.0 * v[k:k + 1], lights=lights_of(k), **kw
                         )[0, :, 0, 0])
    return torch.stack(out)


# ---------------------------------------------------------------------------- furnaces

ROUGH = (0.045, 0.3, 0.6, 1.0)


@pytest.mark.parametrize("metallic", [1.0, 0.0])
@pytest.mark.parametrize("rough", ROUGH)
def test_white_furnace_ambient(metallic: float, rough: float) -> None:
    # Uniform white ambient, albedo 1: a white metal (f0 = 1) and a white dielectric
    # (Lambert albedo 1 under a 4 % coat) are lossless and must reflect 1.
    gb, v = _view_pixels(albedo=1.0, metallic=metallic, roughness=rough)
    amb = lights_from_config([{"type": "ambient", "color": [1.0, 1.0, 1.0]}], dtype=F64)
    out = _render_each_view(gb, v, lambda k: amb)
    assert float((out - 1).abs().max()) < 0.01, out
    single = _render_each_view(gb, v, lambda k: amb, multiscatter=False)
    if metallic == 1.0 and rough >= 0.6:  # single scattering loses >= 10 % there
        assert float(single.max()) < 0.9, single


def _hemisphere_lights(theta_v: float, n_theta: int = 160, n_phi: int = 48) -> Lights:
    """Directional lights on a quadrature of the light hemisphere, parametrised by the half
    vector (graded towards the normal, dw_l = 4 (v.h) dw_h): radiance 1 from every
    direction, i.e. sum of f cos E over the lights = the directional albedo of f."""
    l, w = furnace_hemisphere(theta_v, n_theta, n_phi)
    return Lights(directional=DirectionalLights(
        direction=-l[None], color=torch.ones(1, l.shape[0], 3, dtype=F64), intensity=w[None]))


@pytest.mark.parametrize("metallic", [1.0, 0.0])
@pytest.mark.parametrize("rough", [0.3, 0.6, 1.0])
def test_white_furnace_punctual(metallic: float, rough: float) -> None:
    # The same furnace made of ~7000 directional lights: the punctual path's BRDF
    # (compensated lobe + reduced diffuse) integrates to 1 over the hemisphere.
    gb, v = _view_pixels(albedo=1.0, metallic=metallic, roughness=rough)
    lights = [_hemisphere_lights(t) for t in THETAS]
    out = _render_each_view(gb, v, lambda k: lights[k])
    assert float((out - 1).abs().max()) < 0.015, out
    if metallic == 1.0 and rough >= 0.6:
        single = _render_each_view(gb, v, lambda k: lights[k], multiscatter=False)
        assert float(single.max()) < 0.9, single


def test_white_furnace_ibl_dielectric_exact() -> None:
    # IBL uses the same convention: a white dielectric under a white environment reflects 1
    # (diffuse 1 - E_spec plus the specular E_spec), the single-scattering sum more than 1.
    env = Environment(torch.ones(3, 32, 64, dtype=F64), specular_size=8, specular_levels=5,
                      specular_samples=16)
    gb, v = _view_pixels(albedo=1.0, metallic=0.0, roughness=0.5)
    n, a, m, r = gb.normal, gb.albedo, gb.metallic, gb.roughness
    vv = v.T.reshape(1, 3, 1, -1)
    out = shade_ibl(n, vv, a, m, r, None, env)
    assert float((out - 1).abs().max()) < 0.01, out
    assert float(shade_ibl(n, vv, a, m, r, None, env, multiscatter=False).min()) > 1.03


# ------------------------------------------------------------------------- Monte Carlo


def _mc_albedo(theta_v: float, rough: float, f0: float, n: int = 2**18) -> float:
    """Single-scattering specular albedo int D G F cos / (4 n.v n.l) dl (Schlick F with
    f90 = 1), by GGX half-vector importance sampling: pdf(l) = D (n.h) / (4 v.h)."""
    g = torch.Generator().manual_seed(1234)
    u = torch.rand(n, 2, generator=g, dtype=F64)
    a = max(rough, 0.045) ** 2
    cos_h = torch.sqrt((1 - u[:, 0]) / (1 + (a * a - 1) * u[:, 0]))
    sin_h = torch.sqrt(1 - cos_h**2)
    phi = 2 * math.pi * u[:, 1]
    h = torch.stack([sin_h * phi.cos(), sin_h * phi.sin(), cos_h], -1)
    v = torch.tensor([math.sin(theta_v), 0.0, math.cos(theta_v)], dtype=F64)
    vh = h @ v
    l = 2 * vh[:, None] * h - v
    nl, nv = l[:, 2], max(v[2].item(), 1e-4)
    ok = (nl > 0) & (vh > 0)
    nl_s = nl.clamp_min(1e-12)
    fres = f0 + (1 - f0) * (1 - vh.clamp(0, 1)) ** 5
    # f cos / pdf = D V F nl / (D nh / (4 vh)) = 4 V F nl vh / nh
    est = 4 * heitz_v(torch.tensor(nv, dtype=F64), nl_s, a) * fres * nl_s * vh / cos_h
    return float(torch.where(ok, est, 0.0).mean())


@pytest.mark.parametrize("rough", [0.2, 0.5, 0.9])
def test_point_light_vs_monte_carlo(rough: float) -> None:
    # The renderer's point-light radiance against the compensation model evaluated with
    # an independent Monte-Carlo albedo and the reference GGX / Smith forms.
    albedo = torch.tensor([1.0, 0.78, 0.34], dtype=F64)  # gold
    for metallic in (1.0, 0.3):
        for theta_v, theta_l in ((0.0, 0.5), (0.8, 0.3), (1.2, 1.0)):
            v = torch.tensor([math.sin(theta_v), 0.0, math.cos(theta_v)], dtype=F64)
            l = torch.tensor([-math.sin(theta_l) * 0.8, math.sin(theta_l) * 0.6,
                              math.cos(theta_l)], dtype=F64)
            gb, _ = _view_pixels((theta_v,), albedo=1.0, metallic=metallic, roughness=rough)
            gb = GBuffer(**{**{c: getattr(gb, c) for c in ("position", "normal", "metallic",
                                                           "roughness")},
                            "albedo": albedo.view(1, 3, 1, 1)})
            lights = lights_from_config([{"type": "point", "position": (3.0 * l).tolist(),
                                          "intensity": 9.0}], dtype=F64)  # E = 1 lux
            got = shade(gb, camera_position=10.0 * v[None], lights=lights)[0, :, 0, 0]
            f0 = 0.04 * (1 - metallic) + albedo * metallic
            e1 = _mc_albedo(theta_v, rough, 1.0)  # E_ss for f0 = 1 (= A + B)
            e0 = _mc_albedo(theta_v, rough, 0.0)  # B
            ms = 1 + f0 * (1 / e1 - 1)
            e_spec = (f0 * (e1 - e0) + e0) * ms
            h = torch.nn.functional.normalize(v + l, dim=0)
            a = rough**2
            nh, vh, nl, nv = h[2], v @ h, l[2], v[2]
            spec = walter_ggx(nh, a) * heitz_v(nv, nl, a) * (f0 + (1 - f0) * (1 - vh) ** 5)
            ref = ((1 - metallic) * albedo * (1 - e_spec) / math.pi + spec * ms) * nl
            torch.testing.assert_close(got, ref, rtol=0.01, atol=1e-4)
            single = shade(gb, camera_position=10.0 * v[None], lights=lights,
                           multiscatter=False)[0, :, 0, 0]
            ref_single = ((1 - metallic) * albedo / math.pi + spec) * nl
            torch.testing.assert_close(single, ref_single, rtol=1e-9, atol=1e-12)


def test_lut_albedo_vs_monte_carlo() -> None:
    lut = dfg_lut(32, 96, dtype=F64)
    for rough in (0.1, 0.5, 1.0):
        for theta in (0.2, 1.0, 1.4):
            a, b = dfg_terms(lut, torch.tensor(math.cos(theta), dtype=F64),
                             torch.tensor(rough, dtype=F64))
            assert float(a + b) == pytest.approx(_mc_albedo(theta, rough, 1.0), rel=0.01)
            assert float(b) == pytest.approx(_mc_albedo(theta, rough, 0.0), rel=0.02, abs=1e-3)


# ----------------------------------------------------------------- stability, gradients


def test_energy_terms_hostile_and_gradcheck() -> None:
    lut = dfg_lut(32, 96, dtype=F64)
    nv = torch.tensor([0.0, 1e-6, 0.5, 1.0, -1.0, 2.0], dtype=F64)
    rough = torch.tensor([0.0, 1.0, 0.045, -0.5, 1.5, 0.3], dtype=F64)
    f0 = torch.tensor([1.0, 0.04, 0.0, 1.0, 0.5, 2.0], dtype=F64)
    ms, kd = energy_terms(f0, nv, rough, lut)
    assert bool(torch.isfinite(ms).all() and torch.isfinite(kd).all())
    assert bool((ms >= 1).all() and (kd >= 0).all() and (kd <= 1).all())

    def f(f0, nv, r):
        return torch.cat(energy_terms(f0, nv, r, lut))

    args = (torch.tensor([0.3, 0.9], dtype=F64, requires_grad=True),
            torch.tensor([0.33, 0.71], dtype=F64, requires_grad=True),
            torch.tensor([0.41, 0.77], dtype=F64, requires_grad=True))
    assert torch.autograd.gradcheck(f, args)


def test_shade_gradients_finite_roughness_zero_grazing() -> None:
    gb, v = _view_pixels((0.0, math.pi / 2, 1.55), albedo=0.8, metallic=0.5, roughness=0.0)
    params = {c: getattr(gb, c).clone().requires_grad_(True)
              for c in ("albedo", "metallic", "roughness")}
    gb = GBuffer(position=gb.position, normal=gb.normal, **params)
    lights = lights_from_config([{"type": "point", "position": [0.3, 0.2, 2.0],
                                  "intensity": 1e6},
                                 {"type": "ambient", "color": [0.5, 0.5, 0.5]}], dtype=F64)
    out = shade(gb, camera_position=10.0 * v[1:2], lights=lights)
    out.sum().backward()
    assert bool(torch.isfinite(out).all())
    assert all(bool(torch.isfinite(p.grad).all()) for p in params.values())
