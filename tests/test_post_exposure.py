"""Auto-exposure: metering, key value, EV clamps, percentile metering, temporal adaptation."""

from __future__ import annotations

import math

import pytest
import torch

from torchraster.post import AutoExposure, luminance, metered_log2_luminance
from torchraster.post.exposure import LUM_FLOOR


def _const(values: list[float], h: int = 8, w: int = 8) -> torch.Tensor:
    """(B, 3, h, w) grey images of the given luminances (grey: luminance = value)."""
    v = torch.tensor(values, dtype=torch.float64).reshape(-1, 1, 1, 1)
    return v.expand(-1, 3, h, w).contiguous()


def test_rec709_luminance_weights() -> None:
    x = torch.zeros(3, 3, 1, 1, dtype=torch.float64)
    for c in range(3):
        x[c, c] = 1.0
    assert luminance(x).flatten().tolist() == pytest.approx([0.2126, 0.7152, 0.0722])


@pytest.mark.parametrize("metering", ["average", "percentile"])
def test_constant_image_is_exposed_to_the_key(metering: str) -> None:
    lums = [0.01, 0.5, 5.0, 3000.0]
    y = AutoExposure(key=0.18, metering=metering)(_const(lums))
    # exposure 0.18 / (L + LUM_FLOOR) (Reinhard eq. 1-2 with his delta)
    exp = torch.tensor([0.18 * v / (v + LUM_FLOOR) for v in lums], dtype=torch.float64)
    torch.testing.assert_close(y[:, 0, 0, 0], exp, rtol=1e-9, atol=0)


def test_log_average_is_geometric_mean() -> None:
    x = _const([1.0], 4, 4)
    x[:, :, :2] = 16.0  # half the pixels 16, half 1 -> geometric mean 4
    assert float(metered_log2_luminance(x)[0]) == pytest.approx(2.0, abs=1e-6)


def test_ev_clamps_and_compensation() -> None:
    ae = AutoExposure(min_ev=-2.0, max_ev=3.0)
    ae(_const([1e-4, 1e4]))
    assert ae.last_ev.tolist() == [3.0, -2.0]
    ae = AutoExposure(compensation=torch.tensor([1.0, -1.0]))
    ae(_const([0.18, 0.18]))
    torch.testing.assert_close(ae.last_ev, torch.tensor([1.0, -1.0], dtype=torch.float64),
                               atol=1e-4, rtol=0)


def test_percentile_metering_ignores_highlights() -> None:
    x = _const([1.0], 20, 20)
    x[:, :, 0, :] = 1e6  # a very bright first row: 5 % of the pixels
    avg = AutoExposure(metering="average")
    pct = AutoExposure(metering="percentile", percentile_low=0.1, percentile_high=0.9)
    avg(x)
    pct(x)
    assert float(pct.last_ev[0]) == pytest.approx(math.log2(0.18), abs=1e-5)
    assert float(avg.last_ev[0]) < math.log2(0.18) - 0.9  # pulled down by ~20 * 0.05 stops


def test_temporal_adaptation_follows_closed_form_and_converges() -> None:
    rate, dt = 2.0, 1.0 / 30.0
    ae = AutoExposure(rate=rate)
    ae(_const([1.0]))  # first frame: adapts instantly to log2 L = 0
    assert float(ae.last_ev[0]) == pytest.approx(math.log2(0.18), abs=1e-5)
    bright = _const([16.0])  # log2 L = 4
    for n in range(1, 31):
        ae(bright, dt=dt)
        adapted = 4.0 * (1.0 - math.exp(-rate * n * dt))  # exponential adaptation
        assert float(ae.adapted_log2_lum[0]) == pytest.approx(adapted, abs=1e-5)
    for _ in range(300):
        y = ae(bright, dt=dt)
    assert float(y[0, 0, 0, 0]) == pytest.approx(0.18, rel=1e-4)


def test_adaptation_is_frame_rate_independent_and_reset_works() -> None:
    a, b = AutoExposure(rate=1.0), AutoExposure(rate=1.0)
    for m in (a, b):
        m(_const([1.0]))
    for _ in range(10):
        a(_const([8.0]), dt=0.1)
    b(_const([8.0]), dt=1.0)
    torch.testing.assert_close(a.adapted_log2_lum, b.adapted_log2_lum)
    a.reset()
    a(_const([8.0]), dt=0.1)
    assert float(a.adapted_log2_lum[0]) == pytest.approx(3.0, abs=1e-5)


def test_state_has_no_graph_and_per_sample_dt() -> None:
    ae = AutoExposure(rate=1.0)
    x = _const([1.0, 1.0]).requires_grad_()
    ae(x)
    ae(_const([4.0, 4.0]), dt=torch.tensor([0.0, 1e9]))
    assert not ae.adapted_log2_lum.requires_grad
    assert ae.adapted_log2_lum.tolist() == pytest.approx([0.0, 2.0], abs=1e-5)


def test_disabled_and_bad_args() -> None:
    x = _const([1.0])
    assert AutoExposure(enabled=False)(x) is x
    with pytest.raises(ValueError, match="metering"):
        AutoExposure(metering="spot")
    with pytest.raises(ValueError, match="min_ev"):
        AutoExposure(min_ev=3, max_ev=1)
    with pytest.raises(ValueError, match="dt"):
        ae = AutoExposure()
        ae(x)
        ae(x, dt=-1.0)
    with pytest.raises(ValueError, match="x"):
        AutoExposure()(torch.rand(1, 4, 2, 2))
