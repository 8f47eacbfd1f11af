"""YAML render configs: the schema, its validation and the builders of the objects it names.

The config layer is the only place that knows YAML. A config names a scene (mesh or glTF
file, relative to the config file), cameras, render settings, lights, an optional
environment map, material overrides, post-processing and outputs; the full reference is
``docs/config.md`` (``torchraster schema`` prints it). Unknown keys are errors, with a
"did you mean" suggestion. Every error names the file, the line and the key path, e.g.
``quickstart.yaml:7: cameras.0.fov_deg: Input should be less than 180``, and
:func:`check_config` finds every missing file and degenerate camera in one pass before
anything renders.

Defaults live in one place: the keyword defaults of the objects the config builds
(``Bloom(threshold=1.0)``, ``Renderer(supersample=1)``, ...) or the named constants of their
module (light defaults); the pydantic fields read them (:func:`default_of`) and the
builders pass keyword arguments.

Example (``configs/quickstart.yaml``)::

    scene:
      mesh: ../torchraster/assets/spot/spot_triangulated.obj
    cameras:
      - orbit: {azimuth_deg: 30, elevation_deg: 15}
    render:
      resolution: [512, 512]    # [H, W], or one int for a square image
"""

from __future__ import annotations

import difflib
import glob
import hashlib
import inspect
import math
import os
import random
import re
import typing
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import torch
import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    TypeAdapter,
    ValidationError,
    field_validator,
    model_validator,
)

from .anisotropic import MAX_TEXTURE_ANISOTROPY
from .background import FITS, load_background
from .dissolve import MAX_OCTAVES, Dissolve
from .post import (
    SSAO,
    SSR,
    AutoExposure,
    Bloom,
    DepthOfField,
    EncodeSRGB,
    Exposure,
    PostChain,
    ToneMap,
)
from .post.tonemap import CURVES
from .renderer import LIT_MODELS, SHADING, Renderer
from .shading.ibl import SPECULAR_MODES, Environment
from .shading.lights import (
    DEFAULT_COLOR,
    DEFAULT_DIRECTION,
    DEFAULT_INNER_CONE_ANGLE,
    DEFAULT_INTENSITY,
    DEFAULT_OUTER_CONE_ANGLE,
    SH_C0,
    DirectionalLights,
    Lights,
    PointLights,
    SpotLights,
)
from .shading.models import model_options
from .shading.shadows import FILTERS, PATTERNS, ShadowSettings
from .shading.volumetric import MAX_ANISOTROPY, MAX_DENSITY, Fog

#: YAML nodes a config may expand to (aliases expanded): far above any real config, far
#: below what a "billion laughs" document would make us allocate.
MAX_YAML_NODES: int = 100_000
#: Largest supersampled image side (``render.supersample * max(resolution)``).
MAX_SUPERSAMPLED_SIDE: int = 16384
#: Largest image side of ``render.resolution``.
MAX_RESOLUTION: int = 16384
MAX_SSAO_SAMPLES: int = 1024
MAX_SSR_STEPS: int = 4096
MAX_DOF_LEVELS: int = 64
MAX_BLOOM_LEVELS: int = 16
#: Most views one ``random_orbits`` camera entry may expand to (per object).
MAX_RANDOM_VIEWS: int = 100_000


def default_of(obj: Any, name: str) -> Any:
    """The default of keyword argument ``name`` of ``obj`` (a class: its ``__init__``)."""
    target = obj.__init__ if inspect.isclass(obj) else obj
    default = inspect.signature(target).parameters[name].default
    if default is inspect.Parameter.empty:
        raise TypeError(f"{obj.__name__}({name}=...) has no default")
    return default


Finite = Annotated[float, Field(allow_inf_nan=False)]
NonNeg = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Vec3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]
Color3 = Annotated[list[NonNeg], Field(min_length=3, max_length=3)]


