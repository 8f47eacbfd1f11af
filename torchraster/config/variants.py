"""Domain randomisation: a config with ``randomize:`` becomes ``scenes`` concrete configs.

Each variant ``scene_<i:04d>`` draws its values (objects from the pool with their sizes,
placements, materials and motion; lights; environment; orbit cameras; background image)
from its own generator, :func:`torchraster.randomize.rng_for` of (``randomize.seed``, the
dataset seed, ``i``, the aspect drawn): the same on every rank and in any order, and adding
scenes never changes the existing ones. The drawn values are written into the variant's
config as ordinary fields (objects with a ``transform`` and an ``animation``, lights,
``environment``, ...), so a variant renders like any config, its hash covers its draws,
and :attr:`Variant.drawn` (recorded in the manifest) is enough to re-render any view alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..randomize import Choice, LogUniform, Normal, Uniform, files_in, place_on_floor, rng_for
from ..randomize import sample as draw_value
from .schema import (
    AnimationConfig,
    CameraConfig,
    ConfigError,
    DirectionalLightConfig,
    DistConfig,
    EnvironmentConfig,
    EnvironmentShadingConfig,
    KeyframeConfig,
    ObjectConfig,
    RandomObjectsConfig,
    RenderFile,
    TransformConfig,
    resolve_path,
)

#: Whole placements tried before a randomised scene is given up (each up to ``max_tries``
#: draws per object).
PLACEMENT_RESTARTS: int = 10
#: Environment map suffixes found in a folder of ``randomize.environment.paths``.
HDR_SUFFIXES = (".hdr", ".exr")


@dataclass
class Variant:
    """One concrete scene of a randomised config.

    Attributes:
        name: ``scene_<i:04d>``.
        config: the config with every draw written in (no ``randomize`` left).
        drawn: the draws, JSON-ready (the manifest's ``randomized`` record field).
    """

    name: str
    config: RenderFile = field(repr=False)
    drawn: dict = field(default_factory=dict)


def _spec(value: object) -> object:
    """A constant, or the :mod:`torchraster.randomize` distribution of a DistConfig."""
    if not isinstance(value, DistConfig):
        return value
    if value.uniform is not None:
        return Uniform(*value.uniform)
    if value.loguniform is not None:
        return LogUniform(*value.loguniform)
    if value.normal is not None:
        return Normal(*value.normal)
    return Choice(value.choice, value.weights)


def draw(value: object, rng: np.random.Generator) -> object:
    """One value of a config field that may be random (see :class:`DistConfig`)."""
    return draw_value(_spec(value), rng)


def _count(value: object, rng: np.random.Generator, where: str) -> int:
    n = draw(value, rng)
    if isinstance(n, list) or not isinstance(n, int | float) or not math.isfinite(n):
        raise ConfigError(f"{where}: expected a count, drew {n!r}")
    return max(0, int(round(n)))


def _vec3(value: object, where: str) -> list[float]:
    v = value if isinstance(value, list) else [value] * 3
    if len(v) != 3:
        raise ConfigError(f"{where}: expected 3 values, drew {value!r}")
    return [float(x) for x in v]


@lru_cache(maxsize=64)
def _mesh_footprint(path: str) -> tuple[float, float, float]:
    """(radius about the y axis in the floor plane, min y, max y) of a mesh file at scale 1."""
    import trimesh

    mesh = trimesh.load(path, force="mesh", process=False)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    return float(np.hypot(v[:, 0], v[:, 2]).max()), float(v[:, 1].min()), float(v[:, 1].max())


def _footprint(entry: object) -> tuple[float, float]:
    """(radius, min y) of a pool entry at scale 1 (see ``place_on_floor``)."""
    if entry.mesh is not None:
        r, lo, _ = _mesh_footprint(str(entry.mesh))
        return r, lo
    s = float(entry.size)
    return (s * math.sqrt(0.5), -s / 2) if entry.primitive == "box" else (s / 2, -s / 2)


def scene_variants(cfg: RenderFile, seed: int = 0) -> list[Variant]:
    """The concrete configs of a randomised config (``[]`` without ``randomize``).

    Args:
        cfg: a validated config.
        seed: the dataset seed (``RenderDataset(seed=...)``; 0 on the command line).

    Raises:
        ConfigError: naming the key when a draw cannot be used (a placement that does not
            fit, an empty folder, ...).
    """
    rz = cfg.randomize
    if rz is None:
        return []
    return [_variant(cfg, seed, i) for i in range(rz.scenes)]


def _variant(cfg: RenderFile, seed: int, index: int) -> Variant:
    rz = cfg.randomize
    name = f"scene_{index:04d}"

    def rng(aspect: str) -> np.random.Generator:
        return rng_for(rz.seed, seed, index, aspect)

    drawn: dict = {"scene": name, "index": index}
    update: dict = {"randomize": None}
    scene = cfg.scene
    if rz.objects is not None:
        objects, drawn["objects"] = _objects(cfg, rz.objects, rng("objects"))
        scene = scene.model_copy(update={"objects": list(scene.objects) + objects})
        update["scene"] = scene
    if rz.lights is not None:
        lights, drawn["lights"] = _lights(rz.lights, rng("lights"), cfg)
        update["lights"] = list(cfg.lights) + lights
    if rz.environment is not None:
        env = rz.environment
        g = rng("environment")
        files = _environment_files(cfg, env.paths)
        path = draw(Choice([str(p) for p in files]), g)
        rotation, intensity = draw(env.rotation_deg, g), draw(env.intensity, g)
        shading = {k: getattr(env, k) for k in EnvironmentShadingConfig.model_fields}
        update["environment"] = EnvironmentConfig(
            path=resolve_path(path, cfg.base_dir), rotation_deg=float(rotation),
            intensity=max(0.0, float(intensity)), background=env.background, **shading)
        drawn["environment"] = {"path": path, "rotation_deg": rotation, "intensity": intensity}
    if rz.camera is not None:
        cams, drawn["cameras"] = _cameras(cfg, rng("camera"))
        update["cameras"] = cams
    if rz.background_images is not None:
        files = _folder(cfg, ("randomize", "background_images"), rz.background_images)
        path = draw(Choice([str(p) for p in files]), rng("background"))
        image = cfg.render.background_image
        fit = {} if image is None else {"fit": image.fit}
        from .schema import BackgroundImageConfig

        update["render"] = cfg.render.model_copy(update={"background_image": BackgroundImageConfig(
            path=resolve_path(path, cfg.base_dir), **fit)})
        drawn["background_image"] = path
    out = cfg.model_copy(update=update)
    out._base_dir, out._source, out._lines = cfg._base_dir, cfg._source, cfg._lines
    return Variant(name, out, drawn)


def _folder(cfg: RenderFile, loc: tuple, folder: str, suffixes: tuple = ()) -> list[Path]:
    try:  # strict: a file that is not an image in an image folder is a mistake, not noise
        return (files_in(folder, suffixes, strict=True) if suffixes
                else files_in(folder, strict=True))
    except (OSError, ValueError) as e:
        raise ConfigError(f"{cfg.where(*loc)}: {e}") from None


def _environment_files(cfg: RenderFile, paths: list[str]) -> list[Path]:
    files: list[Path] = []
    for i, p in enumerate(paths):
        path = Path(p)
        if path.is_dir():
            files += _folder(cfg, ("randomize", "environment", "paths", i), p, HDR_SUFFIXES)
        elif path.is_file():
            files.append(path)
        else:
            raise ConfigError(f"{cfg.where('randomize', 'environment', 'paths', i)}: file "
                              f"not found: {p}")
    return files


def _objects(cfg: RenderFile, ro: RandomObjectsConfig, g: np.random.Generator
             ) -> tuple[list[ObjectConfig], list[dict]]:
    """Objects drawn from the pool, placed, coloured and set in motion."""
    where = cfg.where("randomize", "objects")
    n = _count(ro.count, g, f"{where}.count")
    weights = [e.weight for e in ro.pool]
    if not sum(weights) > 0:
        raise ConfigError(f"{where}.pool: every weight is 0")
    kinds = [int(draw(Choice(list(range(len(ro.pool))), weights), g)) for _ in range(n)]
    scales = [float(draw(ro.scale, g)) for _ in range(n)]
    if any(not s > 0 for s in scales):
        raise ConfigError(f"{where}.scale: drew a scale <= 0 ({min(scales)})")
    foot = [_footprint(ro.pool[k]) for k in kinds]
    radii = [r * s for (r, _), s in zip(foot, scales, strict=True)]
    min_y = [lo * s for (_, lo), s in zip(foot, scales, strict=True)]
    for attempt in range(PLACEMENT_RESTARTS):  # sequential placement can paint itself in
        try:
            positions, yaws = place_on_floor(radii, min_y, ro.bounds, ro.floor_y, g,
                                             max_tries=ro.max_tries, gap=ro.gap)
            break
        except ValueError as e:
            if attempt == PLACEMENT_RESTARTS - 1:
                raise ConfigError(f"{where}: {e} (after {PLACEMENT_RESTARTS} restarts)"
                                  ) from None
    textures = (_folder(cfg, ("randomize", "objects", "textures"), ro.textures)
                if ro.textures is not None else None)
    duration = max(cfg.frames.count - 1, 1) / cfg.frames.fps
    objects, records = [], []
    for i, k in enumerate(kinds):
        entry = ro.pool[k]
        rec: dict = {"pool": k, "scale": scales[i], "position": positions[i], "yaw_deg": yaws[i]}
        material: dict = {}
        for key in ("base_color", "roughness", "metallic"):
            value = getattr(ro, key)
            if value is not None:
                v = draw(value, g)
                v = ([min(max(float(x), 0.0), 1.0) for x in _vec3(v, f"{where}.{key}")]
                     if key == "base_color" else min(max(float(v), 0.0), 1.0))
                material[key] = rec[key] = v
        if textures is not None:
            material["base_color_texture"] = rec["texture"] = draw(
                Choice([str(p) for p in textures]), g)
        velocity = (_vec3(draw(ro.velocity, g), f"{where}.velocity")
                    if ro.velocity is not None else [0.0, 0.0, 0.0])
        spin = float(draw(ro.spin_deg_per_s, g)) if ro.spin_deg_per_s is not None else 0.0
        rec.update(velocity=velocity, spin_deg_per_s=spin)
        transform = TransformConfig(translate=positions[i], rotate_deg=[0.0, yaws[i], 0.0],
                                    scale=scales[i])
        animation = None
        if any(velocity) or spin:
            # keys at most 90 degrees of spin apart: slerp takes the short way round
            n_keys = max(2, math.ceil(abs(spin) * duration / 90.0) + 1)
            keys = []
            for j in range(n_keys):
                t = duration * j / (n_keys - 1)
                keys.append(KeyframeConfig(
                    time=t, translate=[p + v * t for p, v in zip(positions[i], velocity,
                                                                    strict=True)],
                    rotate_deg=[0.0, yaws[i] + spin * t, 0.0]))
            animation = AnimationConfig(keys=keys)
        data: dict = {"name": f"random{i}", "size": entry.size, "category": entry.category,
                      "transform": transform.model_dump(),
                      "material": material or None,
                      "animation": animation.model_dump() if animation is not None else None}
        data.update({"mesh": str(entry.mesh)} if entry.mesh is not None
                    else {"primitive": entry.primitive})
        objects.append(ObjectConfig.model_validate(data, context={"base_dir": cfg.base_dir}))
        records.append(rec)
    return objects, records


def _lights(rl: object, g: np.random.Generator, cfg: RenderFile
            ) -> tuple[list[DirectionalLightConfig], list[dict]]:
    n = _count(rl.count, g, f"{cfg.where('randomize', 'lights')}.count")
    lights, records = [], []
    for _ in range(n):
        az, el = float(draw(rl.azimuth_deg, g)), float(draw(rl.elevation_deg, g))
        intensity = max(0.0, float(draw(rl.intensity, g)))
        color = [max(0.0, x) for x in _vec3(draw(rl.color, g), "randomize.lights.color")]
        a, e = math.radians(az), math.radians(el)
        towards = [math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)]
        light = DirectionalLightConfig(type="directional", direction=[-x for x in towards],
                                       intensity=intensity,
                                       color=color, shadows=rl.shadows)
        lights.append(light)
        records.append({"azimuth_deg": az, "elevation_deg": el, "intensity": intensity,
                        "color": color})
    return lights, records


def _cameras(cfg: RenderFile, g: np.random.Generator) -> tuple[list[CameraConfig], list[dict]]:
    rc = cfg.randomize.camera
    cams, records = [], []
    for cam in cfg.cameras:
        rec: dict = {}
        update: dict = {}
        if rc.fov_deg is not None:
            rec["fov_deg"] = update["fov_deg"] = min(max(float(draw(rc.fov_deg, g)), 1.0), 170.0)
        if cam.orbit is not None:
            orbit: dict = {}
            for key in ("azimuth_deg", "elevation_deg", "distance", "target"):
                value = getattr(rc, key)
                if value is None:
                    continue
                v = draw(value, g)
                if key == "elevation_deg":
                    v = min(max(float(v), -89.0), 89.0)
                elif key == "distance":
                    v = max(float(v), 1e-3)
                elif key == "target":
                    v = _vec3(v, "randomize.camera.target")
                else:
                    v = float(v)
                orbit[key] = rec[key] = v
            update["orbit"] = cam.orbit.model_copy(update=orbit)
        cams.append(cam.model_copy(update=update))
        records.append(rec)
    return cams, records
