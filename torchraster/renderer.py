"""The renderer: one planning step decides the passes a scene needs, ``forward`` runs them.

    renderer = tr.Renderer((512, 512), shading="pbr")
    out = renderer(tr.load_spot(), view, proj, lights=lights, environment=env)
    out.image  # (B, 3, H, W) linear HDR radiance;  out.alpha (B, 1, H, W);  out.plan

Data flow (each arrow a pass that runs only when the plan says so)::

    scene --transform--> clip --rasterize--> Fragments --geometry_pass--> GBuffer
      GBuffer (+ SSAO) --shade / headlight / unlit--> radiance --+ background--> image
      (supersampled: --box filter--> image, alpha, G-buffer channels)

Shading models: ``"pbr"`` (Cook-Torrance with the given lights / environment),
``"headlight"`` (Lambert lit from the camera, E = pi, so a white surface facing the camera
is 1.0; needs no lights), ``"unlit"`` (albedo + emissive). Post-processing is a separate
``torchraster.post.PostChain`` applied by the caller (the CLI does).
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import nn

from ._validate import check_resolution, check_tensor
from .gbuffer import CHANNELS, GBuffer, MipCache, check_channels, geometry_pass
from .mesh import transform_points, vertex_normals
from .numerics import safe_normalize
from .raster import antialias, rasterize
from .scene import RenderScene, as_render_scene
from .shading.ibl import Environment, shade_ibl
from .shading.lighting import shade
from .shading.lights import Lights
from .shading.shadows import (
    ShadowMaps,
    ShadowSettings,
    directional_views,
    local_views,
    render_shadow_maps,
    shadow_visibility,
)
from .transparency import (
    composite_over,
    face_alpha_modes,
    first_opaque,
    layer_opacity,
    select_layers,
)

log = logging.getLogger("torchraster")

SHADING = ("pbr", "headlight", "unlit")
TEXTURE_FILTERS = ("trilinear", "bilinear", "nearest")
_SHADING_NEEDS = {
    "pbr": {"position", "normal", "albedo", "metallic", "roughness", "ao", "emissive", "mask"},
    "headlight": {"position", "normal", "albedo", "mask"},
    "unlit": {"albedo", "emissive", "mask"},
}
_TEXTURE_SLOTS = ("base_color_texture", "metallic_roughness_texture", "normal_texture",
                  "occlusion_texture", "emissive_texture")


class NotImplementedWarning(UserWarning):
    """An input asks for a feature that is not implemented yet and is rendered without it
    (e.g. glTF ``alphaMode: BLEND``). Filter with ``warnings.simplefilter``."""


@dataclass(frozen=True)
class RenderPlan:
    """The decisions of one render call, made once by :meth:`Renderer.plan` and executed by
    :meth:`Renderer.forward` (so the reported plan is what ran).

    Attributes:
        resolution: ``(H, W)`` rasterized (the output resolution times ``supersample``).
        supersample: box-filter factor applied at the end (1 = none).
        channels: the G-buffer channels computed.
        requested: the channels the caller asked for (returned in ``RenderOutput.gbuffer``).
        shading: ``"pbr"``, ``"headlight"`` or ``"unlit"`` (``"pbr"`` without lights and
            environment is planned as ``"unlit"``).
        lights: ``(kind, count)`` of each light type present (count None for ambient).
        ssao: SSAO multiplies the AO before lighting.
        ibl: image-based lighting from the environment.
        background: ``"environment"``, ``"colour"`` or ``"none"``.
        cull: back faces dropped: ``"none"``, ``"all"`` (``cull_backfaces=True``) or
            ``"single-sided"`` (faces of materials with ``double_sided=False``).
        derivatives: screen-space UV derivatives are computed (trilinear texturing).
        shadow_lights: ``(kind, light indices, settings)`` of each group of lights whose
            shadow maps are rendered (only lights with ``cast_shadows``, and only when some
            face casts and some face receives).
        shadow_maps: what the shadow pass rendered (views and sizes), filled in by
            ``forward`` (cascades that cover nothing are skipped there).
        layers: depth layers rasterized (> 1 for glTF ``MASK`` / ``BLEND`` materials).
        alpha: ``"none"``, ``"mask"`` (cut-outs: the first opaque layer is shaded) or
            ``"blend"`` (every layer shaded and composited front to back).
        antialias: silhouettes antialiased analytically (:func:`~torchraster.antialias`).

    Iterating a plan yields its human-readable :attr:`steps`.
    """

    resolution: tuple[int, int]
    supersample: int
    channels: frozenset[str]
    requested: frozenset[str]
    shading: str
    lights: tuple[tuple[str, int | None], ...]
    ssao: bool
    ibl: bool
    background: str
    cull: str
    derivatives: bool
    shadow_lights: tuple[tuple[str, tuple[int, ...], ShadowSettings], ...] = ()
    shadow_maps: tuple[str, ...] = ()
    layers: int = 1
    alpha: str = "none"
    antialias: bool = False

    @property
    def steps(self) -> list[str]:
        """The passes in order, e.g. ``["rasterize 64x64", "gbuffer albedo,mask", ...]``."""
        cull = "" if self.cull == "none" else f" (cull {self.cull} back faces)"
        layers = f" {self.layers} layers" if self.layers > 1 else ""
        steps = [f"rasterize {self.resolution[0]}x{self.resolution[1]}{layers}{cull}",
                 "gbuffer " + ",".join(sorted(self.channels))]
        if self.shading == "pbr":
            if self.shadow_maps:
                steps += list(self.shadow_maps)
            else:
                steps += [f"shadow {kind}{list(ids)} {s.map_size}x{s.map_size} {s.filter}"
                          for kind, ids, s in self.shadow_lights]
            steps += [f"light {kind}" + (f" x{n}" if n else "") for kind, n in self.lights]
            steps += ["ssao"] * self.ssao + ["ibl"] * self.ibl
        else:
            steps.append(self.shading)
        if self.alpha == "mask":
            steps.append("alpha mask (first opaque layer)")
        elif self.alpha == "blend":
            steps.append(f"blend {self.layers} layers front to back")
        if self.background != "none":
            steps.append(f"background {self.background}")
        if self.antialias:
            steps.append("antialias")
        if self.supersample > 1:
            steps.append(f"downsample {self.supersample}x")
        return steps

    def __iter__(self) -> Iterator[str]:
        return iter(self.steps)

    def __contains__(self, step: object) -> bool:
        return step in self.steps

    def __str__(self) -> str:
        return "; ".join(self.steps)


@dataclass
class RenderOutput:
    """What :class:`Renderer` returns.

    Attributes:
        image: ``(B, 3, H, W)`` linear HDR radiance including the background.
        alpha: ``(B, 1, H, W)`` coverage (times the material's base-colour alpha when the
            ``alpha`` channel was requested).
        gbuffer: ``{channel: (B, C, H, W)}`` for the requested channels.
        plan: the :class:`RenderPlan` that ran.
    """

    image: torch.Tensor
    alpha: torch.Tensor
    gbuffer: dict[str, torch.Tensor]
    plan: RenderPlan


def camera_position(view: torch.Tensor) -> torch.Tensor:
    """Eye positions ``(B, 3)`` of world -> view matrices ``(B, 4, 4)``: ``-R^T t``."""
    rot, t = view[:, :3, :3], view[:, :3, 3:]
    return -(rot.transpose(1, 2) @ t).squeeze(-1)


def view_rays(view: torch.Tensor, proj: torch.Tensor, resolution: tuple[int, int]) -> torch.Tensor:
    """Unit world-space directions from the eye through each pixel centre.

    Args:
        view: ``(B, 4, 4)`` world -> view; proj: ``(B, 4, 4)`` or ``(1, 4, 4)``.
        resolution: ``(H, W)``.

    Returns:
        ``(B, 3, H, W)``.
    """
    h, w = resolution
    dtype, device = proj.dtype, proj.device
    xs = (2 * torch.arange(w, dtype=dtype, device=device) + 1) / w - 1
    ys = 1 - (2 * torch.arange(h, dtype=dtype, device=device) + 1) / h
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    inv = torch.linalg.inv(proj.to(torch.float64)).to(dtype)  # (B, 4, 4)

    def unproject(z: float) -> torch.Tensor:
        p = torch.stack([x, y, torch.full_like(x, z), torch.ones_like(x)]).view(4, -1)
        q = inv @ p  # (B, 4, HW)
        return q[:, :3] / q[:, 3:]

    d = unproject(-0.5) - unproject(-1.0)  # view space, both points in front of the eye
    d = view[:, :3, :3].transpose(1, 2).to(dtype) @ d
    return safe_normalize(d.view(-1, 3, h, w), dim=1)


def _check_camera(name: str, m: torch.Tensor) -> torch.Tensor:
    """``(4, 4)`` or ``(B, 4, 4)`` finite, invertible matrices -> ``(B, 4, 4)``."""
    if isinstance(m, torch.Tensor) and m.dim() == 2:
        m = m.unsqueeze(0)
    check_tensor(name, m, ("B", 4, 4), floating=True, finite=True)
    m64 = m.detach().to(torch.float64)
    # |det| relative to the largest entry's 4th power: scale-free test for rank < 4
    singular = torch.linalg.det(m64).abs() <= 1e-14 * m64.abs().amax((-2, -1)) ** 4
    if bool(singular.any()):
        bad = singular.nonzero().flatten().tolist()
        raise ValueError(f"{name}: matrix of batch item(s) {bad} is singular (e.g. all zero, "
                         "or a look_at with eye == target); expected an invertible 4x4")
    return m


class Renderer(nn.Module):
    """Differentiable deferred renderer (see the module docstring for the data flow).

    Args:
        resolution: ``(H, W)`` or an int for a square image.
        shading: ``"pbr"``, ``"headlight"`` or ``"unlit"``.
        supersample: render at ``s x`` the resolution and box-filter down (anti-aliasing).
        cull_backfaces: drop clockwise (back-facing) triangles.
        background: RGB (3 non-negative finite floats) of empty pixels; replaced by the
            environment when ``environment_background``.
        environment_background: show the environment behind the scene.
        texture_filter: ``"trilinear"``, ``"bilinear"`` or ``"nearest"``.
        ssao: an enabled ``torchraster.post.SSAO`` module: its AO (from depth and view-space
            normals) multiplies the material AO before lighting (``"pbr"`` shading only).
        mip_cache_bytes: bound of the cache of constant textures' mip pyramids.
        shadows: render shadow maps for lights with ``cast_shadows`` (False: no shadow
            pass at all, whatever the lights say).
        alpha_layers: depth layers rasterized when a material's ``alpha_mode`` is ``MASK``
            or ``BLEND`` (surfaces behind the K nearest are not seen through cut-outs or
            blended surfaces; shadow maps ignore alpha: cut-outs cast solid shadows).
        antialias: blend colours and coverage across silhouette edges by the sub-pixel
            position of the edge (:func:`~torchraster.antialias`), which gives gradients
            with respect to geometry and camera at silhouettes (``out.alpha`` too).
        shadow_settings: the :class:`~torchraster.shading.shadows.ShadowSettings` of
            shadow-casting lights that carry none of their own (``lights.<kind>.shadow``).

    Example:
        >>> renderer = Renderer(256, shading="headlight")
        >>> out = renderer(tr.load_spot(), view, proj)   # out.image (B, 3, 256, 256)
    """

    def __init__(
        self,
        resolution: tuple[int, int] | int,
        *,
        shading: str = "pbr",
        supersample: int = 1,
        cull_backfaces: bool = False,
        background: Sequence[float] = (0.0, 0.0, 0.0),
        environment_background: bool = True,
        texture_filter: str = "trilinear",
        ssao: nn.Module | None = None,
        mip_cache_bytes: int = 512 * 2**20,
        shadows: bool = True,
        shadow_settings: ShadowSettings | None = None,
        alpha_layers: int = 4,
        antialias: bool = False,
    ) -> None:
        super().__init__()
        self.resolution = check_resolution(resolution)
        if shading not in SHADING:
            raise ValueError(f"shading: expected one of {SHADING}, got {shading!r}")
        if isinstance(supersample, bool) or not isinstance(supersample, int) or supersample < 1:
            raise ValueError(f"supersample: expected an int >= 1, got {supersample!r}")
        if texture_filter not in TEXTURE_FILTERS:
            raise ValueError(f"texture_filter: expected one of {TEXTURE_FILTERS}, got "
                             f"{texture_filter!r}")
        try:
            bg = torch.as_tensor(background, dtype=torch.float32, device="cpu").flatten()  # buffer
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"background: expected 3 floats (RGB), got {background!r}") from None
        if bg.numel() != 3 or not bool(torch.isfinite(bg).all()) or bool((bg < 0).any()):
            raise ValueError(f"background: expected 3 finite, non-negative floats (linear RGB), "
                             f"got {background!r}")
        self.shading = shading
        self.supersample = supersample
        self.cull_backfaces = bool(cull_backfaces)
        self.register_buffer("background", bg, persistent=False)
        self.environment_background = bool(environment_background)
        self.texture_filter = texture_filter
        self.ssao = ssao if ssao is not None and getattr(ssao, "enabled", True) else None
        self.mip_cache = MipCache(mip_cache_bytes)
        if shadow_settings is not None and not isinstance(shadow_settings, ShadowSettings):
            raise TypeError(f"shadow_settings: expected a ShadowSettings or None, got "
                            f"{type(shadow_settings).__name__}")
        self.shadows = bool(shadows)
        self.shadow_settings = shadow_settings or ShadowSettings()
        if isinstance(alpha_layers, bool) or not isinstance(alpha_layers, int) or not (
                1 <= alpha_layers <= 16):
            raise ValueError(f"alpha_layers: expected an int in [1, 16], got {alpha_layers!r}")
        self.alpha_layers = alpha_layers
        self.antialias = bool(antialias)

    def plan(self, scene: RenderScene, lights: Lights | None = None,
             environment: Environment | None = None, channels: Iterable[str] = ()
             ) -> RenderPlan:
        """Decide the passes of a render call (``forward`` runs exactly these).

        Warns (:class:`NotImplementedWarning`, once per cause) where the input asks for
        something the renderer does not do yet, and when ``"pbr"`` has nothing to light it.
        """
        scene = as_render_scene(scene)
        requested = check_channels(channels)
        if lights is not None and not isinstance(lights, Lights):
            raise TypeError(f"lights: expected a torchraster.Lights or None, got "
                            f"{type(lights).__name__}")
        if environment is not None and not isinstance(environment, Environment):
            raise TypeError(f"environment: expected a torchraster.Environment or None, got "
                            f"{type(environment).__name__}")
        shading = self.shading
        if shading == "pbr" and lights is None and environment is None:
            warnings.warn("Renderer(shading='pbr') got no lights and no environment: rendering "
                          "albedo + emissive (unlit). Pass lights= or environment=, or use "
                          "shading='unlit' to say so.", stacklevel=3)
            shading = "unlit"
        ssao = self.ssao is not None and shading == "pbr"
        modes = {m.alpha_mode for m in scene.materials if m is not None}
        alpha = "blend" if "BLEND" in modes else "mask" if "MASK" in modes else "none"
        channels = set(requested) | _SHADING_NEEDS[shading] | ({"depth"} if ssao else set())
        if alpha != "none":
            channels.add("alpha")
        light_kinds = []
        if shading == "pbr" and lights is not None:
            if lights.ambient is not None:
                light_kinds.append(("ambient", None))
            for kind in ("directional", "point", "spot"):
                group = getattr(lights, kind)
                if group is not None and group.count:
                    light_kinds.append((kind, group.count))
        if environment is not None and self.environment_background:
            background = "environment"
        elif bool((self.background != 0).any()):
            background = "colour"
        else:
            background = "none"
        textured = any(m is not None and any(getattr(m, s) is not None for s in _TEXTURE_SLOTS)
                       for m in scene.materials)
        single_sided = [m is not None and not m.double_sided for m in scene.materials]
        cull = "all" if self.cull_backfaces else "single-sided" if any(single_sided) else "none"
        s = self.supersample
        shadow_lights = ()
        if shading == "pbr" and lights is not None and self.shadows:
            shadow_lights = self._plan_shadows(scene, lights)
        return RenderPlan(
            resolution=(self.resolution[0] * s, self.resolution[1] * s), supersample=s,
            channels=frozenset(channels), requested=frozenset(requested), shading=shading,
            lights=tuple(light_kinds), ssao=ssao,
            ibl=shading == "pbr" and environment is not None, background=background, cull=cull,
            derivatives=textured and self.texture_filter == "trilinear",
            shadow_lights=shadow_lights, layers=self.alpha_layers if alpha != "none" else 1,
            alpha=alpha, antialias=self.antialias)

    def _plan_shadows(self, scene: RenderScene, lights: Lights
                      ) -> tuple[tuple[str, tuple[int, ...], ShadowSettings], ...]:
        """Groups of shadow-casting lights with one settings object each; none when no
        face casts or none receives."""
        for flags in (scene.cast_shadows, scene.receive_shadows):
            if flags is not None and not bool(flags.any()):
                return ()
        groups: list[tuple[str, tuple[int, ...], ShadowSettings]] = []
        for kind in ("directional", "point", "spot"):
            part = getattr(lights, kind)
            if part is None or part.count == 0:
                continue
            casting = part.cast_shadows.any(0).nonzero().flatten().tolist()
            by_settings: dict[ShadowSettings, list[int]] = {}
            for i in casting:
                by_settings.setdefault(part.settings_of(i) or self.shadow_settings, []).append(i)
            groups += [(kind, tuple(ids), st) for st, ids in by_settings.items()]
        return tuple(groups)

    def forward(
        self,
        scene: RenderScene | object,
        view: torch.Tensor,
        proj: torch.Tensor,
        lights: Lights | None = None,
        environment: Environment | None = None,
        channels: Iterable[str] = (),
    ) -> RenderOutput:
        """Render a batch of scenes.

        Args:
            scene: a :class:`~torchraster.scene.RenderScene`, a Mesh, an ``io.Scene`` or a
                list of B meshes (item i draws mesh i).
            view: ``(B, 4, 4)`` or ``(4, 4)`` world -> view; proj: likewise (OpenGL clip).
            lights: :class:`Lights` of batch size B or 1, or None.
            environment: an :class:`Environment` for image-based lighting / background.
            channels: G-buffer channels to return (see :data:`CHANNELS`).

        Returns:
            :class:`RenderOutput` (image, alpha, requested G-buffer channels, plan).
        """
        scene = as_render_scene(scene)
        view = _check_camera("view", view)
        proj = _check_camera("proj", proj)
        plan = self.plan(scene, lights, environment, channels)
        log.debug("torchraster plan: %s", plan)

        positions = scene.positions
        b = max(view.shape[0], proj.shape[0], scene.batch_size)
        for name, n in (("view", view.shape[0]), ("proj", proj.shape[0]),
                        ("scene", scene.batch_size)):
            if n not in (1, b):
                raise ValueError(f"{name}: batch size {n} does not match the others' {b} "
                                 "(use 1 to share)")
        view, proj = view.expand(b, 4, 4), proj.expand(b, 4, 4)
        clip = transform_points(positions, (proj @ view).to(positions.dtype))
        if clip.shape[0] != b:
            clip = clip.expand(b, -1, -1)
        face_ranges = scene.face_ranges
        if face_ranges is not None and face_ranges.shape[0] != b:
            face_ranges = face_ranges.expand(b, 2)
        frags = rasterize(clip, scene.faces, plan.resolution,
                          cull_backfaces=_cull_mask(plan, scene), face_ranges=face_ranges,
                          derivatives=plan.derivatives, layers=plan.layers)
        normals = scene.normals
        if "normal" in plan.channels and normals is None:
            normals = vertex_normals(positions, scene.faces)
        layers = frags.layers if plan.layers > 1 else (frags,)
        gbs = [geometry_pass(f, plan.channels, positions=positions, view=view,
                             normals=normals, uvs=scene.uvs, tangents=scene.tangents,
                             face_material=scene.face_material, materials=scene.materials,
                             texture_filter=self.texture_filter, mip_cache=self.mip_cache)
               for f in layers]
        eye = camera_position(view.to(positions.dtype))
        groups = None
        if plan.shadow_lights:
            groups, lights_b = self._shadow_maps(plan, scene, view, proj, lights, b, face_ranges)
            plan = replace(plan, shadow_maps=tuple(st for g in groups for st in g.steps))

        def radiance_of(gb: GBuffer, face_id: torch.Tensor) -> torch.Tensor:
            hook = None if groups is None else self._shadow_hook(groups, lights_b, scene, gb,
                                                                 face_id, view, b)
            return self._shade(plan, gb, view, proj, eye, lights, environment, hook) * gb.mask

        visible = frags  # the face ids / depths antialiasing sees
        if plan.alpha == "none":
            gb = gbs[0]
            radiance, coverage = radiance_of(gb, frags.face_id), gb.mask
            transmittance = 1 - coverage
        else:
            modes, cutoffs = face_alpha_modes(scene.materials, scene.face_material,
                                              scene.faces.shape[0], positions.device)
            opacity = [layer_opacity(g, f.face_id, modes, cutoffs) for g, f in zip(
                gbs, layers, strict=True)]
            if plan.alpha == "mask":
                first = first_opaque(opacity)
                gb = select_layers(gbs, first)
                fid = torch.gather(torch.stack([f.face_id for f in layers]), 0,
                                   first.squeeze(1).unsqueeze(0))[0]
                coverage = torch.gather(torch.stack(opacity), 0, first.unsqueeze(0))[0]
                depth = torch.gather(torch.stack([f.depth for f in layers]), 0,
                                     first.squeeze(1).unsqueeze(0))[0]
                visible = _Visible(fid, depth)
                radiance = radiance_of(gb, fid) * coverage
                transmittance = 1 - coverage
            else:
                colors, used = [], []
                transmittance = torch.ones_like(opacity[0])
                for g, f, a in zip(gbs, layers, opacity, strict=True):
                    if not bool((transmittance * a > 0).any()):
                        break  # everything behind is hidden
                    colors.append(radiance_of(g, f.face_id))
                    used.append(a)
                    transmittance = transmittance * (1 - a)
                radiance, transmittance = composite_over(colors, used)
                gb = select_layers(gbs, first_opaque(opacity))
        if plan.background == "environment":
            rays = view_rays(view, proj, plan.resolution).to(radiance.dtype)
            background = environment.background(rays)
        else:
            background = self.background.to(radiance).view(1, 3, 1, 1)
        image = radiance + transmittance * background
        if plan.alpha != "none":
            alpha = 1 - transmittance
        else:
            alpha = gb.mask * gb.alpha if gb.alpha is not None else gb.mask
        if plan.antialias:  # one call for colour and coverage
            both = antialias(torch.cat([image, alpha.to(image.dtype)], 1), visible, clip,
                             scene.faces)
            image, alpha = both[:, :3], both[:, 3:]
        outputs = GBuffer(**{ch: getattr(gb, ch) for ch in plan.requested})
        if plan.supersample > 1:
            s = plan.supersample
            image, alpha = F.avg_pool2d(image, s), F.avg_pool2d(alpha, s)
            outputs = outputs.downsample(s)
        return RenderOutput(image=image, alpha=alpha, gbuffer=outputs.as_dict(), plan=plan)

    def _shadow_maps(self, plan: RenderPlan, scene: RenderScene, view: torch.Tensor,
                     proj: torch.Tensor, lights: Lights, b: int,
                     face_ranges: torch.Tensor | None) -> tuple[list[ShadowMaps], Lights]:
        """Render the planned shadow maps (one batched pass per map size); returns the
        groups and the lights expanded to the batch."""
        positions = scene.positions
        faces = scene.faces
        scene_bounds = _caster_bounds(positions, faces, face_ranges, b)  # what may receive
        cast = scene.cast_shadows
        if cast is not None:
            faces = faces[cast.to(faces.device)]
            if face_ranges is not None:
                before = torch.cat([cast.new_zeros(1, dtype=torch.int64),
                                    torch.cumsum(cast.to(torch.int64), 0)])
                face_ranges = before.to(face_ranges.device)[face_ranges]
        bounds = _caster_bounds(positions, faces, face_ranges, b)
        lights = lights.expand(b) if lights.batch_size == 1 and b > 1 else lights
        lights = lights.to(device=positions.device, dtype=positions.dtype)
        groups: list[ShadowMaps] = []
        for kind, ids, settings in plan.shadow_lights:
            part = getattr(lights, kind).select(torch.tensor(ids))
            if kind == "directional":
                g = directional_views(part.direction, settings, bounds, view.to(positions.dtype),
                                      proj.to(positions.dtype), receiver_bounds=scene_bounds)
            else:
                g = local_views(kind, part.position,
                                part.direction if kind == "spot" else None,
                                part.outer_cone_angle if kind == "spot" else None, settings,
                                bounds)
            g.lights = list(ids)
            groups.append(g)
        render_shadow_maps(groups, positions, faces, face_ranges)
        return groups, lights

    def _shadow_hook(self, groups: list[ShadowMaps], lights: Lights, scene: RenderScene,
                     gb: GBuffer, face_id: torch.Tensor, view: torch.Tensor, b: int):
        """The ``shade`` visibility hook of the surfaces in ``gb`` (face ids ``face_id``)."""
        receive = gb.mask > 0
        if scene.receive_shadows is not None:
            flags = scene.receive_shadows.to(face_id.device)
            receive = receive & flags[face_id.clamp_min(0)].unsqueeze(1) & (
                face_id >= 0).unsqueeze(1)
        full: dict[str, torch.Tensor] = {}
        for g in groups:
            vis = shadow_visibility(g, gb.position, safe_normalize(gb.normal, dim=1), receive,
                                    view)
            count = getattr(lights, g.kind).count
            if g.kind not in full:
                full[g.kind] = vis.new_ones(b, count, 1, *vis.shape[-2:])
            full[g.kind] = full[g.kind].index_copy(
                1, torch.tensor(g.lights, device=vis.device), vis)

        def hook(kind: str, sl: slice) -> torch.Tensor | None:
            return full[kind][:, sl] if kind in full else None

        return hook

    def _shade(self, plan: RenderPlan, gb: GBuffer, view: torch.Tensor, proj: torch.Tensor,
               eye: torch.Tensor, lights: Lights | None,
               environment: Environment | None, visibility=None) -> torch.Tensor:
        """Radiance ``(B, 3, H, W)`` of the covered pixels, by the plan's shading path."""
        if plan.shading == "headlight":
            to_eye = safe_normalize(eye[:, :, None, None] - gb.position, dim=1)
            return gb.albedo * (gb.normal * to_eye).sum(1, keepdim=True).clamp(min=0)
        if plan.shading == "unlit":
            return gb.albedo + gb.emissive
        if plan.ssao:
            normal_view = torch.einsum("bij,bjhw->bihw", view[:, :3, :3].to(gb.normal.dtype),
                                       gb.normal)
            depth = torch.where(gb.mask > 0, gb.depth, torch.zeros_like(gb.depth))
            gb = gb.replace(ao=gb.ao * self.ssao(depth, normal_view,
                                                 projection=proj.to(depth.dtype)))
        ibl = None
        if plan.ibl:
            def ibl(n, v, a, m, r):
                return shade_ibl(n, v, a, m, r, None, environment)
        return shade(gb, camera_position=eye, lights=lights, ibl=ibl, visibility=visibility)


