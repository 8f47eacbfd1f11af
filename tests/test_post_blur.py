"""Separable conv2d Gaussian blur against kornia and a brute-force 2-D convolution."""

from __future__ import annotations

import math

import kornia
import pytest
import torch
import torch.nn.functional as F

from torchraster.post import GaussianBlur, gaussian_blur


def _brute(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Direct 2-D correlation with the full (non-separated) normalized Gaussian."""
    r = math.ceil(3 * sigma)
    t = torch.arange(-r, r + 1, dtype=x.dtype)
    yy, xx = torch.meshgrid(t, t, indexing="ij")
    k = torch.exp(-(xx**2 + yy**2) / (2 * sigma**2))
    k = (k / k.sum()).expand(x.shape[1], 1, -1, -1)
    return F.conv2d(F.pad(x, (r, r, r, r), mode="replicate"), k, groups=x.shape[1])


@pytest.mark.parametrize("sigma", [0.7, 2.0, 3.5])
def test_matches_brute_force_and_kornia(sigma: float) -> None:
    x = torch.rand(2, 3, 24, 20, dtype=torch.float64)
    y = gaussian_blur(x, sigma)
    torch.testing.assert_close(y, _brute(x, sigma), atol=1e-12, rtol=0)
    k = 2 * math.ceil(3 * sigma) + 1
    ref = kornia.filters.gaussian_blur2d(x, k, (sigma, sigma), border_type="replicate")
    torch.testing.assert_close(y, ref, atol=1e-12, rtol=0)


def test_zero_sigma_and_disabled_are_identity() -> None:
    x = torch.rand(1, 2, 5, 5)
    assert gaussian_blur(x, 0.0) is x
    assert GaussianBlur(2.0, enabled=False)(x) is x


def test_gradcheck() -> None:
    x = torch.rand(1, 3, 8, 8, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: gaussian_blur(t, 1.2), (x,))


def test_bad_args() -> None:
    with pytest.raises(ValueError, match="border"):
        gaussian_blur(torch.rand(1, 1, 4, 4), 1.0, border="mirror")
    with pytest.raises(TypeError, match="x"):
        gaussian_blur(torch.ones(1, 1, 4, 4, dtype=torch.int64), 1.0)
