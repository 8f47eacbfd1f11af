"""Depth of field: thin-lens CoC numbers, brute-force per-pixel gather, halos and bleeding."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from torchraster.post import DepthOfField, circle_of_confusion
from torchraster.post.dof import COC_RAMP_PX


def test_coc_thin_lens_numbers() -> None:
    # f = 50 mm, N = 2 (A = 25 mm), focus 2 m: A f / (zf - f) = 25 mm * 0.05 / 1.95.
    # z = 4 m: * (1 - 2/4) = 0.320513 mm; z = 1 m: * (1 - 2) = -0.641026 mm; z = inf: +0.641.
    # Sensor 36 mm over 360 px -> 10 px per mm.
    depth = torch.tensor([4.0, 1.0, math.inf, 2.0], dtype=torch.float64).reshape(1, 1, 1, 4)
    depth = depth.expand(1, 1, 1, 4).repeat(1, 1, 1, 90)  # width 360 px
    c = circle_of_confusion(depth, 2.0, 50.0, 2.0, 36.0)[0, 0, 0, :4]
    exp = torch.tensor([3.2051282, -6.4102564, 6.4102564, 0.0], dtype=torch.float64)
    torch.testing.assert_close(c, exp, atol=1e-6, rtol=0)


def test_coc_per_sample_focus() -> None:
    depth = torch.full((2, 1, 4, 4), 3.0, dtype=torch.float64)
    c = circle_of_confusion(depth, torch.tensor([3.0, 1.0], dtype=torch.float64))
    assert float(c[0].abs().max()) == 0.0 and float(c[1].min()) > 0


# ---- brute-force reference: per-pixel variable-sigma Gaussian gather (no blur stack) ----

def _gather(img: torch.Tensor, sigma: torch.Tensor, weight: torch.Tensor | None = None,
            normalize: bool = True) -> torch.Tensor:
    """out(p) = sum_q g_p(q) w(q) img(q) [/ sum_q g_p(q) w(q)], g_p = Gaussian of sigma(p)
    truncated to the square |dx|, |dy| <= ceil(3 sigma(p)); clamp-to-edge borders.
    Without ``normalize`` the result is divided by sum_q g_p(q) only."""
    _, c, h, w = img.shape
    r = max(1, math.ceil(3 * float(sigma.max())))
    wt = torch.ones_like(sigma) if weight is None else weight
    def win(t: torch.Tensor) -> torch.Tensor:
        return F.unfold(F.pad(t, (r, r, r, r), mode="replicate"), 2 * r + 1)  # (1, C*K, HW)
    k = (2 * r + 1) ** 2
    t = torch.arange(-r, r + 1, dtype=img.dtype)
    dy, dx = (v.reshape(k, 1) for v in torch.meshgrid(t, t, indexing="ij"))
    s = sigma.reshape(1, h * w)
    rad = torch.ceil(3 * s)
    g = torch.exp(-(dx**2 + dy**2) / (2 * s.clamp(min=1e-12) ** 2))
    g = torch.where((dx.abs() <= rad) & (dy.abs() <= rad), g, torch.zeros_like(g))
    g = torch.where(s > 0, g, (dx == 0) & (dy == 0)).to(img.dtype)  # sigma 0: the pixel itself
    wq = win(wt).reshape(k, h * w)
    xq = win(img).reshape(c, k, h * w)
    num = (g * wq * xq).sum(1)
    den = (g * wq).sum(0) if normalize else g.sum(0)
    out = num / den.clamp(min=1e-300)
    if normalize:
        out = torch.where(den > 1e-6, out, img.reshape(c, h * w))
    return out.reshape(1, c, h, w)


def _reference_dof(x: torch.Tensor, coc: torch.Tensor, max_coc: float) -> torch.Tensor:
    coc = coc.clamp(-max_coc, max_coc)
    w_far = (coc / COC_RAMP_PX).clamp(0, 1)
    a = (-coc / COC_RAMP_PX).clamp(0, 1)
    far = _gather(x, coc.abs() / 4, w_far)
    # near sigma: max filter of radius ceil(max_coc/2), then a Gaussian of half that radius
    r = math.ceil(max_coc / 2)
    sn = ((-coc).clamp(0, max_coc) / 4)
    sn = F.unfold(F.pad(sn, (r, r, r, r), mode="replicate"), 2 * r + 1).amax(1)
    sn = _gather(sn.reshape(coc.shape), torch.full_like(coc, r / 2))
    near = _gather(torch.cat([x * a, a], 1), sn, normalize=False)
    alpha = near[:, -1:].clamp(0, 1)
    return near[:, :-1] + (1 - alpha) * far


def _scene(n: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    x = torch.rand(1, 3, n, n, generator=g, dtype=torch.float64) * 4
    z = torch.empty(1, 1, n, n, dtype=torch.float64)
    col = torch.arange(n, dtype=torch.float64)
    z[...] = 1.0 + 3.0 * (col / (n - 1)) ** 2  # far field ramp 1 m .. 4 m (focus at 1 m)
    z[..., 8:16, 4:12] = 1.0  # in-focus block
    z[..., 18:26, 14:24] = 0.55  # near block
    return x, z


LENS = dict(focus_distance=1.0, focal_length_mm=50.0, f_number=1.4, sensor_width_mm=6.0)


@pytest.mark.parametrize("levels,tol", [(65, 0.003), (33, 0.01), (9, 0.08)])
def test_matches_brute_force_gather(levels: int, tol: float) -> None:
    # The stack blends blur levels linearly in sigma; the reference gathers every pixel with
    # its own sigma, so the error is the sigma interpolation and falls ~1/levels^2.
    # Tolerances (max abs error / image max) at max_coc 8 px: measured 0.14 % (65 levels),
    # 0.51 % (33) and 5.4 % (9) on this random-colour scene, the worst case for blending.
    x, z = _scene()
    mod = DepthOfField(max_coc=8.0, levels=levels, **LENS)
    out = mod(x, z)
    coc = circle_of_confusion(z, **LENS)
    assert float(coc.min()) < -6 and float(coc.max()) > 6  # both fields are exercised
    ref = _reference_dof(x, coc, 8.0)
    err = float((out - ref).abs().max() / x.max())
    assert err < tol, err


def test_error_shrinks_with_levels() -> None:
    x, z = _scene()
    ref = _reference_dof(x, circle_of_confusion(z, **LENS), 8.0)
    errs = [float((DepthOfField(max_coc=8.0, levels=k, **LENS)(x, z) - ref).abs().mean())
            for k in (2, 5, 17)]
    assert errs[0] > errs[1] > errs[2]


def test_no_halo_around_in_focus_foreground() -> None:
    # blue background far behind the focus plane (blurry), red in-focus square in front
    n = 32
    x = torch.zeros(1, 3, n, n, dtype=torch.float64)
    x[:, 2] = 1.0
    z = torch.full((1, 1, n, n), 50.0, dtype=torch.float64)
    x[:, :, 12:20, 12:20] = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64).reshape(3, 1, 1)
    z[..., 12:20, 12:20] = 1.0
    out = DepthOfField(max_coc=8.0, levels=6, **LENS)(x, z)
    assert float(out[0, 0, 12:20, 12:20].min()) > 0.999  # the square stays sharp
    ring = torch.ones(n, n, dtype=torch.bool)
    ring[12:20, 12:20] = False
    assert float(out[0, 0][ring].max()) < 1e-9  # no red leaks into the blurry background
    # a plain per-pixel gather (no layer weights) would leak red: the test can fail
    plain = _gather(x, circle_of_confusion(z, **LENS).abs().clamp(max=8) / 4)
    assert float(plain[0, 0][ring].max()) > 0.1


def test_near_field_bleeds_over_in_focus_background() -> None:
    n = 32
    x = torch.zeros(1, 3, n, n, dtype=torch.float64)
    x[:, 2] = 1.0
    x[:, :, 12:20, 12:20] = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64).reshape(3, 1, 1)
    z = torch.full((1, 1, n, n), 1.0, dtype=torch.float64)  # background in focus
    z[..., 12:20, 12:20] = 0.55  # red square near: CoC about -8 px
    out = DepthOfField(max_coc=8.0, levels=6, **LENS)(x, z)
    assert float(out[0, 0, 15, 10]) > 0.1  # red bleeds 2 px over the sharp background
    assert float(out[0, 0, 15, 2]) < 1e-6  # ... but not far beyond the blur radius
    assert float(out[0, 2, 15, 2]) == pytest.approx(1.0)  # background there stays sharp


def test_disabled_per_sample_and_bad_args() -> None:
    x, z = torch.rand(2, 3, 8, 8), torch.rand(2, 1, 8, 8) + 1
    assert DepthOfField(enabled=False)(x, z) is x
    out = DepthOfField(focus_distance=torch.tensor([1.0, 5.0]))(x, z)
    assert out.shape == x.shape
    with pytest.raises(ValueError, match="depth"):
        DepthOfField()(x, z[:1])
    with pytest.raises(ValueError, match="focus_distance"):
        DepthOfField(focus_distance=0.01)(x, z)
    with pytest.raises(ValueError, match="levels"):
        DepthOfField(levels=1)
    with pytest.raises(ValueError, match="depth"):
        DepthOfField()(x, torch.full_like(z, math.nan))
