"""gradcheck (float64) for every post module, and hostile inputs in float32/16/bfloat16."""

from __future__ import annotations

import pytest
import torch
from torch.autograd import gradcheck

from torchraster.config import PostConfig, build_post_chain
from torchraster.post import (
    SSAO,
    AutoExposure,
    Bloom,
    DepthOfField,
    EncodeSRGB,
    Exposure,
    GaussianBlur,
    ToneMap,
)

D = torch.float64
KS = torch.tensor([9.0, 9.0, 3.5, 3.5], dtype=D)  # intrinsics for 8x8 images


def _x(lo: float = 0.05, hi: float = 4.0, shape=(1, 3, 8, 8)) -> torch.Tensor:
    return (torch.rand(*shape, dtype=D) * (hi - lo) + lo).requires_grad_()


def _scalar(v: float) -> torch.Tensor:
    return torch.tensor([v], dtype=D, requires_grad=True)


# ------------------------------------------------------------------ gradcheck (float64)

def test_gradcheck_exposure_wrt_image_and_ev() -> None:
    assert gradcheck(lambda x, ev: Exposure()(x, ev=ev), (_x(), _scalar(0.7)))


@pytest.mark.parametrize("curve", ["linear", "reinhard", "reinhard_extended", "aces", "hable"])
def test_gradcheck_tone_curves(curve: str) -> None:
    x = _x(0.05, 0.9) if curve == "linear" else _x(0.05, 6.0)
    assert gradcheck(ToneMap(curve, white=3.0), (x,))


def test_gradcheck_encode() -> None:
    assert gradcheck(EncodeSRGB(), (_x(0.0005, 0.99),))


@pytest.mark.parametrize("metering", ["average", "percentile"])
def test_gradcheck_auto_exposure_wrt_image_and_compensation(metering: str) -> None:
    prev = torch.full((1, 3, 8, 8), 0.3, dtype=D)

    def f(x: torch.Tensor, comp: torch.Tensor) -> torch.Tensor:
        ae = AutoExposure(compensation=comp, metering=metering)
        ae(prev)  # a previous frame sets the adaptation state
        return ae(x, dt=0.05)

    assert gradcheck(f, (_x(), _scalar(0.5)))


def test_gradcheck_bloom_wrt_image_and_intensity() -> None:
    def f(x: torch.Tensor, intensity: torch.Tensor) -> torch.Tensor:
        return Bloom(threshold=0.8, knee=0.5, intensity=intensity, levels=3, karis=True)(x)

    assert gradcheck(f, (_x(), _scalar(0.3)))


def test_gradcheck_dof_wrt_image_focus_and_aperture() -> None:
    depth = torch.rand(1, 1, 8, 8, dtype=D) * 3 + 0.6
    mod = DepthOfField(focal_length_mm=50.0, sensor_width_mm=36.0, max_coc=4.0, levels=4)

    def f(x: torch.Tensor, focus: torch.Tensor, fnum: torch.Tensor) -> torch.Tensor:
        return mod(x, depth, focus_distance=focus, f_number=fnum)

    # CoC up to ~2.5 px on this 8 px wide image: every layer and blend path is active
    assert gradcheck(f, (_x(), _scalar(1.3), _scalar(0.25)))


def test_gradcheck_ssao_wrt_depth_and_normals() -> None:
    depth = (torch.rand(1, 1, 8, 8, dtype=D) * 0.6 + 2.0).requires_grad_()
    normals = (torch.randn(1, 3, 8, 8, dtype=D) * 0.3 + torch.tensor([0, 0, 1.0], dtype=D)
               .reshape(1, 3, 1, 1)).requires_grad_()
    mod = SSAO(radius=0.6, samples=4, bias=0.02, softness=0.2)
    assert gradcheck(lambda d, n: mod(d, n, intrinsics=KS), (depth, normals))


