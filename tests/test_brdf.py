"""BRDF terms against analytic integrals and independent formulas (Walter 2007, Heitz 2014)."""

from __future__ import annotations

import math

import pytest
import torch

from torchraster.shading.brdf import (
    MIN_COS,
    MIN_ROUGHNESS,
    cook_torrance,
    d_ggx,
    f_schlick,
    fd_lambert,
    safe_normalize,
    v_smith_ggx_correlated,
)
from torchraster.testing import reference_brdf
from torchraster.testing.reference_brdf import heitz_v, walter_ggx

F64 = torch.float64


def graded_cos_grid(n: int = 4001) -> torch.Tensor:
    """cos(theta) in [0, 1], points clustered geometrically towards the pole (cos = 1)."""
    s = torch.logspace(-14, 0, n, dtype=F64)  # 1 - cos(theta)
    return torch.cat([torch.ones(1, dtype=F64), 1.0 - s, torch.zeros(1, dtype=F64)]).unique()


@pytest.mark.parametrize("roughness", [MIN_ROUGHNESS, 0.1, 0.3, 0.6, 1.0])
def test_ggx_normalisation(roughness: float) -> None:
    # integral over the hemisphere of D(h) (n.h) dw = 2 pi integral_0^1 D(mu) mu dmu = 1
    mu = graded_cos_grid()
    integrand = d_ggx(mu, roughness) * mu
    total = 2 * math.pi * torch.trapezoid(integrand, mu)
    assert abs(total.item() - 1.0) < 1e-4, total.item()


def test_ggx_matches_walter_and_floor() -> None:
    mu = torch.linspace(0.01, 1.0, 200, dtype=F64)
    for r in (0.2, 0.5, 1.0):
        torch.testing.assert_close(d_ggx(mu, r), walter_ggx(mu, r * r), rtol=1e-10, atol=0)
    # roughness below the floor is the floor; the peak stays finite (~7.8e4)
    one = torch.ones(1, dtype=F64)
    assert d_ggx(one, 0.0).item() == d_ggx(one, MIN_ROUGHNESS).item()
    assert d_ggx(one, 0.0).item() == pytest.approx(1 / (math.pi * MIN_ROUGHNESS**4))
    assert d_ggx(-one, 0.5).item() == 0.0


def test_smith_matches_heitz_and_symmetric() -> None:
    g = torch.Generator().manual_seed(1)
    nv = torch.rand(500, generator=g, dtype=F64) * 0.99 + 0.01
    nl = torch.rand(500, generator=g, dtype=F64) * 0.99 + 0.01
    for r in (MIN_ROUGHNESS, 0.4, 1.0):
        v = v_smith_ggx_correlated(nv, nl, r)
        torch.testing.assert_close(v, heitz_v(nv, nl, r * r), rtol=1e-10, atol=0)
        torch.testing.assert_close(v, v_smith_ggx_correlated(nl, nv, r))
    # grazing / back-facing cosines hit the floor and stay finite
    z = torch.tensor([0.0, -0.5, -1.0], dtype=F64)
    out = v_smith_ggx_correlated(z, z, 0.0)
    assert torch.isfinite(out).all()
    assert out[0].item() == v_smith_ggx_correlated(torch.tensor(MIN_COS, dtype=F64),
                                                    torch.tensor(MIN_COS, dtype=F64), 0.0).item()


def test_schlick_endpoints() -> None:
    f0 = torch.tensor([0.04, 0.5, 1.0], dtype=F64)
    torch.testing.assert_close(f_schlick(torch.ones(3, dtype=F64), f0), f0)
    torch.testing.assert_close(f_schlick(torch.zeros(3, dtype=F64), f0), torch.ones(3, dtype=F64))
    half = f_schlick(torch.full((3,), 0.5, dtype=F64), f0, 0.5)
    torch.testing.assert_close(half, f0 + (0.5 - f0) / 32)
    assert fd_lambert() == pytest.approx(1 / math.pi)


def random_hemisphere(n: int, g: torch.Generator) -> torch.Tensor:
    """(n, 3, 1, 1) unit vectors with z > 0.05."""
    d = torch.randn(n, 3, generator=g, dtype=F64)
    d[:, 2] = d[:, 2].abs() + 0.1
    return safe_normalize(d, dim=1)[..., None, None]


def test_helmholtz_reciprocity() -> None:
    g = torch.Generator().manual_seed(2)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64).view(1, 3, 1, 1).expand(256, 3, 1, 1)
    v, l = random_hemisphere(256, g), random_hemisphere(256, g)
    albedo = torch.rand(256, 3, 1, 1, generator=g, dtype=F64)
    metallic = torch.rand(256, 1, 1, 1, generator=g, dtype=F64)
    rough = torch.rand(256, 1, 1, 1, generator=g, dtype=F64)
    f_vl = cook_torrance(n, v, l, albedo, metallic, rough, include_cosine=False)
    f_lv = cook_torrance(n, l, v, albedo, metallic, rough, include_cosine=False)
    torch.testing.assert_close(f_vl, f_lv, rtol=1e-12, atol=0)
    # the default result is f * max(n.l, 0)
    torch.testing.assert_close(
        cook_torrance(n, v, l, albedo, metallic, rough), f_vl * l[:, 2:3], rtol=1e-12, atol=0
    )


def directional_albedo(
    theta_v: float, roughness: float, metallic: float, albedo: float,
    n_theta: int = 600, n_phi: int = 96,
) -> float:
    """Directional albedo of the engine's Cook-Torrance BRDF by the reference quadrature."""
    return reference_brdf.directional_albedo(
        lambda n, v, l: cook_torrance(n, v, l, albedo, metallic, roughness),
        theta_v, n_theta, n_phi)


