"""The schema of a render config: one pydantic model per YAML section.

Defaults live in one place: the keyword defaults of the objects the config builds
(``Bloom(threshold=1.0)``, ``RasterSettings(supersample=1)``, ...) or the named constants of their
module (light defaults); the fields read them (:func:`default_of`) and the builders
(:mod:`torchraster.config.build`) pass keyword arguments.

Paths (:data:`FilePath` fields) are resolved when the config is validated: relative to the
``base_dir`` of the validation context (the config file's folder; :func:`parse_config`
passes it), else to the working folder. Each holds a :class:`ConfigPath`: the absolute path
as a ``str`` that remembers the text the file gave (``.written``); dumps (``model_dump``,
the manifest's config hash and records) show that text, so they do not depend on where the
project lives. A new section with a file in it only needs to type the field ``FilePath``.
"""

from __future__ import annotations

import inspect
import math
import random
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PlainSerializer,
    PrivateAttr,
    TypeAdapter,
    ValidationInfo,
    field_validator,
    model_validator,
)

from ..animation import MAX_FRAMES
from ..background import FITS
from ..dissolve import MAX_OCTAVES, Dissolve
from ..post import SSAO, SSR, AutoExposure, Bloom, DepthOfField, Exposure, ToneMap
from ..post.tonemap import CURVES
from ..settings import (
    LIT_MODELS,
    SETTINGS_BOUNDS,
    SHADING,
    TEXTURE_FILTERS,
    BackgroundSettings,
    RasterSettings,
    ShadingSettings,
    TextureSettings,
)
from ..shading.ibl import SPECULAR_MODES, Environment
from ..shading.lights import (
    AREA_SHADOW_TAPS,
    DEFAULT_COLOR,
    DEFAULT_DIRECTION,
    DEFAULT_INNER_CONE_ANGLE,
    DEFAULT_INTENSITY,
    DEFAULT_OUTER_CONE_ANGLE,
)
from ..shading.models import model_options
from ..shading.shadows import (
    FILTERS,
    PATTERNS,
    SHADOW_BOUNDS,
    SHADOW_INT_FIELDS,
    ShadowSettings,
)
from ..shading.volumetric import MAX_ANISOTROPY, MAX_DENSITY, Fog
from .lines import line_of

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


class ConfigPath(str):
    """An absolute path from a config (a ``str``), with the text the file gave
    (``.written``: what error messages and dumps show)."""

    written: str

    def __new__(cls, absolute: str | Path, written: str) -> ConfigPath:
        obj = super().__new__(cls, str(absolute))
        obj.written = written
        return obj

    def __getnewargs__(self) -> tuple[str, str]:  # pickling (DataLoader workers, torchrun)
        return str(self), self.written

    @property
    def path(self) -> Path:
        """The absolute path as a :class:`~pathlib.Path`."""
        return Path(self)


def resolve_path(text: str, base_dir: str | Path | None = None) -> ConfigPath:
    """``text`` (``~`` expanded) made absolute against ``base_dir`` (default: the working
    folder), symbolic links resolved for relative paths, as a :class:`ConfigPath`.

    Raises:
        ValueError: ``~user`` names no user.
    """
    if isinstance(text, ConfigPath):
        return text
    try:
        p = Path(text).expanduser()
    except RuntimeError as e:  # "~nobody/..."
        raise ValueError(f"cannot expand {text!r}: {e}") from None
    if not p.is_absolute():
        p = (Path(base_dir if base_dir is not None else ".") / p).resolve()
    return ConfigPath(p, text)


def written(value: str) -> str:
    """The text the config gave for a path field (the value itself if it is no
    :class:`ConfigPath`)."""
    return getattr(value, "written", value)


def _resolve_in_context(value: str, info: ValidationInfo) -> ConfigPath:
    base = (info.context or {}).get("base_dir") if isinstance(info.context, dict) else None
    return resolve_path(value, base)