def test_gradcheck_blur_and_full_chain() -> None:
    assert gradcheck(GaussianBlur(0.8), (_x(),))
    cfg = PostConfig.model_validate({
        "dof": {"enabled": True, "focus_distance": 1.3, "f_number": 0.25, "max_coc": 4,
                "levels": 3},
        "bloom": {"enabled": True, "levels": 2, "threshold": 0.5},
        "auto_exposure": {"enabled": True},
        "tonemap": {"curve": "hable"},
    })
    chain = build_post_chain(cfg)
    depth = torch.rand(1, 1, 8, 8, dtype=D) * 3 + 0.6
    assert gradcheck(lambda x: chain(x, depth), (_x(),))
    assert chain.last_run == ["dof", "bloom", "auto_exposure", "tonemap", "encode"]


# ---------------------------------------------------------------- hostile inputs

def _hostile(dtype: torch.dtype) -> torch.Tensor:
    """(2, 3, 16, 16) with zeros, the largest sane HDR value and denormals of ``dtype``."""
    big = 6e4 if dtype == torch.float16 else 1e6
    tiny = torch.finfo(dtype).tiny / 4  # a denormal
    x = torch.rand(2, 3, 16, 16) * 3
    x[:, :, :4] = 0.0
    x[:, :, 4:6] = big
    x[:, :, 6:8] = tiny
    x[0, 1, 9, 9] = big
    return x.to(dtype)


def _depth(dtype: torch.dtype) -> torch.Tensor:
    d = torch.rand(2, 1, 16, 16) * 10 + 0.2
    d[:, :, 0] = 0.0
    d[:, :, 1] = torch.finfo(dtype).tiny / 4
    d[:, :, 2] = 6e4 if dtype == torch.float16 else 1e6
    d[:, :, 3] = float("inf")
    return d.to(dtype)


def _modules() -> dict[str, torch.nn.Module]:
    cfg = PostConfig.model_validate({
        "dof": {"enabled": True, "focus_distance": 2.0}, "bloom": {"enabled": True},
        "auto_exposure": {"enabled": True, "metering": "percentile"},
    })
    return {
        "exposure": Exposure(3.0), "reinhard": ToneMap("reinhard"),
        "reinhard_extended": ToneMap("reinhard_extended"), "aces": ToneMap("aces"),
        "hable": ToneMap("hable"), "linear": ToneMap("linear"), "encode": EncodeSRGB(),
        "auto_exposure": AutoExposure(), "bloom": Bloom(threshold=0.0), "blur": GaussianBlur(2.0),
        "dof": DepthOfField(focus_distance=2.0), "chain": build_post_chain(cfg),
    }


def _run(name: str, mod: torch.nn.Module, x: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    if name == "encode":
        x = x.clamp(max=1.0)
    return mod(x, depth) if name in ("dof", "chain") else mod(x)


@pytest.mark.parametrize("name", list(_modules()))
def test_hostile_inputs_float32_finite_values_and_grads(name: str) -> None:
    mod = _modules()[name]
    x = _hostile(torch.float32).requires_grad_()
    y = _run(name, mod, x, _depth(torch.float32))
    assert bool(torch.isfinite(y).all()), name
    (y * torch.rand_like(y)).sum().backward()
    assert bool(torch.isfinite(x.grad).all()), name


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("name", list(_modules()))
def test_half_precision_inputs(name: str, dtype: torch.dtype) -> None:
    # every op used is implemented on CPU for both dtypes in torch >= 2.5; the modules
    # compute in float32 internally (x^2 terms overflow float16) and return ``dtype``
    y = _run(name, _modules()[name], _hostile(dtype), _depth(dtype))
    assert y.dtype == dtype
    assert bool(torch.isfinite(y).all()), name


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16])
def test_ssao_hostile_depth_and_zero_normals(dtype: torch.dtype) -> None:
    depth = _depth(dtype).float().requires_grad_()
    normals = torch.randn(2, 3, 16, 16)
    normals[:, :, 5] = 0.0
    normals[:, :, 6] = torch.finfo(torch.float32).tiny / 4
    normals = normals.requires_grad_()
    ao = SSAO(samples=8)(depth.to(dtype), normals.to(dtype), intrinsics=torch.tensor(
        [14.0, 14.0, 7.5, 7.5]))
    assert ao.dtype == dtype and bool(torch.isfinite(ao).all())
    assert float(ao.detach().min()) >= 0 and float(ao.detach().max()) <= 1
    ao.float().sum().backward()
    assert bool(torch.isfinite(depth.grad).all()) and bool(torch.isfinite(normals.grad).all())
