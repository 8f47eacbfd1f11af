"""Every builder of the config layer: from validated sections to the objects they name.

One entry point for a config of one object, :func:`build_setup` (scene, lights, environment,
renderer, post chain, G-buffer channels), and :func:`build_camera` for each of its views; the
section builders it calls are public too (``build_renderer``, ``build_post_chain``,
``lights_from_config``, ...). Paths are absolute already (resolved when the config was
loaded); builders pass keyword arguments, so every default stays the constructor's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from pydantic import BaseModel

from .. import camera
from ..animation import look_at_path
from ..background import load_background
from ..dissolve import Dissolve
from ..hdr_io import read_hdr
from ..post import (
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
from ..renderer import Renderer
from ..scene import RenderScene
from ..settings import BackgroundSettings, RasterSettings, ShadingSettings, TextureSettings
from ..shading.ibl import Environment
from ..shading.lights import (
    SH_C0,
    AreaLights,
    DirectionalLights,
    Lights,
    PointLights,
    SpotLights,
    area_light_axes,
)
from ..shading.shadows import ShadowSettings
from ..shading.volumetric import Fog
from .objects import SceneObjects, build_objects
from .schema import (
    CameraConfig,
    ConfigError,
    DissolveConfig,
    EnvironmentShadingConfig,
    FogConfig,
    PostConfig,
    RenderFile,
    ShadowConfig,
    SSAOConfig,
    SSRConfig,
    parse_lights,
)


@dataclass
class RenderSetup:
    """What every view of a one-object config shares (see :func:`build_setup`).

    Attributes:
        scene: the scene at time 0, on the render device.
        objects: its instances with identity and motion (``objects.at(t)`` poses the scene
            for another time).
        lights: the lights (batch 1) or None.
        environment: the environment map or None.
        renderer: the :class:`~torchraster.Renderer` of ``render:`` (and ``post.ssao``,
            ``post.ssr``).
        post: the post chain (:func:`build_post`).
        channels: the G-buffer channels to render (the outputs', plus depth for depth of
            field).
    """

    scene: RenderScene
    objects: SceneObjects
    lights: Lights | None
    environment: Environment | None
    renderer: Renderer
    post: PostChain
    channels: set[str]


def build_setup(cfg: RenderFile, device: str | torch.device = "cpu") -> RenderSetup:
    """Build what a one-object config's views share, once.

    Args:
        cfg: a config of one object (not a mesh set; see
            :func:`torchraster.pipeline.plan_objects`).
        device: where to render.
    """
    objects = build_objects(cfg).to(device)
    scene = objects.scene
    lights = lights_from_config(cfg.lights, 1, device) if cfg.lights else None
    env = build_environment(cfg, device)
    post = build_post(cfg)
    renderer = build_renderer(cfg, env is not None)
    channels = set(cfg.outputs.channels) - {"color", "radiance", "alpha"}
    if post.dof.enabled:
        channels.add("depth")
    return RenderSetup(scene, objects, lights, env, renderer, post, channels)


def build_post(cfg: RenderFile) -> PostChain:
    """The post chain of a config: without a ``post:`` section no tone mapping, sRGB
    encoding only (the linear image clipped); with one (even ``post: {}``) every stage at
    its default (ACES tone mapping), see :func:`build_post_chain`."""
    if cfg.post is None:
        return PostChain(encode=EncodeSRGB())
    return build_post_chain(cfg.post)


def build_environment(cfg: RenderFile, device: str | torch.device = "cpu"
                      ) -> Environment | None:
    """The :class:`~torchraster.shading.ibl.Environment` of ``environment:`` (None without
    one), its radiance on ``device``."""
    e = cfg.environment
    if e is None:
        return None
    radiance = read_hdr(Path(e.path)).to(device)
    shading = {k: getattr(e, k) for k in EnvironmentShadingConfig.model_fields}  # same names
    return Environment(radiance, yaw=math.radians(e.rotation_deg), intensity=e.intensity,
                       **shading)


def build_fog(cfg: FogConfig) -> Fog | None:
    """The :class:`~torchraster.shading.volumetric.Fog` of ``render.fog`` (None if
    disabled)."""
    if not cfg.enabled:
        return None
    d = cfg.model_dump(exclude={"enabled", "max_distance"})
    return Fog(**{**d, "color": tuple(d["color"]), "ambient": tuple(d["ambient"])},
               max_distance=math.inf if cfg.max_distance is None else cfg.max_distance)


def build_dissolve(cfg: DissolveConfig) -> Dissolve:
    """The :class:`~torchraster.dissolve.Dissolve` of ``render.dissolve``."""
    return Dissolve(**{**cfg.model_dump(), "edge_color": tuple(cfg.edge_color)})


def build_shadow_settings(cfg: ShadowConfig) -> ShadowSettings:
    """The :class:`~torchraster.shading.shadows.ShadowSettings` of a light's ``shadows:``."""
    return ShadowSettings(**cfg.model_dump(exclude={"enabled"}))


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


