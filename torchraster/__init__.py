"""torchraster: a differentiable binning rasterizer and PBR renderer in batched PyTorch ops."""

from . import camera
from .raster import Fragments, interpolate, rasterize

__all__ = ["Fragments", "camera", "interpolate", "rasterize"]
__version__ = "0.1.0"