#: A file named by a config: validated to an absolute :class:`ConfigPath`, dumped as written.
FilePath = Annotated[str, AfterValidator(_resolve_in_context),
                     PlainSerializer(written, return_type=str)]


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
    base_color_texture: FilePath | None = Field(
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


#: Most instances a scene may hold: ``instance`` / ``semantic`` PNGs are 16-bit.
MAX_INSTANCES: int = 65_535
Quaternion = Annotated[list[Finite], Field(min_length=4, max_length=4)]
Scale3 = Annotated[list[Positive], Field(min_length=3, max_length=3)]


class KeyframeConfig(_Strict):
    """One key of an object's animation. A component a key leaves out is the object's
    ``transform`` value."""

    time: NonNeg = Field(description="seconds (frame i is at i / frames.fps)")
    translate: Vec3 | None = None
    rotate_deg: Vec3 | None = Field(None, description="Euler angles in degrees, order "
                                    "`euler_order` of the animation")
    rotation: Quaternion | None = Field(None, description="unit quaternion [w, x, y, z] "
                                        "(normalised), instead of rotate_deg")
    scale: Positive | Scale3 | None = None

    @model_validator(mode="after")
    def _one_rotation(self) -> KeyframeConfig:
        if self.rotate_deg is not None and self.rotation is not None:
            raise ValueError("give 'rotate_deg' (Euler) or 'rotation' (quaternion), not both")
        if self.rotation is not None and sum(x * x for x in self.rotation) <= 1e-12:
            raise ValueError("rotation: the zero quaternion is no rotation; use [1, 0, 0, 0]")
        return self


class AnimationConfig(_Strict):
    """Keyframed motion of an object: at time t its transform is the keys interpolated
    (translation and scale linearly, rotation by slerp; ``step`` holds each key until the
    next); before the first key and after the last the end keys hold."""

    interpolation: Literal["linear", "step"] = "linear"
    euler_order: Annotated[str, Field(pattern=r"^([xyz]{3}|[XYZ]{3})$")] = Field(
        "xyz", description="order of `rotate_deg`: lower case about the world axes, the first "
        "letter applied first (xyz = Rz Ry Rx, as `transform.rotate_deg`); upper case about the "
        "object's own axes")
    keys: Annotated[list[KeyframeConfig], Field(min_length=1, max_length=100_000)] = Field(
        description="in increasing time order (checked with the line of the key)")


class ObjectConfig(_Strict):
    """One more object of the scene: a mesh file or a primitive built here (a ground plane
    under a model, a box, a sphere), with its own transform and shadow flags."""

    name: str | None = None
    mesh: FilePath | None = Field(None, description="mesh / glTF file, relative to the config "
                                  "file")
    primitive: Primitive | None = Field(
        None, description="plane: `size` x `size` in XZ facing +Y, centred at the origin; box: "
        "a cube of side `size`; sphere: diameter `size` (an icosphere)")
    size: Positive = 1.0
    transform: TransformConfig = Field(default_factory=TransformConfig)
    material: ObjectMaterialConfig | None = Field(
        None, description="for primitives (default: light grey, rough dielectric); for a mesh "
        "file, the fields given replace those of every material of this object")
    cast_shadows: bool = True
    receive_shadows: bool = True
    category: str | None = Field(None, description="class name for the `semantic` channel "
                                 "and the exports (one of `categories:` when given)")
    animation: AnimationConfig | None = Field(None, description="keyframed motion over the "
                                              "frames (replaces `transform` per key)")
    keypoints: list[Vec3] | None = Field(None, description="model-space points projected "
                                         "into every view's record with their visibility")

    @model_validator(mode="after")
    def _one_source(self) -> ObjectConfig:
        if (self.mesh is None) == (self.primitive is None):
            raise ValueError("give exactly one of 'mesh' (a file) or 'primitive' "
                             "(plane, box, sphere)")
        if self.mesh is not None and self.material is not None and (
                {"name", "alpha_mode", "alpha_cutoff"} & self.material.model_fields_set):
            raise ValueError("material: a mesh file keeps its materials' names and alpha "
                             "modes; only base_color, metallic, roughness, emissive and "
                             "base_color_texture override them")
        return self


class SceneConfig(_Strict):
    """The geometry: a mesh or glTF scene file, relative to the config file, and optional
    further ``objects`` (e.g. a ground plane).

    A *mesh set* renders many objects with one config, one at a time (each with the
    ``objects``, lights and cameras of the config): ``mesh`` as a glob pattern
    (``objects/*.glb``, ``**`` recurses; sorted) or ``meshes_from``, a list file. Each
    object is named after its file (sanitised; the path is added where two stems clash)
    and written to ``<out>/<config>/<object>/<camera>/``."""

    mesh: FilePath | None = Field(None, description="the main mesh / glTF scene (optional when "
                             "`objects` is given), or a glob pattern naming a mesh set")
    meshes_from: FilePath | None = Field(
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
    category: str | None = Field(None, description="class name of the main mesh (each of "
                                 "its glTF nodes with a mesh is one instance)")
    animation: AnimationConfig | None = Field(None, description="keyframed motion of the "
                                              "main mesh")
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
    degrees_per_second: Finite = Field(0.0, description="azimuth turn over time (frames)")


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


class CameraKeyConfig(_Strict):
    """One key of a camera trajectory: at ``time`` the camera is at ``eye`` looking at
    ``target``."""

    time: NonNeg
    eye: Vec3
    target: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    up: Vec3 = Field(default_factory=lambda: [0.0, 1.0, 0.0])


class TrajectoryConfig(_Strict):
    """A camera moving over the frames: eye, target and up interpolated between keys."""

    interpolation: Literal["linear", "step"] = "linear"
    keys: Annotated[list[CameraKeyConfig], Field(min_length=1, max_length=100_000)] = Field(
        description="in increasing time order (checked with the line of the key)")


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
    trajectory: TrajectoryConfig | None = None

    @model_validator(mode="after")
    def _one_placement(self) -> CameraConfig:
        given = [k for k in ("orbit", "look_at", "random_orbits", "trajectory")
                 if getattr(self, k) is not None]
        if len(given) > 1:
            raise ValueError(f"give one of 'orbit', 'look_at', 'random_orbits' or 'trajectory', "
                             f"not "
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

    path: FilePath = Field(description="the image file")
    fit: Literal[FITS] = Field(  # type: ignore[valid-type]
        default_of(BackgroundSettings, "fit"), description="cover: fill the frame, crop "
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
    light_transmittance: bool = Field(
        default_of(Fog, "light_transmittance"), description="dim each light by the fog "
        "between it and the lit point (a sun in homogeneous fog or below the horizon is "
        "absorbed); false: only the view ray is attenuated")


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


def _settings_bounds(name: str) -> Any:
    """``Field(ge=, le=)`` of a renderer settings count: the bounds the settings class
    checks (:data:`torchraster.settings.SETTINGS_BOUNDS`; ``true`` is not 1)."""
    lo, hi = SETTINGS_BOUNDS[name]
    return Field(ge=lo, le=hi, strict=True)


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
        default_factory=lambda: list(default_of(BackgroundSettings, "color")),
        description="linear RGB of empty pixels (the environment replaces it when shown)")
    background_image: BackgroundImageConfig | None = Field(
        None, description="an image behind the scene, fitted to the frame (replaces the "
        "colour and the environment as background)")
    dissolve: DissolveConfig | None = Field(
        None, description="the dissolve effect on every surface (cut-outs, alpha_layers "
        "deep, with a glowing edge)")
    supersample: Annotated[int, _settings_bounds("supersample")] = Field(
        default_of(RasterSettings, "supersample"),
        description="render at s x the resolution and box-filter down")
    edge_supersample: Annotated[int, _settings_bounds("edge_supersample")] = Field(
        default_of(RasterSettings, "edge_supersample"),
        description="antialias edges only: the pixels on geometric and shadow edges are "
        "shaded at k x k sub-samples and box-filtered (labels stay exact; 1 = off; not with "
        "supersample > 1, antialias, ssao, ssr, fog, dissolve or MASK / BLEND materials)")
    cull_backfaces: bool = Field(default_of(RasterSettings, "cull_backfaces"),
                                 description="drop back faces of every material")
    texture_filter: Literal[TEXTURE_FILTERS] = Field(  # type: ignore[valid-type]
        default_of(TextureSettings, "filter"), description="anisotropic: up to "
        "max_anisotropy trilinear probes along each pixel's footprint (sharper on steep "
        "surfaces, slower)")
    max_anisotropy: Annotated[int, _settings_bounds("max_anisotropy")] = Field(
        default_of(TextureSettings, "max_anisotropy"), description="the most probes a pixel of "
        "texture_filter: anisotropic (refused with the other filters)")
    alpha_layers: Annotated[int, _settings_bounds("alpha_layers")] = Field(
        default_of(RasterSettings, "alpha_layers"), description="depth layers for MASK / BLEND "
        "materials (what lies behind the nearest K is not seen through them)")
    antialias: bool = Field(default_of(RasterSettings, "antialias"), description="analytic "
                            "antialiasing of silhouette and occlusion edges (gradients at "
                            "edges; the cheapest edge antialiasing, shadow edges as soft as "
                            "the shadow filter)")
    fog: FogConfig | None = Field(None, description="volumetric height fog and light shafts")
    multiscatter: bool = Field(default_of(ShadingSettings, "multiscatter"), description="pbr: "
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
    def _one_supersampling(self) -> RenderConfig:
        if self.edge_supersample > 1 and self.supersample > 1:
            raise ValueError(f"edge_supersample: not combined with supersample "
                             f"{self.supersample} (use one of them)")
        return self

    @model_validator(mode="after")
    def _bounded(self) -> RenderConfig:
        side = max(self.size) * max(self.supersample, self.edge_supersample)
        if side > MAX_SUPERSAMPLED_SIDE:
            raise ValueError(f"supersample x resolution = {side} pixels a side exceeds "
                             f"{MAX_SUPERSAMPLED_SIDE}; lower supersample or resolution")
        return self

    @property
    def size(self) -> tuple[int, int]:
        r = self.resolution
        return (r, r) if isinstance(r, int) else (r[0], r[1])


class EnvironmentShadingConfig(_Strict):
    """How an environment's specular is integrated (the knobs of
    :class:`~torchraster.shading.ibl.Environment`), shared by ``environment`` and
    ``randomize.environment``."""

    specular: Literal[SPECULAR_MODES] = Field(  # type: ignore[valid-type]
        default_of(Environment, "specular"), description="table (default: the GGX lobe "
        "pre-integrated per map, ~1 % mean error at roughness >= 0.3), split_sum (one "
        "prefiltered lookup, fastest), fitted (the chain at the lobe's fitted mean and "
        "spread) or importance (per-pixel filtered importance sampling of the GGX lobe)")
    importance_samples: Annotated[int, Field(ge=1, le=1024)] = Field(
        default_of(Environment, "importance_samples"),
        description="samples a pixel for specular: importance")
    sun_threshold: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = Field(
        None, description="split the map's sun off as a directional light shaded with the "
        "exact GGX BRDF: the texels near the brightest one above this many times the mean "
        "radiance (e.g. 10; none: off). Closer glossy reflections of sunny maps; not with "
        "render.ssr")
    table_levels: Annotated[int, Field(ge=2, le=64, strict=True)] = Field(
        default_of(Environment, "table_levels"), description="specular: table: roughness "
        "levels from 0.3 to 1")
    table_views: Annotated[int, Field(ge=2, le=64, strict=True)] = Field(
        default_of(Environment, "table_views"), description="specular: table: nodes of "
        "acos(n.v)")
    table_azimuths: Annotated[int, Field(ge=2, le=128, strict=True)] = Field(
        default_of(Environment, "table_azimuths"), description="specular: table: nodes of "
        "the normal's azimuth about the reflection (even). The table builds in ~0.5 s a "
        "map and process with the defaults (8, 8, 16); (6, 6, 12) in ~0.3 s at 1.2 % "
        "instead of 1.0 % mean error at roughness 0.6 (docs/benchmarks.md, ibl-specular)")

    @field_validator("table_azimuths")
    @classmethod
    def _even(cls, v: int) -> int:
        if v % 2:
            raise ValueError(f"expected an even number, got {v}")
        return v


class EnvironmentConfig(EnvironmentShadingConfig):
    """An equirectangular HDR environment (``.hdr`` / ``.exr``), relative to the config."""

    path: FilePath
    intensity: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 1.0
    rotation_deg: Finite = 0.0
    background: bool = True


def _shadow_default(name: str) -> Any:
    return default_of(ShadowSettings, name)


def _shadow_bounds(name: str) -> Any:
    """``Field(ge=, le=)`` of a ShadowSettings field: the bounds ShadowSettings checks
    (counts strict: ``true`` is not 1)."""
    lo, hi = SHADOW_BOUNDS[name]
    return Field(ge=lo, le=hi, strict=True) if name in SHADOW_INT_FIELDS else Field(ge=lo, le=hi)


#: Shadow fields that only some filters read.
_FILTER_USES = {
    "hard": set(),
    "pcf": {"pcf_radius", "pcf_taps", "pcf_pattern", "pixel_radius"},
    "pcss": {"pcf_taps", "pcf_pattern", "light_size", "max_penumbra", "pixel_radius"},
    "vsm": {"vsm_blur", "vsm_bleed", "vsm_min_variance"},
}
_FILTER_FIELDS = set().union(*_FILTER_USES.values())


def _users_of(name: str) -> str:
    return ", ".join(f for f, uses in _FILTER_USES.items() if name in uses)


class ShadowConfig(_Strict):
    """Shadow maps of one light (``enabled: true`` is what ``cast_shadows: true`` means).
    Sizes and biases are in shadow-map texels; see docs/design.md, "Shadows"."""

    enabled: bool = True
    map_size: Annotated[int, _shadow_bounds("map_size")] = _shadow_default("map_size")
    filter: Literal[FILTERS] = Field(  # type: ignore[valid-type]
        _shadow_default("filter"), description="hard (1 tap), pcf, pcss (contact-hardening "
        "penumbra from light_size) or vsm (variance shadow maps)")
    pcf_radius: Annotated[float, _shadow_bounds("pcf_radius")] = _shadow_default("pcf_radius")
    pcf_taps: Annotated[int, _shadow_bounds("pcf_taps")] = _shadow_default("pcf_taps")
    pcf_pattern: Literal[PATTERNS] = _shadow_default("pcf_pattern")  # type: ignore[valid-type]
    bias: Annotated[float, _shadow_bounds("bias")] = Field(
        _shadow_default("bias"), description="constant depth bias (texels)")
    slope_bias: Annotated[float, _shadow_bounds("slope_bias")] = Field(
        _shadow_default("slope_bias"), description="slope-scaled depth bias (texels)")
    normal_bias: Annotated[float, _shadow_bounds("normal_bias")] = Field(
        _shadow_default("normal_bias"), description="normal offset of receivers (texels)")
    intensity: Annotated[float, _shadow_bounds("intensity")] = Field(
        _shadow_default("intensity"), description="0 = no darkening, 1 = full")
    cascades: Annotated[int, _shadow_bounds("cascades")] = Field(
        _shadow_default("cascades"), description="cascaded maps (directional lights only)")
    split_lambda: Annotated[float, _shadow_bounds("split_lambda")] = (
        _shadow_default("split_lambda"))
    cascade_blend: Annotated[float, _shadow_bounds("cascade_blend")] = (
        _shadow_default("cascade_blend"))
    max_distance: Positive | None = Field(
        _shadow_default("max_distance"), description="directional: cascades end at this "
        "camera depth (m); default the farthest scene point")
    light_size: Annotated[float, _shadow_bounds("light_size")] = Field(
        _shadow_default("light_size"), description="pcss: radius (m) of point / spot lights, "
        "angular diameter (degrees) of directional lights")
    max_penumbra: Annotated[float, _shadow_bounds("max_penumbra")] = (
        _shadow_default("max_penumbra"))
    vsm_blur: Annotated[float, _shadow_bounds("vsm_blur")] = _shadow_default("vsm_blur")
    vsm_bleed: Annotated[float, _shadow_bounds("vsm_bleed")] = _shadow_default("vsm_bleed")
    vsm_min_variance: Annotated[float, _shadow_bounds("vsm_min_variance")] = (
        _shadow_default("vsm_min_variance"))
    pixel_radius: Annotated[float, _shadow_bounds("pixel_radius")] = Field(
        _shadow_default("pixel_radius"), description="pcf / pcss: the filter also spans this "
        "many pixels of the frame at each receiver (0.56: shadow edges about as soft as "
        "averaging over the pixel; 0 = off)")

    @model_validator(mode="after")
    def _used_by_filter(self) -> ShadowConfig:
        unused = sorted(self.model_fields_set & (_FILTER_FIELDS - _FILTER_USES[self.filter]))
        if unused:
            raise ValueError(f"{', '.join(unused)}: not used by filter {self.filter!r} (used "
                             f"by: {_users_of(unused[0])}); remove it or change the filter")
        return self


class AreaShadowConfig(ShadowConfig):
    """Shadow maps of an area light: a cube map from its centre, filtered with PCSS of 16
    taps by default; the PCSS light size is the light's own (``light_size`` is refused)."""

    filter: Literal[FILTERS] = Field(  # type: ignore[valid-type]
        "pcss", description="pcss (default: a penumbra from the light's own size), hard, pcf "
        "or vsm")
    pcf_taps: Annotated[int, _shadow_bounds("pcf_taps")] = Field(
        AREA_SHADOW_TAPS, description="taps of pcf / pcss (wide penumbrae need many)")


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


def _refuse_cascades(light: Any) -> None:
    """Cascade keys in the ``shadows`` block of a light that is not directional."""
    cascade_keys = {"cascades", "max_distance", "split_lambda", "cascade_blend"}
    if light.shadows is not None and light.shadows.model_fields_set & cascade_keys:
        raise ValueError(f"shadows.{sorted(light.shadows.model_fields_set & cascade_keys)[0]}:"
                         " cascades are for directional lights only")


def _check_shadow_switch(light: Any) -> Any:
    if light.cast_shadows is not None and light.shadows is not None and (
            light.cast_shadows != light.shadows.enabled):
        raise ValueError(f"cast_shadows: {str(light.cast_shadows).lower()} contradicts "
                         f"shadows.enabled: {str(light.shadows.enabled).lower()}; give one")
    return light


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
        _refuse_cascades(self)
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


class AreaLightConfig(_DirectionMixin, _LightConfigBase):
    """Area light centred at ``position``, emitting towards ``direction`` (default -Z): a
    rectangle ``size: [width, height]`` (m; default 1 x 1) or a disc ``radius`` (m);
    ``intensity`` is its luminance in nits (cd/m^2); ``up`` orients the height side
    (default +Y, or +Z for a light facing along Y); ``two_sided`` emits on both sides.
    Shadows: a cube map from the centre filtered with PCSS of the light's size."""

    type: Literal["area"]
    shape: Literal["rect", "disc"] = "rect"
    position: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    direction: Vec3 = Field(default_factory=lambda: list(DEFAULT_DIRECTION))
    size: Annotated[list[Positive], Field(min_length=2, max_length=2)] | None = Field(
        None, description="rect: [width, height] (m), default [1, 1]")
    radius: Positive | None = Field(None, description="disc: radius (m), default 0.5")
    up: Vec3 | None = None
    two_sided: bool = False
    cast_shadows: bool | None = Field(None, description="true: shadows with default settings "
                                      "(same as `shadows: {}`)")
    shadows: AreaShadowConfig | None = None

    @model_validator(mode="after")
    def _shape(self) -> AreaLightConfig:
        if self.shape == "rect" and self.radius is not None:
            raise ValueError("radius: is for shape: disc; a rect takes size: [width, height]")
        if self.shape == "disc" and self.size is not None:
            raise ValueError("size: is for shape: rect; a disc takes radius")
        if self.up is not None:
            d, u = self.direction, self.up
            cross = [d[1] * u[2] - d[2] * u[1], d[2] * u[0] - d[0] * u[2],
                     d[0] * u[1] - d[1] * u[0]]
            if sum(c * c for c in cross) <= 1e-12 * sum(x * x for x in d) * sum(
                    x * x for x in u):
                raise ValueError("up: must not be zero or parallel to direction")
        _refuse_cascades(self)
        if self.shadows is not None and "light_size" in self.shadows.model_fields_set:
            raise ValueError("shadows.light_size: an area light's PCSS light size is its own "
                             "(the radius of the disc of its area)")
        return _check_shadow_switch(self)


LightConfig = Annotated[
    AmbientLightConfig | DirectionalLightConfig | PointLightConfig | SpotLightConfig
    | AreaLightConfig,
    Field(discriminator="type"),
]
_LIGHT_LIST = TypeAdapter(list[LightConfig])


def parse_lights(data: object) -> list:
    """Validate a YAML/JSON list of light dicts into :data:`LightConfig` models.

    Raises ``pydantic.ValidationError`` whose messages carry the key path (e.g. ``1.spot.range``).
    """
    return _LIGHT_LIST.validate_python(data)


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
    """The ``post:`` section of a render config. Leaving ``post:`` out means no tone
    mapping: the linear image is clipped to [0, 1] and sRGB encoded. Giving it, even as
    ``post: {}``, runs every stage at its default below (exposure, ACES tone mapping,
    sRGB encoding)."""

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
    base_color_texture: FilePath | None = Field(
        None, description="image file (sRGB), relative to the config file")


Channel = Literal["color", "radiance", "alpha", "depth", "position", "normal", "albedo", "metallic",
                  "roughness", "ao", "emissive", "face_id", "uv", "instance", "semantic",
                  "object_coords", "distance", "amodal", "flow_forward", "flow_backward",
                  "flow_forward_valid", "flow_backward_valid", "motion"]
#: Channels that need another frame.
FLOW_CHANNELS = {"flow_forward", "flow_backward", "flow_forward_valid", "flow_backward_valid",
                 "motion"}
Export = Literal["coco", "bop", "nerf", "webdataset", "tracks"]


class OutputConfig(_Strict):
    """What to write: channels and file formats (exr needs the optional OpenEXR package).

    ``color`` is the display image (post chain applied, tone mapped, sRGB encoded, in [0, 1]);
    ``radiance`` is linear HDR (post chain up to, not including, tone mapping). Float
    formats (npy, exr) hold the raw values; png a display encoding (see the README table).
    """

    channels: list[Channel] = Field(default_factory=lambda: ["color", "depth", "normal"])
    formats: list[Literal["png", "npy", "exr"]] = Field(default_factory=lambda: ["png"])
    exports: list[Export] = Field(
        default_factory=list, description="dataset files written next to the manifest after a "
        "run (`exports/<format>/`): COCO instances (needs `instance`), BOP (needs `instance`, "
        "`amodal`, `depth`), NeRF transforms.json, WebDataset shards, point tracks (needs "
        "`instance`, `object_coords`, `depth` as npy)")
    previews: bool = Field(False, description="also write `instance_preview.png` / "
                           "`semantic_preview.png`: ids in distinct colours")
    png_compression: Annotated[int, Field(ge=0, le=9)] = Field(
        1, description="zlib level of the PNGs (0 none .. 9 smallest; lossless at every "
        "level): 1 writes a labelled 256² view's files in ~55 % of level 6's time for ~35 % "
        "more PNG bytes (docs/benchmarks.md, dataset-png)")
    track_points: Annotated[int, Field(ge=1, le=1_000_000)] = Field(
        256, description="query points per video of the `tracks` export (TAP-Vid style: "
        "drawn among the first frame's covered pixels)")


class DistConfig(_Strict):
    """A random value: exactly one of ``uniform: [low, high]``, ``loguniform: [low, high]``
    (low > 0), ``normal: [mean, std]`` (each bound a number or a list per component) or
    ``choice: [options]`` (with optional ``weights``). Drawn per scene variant from the seed
    of ``randomize`` and recorded in the manifest."""

    uniform: Annotated[list[Finite | list[Finite]], Field(min_length=2, max_length=2)] | None = None
    loguniform: Annotated[list[Finite | list[Finite]], Field(min_length=2,
                                                             max_length=2)] | None = None
    normal: Annotated[list[Finite | list[Finite]], Field(min_length=2, max_length=2)] | None = None
    choice: Annotated[list[Any], Field(min_length=1)] | None = None
    weights: list[NonNeg] | None = None

    @model_validator(mode="after")
    def _one(self) -> DistConfig:
        given = [k for k in ("uniform", "loguniform", "normal", "choice")
                 if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError("give exactly one of uniform, loguniform, normal or choice, got "
                             f"{given or 'none'}")
        if self.weights is not None and self.choice is None:
            raise ValueError("weights go with choice")
        if self.weights is not None and len(self.weights) != len(self.choice):
            raise ValueError(f"weights: expected {len(self.choice)} (one per choice), got "
                             f"{len(self.weights)}")
        return self


#: A constant or a distribution.
Random = Finite | list[Finite] | DistConfig
RandomCount = Annotated[int, Field(ge=0, le=MAX_INSTANCES)] | DistConfig


class PoolEntryConfig(_Strict):
    """One kind of object random scenes draw from: a mesh file or a primitive."""

    mesh: FilePath | None = None
    primitive: Literal["box", "sphere"] | None = None
    size: Positive = 1.0
    category: str | None = None
    weight: NonNeg = Field(1.0, description="relative chance of being drawn")

    @model_validator(mode="after")
    def _one_source(self) -> PoolEntryConfig:
        if (self.mesh is None) == (self.primitive is None):
            raise ValueError("give exactly one of 'mesh' (a file) or 'primitive' (box, sphere)")
        return self


class RandomObjectsConfig(_Strict):
    """``count`` objects drawn from ``pool``, placed on the floor ``y = floor_y`` inside
    ``bounds`` without overlapping (bounding circles), resting on it, with a random yaw; each
    drawn value is recorded. ``velocity`` (m/s) and ``spin_deg_per_s`` (about +y) move them
    over the frames (straight lines: no collisions)."""

    count: RandomCount = 8
    pool: Annotated[list[PoolEntryConfig], Field(min_length=1)]
    scale: Random = 1.0
    bounds: Annotated[list[Finite], Field(min_length=4, max_length=4)] = Field(
        default_factory=lambda: [-2.0, -2.0, 2.0, 2.0], description="[x0, z0, x1, z1]")
    floor_y: Finite = 0.0
    gap: NonNeg = 0.0
    max_tries: Annotated[int, Field(ge=1, le=1_000_000)] = 1000
    base_color: Random | None = Field(None, description="RGB in [0, 1] (clipped)")
    roughness: Random | None = None
    metallic: Random | None = None
    textures: FilePath | None = Field(None, description="a folder of images: each object's "
                                      "base colour texture drawn from it")
    velocity: Random | None = Field(None, description="[vx, vy, vz] m/s")
    spin_deg_per_s: Random | None = None

    @field_validator("bounds")
    @classmethod
    def _ordered_bounds(cls, v: list[float]) -> list[float]:
        if v[0] >= v[2] or v[1] >= v[3]:
            raise ValueError(f"expected [x0, z0, x1, z1] with x0 < x1 and z0 < z1, got {v}")
        return v


class RandomLightsConfig(_Strict):
    """``count`` directional lights from random directions (``azimuth_deg`` about +y from
    +z, ``elevation_deg`` above the horizon) added to ``lights:``."""

    count: RandomCount = 1
    azimuth_deg: Random = Field(default_factory=lambda: DistConfig(uniform=[0.0, 360.0]))
    elevation_deg: Random = Field(default_factory=lambda: DistConfig(uniform=[20.0, 70.0]))
    intensity: Random = 3.0
    color: Random = Field(default_factory=lambda: [1.0, 1.0, 1.0])
    shadows: ShadowConfig | None = None


class RandomEnvironmentConfig(EnvironmentShadingConfig):
    """An environment map drawn from ``paths`` (files, or folders of .hdr / .exr); the
    specular knobs apply to every map drawn."""

    paths: Annotated[list[FilePath], Field(min_length=1)]
    rotation_deg: Random = Field(default_factory=lambda: DistConfig(uniform=[0.0, 360.0]))
    intensity: Random = 1.0
    background: bool = True


class RandomCameraConfig(_Strict):
    """Random values replacing the ``orbit`` fields of every orbit camera."""

    azimuth_deg: Random | None = None
    elevation_deg: Random | None = None
    distance: Random | None = None
    target: Random | None = None
    fov_deg: Random | None = None


class RandomizeConfig(_Strict):
    """Domain randomisation: ``scenes`` variants of the config, each with its own draws
    (objects, lights, environment, cameras, background image) from ``seed``. A variant is an
    object of the config: views are variants x cameras x frames, written to
    ``<variant>/<camera>/...``; the same seed gives the same dataset on any number of
    ranks, and each record holds its variant's draws."""

    seed: Annotated[int, Field(ge=0)] = 0
    scenes: Annotated[int, Field(ge=1, le=MAX_RANDOM_VIEWS)] = 1
    objects: RandomObjectsConfig | None = None
    lights: RandomLightsConfig | None = None
    environment: RandomEnvironmentConfig | None = None
    camera: RandomCameraConfig | None = None
    background_images: FilePath | None = Field(None, description="a folder of images: the "
                                               "background image drawn from it")


class FramesConfig(_Strict):
    """Time: every camera renders ``count`` frames, frame i at time i / ``fps`` seconds."""

    count: Annotated[int, Field(ge=1, le=MAX_FRAMES)] = 1
    fps: Annotated[float, Field(gt=0, le=10_000, allow_inf_nan=False)] = 24.0


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
    categories: list[str] | None = Field(
        None, description="class names; category id i + 1 is categories[i] (0 = background). "
        "Without it, ids follow the order in which objects name their category")
    frames: FramesConfig = Field(default_factory=FramesConfig)
    randomize: RandomizeConfig | None = None

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

    @model_validator(mode="after")
    def _pbr_needs_light(self) -> RenderFile:
        rz = self.randomize
        drawn = rz is not None and (rz.lights is not None or rz.environment is not None)
        lit = bool(self.lights) or self.environment is not None or drawn
        if self.render.shading is None:
            self.render.shading = "toon" if self.render.toon is not None else (
                "pbr" if lit else "headlight")
        elif self.render.shading not in LIT_MODELS and self.lights:
            raise ValueError(f"render.shading {self.render.shading!r} ignores 'lights:'; remove "
                             "them, or use shading: pbr (the default when lights are given) or "
                             "another lit model (blinn_phong, half_lambert, toon)")
        if self.render.shading in LIT_MODELS and not lit:
            raise ValueError(f"render.shading {self.render.shading!r} needs light: add a "
                             "'lights:' entry or an 'environment:', or use shading: "
                             "headlight / unlit")
        return self

    def where(self, *loc: str | int) -> str:
        """``file:line: key.path`` of a key path (the nearest line found)."""
        line = line_of(self._lines, loc)
        key = ".".join(str(p) for p in loc)
        return f"{self._source}:{line}: {key}" if line else f"{self._source}: {key}"

    def resolve(self, relative: str) -> Path:
        """A path resolved against the config file's folder (the config's own path fields
        are absolute already, resolved when it was validated)."""
        p = Path(relative).expanduser()
        return p if p.is_absolute() else (self.base_dir / p).resolve()