#: The ``Renderer`` argument of each settings group built from ``render:``.
SETTINGS_OF_RENDER: dict[str, type] = {
    "shading": ShadingSettings, "raster": RasterSettings, "textures": TextureSettings,
    "background": BackgroundSettings}
#: The ``render:`` keys that are fields of a settings group: (group, field). The others:
#: ``resolution``, ``toon`` (the options of ``shading: toon``), ``background_image``
#: (``BackgroundSettings.image`` and ``fit``) and the effects ``fog`` and ``dissolve``.
RENDER_SETTINGS_KEYS: dict[str, tuple[type, str]] = {
    "shading": (ShadingSettings, "model"), "multiscatter": (ShadingSettings, "multiscatter"),
    **{key: (RasterSettings, key) for key in (
        "supersample", "edge_supersample", "antialias", "cull_backfaces", "alpha_layers")},
    "texture_filter": (TextureSettings, "filter"),
    "max_anisotropy": (TextureSettings, "max_anisotropy"),
    "background": (BackgroundSettings, "color"),
}


def build_renderer(cfg: RenderFile, with_environment: bool) -> Renderer:
    """The :class:`~torchraster.Renderer` of a config's ``render:`` (and ``post.ssao``,
    ``post.ssr``)."""
    r = cfg.render
    ssao = build_ssao(cfg.post) if cfg.post is not None and cfg.post.ssao.enabled else None
    ssr = build_ssr(cfg.post) if cfg.post is not None and cfg.post.ssr.enabled else None
    options = r.toon.model_dump() if r.toon is not None else None
    image = None
    if r.background_image is not None:
        path = Path(r.background_image.path)
        try:
            image = load_background(path)
        except (OSError, ValueError) as e:
            where = cfg.where("render", "background_image", "path")
            raise ConfigError(f"{where}: {e}") from None
    groups: dict[type, dict[str, Any]] = {cls: {} for cls in SETTINGS_OF_RENDER.values()}
    for key, (cls, name) in RENDER_SETTINGS_KEYS.items():
        groups[cls][name] = getattr(r, key)
    groups[ShadingSettings]["options"] = options or {}
    groups[BackgroundSettings].update(
        environment=bool(with_environment and cfg.environment and cfg.environment.background),
        image=image, fit=r.background_image.fit if image is not None else "cover")
    return Renderer(
        r.size, **{arg: cls(**groups[cls]) for arg, cls in SETTINGS_OF_RENDER.items()},
        ssao=ssao, ssr=ssr, fog=build_fog(r.fog) if r.fog is not None else None,
        dissolve=build_dissolve(r.dissolve) if r.dissolve is not None else None)


def _casts(light: BaseModel) -> bool:
    if light.shadows is not None:
        return light.shadows.enabled
    return bool(light.cast_shadows)


