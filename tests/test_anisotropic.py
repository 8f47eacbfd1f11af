"""Anisotropic texture filtering (torchraster.anisotropic) against independent references.

* quality: on the steep checkerboard plane of the benchmark (scripts/bench_quality.py) the
  16x filter is within 1.5 % of the exact pixel-area average
  (``torchraster.testing.reference_texture``, which uses no texture sampler and is itself
  checked against brute-force supersampling here);
* the probes: a per-pixel loop that re-derives the EXT_texture_filter_anisotropic formula
  in float64 Python and calls the trilinear sampler once per probe;
* isotropic and magnified footprints give exactly trilinear filtering;
* hostile derivatives (zero, huge, grazing) give finite values and gradients; gradcheck;
* the Renderer / YAML option, its plan step, and errors that name the bad argument.
"""

from __future__ import annotations

import math

import pytest
import torch

import torchraster as tr
from torchraster.anisotropic import (
    anisotropic_footprint,
    sample_anisotropic,
    sample_anisotropic_dense,
)
from torchraster.testing.reference_texture import (
    checkerboard,
    checkerboard_plane_reference,
    steep_plane,
)
from torchraster.texture import MipTexture, sample_texture

D64 = torch.float64


def _checker_value(uv: torch.Tensor, checks: int = 32) -> torch.Tensor:
    """The checkerboard's value at uv ``(1, 2, h, w)`` straight from its definition."""
    ku, kv = torch.floor(checks * uv[:, 0]), torch.floor(checks * (1 - uv[:, 1]))
    return (0.1 + 0.8 * torch.remainder(ku + kv, 2))[:, None]


# ------------------------------------------------------------------ the reference itself


def test_reference_plane_derivatives_match_finite_differences() -> None:
    uv, dx, dy = steep_plane(12, 16)
    e = 1e-6
    torch.testing.assert_close((steep_plane(12, 16, offset=(0.0, e))[0] - uv) / e, dx,
                               rtol=1e-4, atol=1e-7)
    torch.testing.assert_close((steep_plane(12, 16, offset=(e, 0.0))[0] - uv) / e, dy,
                               rtol=1e-4, atol=1e-7)


def test_reference_texture_convention_matches_the_sampler() -> None:
    """The reference reads the checkerboard where the engine's nearest lookup does."""
    uv = steep_plane(24, 32)[0]
    got = sample_texture(checkerboard(dtype=D64), uv, filter="nearest")
    torch.testing.assert_close(got, _checker_value(uv))


def test_reference_equals_brute_force_supersampling() -> None:
    """Closed-form integration along lines == many point samples of the definition (a
    frame k times larger holds k x k stratified samples of each pixel)."""
    h, w, k = 12, 16, 160
    ref = checkerboard_plane_reference(h, w, row_samples=1024)
    brute = torch.nn.functional.avg_pool2d(_checker_value(steep_plane(h * k, w * k)[0]), k)
    err = float((ref - brute).abs().mean() / brute.mean())
    assert err < 3e-3, err


# ------------------------------------------------------------------------------ quality


def test_16x_is_within_1p5_percent_on_the_steep_plane() -> None:
    h, w = 192, 256  # the benchmark's frame
    ref = checkerboard_plane_reference(h, w, row_samples=128)
    uv, dx, dy = steep_plane(h, w)
    mt = MipTexture(checkerboard())
    uv, dx, dy = uv.float(), dx.float(), dy.float()

    def err(out: torch.Tensor) -> float:
        return float((out.double() - ref).abs().mean() / ref.mean()) * 100

    tri = err(mt.sample(uv, dx, dy))
    aniso = {k: err(mt.sample(uv, dx, dy, filter="anisotropic", max_anisotropy=k))
             for k in (2, 4, 16)}
    assert aniso[16] <= 1.5, (aniso, tri)
    assert tri > 4.0 and aniso[2] < tri and aniso[4] < aniso[2] and aniso[16] <= aniso[4]


# ------------------------------------------------------------------------- the probes


