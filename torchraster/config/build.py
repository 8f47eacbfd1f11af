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
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from pydantic import BaseModel

from .. import camera
from ..background import load_background
from ..dissolve import Dissolve
from ..hdr_io import read_hdr
from ..io import load_scene, load_texture
from ..material import Material
from ..mesh import Mesh, vertex_normals
from ..mesh import flat as flat_mesh
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
from ..shading.ibl import Environment
from ..shading.lights import SH_C0, DirectionalLights, Lights, PointLights, SpotLights
from ..shading.shadows import ShadowSettings
from ..shading.volumetric import Fog
from .schema import (
    CameraConfig,
    ConfigError,
    DissolveConfig,
    FogConfig,
    ObjectConfig,
    ObjectMaterialConfig,
    PostConfig,
    RenderFile,
    ShadowConfig,
    SSAOConfig,
    SSRConfig,
    TransformConfig,
    parse_lights,
)


@dataclass
class RenderSetup:
    """What every view of a one-object config shares (see :func:`build_setup`).

    Attributes:
        scene: the scene, on the render device.
        lights: the lights (batch 1) or None.
        environment: the environment map or None.
        renderer: the :class:`~torchraster.Renderer` of ``render:`` (and ``post.ssao``,
            ``post.ssr``).
        post: the post chain (:func:`build_post`).
        channels: the G-buffer channels to render (the outputs', plus depth for depth of
            field).
    """

    scene: RenderScene
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
    scene = build_scene(cfg).to(device)
    lights = lights_from_config(cfg.lights, 1, device) if cfg.lights else None
    env = build_environment(cfg, device)
    post = build_post(cfg)
    renderer = build_renderer(cfg, env is not None)
    channels = set(cfg.outputs.channels) - {"color", "radiance", "alpha"}
    if post.dof.enabled:
        channels.add("depth")
    return RenderSetup(scene, lights, env, renderer, post, channels)


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
    return Environment(radiance, yaw=math.radians(e.rotation_deg), intensity=e.intensity,
                       specular=e.specular, importance_samples=e.importance_samples)


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
    return Renderer(r.size, shading=r.shading, shading_options=options,
                    background_image=image,
                    background_fit=r.background_image.fit if image is not None else "cover",
                    dissolve=build_dissolve(r.dissolve) if r.dissolve is not None else None,
                    supersample=r.supersample,
                    cull_backfaces=r.cull_backfaces, background=r.background,
                    environment_background=bool(with_environment and cfg.environment
                                                and cfg.environment.background),
                    texture_filter=r.texture_filter, max_anisotropy=r.max_anisotropy,
                    ssao=ssao, ssr=ssr, alpha_layers=r.alpha_layers,
                    antialias=r.antialias, fog=build_fog(r.fog) if r.fog is not None else None,
                    multiscatter=r.multiscatter)


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


def _transform_matrix(t: TransformConfig) -> torch.Tensor:
    """(4, 4) model -> world: scale, then rotations about x, y, z (degrees), then translate."""
    import kornia

    scale = torch.tensor(t.scale if isinstance(t.scale, list) else [t.scale] * 3)
    angles = torch.deg2rad(torch.tensor(t.rotate_deg))[None]
    rx, ry, rz = (kornia.geometry.conversions.axis_angle_to_rotation_matrix(
        torch.eye(3)[i:i + 1] * angles[0, i]) for i in range(3))
    m = torch.eye(4)
    m[:3, :3] = (rz @ ry @ rx)[0] * scale
    m[:3, 3] = torch.tensor(t.translate)
    return m


def build_scene(cfg: RenderFile) -> RenderScene:
    """Load and transform the config's scene (the main mesh and every entry of
    ``scene.objects``) into one :class:`RenderScene` with per-face materials and shadow
    flags (names the file on error)."""
    parts: list[_Part] = []
    sc = cfg.scene
    if sc.mesh is not None:
        parts.append(_file_part(cfg, sc.mesh, sc.transform, sc.normals, sc.cast_shadows,
                                sc.receive_shadows))
    for i, obj in enumerate(sc.objects):
        if obj.mesh is not None:
            parts.append(_file_part(cfg, obj.mesh, obj.transform, "auto", obj.cast_shadows,
                                    obj.receive_shadows))
        else:
            parts.append(_primitive_part(obj, obj.name or f"{obj.primitive}{i}",
                                         sc.max_texture_size))
    for part in parts:
        part.materials = [_override(mat, cfg) for mat in part.materials]
    return _merge(parts)


