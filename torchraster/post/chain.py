"""``PostChain``: DOF -> bloom -> exposure / auto-exposure -> tone map -> sRGB encode.

Two halves: :meth:`PostChain.hdr` (DOF, bloom, exposure: linear HDR in, linear HDR out)
and :meth:`PostChain.display` (tone map, encode: display values in [0, 1]). The YAML
``post:`` section is built into a chain by :func:`torchraster.config.build_post_chain`.
"""

from __future__ import annotations

import torch
from torch import nn

from .bloom import Bloom
from .dof import DepthOfField
from .exposure import AutoExposure
from .tonemap import EncodeSRGB, Exposure, ToneMap


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

    def hdr(
        self,
        x: torch.Tensor,
        depth: torch.Tensor | None = None,
        dt: float | torch.Tensor | None = None,
    ) -> torch.Tensor:
        """The linear half: DOF -> bloom -> exposure (or auto-exposure).

        Args:
            x: ``(B, 3, H, W)`` linear HDR radiance.
            depth: ``(B, 1, H, W)`` linear depth in metres, required when DOF is enabled.
            dt: frame time in seconds for auto-exposure adaptation (None = no lag).

        Returns:
            ``(B, 3, H, W)`` linear HDR (exposed radiance); ``x`` itself when all are off.
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
        self.last_run = run
        return x

    def display(self, x: torch.Tensor) -> torch.Tensor:
        """The display half: tone map -> sRGB encode, ``(B, 3, H, W)`` -> ``(B, 3, H, W)``
        (appends to :attr:`last_run`)."""
        for name in ("tonemap", "encode"):
            mod = getattr(self, name)
            if mod.enabled:
                x = mod(x)
                self.last_run.append(name)
        return x

    def forward(
        self,
        x: torch.Tensor,
        depth: torch.Tensor | None = None,
        dt: float | torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Linear HDR ``(B, 3, H, W)`` -> post-processed ``(B, 3, H, W)``:
        ``display(hdr(x, depth, dt))`` (see :meth:`hdr` and :meth:`display`)."""
        return self.display(self.hdr(x, depth, dt))
