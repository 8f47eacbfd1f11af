"""``PostChain``: DOF -> bloom -> exposure / auto-exposure -> tone map -> sRGB encode.

Configured from the ``post:`` section of a YAML render config through the pydantic model
:class:`PostConfig` (every effect has an ``enabled`` flag; unknown keys are errors). SSAO
feeds the lighting pass, not this chain: it is configured here (``post.ssao``) but built
separately with :func:`build_ssao`.
"""

from __future__ import annotations

from typing import Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator
from torch import nn

from .bloom import Bloom
from .dof import DepthOfField
from .exposure import AutoExposure
from .ssao import SSAO
from .tonemap import EncodeSRGB, Exposure, ToneMap


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class DOFConfig(_Section):
    """Thin-lens depth of field (needs linear depth)."""

    enabled: bool = False
    focus_distance: float = Field(5.0, gt=0, description="metres")
    focal_length_mm: float = Field(50.0, gt=0)
    f_number: float = Field(2.8, gt=0)
    sensor_width_mm: float = Field(36.0, gt=0)
    max_coc: float = Field(16.0, gt=0, description="largest CoC diameter, pixels")
    levels: int = Field(12, ge=2, description="blur levels blended per pixel")


class BloomConfig(_Section):
    """HDR bloom (bright pass + 13-tap pyramid)."""

    enabled: bool = False
    threshold: float = Field(1.0, ge=0)
    knee: float = Field(0.5, ge=0)
    intensity: float = Field(0.05, ge=0)
    radius: float = Field(1.5, ge=0, description="Gaussian sigma per level, level pixels")
    levels: int = Field(5, ge=1)
    karis: bool = True


class ExposureConfig(_Section):
    """Manual exposure in EV (also the compensation when auto-exposure is on)."""

    enabled: bool = True
    ev: float = 0.0


class AutoExposureConfig(_Section):
    """Metered exposure with temporal adaptation (replaces manual exposure when enabled)."""

    enabled: bool = False
    key: float = Field(0.18, gt=0)
    min_ev: float = -16.0
    max_ev: float = 16.0
    metering: Literal["average", "percentile"] = "average"
    percentile_low: float = Field(0.1, ge=0, le=1)
    percentile_high: float = Field(0.9, ge=0, le=1)
    rate: float = Field(1.5, ge=0, description="adaptation speed, 1/s")

    @model_validator(mode="after")
    def _ordered(self) -> AutoExposureConfig:
        if self.min_ev > self.max_ev:
            raise ValueError("min_ev must be <= max_ev")
        if self.percentile_low >= self.percentile_high:
            raise ValueError("percentile_low must be < percentile_high")
        return self


class ToneMapConfig(_Section):
    """Tone curve (see ``torchraster.post.tonemap``)."""

    enabled: bool = True
    curve: Literal["linear", "reinhard", "reinhard_extended", "aces", "hable"] = "aces"
    white: float = Field(4.0, gt=0, description="white point of reinhard_extended")


class EncodeConfig(_Section):
    """Output encoding (linear -> sRGB transfer function)."""

    enabled: bool = True


class SSAOConfig(_Section):
    """Screen-space ambient occlusion (used by the lighting pass, not by PostChain)."""

    enabled: bool = False
    radius: float = Field(0.5, gt=0, description="scene units")
    samples: int = Field(16, ge=1)
    bias: float = Field(0.025, ge=0)
    softness: float = Field(0.025, gt=0)
    blur: bool = True


class PostConfig(_Section):
    """The ``post:`` section of a render config."""

    dof: DOFConfig = Field(default_factory=DOFConfig)
    bloom: BloomConfig = Field(default_factory=BloomConfig)
    exposure: ExposureConfig = Field(default_factory=ExposureConfig)
    auto_exposure: AutoExposureConfig = Field(default_factory=AutoExposureConfig)
    tonemap: ToneMapConfig = Field(default_factory=ToneMapConfig)
    encode: EncodeConfig = Field(default_factory=EncodeConfig)
    ssao: SSAOConfig = Field(default_factory=SSAOConfig)


