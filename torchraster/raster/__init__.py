"""Rasterization: clipping and culling, binning, visibility and interpolation."""

from .antialias import antialias, antialias_topology
from .interpolate import (
    Interpolated,
    interpolate,
    interpolate_packed,
    interpolate_with_derivatives,
    to_image,
)
from .rasterize import Fragments, rasterize, rasterize_coverage, rasterize_depth
from .soft import SoftFragments, soft_blend, soft_rasterize

__all__ = ["Fragments", "Interpolated", "antialias", "antialias_topology", "interpolate",
           "interpolate_packed", "interpolate_with_derivatives", "rasterize",
           "rasterize_coverage", "rasterize_depth", "SoftFragments", "soft_blend",
           "soft_rasterize", "to_image"]
