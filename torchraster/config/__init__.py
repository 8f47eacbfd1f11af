"""YAML render configs: the schema, reading and checking them, their views, and the builders
of the objects they name.

The config layer is the only place that knows YAML. A config names a scene (mesh or glTF
file, relative to the config file), cameras, render settings, lights, an optional
environment map, material overrides, post-processing and outputs; the full reference is
``docs/config.md`` (``torchraster schema`` prints it). One module per concept:

- :mod:`~torchraster.config.schema`: the pydantic models (one per section), their bounds
  and defaults; path fields become absolute when validated.
- :mod:`~torchraster.config.source`: YAML text to a validated :class:`RenderFile`
  (:func:`load_config`, :func:`parse_config`); every error names the file, the line and the
  key path, e.g. ``quickstart.yaml:7: cameras.0.fov_deg: Input should be less than 180``.
- :mod:`~torchraster.config.views`: camera and view names, mesh sets, seeded cameras.
- :mod:`~torchraster.config.check`: :func:`check_config` finds every missing file and
  degenerate camera in one pass before anything renders.
- :mod:`~torchraster.config.build`: every builder (scene, cameras, lights, environment,
  renderer, post chain, fog, dissolve, shadow settings).
- :mod:`~torchraster.config.reference`: the Markdown reference of the schema.

Example (``configs/quickstart.yaml``)::

    scene:
      mesh: ../torchraster/assets/spot/spot_triangulated.obj
    cameras:
      - orbit: {azimuth_deg: 30, elevation_deg: 15}
    render:
      resolution: [512, 512]    # [H, W], or one int for a square image
"""

from .build import (
    RenderSetup,
    build_camera,
    build_dissolve,
    build_environment,
    build_fog,
    build_post,
    build_post_chain,
    build_renderer,
    build_setup,
    build_shadow_settings,
    build_ssao,
    build_ssr,
    lights_from_config,
)
from .check import check_config
from .objects import SceneObjects, build_objects, build_scene
from .reference import config_reference
from .schema import (
    MAX_BLOOM_LEVELS,
    MAX_DOF_LEVELS,
    MAX_RANDOM_VIEWS,
    MAX_RESOLUTION,
    MAX_SSAO_SAMPLES,
    MAX_SSR_STEPS,
    MAX_SUPERSAMPLED_SIDE,
    AmbientLightConfig,
    AnimationConfig,
    AreaLightConfig,
    AutoExposureConfig,
    BackgroundImageConfig,
    BloomConfig,
    CameraConfig,
    Channel,
    ConfigError,
    ConfigPath,
    DirectionalLightConfig,
    DissolveConfig,
    DOFConfig,
    EncodeConfig,
    EnvironmentConfig,
    ExposureConfig,
    FilePath,
    FogConfig,
    FramesConfig,
    IntrinsicsConfig,
    KeyframeConfig,
    LightConfig,
    LookAtConfig,
    MaterialOverride,
    ObjectConfig,
    ObjectMaterialConfig,
    OrbitConfig,
    OutputConfig,
    PointLightConfig,
    PostConfig,
    RandomOrbitsConfig,
    RenderConfig,
    RenderFile,
    SceneConfig,
    ShadowConfig,
    SpotLightConfig,
    SSAOConfig,
    SSRConfig,
    ToneMapConfig,
    ToonConfig,
    TrajectoryConfig,
    TransformConfig,
    default_of,
    parse_lights,
    resolve_path,
    written,
)
from .source import MAX_YAML_NODES, load_config, parse_config
from .variants import Variant, scene_variants
from .views import (
    MeshSetEntry,
    PlannedCamera,
    camera_names,
    expand_cameras,
    is_mesh_set,
    mesh_set,
    object_config,
    object_name,
    safe_name,
    stable_seed,
    view_names,
)

__all__ = [
    "AmbientLightConfig", "AutoExposureConfig", "BackgroundImageConfig", "BloomConfig",
    "AnimationConfig", "build_camera", "build_dissolve", "build_objects", "FramesConfig",
    "KeyframeConfig", "SceneObjects", "TrajectoryConfig", "Variant", "scene_variants",
    "build_environment", "build_fog",
    "build_post",
    "build_post_chain", "build_renderer", "build_scene", "build_setup",
    "build_shadow_settings", "build_ssao", "build_ssr", "camera_names", "CameraConfig",
    "Channel", "check_config", "config_reference", "ConfigError", "ConfigPath", "default_of",
    "DirectionalLightConfig", "DissolveConfig", "DOFConfig", "EncodeConfig",
    "AreaLightConfig", "EnvironmentConfig", "expand_cameras", "ExposureConfig", "FilePath",
    "FogConfig",
    "IntrinsicsConfig", "is_mesh_set", "LightConfig", "lights_from_config", "load_config",
    "LookAtConfig", "MaterialOverride", "MAX_BLOOM_LEVELS", "MAX_DOF_LEVELS",
    "MAX_RANDOM_VIEWS", "MAX_RESOLUTION", "MAX_SSAO_SAMPLES", "MAX_SSR_STEPS",
    "MAX_SUPERSAMPLED_SIDE", "MAX_YAML_NODES", "mesh_set", "MeshSetEntry", "object_config",
    "object_name", "ObjectConfig", "ObjectMaterialConfig", "OrbitConfig", "OutputConfig",
    "parse_config", "parse_lights", "PlannedCamera", "PointLightConfig", "PostConfig",
    "RandomOrbitsConfig", "RenderConfig", "RenderFile", "RenderSetup", "resolve_path",
    "safe_name", "SceneConfig", "ShadowConfig", "SpotLightConfig", "SSAOConfig", "SSRConfig",
    "stable_seed", "ToneMapConfig", "ToonConfig", "TransformConfig", "view_names", "written",
]
