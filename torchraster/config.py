"""YAML render configs: schema, defaults and validation with key paths and line numbers.

A config names a scene (mesh or glTF file, relative to the config file), one or more
cameras, render settings, lights, an optional environment map, material overrides,
post-processing and outputs. Unknown keys are errors. Every error names the file, the line
and the key path, e.g. ``quickstart.yaml:7: cameras.0.fov_deg: Input should be less than 180``.

Example (``configs/quickstart.yaml``)::

    scene:
      mesh: ../torchraster/assets/spot/spot_triangulated.obj
    cameras:
      - orbit: {azimuth_deg: 30, elevation_deg: 15}
    render:
      resolution: [512, 512]
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .post.chain import PostConfig
from .shading.lights import LightConfig

Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Vec3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]
Color3 = Annotated[list[Annotated[float, Field(ge=0, allow_inf_nan=False)]],
                   Field(min_length=3, max_length=3)]


class ConfigError(ValueError):
    """A render config is invalid; the message names the file, line and key path."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class TransformConfig(_Strict):
    """Model -> world transform: scale, then rotation (XYZ Euler degrees), then translation."""

    translate: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    rotate_deg: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    scale: Positive | Annotated[list[Positive], Field(min_length=3, max_length=3)] = 1.0


class SceneConfig(_Strict):
    """The geometry: a mesh or glTF scene file, relative to the config file."""

    mesh: str
    transform: TransformConfig = Field(default_factory=TransformConfig)
    normals: Literal["auto", "smooth", "flat"] = "auto"
    max_texture_size: Annotated[int, Field(ge=1)] | None = 2048


class OrbitConfig(_Strict):
    """Camera on a sphere around ``target`` (default: the scene's centre); ``distance``
    None frames the scene's bounding sphere."""

    azimuth_deg: Finite = 0.0
    elevation_deg: Annotated[float, Field(gt=-90, lt=90)] = 0.0
    distance: Positive | None = None
    target: Vec3 | None = None


class LookAtConfig(_Strict):
    eye: Vec3
    target: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    up: Vec3 = Field(default_factory=lambda: [0.0, 1.0, 0.0])


class IntrinsicsConfig(_Strict):
    """Pinhole intrinsics in pixels (OpenCV convention), for the render resolution."""

    fx: Positive
    fy: Positive
    cx: Finite
    cy: Finite


class CameraConfig(_Strict):
    """One view. Exactly one of ``orbit`` / ``look_at`` places it (default: orbit)."""

    name: str | None = None
    projection: Literal["perspective", "orthographic"] = "perspective"
    fov_deg: Annotated[float, Field(gt=0, lt=180)] = 45.0
    intrinsics: IntrinsicsConfig | None = None
    ortho_height: Positive | None = None
    near: Positive | None = None
    far: Positive | None = None
    reverse_z: bool = False
    orbit: OrbitConfig | None = None
    look_at: LookAtConfig | None = None

    @model_validator(mode="after")
    def _one_placement(self) -> CameraConfig:
        if self.orbit is not None and self.look_at is not None:
            raise ValueError("give either 'orbit' or 'look_at', not both")
        if self.orbit is None and self.look_at is None:
            self.orbit = OrbitConfig()
        if self.near is not None and self.far is not None and self.far <= self.near:
            raise ValueError(f"far ({self.far}) must be greater than near ({self.near})")
        return self


class RenderConfig(_Strict):
    resolution: Annotated[int, Field(ge=1, le=16384)] | Annotated[
        list[Annotated[int, Field(ge=1, le=16384)]], Field(min_length=2, max_length=2)] = 512
    shading: Literal["headlight", "pbr", "unlit"] = "headlight"
    background: Color3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    supersample: Annotated[int, Field(ge=1, le=8)] = 1
    cull_backfaces: bool = False

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


class MaterialOverride(_Strict):
    """Overrides for the materials whose name matches ``match`` ('*' = all)."""

    match: str = "*"
    base_color: Annotated[list[Annotated[float, Field(ge=0, le=1)]],
                          Field(min_length=3, max_length=4)] | None = None
    metallic: Annotated[float, Field(ge=0, le=1)] | None = None
    roughness: Annotated[float, Field(ge=0, le=1)] | None = None
    emissive: Color3 | None = None
    base_color_texture: str | None = None  # image file (sRGB), relative to the config


Channel = Literal["color", "alpha", "depth", "position", "normal", "albedo", "metallic",
                  "roughness", "ao", "emissive", "face_id", "uv"]


class OutputConfig(_Strict):
    """What to write: channels and file formats (exr needs the optional OpenEXR package)."""

    channels: list[Channel] = Field(default_factory=lambda: ["color", "depth", "normal"])
    formats: list[Literal["png", "npy", "exr"]] = Field(default_factory=lambda: ["png"])


class RenderFile(_Strict):
    """A whole render config file."""

    scene: SceneConfig
    cameras: Annotated[list[CameraConfig], Field(min_length=1)] = Field(
        default_factory=lambda: [CameraConfig()])
    render: RenderConfig = Field(default_factory=RenderConfig)
    lights: list[LightConfig] = Field(default_factory=list)
    environment: EnvironmentConfig | None = None
    materials: list[MaterialOverride] = Field(default_factory=list)
    post: PostConfig | None = None
    outputs: OutputConfig = Field(default_factory=OutputConfig)

    # Set by load_config: the folder relative paths are resolved against.
    base_dir: Path = Field(default=Path("."), exclude=True)

    def resolve(self, relative: str) -> Path:
        """A path from the config, resolved against the config file's folder."""
        p = Path(relative).expanduser()
        return p if p.is_absolute() else (self.base_dir / p).resolve()


def _key_lines(node: yaml.Node, path: tuple = (), out: dict | None = None) -> dict:
    """Map every key path in a composed YAML node tree to its 1-based line number."""
    out = {} if out is None else out
    out[path] = node.start_mark.line + 1
    if isinstance(node, yaml.MappingNode):
        for key, value in node.value:
            out[path + (key.value,)] = key.start_mark.line + 1
            _key_lines(value, path + (key.value,), out)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _key_lines(item, path + (i,), out)
    return out


def _line_of(lines: dict, loc: tuple) -> int | None:
    """Line of the longest prefix of ``loc`` found in the YAML (pydantic adds union tags)."""
    loc = tuple(int(p) if isinstance(p, str) and p.isdigit() else p for p in loc)
    for n in range(len(loc), -1, -1):
        cand = tuple(p for p in loc[:n])
        if cand in lines:
            return lines[cand]
        # discriminated unions insert the tag ('point') into the location: skip it
        stripped = tuple(p for p in cand if p not in ("ambient", "directional", "point", "spot"))
        if stripped in lines:
            return lines[stripped]
    return None


def parse_config(text: str, source: str = "<string>", base_dir: Path | None = None) -> RenderFile:
    """Validate YAML text into a :class:`RenderFile`; raises :class:`ConfigError`."""
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
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
            msgs.append(f"{where}: {key}: {err['msg']}")
        raise ConfigError("invalid render config\n  " + "\n  ".join(msgs)) from None
    cfg.base_dir = base_dir if base_dir is not None else Path(".")
    return cfg


def load_config(path: str | Path) -> RenderFile:
    """Read and validate a YAML render config; relative paths resolve against its folder."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as e:
        raise ConfigError(f"{p}: cannot read the config file ({e.strerror})") from None
    return parse_config(text, source=str(p), base_dir=p.resolve().parent)


__all__ = ["ConfigError", "RenderFile", "load_config", "parse_config"]
