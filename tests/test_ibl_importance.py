"""IBL specular by per-pixel filtered importance sampling (``specular="importance"``).

The reference is a brute-force float64 integral of the single-scattering GGX lobe
``D G F (n.l) / (4 (n.l)(n.v))`` over a fine grid of directions of the environment
(reconstructed bilinearly, as the renderer reads it), written here from the reference
GGX / Smith forms of ``torchraster.testing.reference_brdf``.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from torchraster.shading.ibl import Environment, shade_ibl, specular_importance
from torchraster.testing.reference_brdf import heitz_v, walter_ggx
from torchraster.texture import (
    build_mip_pyramid,
    latlong_directions,
    latlong_solid_angles,
    sample_latlong,
)

D64 = torch.float64


def _sun_env(h: int = 64) -> torch.Tensor:
    """(1, 3, h, 2h) sky gradient + a bright sun ~10 degrees wide, low in the sky."""
    d = latlong_directions(h, 2 * h, dtype=D64)
    sun = F.normalize(torch.tensor([0.6, 0.25, -0.7], dtype=D64), dim=0).view(1, 3, 1, 1)
    c = (d * sun).sum(1, keepdim=True)
    sky = 0.2 + 0.3 * d[:, 1:2].clamp_min(0) + torch.tensor([0.0, 0.05, 0.2], dtype=D64
                                                             ).view(1, 3, 1, 1)
    return sky + 60.0 * torch.exp(60.0 * (c - 1.0)) * torch.tensor(
        [1.0, 0.8, 0.6], dtype=D64).view(1, 3, 1, 1)


def _pairs(k: int = 24, seed: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """k (normal, view) pairs with n.v in (0.1, 1): (k, 3) each."""
    g = torch.Generator().manual_seed(seed)
    n = F.normalize(torch.randn(k, 3, generator=g, dtype=D64), dim=1)
    v = F.normalize(torch.randn(k, 3, generator=g, dtype=D64), dim=1)
    v = torch.where((n * v).sum(1, keepdim=True) < 0, -v, v)
    return n, F.normalize(v + 0.2 * n, dim=1)


def _brute_specular(env: torch.Tensor, n: torch.Tensor, v: torch.Tensor, rough: float,
                    res: int = 256) -> torch.Tensor:
    """int L(l) D G F (n.l) / (4 n.l n.v) dl with F = Schlick(f0 = 1): (k, 3)."""
    d = latlong_directions(res, 2 * res, dtype=D64)
    lf = sample_latlong(env, d).reshape(3, -1)
    d, dw = d.reshape(3, -1), latlong_solid_angles(res, 2 * res, dtype=D64).expand(
        res, 2 * res).reshape(-1)
    a = max(rough, 0.045) ** 2
    out = []
    for ni, vi in zip(n, v, strict=True):
        nl = ni @ d
        h = F.normalize(d + vi[:, None], dim=0)
        nh = (ni @ h).clamp(1e-9, 1.0)
        ok = nl > 0
        f = walter_ggx(nh, a) * heitz_v((ni @ vi).clamp_min(1e-4), nl.clamp_min(1e-9), a)
        f = torch.where(ok, f * nl * dw, 0.0)  # F = 1 for f0 = 1
        out.append(lf @ f)
    return torch.stack(out)


def _shade(env: Environment, n, v, rough: float, **kw) -> torch.Tensor:
    k = n.shape[0]
    one = torch.ones(1, 1, 1, k, dtype=D64)
    out = shade_ibl(n.T.reshape(1, 3, 1, k), v.T.reshape(1, 3, 1, k),
                    torch.ones(1, 3, 1, k, dtype=D64), one, rough * one, None, env,
                    multiscatter=False, lut_size=64, lut_samples=256, **kw)
    return out[0, :, 0].T


@pytest.fixture(scope="module")
def sun_case():
    env = _sun_env()
    n, v = _pairs(16)
    refs = {r: _brute_specular(env, n, v, r, res=128) for r in (0.55, 0.8)}
    # float32 radiance: the prefiltered chain is built in float32 (as in rendering)
    return Environment(env.float(), specular_size=32, specular_levels=8), n, v, refs


def _err(got: torch.Tensor, ref: torch.Tensor) -> float:
    return float(((got - ref).abs() / ref).mean())


@pytest.mark.parametrize("rough, samples", [(0.55, 32), (0.8, 128)])
def test_importance_beats_split_sum(rough: float, samples: int, sun_case) -> None:
    # split sum (dominant direction) 12.7 % / 11.2 %; importance 8.5 % (N = 32) / 8.1 %
    # (N = 128): the bright small sun makes the Monte-Carlo noise decay slowly at r = 0.8
    env, n, v, refs = sun_case
    split = _err(_shade(env, n, v, rough, specular="split_sum"), refs[rough])
    fis = _err(_shade(env, n, v, rough, specular="importance", importance_samples=samples),
               refs[rough])
    assert fis < 0.8 * split and split < 0.15, (fis, split)


def test_importance_converges(sun_case) -> None:
    # Monte-Carlo convergence: the error falls ~ 1 / sqrt(N) (23 % at 8, 2 % at 1024)
    env, n, v, refs = sun_case
    errs = [_err(_shade(env, n, v, 0.8, specular="importance", importance_samples=s),
                 refs[0.8]) for s in (8, 1024)]
    assert errs[1] < 0.04 and errs[1] < 0.2 * errs[0], errs


def test_importance_white_furnace_any_n() -> None:
    # A uniform environment: the ratio estimator is exact at any sample count.
    env = Environment(torch.ones(3, 16, 32, dtype=D64), specular="importance",
                      importance_samples=3)
    n, v = _pairs(10)
    for rough in (0.0, 0.5, 1.0):
        got = Environment.specular_lobe(env, n.T.reshape(1, 3, 1, 10), v.T.reshape(1, 3, 1, 10),
                                        torch.full((1, 3, 1, 10), 0.9, dtype=D64), 1.0,
                                        torch.full((1, 1, 1, 10), rough, dtype=D64))
        torch.testing.assert_close(got, torch.ones_like(got))


def test_importance_gradcheck() -> None:
    g = torch.Generator().manual_seed(0)
    env = torch.rand(1, 3, 4, 8, generator=g, dtype=D64, requires_grad=True)
    n = F.normalize(torch.randn(1, 3, 1, 2, generator=g, dtype=D64), dim=1)
    v = F.normalize(n + 0.5 * torch.randn(1, 3, 1, 2, generator=g, dtype=D64), dim=1)
    f0 = torch.rand(1, 3, 1, 2, generator=g, dtype=D64, requires_grad=True)
    rough = (0.3 + 0.5 * torch.rand(1, 1, 1, 2, generator=g, dtype=D64)).requires_grad_(True)

    def f(env, f0, rough):
        return specular_importance(build_mip_pyramid(env), n, v, f0, 1.0, rough, 4)

    assert torch.autograd.gradcheck(f, (env, f0, rough))


def test_importance_hostile_inputs_finite() -> None:
    env = Environment(_sun_env(16) * 1e4, specular="importance", importance_samples=4)
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0],
                      [0.0, 1.0, 0.0]], dtype=D64).T.reshape(1, 3, 1, 5).requires_grad_(True)
    v = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0],
                      [0.0, 1.0, 0.0]], dtype=D64).T.reshape(1, 3, 1, 5)  # grazing, back
    rough = torch.tensor([0.0, 0.5, 0.0, 1.0, 0.0], dtype=D64).view(1, 1, 1, 5)
    rough.requires_grad_(True)
    one = torch.ones(1, 1, 1, 5, dtype=D64)
    out = shade_ibl(n, v, torch.ones(1, 3, 1, 5, dtype=D64), one, rough, None, env)
    out.sum().backward()
    assert bool(torch.isfinite(out).all()) and bool((out >= 0).all())
    assert bool(torch.isfinite(n.grad).all()) and bool(torch.isfinite(rough.grad).all())


def test_importance_knob_errors() -> None:
    env_t = torch.ones(3, 8, 16)
    with pytest.raises(ValueError, match="specular"):
        Environment(env_t, specular="brute")
    with pytest.raises(ValueError, match="importance_samples"):
        Environment(env_t, importance_samples=0)
    n = torch.zeros(1, 3, 1, 1)
    one = torch.ones(1, 1, 1, 1)
    with pytest.raises(ValueError, match="specular"):
        shade_ibl(n, n, one, one, one, None, Environment(env_t), specular="mc")
    with pytest.raises(ValueError, match="importance_samples"):
        shade_ibl(n, n, one, one, one, None, Environment(env_t), importance_samples=-1)


def test_renderer_plans_importance_and_energy() -> None:
    import trimesh

    import torchraster as tr
    from torchraster.camera import look_at, perspective

    ico = trimesh.creation.icosphere(subdivisions=1)
    mesh = tr.Mesh(torch.tensor(ico.vertices, dtype=torch.float32), torch.tensor(ico.faces))
    view, proj = look_at([0.0, 0.5, 3.0], [0.0, 0.0, 0.0]), perspective(40.0, 1.0, 0.1, 10.0)
    env_t = torch.ones(3, 8, 16)
    r = tr.Renderer(16)
    plan = r.plan(mesh, environment=tr.Environment(env_t))
    assert "ibl" in plan and "energy compensation" in plan
    assert "ibl specular table" in plan and plan.ibl_specular == "table"  # the default
    plan = r.plan(mesh, environment=tr.Environment(env_t, specular="importance"))
    assert "ibl specular importance" in plan and plan.ibl_specular == "importance"
    assert "energy compensation" not in tr.Renderer(16,
                                                    shading=tr.ShadingSettings(multiscatter=False)).plan(
        mesh, environment=tr.Environment(env_t))
    assert "energy compensation" not in tr.Renderer(16, shading="unlit").plan(mesh)
    out = r(mesh, view, proj, environment=tr.Environment(env_t, specular="importance"))
    assert "ibl specular importance" in out.plan and bool(torch.isfinite(out.image).all())


def test_dominant_direction_limits() -> None:
    from torchraster.shading.ibl import dominant_direction

    n, v = _pairs(6)
    n, v = n.T.reshape(1, 3, 1, 6), v.T.reshape(1, 3, 1, 6)
    r = 2 * (n * v).sum(1, keepdim=True) * n - v
    zero, one = torch.zeros(1, 1, 1, 6, dtype=D64), torch.ones(1, 1, 1, 6, dtype=D64)
    torch.testing.assert_close(dominant_direction(n, r, zero), r)  # a mirror reads r
    torch.testing.assert_close(dominant_direction(n, r, one), n)  # the widest lobe: n
    mid = dominant_direction(n, r, 0.6 * one)
    assert bool(((mid * n).sum(1) > (r * n).sum(1) - 1e-12).all())  # bent towards n