@dataclass
class _Part:
    """One object of a config's scene, in world space."""

    positions: torch.Tensor
    faces: torch.Tensor
    normals: torch.Tensor | None
    uvs: torch.Tensor | None
    tangents: torch.Tensor | None
    face_material: torch.Tensor
    materials: list
    cast: torch.Tensor
    receive: torch.Tensor


def _file_part(cfg: RenderFile, path: str, transform: TransformConfig, normals_mode: str,
               cast: bool, receive: bool) -> _Part:
    scene = load_scene(Path(path), max_texture_size=cfg.scene.max_texture_size,
                       allow_missing_textures=cfg.scene.allow_missing_textures)
    mesh, face_material, materials = scene.flatten()
    node_cast, node_receive = scene.face_shadow_flags()
    if normals_mode == "flat":
        mesh = flat_mesh(mesh)
    m = _transform_matrix(transform)
    positions = mesh.positions @ m[:3, :3].T + m[:3, 3]
    normals = None
    if mesh.normals is not None and normals_mode != "smooth":
        normals = torch.nn.functional.normalize(mesh.normals @ torch.linalg.inv(m[:3, :3]), dim=-1)
    return _Part(positions, mesh.faces, normals, mesh.uvs, mesh.tangents, face_material,
                 list(materials), node_cast & cast, node_receive & receive)


def _primitive_part(obj: ObjectConfig, name: str, max_texture: int | None) -> _Part:
    """A plane, box or sphere of ``obj.size`` with its material, in world space."""
    import trimesh

    s = float(obj.size)
    if obj.primitive == "plane":
        h = s / 2
        positions = torch.tensor([[-h, 0, -h], [h, 0, -h], [h, 0, h], [-h, 0, h]])
        faces = torch.tensor([[0, 2, 1], [0, 3, 2]])  # counter-clockwise seen from +Y
        normals = torch.tensor([[0.0, 1.0, 0.0]]).expand(4, 3)
        uvs = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    else:
        tm = (trimesh.creation.box(extents=[s, s, s]) if obj.primitive == "box"
              else trimesh.creation.icosphere(subdivisions=3, radius=s / 2))
        mesh = Mesh(torch.tensor(tm.vertices, dtype=torch.float32),
                    torch.tensor(tm.faces, dtype=torch.int64))
        if obj.primitive == "box":
            mesh = flat_mesh(mesh)  # sharp edges: one normal per face
            positions, faces, normals = mesh.positions, mesh.faces, mesh.normals
            # each face projected along its axis: [0, 1]^2 over the face
            axis = normals.abs().argmax(-1, keepdim=True)
            keep = torch.tensor([[1, 2], [0, 2], [0, 1]]).index_select(0, axis.flatten())
            uvs = torch.gather(positions, 1, keep) / s + 0.5
        else:
            positions, faces = mesh.positions, mesh.faces
            normals = torch.nn.functional.normalize(positions, dim=-1)
            # latitude-longitude
            uvs = torch.stack([0.5 + torch.atan2(normals[:, 0], normals[:, 2]) / (2 * math.pi),
                               0.5 + torch.asin(normals[:, 1].clamp(-1, 1)) / math.pi], -1)
    m = _transform_matrix(obj.transform)
    positions = positions.float() @ m[:3, :3].T + m[:3, 3]
    normals = torch.nn.functional.normalize(normals.float() @ torch.linalg.inv(m[:3, :3]),
                                            dim=-1)
    mc = obj.material or ObjectMaterialConfig()
    rgba = list(mc.base_color) + ([1.0] if len(mc.base_color) == 3 else [])
    texture = None
    if mc.base_color_texture is not None:
        texture = load_texture(Path(mc.base_color_texture), max_size=max_texture)
    material = Material(name=mc.name or f"object:{name}", base_color_factor=torch.tensor(rgba),
                        base_color_texture=texture, metallic_factor=mc.metallic,
                        roughness_factor=mc.roughness, emissive_factor=torch.tensor(mc.emissive),
                        alpha_mode=mc.alpha_mode, alpha_cutoff=mc.alpha_cutoff,
                        double_sided=obj.primitive == "plane" or mc.alpha_mode != "OPAQUE")
    n_faces = faces.shape[0]
    return _Part(positions, faces, normals, uvs, None,
                 torch.zeros(n_faces, dtype=torch.int64), [material],
                 torch.full((n_faces,), obj.cast_shadows), torch.full((n_faces,),
                                                                      obj.receive_shadows))


