"""Exposure, tone curves and sRGB encoding against their published formulas."""

from __future__ import annotations

import math

import pytest
import torch

from torchraster.post import EncodeSRGB, Exposure, ToneMap, encode_srgb, tone_curve


def _img(values: list[float], dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Values as a (1, 3, 1, N) image (same value in all channels)."""
    v = torch.tensor(values, dtype=dtype)
    return v.reshape(1, 1, 1, -1).expand(1, 3, 1, -1).contiguous()


# Expected numbers worked out by hand from the papers' formulas (not from the module):
# Reinhard 2002 eq. 3: x/(1+x). Eq. 4 with white w=4: x(1+x/16)/(1+x).
# Narkowicz 2015: x(2.51x+0.03)/(x(2.43x+0.59)+0.14), e.g. x=1 -> 2.54/3.16.
# Hable 2010: f(2x)/f(11.2), f(x) = (x(0.15x+0.05)+0.004)/(x(0.15x+0.5)+0.06) - 0.02/0.3,
#   e.g. x=1: f(2) = 0.704/1.66 - 1/15 = 0.3574297, f(11.2) = 19.38/24.476 - 1/15 = 0.7251296.
CASES = {
    "linear": ([0.0, 0.25, 1.0, 7.0], [0.0, 0.25, 1.0, 1.0]),
    "reinhard": ([0.0, 1.0, 3.0, 1e6], [0.0, 0.5, 0.75, 1e6 / (1e6 + 1)]),
    "reinhard_extended": ([0.0, 1.0, 2.0, 4.0, 9.0], [0.0, 0.53125, 0.75, 1.0, 1.0]),
    "aces": ([0.0, 0.18, 1.0, 4.0, 100.0], [0.0, 0.2668989204, 2.54 / 3.16, 0.9734171097, 1.0]),
    "hable": ([0.0, 0.18, 1.0, 4.0, 1e6], [0.0, 0.1283384489, 0.4929185460, 0.9180300793, 1.0]),
}


@pytest.mark.parametrize("curve", list(CASES))
def test_tone_curves_match_published_formulas(curve: str) -> None:
    xs, expected = CASES[curve]
    y = ToneMap(curve, white=4.0)(_img(xs))
    torch.testing.assert_close(y[0, 0, 0], torch.tensor(expected, dtype=torch.float64),
                               atol=2e-7, rtol=1e-7)


@pytest.mark.parametrize("curve", list(CASES))
def test_tone_curves_monotone_and_bounded(curve: str) -> None:
    x = torch.logspace(-6, 6, 500, dtype=torch.float64).reshape(1, 1, 1, -1).expand(1, 3, 1, -1)
    y = tone_curve(x, curve)
    assert bool((y >= 0).all() and (y <= 1).all())
    assert bool((y[..., 1:] >= y[..., :-1] - 1e-12).all())


def test_negative_input_clamped_to_black() -> None:
    assert float(tone_curve(_img([-3.0]), "aces").abs().max()) == 0.0


def test_srgb_transfer_function_points() -> None:
    # IEC 61966-2-1: 12.92 x below 0.0031308, else 1.055 x^(1/2.4) - 0.055
    xs = [0.0, 0.001, 0.0031308, 0.18, 0.5, 1.0, 2.0]
    exp = [0.0, 0.01292, 0.04045, 1.055 * 0.18 ** (1 / 2.4) - 0.055,
           1.055 * 0.5 ** (1 / 2.4) - 0.055, 1.0, 1.0]
    y = EncodeSRGB()(_img(xs))
    torch.testing.assert_close(y[0, 1, 0], torch.tensor(exp, dtype=torch.float64),
                               atol=2e-5, rtol=0)
    assert abs(float(y[0, 0, 0, 4]) - 0.735356983) < 1e-6


def test_exposure_scales_by_two_to_the_ev_per_sample() -> None:
    x = torch.rand(3, 3, 4, 5, dtype=torch.float64)
    ev = torch.tensor([0.0, 1.0, -2.5], dtype=torch.float64)
    y = Exposure(ev)(x)
    scale = torch.tensor([1.0, 2.0, 2.0 ** -2.5], dtype=torch.float64).reshape(3, 1, 1, 1)
    torch.testing.assert_close(y, x * scale)
    torch.testing.assert_close(Exposure(1.0)(x, ev=math.log2(3.0)), 3.0 * x)


def test_disabled_modules_return_input_object() -> None:
    x = torch.rand(1, 3, 4, 4)
    for mod in (Exposure(2.0, enabled=False), ToneMap(enabled=False), EncodeSRGB(enabled=False)):
        assert mod(x) is x


def test_bad_arguments_raise_clear_errors() -> None:
    x = torch.rand(2, 3, 4, 4)
    with pytest.raises(ValueError, match="curve"):
        ToneMap("filmic")
    with pytest.raises(ValueError, match="ev"):
        Exposure(torch.zeros(3))(x)
    with pytest.raises(TypeError, match="ev"):
        Exposure("bright")(x)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="x"):
        encode_srgb(torch.rand(2, 4, 4, 4))
    with pytest.raises(ValueError, match="x"):
        tone_curve(torch.rand(3, 4, 4))