def test_lambert_directional_albedo_is_albedo() -> None:
    # With F = f0 = 0 impossible, check the diffuse lobe alone by subtracting metallic=1 black
    for theta in (0.0, 1.0):
        diffuse_only = directional_albedo(theta, 0.5, 0.0, 0.7) - directional_albedo(
            theta, 0.5, 0.0, 0.0
        )
        assert diffuse_only == pytest.approx(0.7, abs=2e-3)


@pytest.mark.parametrize("roughness", [MIN_ROUGHNESS, 0.25, 0.5, 0.75, 1.0])
def test_white_furnace_energy(roughness: float) -> None:
    # White metal (F = 1): single-scattering GGX loses energy with roughness, never gains.
    albedos = [directional_albedo(t, roughness, 1.0, 1.0) for t in (0.0, 0.8, 1.4)]
    assert max(albedos) <= 1.0 + 2e-3, albedos
    if roughness <= 0.1:
        assert min(albedos) > 0.97, albedos  # nearly a mirror: almost no loss
    if roughness == 1.0:
        assert min(albedos) < 0.8, albedos  # known single-scattering loss, see report


def test_gradcheck_terms() -> None:
    g = torch.Generator().manual_seed(3)

    def rnd(*shape, lo=0.1, hi=0.9):
        return (torch.rand(*shape, generator=g, dtype=F64) * (hi - lo) + lo).requires_grad_()

    nh, nv, nl, vh, r = rnd(6), rnd(6), rnd(6), rnd(6), rnd(6)
    f0 = rnd(6)
    assert torch.autograd.gradcheck(d_ggx, (nh, r))
    assert torch.autograd.gradcheck(v_smith_ggx_correlated, (nv, nl, r))
    assert torch.autograd.gradcheck(f_schlick, (vh, f0))
    n = safe_normalize(torch.tensor([0.1, 0.2, 1.0], dtype=F64).view(1, 3, 1, 1))
    v = random_hemisphere(3, g).reshape(1, 3, 3, 1)
    l = random_hemisphere(3, g).reshape(1, 3, 3, 1)
    n = n.expand(1, 3, 3, 1).clone().requires_grad_()
    v.requires_grad_()
    l.requires_grad_()
    albedo, metallic, rough = rnd(1, 3, 3, 1), rnd(1, 1, 3, 1), rnd(1, 1, 3, 1)
    assert torch.autograd.gradcheck(cook_torrance, (n, v, l, albedo, metallic, rough))


def test_hostile_inputs_finite_gradients() -> None:
    # roughness 0 and 1, n.v = 0 / negative, n.l = 0 / negative, v = -l (zero half vector)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float32).view(1, 3, 1, 1).repeat(1, 1, 1, 6)
    v = torch.tensor([[0, 0, 1], [1, 0, 0], [1, 0, -0.2], [0, 0, 1], [0.6, 0, 0.8],
                      [0.6, 0, 0.8]], dtype=torch.float32)
    l = torch.tensor([[0, 0, 1], [0, 0, 1], [0, 0.6, 0.8], [1, 0, 0], [0, 0, -1],
                      [-0.6, 0, -0.8]], dtype=torch.float32)
    v = safe_normalize(v.T.reshape(1, 3, 1, 6))
    l = safe_normalize(l.T.reshape(1, 3, 1, 6))
    for rough in (0.0, 1.0):
        n_, v_, l_ = (t.clone().requires_grad_() for t in (n, v, l))
        r = torch.full((1, 1, 1, 6), rough, requires_grad=True)
        m = torch.full((1, 1, 1, 6), 0.5, requires_grad=True)
        a = torch.full((1, 3, 1, 6), 0.8, requires_grad=True)
        out = cook_torrance(n_, v_, l_, a, m, r)
        assert torch.isfinite(out).all()
        out.sum().backward()
        for t in (n_, v_, l_, r, m, a):
            assert torch.isfinite(t.grad).all()
    # zero-length vectors normalise to 0 with zero gradient
    z = torch.zeros(1, 3, 1, 1, requires_grad=True)
    safe_normalize(z).sum().backward()
    assert (z.grad == 0).all()


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_low_precision(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(4)
    n = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(64, 3, 1, 1)
    v, l = random_hemisphere(64, g).float(), random_hemisphere(64, g).float()
    v[0] = l[0] = n[0]  # exact mirror direction: the GGX peak
    rough = torch.rand(64, 1, 1, 1, generator=g)
    rough[0] = 0.0
    n, v, l, rough = (t.to(dtype) for t in (n, v, l, rough))
    # reference: the same (rounded) inputs evaluated in float32
    ref = cook_torrance(n.float(), v.float(), l.float(), 1.0, 1.0, rough.float())
    low = cook_torrance(n, v, l, 1.0, 1.0, rough)
    assert low.dtype == dtype and torch.isfinite(low).all()
    # peak D alone overflows float16 (7.8e4 > 65504): saturated, not Inf
    d = d_ggx(torch.ones(1, dtype=dtype), 0.0)
    assert torch.isfinite(d).all() and d.item() >= 6e4
    rel = ((low.float() - ref).abs() / ref.abs().clamp_min(1e-2)).max().item()
    assert rel < 0.01  # only the output is rounded to 8 (bf16) / 11 (fp16) bits


def test_bad_inputs() -> None:
    with pytest.raises(TypeError, match="n_dot_h"):
        d_ggx([1.0], 0.5)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="roughness"):
        d_ggx(torch.ones(2), "rough")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="v: expected xyz"):
        cook_torrance(torch.ones(1, 3, 1, 1), torch.ones(1, 2, 1, 1), torch.ones(1, 3, 1, 1),
                      1.0, 0.0, 0.5)
