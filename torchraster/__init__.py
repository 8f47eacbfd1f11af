"""torchraster: a differentiable binning rasterizer and PBR renderer in batched PyTorch ops.

Public contract (see DESIGN.md): :func:`rasterize` and :func:`interpolate`. The rest:
cameras (:mod:`torchraster.camera`), meshes and files (:mod:`~torchraster.mesh`,
:mod:`~torchraster.io`), materials, textures, the deferred :class:`Renderer`, lights and
image-based lighting (:mod:`torchraster.shading`), post-processing
(:mod:`torchraster.post`) and YAML render configs (:func:`load_config`,
:func:`render_to_files`).
"""

from . import camera, post, shading
from .config import ConfigError, load_config, parse_config
from .io import MeshFileError, load_mesh, load_scene, load_spot
from .material import Material
from .mesh import Mesh, pack_meshes, vertex_normals
from .pipeline import render_config, render_to_files
from .raster import Fragments, interpolate, rasterize
from .renderer import Renderer, RenderOutput, RenderScene

__all__ = [
    "ConfigError", "Fragments", "Material", "Mesh", "MeshFileError", "RenderOutput",
    "RenderScene", "Renderer", "camera", "interpolate", "load_config", "load_mesh",
    "load_scene", "load_spot", "pack_meshes", "parse_config", "post", "rasterize",
    "render_config", "render_to_files", "shading", "vertex_normals",
]
__version__ = "0.1.0"
