"""Rasterization: clipping and culling, binning, visibility and interpolation."""

from .interpolate import interpolate
from .rasterize import Fragments, rasterize

__all__ = ["Fragments", "interpolate", "rasterize"]
