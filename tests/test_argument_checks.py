"""Bad arguments raise one error naming the argument (issue 22): no silent truthiness, no
bools as counts, no OverflowError / MemoryError / deep torch traceback for a bad value.
Python and YAML take the shadow limits from one table (``shadows.SHADOW_BOUNDS``)."""

from __future__ import annotations

import math
import re

import pydantic
import pytest
import torch

import torchraster as tr
from torchraster.config.schema import ShadowConfig
from torchraster.post import SSR
from torchraster.shading.shadows import (
    MAX_MAP_SIZE,
    SHADOW_BOUNDS,
    SHADOW_INT_FIELDS,
    ShadowSettings,
)

NOT_BOOLS = ["no", None, 0.5, 1, torch.tensor(True), torch.tensor([1.0, 0.0])]


def _triangle() -> tuple[torch.Tensor, torch.Tensor]:
    clip = torch.tensor([[[-0.5, -0.5, 0.0, 1.0], [0.5, -0.5, 0.0, 1.0], [0.0, 0.5, 0.0, 1.0]]])
    return clip, torch.tensor([[0, 1, 2]])


@pytest.mark.parametrize("name", ["blur", "enabled"])
@pytest.mark.parametrize("value", NOT_BOOLS, ids=repr)
def test_ssr_flags_are_bools(name: str, value: object) -> None:
    with pytest.raises(TypeError, match=rf"^{name}: expected True or False"):
        SSR(**{name: value})
    assert getattr(SSR(**{name: False}), name) is False


@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan, "0.1", True])
def test_ssr_thickness_finite(value: object) -> None:
    with pytest.raises(ValueError, match=r"^thickness: expected a finite number > 0"):
        SSR(thickness=value)
    assert SSR(max_distance=math.inf).max_distance == math.inf  # inf = unbounded, documented


FLAGS = [(tr.RasterSettings, "antialias"), (tr.RasterSettings, "cull_backfaces"),
         (tr.BackgroundSettings, "environment"), (tr.ShadingSettings, "multiscatter")]


@pytest.mark.parametrize("group,name", FLAGS, ids=lambda x: getattr(x, "__name__", x))
@pytest.mark.parametrize("value", NOT_BOOLS, ids=repr)
def test_renderer_flags_are_bools(group: type, name: str, value: object) -> None:
    with pytest.raises(TypeError, match=rf"^{group.__name__}.{name}: expected True or False"):
        group(**{name: value})
    assert getattr(group(**{name: True}), name) is True


@pytest.mark.parametrize("value", NOT_BOOLS, ids=repr)
def test_renderer_shadows_is_a_flag_or_settings(value: object) -> None:
    with pytest.raises(TypeError, match=r"^shadows: expected True, False or a ShadowSettings"):
        tr.Renderer(8, shadows=value)
    assert tr.Renderer(8, shadows=False).shadows is False
    settings = tr.ShadowSettings(map_size=64)
    assert tr.Renderer(8, shadows=settings).shadow_settings is settings


@pytest.mark.parametrize("group,name,value", [
    (tr.RasterSettings, "supersample", True), (tr.RasterSettings, "supersample", 2.0),
    (tr.RasterSettings, "supersample", 9), (tr.RasterSettings, "alpha_layers", True),
    (tr.RasterSettings, "max_batch", 0), (tr.TextureSettings, "cache_bytes", True),
    (tr.TextureSettings, "cache_bytes", -1)], ids=str)
def test_renderer_counts_are_ints(group: type, name: str, value: object) -> None:
    with pytest.raises(ValueError, match=rf"^{group.__name__}.{name}: expected an int"):
        group(**{name: value})


@pytest.mark.parametrize("name,home", [("supersample", "RasterSettings(supersample=...)"),
                                       ("texture_filter", "TextureSettings(filter=...)"),
                                       ("background_image", "BackgroundSettings(image=...)"),
                                       ("shading_options", "ShadingSettings(options=...)"),
                                       ("shadow_settings", "shadows=ShadowSettings(...)")])
def test_renderer_former_arguments_say_where_they_went(name: str, home: str) -> None:
    with pytest.raises(TypeError, match=rf"^Renderer\({name}=...\): .*{re.escape(home)}"):
        tr.Renderer(8, **{name: 1})
    with pytest.raises(TypeError, match=r"^Renderer: unexpected keyword argument 'colour'"):
        tr.Renderer(8, colour=1)


@pytest.mark.parametrize("name,value", [("raster", {"supersample": 2}), ("textures", "nearest"),
                                        ("shading", 3), ("background", "white")])
def test_renderer_groups_are_typed(name: str, value: object) -> None:
    with pytest.raises(TypeError, match=rf"^{name}: expected a"):
        tr.Renderer(8, **{name: value})