def _loop_reference(tex: torch.Tensor, uv: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor,
                    max_aniso: int) -> torch.Tensor:
    """Pixel by pixel: EXT_texture_filter_anisotropic's Px, Py, N, lod in Python floats
    (P_min floored at one texel), N trilinear lookups at the centres of N equal parts of
    the longer derivative vector, averaged."""
    b, _, h, w = uv.shape
    ht, wt = tex.shape[-2:]
    out = torch.zeros(b, tex.shape[1], h, w, dtype=D64)
    for n_ in range(b):
        for i in range(h):
            for j in range(w):
                jx = (float(dx[n_, 0, i, j]) * wt, float(dx[n_, 1, i, j]) * ht)
                jy = (float(dy[n_, 0, i, j]) * wt, float(dy[n_, 1, i, j]) * ht)
                px, py = math.hypot(*jx), math.hypot(*jy)
                pmax, pmin = max(px, py), min(px, py)
                n = min(max(math.ceil(pmax / max(pmin, 1.0) - 1e-4), 1), max_aniso)
                lod = math.log2(max(pmax, 2.0**-20) / n)
                axis = dx[n_, :, i, j] if px >= py else dy[n_, :, i, j]
                acc = 0.0
                for k in range(n):
                    p = uv[n_, :, i, j] + ((k + 0.5) / n - 0.5) * axis
                    acc = acc + sample_texture(
                        tex[n_:n_ + 1] if tex.shape[0] > 1 else tex, p.view(1, 2, 1, 1),
                        filter="trilinear", lod=torch.full((1, 1, 1, 1), lod, dtype=D64))
                out[n_, :, i, j] = (acc / n).view(-1)
    return out


@pytest.mark.parametrize("shared", [True, False])
def test_probes_match_a_per_pixel_loop(shared: bool) -> None:
    g = torch.Generator().manual_seed(1)
    tex = torch.rand(1 if shared else 2, 3, 32, 24, generator=g, dtype=D64)
    uv = torch.rand(2, 2, 3, 5, generator=g, dtype=D64) * 3 - 1
    angle = torch.rand(2, 1, 3, 5, generator=g, dtype=D64) * 6.3
    major = torch.cat((angle.cos(), angle.sin()), 1) * 0.6 * torch.rand(2, 1, 3, 5, generator=g,
                                                                         dtype=D64)
    minor = torch.randn(2, 2, 3, 5, generator=g, dtype=D64) * 0.01
    dx, dy = major, minor
    dx[:, :, 0], dy[:, :, 0] = minor[:, :, 0], major[:, :, 0]  # major axis along y too
    mt = MipTexture(tex)
    got = mt.sample(uv, dx, dy, filter="anisotropic", max_anisotropy=8)
    counts = anisotropic_footprint(dx, dy, (32, 24), 8)[0]
    assert int(counts.min()) == 1 and int(counts.max()) == 8  # the range is exercised
    torch.testing.assert_close(got, _loop_reference(tex, uv, dx, dy, 8), rtol=1e-10,
                               atol=1e-12)
    dense = sample_anisotropic_dense(mt.levels, uv, dx, dy, mt.address, 8)
    torch.testing.assert_close(got, dense, rtol=1e-12, atol=1e-12)


def test_isotropic_and_magnified_footprints_equal_trilinear() -> None:
    g = torch.Generator().manual_seed(2)
    tex = torch.rand(1, 2, 64, 32, generator=g, dtype=D64)
    uv = torch.rand(1, 2, 6, 7, generator=g, dtype=D64)
    angle = torch.rand(1, 1, 6, 7, generator=g, dtype=D64) * 6.3
    length = 2.0 ** (torch.rand(1, 1, 6, 7, generator=g, dtype=D64) * 10 - 3)  # 1/8..128
    scale = torch.tensor([1 / 32, 1 / 64], dtype=D64).view(1, 2, 1, 1)  # texels -> uv
    dx = torch.cat((angle.cos(), angle.sin()), 1) * length * scale  # |dx| = |dy| in texels
    dy = torch.cat((-angle.sin(), angle.cos()), 1) * length * scale
    mt = MipTexture(tex)
    tri = mt.sample(uv, dx, dy)
    torch.testing.assert_close(mt.sample(uv, dx, dy, filter="anisotropic"), tri, rtol=0,
                               atol=1e-14)
    # magnified but anisotropic (< 1 texel): one probe, as trilinear; mixed with
    # minified anisotropic pixels, so the gathered path runs
    dy_mag = dy * 0.3
    dy_mag[..., :3] = dy[..., :3] * 0.3 / length[..., :3] * 0.5  # 0.5 texel
    dx_mag = dx / length * 0.9  # 0.9 texel
    dx_mag[..., 3:] = dx[..., 3:] / length[..., 3:] * 40  # 40 texels: anisotropic
    out = mt.sample(uv, dx_mag, dy_mag, filter="anisotropic")
    torch.testing.assert_close(out[..., :3], mt.sample(uv, dx_mag, dy_mag)[..., :3], rtol=0,
                               atol=1e-14)
    assert not torch.allclose(out[..., 3:], mt.sample(uv, dx_mag, dy_mag)[..., 3:])


