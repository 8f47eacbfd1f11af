"""Bloom: pyramid vs brute-force sum of full-resolution Gaussians, bright pass, Karis."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from torchraster.post import Bloom, bright_pass


def _gauss_brute(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Full-resolution 2-D Gaussian (direct 2-D kernel, zero outside the image)."""
    r = min(math.ceil(4 * sigma), x.shape[-1])
    t = torch.arange(-r, r + 1, dtype=x.dtype)
    yy, xx = torch.meshgrid(t, t, indexing="ij")
    k = torch.exp(-(xx**2 + yy**2) / (2 * sigma**2))
    k = k / k.sum()
    return F.conv2d(F.pad(x, (r, r, r, r)), k[None, None])


def _scene(h: int = 96) -> torch.Tensor:
    """Bright content well inside a black frame (so the borders play no role)."""
    g = torch.Generator().manual_seed(1)
    x = torch.zeros(1, 1, h, h, dtype=torch.float64)
    x[0, 0, 44:52, 44:52] = torch.rand(8, 8, generator=g, dtype=torch.float64) * 10
    x[0, 0, 40, 53] = 50.0
    return x


@pytest.mark.parametrize("levels", [1, 2, 3])
def test_pyramid_matches_sum_of_full_res_gaussians(levels: int) -> None:
    # Level l of the pyramid (13-tap down, sigma=radius blur, bilinear+tent up) is a
    # Gaussian of variance (4^l - 1) + radius^2 4^l full-res px^2 per axis (variance
    # bookkeeping in bloom.py). Tolerance 1.5 % of the reference peak: the 13-tap and
    # tent kernels are only approximately Gaussian and decimation by 2 aliases a little;
    # measured 0.66-0.98 % on this scene; a wrong level sigma (e.g. off by one level's
    # blur) gives > 10 %.
    x, radius, intensity = _scene(), 1.0, 0.5
    out = Bloom(threshold=0.0, intensity=intensity, radius=radius, levels=levels,
                karis=False)(x)
    ref = sum(_gauss_brute(x, math.sqrt(4**lv * (1 + radius**2) - 1))
              for lv in range(1, levels + 1)) * (intensity / levels)
    err = float((out - x - ref).abs().max() / ref.abs().max())
    assert err < 0.015, err
    # every filter is normalized: the glow carries exactly the input energy (x intensity)
    assert float((out - x).sum() / (intensity * x.sum())) == pytest.approx(1.0, abs=1e-9)


def test_wrong_sigma_would_fail_the_reference_test() -> None:
    x = _scene()
    out = Bloom(threshold=0.0, intensity=1.0, radius=1.0, levels=1, karis=False)(x) - x
    wrong = _gauss_brute(x, math.sqrt(4 * (1 + 1.0**2) - 1) * 1.3)
    assert float((out - wrong).abs().max() / wrong.abs().max()) > 0.1


def test_soft_knee_bright_pass_points() -> None:
    # threshold 1, knee 0.5 -> k = 0.5: quadratic ramp on [0.5, 1.5], linear above.
    # b=0.4 -> 0; b=1 -> (0.5^2 / 2) / 1 = 0.125; b=1.5 -> max(1/2, 0.5)/1.5; b=3 -> 2/3.
    b = torch.tensor([0.4, 1.0, 1.5, 3.0], dtype=torch.float64)
    x = torch.stack([b, 0.5 * b, 0 * b]).reshape(1, 3, 1, 4)
    w = bright_pass(x, 1.0, 0.5)[0, 0, 0] / b
    torch.testing.assert_close(w, torch.tensor([0.0, 0.125, 0.5 / 1.5, 2.0 / 3.0],
                                               dtype=torch.float64))
    hard = bright_pass(x, 1.0, 0.0)[0, 0, 0] / b
    assert hard[0] == 0 and abs(float(hard[1])) < 1e-5


def test_karis_average_suppresses_fireflies_only() -> None:
    patch = torch.zeros(1, 3, 32, 32, dtype=torch.float64)
    patch[0, :, 20:26, 4:10] = 3.0  # a bright patch ...
    both = patch.clone()
    both[0, :, 13, 17] = 1e4  # ... and a single-pixel firefly

    def glow(x: torch.Tensor, karis: bool) -> torch.Tensor:
        return Bloom(threshold=1.0, intensity=1.0, karis=karis)(x) - x

    # the firefly's own glow collapses (its texel gets weight 1/(1 + luma) ~ 1e-4) ...
    assert float(glow(both, True)[0, 0, 13, 17]) < 0.01 * float(glow(both, False)[0, 0, 13, 17])
    # ... so the glow around the patch stays what it is without the firefly, while without
    # the Karis average the firefly's glow swamps it
    ref_k, ref_p = glow(patch, True)[0, 0, 23, 6], glow(patch, False)[0, 0, 23, 6]
    assert abs(float(glow(both, True)[0, 0, 23, 6] / ref_k) - 1.0) < 0.2
    assert float(glow(both, False)[0, 0, 23, 6] / ref_p) > 3.0
    flat = torch.full((1, 3, 32, 32), 2.0, dtype=torch.float64)
    torch.testing.assert_close(Bloom(karis=True)(flat), Bloom(karis=False)(flat))


def test_per_sample_intensity_and_odd_sizes() -> None:
    x = torch.rand(2, 3, 37, 23, dtype=torch.float64) * 4
    y = Bloom(intensity=torch.tensor([0.0, 0.2], dtype=torch.float64), levels=8)(x)
    assert y.shape == x.shape
    torch.testing.assert_close(y[0], x[0])
    assert float((y[1] - x[1]).min()) >= 0 and float((y[1] - x[1]).max()) > 0


def test_disabled_and_bad_args() -> None:
    x = torch.rand(1, 3, 8, 8)
    assert Bloom(enabled=False)(x) is x
    with pytest.raises(ValueError, match="levels"):
        Bloom(levels=0)
    with pytest.raises(ValueError, match="threshold"):
        Bloom(threshold=-1.0)
    with pytest.raises(ValueError, match="intensity"):
        Bloom(intensity=torch.ones(3))(x)
