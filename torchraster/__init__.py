"""torchraster: a differentiable binning rasterizer and PBR renderer in batched PyTorch ops.

The contract and the layers are described in ``docs/design.md``. In data-flow order:

* cameras: :mod:`torchraster.camera` (``look_at``, ``orbit``, ``perspective``, ...);
* geometry and files: :class:`Mesh`, :func:`load_mesh`, :func:`load_scene`,
  :class:`RenderScene`, :class:`Material`, :func:`read_hdr`;
* visibility: :func:`rasterize` -> :class:`Fragments`, :func:`interpolate`,
  :func:`interpolate_with_derivatives`;
* surfaces: :func:`geometry_pass` -> :class:`GBuffer`;
* light: :class:`Lights` (:class:`DirectionalLights`, :class:`PointLights`,
  :class:`SpotLights`, :class:`AreaLights` with :func:`area_light_axes`, ambient SH from
  :func:`sh_from_color`), :class:`Environment`,
  :func:`shade`;
* the whole frame: :class:`Renderer` -> :class:`RenderOutput` (settings:
  :class:`ShadingSettings`, :class:`RasterSettings`, :class:`TextureSettings`,
  :class:`BackgroundSettings`, :class:`ShadowSettings`; effects:
  :class:`Dissolve`, background images :func:`load_background` / :func:`fit_background`);
* post-processing: :mod:`torchraster.post`; YAML configs: :func:`load_config`,
  :func:`render_to_files`.
"""

from . import camera, post, shading
from .background import fit_background, load_background
from .config import ConfigError, lights_from_config, load_config, parse_config
from .dissolve import Dissolve
from .gbuffer import CHANNELS, GBuffer, geometry_pass
from .hdr_io import read_hdr
from .io import MeshFileError, Scene, load_mesh, load_scene, load_spot
from .material import Material
from .mesh import Mesh, pack_meshes, vertex_normals
from .pipeline import render_config, render_to_files
from .raster import Fragments, antialias, interpolate, interpolate_with_derivatives, rasterize
from .renderer import NotImplementedWarning, Renderer, RenderOutput, RenderPlan
from .scene import RenderScene
from .settings import BackgroundSettings, RasterSettings, ShadingSettings, TextureSettings
from .shading.ibl import Environment
from .shading.lighting import shade
from .shading.lights import (
    AreaLights,
    DirectionalLights,
    Lights,
    PointLights,
    SpotLights,
    area_light_axes,
    sh_from_color,
)
from .shading.shadows import ShadowSettings
from .shading.volumetric import Fog

__all__ = [
    "AreaLights", "BackgroundSettings", "CHANNELS", "ConfigError", "DirectionalLights",
    "Dissolve", "Environment", "Fog", "Fragments",
    "GBuffer", "Lights", "Material", "Mesh", "MeshFileError", "NotImplementedWarning",
    "PointLights", "RasterSettings", "RenderOutput", "RenderPlan", "RenderScene", "Renderer",
    "Scene", "ShadingSettings", "ShadowSettings", "SpotLights", "TextureSettings",
    "antialias", "area_light_axes", "camera", "fit_background", "geometry_pass", "interpolate",
    "interpolate_with_derivatives", "lights_from_config", "load_background", "load_config",
    "load_mesh", "load_scene", "load_spot", "pack_meshes", "parse_config", "post", "rasterize",
    "read_hdr", "render_config", "render_to_files", "sh_from_color", "shade", "shading",
    "vertex_normals",
]
__version__ = "0.1.0"