def _shadow_settings(light: BaseModel) -> ShadowSettings | None:
    return build_shadow_settings(light.shadows) if light.shadows is not None else None


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
        directional / point / spot / area containers with ``L`` = number of lights of each type
        (None for types that are absent).
    """
    if not isinstance(batch, int) or isinstance(batch, bool) or batch < 1:
        raise ValueError(f"batch: expected a positive int, got {batch!r}")
    cfgs = parse_lights([c.model_dump(exclude_unset=True) if isinstance(c, BaseModel) else c
                        for c in configs])

    def tensor(rows: list, shape_tail: tuple[int, ...] = ()) -> torch.Tensor:
        t = torch.tensor(rows, device=device, dtype=dtype).reshape(1, len(rows), *shape_tail)
        return t.expand(batch, *t.shape[1:]).contiguous()

    def flags(rows: list) -> torch.Tensor:
        t = torch.tensor(rows, device=device, dtype=torch.bool).reshape(1, -1)
        return t.expand(batch, -1).contiguous()

    def inf_if_none(r: float | None) -> float:
        return math.inf if r is None else r

    by_type: dict[str, list] = {"ambient": [], "directional": [], "point": [], "spot": [],
                                "area": []}
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
            cast_shadows=flags([_casts(c) for c in d]),
            shadow=tuple(_shadow_settings(c) for c in d),
        )
    if p := by_type["point"]:
        point = PointLights(
            position=tensor([c.position for c in p], (3,)),
            color=tensor([c.color for c in p], (3,)),
            intensity=tensor([c.intensity for c in p]),
            range=tensor([inf_if_none(c.range) for c in p]),
            cast_shadows=flags([_casts(c) for c in p]),
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
            cast_shadows=flags([_casts(c) for c in s]),
            shadow=tuple(_shadow_settings(c) for c in s),
        )
    area = None
    if a := by_type["area"]:
        axes = []
        for c in a:  # u and v of each light (its own up, or the default)
            w, h = c.size or (1.0, 1.0) if c.shape == "rect" else (2 * (c.radius or 0.5),) * 2
            f64 = {"dtype": torch.float64}
            axes.append(torch.stack(area_light_axes(
                torch.tensor(c.direction, **f64), torch.tensor(w, **f64),
                torch.tensor(h, **f64), None if c.up is None else torch.tensor(c.up, **f64))))
        u, v = torch.stack(axes).unbind(1)
        area = AreaLights(
            position=tensor([c.position for c in a], (3,)),
            u=tensor(u.tolist(), (3,)),
            v=tensor(v.tolist(), (3,)),
            color=tensor([c.color for c in a], (3,)),
            intensity=tensor([c.intensity for c in a]),
            disc=flags([c.shape == "disc" for c in a]),
            two_sided=flags([c.two_sided for c in a]),
            cast_shadows=flags([_casts(c) for c in a]),
            shadow=tuple(_shadow_settings(c) for c in a),
        )
    return Lights(ambient=ambient, directional=directional, point=point, spot=spot, area=area)


def build_camera(cam: CameraConfig, positions: torch.Tensor, resolution: tuple[int, int],
                 time: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """World -> view and projection matrices ``(1, 4, 4)`` of one camera at ``time``
    seconds, framing the scene's bounding sphere where distances or planes are left out.

    Args:
        cam: the camera's config.
        positions: ``(V, 3)`` world positions of the scene (at time 0: the framing does not
            follow moving objects).
        resolution: ``(H, W)``.
        time: for ``trajectory`` cameras and orbits with ``degrees_per_second``.
    """
    h, w = resolution
    lo, hi = positions.amin(0), positions.amax(0)
    center = (lo + hi) / 2
    radius = float((positions - center).norm(dim=-1).max().clamp(min=1e-6))
    exact = positions.dtype == torch.float64  # a world far from the origin (config/objects)

    def vec(v):  # its camera in float64 too (float32 rounds 1e6 to 1/16; relative.py)
        return torch.as_tensor(v, dtype=torch.float64) if exact else v

    if cam.look_at is not None:
        view = camera.look_at(vec(cam.look_at.eye), vec(cam.look_at.target), cam.look_at.up)
        distance = float((torch.tensor(cam.look_at.eye) - torch.tensor(cam.look_at.target)).norm())
    elif cam.trajectory is not None:
        keys = cam.trajectory.keys
        view = look_at_path([k.time for k in keys], vec([k.eye for k in keys]),
                            vec([k.target for k in keys]), [k.up for k in keys], t=[time],
                            interpolation=cam.trajectory.interpolation)
        eye = view.inverse()[0, :3, 3]
        distance = float((eye - center).norm().clamp(min=radius * 1e-3))
    else:
        o = cam.orbit
        target = o.target if o.target is not None else center.tolist()
        fov = math.radians(cam.fov_deg)
        distance = o.distance or radius / math.sin(min(fov, fov * w / h) / 2) * 1.05
        view = camera.orbit(vec(o.azimuth_deg + o.degrees_per_second * time),
                            o.elevation_deg, distance, vec(target))
    near = cam.near or max(distance - 2 * radius, distance * 1e-3, 1e-4)
    far = cam.far or math.inf
    if cam.projection == "orthographic":
        half_h = (cam.ortho_height or 2.2 * radius) / 2
        half_w = half_h * w / h
        far = cam.far or distance + 4 * radius
        near = cam.near or max(distance - 4 * radius, 1e-4)
        proj = camera.orthographic(-half_w, half_w, -half_h, half_h, near, far)
    elif cam.intrinsics is not None:
        k = cam.intrinsics
        proj = camera.from_intrinsics(k.fx, k.fy, k.cx, k.cy, w, h, near, far, cam.reverse_z)
    else:
        proj = camera.perspective(cam.fov_deg, w / h, near, far, cam.reverse_z)
    return view, proj