@pytest.mark.parametrize("name", ["ssao", "ssr"])
def test_renderer_modules_typed(name: str) -> None:
    with pytest.raises(TypeError, match=rf"^{name}: expected a torchraster.post"):
        tr.Renderer(8, **{name: "yes"})


@pytest.mark.parametrize("name", SHADOW_INT_FIELDS)
def test_shadow_counts_refuse_bools(name: str) -> None:
    with pytest.raises(ValueError, match=rf"ShadowSettings.{name}: expected an int in"):
        ShadowSettings(**{name: True})
    with pytest.raises(pydantic.ValidationError, match=name):
        ShadowConfig(**{name: True})


@pytest.mark.parametrize("name", sorted(SHADOW_BOUNDS))
def test_shadow_bounds_agree_in_python_and_yaml(name: str) -> None:
    """Every bound end is accepted by both, one step beyond it refused by both."""
    lo, hi = SHADOW_BOUNDS[name]
    extra = {"filter": "pcss"} if name in ("light_size", "max_penumbra") else (
        {"filter": "vsm"} if name.startswith("vsm") else {})
    step = 1 if name in SHADOW_INT_FIELDS else 1e-6 * max(1.0, abs(hi))
    for value in (lo, hi):
        value = int(value) if name in SHADOW_INT_FIELDS else float(value)
        assert getattr(ShadowSettings(**{name: value}), name) == value
        assert getattr(ShadowConfig(**{name: value}, **extra), name) == value
    for value in (lo - step, hi + step):
        value = int(value) if name in SHADOW_INT_FIELDS else value
        with pytest.raises(ValueError, match=f"ShadowSettings.{name}"):
            ShadowSettings(**{name: value})
        with pytest.raises(pydantic.ValidationError, match=name):
            ShadowConfig(**{name: value}, **extra)


def test_shadow_map_size_one_limit() -> None:
    """ShadowSettings took 16384 while the YAML said <= 8192."""
    assert ShadowConfig.model_fields["map_size"].metadata  # bounded in the schema
    for make in (lambda v: ShadowSettings(map_size=v), lambda v: ShadowConfig(map_size=v)):
        make(MAX_MAP_SIZE)
        with pytest.raises(ValueError, match="map_size"):
            make(2 * MAX_MAP_SIZE)


@pytest.mark.parametrize("value", [math.nan, math.inf, 1e6, 10**6, True, 0, 2.5, "2"])
def test_rasterize_layers_named(value: object) -> None:
    """nan / inf gave ValueError / OverflowError from int(); 1e6 ran out of memory or hung."""
    clip, faces = _triangle()
    with pytest.raises(ValueError, match=r"^layers: expected an int in \[1, "):
        tr.rasterize(clip, faces, (4, 4), layers=value)
    assert len(tr.rasterize(clip, faces, (4, 4), layers=2.0).layers) == 2


def test_meta_and_float8_inputs_named() -> None:
    clip, faces = _triangle()
    with pytest.raises(ValueError, match=r"^clip_pos: a 'meta' tensor holds no data"):
        tr.rasterize(clip.to("meta"), faces, (4, 4))
    with pytest.raises(ValueError, match=r"^faces: a 'meta' tensor"):
        tr.rasterize(clip, faces.to("meta"), (4, 4))
    with pytest.raises(TypeError, match=r"^clip_pos: dtype torch.float8_e4m3fn is not supp"):
        tr.rasterize(clip.to(torch.float8_e4m3fn), faces, (4, 4))


def test_antialias_blames_mismatched_frags() -> None:
    clip, faces = _triangle()
    frags = tr.rasterize(clip, faces, (4, 4))
    with pytest.raises(ValueError, match=r"^frags: fragments of \(B, H, W\) = \(1, 4, 4\)"):
        tr.antialias(torch.zeros(1, 3, 8, 8), frags, clip, faces)
    with pytest.raises(ValueError, match=r"^color: expected shape"):
        tr.antialias(torch.zeros(3, 4, 4), frags, clip, faces)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_finite_check_finds_one_bad_value(dtype: torch.dtype, bad: float) -> None:
    from torchraster._validate import check_tensor

    x = torch.rand(2, 3, 17, 19).to(dtype)
    assert check_tensor("x", x, (2, 3, None, None), finite=True) is x
    x[1, 2, 16, 18] = bad  # the last value
    with pytest.raises(ValueError, match=r"^x: contains 1 NaN/Inf value"):
        check_tensor("x", x, (2, 3, None, None), finite=True)
    x = x.flip(-1).requires_grad_(True)  # a graph leaf: checked without recording
    with pytest.raises(ValueError, match=r"^x: contains 1 NaN/Inf value"):
        check_tensor("x", x, (2, 3, None, None), finite=True)