def build_ssao(cfg: PostConfig | SSAOConfig) -> SSAO:
    """The SSAO module described by ``cfg.ssao`` (or an :class:`SSAOConfig`)."""
    c = cfg.ssao if isinstance(cfg, PostConfig) else cfg
    return SSAO(c.radius, c.samples, c.bias, c.softness, c.blur, enabled=c.enabled)


class PostChain(nn.Module):
    """Post-processing in canonical order on linear HDR (B, 3, H, W).

    DOF -> bloom -> exposure (auto-exposure when enabled, with the manual ``ev`` as
    compensation) -> tone map -> sRGB encode. Disabled stages cost nothing; with every
    stage disabled the input object itself is returned. After each call ``last_run`` lists
    the stages that ran (names: "dof", "bloom", "exposure", "auto_exposure", "tonemap",
    "encode").
    """

    def __init__(
        self,
        dof: DepthOfField | None = None,
        bloom: Bloom | None = None,
        exposure: Exposure | None = None,
        auto_exposure: AutoExposure | None = None,
        tonemap: ToneMap | None = None,
        encode: EncodeSRGB | None = None,
    ):
        super().__init__()
        self.dof = dof or DepthOfField(enabled=False)
        self.bloom = bloom or Bloom(enabled=False)
        self.exposure = exposure or Exposure(enabled=False)
        self.auto_exposure = auto_exposure or AutoExposure(enabled=False)
        self.tonemap = tonemap or ToneMap(enabled=False)
        self.encode = encode or EncodeSRGB(enabled=False)
        self.last_run: list[str] = []

    @classmethod
    def from_config(cls, cfg: PostConfig | dict | None = None) -> PostChain:
        """Build the chain from a :class:`PostConfig` (or the raw ``post:`` mapping)."""
        cfg = PostConfig.model_validate(cfg or {}) if not isinstance(cfg, PostConfig) else cfg
        d, b, e, a, t = cfg.dof, cfg.bloom, cfg.exposure, cfg.auto_exposure, cfg.tonemap
        return cls(
            dof=DepthOfField(d.focus_distance, d.focal_length_mm, d.f_number,
                             d.sensor_width_mm, d.max_coc, d.levels, enabled=d.enabled),
            bloom=Bloom(b.threshold, b.knee, b.intensity, b.radius, b.levels, b.karis,
                        enabled=b.enabled),
            exposure=Exposure(e.ev, enabled=e.enabled and not a.enabled),
            auto_exposure=AutoExposure(a.key, a.min_ev, a.max_ev,
                                       e.ev if e.enabled else 0.0, a.metering,
                                       a.percentile_low, a.percentile_high, a.rate,
                                       enabled=a.enabled),
            tonemap=ToneMap(t.curve, t.white, enabled=t.enabled),
            encode=EncodeSRGB(enabled=cfg.encode.enabled),
        )

    def forward(
        self,
        x: torch.Tensor,
        depth: torch.Tensor | None = None,
        dt: float | torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Linear HDR (B, 3, H, W) -> post-processed (B, 3, H, W).

        ``depth``: linear depth (B, 1, H, W) in metres, required when DOF is enabled.
        ``dt``: frame time in seconds for auto-exposure adaptation (None = no lag).
        """
        run: list[str] = []
        if self.dof.enabled:
            if depth is None:
                raise ValueError("depth: required (B, 1, H, W) linear depth when dof is enabled")
            x = self.dof(x, depth)
            run.append("dof")
        for name in ("bloom", "exposure"):
            mod = getattr(self, name)
            if mod.enabled:
                x = mod(x)
                run.append(name)
        if self.auto_exposure.enabled:
            x = self.auto_exposure(x, dt)
            run.append("auto_exposure")
        for name in ("tonemap", "encode"):
            mod = getattr(self, name)
            if mod.enabled:
                x = mod(x)
                run.append(name)
        self.last_run = run
        return x
