"""Image-based lighting: SH irradiance, prefiltered specular, DFG LUT, shade_ibl.

References are independent of the code under test: analytic irradiance of a band-limited
environment, brute-force quadrature of the irradiance / GGX-lobe / BRDF-albedo integrals on
fine direction grids, white-furnace identities, finite differences (gradcheck).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from torchraster.shading.brdf import d_ggx, v_smith_ggx_correlated
from torchraster.shading.ibl import (
    Environment,
    dfg_lut,
    irradiance_sh,
    lod_to_roughness,
    lookup_dfg,
    prefilter_specular,
    roughness_to_lod,
    sh_project,
    shade_ibl,
    yaw_rotation,
)
from torchraster.texture import latlong_directions, latlong_solid_angles, sample_latlong

D64 = torch.float64


def _unit(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return F.normalize(torch.randn(1, 3, 1, n, generator=g, dtype=D64), dim=1)


def _smooth_env(h: int = 32) -> torch.Tensor:
    """A synthetic, smooth but anisotropic HDR env (1, 3, h, 2h): sky gradient + soft sun."""
    d = latlong_directions(h, 2 * h, dtype=D64)
    sun = F.normalize(torch.tensor([0.5, 0.4, -0.6], dtype=D64), dim=0).view(1, 3, 1, 1)
    c = (d * sun).sum(1, keepdim=True)
    sky = 0.3 + 0.2 * d[:, 1:2] + torch.tensor([0.0, 0.05, 0.2], dtype=D64).view(1, 3, 1, 1)
    return sky + 8.0 * torch.exp(8.0 * (c - 1.0)) * torch.tensor([1.0, 0.8, 0.6], dtype=D64
                                                                  ).view(1, 3, 1, 1)


def _brute_irradiance(env: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """E(n) = sum_texels L max(0, n.w) dw, texel-exact solid angles. n: (1, 3, 1, N)."""
    he, we = env.shape[-2:]
    dirs = latlong_directions(he, we, dtype=env.dtype)
    w = latlong_solid_angles(he, we, dtype=env.dtype)
    cos = torch.einsum("cn,chw->nhw", n[0, :, 0], dirs[0]).clamp_min(0)
    return torch.einsum("nhw,bchw->bcn", cos * w, env)


def _brute_lobe(env: torch.Tensor, n: torch.Tensor, rough: float, res: int = 256) -> torch.Tensor:
    """GGX-lobe mean int L D(n.h) (n.l)+ / int D (n.l)+ on a fine grid, n = v, with the env
    reconstructed bilinearly. n: (1, 3, 1, N) -> (1, 3, N)."""
    fine = latlong_directions(res, 2 * res, dtype=D64)
    fw = latlong_solid_angles(res, 2 * res, dtype=D64)
    lf = sample_latlong(env, fine)
    nn = n[:, :, 0, :, None, None]
    h = F.normalize(nn + fine[:, :, None], dim=1)
    n_dot_h = (h * nn).sum(1)
    n_dot_l = (fine[:, :, None] * nn).sum(1).clamp_min(0)
    wt = d_ggx(n_dot_h, rough) * n_dot_l * fw
    return torch.einsum("bnhw,bchw->bcn", wt, lf) / wt.sum((2, 3))[:, None]


# ---------------------------------------------------------------- SH irradiance (diffuse)


def test_sh_irradiance_analytic_band_limited_env() -> None:
    d = latlong_directions(64, 128, dtype=D64)
    a, b = 0.7, torch.tensor([0.2, -0.3, 0.25], dtype=D64)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    lum = a + b[0] * x + b[1] * y + b[2] * z + 0.4 * x * y  # bands 0, 1, 2 only
    env = lum[:, None].expand(1, 3, 64, 128)
    n = _unit(50)
    e = irradiance_sh(sh_project(env), n)[:, :, 0]
    nx, ny, nz = n[0, :, 0]
    # Ramamoorthi & Hanrahan: E = pi L0 + 2pi/3 L1 + pi/4 L2 per band
    expect = math.pi * a + 2 * math.pi / 3 * (b[0] * nx + b[1] * ny + b[2] * nz) \
        + math.pi / 4 * 0.4 * nx * ny
    rel = (e - expect).abs() / expect.abs()
    assert float(rel.max()) < 1e-3


def test_sh_irradiance_vs_brute_force_smooth_env() -> None:
    # a broad sun (lobe exp(3 (cos - 1))): order-2 SH is within ~1 % of the brute force; a
    # sharp sun is not band-limited (see test_sh_irradiance_real_env)
    d = latlong_directions(32, 64, dtype=D64)
    sun = F.normalize(torch.tensor([0.5, 0.4, -0.6], dtype=D64), dim=0).view(1, 3, 1, 1)
    env = 0.3 + 0.2 * d[:, 1:2] + 4.0 * torch.exp(3.0 * ((d * sun).sum(1, keepdim=True) - 1))
    env = env * torch.tensor([1.0, 0.8, 0.6], dtype=D64).view(1, 3, 1, 1)
    n = _unit(60, seed=1)
    e = irradiance_sh(sh_project(env), n)[:, :, 0]
    ref = _brute_irradiance(env, n)
    rel = (e - ref).abs() / ref
    assert float(rel.mean()) < 0.01 and float(rel.max()) < 0.02, (rel.mean(), rel.max())


def test_sh_irradiance_real_env(shared_data: Path) -> None:
    from torchraster.hdr_io import read_hdr

    img = read_hdr(shared_data / "envmaps" / "venice_sunset_1k.hdr")[None].to(D64)
    env = F.adaptive_avg_pool2d(img, (64, 128))
    n = _unit(60, seed=2)
    e = irradiance_sh(sh_project(env), n)[:, :, 0]
    ref = _brute_irradiance(env, n)
    rel = (e - ref).abs() / ref
    # order-2 SH of a sunset (sun on the horizon) is an approximation: ~2 % on average
    # (Ramamoorthi & Hanrahan report < 3 %); the worst normals face away from the sun.
    assert float(rel.mean()) < 0.03, float(rel.mean())
    assert float(((e - ref).abs() / ref.mean()).max()) < 0.08


# -------------------------------------------------------------------- prefiltered specular


def test_uniform_env_prefilters_to_itself() -> None:
    env = torch.full((1, 3, 16, 32), 2.5, dtype=D64)
    for budget in (0, 2**20):  # all importance sampled / rough levels by quadrature
        chain = prefilter_specular(env, size=16, levels=5, samples=16, quadrature_budget=budget)
        for level in chain:
            torch.testing.assert_close(level, torch.full_like(level, 2.5))


@pytest.mark.parametrize("rough", [0.2, 0.5, 1.0])
def test_row_quadrature_equals_the_brute_force_sum(rough: float) -> None:
    """The same-grid quadrature (row-wise circular correlations by FFT) against the sum over
    every pair of texels, written out here, float64, on a rough random map."""
    from torchraster.shading.ibl import _prefilter_rows

    g = torch.Generator().manual_seed(1)
    env = torch.rand(2, 3, 12, 24, generator=g, dtype=D64) ** 4 * 5
    d = latlong_directions(12, 24, dtype=D64).reshape(3, -1)
    c = d.T @ d  # n.l between every output and source texel centre
    w = d_ggx(torch.sqrt(((1 + c) / 2).clamp_min(0)), rough) * c.clamp_min(0) * (
        latlong_solid_angles(12, 24, dtype=D64).expand(12, 24).reshape(-1))
    ref = (torch.einsum("ns,bcs->bcn", w, env.reshape(2, 3, -1)) / w.sum(1)).view(2, 3, 12, 24)
    torch.testing.assert_close(_prefilter_rows(env, rough), ref, rtol=1e-10, atol=0)
    env.requires_grad_(True)  # differentiable like the brute force
    (grad,) = torch.autograd.grad(_prefilter_rows(env, rough).sum(), env)
    torch.testing.assert_close(grad, (w / w.sum(1, keepdim=True)).sum(0).view(12, 24).expand(
        2, 3, 12, 24), rtol=1e-9, atol=1e-12)


def test_roughness_lod_mapping_roundtrip() -> None:
    for k in range(6):
        r = lod_to_roughness(k, 6)
        assert abs(float(roughness_to_lod(torch.tensor(r), 6)) - k) < 1e-9
    assert lod_to_roughness(0, 6) == 0.0 and lod_to_roughness(5, 6) == 1.0


@pytest.fixture(scope="module")
def smooth_environment() -> Environment:
    # float32 precomputation (the default dtype); the reference is float64
    ev = Environment(_smooth_env(32).float(), specular_size=32, specular_levels=8,
                     specular_samples=64)
    ev.specular_chain  # noqa: B018  (precompute once for the module)
    return ev


@pytest.mark.parametrize("rough", [0.1, 0.5, 1.0])
def test_prefiltered_specular_vs_brute_force(rough: float, smooth_environment: Environment
                                             ) -> None:
    ev = smooth_environment
    env = ev.radiance.double()
    n = _unit(40, seed=3)
    got = ev.specular(n, torch.full((1, 1, 1, 40), rough, dtype=D64))[:, :, 0]
    ref = _brute_lobe(env, n, rough)
    rel = (got - ref).abs() / ref
    assert float(rel.mean()) < 0.01, (float(rel.mean()), float(rel.max()))
    assert float(rel.max()) < 0.03, (float(rel.mean()), float(rel.max()))


@pytest.mark.slow
def test_prefiltered_specular_real_env_levels(shared_data: Path) -> None:
    """On an exact level roughness there is no level blending: quadrature / importance
    sampling alone against the brute-force lobe on the real (downsampled) env."""
    from torchraster.hdr_io import read_hdr

    img = read_hdr(shared_data / "envmaps" / "venice_sunset_1k.hdr")[None].to(D64)
    env = F.adaptive_avg_pool2d(img, (32, 64))
    ev = Environment(env.float(), specular_size=32, specular_levels=6, specular_samples=64)
    n = _unit(30, seed=4)
    for k in (3, 5):  # r = 0.37 (importance sampled), r = 1 (quadrature)
        r = lod_to_roughness(k, 6)
        got = ev.specular(n, torch.full((1, 1, 1, 30), r, dtype=D64))[:, :, 0]
        ref = _brute_lobe(env, n, r)
        rel = (got - ref).abs() / ref
        assert float(rel.mean()) < 0.02, (k, float(rel.mean()), float(rel.max()))


# -------------------------------------------------------------------------------- DFG LUT


def _brute_albedo(nv: float, rough: float, res: int = 400) -> tuple[float, float]:
    """(A, B) by midpoint quadrature over the hemisphere of l (theta, phi grid)."""
    th = (torch.arange(res, dtype=D64) + 0.5) * (math.pi / 2 / res)
    ph = (torch.arange(2 * res, dtype=D64) + 0.5) * (2 * math.pi / (2 * res))
    t, p = torch.meshgrid(th, ph, indexing="ij")
    l = torch.stack((torch.sin(t) * torch.cos(p), torch.sin(t) * torch.sin(p), torch.cos(t)))
    v = torch.tensor([math.sqrt(1 - nv * nv), 0.0, nv], dtype=D64).view(3, 1, 1)
    h = F.normalize(l + v, dim=0)
    n_dot_l = l[2]
    dw = torch.sin(t) * (math.pi / 2 / res) * (2 * math.pi / (2 * res))
    spec = d_ggx(h[2], rough) * v_smith_ggx_correlated(torch.tensor(nv, dtype=D64), n_dot_l,
                                                       rough)
    fc = (1 - (v * h).sum(0)).clamp(0, 1) ** 5
    f = spec * n_dot_l * dw
    return float(((1 - fc) * f).sum()), float((fc * f).sum())


@pytest.mark.parametrize("nv, rough", [(0.9, 0.3), (0.5, 0.6), (0.2, 1.0), (0.7, 0.8)])
def test_dfg_lut_vs_quadrature(nv: float, rough: float) -> None:
    lut = dfg_lut(64, 1024, dtype=D64)
    a, b = lookup_dfg(lut, torch.full((1, 1, 1, 1), nv, dtype=D64),
                      torch.full((1, 1, 1, 1), rough, dtype=D64))
    ra, rb = _brute_albedo(nv, rough)
    assert abs(float(a) - ra) < 0.01 * (ra + rb), (float(a), ra)
    assert abs(float(b) - rb) < 0.01 * (ra + rb), (float(b), rb)


def test_dfg_lut_cached_and_sized() -> None:
    from torchraster.shading.ibl import dfg_lut_uncached

    t1 = dfg_lut(16, 64)
    hits = dfg_lut_uncached.cache_info().hits
    assert t1.shape == (2, 16, 16) and t1.dtype == torch.float32
    torch.testing.assert_close(dfg_lut(16, 64, dtype=D64).float(), t1)
    assert dfg_lut_uncached.cache_info().hits == hits + 1  # computed once, then cached
    # A + B is a directional albedo: <= 1 up to the sampling error of the table
    assert bool((t1 >= 0).all()) and bool((t1.sum(0) <= 1.005).all())


# ------------------------------------------------------------------------ white furnace


def _surface(h: int = 4, w: int = 6, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    n = F.normalize(torch.randn(1, 3, h, w, generator=g, dtype=D64), dim=1)
    v = F.normalize(torch.randn(1, 3, h, w, generator=g, dtype=D64), dim=1)
    v = torch.where((n * v).sum(1, keepdim=True) < 0.05, n, v)  # views above the surface
    return n, v


SMALL = dict(specular_size=8, specular_levels=5, specular_samples=16)  # cheap chains


@pytest.fixture(scope="module")
def white_env() -> Environment:
    return Environment(torch.ones(3, 32, 64, dtype=D64), **SMALL)


@pytest.mark.parametrize("diffuse, tol", [("sh", 1e-9), ("map", 2e-3)])
def test_white_furnace_lambert(diffuse: str, tol: float) -> None:
    # SH projection is exact for a constant map; the irradiance map is a texel-centre
    # quadrature of the clamped cosine (64 x 128 source after no downsampling here)
    env = Environment(torch.ones(3, 64, 128, dtype=D64), diffuse=diffuse, **SMALL)
    n, v = _surface()
    ones = torch.ones(1, 1, 4, 6, dtype=D64)
    out = shade_ibl(n, v, torch.ones(1, 3, 4, 6, dtype=D64), 0 * ones, 0.5 * ones, None, env,
                    f0_dielectric=0.0)
    assert float((out - 1).abs().max()) < tol


def test_irradiance_map_vs_brute_force() -> None:
    env = _smooth_env(32)
    n = _unit(60, seed=6)
    got = Environment(env, diffuse="map", irradiance_height=32,
                      irradiance_source_height=None).irradiance(n)[:, :, 0]
    rel = (got - _brute_irradiance(env, n)).abs() / _brute_irradiance(env, n)
    assert float(rel.mean()) < 0.005 and float(rel.max()) < 0.02, (rel.mean(), rel.max())


@pytest.mark.parametrize("metallic", [0.0, 1.0])
@pytest.mark.parametrize("rough", [0.0, 0.3, 0.7, 1.0])
def test_white_furnace_ggx_energy_compensated(metallic: float, rough: float,
                                              white_env: Environment) -> None:
    env = white_env
    n, v = _surface()
    ones = torch.ones(1, 1, 4, 6, dtype=D64)
    args = (n, v, torch.ones(1, 3, 4, 6, dtype=D64), metallic * ones, rough * ones, None, env)
    out = shade_ibl(*args)
    assert float((out - 1).abs().max()) < 0.02
    single = shade_ibl(*args, multiscatter=False)
    if metallic == 1.0 and rough == 1.0:  # single scattering loses energy at high roughness
        assert float(single.max()) < 0.95


# ------------------------------------------------------------ environment transforms


def test_yaw_equals_rolled_image() -> None:
    env = torch.rand(1, 3, 16, 32, dtype=D64)
    d = torch.randn(1, 3, 5, 7, dtype=D64)
    rotated = Environment(env, yaw=math.pi / 2, **SMALL)
    rolled = Environment(torch.roll(env, -8, dims=-1), **SMALL)  # content at -z moves to -x
    torch.testing.assert_close(rotated.background(d), rolled.background(d))
    torch.testing.assert_close(rotated.irradiance(d), rolled.irradiance(d))
    by_matrix = Environment(env, rotation=yaw_rotation(math.pi / 2).to(D64), **SMALL)
    torch.testing.assert_close(by_matrix.background(d), rolled.background(d))


def test_intensity_scales_everything() -> None:
    env = torch.rand(3, 8, 16, dtype=D64)
    d = torch.randn(1, 3, 2, 3, dtype=D64)
    r = torch.rand(1, 1, 2, 3, dtype=D64)
    e1, e3 = Environment(env, **SMALL), Environment(env, intensity=3.0, **SMALL)
    torch.testing.assert_close(e3.background(d), 3 * e1.background(d))
    torch.testing.assert_close(e3.irradiance(d), 3 * e1.irradiance(d))
    torch.testing.assert_close(e3.specular(d, r), 3 * e1.specular(d, r))


# ---------------------------------------------------------------- gradients, stability


def test_gradcheck_ibl_lookup() -> None:
    env = Environment(_smooth_env(8), specular_size=8, specular_levels=4, specular_samples=8)
    r = torch.randn(1, 3, 2, 2, dtype=D64, requires_grad=True)
    rough = (torch.rand(1, 1, 2, 2, dtype=D64) * 0.8 + 0.1).requires_grad_()
    torch.autograd.gradcheck(env.specular, (r, rough))
    torch.autograd.gradcheck(env.irradiance, (r,))
    torch.autograd.gradcheck(env.background, (r,))


def test_gradcheck_shade_ibl() -> None:
    env = Environment(_smooth_env(8), specular_size=8, specular_levels=4, specular_samples=8)
    n, v = _surface(1, 2, seed=5)
    n = n.requires_grad_()
    albedo = torch.rand(1, 3, 1, 2, dtype=D64, requires_grad=True)
    metal = (torch.rand(1, 1, 1, 2, dtype=D64) * 0.8 + 0.1).requires_grad_()
    rough = (torch.rand(1, 1, 1, 2, dtype=D64) * 0.8 + 0.1).requires_grad_()
    torch.autograd.gradcheck(
        lambda nn, a, m, r: shade_ibl(nn, v, a, m, r, None, env, lut_size=16, lut_samples=64),
        (n, albedo, metal, rough),
    )


def test_gradient_flows_to_environment() -> None:
    radiance = _smooth_env(8).requires_grad_()
    env = Environment(radiance, specular_size=8, specular_levels=4, specular_samples=8)
    n, v = _surface(2, 3)
    ones = torch.ones(1, 1, 2, 3, dtype=D64)
    shade_ibl(n, v, torch.ones(1, 3, 2, 3, dtype=D64), 0.5 * ones, 0.5 * ones, ones, env
              ).sum().backward()
    assert radiance.grad is not None and bool(torch.isfinite(radiance.grad).all())
    assert float(radiance.grad.abs().sum()) > 0


def test_hostile_inputs_finite_values_and_gradients() -> None:
    for intensity in (0.0, 1e6):
        env = Environment(_smooth_env(8).float(), intensity=intensity, specular_size=8,
                          specular_levels=4, specular_samples=8)
        n = torch.tensor([[0, 0, 1], [0, 0, 0], [0, 0, 1], [0, 1, 0], [1e-30, 0, 0],
                          [0, 0, -1]], dtype=torch.float32).T.reshape(1, 3, 1, 6)
        v = torch.tensor([[1, 0, 0], [0, 0, 1], [0, 0, 1], [0, 1, 0], [0, 0, 1],
                          [0, 0, 1]], dtype=torch.float32).T.reshape(1, 3, 1, 6)  # grazing...
        n.requires_grad_()
        v.requires_grad_()
        rough = torch.tensor([0.0, 1.0, 0.0, 1.0, 0.5, 0.5]).view(1, 1, 1, 6).requires_grad_()
        metal = torch.tensor([1.0, 0.0, 0.0, 1.0, 0.5, 0.5]).view(1, 1, 1, 6)
        albedo = torch.full((1, 3, 1, 6), 0.8, requires_grad=True)
        ao = torch.ones(1, 1, 1, 6)
        out = shade_ibl(n, v, albedo, metal, rough, ao, env)
        bg = env.background(torch.zeros(1, 3, 1, 6))
        (out.sum() + bg.sum()).backward()
        assert bool(torch.isfinite(out).all()) and bool(torch.isfinite(bg).all())
        for g in (n.grad, v.grad, rough.grad, albedo.grad):
            assert g is not None and bool(torch.isfinite(g).all())


def test_bad_inputs() -> None:
    env = Environment(torch.ones(3, 8, 16), **SMALL)
    x = torch.ones(1, 3, 2, 2)
    one = torch.ones(1, 1, 2, 2)
    with pytest.raises(ValueError, match="radiance"):
        Environment(torch.ones(4, 8, 16))
    with pytest.raises(ValueError, match="rotation"):
        Environment(torch.ones(3, 8, 16), rotation=torch.eye(4))
    with pytest.raises(ValueError, match="roughness"):
        shade_ibl(x, x, x, one, torch.ones(1, 2, 2, 2), None, env)
    with pytest.raises(ValueError, match="view_dir"):
        shade_ibl(x, torch.ones(1, 3, 2, 3), x, one, one, None, env)
    with pytest.raises(TypeError, match="env"):
        shade_ibl(x, x, x, one, one, None, torch.ones(3, 8, 16))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="samples"):
        prefilter_specular(torch.ones(1, 3, 8, 16), samples=0)
    with pytest.raises(ValueError, match="size"):
        dfg_lut(1)


def test_batched_environments_and_rotations() -> None:
    env = torch.rand(2, 3, 8, 16, dtype=D64)
    rot = torch.stack((torch.eye(3, dtype=D64), yaw_rotation(math.pi / 2).to(D64)))
    batched = Environment(env, rotation=rot, intensity=torch.tensor([1.0, 2.0], dtype=D64),
                          **SMALL)
    d = torch.randn(2, 3, 3, 4, dtype=D64)
    rough = torch.rand(2, 1, 3, 4, dtype=D64)
    out = batched.specular(d, rough)
    assert out.shape == (2, 3, 3, 4)
    single = Environment(env[1], yaw=math.pi / 2, intensity=2.0, **SMALL)
    torch.testing.assert_close(out[1:], single.specular(d[1:], rough[1:]))
    torch.testing.assert_close(batched.irradiance(d)[1:], single.irradiance(d[1:]))
