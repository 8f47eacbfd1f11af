"""PostChain: canonical order, config parsing (YAML post: section), last_run, identity."""

from __future__ import annotations

import pydantic
import pytest
import torch
import yaml

from torchraster.config import PostConfig, build_post_chain, build_ssao
from torchraster.post import (
    SSAO,
    AutoExposure,
    Bloom,
    DepthOfField,
    EncodeSRGB,
    ToneMap,
)

YAML = """
post:
  dof: {enabled: true, focus_distance: 2.5, f_number: 1.8}
  bloom: {enabled: true, intensity: 0.1, levels: 4}
  exposure: {ev: 1.0}
  auto_exposure: {enabled: true, metering: percentile}
  tonemap: {curve: hable}
  ssao: {enabled: true, samples: 8}
"""


def test_defaults_are_sensible() -> None:
    cfg = PostConfig()
    assert not cfg.dof.enabled and not cfg.bloom.enabled and not cfg.auto_exposure.enabled
    assert cfg.exposure.enabled and cfg.tonemap.enabled and cfg.encode.enabled
    chain = build_post_chain(cfg)
    x = torch.rand(1, 3, 8, 8) * 4
    y = chain(x)
    assert chain.last_run == ["exposure", "tonemap", "encode"]
    assert float(y.min()) >= 0 and float(y.max()) <= 1


def test_chain_runs_canonical_order_and_matches_manual_composition() -> None:
    cfg = PostConfig.model_validate(yaml.safe_load(YAML)["post"])
    chain = build_post_chain(cfg)
    x = torch.rand(2, 3, 16, 16, dtype=torch.float64) * 5
    depth = torch.rand(2, 1, 16, 16, dtype=torch.float64) * 8 + 0.5
    y = chain(x, depth, dt=None)
    assert chain.last_run == ["dof", "bloom", "auto_exposure", "tonemap", "encode"]
    # the same modules built by hand, applied in the documented order
    manual = DepthOfField(2.5, 50.0, 1.8)(x, depth)
    manual = Bloom(intensity=0.1, levels=4)(manual)
    manual = AutoExposure(compensation=1.0, metering="percentile")(manual)
    manual = EncodeSRGB()(ToneMap("hable")(manual))
    torch.testing.assert_close(y, manual)


def test_all_disabled_returns_input_object() -> None:
    cfg = PostConfig.model_validate({"exposure": {"enabled": False},
                                     "tonemap": {"enabled": False},
                                     "encode": {"enabled": False}})
    chain = build_post_chain(cfg)
    x = torch.rand(1, 3, 4, 4)
    assert chain(x) is x and chain.last_run == []


def test_config_rejects_unknown_keys_and_bad_values() -> None:
    with pytest.raises(pydantic.ValidationError, match="blooom"):
        PostConfig.model_validate({"blooom": {}})
    with pytest.raises(pydantic.ValidationError, match="strength"):
        PostConfig.model_validate({"bloom": {"strength": 1}})
    with pytest.raises(pydantic.ValidationError, match="curve"):
        PostConfig.model_validate({"tonemap": {"curve": "filmic"}})
    with pytest.raises(pydantic.ValidationError, match="levels"):
        PostConfig.model_validate({"dof": {"levels": 1}})
    with pytest.raises(pydantic.ValidationError, match="min_ev"):
        PostConfig.model_validate({"auto_exposure": {"min_ev": 5, "max_ev": 1}})


def test_dof_needs_depth_and_ssao_is_separate() -> None:
    chain = build_post_chain({"dof": {"enabled": True}})
    with pytest.raises(ValueError, match="depth"):
        chain(torch.rand(1, 3, 8, 8))
    cfg = PostConfig.model_validate(yaml.safe_load(YAML)["post"])
    ssao = build_ssao(cfg)
    assert isinstance(ssao, SSAO) and ssao.samples == 8 and ssao.enabled
    assert not any(isinstance(m, SSAO) for m in build_post_chain(cfg).modules())