@dataclass
class _Visible:
    """The visible surface per pixel (what ``antialias`` reads of Fragments) when cut-outs
    select a deeper layer: ``face_id`` ``(B, H, W)`` (-1 empty), ``depth`` ``(B, H, W)``."""

    face_id: torch.Tensor
    depth: torch.Tensor


def _caster_bounds(positions: torch.Tensor, faces: torch.Tensor,
                   face_ranges: torch.Tensor | None, b: int) -> torch.Tensor:
    """``(B, 2, 3)`` world bounds of the vertices of ``faces`` (per batch item): of the
    shadow casters, or of the whole scene."""
    with torch.no_grad():
        pos = positions if positions.dim() == 3 else positions[None]
        used = torch.zeros(pos.shape[1], dtype=torch.bool, device=pos.device)
        rows = []
        for i in range(b if face_ranges is not None or pos.shape[0] > 1 else 1):
            f = faces if face_ranges is None else faces[int(face_ranges[i, 0]):
                                                        int(face_ranges[i, 1])]
            used = used.zero_().index_fill_(0, f.reshape(-1), True)
            p = pos[min(i, pos.shape[0] - 1)][used]
            if p.shape[0] == 0:
                p = pos.new_zeros(1, 3)
            rows.append(torch.stack([p.amin(0), p.amax(0)]))
        out = torch.stack(rows)
        return out.expand(b, 2, 3) if out.shape[0] == 1 else out


def _cull_mask(plan: RenderPlan, scene: RenderScene) -> bool | torch.Tensor:
    """``rasterize``'s ``cull_backfaces``: a bool, or ``(F,)`` True on faces of single-sided
    materials (glTF ``doubleSided: false``; no material = drawn from both sides)."""
    if plan.cull != "single-sided":
        return plan.cull == "all"
    single = torch.tensor([m is not None and not m.double_sided for m in scene.materials],
                          device=scene.faces.device)
    if scene.face_material is None:
        return single[:1].expand(scene.faces.shape[0])
    return single.index_select(0, scene.face_material.to(single.device))


__all__ = ["CHANNELS", "NotImplementedWarning", "RenderOutput", "RenderPlan", "RenderScene",
           "Renderer", "camera_position", "view_rays"]