class ConfigError(ValueError):
    """A render config is invalid; the message names the file, line and key path."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class TransformConfig(_Strict):
    """Model -> world transform: scale, then rotation (XYZ Euler degrees), then translation."""

    translate: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    rotate_deg: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    scale: Positive | Annotated[list[Positive], Field(min_length=3, max_length=3)] = 1.0


Primitive = Literal["plane", "box", "sphere"]


class ObjectMaterialConfig(_Strict):
    """The material of a scene object (glTF metallic-roughness factors)."""

    name: str | None = Field(None, description="material name (matched by `materials:` "
                             "overrides); default: `object:<object name>`")
    base_color: Annotated[list[Annotated[float, Field(ge=0, le=1)]],
                          Field(min_length=3, max_length=4)] = Field(
        default_factory=lambda: [0.8, 0.8, 0.8])
    metallic: Annotated[float, Field(ge=0, le=1)] = 0.0
    roughness: Annotated[float, Field(ge=0, le=1)] = 0.8
    emissive: Color3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    base_color_texture: str | None = Field(
        None, description="image file (sRGB, alpha used by MASK / BLEND), relative to the "
        "config file; primitives' UVs span [0, 1] over each face")
    alpha_mode: Literal["OPAQUE", "MASK", "BLEND"] = Field(
        "OPAQUE", description="glTF alphaMode: MASK cuts out where alpha < alpha_cutoff (the "
        "surface behind shows), BLEND composites front to back (render.alpha_layers deep)")
    alpha_cutoff: Annotated[float, Field(ge=0, le=1)] = 0.5

    @model_validator(mode="after")
    def _cutoff_needs_mask(self) -> ObjectMaterialConfig:
        if "alpha_cutoff" in self.model_fields_set and self.alpha_mode != "MASK":
            raise ValueError("alpha_cutoff is used by alpha_mode MASK only")
        return self


class ObjectConfig(_Strict):
    """One more object of the scene: a mesh file or a primitive built here (a ground plane
    under a model, a box, a sphere), with its own transform and shadow flags."""

    name: str | None = None
    mesh: str | None = Field(None, description="mesh / glTF file, relative to the config file")
    primitive: Primitive | None = Field(
        None, description="plane: `size` x `size` in XZ facing +Y, centred at the origin; box: "
        "a cube of side `size`; sphere: diameter `size` (an icosphere)")
    size: Positive = 1.0
    transform: TransformConfig = Field(default_factory=TransformConfig)
    material: ObjectMaterialConfig | None = Field(
        None, description="for primitives (default: light grey, rough dielectric); a mesh "
        "file keeps its own materials")
    cast_shadows: bool = True
    receive_shadows: bool = True

    @model_validator(mode="after")
    def _one_source(self) -> ObjectConfig:
        if (self.mesh is None) == (self.primitive is None):
            raise ValueError("give exactly one of 'mesh' (a file) or 'primitive' "
                             "(plane, box, sphere)")
        if self.mesh is not None and self.material is not None:
            raise ValueError("'material' is for primitives; a mesh file keeps its own "
                             "materials (use the top-level 'materials:' overrides)")
        return self


class SceneConfig(_Strict):
    """The geometry: a mesh or glTF scene file, relative to the config file, and optional
    further ``objects`` (e.g. a ground plane).

    A *mesh set* renders many objects with one config, one at a time (each with the
    ``objects``, lights and cameras of the config): ``mesh`` as a glob pattern
    (``objects/*.glb``, ``**`` recurses; sorted) or ``meshes_from``, a list file. Each
    object is named after its file (sanitised; the path is added where two stems clash)
    and written to ``<out>/<config>/<object>/<camera>/``."""

    mesh: str | None = Field(None, description="the main mesh / glTF scene (optional when "
                             "`objects` is given), or a glob pattern naming a mesh set")
    meshes_from: str | None = Field(
        None, description="a mesh set listed in a text file: one mesh path per line, "
        "relative to the list file; blank lines and `#` comments skipped")
    transform: TransformConfig = Field(default_factory=TransformConfig)
    normals: Literal["auto", "smooth", "flat"] = Field(
        "auto", description="auto: the file's normals (smooth if it has none); smooth: "
        "computed vertex normals; flat: one normal per face")
    max_texture_size: Annotated[int, Field(ge=1)] | None = Field(
        2048, description="textures are downscaled so the longer side is at most this")
    allow_missing_textures: bool = Field(
        False, description="render a mesh whose texture files are missing without them "
        "(with a warning) instead of failing")
    cast_shadows: bool = Field(True, description="the main mesh is drawn into shadow maps")
    receive_shadows: bool = Field(True, description="the main mesh is darkened by shadows")
    objects: list[ObjectConfig] = Field(default_factory=list)

    @model_validator(mode="after")
    def _something(self) -> SceneConfig:
        if self.mesh is not None and self.meshes_from is not None:
            raise ValueError("give either 'mesh' or 'meshes_from' (a list of meshes), not "
                             "both")
        if self.mesh is None and self.meshes_from is None and not self.objects:
            raise ValueError("give 'mesh' (a file) or at least one entry in 'objects'")
        return self


class OrbitConfig(_Strict):
    """Camera on a sphere around ``target`` (default: the scene's centre); ``distance``
    None frames the scene's bounding sphere."""

    azimuth_deg: Finite = 0.0
    elevation_deg: Annotated[float, Field(gt=-90, lt=90)] = 0.0
    distance: Positive | None = None
    target: Vec3 | None = None


class LookAtConfig(_Strict):
    """Camera at ``eye`` looking at ``target`` with ``up`` roughly up."""

    eye: Vec3
    target: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    up: Vec3 = Field(default_factory=lambda: [0.0, 1.0, 0.0])


Range = Annotated[list[Finite], Field(min_length=2, max_length=2)]
ElevationRange = Annotated[list[Annotated[float, Field(gt=-90, lt=90)]],
                           Field(min_length=2, max_length=2)]


class RandomOrbitsConfig(_Strict):
    """``count`` cameras on random orbits, drawn anew for every object of the scene: view
    ``j`` of an object draws from the seed of (``seed``, the object's name, the view's name),
    so each object gets its own views, the same on every run and every rank, and adding
    objects to a set changes no other object's views. Directions are uniform on the sphere
    band between the two elevations (within the azimuth range); views are named
    ``<name>_000``, ``<name>_001``, ... (``name`` default ``view<index>``). A dataset of
    24 views of every ``.glb`` file under ``objects/``, in one command (``torchraster render
    dataset.yaml --out DIR``, or under ``torchrun``)::

        scene:
          mesh: objects/**/*.glb          # or meshes_from: objects.txt
        cameras:
          - random_orbits: {count: 24, seed: 0, elevation_deg: [0, 45]}
        render:
          resolution: 128
        outputs:
          channels: [color, alpha, depth, normal]"""

    count: Annotated[int, Field(ge=1, le=MAX_RANDOM_VIEWS)] = Field(
        description="views per object")
    seed: Annotated[int, Field(ge=0)] = Field(0, description="change it for other views")
    azimuth_deg: Range = Field(default_factory=lambda: [0.0, 360.0],
                               description="[min, max] degrees")
    elevation_deg: ElevationRange = Field(default_factory=lambda: [-20.0, 60.0],
                                          description="[min, max] degrees")
    distance: Positive | Annotated[list[Positive], Field(min_length=2, max_length=2)] | None = (
        Field(None, description="a distance or a [min, max] range; null frames the scene's "
              "bounding sphere (as `orbit`)"))
    target: Vec3 | None = Field(None, description="default: the scene's centre")

    @field_validator("azimuth_deg", "elevation_deg", "distance")
    @classmethod
    def _ordered(cls, value: Any) -> Any:
        if isinstance(value, list) and value[0] > value[1]:
            raise ValueError(f"expected [min, max], got {value}")
        return value

    def draw(self, seed: int) -> OrbitConfig:
        """The orbit of the view whose seed is ``seed`` (see :func:`stable_seed`)."""
        rng = random.Random(seed)
        lo, hi = self.azimuth_deg
        azimuth = lo + (hi - lo) * rng.random()
        s0, s1 = (math.sin(math.radians(e)) for e in self.elevation_deg)
        elevation = math.degrees(math.asin(s0 + (s1 - s0) * rng.random()))
        distance = self.distance
        if isinstance(distance, list):
            distance = distance[0] + (distance[1] - distance[0]) * rng.random()
        return OrbitConfig(azimuth_deg=azimuth, elevation_deg=elevation, distance=distance,
                           target=self.target)


class IntrinsicsConfig(_Strict):
    """Pinhole intrinsics in pixels (OpenCV convention), for the render resolution."""

    fx: Positive
    fy: Positive
    cx: Finite
    cy: Finite


class CameraConfig(_Strict):
    """One view, or with ``random_orbits`` a set of views. At most one of ``orbit`` /
    ``look_at`` / ``random_orbits`` places it (default: orbit)."""

    name: str | None = Field(None, description="output sub-folder (sanitised to letters, "
                             "digits, '.', '_', '-'); default view<index>")
    projection: Literal["perspective", "orthographic"] = "perspective"
    fov_deg: Annotated[float, Field(gt=0, lt=180)] = 45.0
    intrinsics: IntrinsicsConfig | None = None
    ortho_height: Positive | None = None
    near: Positive | None = None
    far: Positive | None = None
    reverse_z: bool = False
    orbit: OrbitConfig | None = None
    look_at: LookAtConfig | None = None
    random_orbits: RandomOrbitsConfig | None = None

    @model_validator(mode="after")
    def _one_placement(self) -> CameraConfig:
        given = [k for k in ("orbit", "look_at", "random_orbits") if getattr(self, k) is not None]
        if len(given) > 1:
            raise ValueError(f"give one of 'orbit', 'look_at' or 'random_orbits', not "
                             f"{' and '.join(repr(k) for k in given)}")
        if not given:
            self.orbit = OrbitConfig()
        if self.near is not None and self.far is not None and self.far <= self.near:
            raise ValueError(f"far ({self.far}) must be greater than near ({self.near})")
        return self


class ToonConfig(_Strict):
    """Options of ``shading: toon`` (:func:`torchraster.shading.models.toon`)."""

    bands: Annotated[int, Field(ge=1, le=64)] = Field(
        model_options("toon")["bands"], description="diffuse levels above black")
    rim: NonNeg = Field(model_options("toon")["rim"], description="rim light brightness "
                        "(relative to a fully lit white surface; 0 = no rim)")
    rim_width: Annotated[float, Field(ge=0, le=1)] = Field(
        model_options("toon")["rim_width"], description="the rim covers n.v < rim_width "
        "(silhouette side, lit side only)")


class BackgroundImageConfig(_Strict):
    """An image behind the scene (:mod:`torchraster.background`): PNG / JPEG / ... (sRGB,
    decoded to linear) or ``.hdr`` / ``.exr`` (linear), relative to the config file."""

    path: str = Field(description="the image file")
    fit: Literal[FITS] = Field(  # type: ignore[valid-type]
        default_of(Renderer, "background_fit"), description="cover: fill the frame, crop "
        "the overflow; contain: fit inside, bars in `render.background`; stretch: fill, "
        "aspect not kept")


class FogConfig(_Strict):
    """Exponential height fog lit by the lights, with light shafts from the lights that cast
    shadows (see ``torchraster.shading.volumetric``)."""

    enabled: bool = True
    density: Annotated[float, Field(ge=0, le=MAX_DENSITY)] = Field(
        default_of(Fog, "density"), description="extinction (1/m) at base_height")
    height_falloff: NonNeg = Field(default_of(Fog, "height_falloff"),
                                   description="1/m: density * exp(-falloff (y - base_height));"
                                   " 0 = homogeneous")
    base_height: Finite = Field(default_of(Fog, "base_height"), description="world y (m)")
    color: Annotated[list[Annotated[float, Field(ge=0, le=1)]],
                     Field(min_length=3, max_length=3)] = Field(
        default_factory=lambda: list(default_of(Fog, "color")),
        description="scattering albedo (RGB tint of the fog)")
    ambient: Color3 = Field(default_factory=lambda: list(default_of(Fog, "ambient")),
                            description="extra isotropic radiance in-scattered (RGB)")
    anisotropy: Annotated[float, Field(ge=-MAX_ANISOTROPY, le=MAX_ANISOTROPY)] = Field(
        default_of(Fog, "anisotropy"), description="Henyey-Greenstein g: > 0 forward "
        "scattering (halo towards lights)")
    steps: Annotated[int, Field(ge=1, le=1024)] = Field(
        default_of(Fog, "steps"), description="march steps (point / spot / shadowed lights)")
    jitter: bool = Field(default_of(Fog, "jitter"), description="per-pixel jittered march")
    blur: Annotated[float, Field(ge=0, le=16)] = Field(
        default_of(Fog, "blur"), description="depth-aware blur of the marched light (px)")
    max_distance: Positive | None = Field(
        None, description="distance (m) of the background; null = infinitely far")
    seed: Annotated[int, Field(ge=0)] = Field(default_of(Fog, "seed"),
                                              description="offset of the jitter pattern")

    def fog(self) -> Fog | None:
        """The :class:`~torchraster.shading.volumetric.Fog` of this block (None if disabled)."""
        if not self.enabled:
            return None
        d = self.model_dump(exclude={"enabled", "max_distance"})
        return Fog(**{**d, "color": tuple(d["color"]), "ambient": tuple(d["ambient"])},
                   max_distance=math.inf if self.max_distance is None else self.max_distance)


class DissolveConfig(_Strict):
    """The dissolve effect (:mod:`torchraster.dissolve`): surfaces are cut away where a seeded
    world-space noise falls below ``threshold``, with a glowing band above it."""

    threshold: Annotated[float, Field(ge=0, le=1)] = Field(
        default_of(Dissolve, "threshold"), description="0 keeps everything, 1 dissolves "
        "everything; about the fraction of the surface dissolved")
    edge_width: NonNeg = Field(default_of(Dissolve, "edge_width"),
                               description="width of the glowing band (noise units)")
    edge_color: Color3 = Field(default_factory=lambda: list(default_of(Dissolve, "edge_color")),
                               description="linear RGB of the glow")
    edge_intensity: NonNeg = Field(default_of(Dissolve, "edge_intensity"),
                                   description="multiplies edge_color (radiance)")
    scale: Positive = Field(default_of(Dissolve, "scale"),
                            description="noise cells per world unit")
    octaves: Annotated[int, Field(ge=1, le=MAX_OCTAVES)] = default_of(Dissolve, "octaves")
    seed: Annotated[int, Field(ge=0, lt=2**63)] = Field(default_of(Dissolve, "seed"),
                                                        description="the noise pattern")

    def build(self) -> Dissolve:
        """The :class:`~torchraster.dissolve.Dissolve` of this block."""
        return Dissolve(**{**self.model_dump(), "edge_color": tuple(self.edge_color)})


class RenderConfig(_Strict):
    """Image size and shading (``resolution``: ``[H, W]`` or one int for a square)."""

    resolution: Annotated[int, Field(ge=1, le=MAX_RESOLUTION)] | Annotated[
        list[Annotated[int, Field(ge=1, le=MAX_RESOLUTION)]], Field(min_length=2, max_length=2)
    ] = Field(512, description="[H, W] in pixels, or one int for a square image")
    shading: Literal[SHADING] | None = Field(  # type: ignore[valid-type]
        None, description="default: pbr when the config has lights or an environment, else "
        "headlight. pbr (Cook-Torrance) and the stylised blinn_phong, half_lambert and toon "
        "need lights or an environment; headlight is Lambert lit from the camera; unlit is "
        "albedo + emissive (both ignore lights, so they refuse them)")
    toon: ToonConfig | None = Field(None, description="options of shading: toon (bands, "
                                    "rim light); refused with other shading models")
    background: Color3 = Field(
        default_factory=lambda: list(default_of(Renderer, "background")),
        description="linear RGB of empty pixels (the environment replaces it when shown)")
    background_image: BackgroundImageConfig | None = Field(
        None, description="an image behind the scene, fitted to the frame (replaces the "
        "colour and the environment as background)")
    dissolve: DissolveConfig | None = Field(
        None, description="the dissolve effect on every surface (cut-outs, alpha_layers "
        "deep, with a glowing edge)")
    supersample: Annotated[int, Field(ge=1, le=8)] = Field(
        default_of(Renderer, "supersample"),
        description="render at s x the resolution and box-filter down")
    cull_backfaces: bool = Field(default_of(Renderer, "cull_backfaces"),
                                 description="drop back faces of every material")
    texture_filter: Literal["trilinear", "anisotropic", "bilinear", "nearest"] = Field(
        default_of(Renderer, "texture_filter"), description="anisotropic: up to "
        "max_anisotropy trilinear probes along each pixel's footprint (sharper on steep "
        "surfaces, slower)")
    max_anisotropy: Annotated[int, Field(ge=1, le=MAX_TEXTURE_ANISOTROPY)] = Field(
        default_of(Renderer, "max_anisotropy"), description="the most probes a pixel of "
        "texture_filter: anisotropic (refused with the other filters)")
    alpha_layers: Annotated[int, Field(ge=1, le=16)] = Field(
        default_of(Renderer, "alpha_layers"), description="depth layers for MASK / BLEND "
        "materials (what lies behind the nearest K is not seen through them)")
    antialias: bool = Field(default_of(Renderer, "antialias"), description="analytic "
                            "antialiasing of silhouettes (gradients at edges)")
    fog: FogConfig | None = Field(None, description="volumetric height fog and light shafts")
    multiscatter: bool = Field(default_of(Renderer, "multiscatter"), description="pbr: "
                               "multiple-scattering energy compensation of the specular and "
                               "the diffuse reduced by the specular albedo, for every light")

    @model_validator(mode="after")
    def _toon_options(self) -> RenderConfig:
        if self.toon is not None and self.shading not in (None, "toon"):
            raise ValueError(f"toon: options of shading: toon; shading is {self.shading!r}")
        return self

    @model_validator(mode="after")
    def _multiscatter_needs_pbr(self) -> RenderConfig:
        if "multiscatter" in self.model_fields_set and self.shading not in (None, "pbr"):
            raise ValueError(f"multiscatter: energy terms of shading: pbr only; shading is "
                             f"{self.shading!r}")
        return self

    @model_validator(mode="after")
    def _anisotropy_needs_filter(self) -> RenderConfig:
        if "max_anisotropy" in self.model_fields_set and self.texture_filter != "anisotropic":
            raise ValueError(f"max_anisotropy: used by texture_filter anisotropic only; "
                             f"texture_filter is {self.texture_filter!r}")
        return self

    @model_validator(mode="after")
    def _bounded(self) -> RenderConfig:
        side = max(self.size) * self.supersample
        if side > MAX_SUPERSAMPLED_SIDE:
            raise ValueError(f"supersample x resolution = {side} pixels a side exceeds "
                             f"{MAX_SUPERSAMPLED_SIDE}; lower supersample or resolution")
        return self

    @property
    def size(self) -> tuple[int, int]:
        r = self.resolution
        return (r, r) if isinstance(r, int) else (r[0], r[1])


class EnvironmentConfig(_Strict):
    """An equirectangular HDR environment (``.hdr`` / ``.exr``), relative to the config."""

    path: str
    intensity: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 1.0
    rotation_deg: Finite = 0.0
    background: bool = True
    specular: Literal[SPECULAR_MODES] = Field(  # type: ignore[valid-type]
        default_of(Environment, "specular"), description="split_sum (prefiltered, fast) or "
        "importance (per-pixel filtered importance sampling of the GGX lobe)")
    importance_samples: Annotated[int, Field(ge=1, le=1024)] = Field(
        default_of(Environment, "importance_samples"),
        description="samples a pixel for specular: importance")


def _shadow_default(name: str) -> Any:
    return default_of(ShadowSettings, name)


#: Shadow fields that only some filters read.
_FILTER_USES = {
    "hard": set(),
    "pcf": {"pcf_radius", "pcf_taps", "pcf_pattern"},
    "pcss": {"pcf_taps", "pcf_pattern", "light_size", "max_penumbra"},
    "vsm": {"vsm_blur", "vsm_bleed", "vsm_min_variance"},
}
_FILTER_FIELDS = set().union(*_FILTER_USES.values())


def _users_of(name: str) -> str:
    return ", ".join(f for f, uses in _FILTER_USES.items() if name in uses)


class ShadowConfig(_Strict):
    """Shadow maps of one light (``enabled: true`` is what ``cast_shadows: true`` means).
    Sizes and biases are in shadow-map texels; see docs/design.md, "Shadows"."""

    enabled: bool = True
    map_size: Annotated[int, Field(ge=8, le=8192)] = _shadow_default("map_size")
    filter: Literal[FILTERS] = Field(  # type: ignore[valid-type]
        _shadow_default("filter"), description="hard (1 tap), pcf, pcss (contact-hardening "
        "penumbra from light_size) or vsm (variance shadow maps)")
    pcf_radius: Annotated[float, Field(ge=0, le=64)] = _shadow_default("pcf_radius")
    pcf_taps: Annotated[int, Field(ge=1, le=256)] = _shadow_default("pcf_taps")
    pcf_pattern: Literal[PATTERNS] = _shadow_default("pcf_pattern")  # type: ignore[valid-type]
    bias: Annotated[float, Field(ge=0, le=1000)] = Field(
        _shadow_default("bias"), description="constant depth bias (texels)")
    slope_bias: Annotated[float, Field(ge=0, le=1000)] = Field(
        _shadow_default("slope_bias"), description="slope-scaled depth bias (texels)")
    normal_bias: Annotated[float, Field(ge=0, le=1000)] = Field(
        _shadow_default("normal_bias"), description="normal offset of receivers (texels)")
    intensity: Annotated[float, Field(ge=0, le=1)] = Field(
        _shadow_default("intensity"), description="0 = no darkening, 1 = full")
    cascades: Annotated[int, Field(ge=1, le=4)] = Field(
        _shadow_default("cascades"), description="cascaded maps (directional lights only)")
    split_lambda: Annotated[float, Field(ge=0, le=1)] = _shadow_default("split_lambda")
    cascade_blend: Annotated[float, Field(ge=0, le=0.5)] = _shadow_default("cascade_blend")
    max_distance: Positive | None = Field(
        _shadow_default("max_distance"), description="directional: cascades end at this "
        "camera depth (m); default the farthest scene point")
    light_size: Annotated[float, Field(ge=0, le=1e6)] = Field(
        _shadow_default("light_size"), description="pcss: radius (m) of point / spot lights, "
        "angular diameter (degrees) of directional lights")
    max_penumbra: Annotated[float, Field(ge=0.5, le=64)] = _shadow_default("max_penumbra")
    vsm_blur: Annotated[float, Field(ge=0, le=64)] = _shadow_default("vsm_blur")
    vsm_bleed: Annotated[float, Field(ge=0, le=0.99)] = _shadow_default("vsm_bleed")
    vsm_min_variance: Annotated[float, Field(ge=0, le=1)] = _shadow_default("vsm_min_variance")

    @model_validator(mode="after")
    def _used_by_filter(self) -> ShadowConfig:
        unused = sorted(self.model_fields_set & (_FILTER_FIELDS - _FILTER_USES[self.filter]))
        if unused:
            raise ValueError(f"{', '.join(unused)}: not used by filter {self.filter!r} (used "
                             f"by: {_users_of(unused[0])}); remove it or change the filter")
        return self

    def settings(self) -> ShadowSettings:
        """The :class:`~torchraster.shading.shadows.ShadowSettings` of this block."""
        return ShadowSettings(**self.model_dump(exclude={"enabled"}))


class _LightConfigBase(_Strict):
    name: str | None = None
    color: Color3 = Field(default_factory=lambda: list(DEFAULT_COLOR))
    intensity: NonNeg = DEFAULT_INTENSITY


class _DirectionMixin(BaseModel):
    @field_validator("direction", check_fields=False)
    @classmethod
    def check_direction(cls, v: list[float]) -> list[float]:
        if sum(x * x for x in v) <= 0.0:
            raise ValueError("direction must not be the zero vector")
        return v


class AmbientLightConfig(_LightConfigBase):
    """Constant ambient radiance ``color * intensity`` (nits), or ``sh``: 9 RGB SH
    coefficients of the incident radiance (scaled by ``intensity``, ``color`` ignored)."""

    type: Literal["ambient"]
    sh: Annotated[list[Vec3], Field(min_length=9, max_length=9)] | None = None


def _check_shadow_switch(light: Any) -> Any:
    if light.cast_shadows is not None and light.shadows is not None and (
            light.cast_shadows != light.shadows.enabled):
        raise ValueError(f"cast_shadows: {str(light.cast_shadows).lower()} contradicts "
                         f"shadows.enabled: {str(light.shadows.enabled).lower()}; give one")
    return light


def _casts(light: Any) -> bool:
    if light.shadows is not None:
        return light.shadows.enabled
    return bool(light.cast_shadows)


def _shadow_settings(light: Any) -> ShadowSettings | None:
    return light.shadows.settings() if light.shadows is not None else None


class DirectionalLightConfig(_DirectionMixin, _LightConfigBase):
    """Directional light: ``direction`` the light travels (default -Z, glTF), lux."""

    type: Literal["directional"]
    direction: Vec3 = Field(default_factory=lambda: list(DEFAULT_DIRECTION))
    cast_shadows: bool | None = Field(None, description="true: shadows with default settings "
                                      "(same as `shadows: {}`)")
    shadows: ShadowConfig | None = None

    @model_validator(mode="after")
    def _shadow_switch(self) -> DirectionalLightConfig:
        return _check_shadow_switch(self)


class PointLightConfig(_LightConfigBase):
    """Point light at ``position``; ``intensity`` in candela, optional ``range`` (m)."""

    type: Literal["point"]
    position: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    range: Annotated[float, Field(gt=0.0)] | None = None
    cast_shadows: bool | None = Field(None, description="true: shadows with default settings "
                                      "(same as `shadows: {}`)")
    shadows: ShadowConfig | None = None

    @model_validator(mode="after")
    def _shadow_switch(self) -> PointLightConfig:
        cascade_keys = {"cascades", "max_distance", "split_lambda", "cascade_blend"}
        if self.shadows is not None and self.shadows.model_fields_set & cascade_keys:
            raise ValueError(f"shadows.{sorted(self.shadows.model_fields_set & cascade_keys)[0]}:"
                             " cascades are for directional lights only")
        return _check_shadow_switch(self)


class SpotLightConfig(_DirectionMixin, PointLightConfig):
    """Spot light: a point light limited to a cone around ``direction`` (default -Z)."""

    type: Literal["spot"]  # type: ignore[assignment]
    direction: Vec3 = Field(default_factory=lambda: list(DEFAULT_DIRECTION))
    inner_cone_angle: Annotated[float, Field(ge=0.0, le=math.pi / 2)] = DEFAULT_INNER_CONE_ANGLE
    outer_cone_angle: Annotated[float, Field(gt=0.0, le=math.pi / 2)] = DEFAULT_OUTER_CONE_ANGLE

    @model_validator(mode="after")
    def _cones(self) -> SpotLightConfig:
        if self.inner_cone_angle >= self.outer_cone_angle:
            raise ValueError(
                f"inner_cone_angle ({self.inner_cone_angle}) must be < outer_cone_angle "
                f"({self.outer_cone_angle}) (radians)"
            )
        return self


LightConfig = Annotated[
    AmbientLightConfig | DirectionalLightConfig | PointLightConfig | SpotLightConfig,
    Field(discriminator="type"),
]
_LIGHT_LIST = TypeAdapter(list[LightConfig])


class DOFConfig(_Strict):
    """Thin-lens depth of field (needs linear depth)."""

    enabled: bool = False
    focus_distance: Positive = Field(default_of(DepthOfField, "focus_distance"),
                                     description="metres")
    focal_length_mm: Positive = default_of(DepthOfField, "focal_length_mm")
    f_number: Positive = default_of(DepthOfField, "f_number")
    sensor_width_mm: Positive = default_of(DepthOfField, "sensor_width_mm")
    max_coc: Positive = Field(default_of(DepthOfField, "max_coc"),
                              description="largest CoC diameter, pixels")
    levels: Annotated[int, Field(ge=2, le=MAX_DOF_LEVELS)] = Field(
        default_of(DepthOfField, "levels"), description="blur levels blended per pixel")


class BloomConfig(_Strict):
    """HDR bloom (bright pass + 13-tap pyramid)."""

    enabled: bool = False
    threshold: NonNeg = default_of(Bloom, "threshold")
    knee: NonNeg = default_of(Bloom, "knee")
    intensity: NonNeg = default_of(Bloom, "intensity")
    radius: NonNeg = Field(default_of(Bloom, "radius"),
                           description="Gaussian sigma per level, level pixels")
    levels: Annotated[int, Field(ge=1, le=MAX_BLOOM_LEVELS)] = default_of(Bloom, "levels")
    karis: bool = default_of(Bloom, "karis")


class ExposureConfig(_Strict):
    """Manual exposure in EV (also the compensation when auto-exposure is on)."""

    enabled: bool = True
    ev: Finite = default_of(Exposure, "ev")


class AutoExposureConfig(_Strict):
    """Metered exposure with temporal adaptation (replaces manual exposure when enabled)."""

    enabled: bool = False
    key: Positive = default_of(AutoExposure, "key")
    min_ev: Finite = default_of(AutoExposure, "min_ev")
    max_ev: Finite = default_of(AutoExposure, "max_ev")
    metering: Literal["average", "percentile"] = default_of(AutoExposure, "metering")
    percentile_low: Annotated[float, Field(ge=0, le=1)] = default_of(AutoExposure,
                                                                     "percentile_low")
    percentile_high: Annotated[float, Field(ge=0, le=1)] = default_of(AutoExposure,
                                                                      "percentile_high")
    rate: NonNeg = Field(default_of(AutoExposure, "rate"), description="adaptation speed, 1/s")

    @model_validator(mode="after")
    def _ordered(self) -> AutoExposureConfig:
        if self.min_ev > self.max_ev:
            raise ValueError("min_ev must be <= max_ev")
        if self.percentile_low >= self.percentile_high:
            raise ValueError("percentile_low must be < percentile_high")
        return self


class ToneMapConfig(_Strict):
    """Tone curve (see ``torchraster.post.tonemap``)."""

    enabled: bool = True
    curve: Literal[CURVES] = default_of(ToneMap, "curve")  # type: ignore[valid-type]
    white: Positive = Field(default_of(ToneMap, "white"),
                            description="white point of reinhard_extended")


class EncodeConfig(_Strict):
    """Output encoding (linear -> sRGB transfer function)."""

    enabled: bool = True


class SSAOConfig(_Strict):
    """Screen-space ambient occlusion (feeds the lighting pass, pbr shading only)."""

    enabled: bool = False
    radius: Positive = Field(default_of(SSAO, "radius"), description="scene units")
    samples: Annotated[int, Field(ge=1, le=MAX_SSAO_SAMPLES)] = default_of(SSAO, "samples")
    bias: NonNeg = default_of(SSAO, "bias")
    softness: Positive = default_of(SSAO, "softness")
    blur: bool = default_of(SSAO, "blur")


class SSRConfig(_Strict):
    """Screen-space reflections (replace the environment's specular where the mirror rays
    hit; pbr shading only; see ``torchraster.post.ssr``)."""

    enabled: bool = False
    max_steps: Annotated[int, Field(ge=1, le=MAX_SSR_STEPS)] = default_of(SSR, "max_steps")
    thickness: Positive = Field(default_of(SSR, "thickness"), description="scene units")
    max_roughness: Annotated[float, Field(gt=0, le=1)] = default_of(SSR, "max_roughness")
    edge_fade: Annotated[float, Field(ge=0, le=0.5)] = Field(
        default_of(SSR, "edge_fade"), description="fraction of min(H, W)")
    refine_steps: Annotated[int, Field(ge=0, le=32)] = default_of(SSR, "refine_steps")
    max_distance: Annotated[float, Field(gt=0)] = Field(
        default_of(SSR, "max_distance"), description="scene units (.inf: no limit)")
    blur: bool = default_of(SSR, "blur")


class PostConfig(_Strict):
    """The ``post:`` section of a render config."""

    dof: DOFConfig = Field(default_factory=DOFConfig)
    bloom: BloomConfig = Field(default_factory=BloomConfig)
    exposure: ExposureConfig = Field(default_factory=ExposureConfig)
    auto_exposure: AutoExposureConfig = Field(default_factory=AutoExposureConfig)
    tonemap: ToneMapConfig = Field(default_factory=ToneMapConfig)
    encode: EncodeConfig = Field(default_factory=EncodeConfig)
    ssao: SSAOConfig = Field(default_factory=SSAOConfig)
    ssr: SSRConfig = Field(default_factory=SSRConfig)


class MaterialOverride(_Strict):
    """Overrides for the materials whose name matches ``match`` ('*' = all)."""

    match: str = "*"
    base_color: Annotated[list[Annotated[float, Field(ge=0, le=1)]],
                          Field(min_length=3, max_length=4)] | None = None
    metallic: Annotated[float, Field(ge=0, le=1)] | None = None
    roughness: Annotated[float, Field(ge=0, le=1)] | None = None
    emissive: Color3 | None = None
    base_color_texture: str | None = None  # image file (sRGB), relative to the config


Channel = Literal["color", "radiance", "alpha", "depth", "position", "normal", "albedo", "metallic",
                  "roughness", "ao", "emissive", "face_id", "uv"]


class OutputConfig(_Strict):
    """What to write: channels and file formats (exr needs the optional OpenEXR package).

    ``color`` is the display image (post chain applied, tone mapped, sRGB encoded, in [0, 1]);
    ``radiance`` is linear HDR (post chain up to, not including, tone mapping). Float
    formats (npy, exr) hold the raw values; png a display encoding (see the README table).
    """

    channels: list[Channel] = Field(default_factory=lambda: ["color", "depth", "normal"])
    formats: list[Literal["png", "npy", "exr"]] = Field(default_factory=lambda: ["png"])


class RenderFile(_Strict):
    """A whole render config file."""

    scene: SceneConfig
    cameras: Annotated[list[CameraConfig], Field(min_length=1)] = Field(
        default_factory=lambda: [CameraConfig()])
    render: RenderConfig = Field(default_factory=RenderConfig)
    lights: list[LightConfig] = Field(default_factory=list)  # type: ignore[valid-type]
    environment: EnvironmentConfig | None = None
    materials: list[MaterialOverride] = Field(default_factory=list)
    post: PostConfig | None = None
    outputs: OutputConfig = Field(default_factory=OutputConfig)

    # Set by parse_config: the folder relative paths are resolved against, the source name
    # and the line of every key path (for errors found after validation). Private, so a
    # `base_dir:` key in a file is an unknown key, not silently overwritten.
    _base_dir: Path = PrivateAttr(default=Path("."))
    _source: str = PrivateAttr(default="<config>")
    _lines: dict = PrivateAttr(default_factory=dict)

    @property
    def base_dir(self) -> Path:
        """The folder relative paths resolve against (the config file's folder)."""
        return self._base_dir

    @base_dir.setter
    def base_dir(self, value: str | Path) -> None:
        self._base_dir = Path(value)

    @model_validator(mode="after")
    def _pbr_needs_light(self) -> RenderFile:
        lit = bool(self.lights) or self.environment is not None
        if self.render.shading is None:
            self.render.shading = "toon" if self.render.toon is not None else (
                "pbr" if lit else "headlight")
        elif self.render.shading not in LIT_MODELS and self.lights:
            raise ValueError(f"render.shading {self.render.shading!r} ignores 'lights:'; remove "
                             "them, or use shading: pbr (the default when lights are given) or "
                             "another lit model (blinn_phong, half_lambert, toon)")
        if (self.render.shading in LIT_MODELS and not self.lights
                and self.environment is None):
            raise ValueError(f"render.shading {self.render.shading!r} needs light: add a "
                             "'lights:' entry or an 'environment:', or use shading: "
                             "headlight / unlit")
        return self

    def where(self, *loc: str | int) -> str:
        """``file:line: key.path`` of a key path (the nearest line found)."""
        line = _line_of(self._lines, loc)
        key = ".".join(str(p) for p in loc)
        return f"{self._source}:{line}: {key}" if line else f"{self._source}: {key}"

    def resolve(self, relative: str) -> Path:
        """A path from the config, resolved against the config file's folder."""
        p = Path(relative).expanduser()
        return p if p.is_absolute() else (self.base_dir / p).resolve()


# --------------------------------------------------------------------------- parsing


def _expanded_size(node: yaml.Node, source: str) -> int:
    """Number of nodes of the document with aliases expanded (memoised, so a "billion
    laughs" document is measured in linear time); raises ConfigError past MAX_YAML_NODES
    or on a recursive alias."""
    sizes: dict[int, int] = {}
    active: set[int] = set()

    def size(n: yaml.Node) -> int:
        key = id(n)
        if key in sizes:
            return sizes[key]
        if key in active:
            line = n.start_mark.line + 1
            raise ConfigError(f"{source}:{line}: recursive YAML alias (a node that contains "
                              "itself); configs cannot be recursive")
        active.add(key)
        total = 1
        if isinstance(n, yaml.MappingNode):
            total += sum(size(k) + size(v) for k, v in n.value)
        elif isinstance(n, yaml.SequenceNode):
            total += sum(size(v) for v in n.value)
        active.discard(key)
        sizes[key] = min(total, MAX_YAML_NODES + 1)
        return sizes[key]

    total = size(node)
    if total > MAX_YAML_NODES:
        raise ConfigError(f"{source}: YAML aliases expand to more than {MAX_YAML_NODES:,} "
                          "values; refusing to load it (an alias bomb?)")
    return total


def _key_lines(node: yaml.Node) -> dict:
    """Map every key path of a composed YAML tree to its 1-based line number (each node
    visited once: aliased content keeps the line of its anchor)."""
    out: dict = {}
    seen: set[int] = set()
    stack: list[tuple[yaml.Node, tuple]] = [(node, ())]
    while stack:
        n, path = stack.pop()
        out.setdefault(path, n.start_mark.line + 1)
        if id(n) in seen:
            continue
        seen.add(id(n))
        if isinstance(n, yaml.MappingNode):
            for key, value in n.value:
                kp = path + (getattr(key, "value", str(key)),)
                out.setdefault(kp, key.start_mark.line + 1)
                stack.append((value, kp))
        elif isinstance(n, yaml.SequenceNode):
            stack.extend((item, path + (i,)) for i, item in enumerate(n.value))
    return out


_UNION_TAGS = ("ambient", "directional", "point", "spot")


def _line_of(lines: dict, loc: Sequence) -> int | None:
    """Line of the longest prefix of ``loc`` found in the YAML (pydantic adds union tags)."""
    loc = tuple(int(p) if isinstance(p, str) and p.isdigit() else p for p in loc)
    for n in range(len(loc), -1, -1):
        cand = tuple(loc[:n])
        if cand in lines:
            return lines[cand]
        stripped = tuple(p for p in cand if p not in _UNION_TAGS)
        if stripped in lines:
            return lines[stripped]
    return None


def _model_at(loc: Sequence) -> type[BaseModel] | None:
    """The config model that holds the key at ``loc`` (for "did you mean" suggestions)."""
    model: Any = RenderFile
    for part in loc[:-1]:
        if isinstance(part, int) or (isinstance(part, str) and part.isdigit()):
            continue
        if part in _UNION_TAGS:
            model = {"ambient": AmbientLightConfig, "directional": DirectionalLightConfig,
                     "point": PointLightConfig, "spot": SpotLightConfig}[part]
            continue
        field = model.model_fields.get(part) if isinstance(model, type) else None
        if field is None:
            return None
        model = _inner_model(field.annotation)
        if model is None:
            return None
    return model if isinstance(model, type) and issubclass(model, BaseModel) else None


def _inner_model(annotation: Any) -> type[BaseModel] | None:
    """The (single) pydantic model inside an annotation like ``list[X] | None``."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        found = _inner_model(arg)
        if found is not None:
            return found
    return None


def _message(err: dict) -> str:
    """A pydantic error message, with a suggestion for a misspelt key."""
    if err["type"] != "extra_forbidden":
        return err["msg"]
    key = str(err["loc"][-1])
    model = _model_at(err["loc"])
    names = list(model.model_fields) if model is not None else []
    close = difflib.get_close_matches(key, names, n=1)
    hint = f"; did you mean {close[0]!r}?" if close else (
        f"; expected one of {names}" if names else "")
    return f"unknown key{hint}"


def parse_config(text: str | bytes, source: str = "<string>",
                 base_dir: Path | None = None) -> RenderFile:
    """Validate YAML text into a :class:`RenderFile`.

    Args:
        text: the YAML document (bytes must be UTF-8).
        source: the file name used in error messages.
        base_dir: the folder relative paths resolve against (default: the working folder).

    Returns:
        The validated config.

    Raises:
        ConfigError: naming ``source``, the line and the key path of every problem.
    """
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8-sig")
        except UnicodeDecodeError as e:
            raise ConfigError(f"{source}: not UTF-8 text (invalid byte at offset {e.start}); "
                              "save the config as UTF-8") from None
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        if node is not None:
            _expanded_size(node, source)
        data = yaml.safe_load(text)
    except yaml.MarkedYAMLError as e:
        mark = e.context_mark or e.problem_mark  # where the broken construct starts
        line = mark.line + 1 if mark else "?"
        detail = f"{e.context}; {e.problem}" if e.context else str(e.problem)
        if e.problem_mark and mark is not e.problem_mark:
            detail += f" (line {e.problem_mark.line + 1})"
        raise ConfigError(f"{source}:{line}: malformed YAML: {detail}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{source}: malformed YAML: {e}") from None
    except RecursionError:
        raise ConfigError(f"{source}: YAML nested too deeply") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level (scene:, cameras:, ...)")
    lines = _key_lines(node) if node is not None else {}
    try:
        cfg = RenderFile.model_validate(data)
    except ValidationError as e:
        msgs = []
        for err in e.errors():
            loc = tuple(err["loc"])
            key = ".".join(str(p) for p in loc) or "(top level)"
            line = _line_of(lines, loc)
            where = f"{source}:{line}" if line else source
            msgs.append(f"{where}: {key}: {_message(err)}")
        raise ConfigError("invalid render config\n  " + "\n  ".join(msgs)) from None
    cfg.base_dir = base_dir if base_dir is not None else Path(".")
    cfg._source, cfg._lines = source, lines
    problems = _duplicate_cameras(cfg)
    if problems:
        raise ConfigError("invalid render config\n  " + "\n  ".join(problems))
    return cfg


def load_config(path: str | Path) -> RenderFile:
    """Read and validate a YAML render config; relative paths resolve against its folder.

    Raises:
        ConfigError: naming the file (and line and key path) of every problem.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except IsADirectoryError:
        raise ConfigError(f"{p}: is a folder, not a config file") from None
    except OSError as e:
        raise ConfigError(f"{p}: cannot read the config file ({e.strerror})") from None
    return parse_config(data, source=str(p), base_dir=p.resolve().parent)


_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


def safe_name(name: str) -> str:
    """A file-system-safe name: letters, digits, ``.``, ``_`` and ``-`` kept, any other run
    of characters replaced by ``_``, no leading dots (so never ``..``); never empty."""
    cleaned = _UNSAFE.sub("_", name).lstrip(".")
    return cleaned or "_"


def camera_names(cfg: RenderFile) -> list[str]:
    """The output folder name of every camera (sanitised ``name``, or ``view<index>``)."""
    return [safe_name(c.name) if c.name is not None else f"view{i}"
            for i, c in enumerate(cfg.cameras)]


def view_names(cfg: RenderFile) -> list[list[str]]:
    """The output name of every view of every camera entry: ``[name]`` for a single camera,
    ``[name_000, name_001, ...]`` for ``random_orbits`` (``name`` as in :func:`camera_names`)."""
    out = []
    for base, cam in zip(camera_names(cfg), cfg.cameras, strict=True):
        if cam.random_orbits is None:
            out.append([base])
        else:
            count = cam.random_orbits.count
            width = max(3, len(str(count - 1)))
            out.append([f"{base}_{j:0{width}d}" for j in range(count)])
    return out


def _duplicate_cameras(cfg: RenderFile) -> list[str]:
    seen: dict[str, int] = {}
    problems = []
    for i, names in enumerate(view_names(cfg)):
        for name in names:
            if name in seen and seen[name] != i:
                problems.append(f"{cfg.where('cameras', i, 'name')}: camera name {name!r} is "
                                f"used by cameras.{seen[name]} too; names must be unique "
                                "(after sanitising to letters, digits, '.', '_', '-')")
                break
            seen.setdefault(name, i)
    return problems


# --------------------------------------------------------------------------- mesh sets


def stable_seed(*parts: object) -> int:
    """A seed in [0, 2**63) from ``parts`` (their ``str``), the same in every process and on
    every machine (unlike ``hash``)."""
    digest = hashlib.sha256("\x1f".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


@dataclass(frozen=True)
class MeshSetEntry:
    """One object of a mesh set: its output name, its file and where it was named (for
    errors: ``list.txt:7`` or ``config.yaml:2: scene.mesh``)."""

    name: str
    path: Path
    source: str


_GLOB_MAGIC = re.compile(r"[*?[]")


def is_mesh_set(cfg: RenderFile) -> bool:
    """Whether the config names a set of objects (``scene.meshes_from``, or ``scene.mesh``
    as a glob pattern that is not itself an existing file)."""
    sc = cfg.scene
    if sc.meshes_from is not None:
        return True
    return (sc.mesh is not None and _GLOB_MAGIC.search(sc.mesh) is not None
            and not cfg.resolve(sc.mesh).is_file())


def _listed_meshes(cfg: RenderFile) -> tuple[Path, list[tuple[int, Path]]]:
    """The list file of ``scene.meshes_from`` and its entries ``(line, resolved path)``."""
    listing = cfg.resolve(cfg.scene.meshes_from)
    try:
        text = listing.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        reason = "is a folder" if listing.is_dir() else (
            "file not found" if not listing.exists() else getattr(e, "strerror", None) or e)
        raise ConfigError(f"{cfg.where('scene', 'meshes_from')}: {listing}: {reason}") from None
    entries = []
    for number, line in enumerate(text.splitlines(), 1):
        entry = line.strip()
        if entry and not entry.startswith("#"):
            path = Path(entry).expanduser()
            entries.append((number, path if path.is_absolute() else
                            (listing.parent / path).resolve()))
    return listing, entries


def _unique_object_names(paths: list[Path], base: Path) -> list[str]:
    """Sanitised file stems; where stems clash, the path relative to ``base`` (suffix
    kept); any clash left gets ``-2``, ``-3``, ..."""
    stems = [safe_name(p.stem) for p in paths]
    counts = Counter(stems)
    names = [safe_name(os.path.relpath(p, base).replace(os.sep, "_")) if counts[s] > 1 else s
             for p, s in zip(paths, stems, strict=True)]
    seen: Counter = Counter()
    out = []
    for n in names:
        seen[n] += 1
        out.append(n if seen[n] == 1 else f"{n}-{seen[n]}")
    return out


def mesh_set(cfg: RenderFile) -> list[MeshSetEntry]:
    """The objects of a mesh set config in order (glob matches sorted; list entries in file
    order, duplicates dropped), each with a unique sanitised name. Empty when nothing
    matches (:func:`check_config` reports it).

    Raises:
        ConfigError: the list file of ``scene.meshes_from`` cannot be read.
    """
    sc = cfg.scene
    if sc.meshes_from is not None:
        listing, entries = _listed_meshes(cfg)
        first: dict[Path, int] = {}
        for number, path in entries:
            first.setdefault(path, number)
        paths = list(first)
        sources = [f"{listing}:{first[p]}" for p in paths]
        base = listing.parent
    else:
        pattern = cfg.resolve(sc.mesh)
        paths = sorted(Path(m) for m in glob.glob(str(pattern), recursive=True)
                       if os.path.isfile(m))
        sources = [cfg.where("scene", "mesh")] * len(paths)
        parts = pattern.parts  # names are made relative to the folder the pattern starts in
        first = next((i for i, part in enumerate(parts) if _GLOB_MAGIC.search(part)),
                     len(parts) - 1)
        base = Path(*parts[:max(first, 1)])
    names = _unique_object_names(paths, base)
    return [MeshSetEntry(n, p, src) for n, p, src in zip(names, paths, sources, strict=True)]


def _mesh_set_problems(cfg: RenderFile) -> list[str]:
    sc = cfg.scene
    if sc.meshes_from is None:
        return [] if mesh_set(cfg) else [
            f"{cfg.where('scene', 'mesh')}: no file matches {sc.mesh!r} (in "
            f"{cfg.resolve('.')})"]
    try:
        listing, entries = _listed_meshes(cfg)
    except ConfigError as e:
        return [str(e)]
    problems, seen = [], {}
    for number, path in entries:
        if path in seen:
            problems.append(f"{listing}:{number}: {path.name} is listed twice (first at "
                            f"line {seen[path]})")
        elif path.is_dir():
            problems.append(f"{listing}:{number}: {path} is a folder, expected a mesh file")
        elif not path.is_file():
            problems.append(f"{listing}:{number}: file not found: {path}")
        seen.setdefault(path, number)
    if not entries:
        problems.append(f"{cfg.where('scene', 'meshes_from')}: {listing} lists no mesh")
    return problems


def object_name(cfg: RenderFile) -> str:
    """The object name of a config that is not a mesh set: its mesh's sanitised stem, or
    ``scene`` for a scene built from ``objects`` only."""
    return safe_name(Path(cfg.scene.mesh).stem) if cfg.scene.mesh is not None else "scene"


@dataclass(frozen=True)
class PlannedCamera:
    """One view of one object: its name, its camera (``random_orbits`` drawn into an
    ``orbit``; ``name`` set) and its seed (:func:`stable_seed`)."""

    name: str
    camera: CameraConfig
    seed: int


def expand_cameras(cfg: RenderFile, obj: str, seed: int = 0) -> list[PlannedCamera]:
    """The views of object ``obj``: one per camera entry, ``count`` per ``random_orbits``
    entry (drawn from ``stable_seed(seed, random_orbits.seed, obj, view name)``).

    Args:
        cfg: the config.
        obj: the object's name (the same object gets the same views in every process).
        seed: a seed mixed into every view's (``RenderDataset(seed=...)``; 0 on the
            command line).
    """
    out = []
    for cam, names in zip(cfg.cameras, view_names(cfg), strict=True):
        ro = cam.random_orbits
        for name in names:
            view_seed = stable_seed(seed, ro.seed if ro is not None else 0, obj, name)
            update: dict[str, Any] = {"name": name}
            if ro is not None:
                update.update(random_orbits=None, orbit=ro.draw(view_seed))
            out.append(PlannedCamera(name, cam.model_copy(update=update), view_seed))
    return out


def object_config(cfg: RenderFile, mesh: Path | str | None,
                  cameras: Sequence[CameraConfig]) -> RenderFile:
    """A copy of ``cfg`` that renders one object (``mesh``, an absolute path or None for a
    scene of ``objects`` only) with the given concrete cameras (names set, no
    ``random_orbits``)."""
    scene = cfg.scene.model_copy(update={"mesh": None if mesh is None else str(mesh),
                                         "meshes_from": None})
    return cfg.model_copy(update={"scene": scene, "cameras": list(cameras)})


def check_config(cfg: RenderFile) -> None:
    """Find, in one pass before rendering, every problem validation cannot see: missing or
    unreadable files (mesh, environment, textures) and degenerate cameras.

    Raises:
        ConfigError: listing each problem as ``file:line: key.path: message``.
    """
    problems = []

    def need_file(loc: tuple, relative: str) -> None:
        p = cfg.resolve(relative)
        if p.is_dir():
            problems.append(f"{cfg.where(*loc)}: {p} is a folder, expected a file")
        elif not p.is_file():
            problems.append(f"{cfg.where(*loc)}: file not found: {p}")

    mesh_set_config = is_mesh_set(cfg)
    if mesh_set_config:  # files checked to exist; textures when each object loads
        problems += _mesh_set_problems(cfg)
    meshes = [(("scene", "mesh"), cfg.scene.mesh)] if (
        cfg.scene.mesh is not None and not mesh_set_config) else []
    meshes += [(("scene", "objects", i, "mesh"), o.mesh)
               for i, o in enumerate(cfg.scene.objects) if o.mesh is not None]
    for loc, relative in meshes:
        need_file(loc, relative)
        mesh = cfg.resolve(relative)
        if mesh.is_file() and not cfg.scene.allow_missing_textures:
            from .io import missing_textures

            missing = missing_textures(mesh)
            if missing:
                problems.append(f"{cfg.where(*loc)}: {mesh.name} refers to missing texture "
                                f"file(s) {', '.join(missing)} (set "
                                "scene.allow_missing_textures: true to render without them)")
    if cfg.environment is not None:
        need_file(("environment", "path"), cfg.environment.path)
    if cfg.render.background_image is not None:
        need_file(("render", "background_image", "path"), cfg.render.background_image.path)
    for i, m in enumerate(cfg.materials):
        if m.base_color_texture is not None:
            need_file(("materials", i, "base_color_texture"), m.base_color_texture)
    for i, cam in enumerate(cfg.cameras):
        if cam.look_at is None:
            continue
        eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in (
            cam.look_at.eye, cam.look_at.target, cam.look_at.up))
        forward = target - eye
        if float(forward.norm()) <= 1e-12 * max(1.0, float(eye.norm())):
            problems.append(f"{cfg.where('cameras', i, 'look_at', 'eye')}: eye and target "
                            "are the same point; the camera has no direction")
        elif float(torch.linalg.cross(forward, up).norm()) <= 1e-9 * float(
                forward.norm() * up.norm()):
            problems.append(f"{cfg.where('cameras', i, 'look_at', 'up')}: up is parallel to "
                            "the view direction (or zero); pick another up vector")
    if problems:
        raise ConfigError("invalid render config\n  " + "\n  ".join(problems))


# --------------------------------------------------------------------------- builders


def build_post_chain(cfg: PostConfig | dict | None = None) -> PostChain:
    """The :class:`~torchraster.post.PostChain` of a ``post:`` section (a
    :class:`PostConfig` or the raw mapping; None: every stage at its default).

    Raises:
        pydantic.ValidationError: for an invalid raw mapping.
    """
    cfg = cfg if isinstance(cfg, PostConfig) else PostConfig.model_validate(cfg or {})
    d, b, e, a, t = cfg.dof, cfg.bloom, cfg.exposure, cfg.auto_exposure, cfg.tonemap
    return PostChain(
        dof=DepthOfField(focus_distance=d.focus_distance, focal_length_mm=d.focal_length_mm,
                         f_number=d.f_number, sensor_width_mm=d.sensor_width_mm,
                         max_coc=d.max_coc, levels=d.levels, enabled=d.enabled),
        bloom=Bloom(threshold=b.threshold, knee=b.knee, intensity=b.intensity,
                    radius=b.radius, levels=b.levels, karis=b.karis, enabled=b.enabled),
        exposure=Exposure(ev=e.ev, enabled=e.enabled and not a.enabled),
        auto_exposure=AutoExposure(key=a.key, min_ev=a.min_ev, max_ev=a.max_ev,
                                   compensation=e.ev if e.enabled else 0.0,
                                   metering=a.metering, percentile_low=a.percentile_low,
                                   percentile_high=a.percentile_high, rate=a.rate,
                                   enabled=a.enabled),
        tonemap=ToneMap(curve=t.curve, white=t.white, enabled=t.enabled),
        encode=EncodeSRGB(enabled=cfg.encode.enabled),
    )


def build_ssao(cfg: PostConfig | SSAOConfig) -> SSAO:
    """The SSAO module of ``post.ssao`` (or an :class:`SSAOConfig`)."""
    c = cfg.ssao if isinstance(cfg, PostConfig) else cfg
    return SSAO(radius=c.radius, samples=c.samples, bias=c.bias, softness=c.softness,
                blur=c.blur, enabled=c.enabled)


def build_ssr(cfg: PostConfig | SSRConfig) -> SSR:
    """The SSR module of ``post.ssr`` (or an :class:`SSRConfig`)."""
    c = cfg.ssr if isinstance(cfg, PostConfig) else cfg
    return SSR(max_steps=c.max_steps, thickness=c.thickness, max_roughness=c.max_roughness,
               edge_fade=c.edge_fade, refine_steps=c.refine_steps,
               max_distance=c.max_distance, blur=c.blur, enabled=c.enabled)


def build_renderer(cfg: RenderFile, with_environment: bool) -> Renderer:
    """The :class:`~torchraster.Renderer` of a config's ``render:`` (and ``post.ssao``,
    ``post.ssr``)."""
    r = cfg.render
    ssao = build_ssao(cfg.post) if cfg.post is not None and cfg.post.ssao.enabled else None
    ssr = build_ssr(cfg.post) if cfg.post is not None and cfg.post.ssr.enabled else None
    options = r.toon.model_dump() if r.toon is not None else None
    image = None
    if r.background_image is not None:
        path = cfg.resolve(r.background_image.path)
        try:
            image = load_background(path)
        except (OSError, ValueError) as e:
            where = cfg.where("render", "background_image", "path")
            raise ConfigError(f"{where}: {e}") from None
    return Renderer(r.size, shading=r.shading, shading_options=options,
                    background_image=image,
                    background_fit=r.background_image.fit if image is not None else "cover",
                    dissolve=r.dissolve.build() if r.dissolve is not None else None,
                    supersample=r.supersample,
                    cull_backfaces=r.cull_backfaces, background=r.background,
                    environment_background=bool(with_environment and cfg.environment
                                                and cfg.environment.background),
                    texture_filter=r.texture_filter, max_anisotropy=r.max_anisotropy,
                    ssao=ssao, ssr=ssr, alpha_layers=r.alpha_layers,
                    antialias=r.antialias, fog=r.fog.fog() if r.fog is not None else None,
                    multiscatter=r.multiscatter)


def parse_lights(data: object) -> list:
    """Validate a YAML/JSON list of light dicts into :data:`LightConfig` models.

    Raises ``pydantic.ValidationError`` whose messages carry the key path (e.g. ``1.spot.range``).
    """
    return _LIGHT_LIST.validate_python(data)


def lights_from_config(
    configs: Sequence[object],
    batch: int = 1,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Lights:
    """Build :class:`Lights` tensors (the same lights for each of ``batch`` scenes).

    Args:
        configs: :data:`LightConfig` models or plain dicts (validated with
            :func:`parse_lights`).
        batch: batch size B >= 1.
        device, dtype: of the created tensors.

    Returns:
        Lights with ``ambient (B, 9, 3)`` (sum of all ambient lights) or None, and
        directional / point / spot containers with ``L`` = number of lights of each type
        (None for types that are absent).
    """
    if not isinstance(batch, int) or isinstance(batch, bool) or batch < 1:
        raise ValueError(f"batch: expected a positive int, got {batch!r}")
    cfgs = parse_lights([c.model_dump(exclude_unset=True) if isinstance(c, BaseModel) else c
                        for c in configs])

    def tensor(rows: list, shape_tail: tuple[int, ...] = ()) -> torch.Tensor:
        t = torch.tensor(rows, device=device, dtype=dtype).reshape(1, len(rows), *shape_tail)
        return t.expand(batch, *t.shape[1:]).contiguous()

    def shadows(rows: list) -> torch.Tensor:
        t = torch.tensor(rows, device=device, dtype=torch.bool).reshape(1, -1)
        return t.expand(batch, -1).contiguous()

    def inf_if_none(r: float | None) -> float:
        return math.inf if r is None else r

    by_type: dict[str, list] = {"ambient": [], "directional": [], "point": [], "spot": []}
    for c in cfgs:
        by_type[c.type].append(c)

    ambient = None
    if by_type["ambient"]:
        sh = torch.zeros(9, 3, dtype=torch.float64)
        for c in by_type["ambient"]:
            if c.sh is not None:
                sh += torch.tensor(c.sh, dtype=torch.float64) * c.intensity
            else:
                sh[0] += torch.tensor(c.color, dtype=torch.float64) * c.intensity / SH_C0
        ambient = sh.to(device=device, dtype=dtype)[None].expand(batch, 9, 3).contiguous()

    directional = point = spot = None
    if d := by_type["directional"]:
        directional = DirectionalLights(
            direction=tensor([c.direction for c in d], (3,)),
            color=tensor([c.color for c in d], (3,)),
            intensity=tensor([c.intensity for c in d]),
            cast_shadows=shadows([_casts(c) for c in d]),
            shadow=tuple(_shadow_settings(c) for c in d),
        )
    if p := by_type["point"]:
        point = PointLights(
            position=tensor([c.position for c in p], (3,)),
            color=tensor([c.color for c in p], (3,)),
            intensity=tensor([c.intensity for c in p]),
            range=tensor([inf_if_none(c.range) for c in p]),
            cast_shadows=shadows([_casts(c) for c in p]),
            shadow=tuple(_shadow_settings(c) for c in p),
        )
    if s := by_type["spot"]:
        spot = SpotLights(
            position=tensor([c.position for c in s], (3,)),
            direction=tensor([c.direction for c in s], (3,)),
            color=tensor([c.color for c in s], (3,)),
            intensity=tensor([c.intensity for c in s]),
            range=tensor([inf_if_none(c.range) for c in s]),
            inner_cone_angle=tensor([c.inner_cone_angle for c in s]),
            outer_cone_angle=tensor([c.outer_cone_angle for c in s]),
            cast_shadows=shadows([_casts(c) for c in s]),
            shadow=tuple(_shadow_settings(c) for c in s),
        )
    return Lights(ambient=ambient, directional=directional, point=point, spot=spot)


# --------------------------------------------------------------------------- reference


def _type_name(annotation: Any) -> str:
    """A short readable type of a field annotation (``float >= 0``, ``[float] x 3``, ...)."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is Annotated:
        base, *meta = args
        text = _type_name(base)
        for m in meta:
            for attr, sym in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<")):
                for c in getattr(m, "metadata", [m]):
                    if getattr(c, attr, None) is not None:
                        text += f" {sym} {getattr(c, attr):g}"
            lo, hi = getattr(m, "min_length", None), getattr(m, "max_length", None)
            for c in getattr(m, "metadata", []):
                lo = getattr(c, "min_length", lo)
                hi = getattr(c, "max_length", hi)
            if lo is not None and lo == hi:
                text += f" (exactly {lo})"
            elif lo:
                text += f" (at least {lo})"
        return text
    if origin is Literal:
        return " \\| ".join(repr(a) for a in args)
    if origin in (list, Sequence):
        return f"list of {_type_name(args[0])}" if args else "list"
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        return " or ".join(_type_name(a) for a in args if a is not type(None)) + (
            " or null" if type(None) in args else "")
    if isinstance(annotation, type):
        if issubclass(annotation, BaseModel):
            return f"[{annotation.__name__}](#{annotation.__name__.lower()})"
        return annotation.__name__
    return str(annotation).replace("typing.", "")


def _default_text(field: Any) -> str:
    if field.is_required():
        return "**required**"
    value = field.default_factory() if field.default_factory is not None else field.default
    if isinstance(value, BaseModel):
        return "(section defaults)"
    if isinstance(value, float) and math.isfinite(value):
        return f"`{value:g}`"
    return f"`{value!r}`" if not isinstance(value, Path) else f"`{value}`"


def config_reference() -> str:
    """The config reference as Markdown, generated from the pydantic models (every key with
    its type, bounds, default and description). ``torchraster schema`` prints it;
    ``scripts/make_config_docs.py`` writes it to ``docs/config.md``."""
    order: list[type[BaseModel]] = []

    def visit(model: type[BaseModel]) -> None:
        if model in order:
            return
        order.append(model)
        for field in model.model_fields.values():
            for sub in _models_in(field.annotation):
                visit(sub)

    visit(RenderFile)
    out = ["# Render config reference", "",
           "Generated from the pydantic models in `torchraster/config.py` by "
           "`python scripts/make_config_docs.py` (also `torchraster schema`). Unknown keys "
           "are errors; paths are relative to the config file; `resolution` is `[H, W]` "
           "(or one int for a square image). Lights are a list of entries with a `type`.", ""]
    for model in order:
        out += [f"## {model.__name__}", ""]
        doc = inspect.getdoc(model) or ""
        if doc and model.__module__ == __name__:
            out += [doc, ""]
        out += ["| key | type | default | description |", "|---|---|---|---|"]
        for name, field in model.model_fields.items():
            if field.exclude:
                continue
            desc = (field.description or "").replace("|", "\\|").replace("\n", " ")
            out.append(f"| `{name}` | {_type_name(field.annotation)} | "
                       f"{_default_text(field)} | {desc} |")
        out.append("")
    return "\n".join(out)


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    found = []
    for arg in typing.get_args(annotation):
        found += _models_in(arg)
    return found


__all__ = [
    "ConfigError", "RenderFile", "build_post_chain", "build_renderer", "build_ssao", "build_ssr",
    "camera_names", "check_config", "config_reference", "default_of", "expand_cameras",
    "is_mesh_set", "lights_from_config", "load_config", "mesh_set", "object_config",
    "object_name", "parse_config", "parse_lights", "safe_name", "stable_seed", "view_names",
]