def _merge(parts: list[_Part]) -> RenderScene:
    """One RenderScene of all parts (missing normals computed, missing UVs / tangents
    zero-filled where another part has them)."""
    if len(parts) == 1 and bool(parts[0].cast.all()) and bool(parts[0].receive.all()):
        p = parts[0]
        return RenderScene(p.positions, p.faces, p.normals, p.uvs, p.tangents, p.face_material,
                           p.materials)
    any_uv = any(p.uvs is not None for p in parts)
    any_tan = any(p.tangents is not None for p in parts)
    pos, faces, nrm, uvs, tan, fmat, mats = [], [], [], [], [], [], []
    offset = 0
    for p in parts:
        n_vert = p.positions.shape[0]
        pos.append(p.positions)
        faces.append(p.faces + offset)
        nrm.append(p.normals if p.normals is not None
                   else vertex_normals(p.positions, p.faces).reshape(-1, 3))
        if any_uv:
            uvs.append(p.uvs if p.uvs is not None else p.positions.new_zeros(n_vert, 2))
        if any_tan:
            tan.append(p.tangents if p.tangents is not None else p.positions.new_zeros(n_vert, 4))
        fmat.append(p.face_material + len(mats))
        mats += p.materials
        offset += n_vert
    cast = torch.cat([p.cast for p in parts])
    receive = torch.cat([p.receive for p in parts])
    return RenderScene(torch.cat(pos), torch.cat(faces), torch.cat(nrm),
                       torch.cat(uvs) if any_uv else None, torch.cat(tan) if any_tan else None,
                       torch.cat(fmat), mats, cast_shadows=None if bool(cast.all()) else cast,
                       receive_shadows=None if bool(receive.all()) else receive)


def _override(mat: Material | None, cfg: RenderFile) -> Material | None:
    """Apply the config's material overrides (in order) to one material."""
    for o in cfg.materials:
        if o.match != "*" and (mat is None or mat.name != o.match):
            continue
        mat = mat if mat is not None else Material()
        changes = {}
        if o.base_color is not None:
            rgba = list(o.base_color) + ([1.0] if len(o.base_color) == 3 else [])
            changes["base_color_factor"] = torch.tensor(rgba)
        if o.metallic is not None:
            changes["metallic_factor"] = o.metallic
        if o.roughness is not None:
            changes["roughness_factor"] = o.roughness
        if o.emissive is not None:
            changes["emissive_factor"] = torch.tensor(o.emissive)
        if o.base_color_texture is not None:
            changes["base_color_texture"] = load_texture(
                Path(o.base_color_texture), max_size=cfg.scene.max_texture_size)
        mat = replace(mat, **changes)
    return mat


def build_camera(cam: CameraConfig, positions: torch.Tensor, resolution: tuple[int, int]
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """World -> view and projection matrices ``(1, 4, 4)`` of one camera, framing the
    scene's bounding sphere where distances or planes are left out.

    Args:
        cam: the camera's config.
        positions: ``(V, 3)`` world positions of the scene.
        resolution: ``(H, W)``.
    """
    h, w = resolution
    lo, hi = positions.amin(0), positions.amax(0)
    center = (lo + hi) / 2
    radius = float((positions - center).norm(dim=-1).max().clamp(min=1e-6))
    if cam.look_at is not None:
        view = camera.look_at(cam.look_at.eye, cam.look_at.target, cam.look_at.up)
        distance = float((torch.tensor(cam.look_at.eye) - torch.tensor(cam.look_at.target)).norm())
    else:
        o = cam.orbit
        target = o.target if o.target is not None else center.tolist()
        fov = math.radians(cam.fov_deg)
        distance = o.distance or radius / math.sin(min(fov, fov * w / h) / 2) * 1.05
        view = camera.orbit(o.azimuth_deg, o.elevation_deg, distance, target)
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
