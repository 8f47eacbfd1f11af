"""Shading: BRDFs, shading models, lights and the deferred lighting pass.

Submodules: ``brdf`` (GGX, Smith, Schlick, Lambert, Cook-Torrance), ``models`` (shading
models by name), ``lights`` (batched lights), ``lighting`` (deferred pass), ``area`` and
``ltc`` (area lights by linearly transformed cosines).
"""

from torchraster.shading.brdf import (
    MIN_ROUGHNESS,
    cook_torrance,
    d_ggx,
    f_schlick,
    fd_lambert,
    v_smith_ggx_correlated,
)
from torchraster.shading.lighting import shade
from torchraster.shading.lights import (
    AreaLights,
    DirectionalLights,
    Lights,
    PointLights,
    SpotLights,
)
from torchraster.shading.models import MODELS, get_model
from torchraster.shading.surface import PixelSurface, Surface, pixel_surface

__all__ = [
    "MIN_ROUGHNESS",
    "MODELS",
    "AreaLights",
    "DirectionalLights",
    "Lights",
    "PixelSurface",
    "PointLights",
    "SpotLights",
    "Surface",
    "cook_torrance",
    "d_ggx",
    "f_schlick",
    "fd_lambert",
    "get_model",
    "pixel_surface",
    "shade",
    "v_smith_ggx_correlated",
]