# ------------------------------------------------------------------- hostile inputs


@pytest.mark.parametrize("dtype", [torch.float32, D64])
def test_hostile_derivatives_are_finite_with_finite_gradients(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(3)
    tex = torch.rand(1, 3, 16, 16, generator=g, dtype=dtype).requires_grad_()
    uv = (torch.rand(1, 2, 4, 6, generator=g, dtype=dtype) * 4 - 2).requires_grad_()
    dx = torch.zeros(1, 2, 4, 6, dtype=dtype)
    dy = torch.zeros(1, 2, 4, 6, dtype=dtype)
    dx[..., 0, :] = 1e6  # huge (every level)
    dy[..., 0, :] = 1e6
    dx[..., 1, :] = 1e-30  # tiny and zero: magnified
    dx[:, 0, 2, :] = 1e4  # grazing: huge along x, zero along y
    dy[:, 1, 3, :] = 50.0
    dx[:, 0, 3, :] = 1e-3
    dx.requires_grad_()
    dy.requires_grad_()
    mt = MipTexture(tex)
    out = mt.sample(uv, dx, dy, filter="anisotropic")
    assert out.shape == (1, 3, 4, 6) and bool(torch.isfinite(out).all())
    out.square().sum().backward()
    for t in (tex, uv, dx, dy):
        assert t.grad is not None and bool(torch.isfinite(t.grad).all())
    empty = mt.sample(uv[..., :0], dx[..., :0], dy[..., :0], filter="anisotropic")
    assert empty.shape == (1, 3, 4, 0)


def test_gradcheck() -> None:
    g = torch.Generator().manual_seed(4)
    tex = torch.rand(1, 1, 8, 8, generator=g, dtype=D64, requires_grad=True)
    uv = torch.tensor([[[[0.31, 0.58]], [[0.47, 0.22]]]], dtype=D64, requires_grad=True)
    dx = torch.tensor([[[[0.21, 0.013]], [[0.072, 0.004]]]], dtype=D64, requires_grad=True)
    dy = torch.tensor([[[[0.009, -0.27]], [[-0.015, 0.11]]]], dtype=D64, requires_grad=True)
    n = anisotropic_footprint(dx, dy, (8, 8), 16)[0]
    assert n.flatten().tolist() == [2, 3]  # probes away from the ratio thresholds

    def f(t: torch.Tensor, u: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return sample_anisotropic([t, *tr.texture.build_mip_pyramid(t)[1:]], u, a, b,
                                  ("wrap", "wrap"))

    assert torch.autograd.gradcheck(f, (tex, uv, dx, dy), eps=1e-6, atol=1e-5)


# --------------------------------------------------------------- renderer and config


def _ground(texture: torch.Tensor) -> tr.RenderScene:
    pos = torch.tensor([[-20.0, 0, -40], [20, 0, -40], [20, 0, 2], [-20, 0, 2]])
    faces = torch.tensor([[0, 2, 1], [0, 3, 2]])
    uvs = torch.stack((pos[:, 0] / 4, -pos[:, 2] / 4), 1)
    return tr.RenderScene(pos, faces, uvs=uvs,
                          materials=[tr.Material(base_color_texture=texture)])


EYE_VIEW = tr.camera.look_at(torch.tensor([0.0, 1.0, 1.0]), torch.tensor([0.0, 0.0, -6.0]),
                             torch.tensor([0.0, 1.0, 0.0]))
PROJ = tr.camera.perspective(50.0, 1.0, 0.05)


def test_renderer_runs_the_filter_and_plans_it() -> None:
    tex = checkerboard(64, 8)[0].expand(3, -1, -1).clone()
    scene = _ground(tex)
    r = tr.Renderer(24,
                    shading="unlit",
                    textures=tr.TextureSettings(filter="anisotropic", max_anisotropy=8))
    out = r(scene, EYE_VIEW, PROJ)
    assert out.plan.anisotropy == 8 and out.plan.derivatives
    assert "anisotropic texture filtering 8x" in out.plan
    # the same pixels from the public pieces: rasterize, interpolate UVs and derivatives,
    # sample with the filter
    clip = tr.camera.transform_points(scene.positions, PROJ @ EYE_VIEW)
    frags = tr.rasterize(clip.view(1, -1, 4), scene.faces, (24, 24), derivatives=True)
    uv, ddx, ddy = tr.interpolate_with_derivatives(scene.uvs, frags, scene.faces)
    want = MipTexture(tex[None]).sample(uv, ddx, ddy, filter="anisotropic", max_anisotropy=8)
    mask = frags.face_id[:, None] >= 0
    assert int(mask.sum()) > 100
    torch.testing.assert_close(out.image, want * mask, rtol=1e-5, atol=1e-6)
    tri = tr.Renderer(24, shading="unlit")(scene, EYE_VIEW, PROJ)
    assert "anisotropic texture filtering 16x" not in tri.plan and tri.plan.anisotropy == 0
    assert not torch.allclose(tri.image, out.image)


def test_renderer_skips_it_without_textures_and_stays_finite() -> None:
    r = tr.Renderer(16, shading="unlit", textures=tr.TextureSettings(filter="anisotropic"))
    plain = tr.RenderScene(torch.tensor([[-1.0, 0, -3], [1, 0, -3], [0, 1, -3]]),
                           torch.tensor([[0, 1, 2]]))
    out = r(plain, EYE_VIEW, PROJ)
    assert out.plan.anisotropy == 0 and not out.plan.derivatives
    assert not any("anisotropic" in s for s in out.plan)
    tex = torch.rand(3, 16, 16, requires_grad=True)
    away = tr.camera.look_at(torch.tensor([0.0, 1.0, 1.0]), torch.tensor([0.0, 2.0, 5.0]),
                             torch.tensor([0.0, 1.0, 0.0]))  # empty frame
    grazing = tr.camera.look_at(torch.tensor([0.0, 0.02, 1.0]), torch.tensor([0.0, 0.02, -9.0]),
                                torch.tensor([0.0, 1.0, 0.0]))  # ground 1.5-25 deg down
    empty = r(_ground(tex), away, PROJ)
    assert float(empty.alpha.sum()) == 0 and bool(torch.isfinite(empty.image).all())
    for view in (grazing, EYE_VIEW):
        out = r(_ground(tex), view, PROJ)
        assert out.plan.anisotropy == 16 and float(out.alpha.sum()) > 0
        img = out.image
        assert bool(torch.isfinite(img).all())
        img.sum().backward()
        assert tex.grad is not None and bool(torch.isfinite(tex.grad).all())
        tex.grad = None


def test_bad_options_name_the_argument() -> None:
    for bad in (0, 65, 2.0, True):
        with pytest.raises(ValueError, match="max_anisotropy"):
            tr.Renderer(8, textures=tr.TextureSettings(filter="anisotropic", max_anisotropy=bad))
    with pytest.raises(ValueError, match=r"^TextureSettings.filter: expected one of"):
        tr.Renderer(8, textures=tr.TextureSettings(filter="ewa"))
    with pytest.raises(ValueError, match=r"^TextureSettings.max_anisotropy: used by filter="):
        tr.TextureSettings(max_anisotropy=4)
    mt = MipTexture(torch.rand(1, 1, 8, 8))
    uv = torch.rand(1, 2, 2, 2)
    with pytest.raises(ValueError, match="duv_dx, duv_dy"):
        mt.sample(uv, filter="anisotropic")
    with pytest.raises(ValueError, match="lod"):
        mt.sample(uv, uv, uv, filter="anisotropic", lod=torch.zeros(1, 1, 2, 2))
    with pytest.raises(ValueError, match="max_anisotropy"):
        mt.sample(uv, uv, uv, filter="anisotropic", max_anisotropy=0)
    with pytest.raises(ValueError, match="filter"):
        tr.texture.sample_latlong(torch.rand(1, 3, 4, 8), torch.rand(1, 3, 2, 2),
                                  filter="anisotropic")


def test_yaml_option(tmp_path) -> None:  # noqa: ANN001
    base = "scene: {mesh: spot}\nrender: {resolution: 8, %s}\n"
    cfg = tr.parse_config(base % "texture_filter: anisotropic, max_anisotropy: 4", "a.yaml",
                          base_dir=tmp_path)
    assert cfg.render.texture_filter == "anisotropic" and cfg.render.max_anisotropy == 4
    from torchraster.config import build_renderer

    r = build_renderer(cfg, with_environment=False)
    assert r.texture_settings == tr.TextureSettings(filter="anisotropic", max_anisotropy=4)
    with pytest.raises(tr.ConfigError, match="max_anisotropy"):
        tr.parse_config(base % "max_anisotropy: 4", "b.yaml", base_dir=tmp_path)
    with pytest.raises(tr.ConfigError, match="max_anisotropy"):
        tr.parse_config(base % "texture_filter: anisotropic, max_anisotropy: 0", "c.yaml",
                        base_dir=tmp_path)
