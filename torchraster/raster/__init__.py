"""Rasterization: clipping and culling, binning, visibility and interpolation."""

from .interpolate import interpolate, interpolate_packed, to_image
from .rasterize import Fragments, rasterize, rasterize_depth

__all__ = ["Fragments", "interpolate", "interpolate_packed", "rasterize", "rasterize_depth",
           "to_image"]
