"""The settings of a :class:`~torchraster.Renderer`, grouped as PyTorch3D groups
``RasterizationSettings``: what to shade with, how to rasterize, how to filter textures and
what lies behind the scene. Shadows have :class:`~torchraster.shading.shadows.ShadowSettings`.

Each group is a frozen dataclass that checks itself on construction (a bad value raises an
error naming ``Group.field``); the YAML ``render:`` section takes the same fields, with
defaults and bounds read from here (one source for Python and YAML)::

    renderer = tr.Renderer(512, shading="pbr",
                           raster=RasterSettings(supersample=2, cull_backfaces=True),
                           textures=TextureSettings(filter="anisotropic", max_anisotropy=8))

Example:
    >>> RasterSettings(edge_supersample=4).edge_supersample
    4
    >>> RasterSettings(supersample=0)
    Traceback (most recent call last):
    ...
    ValueError: RasterSettings.supersample: expected an int in [1, 8], got 0
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from ._validate import check_bool, check_int, check_tensor
from .anisotropic import MAX_TEXTURE_ANISOTROPY, check_max_anisotropy
from .background import FITS
from .edge_aa import MAX_EDGE_SUPERSAMPLE
from .shading.models import get_model

#: Shading paths of the renderer (see :mod:`torchraster.renderer`).
SHADING = ("pbr", "blinn_phong", "half_lambert", "toon", "headlight", "unlit")
#: The lit shading paths and the model of :mod:`torchraster.shading.models` each uses.
LIT_MODELS = {"pbr": "cook_torrance", "blinn_phong": "blinn_phong",
              "half_lambert": "half_lambert", "toon": "toon"}
TEXTURE_FILTERS = ("trilinear", "anisotropic", "bilinear", "nearest")
#: Largest supersampling factor (the frame is rendered at s x s pixels per pixel).
MAX_SUPERSAMPLE: int = 8
#: Most depth layers of MASK / BLEND materials.
MAX_ALPHA_LAYERS: int = 16
#: Closed bounds of the integer fields of :class:`RasterSettings` and
#: :class:`TextureSettings`: the limits they check and the YAML schema states.
SETTINGS_BOUNDS: dict[str, tuple[int, int]] = {
    "supersample": (1, MAX_SUPERSAMPLE), "edge_supersample": (1, MAX_EDGE_SUPERSAMPLE),
    "alpha_layers": (1, MAX_ALPHA_LAYERS), "max_anisotropy": (1, MAX_TEXTURE_ANISOTROPY),
}


@dataclass(frozen=True, eq=False)
class ShadingSettings:
    """What the surfaces are shaded with.

    Args:
        model: one of :data:`SHADING`: ``"pbr"`` (Cook-Torrance), the stylised
            ``"blinn_phong"``, ``"half_lambert"`` and ``"toon"`` (lit by the same lights),
            ``"headlight"`` (Lambert lit from the camera) or ``"unlit"`` (albedo + emissive).
        options: keyword options of a lit model's BRDF (e.g. ``{"bands": 3}`` for toon; see
            :mod:`torchraster.shading.models`); refused by headlight and unlit.
        multiscatter: pbr's multiple-scattering energy compensation (False: the
            single-scattering BRDF); only ``"pbr"`` has it to switch off.
    """

    model: str = "pbr"
    options: Mapping[str, Any] = field(default_factory=dict)
    multiscatter: bool = True

    def __post_init__(self) -> None:
        if self.model not in SHADING:
            raise ValueError(f"ShadingSettings.model: expected one of {SHADING}, got "
                             f"{self.model!r}")
        if not isinstance(self.options, Mapping):
            raise TypeError(f"ShadingSettings.options: expected a mapping of option names to "
                            f"values, got {type(self.options).__name__}")
        if self.options and self.model not in LIT_MODELS:
            raise ValueError(f"ShadingSettings.options: shading {self.model!r} takes no "
                             f"options, got {sorted(self.options)}")
        object.__setattr__(self, "options", dict(self.options))
        if self.model in LIT_MODELS:
            get_model(LIT_MODELS[self.model], **self.options)  # unknown options raise here
        check_bool("ShadingSettings.multiscatter", self.multiscatter)
        if not self.multiscatter and self.model != "pbr":
            raise ValueError(f"ShadingSettings.multiscatter: the energy terms of pbr shading; "
                             f"model is {self.model!r}, which has none to switch off")


@dataclass(frozen=True)
class RasterSettings:
    """How the frame is rasterized and sampled.

    Args:
        supersample: render at ``s`` x the resolution and box-filter down (1 = off).
        edge_supersample: antialias edges only: pixels on geometric and shadow edges are
            shaded at ``k x k`` sub-samples and box-filtered (labels stay exact; 1 = off; not
            combined with ``supersample > 1`` or ``antialias``).
        antialias: analytic antialiasing of silhouette and occlusion edges (gradients at
            edges): the cheapest edge antialiasing of images (1.2-1.4x a frame on the
            edge-antialiasing scenes of docs/benchmarks.md, 43.7-44.6 dB against 8 x 8
            supersampling; 1.3-1.7x on Spot); shadow edges stay as soft as the shadow
            filter makes them.
        cull_backfaces: drop back faces of every material (else only of single-sided
            glTF materials).
        alpha_layers: depth layers for MASK / BLEND materials.
        max_batch: render larger batches in chunks of at most this many items (bounded
            memory, identical results; None = one pass).
        camera_relative: rasterize in coordinates centred on each camera (True), never
            (False), or when float32 world coordinates are far from the origin (None).
    """

    supersample: int = 1
    edge_supersample: int = 1
    antialias: bool = False
    cull_backfaces: bool = False
    alpha_layers: int = 4
    max_batch: int | None = None
    camera_relative: bool | None = None

    def __post_init__(self) -> None:
        for name in ("supersample", "edge_supersample", "alpha_layers"):
            lo, hi = SETTINGS_BOUNDS[name]
            object.__setattr__(self, name, check_int(f"RasterSettings.{name}",
                                                     getattr(self, name), lo, hi))
        check_bool("RasterSettings.antialias", self.antialias)
        check_bool("RasterSettings.cull_backfaces", self.cull_backfaces)
        if self.max_batch is not None:
            check_int("RasterSettings.max_batch", self.max_batch, 1)
        if self.camera_relative is not None:
            check_bool("RasterSettings.camera_relative", self.camera_relative)
        if self.edge_supersample > 1 and self.supersample > 1:
            raise ValueError(f"RasterSettings.edge_supersample: not combined with supersample="
                             f"{self.supersample} (use one of them)")
        if self.edge_supersample > 1 and self.antialias:
            raise ValueError("RasterSettings.edge_supersample: not combined with "
                             "antialias=True (both antialias edges; use one of them)")


@dataclass(frozen=True)
class TextureSettings:
    """How textures are filtered.

    Args:
        filter: one of :data:`TEXTURE_FILTERS`; ``"anisotropic"`` takes up to
            ``max_anisotropy`` trilinear probes along each pixel's footprint.
        max_anisotropy: most probes of the anisotropic filter (refused with other filters).
        cache_bytes: bound of the renderer's cache of texture mip pyramids (0 = no cache).
    """

    filter: str = "trilinear"
    max_anisotropy: int = 16
    cache_bytes: int = 512 * 2**20

    def __post_init__(self) -> None:
        if self.filter not in TEXTURE_FILTERS:
            raise ValueError(f"TextureSettings.filter: expected one of {TEXTURE_FILTERS}, got "
                             f"{self.filter!r}")
        try:
            check_max_anisotropy(self.max_anisotropy)
        except ValueError as e:
            raise ValueError(f"TextureSettings.{e}") from None
        if self.max_anisotropy != 16 and self.filter != "anisotropic":
            raise ValueError(f"TextureSettings.max_anisotropy: used by filter='anisotropic' "
                             f"only; filter is {self.filter!r}")
        check_int("TextureSettings.cache_bytes", self.cache_bytes, 0)


@dataclass(frozen=True, eq=False)
class BackgroundSettings:
    """What empty pixels show.

    Args:
        color: linear RGB of empty pixels (3 finite, non-negative floats).
        environment: show the environment map (when one is given) instead of ``color``.
        image: ``(B, 3, h, w)`` or ``(3, h, w)`` linear RGB behind the scene (replaces the
            colour and the environment), fitted to the frame by ``fit``; None = none.
        fit: ``"cover"``, ``"contain"`` or ``"stretch"`` (see
            :func:`~torchraster.background.fit_background`).
    """

    color: Sequence[float] = (0.0, 0.0, 0.0)
    environment: bool = True
    image: torch.Tensor | None = None
    fit: str = "cover"

    def __post_init__(self) -> None:
        try:
            rgb = torch.as_tensor(self.color, dtype=torch.float64, device="cpu").flatten()
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"BackgroundSettings.color: expected 3 floats (RGB), got "
                            f"{self.color!r}") from None
        if rgb.numel() != 3 or not bool(torch.isfinite(rgb).all()) or bool((rgb < 0).any()):
            raise ValueError(f"BackgroundSettings.color: expected 3 finite, non-negative "
                             f"floats (linear RGB), got {self.color!r}")
        object.__setattr__(self, "color", tuple(float(c) for c in rgb))
        check_bool("BackgroundSettings.environment", self.environment)
        if self.fit not in FITS:
            raise ValueError(f"BackgroundSettings.fit: expected one of {FITS}, got "
                             f"{self.fit!r}")
        image = self.image
        if image is not None:
            if isinstance(image, torch.Tensor) and image.dim() == 3:
                image = image[None]
            check_tensor("BackgroundSettings.image", image, ("B", 3, "h", "w"),
                         floating=True, finite=True)
            object.__setattr__(self, "image", image)


__all__ = ["LIT_MODELS", "MAX_ALPHA_LAYERS", "MAX_SUPERSAMPLE", "SETTINGS_BOUNDS", "SHADING",
           "TEXTURE_FILTERS", "BackgroundSettings", "RasterSettings", "ShadingSettings",
           "TextureSettings"]
