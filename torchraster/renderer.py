"""The renderer: one planning step decides the passes a scene needs, ``forward`` runs them.

    renderer = tr.Renderer((512, 512), shading="pbr")
    out = renderer(tr.load_spot(), view, proj, lights=lights, environment=env)
    out.image  # (B, 3, H, W) linear HDR radiance;  out.alpha (B, 1, H, W);  out.plan

Data flow (each arrow a pass that runs only when the plan says so)::

    scene --transform--> clip --rasterize--> Fragments --geometry_pass--> GBuffer
      GBuffer (+ SSAO) --shade / headlight / unlit--> radiance (--SSR-->) --+ background--> image
      (supersampled: --box filter--> image, alpha, G-buffer channels)

Shading models: ``"pbr"`` (Cook-Torrance with the given lights / environment), the
stylised models of :mod:`torchraster.shading.models` ``"blinn_phong"``, ``"half_lambert"``
and ``"toon"`` (lit by the same lights, shadows, ambient and environment; only the BRDF of
the punctual lights changes), ``"headlight"`` (Lambert lit from the camera, E = pi, so a
white surface facing the camera is 1.0; needs no lights), ``"unlit"`` (albedo + emissive).
Post-processing is a separate ``torchraster.post.PostChain`` applied by the caller (the CLI
does).
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import warnings
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint

from . import edge_aa, low_precision, relative
from ._validate import check_resolution, check_tensor
from .background import fit_background
from .dissolve import Dissolve
from .gbuffer import CHANNELS, GBuffer, MipCache, check_channels, geometry_pass
from .material import Material
from .mesh import transform_points, vertex_normals
from .motion import (
    MOTION_CHANNELS,
    OtherDepth,
    OtherFrame,
    face_depth_slope,
    flow_from,
    motion_from,
    other_depth,
    reproject,
    validity_from,
)
from .numerics import compute_dtype, finish_low_precision, safe_normalize
from .post.ssr import environment_specular, specular_weight
from .raster import Fragments, antialias, antialias_topology, rasterize
from .scene import RenderScene, as_render_scene
from .settings import (
    LIT_MODELS,
    BackgroundSettings,
    RasterSettings,
    ShadingSettings,
    TextureSettings,
)
from .shading.ibl import Environment, content_key, shade_ibl
from .shading.lighting import shade
from .shading.lights import (
    AREA_SHADOW_TAPS,
    LIGHT_KINDS,
    AreaLights,
    Lights,
    area_equivalent_radius,
)
from .shading.models import get_model
from .shading.shadows import (
    ShadowMapCache,
    ShadowMaps,
    ShadowSettings,
    cull_local_views,
    directional_views,
    local_views,
    merge_shadow_steps,
    render_shadow_maps,
    shadow_visibility,
)
from .shading.surface import PixelSurface, Surface
from .shading.volumetric import Fog, apply_fog, surface_light_hook
from .transparency import (
    composite_over,
    face_alpha_modes,
    first_opaque,
    layer_opacity,
    select_layers,
)

log = logging.getLogger("torchraster")

#: Where each former ``Renderer`` keyword argument lives now: (settings class, field).
_MOVED = {
    "shading_options": ("ShadingSettings", "options"),
    "multiscatter": ("ShadingSettings", "multiscatter"),
    **{name: ("RasterSettings", name) for name in (
        "supersample", "edge_supersample", "antialias", "cull_backfaces", "alpha_layers",
        "max_batch", "camera_relative")},
    "texture_filter": ("TextureSettings", "filter"),
    "max_anisotropy": ("TextureSettings", "max_anisotropy"),
    "mip_cache_bytes": ("TextureSettings", "cache_bytes"),
    "environment_background": ("BackgroundSettings", "environment"),
    "background_image": ("BackgroundSettings", "image"),
    "background_fit": ("BackgroundSettings", "fit"),
    "shadow_settings": ("ShadowSettings", ""),
}
#: The ``Renderer`` argument that takes each settings class.
_GROUP_ARG = {"ShadingSettings": "shading", "RasterSettings": "raster",
              "TextureSettings": "textures", "BackgroundSettings": "background",
              "ShadowSettings": "shadows"}
_SHADING_NEEDS = {
    **{name: {"position", "normal", "albedo", "metallic", "roughness", "ao", "emissive", "mask"}
       for name in LIT_MODELS},
    "headlight": {"position", "normal", "albedo", "mask"},
    "unlit": {"albedo", "emissive", "mask"},
}
#: The G-buffer channels that need a RenderScene identity field (the field's name).
_LABEL_NEEDS = {"instance": ("face_object",), "semantic": ("face_object", "object_category"),
                "amodal": ("face_object",), "object_coords": ("object_coords",)}
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
        shading: one of :data:`SHADING` (a lit model without lights and environment is
            planned as ``"unlit"``).
        lights: ``(kind, count)`` of each light type present (count None for ambient).
        ssao: SSAO multiplies the AO before lighting.
        ibl: image-based lighting from the environment.
        background: ``"image <fit>"``, ``"environment"``, ``"colour"`` or ``"none"``.
        cull: back faces dropped: ``"none"``, ``"all"`` (``cull_backfaces=True``) or
            ``"single-sided"`` (faces of materials with ``double_sided=False``).
        derivatives: screen-space UV derivatives are computed (trilinear or anisotropic
            texturing).
        anisotropy: the most probes a pixel of anisotropic texture filtering
            (``TextureSettings(filter="anisotropic", max_anisotropy=...)``), 0 when it
            does not run (another filter, or no material has a texture).
        shadow_lights: ``(kind, light indices, settings)`` of each group of lights whose
            shadow maps are rendered (only lights with ``cast_shadows``, and only when some
            face casts and some face receives).
        shadow_maps: what the shadow pass rendered (views and sizes), filled in by
            ``forward`` (cascades that cover nothing are skipped there).
        layers: depth layers rasterized (> 1 for glTF ``MASK`` / ``BLEND`` materials).
        alpha: ``"none"``, ``"mask"`` (cut-outs: the first opaque layer is shaded) or
            ``"blend"`` (every layer shaded and composited front to back).
        antialias: silhouettes antialiased analytically (:func:`~torchraster.antialias`).
        fog: the steps of the volumetric fog pass (:mod:`~torchraster.shading.volumetric`):
            empty without ``Renderer(fog=...)``; else the analytic in-scattering, the
            march of the light shafts (which lights, how many steps) and the blur.
        multiscatter: the Cook-Torrance energy terms (multiple-scattering compensation and
            the matching diffuse reduction, :mod:`~torchraster.shading.energy`) for every
            light type: ``"pbr"`` with lights or an environment and
            ``ShadingSettings(multiscatter=True)``.
        ibl_specular: ``Environment(specular=...)`` when ``ibl``: ``"table"`` (the
            pre-integrated lobe table, the default), ``"split_sum"`` (prefiltered chain),
            ``"fitted"`` or ``"importance"`` (per-pixel filtered importance sampling).
        dissolve: the dissolve effect (:mod:`~torchraster.dissolve`), e.g.
            ``"dissolve t=0.5 edge 0.05"``; empty without ``Renderer(dissolve=...)``.
        ssr: screen-space reflections replace the environment's specular where the
            mirror ray hits (:mod:`~torchraster.post.ssr`): ``Renderer(ssr=SSR(...))``,
            ``"pbr"`` shading, no ``BLEND`` material, and some material smooth enough
            (roughness factor below the cut-off, or a metallic-roughness texture).
        amodal: the number N of objects whose whole silhouettes the main raster collects
            (the ``amodal`` channel, step ``amodal N objects``); 0 when not requested.
        motion: the steps of the motion pass (:mod:`~torchraster.motion`), one per
            requested channel: ``"flow forward"``, ``"flow forward valid"``,
            ``"flow backward"``, ``"flow backward valid"``, ``"motion vectors"``.
        chunks: the batch sizes of the consecutive calls a batch larger than
            ``RasterSettings(max_batch=...)`` was split into, filled in by ``forward``
            (step ``"batch B in K chunks of <= max_batch"``); empty when it ran in one call.
        edge_supersample: per-axis factor k of the edge antialiasing pass
            (:mod:`~torchraster.edge_aa`, ``RasterSettings(edge_supersample=k)``; 1 = off).
        edge_pixels: how many pixels (whole batch) that pass re-shaded at k x k
            sub-samples, filled in by ``forward`` (step ``"edge supersample kx: N pixels"``;
            None before).
        origin: the world point the render was computed relative to
            (``RasterSettings(camera_relative=...)``, :mod:`~torchraster.relative`), filled in by
            ``forward`` (step ``"camera-relative origin (x, y, z)"``); None when not.
        packed: surface channels the geometry pass keeps packed (covered pixels only, no
            frames; read by the lighting alone): step ``"gbuffer ... (packed ...)"``.

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
    fog: tuple[str, ...] = ()
    multiscatter: bool = False
    dissolve: str = ""
    ibl_specular: str = "table"
    anisotropy: int = 0
    ssr: bool = False
    amodal: int = 0
    motion: tuple[str, ...] = ()
    chunks: tuple[int, ...] = ()
    edge_supersample: int = 1
    edge_pixels: int | None = None
    origin: tuple[float, float, float] | None = None
    packed: frozenset[str] = frozenset()

    @property
    def steps(self) -> list[str]:
        """The passes in order, e.g. ``["rasterize 64x64", "gbuffer albedo,mask", ...]``."""
        cull = "" if self.cull == "none" else f" (cull {self.cull} back faces)"
        layers = f" {self.layers} layers" if self.layers > 1 else ""
        steps = [f"rasterize {self.resolution[0]}x{self.resolution[1]}{layers}{cull}",
                 "gbuffer " + ",".join(sorted(self.channels))
                 + (" (packed " + ",".join(sorted(self.packed)) + ")") * bool(self.packed)]
        if self.chunks:
            steps.insert(0, f"batch {sum(self.chunks)} in {len(self.chunks)} chunks of "
                            f"<= {max(self.chunks)}")
        if self.origin is not None:
            steps.insert(0, "camera-relative origin ({:.9g}, {:.9g}, {:.9g})".format(
                *self.origin))
        if self.amodal:
            steps.append(f"amodal {self.amodal} objects")
        steps += list(self.motion)
        if self.anisotropy:
            steps.append(f"anisotropic texture filtering {self.anisotropy}x")
        if self.shading in LIT_MODELS:
            if self.shadow_maps:
                steps += list(self.shadow_maps)
            else:
                steps += [f"shadow {kind}{list(ids)} {s.map_size}x{s.map_size} {s.filter}"
                          for kind, ids, s in self.shadow_lights]
            steps += [f"light {kind}" + (f" x{n}" if n else "") for kind, n in self.lights]
            steps += ["ssao"] * self.ssao + ["ibl"] * self.ibl
            if self.ibl:
                steps.append(f"ibl specular {self.ibl_specular}")
            steps += ["ssr"] * self.ssr
            steps += ["energy compensation"] * self.multiscatter
            if self.shading != "pbr":
                steps.append(f"shade {self.shading}")
        else:
            steps.append(self.shading)
        if self.dissolve:
            steps.append(self.dissolve)
        if self.alpha == "mask":
            steps.append("alpha mask (first opaque layer)")
        elif self.alpha == "blend":
            steps.append(f"blend {self.layers} layers front to back")
        if self.background != "none":
            steps.append(f"background {self.background}")
        steps += list(self.fog)
        if self.antialias:
            steps.append("antialias")
        if self.edge_supersample > 1:
            k = self.edge_supersample
            count = "" if self.edge_pixels is None else f": {self.edge_pixels} pixels"
            steps.append(f"edge supersample {k}x{count}")
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
        gbuffer: a :class:`~torchraster.GBuffer` holding the requested channels, each
            ``(B, C, H, W)`` (the others None); also a mapping ``{channel: image}``.
        plan: the :class:`RenderPlan` that ran.
    """

    image: torch.Tensor
    alpha: torch.Tensor
    gbuffer: GBuffer
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
    # scale-free test for rank < 4: equilibrate rows, then columns, by their largest entry
    # (a diagonal scaling changes no rank), then compare the singular values. Units and
    # translations (a camera km from the origin) scale rows and columns, not the rank.
    for dim in (-1, -2):
        big = m64.abs().amax(dim, keepdim=True)
        m64 = m64 / torch.where(big > 0, big, torch.ones_like(big))
    sv = torch.linalg.svdvals(m64)  # (B, 4), descending
    singular = sv[..., -1] <= 1e-12 * sv[..., 0]
    if bool(singular.any()):
        bad = singular.nonzero().flatten().tolist()
        raise ValueError(f"{name}: matrix of batch item(s) {bad} is singular (e.g. all zero, "
                         "or a look_at with eye == target); expected an invertible 4x4")
    return m


class Renderer(nn.Module):
    """Differentiable deferred renderer (see the module docstring for the data flow).

    Settings come in groups (:mod:`torchraster.settings`, the fields of the YAML ``render:``
    section); the effects are modules.

    Args:
        resolution: ``(H, W)`` or an int for a square image.
        shading: a :class:`~torchraster.settings.ShadingSettings`, or the name of its
            model (one of :data:`SHADING`): ``"pbr"`` (Cook-Torrance), the stylised
            ``"blinn_phong"``, ``"half_lambert"``, ``"toon"`` (same lights, shadows,
            ambient and environment as pbr, another BRDF for the punctual lights; see
            :mod:`torchraster.shading.models`), ``"headlight"`` or ``"unlit"``.
        raster: :class:`~torchraster.settings.RasterSettings`: supersampling, edge
            antialiasing (:mod:`torchraster.edge_aa`: pixels on geometric and shadow edges
            shaded at ``k x k`` sub-samples; labels and the G-buffer stay the 1x frame's;
            ``out.plan.edge_pixels`` counts them), analytic silhouette antialiasing
            (:func:`~torchraster.antialias`: gradients at silhouettes), back-face culling,
            the depth layers of MASK / BLEND materials (shadow maps ignore alpha: cut-outs
            cast solid shadows), ``max_batch`` and ``camera_relative`` (below).
        textures: :class:`~torchraster.settings.TextureSettings`: the filter
            (:mod:`torchraster.anisotropic` for ``"anisotropic"``; docs/benchmarks.md,
            quality-texture, measures each) and the bound of the mip-pyramid cache.
        background: :class:`~torchraster.settings.BackgroundSettings`, or the RGB of empty
            pixels: a colour, the environment (when one is given and shown), or an image
            (:func:`~torchraster.background.load_background`) fitted to the frame, which
            replaces both (the colour fills the bars of ``"contain"``).
        shadows: True: shadow maps for lights with ``cast_shadows``, with the default
            :class:`~torchraster.shading.shadows.ShadowSettings` for lights that carry none
            of their own (``lights.<kind>.shadow``); a ``ShadowSettings``: the same with
            these settings; False: no shadow pass at all, whatever the lights say.
        ssao: an enabled ``torchraster.post.SSAO`` module: its AO (from depth and view-space
            normals) multiplies the material AO before lighting (lit models only).
        ssr: an enabled ``torchraster.post.SSR`` module: screen-space reflections of the
            lit frame replace the environment's (IBL and ambient) specular where the
            mirror rays hit (``"pbr"`` only; planned only when some material may be
            smoother than its ``max_roughness``; not with ``BLEND`` materials).
        fog: a :class:`~torchraster.shading.volumetric.Fog`: exponential height fog lit by
            the lights (applied to surfaces and background before antialiasing). Lights
            with shadow maps cast light shafts; the others in-scatter unshadowed. With
            ``"headlight"`` / ``"unlit"`` shading only ``Fog.ambient`` lights the fog.
        dissolve: a :class:`~torchraster.dissolve.Dissolve`: surfaces are discarded where
            a seeded noise of their world position falls below its threshold (cut out like
            glTF ``MASK``, ``alpha_layers`` deep) and glow in a band above it; the glow is
            differentiable in the threshold.

    ``RasterSettings.max_batch``: a larger batch is split into consecutive chunks whose
    outputs are concatenated: the same images, alpha and G-buffer channels bit for bit,
    and memory that grows with ``max_batch`` instead of the batch (docs/benchmarks.md,
    section memory). With autograd on, each chunk is recomputed in backward
    (``torch.utils.checkpoint``), so the graph holds the chunks' inputs and outputs only
    (backward then costs one more forward). Every per-item input is sliced (cameras,
    per-item positions and vertex data, ``face_ranges``, lights and other frames of batch
    B, a ``(B, 3, h, w)`` background image, a ``(B,)`` dissolve threshold); an environment
    with per-item radiance, rotation or intensity raises NotImplementedError.
    ``out.plan.chunks`` reports the split.

    ``RasterSettings.camera_relative``: render in coordinates centred at the batch's mean
    eye (:mod:`torchraster.relative`): positions minus that origin are computed in float64
    and then cast, the view, point / spot lights, other frames, fog and dissolve shifted
    alike; the ``position`` channel is returned in world space (in the compute dtype, so far
    from the origin it carries that dtype's absolute rounding). None (default): automatic,
    when float64 positions meet a float32 projection (rendered in float32), a float64 view
    meets a float32 projection, or the farthest eye is more than ``relative.FAR_RATIO``
    (256) times the largest of the scene's extent, the eye's distance to the scene and the
    near plane from the origin; a scene near the origin is rendered exactly as with False
    (``out.plan.origin`` is None; else the origin, step ``camera-relative origin (x, y,
    z)``). Results come out in the positions' dtype, except float64 positions with a
    float32 projection under camera-relative rendering: float32. float32 positions far from
    the origin warn (their rounding cannot be undone; pass float64).

    Example:
        >>> import torchraster as tr
        >>> view = tr.camera.orbit([0.0, 90.0], 20.0, 3.0)  # two views: B = 2
        >>> out = Renderer(64, shading="headlight")(tr.load_spot(), view,
        ...                                         tr.camera.perspective(45.0, 1.0, 0.1))
        >>> out.image.shape, out.alpha.shape
        (torch.Size([2, 3, 64, 64]), torch.Size([2, 1, 64, 64]))
        >>> r = Renderer(64, shading="unlit", raster=RasterSettings(supersample=2))
        >>> r.plan(tr.load_spot()).resolution
        (128, 128)
    """

    def __init__(
        self,
        resolution: tuple[int, int] | int,
        *,
        shading: str | ShadingSettings = "pbr",
        raster: RasterSettings | None = None,
        textures: TextureSettings | None = None,
        background: BackgroundSettings | Sequence[float] | None = None,
        shadows: bool | ShadowSettings = True,
        ssao: nn.Module | None = None,
        ssr: nn.Module | None = None,
        fog: Fog | None = None,
        dissolve: Dissolve | None = None,
        **moved: Any,
    ) -> None:
        super().__init__()
        if moved:
            name = next(iter(moved))
            home = _MOVED.get(name)
            if home is None:
                raise TypeError(f"Renderer: unexpected keyword argument {name!r}")
            group, field_name = home
            if not field_name:
                raise TypeError(f"Renderer({name}=...): pass the {group} as "
                                f"Renderer(..., {_GROUP_ARG[group]}={group}(...))")
            raise TypeError(f"Renderer({name}=...): now {group}({field_name}=...), passed as "
                            f"Renderer(..., {_GROUP_ARG[group]}={group}({field_name}=...))")
        self.resolution = check_resolution(resolution)
        self.shading_settings = (ShadingSettings(shading) if isinstance(shading, str)
                                 else _check_group("shading", shading, ShadingSettings))
        self.raster_settings = _check_group("raster", raster, RasterSettings)
        self.texture_settings = _check_group("textures", textures, TextureSettings)
        if background is not None and not isinstance(background, BackgroundSettings):
            if isinstance(background, (str, bytes, Mapping)):
                raise TypeError(f"background: expected a BackgroundSettings or 3 floats "
                                f"(RGB), got {background!r}")
            background = BackgroundSettings(color=background)
        self.background_settings = background or BackgroundSettings()
        for name, module in (("ssao", ssao), ("ssr", ssr)):
            if module is not None and not isinstance(module, nn.Module):
                raise TypeError(f"{name}: expected a torchraster.post.{name.upper()} module or "
                                f"None, got {type(module).__name__}")
        self.ssao = ssao if ssao is not None and getattr(ssao, "enabled", True) else None
        self.ssr = ssr if ssr is not None and getattr(ssr, "enabled", True) else None
        self._raster_memo = _RasterMemo()
        self._kept_topology: tuple[torch.Tensor, torch.Tensor] | None = None
        self.mip_cache = MipCache(self.texture_settings.cache_bytes)
        if not isinstance(shadows, (bool, ShadowSettings)):
            raise TypeError(f"shadows: expected True, False or a ShadowSettings, got "
                            f"{shadows!r}")
        self.shadows = shadows is not False
        self.shadow_settings = shadows if isinstance(shadows, ShadowSettings) else (
            ShadowSettings())
        # depth maps of static casters and lights reused across calls (None: off)
        self.shadow_cache: ShadowMapCache | None = ShadowMapCache()
        if fog is not None and not isinstance(fog, Fog):
            raise TypeError(f"fog: expected a torchraster.shading.volumetric.Fog or None, got "
                            f"{type(fog).__name__}")
        self.fog = fog
        if dissolve is not None and not isinstance(dissolve, Dissolve):
            raise TypeError(f"dissolve: expected a torchraster.dissolve.Dissolve or None, got "
                            f"{type(dissolve).__name__}")
        self.dissolve = dissolve
        if self.raster_settings.edge_supersample > 1:
            for name in ("ssao", "ssr", "fog", "dissolve"):
                if getattr(self, name) is not None:
                    raise NotImplementedError(
                        f"RasterSettings.edge_supersample: not implemented with {name}= "
                        f"yet; use supersample instead")
        self.world_origin: torch.Tensor | None = None  # set on the inner camera-relative copy

    @property
    def shading(self) -> str:
        """The shading model's name (``shading_settings.model``)."""
        return self.shading_settings.model

    @property
    def shading_settings(self) -> ShadingSettings:
        """What the surfaces are shaded with."""
        return self._shading_settings

    @shading_settings.setter
    def shading_settings(self, settings: ShadingSettings) -> None:
        self._shading_settings = _check_group("shading_settings", settings, ShadingSettings)
        self.model = (get_model(LIT_MODELS[settings.model], **settings.options)
                      if settings.model in LIT_MODELS else None)


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
        if shading in LIT_MODELS and lights is None and environment is None:
            warnings.warn(f"Renderer(shading={shading!r}) got no lights and no environment: "
                          "rendering albedo + emissive (unlit). Pass lights= or "
                          "environment=, or use shading='unlit' to say so.", stacklevel=3)
            shading = "unlit"
        ssao = self.ssao is not None and shading in LIT_MODELS
        modes = {m.alpha_mode for m in scene.materials if m is not None}
        alpha = "blend" if "BLEND" in modes else "mask" if "MASK" in modes else "none"
        if self.dissolve is not None:
            alpha = "mask" if alpha == "none" else alpha  # discarded surfaces show what is behind
        if self.raster_settings.edge_supersample > 1 and alpha != "none":
            raise NotImplementedError(f"edge_supersample: not implemented with glTF "
                                      f"{alpha.upper()} materials yet; use supersample instead")
        ssr = self._plan_ssr(scene, shading, alpha)
        if ssr and environment is not None and environment.sun_threshold is not None:
            raise NotImplementedError(
                "Environment(sun_threshold=...): screen-space reflections read the "
                "environment's specular where their rays miss, which holds the map without "
                "its extracted sun; use sun_threshold=None with Renderer(ssr=...)")
        _check_label_fields(scene, requested)
        channels = (set(requested) - {"amodal"}) | (
            _SHADING_NEEDS[shading] - _neutral_channels(scene.materials)) | (
            {"depth"} if ssao or ssr else set())
        if alpha != "none":
            channels.add("alpha")
        if self.fog is not None or self.dissolve is not None:
            channels.add("position")
        light_kinds = []
        if shading in LIT_MODELS and lights is not None:
            if lights.ambient is not None:
                light_kinds.append(("ambient", None))
            for kind in LIGHT_KINDS:
                group = getattr(lights, kind)
                if group is not None and group.count:
                    light_kinds.append((kind, group.count))
        if self.background_settings.image is not None:
            background = f"image {self.background_settings.fit}"
        elif environment is not None and self.background_settings.environment:
            background = "environment"
        elif any(c != 0 for c in self.background_settings.color):
            background = "colour"
        else:
            background = "none"
        textured = any(m is not None and any(getattr(m, s) is not None for s in _TEXTURE_SLOTS)
                       for m in scene.materials)
        single_sided = [m is not None and not m.double_sided for m in scene.materials]
        rs, ts = self.raster_settings, self.texture_settings
        cull = "all" if rs.cull_backfaces else "single-sided" if any(single_sided) else "none"
        s = rs.supersample
        shadow_lights = ()
        if shading in LIT_MODELS and lights is not None and self.shadows:
            shadow_lights = self._plan_shadows(scene, lights)
        fog = () if self.fog is None else self._plan_fog(
            lights if shading in LIT_MODELS else None, shadow_lights,
            shading in LIT_MODELS and environment is not None)
        return RenderPlan(
            resolution=(self.resolution[0] * s, self.resolution[1] * s), supersample=s,
            channels=frozenset(channels), requested=frozenset(requested), shading=shading,
            lights=tuple(light_kinds), ssao=ssao,
            ibl=shading in LIT_MODELS and environment is not None, background=background, cull=cull,
            derivatives=textured and ts.filter in ("trilinear", "anisotropic"),
            anisotropy=ts.max_anisotropy if textured and ts.filter == "anisotropic" else 0,
            shadow_lights=shadow_lights, layers=rs.alpha_layers if alpha != "none" else 1,
            alpha=alpha, antialias=rs.antialias, fog=fog, dissolve=self._plan_dissolve(),
            multiscatter=self.shading_settings.multiscatter and shading == "pbr" and bool(
                light_kinds or environment is not None),
            ibl_specular=environment.specular_mode if environment is not None
            else "table", ssr=ssr,
            amodal=scene.num_objects if "amodal" in requested else 0,
            motion=_motion_steps(requested), edge_supersample=self.raster_settings.edge_supersample,
            packed=_packed_channels(shading, alpha, channels, requested, shadow_lights, ssao,
                                    fog, ssr, self.raster_settings.edge_supersample))

    def _plan_ssr(self, scene: RenderScene, shading: str, alpha: str) -> bool:
        """SSR runs for ``"pbr"`` when some material may be smoother than the cut-off."""
        if self.ssr is None or shading != "pbr":
            return False
        if alpha == "blend":
            warnings.warn("Renderer(ssr=...): screen-space reflections are not implemented "
                          "for scenes with BLEND materials; rendered without them",
                          NotImplementedWarning, stacklevel=4)
            return False
        cutoff = getattr(self.ssr, "max_roughness", 1.0)
        def smooth(m: Material) -> bool:  # the factor may need grad (a material fit)
            rough = float(torch.as_tensor(m.roughness_factor).detach())
            return m.metallic_roughness_texture is not None or rough < cutoff

        return any(m is not None and smooth(m) for m in scene.materials)

    def _plan_dissolve(self) -> str:
        """The dissolve step of the plan ("" without the effect)."""
        d = self.dissolve
        if d is None:
            return ""
        t = d.threshold
        if isinstance(t, torch.Tensor):
            t = float(t.detach().reshape(-1)[0]) if t.numel() == 1 else None
        t = f"{t:.3g}" if t is not None else f"{d.threshold.numel()} values"
        return f"dissolve t={t} edge {d.edge_width:g}"

    def _plan_fog(self, lights: Lights | None,
                  shadow_lights: tuple[tuple[str, tuple[int, ...], ShadowSettings], ...],
                  environment: bool = False) -> tuple[str, ...]:
        """The steps of the fog pass: analytic in-scattering (ambient, unshadowed
        directional lights), the march (point / spot lights, shadowed directional lights:
        light shafts) and its blur; then the lights dimmed by the fog on their way in."""
        fog = self.fog
        analytic, marched = ["ambient"] if lights is not None and lights.ambient is not None \
            else [], []
        if environment:
            analytic.append("environment")
        shadowed = {(kind, i) for kind, ids, _ in shadow_lights for i in ids}
        dimmed = []
        for kind in LIGHT_KINDS:
            part = None if lights is None else getattr(lights, kind)
            for i in range(0 if part is None else part.count):
                dimmed.append(f"{kind}[{i}]")
                if (kind, i) in shadowed:
                    marched.append(f"{kind}[{i}] shadowed")
                elif kind == "directional":
                    analytic.append(f"{kind}[{i}]")
                else:
                    marched.append(f"{kind}[{i}]")
        steps = ["fog analytic" + (f" ({', '.join(analytic)})" if analytic else "")]
        if marched:
            jitter = " jittered" if fog.jitter else ""
            steps.append(f"fog march {fog.steps} steps{jitter}: {', '.join(marched)}")
            if fog.blur > 0:
                steps.append(f"fog blur {fog.blur:g} px")
        if fog.light_transmittance and dimmed:
            steps.append(f"fog light path: {', '.join(dimmed)}")
        return tuple(steps)

    def _plan_shadows(self, scene: RenderScene, lights: Lights
                      ) -> tuple[tuple[str, tuple[int, ...], ShadowSettings], ...]:
        """Groups of shadow-casting lights with one settings object each; none when no
        face casts or none receives (and no fog needs the maps for light shafts)."""
        receivers = (scene.receive_shadows,) if self.fog is None else ()
        for flags in (scene.cast_shadows, *receivers):
            if flags is not None and not bool(flags.any()):
                return ()
        groups: list[tuple[str, tuple[int, ...], ShadowSettings]] = []
        for kind in LIGHT_KINDS:
            part = getattr(lights, kind)
            if part is None or part.count == 0:
                continue
            casting = part.cast_shadows.any(0).nonzero().flatten().tolist()
            by_settings: dict[ShadowSettings, list[int]] = {}
            for i in casting:
                settings = part.settings_of(i) or self.shadow_settings
                if kind == "area":
                    settings = _area_shadow_settings(part, i, part.settings_of(i) is not None,
                                                     settings)
                by_settings.setdefault(settings, []).append(i)
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
        next_frame: OtherFrame | None = None,
        previous_frame: OtherFrame | None = None,
    ) -> RenderOutput:
        """Render a batch of scenes.

        Args:
            scene: a :class:`~torchraster.scene.RenderScene`, a Mesh, an ``io.Scene`` or a
                list of B meshes (item i draws mesh i).
            view: ``(B, 4, 4)`` or ``(4, 4)`` world -> view; proj: likewise (OpenGL clip).
            lights: :class:`Lights` of batch size B or 1, or None.
            environment: an :class:`Environment` for image-based lighting / background.
            channels: G-buffer channels to return (see :data:`CHANNELS`).
            next_frame: the vertex positions (same vertices) and camera of the next frame,
                a :class:`~torchraster.motion.OtherFrame`; needed by ``flow_forward`` and
                ``flow_forward_valid``.
            previous_frame: likewise for the previous frame; needed by ``flow_backward``,
                ``flow_backward_valid`` and ``motion``. For ``*_valid`` channels the frame's
                visible depth is rasterized unless ``OtherFrame.depth`` is set, and stored
                there (the same frame passed again is not rasterized again).

        Returns:
            :class:`RenderOutput` (image, alpha, requested G-buffer channels, plan).
        """
        scene = as_render_scene(scene)
        view = _check_camera("view", view)
        proj = _check_camera("proj", proj)
        shift = relative.plan_shift(self.raster_settings.camera_relative, scene.positions,
                                    view, proj)
        if shift is not None:  # far from the origin: render camera-relative (relative.py)
            return relative.render(self, shift, scene, view, proj, lights, environment,
                                   channels, next_frame, previous_frame)
        if low_precision.needs_lift(scene, view, proj, lights, {
                "next_frame": next_frame, "previous_frame": previous_frame}):
            return self._forward_lifted(scene, view, proj, lights, environment, channels,
                                        next_frame, previous_frame)
        plan = self.plan(scene, lights, environment, channels)
        frames = _check_frames(plan.requested, next_frame=next_frame,
                               previous_frame=previous_frame)
        log.debug("torchraster plan: %s", plan)

        positions = scene.positions
        b = max(view.shape[0], proj.shape[0], scene.batch_size)
        for name, n in (("view", view.shape[0]), ("proj", proj.shape[0]),
                        ("scene", scene.batch_size)):
            if n not in (1, b):
                raise ValueError(f"{name}: batch size {n} does not match the others' {b} "
                                 "(use 1 to share)")
        for name, frame in frames.items():
            frame.check_against(name, positions.shape[-2], b)
            frame.check_depth(name, plan.resolution, b)
        if self.raster_settings.max_batch is not None and b > self.raster_settings.max_batch:
            return self._forward_chunks(scene, view, proj, lights, environment, channels,
                                        frames, b)
        view, proj = view.expand(b, 4, 4), proj.expand(b, 4, 4)
        clip = _clip_positions(positions, view, proj, b)
        face_ranges = scene.face_ranges
        if face_ranges is not None and face_ranges.shape[0] != b:
            face_ranges = face_ranges.expand(b, 2)
        frags = self._raster_memo.rasterize(clip, scene.faces, plan, _cull_mask(plan, scene),
                                            face_ranges, objects=_amodal_objects(plan, scene))
        normals = scene.normals
        if "normal" in plan.channels and normals is None:
            normals = vertex_normals(positions, scene.faces)
        layers = frags.layers if plan.layers > 1 else (frags,)
        release = not torch.is_grad_enabled() and not self._raster_memo.holds(frags)
        gbs = [geometry_pass(f, plan.channels, positions=positions, view=view,
                             normals=normals, uvs=scene.uvs, tangents=scene.tangents,
                             face_material=scene.face_material, materials=scene.materials,
                             texture_filter=self.texture_settings.filter, mip_cache=self.mip_cache,
                             max_anisotropy=self.texture_settings.max_anisotropy,
                             face_object=scene.face_object,
                             object_category=scene.object_category,
                             object_coords=scene.object_coords,
                             release_derivatives=release and not plan.motion,
                             packed=plan.packed)
               for f in layers]
        if plan.motion:  # per layer: the alpha modes then select them like the other channels
            gbs = _motion_channels(plan, scene, layers, gbs, frames, face_ranges, b,
                                   self._raster_memo)
        if release:
            for f in layers:  # memory: everything is interpolated (face ids, depth stay)
                f.release_interpolation()
        eye = camera_position(view.to(positions.dtype))
        groups = None
        if plan.shadow_lights:
            groups, lights_b = self._shadow_maps(plan, scene, view, proj, lights, b, face_ranges,
                                                 receivers=gbs)
            plan = replace(plan, shadow_maps=tuple(st for g in groups for st in g.steps))

        hooks: list = []  # the shadow hook of each radiance_of call (edge antialiasing)

        def radiance_of(gb: GBuffer, face_id: torch.Tensor, glow: torch.Tensor | None = None,
                        rows: int = plan.resolution[0], last_read: bool = False
                        ) -> torch.Tensor:
            """Radiance of the surfaces ``gb``; ``rows``: pixel rows of the grid they sample
            (the shadow filter's pixel footprint); ``last_read``: nothing reads ``gb.albedo``
            after this (the lighting may write its radiance there)."""
            hook = None if groups is None else self._shadow_hook(groups, lights_b, scene, gb,
                                                                 face_id, view, b, proj, rows)
            hooks.append(hook)
            if plan.fog and lights is not None and self.fog.light_transmittance:
                hook = surface_light_hook(self.fog, lights, gb.position, gb.mask, hook)
            rad = self._shade(plan, gb, view, proj, eye, lights, environment, hook,
                              reuse_albedo=last_read)
            if glow is not None:  # the dissolve's glowing band (0 where discarded)
                rad = rad + glow.to(rad)
            if not torch.is_grad_enabled():  # a fresh frame: masked in place (memory)
                return rad.mul_(gb.mask)
            if glow is None and plan.shading in LIT_MODELS:
                return rad  # shade() zeroed the uncovered pixels (the mask is 0 / 1): no copy
            return rad * gb.mask

        visible = frags  # the face ids / depths antialiasing sees
        if plan.alpha == "none":
            gb = gbs[0]
            # memory: without autograd the lighting may write into the albedo frame when no
            # output or later pass (SSR, fog, the edge pass's 1x frame) reads it
            last = not torch.is_grad_enabled() and "albedo" not in plan.requested and not (
                plan.ssr or plan.fog or plan.edge_supersample > 1)
            radiance, coverage = radiance_of(gb, frags.face_id, last_read=last), gb.mask
            transmittance = 1 - coverage
            if not (plan.ssr or plan.fog or plan.edge_supersample > 1):  # nothing reads the
                # surface frames again: only the outputs, mask and alpha stay alive (memory:
                # with autograd 36 B/px of position, normal and albedo at the composite)
                keep = set(plan.requested) | {"mask", "alpha"}
                gb = gbs[0] = gb.replace(packed=None, **{ch: None for ch in gb.channels()
                                                         if ch not in keep})
        else:
            modes, cutoffs = face_alpha_modes(scene.materials, scene.face_material,
                                              scene.faces.shape[0], positions.device)
            opacity = [layer_opacity(g, f.face_id, modes, cutoffs) for g, f in zip(
                gbs, layers, strict=True)]
            glows = None
            if plan.dissolve:  # discard below the threshold, like a MASK cut-out; glow above
                cuts = [self.dissolve.terms(g.position, a) for a, g in zip(opacity, gbs,
                                                                           strict=True)]
                opacity = [a * keep.to(a) for a, (keep, _) in zip(opacity, cuts, strict=True)]
                glows = [glow for _, glow in cuts]
            if plan.alpha == "mask":
                first = first_opaque(opacity)
                gb = select_layers(gbs, first)
                fid = torch.gather(torch.stack([f.face_id for f in layers]), 0,
                                   first.squeeze(1).unsqueeze(0))[0]
                coverage = torch.gather(torch.stack(opacity), 0, first.unsqueeze(0))[0]
                depth = torch.gather(torch.stack([f.depth for f in layers]), 0,
                                     first.squeeze(1).unsqueeze(0))[0]
                visible = _Visible(fid, depth)
                glow = None if glows is None else torch.gather(
                    torch.stack(glows), 0, first.unsqueeze(0).expand(1, -1, 3, -1, -1))[0]
                radiance = radiance_of(gb, fid, glow) * coverage
                transmittance = 1 - coverage
            else:
                colors, used = [], []
                transmittance = torch.ones_like(opacity[0])
                for k, (g, f, a) in enumerate(zip(gbs, layers, opacity, strict=True)):
                    if not bool((transmittance * a > 0).any()):
                        break  # everything behind is hidden
                    colors.append(radiance_of(g, f.face_id, None if glows is None else glows[k]))
                    used.append(a)
                    transmittance = transmittance * (1 - a)
                radiance, transmittance = composite_over(  # like: nothing opaque in view
                    colors, used, like=(gbs[0].albedo, opacity[0]))
                gb = select_layers(gbs, first_opaque(opacity))
        if plan.ssr:  # replace the environment's specular where the mirror rays hit
            radiance = self._reflect(plan, gb, radiance, coverage, view, proj, eye, lights,
                                     environment)
        color = torch.tensor(self.background_settings.color, device=radiance.device,
                             dtype=radiance.dtype)
        if plan.background == "environment":
            rays = view_rays(view, proj, plan.resolution).to(radiance.dtype)
            background = environment.background(rays)
        elif plan.background.startswith("image"):
            background = fit_background(self.background_settings.image.to(radiance),
                                        plan.resolution, self.background_settings.fit, color)
        else:
            background = color.view(1, 3, 1, 1)
        if plan.alpha == "none" and not torch.is_grad_enabled():  # radiance is this call's
            for c in range(3):  # own frame: added in place, a channel at a time (memory)
                radiance[:, c:c + 1].add_(transmittance * background[:, c:c + 1])
            image = radiance
        else:  # one frame (no (B, 3, H, W) product first)
            image = torch.addcmul(radiance, transmittance, background.to(radiance))
        if plan.fog:
            image = self._apply_fog(plan, image, gb, view, proj, eye, lights, groups, scene,
                                    face_ranges, b, environment if plan.ibl else None)
        if plan.alpha != "none":
            alpha = 1 - transmittance
        else:
            alpha = gb.mask * gb.alpha if gb.alpha is not None else gb.mask
        if plan.antialias:  # one call for colour and coverage
            both = antialias(torch.cat([image, alpha.to(image.dtype)], 1), visible, clip,
                             scene.faces, topology=self._topology(scene.faces))
            image, alpha = both[:, :3], both[:, 3:]
        if plan.edge_supersample > 1:  # re-shade the edge pixels at k x k sub-samples
            image, alpha, plan = self._edge_pass(plan, scene, clip, face_ranges, normals, view,
                                                 proj, radiance_of, hooks[0], background,
                                                 environment, image, alpha)
        outputs = GBuffer(**{ch: getattr(gb, ch) for ch in plan.requested})
        if self.world_origin is not None:  # camera-relative: the position channel in world
            outputs = relative.world_position(outputs, gb.mask, self.world_origin)
        if "amodal" in plan.requested:  # the main raster's candidates, per object
            outputs = outputs.replace(amodal=frags.silhouettes)
        if plan.supersample > 1:
            s = plan.supersample
            image, alpha = F.avg_pool2d(image, s), F.avg_pool2d(alpha, s)
            outputs = outputs.downsample(s)
        return RenderOutput(image=image, alpha=alpha, gbuffer=outputs, plan=plan)

    def _forward_lifted(self, scene: RenderScene, view: torch.Tensor, proj: torch.Tensor,
                        lights: Lights | None, environment: Environment | None,
                        channels: Iterable[str], next_frame: OtherFrame | None,
                        previous_frame: OtherFrame | None) -> RenderOutput:
        """``forward`` of float16 / bfloat16 inputs: rendered in float32, results cast back
        to the positions' dtype (``low_precision``); other frames' rasterized depths are
        stored back on the caller's frames."""
        frames = {"next_frame": next_frame, "previous_frame": previous_frame}
        lifted = {k: low_precision.lift_frame(f) for k, f in frames.items()}
        out = self.forward(low_precision.lift_scene(scene), low_precision.lift(view),
                           low_precision.lift(proj), low_precision.lift_lights(lights),
                           environment, channels, **lifted)
        for k, f in frames.items():
            if isinstance(f, OtherFrame) and f.depth is None:
                f.depth = lifted[k].depth
        image, alpha, gbuffer = low_precision.finish(out.image, out.alpha, out.gbuffer,
                                                     scene.positions.dtype)
        return replace(out, image=image, alpha=alpha, gbuffer=gbuffer)

    def _forward_chunks(self, scene: RenderScene, view: torch.Tensor, proj: torch.Tensor,
                        lights: Lights | None, environment: Environment | None,
                        channels: Iterable[str], frames: dict[str, OtherFrame], b: int
                        ) -> RenderOutput:
        """``forward`` of a batch of ``b > max_batch`` items: consecutive chunks of at most
        ``max_batch`` items, every per-item input sliced alike, outputs concatenated (with
        autograd on, each chunk checkpointed)."""
        if environment is not None and _environment_per_item(environment):
            raise NotImplementedError(
                "max_batch: an Environment with per-item radiance, rotation or intensity "
                "cannot be split into chunks yet; use max_batch=None or a shared environment")
        if environment is not None and torch.is_grad_enabled():  # built once, outside the
            environment.prepare(compute_dtype(scene.positions))  # checkpointed chunks
        outs: list[RenderOutput] = []
        for start in range(0, b, self.raster_settings.max_batch):
            sl = slice(start, min(start + self.raster_settings.max_batch, b))
            # one renderer per chunk (a checkpointed chunk reruns it in backward): it shares
            # the modules, buffers and caches, holds the chunk's items and splits no further
            inner = copy.copy(self)
            # no further split; camera-relative decided (and applied) once for the batch
            inner.raster_settings = replace(self.raster_settings, max_batch=None,
                                            camera_relative=False)
            image = self.background_settings.image
            if image is not None and image.shape[0] == b:
                inner.background_settings = replace(self.background_settings, image=image[sl])
            threshold = None if self.dissolve is None else self.dissolve.threshold
            if isinstance(threshold, torch.Tensor) and threshold.numel() == b > 1:
                inner.dissolve = replace(self.dissolve, threshold=threshold.reshape(-1)[sl])
            args = (_scene_items(scene, sl, b), _items(view, sl, b), _items(proj, sl, b),
                    _lights_items(lights, sl, b), environment, channels)
            kwargs = {name: OtherFrame(_items(f.positions, sl, b, 3), _items(f.view, sl, b, 3),
                                       _items(f.proj, sl, b, 3),
                                       None if f.depth is None else OtherDepth(
                                           *(_items(t, sl, b) for t in f.depth)))
                      for name, f in frames.items()}
            if torch.is_grad_enabled():  # keep only the chunk's outputs; recompute in backward
                plans: list[RenderPlan] = []
                names: list[str] = []

                def run(*_, inner=inner, args=args, kwargs=kwargs, plans=plans, names=names):
                    out = inner.forward(*args, **kwargs)
                    plans[:] = [out.plan]
                    names[:] = list(out.gbuffer)
                    return (out.image, out.alpha, *out.gbuffer.values())

                # the dummy input gives checkpoint a tensor argument (the inputs are read
                # from the closure, which non-reentrant checkpointing supports)
                res = checkpoint(run, view, use_reentrant=False)
                outs.append(RenderOutput(res[0], res[1],
                                         GBuffer(**dict(zip(names, res[2:], strict=True))),
                                         plans[0]))
            else:
                outs.append(inner.forward(*args, **kwargs))
        shadow_maps = merge_shadow_steps(st for o in outs for st in o.plan.shadow_maps)
        plan = replace(outs[0].plan, shadow_maps=shadow_maps,
                       chunks=tuple(o.image.shape[0] for o in outs))
        if plan.edge_pixels is not None:
            plan = replace(plan, edge_pixels=sum(o.plan.edge_pixels for o in outs))
        return RenderOutput(image=torch.cat([o.image for o in outs]),
                            alpha=torch.cat([o.alpha for o in outs]),
                            gbuffer=GBuffer(**{k: torch.cat([o.gbuffer[k] for o in outs])
                                               for k in outs[0].gbuffer}), plan=plan)

    def _reflect(self, plan: RenderPlan, gb: GBuffer, radiance: torch.Tensor,
                 coverage: torch.Tensor, view: torch.Tensor, proj: torch.Tensor,
                 eye: torch.Tensor, lights: Lights | None,
                 environment: Environment | None) -> torch.Tensor:
        """Screen-space reflections of the shaded surfaces ``gb`` (radiance times
        ``coverage``): the split-sum weight and the environment specular already in the
        image (:func:`~torchraster.post.ssr.environment_specular`) go to the SSR module,
        which swaps one for the other where its rays hit."""
        dt = radiance.dtype
        b = radiance.shape[0]
        n = safe_normalize(gb.normal.to(dt), dim=1)
        v = safe_normalize(eye.to(dt)[:, :, None, None] - gb.position.to(dt), dim=1)
        rough, metal = gb.roughness.to(dt), gb.metallic.to(dt)
        weight = specular_weight((n * v).sum(1, keepdim=True), gb.albedo.to(dt), metal, rough,
                                 multiscatter=plan.multiscatter)
        ambient = None
        if lights is not None and lights.ambient is not None:
            ambient = lights.ambient.to(device=radiance.device, dtype=dt).expand(b, 9, 3)
        fallback = environment_specular(n, v, rough, weight, gb.ao,
                                        environment if plan.ibl else None, ambient)
        normal_view = torch.einsum("bij,bjhw->bihw", view[:, :3, :3].to(dt), n)
        depth = torch.where(gb.mask > 0, gb.depth.to(dt), torch.zeros_like(rough))
        cov = coverage.to(dt)
        surface = Surface(albedo=gb.albedo.to(dt), metallic=metal, roughness=rough)
        return self.ssr(radiance, depth, normal_view, surface, projection=proj.to(dt),
                        fallback=fallback * cov, weight=weight * cov)

    def _apply_fog(self, plan: RenderPlan, image: torch.Tensor, gb: GBuffer,
                   view: torch.Tensor, proj: torch.Tensor, eye: torch.Tensor,
                   lights: Lights | None, groups: list[ShadowMaps] | None, scene: RenderScene,
                   face_ranges: torch.Tensor | None, b: int,
                   environment: Environment | None = None) -> torch.Tensor:
        """The fog pass (:func:`~torchraster.shading.volumetric.apply_fog`) over the
        visible surfaces of ``gb`` (the first opaque layer) and the background; the
        environment of image-based lighting also lights the fog."""
        rays = view_rays(view, proj, plan.resolution).to(image.dtype)
        eye = eye.to(image.dtype).expand(b, 3)
        covered = gb.mask > 0
        dist = (gb.position.to(image.dtype) - eye[:, :, None, None]).norm(dim=1, keepdim=True)
        dist = torch.where(covered, dist, torch.full_like(dist, float("inf")))
        lit = plan.shading in LIT_MODELS
        bounds = _caster_bounds(scene.positions, scene.faces, face_ranges, b).to(image.dtype)
        return apply_fog(image, dist, eye, rays, self.fog, lights if lit else None,
                         (groups or ()) if lit else (), view, bounds, environment)

    def _shadow_maps(self, plan: RenderPlan, scene: RenderScene, view: torch.Tensor,
                     proj: torch.Tensor, lights: Lights, b: int,
                     face_ranges: torch.Tensor | None,
                     receivers: Sequence[GBuffer] | None = None
                     ) -> tuple[list[ShadowMaps], Lights]:
        """Render the planned shadow maps (one batched pass per map size); returns the
        groups and the lights expanded to the batch.

        ``receivers``: the G-buffers of every depth layer of the frame (their positions
        are the surfaces that look shadows up): the point / spot views none of them, no
        fog sample along the view rays and (edge antialiasing: sub-samples not known
        yet) nothing in the scene's box can read, or that hold no caster, are not rendered
        (:func:`~torchraster.shading.shadows.cull_local_views`; the same image). None:
        every view is rendered."""
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
        # casters shared by every item (one mesh, no face ranges): point / spot views of
        # the lights as given, so lights of batch 1 (one scene seen by B cameras) have one
        # set of maps for the batch, read by every item (memory: not B copies of them)
        shared = face_ranges is None and (positions.dim() == 2 or positions.shape[0] == 1)
        given = lights.to(device=positions.device, dtype=positions.dtype)
        lights = lights.expand(b) if lights.batch_size == 1 and b > 1 else lights
        lights = lights.to(device=positions.device, dtype=positions.dtype)
        groups: list[ShadowMaps] = []
        for kind, ids, settings in plan.shadow_lights:
            part = getattr(lights, kind).select(torch.tensor(ids))
            if kind == "area":  # a cube map from the centre, PCSS of the light's size
                source = given if shared else lights
                part = source.area.select(torch.tensor(ids))
                g = local_views("point", part.position, None, None, settings,
                                bounds[:1] if shared else bounds)
                g.kind = "area"
            elif kind == "directional":
                g = directional_views(part.direction, settings, bounds, view.to(positions.dtype),
                                      proj.to(positions.dtype), receiver_bounds=scene_bounds)
            else:
                if shared:
                    part = getattr(given, kind).select(torch.tensor(ids))
                g = local_views(kind, part.position,
                                part.direction if kind == "spot" else None,
                                part.outer_cone_angle if kind == "spot" else None, settings,
                                bounds[:1] if shared else bounds)
            g.lights = list(ids)
            groups.append(g)
        # cube maps only: a single spot map is read by most frames, and the receivers' tile
        # boxes cost more than its render saves (docs/benchmarks.md, shadows)
        local = [g for g in groups if g.layout == "cube"]
        if receivers and local and all(gb.position is not None for gb in receivers):
            points = [(gb.position, gb.mask) for gb in receivers]
            segments = None
            if plan.fog:  # fog samples: eye + t ray, 0 <= t <= the surface (inf: none)
                eye = camera_position(view)
                rays = view_rays(view, proj, plan.resolution)
                length = None
                for gb in receivers:  # any layer may be the one the fog stops at
                    d = (gb.position.detach().to(eye.dtype) - eye[:, :, None, None]).norm(
                        dim=1, keepdim=True)
                    d = torch.where(gb.mask > 0, d, torch.full_like(d, float("inf")))
                    length = d if length is None else torch.maximum(length, d)
                segments = (eye, rays, length)
            boxes = scene_bounds if plan.edge_supersample > 1 else None
            cull_local_views(local, points, segments, boxes, (positions, faces, face_ranges))
        render_shadow_maps(groups, positions, faces, face_ranges, cache=self.shadow_cache)
        return groups, lights

    def _shadow_hook(self, groups: list[ShadowMaps], lights: Lights, scene: RenderScene,
                     gb: GBuffer, face_id: torch.Tensor, view: torch.Tensor, b: int,
                     proj: torch.Tensor, rows: int):
        """The ``shade`` visibility hook of the surfaces in ``gb`` (face ids ``face_id``),
        seen in a grid of ``rows`` pixel rows (``ShadowSettings.pixel_radius``)."""
        receive = gb.mask > 0
        pixel = None
        if any(g.settings.pixel_radius > 0 for g in groups):
            pixel = pixel_size(gb.position, view, proj, rows)
        if scene.receive_shadows is not None:
            flags = scene.receive_shadows.to(face_id.device)
            receive = receive & flags[face_id.clamp_min(0)].unsqueeze(1) & (
                face_id >= 0).unsqueeze(1)
        full: dict[str, torch.Tensor] = {}
        for g in groups:
            vis = shadow_visibility(g, gb.position, safe_normalize(gb.normal, dim=1), receive,
                                    view, pixel)
            count = getattr(lights, g.kind).count
            if g.kind not in full and list(g.lights) == list(range(count)):
                full[g.kind] = vis  # the group is every light of its kind: no copy
                continue
            if g.kind not in full:
                full[g.kind] = vis.new_ones(b, count, 1, *vis.shape[-2:])
            full[g.kind] = full[g.kind].index_copy(
                1, torch.tensor(g.lights, device=vis.device), vis)

        def hook(kind: str, sl: slice) -> torch.Tensor | None:
            return full[kind][:, sl] if kind in full else None

        return hook

    def _shade(self, plan: RenderPlan, gb: GBuffer, view: torch.Tensor, proj: torch.Tensor,
               eye: torch.Tensor, lights: Lights | None,
               environment: Environment | None, visibility=None,
               reuse_albedo: bool = False) -> torch.Tensor:
        """Radiance ``(B, 3, H, W)`` of the covered pixels, by the plan's shading path
        (``reuse_albedo``: ``gb.albedo`` is read by nothing after, see ``shade``)."""
        if plan.shading == "headlight":
            to_eye = safe_normalize(eye[:, :, None, None] - gb.position, dim=1)
            return gb.albedo * (gb.normal * to_eye).sum(1, keepdim=True).clamp(min=0)
        if plan.shading == "unlit":  # a new frame (the caller may change it in place)
            return gb.albedo + gb.emissive if gb.emissive is not None else gb.albedo.clone()
        if plan.ssao:
            normal_view = torch.einsum("bij,bjhw->bihw", view[:, :3, :3].to(gb.normal.dtype),
                                       gb.normal)
            depth = torch.where(gb.mask > 0, gb.depth, torch.zeros_like(gb.depth))
            ao = self.ssao(depth, normal_view, projection=proj.to(depth.dtype))
            gb = gb.replace(ao=gb.ao * ao if gb.ao is not None else ao)
        ibl = None
        if plan.ibl:
            def ibl(s: PixelSurface) -> torch.Tensor:  # the covered pixels only (the rest
                return shade_ibl(s.n, s.v, s.albedo, s.metallic, s.roughness,  # is 0, as
                                 None, environment, multiscatter=plan.multiscatter,  # after
                                 mask=gb.mask)  # the mask below)
        return shade(gb, camera_position=eye, lights=lights, model=self.model, ibl=ibl,
                     multiscatter=plan.multiscatter,
                     visibility=visibility, reuse_albedo=reuse_albedo)

    def _topology(self, faces: torch.Tensor) -> torch.Tensor:
        """``antialias_topology(faces)``, kept for the next call with the same faces
        (compared by value: a scene rebuilt every frame passes equal faces)."""
        kept = self._kept_topology
        if kept is not None and kept[0].shape == faces.shape and kept[0].device == faces.device \
                and torch.equal(kept[0], faces):
            return kept[1]
        topology = antialias_topology(faces)
        self._kept_topology = (faces.clone(), topology)
        return topology

    def _edge_pass(self, plan: RenderPlan, scene: RenderScene, clip: torch.Tensor,
                   face_ranges: torch.Tensor | None, normals: torch.Tensor | None,
                   view: torch.Tensor, proj: torch.Tensor, radiance_of, hook,
                   background: torch.Tensor, environment: Environment | None,
                   image: torch.Tensor, alpha: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor, RenderPlan]:
        """Edge antialiasing (:mod:`~torchraster.edge_aa`): rasterize at ``k x``, flag the
        edge pixels (geometric edges of the ``k x`` raster, shadow edges of the 1x frame's
        visibility ``hook``), shade their sub-samples packed ``(B, C, 1, M)`` by
        ``radiance_of`` and put each pixel's mean in ``image`` / ``alpha``."""
        k = plan.edge_supersample
        h, w = plan.resolution
        found: list[torch.Tensor] = []

        def edge_subsamples(face_id_k: torch.Tensor) -> torch.Tensor:
            """The sub-samples of the edge pixels (the rest skip the barycentric pass)."""
            edge = edge_aa.geometric_edges(face_id_k, scene.faces, k,
                                           scene.face_material if len(scene.materials) > 1
                                           else None)
            if hook is not None:  # shadow edges: the 1x visibility of every shadowed light
                vis = [v for kind in LIGHT_KINDS
                       if (v := hook(kind, slice(None))) is not None]
                if vis:
                    edge |= edge_aa.contrast_edges(torch.cat(vis, 1).flatten(1, 2),
                                                   edge_aa.CONTRAST_THRESHOLD)
            elif edge_aa.CONTRAST_THRESHOLD < 0:
                edge |= edge_aa.contrast_edges(image, edge_aa.CONTRAST_THRESHOLD)
            found.append(edge)
            return edge.repeat_interleave(k, 1).repeat_interleave(k, 2)

        frags_k = rasterize(clip, scene.faces, (h * k, w * k),
                            cull_backfaces=_cull_mask(plan, scene), face_ranges=face_ranges,
                            derivatives=plan.derivatives, select=edge_subsamples)
        packed = edge_aa.pack_subsamples(frags_k, found[0], k)
        count = packed.count
        plan = replace(plan, edge_pixels=count)
        if count == 0:
            return image, alpha, plan
        wanted = plan.channels & (_SHADING_NEEDS[plan.shading] | {"alpha"})
        gb = geometry_pass(packed.frags, wanted, positions=scene.positions, view=view,
                           normals=normals, uvs=scene.uvs, tangents=scene.tangents,
                           face_material=scene.face_material, materials=scene.materials,
                           texture_filter=self.texture_settings.filter, mip_cache=self.mip_cache,
                           max_anisotropy=self.texture_settings.max_anisotropy)
        radiance = radiance_of(gb, packed.frags.face_id, rows=plan.resolution[0] * k)
        if plan.background == "environment":
            rays = edge_aa.rays_at(view, proj, packed.ndc.to(radiance.dtype))
            back = environment.background(rays)
        elif background.shape[-2:] == (h, w):  # an image: the pixel's 1x value
            back = edge_aa.per_subsample(background.expand(image.shape[0], -1, -1, -1),
                                         packed)
        else:
            back = background
        sub = radiance + (1 - gb.mask) * back
        sub_alpha = gb.mask * gb.alpha if gb.alpha is not None else gb.mask
        return (edge_aa.resolve_edges(image, sub, packed),
                edge_aa.resolve_edges(alpha, sub_alpha.to(alpha.dtype), packed), plan)


@dataclass
class _Visible:
    """The visible surface per pixel (what ``antialias`` reads of Fragments) when cut-outs
    select a deeper layer: ``face_id`` ``(B, H, W)`` (-1 empty), ``depth`` ``(B, H, W)``."""

    face_id: torch.Tensor
    depth: torch.Tensor


def _items(t: torch.Tensor | None, sl: slice, b: int, dims: int | None = None
           ) -> torch.Tensor | None:
    """Items ``sl`` of a per-item tensor (first dimension ``b``; with ``dims``, only when
    it has that many dimensions: ``(V, 3)`` positions are shared, ``(B, V, 3)`` are not);
    a shared tensor (batch 1, or unbatched) is returned as is."""
    if t is None or t.dim() == 0 or t.shape[0] != b or (dims is not None and t.dim() != dims):
        return t
    return t[sl]


def _scene_items(scene: RenderScene, sl: slice, b: int) -> RenderScene:
    """The scene of batch items ``sl``: per-item vertex data and ``face_ranges`` sliced."""
    fields = {name: _items(getattr(scene, name), sl, b, 3)
              for name in ("positions", "normals", "uvs", "tangents", "object_coords")}
    fields["face_ranges"] = _items(scene.face_ranges, sl, b, 2)
    return dataclasses.replace(scene, **fields)


def _lights_items(lights: Lights | None, sl: slice, b: int) -> Lights | None:
    """The lights of batch items ``sl`` (lights of batch size 1 are shared as they are)."""
    if lights is None or lights.batch_size != b:
        return lights
    parts = {}
    for name in LIGHT_KINDS:
        part = getattr(lights, name)
        if part is not None:
            part = dataclasses.replace(part, **{
                f.name: _items(getattr(part, f.name), sl, b) for f in dataclasses.fields(part)
                if isinstance(getattr(part, f.name), torch.Tensor)})
        parts[name] = part
    return Lights(ambient=_items(lights.ambient, sl, b), **parts)


def _environment_per_item(environment: Environment) -> bool:
    """Whether an environment holds per-item radiance, rotation or intensity (B > 1)."""
    intensity = environment.intensity
    return (environment.radiance.shape[0] > 1 or environment.rotation.shape[0] > 1
            or (isinstance(intensity, torch.Tensor) and intensity.numel() > 1))


def _area_shadow_settings(lights: AreaLights, i: int, given: bool,
                          settings: ShadowSettings) -> ShadowSettings:
    """The shadow settings of area light ``i``: a cube map from its centre, filtered with
    PCSS whose light size is the radius of the disc of the light's area (the largest over
    the batch; :func:`~torchraster.shading.lights.area_equivalent_radius`). ``settings``:
    the light's own (``given``: its filter and taps are kept) or the renderer's default
    (its filter becomes ``"pcss"``, with at least
    :data:`~torchraster.shading.lights.AREA_SHADOW_TAPS` taps)."""
    radius = float(area_equivalent_radius(lights.select(slice(i, i + 1))).detach().amax())
    if given:
        return dataclasses.replace(settings, light_size=radius)
    return dataclasses.replace(settings, light_size=radius, filter="pcss",
                               pcf_taps=max(settings.pcf_taps, AREA_SHADOW_TAPS))


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


def _check_label_fields(scene: RenderScene, requested: set[str]) -> None:
    """A ValueError naming the requested label channel and the RenderScene field it lacks."""
    for channel in sorted(requested & set(_LABEL_NEEDS)):
        for name in _LABEL_NEEDS[channel]:
            if getattr(scene, name) is None:
                raise ValueError(
                    f"channels: {channel!r} needs RenderScene.{name}, which this scene does "
                    "not have (build the scene with RenderScene.from_objects, or set it)")


_MOTION_STEPS = {"flow_forward": "flow forward", "flow_forward_valid": "flow forward valid",
                 "flow_backward": "flow backward", "flow_backward_valid": "flow backward valid",
                 "motion": "motion vectors"}


#: G-buffer channels only the lighting reads; :func:`_packed_channels` keeps them packed
_SURFACE_CHANNELS = frozenset({"position", "normal", "albedo", "metallic", "roughness"})


def _packed_channels(shading: str, alpha: str, channels: Iterable[str],
                     requested: Iterable[str], shadow_lights: tuple, ssao: bool, fog: tuple,
                     ssr: bool, edge_supersample: int) -> frozenset[str]:
    """The surface channels the geometry pass keeps packed (covered pixels only, no
    ``(B, C, H, W)`` frame; memory): those no output and no pass but ``shade`` reads (one
    opaque layer, a lit model; shadow receivers read position and normal frames, SSAO the
    normal, fog the position, SSR and the edge pass all of them)."""
    if shading not in LIT_MODELS or alpha != "none" or ssr or edge_supersample > 1:
        return frozenset()
    framed = set(requested)
    if shadow_lights:
        framed |= {"position", "normal"}
    if ssao:
        framed.add("normal")
    if fog:
        framed.add("position")
    return frozenset(_SURFACE_CHANNELS & set(channels)) - framed


def _motion_steps(requested: Iterable[str]) -> tuple[str, ...]:
    """The plan's motion steps, in a fixed order, for the requested channels."""
    return tuple(step for ch, step in _MOTION_STEPS.items() if ch in requested)


def _check_frames(requested: Iterable[str], **frames: OtherFrame | None
                  ) -> dict[str, OtherFrame]:
    """The given frames by argument name; a ValueError naming the channel and the missing
    argument, a TypeError for a frame that is not an OtherFrame."""
    for name, frame in frames.items():
        if frame is not None and not isinstance(frame, OtherFrame):
            raise TypeError(f"{name}: expected a torchraster.motion.OtherFrame or None, got "
                            f"{type(frame).__name__}")
    for ch in sorted(set(requested) & set(MOTION_CHANNELS)):
        arg = MOTION_CHANNELS[ch]
        if frames[arg] is None:
            raise ValueError(f"channels: {ch!r} needs {arg}= (an OtherFrame with the vertex "
                             f"positions and camera of that frame); {arg} is None")
    return {name: f for name, f in frames.items() if f is not None}


def _motion_channels(plan: RenderPlan, scene: RenderScene, layers: Sequence, gbs: list[GBuffer],
                     frames: dict[str, OtherFrame], face_ranges: torch.Tensor | None, b: int,
                     memo: _RasterMemo) -> list[GBuffer]:
    """Each layer's G-buffer with the requested flow / motion channels of its visible
    surface (:mod:`~torchraster.motion`). Flow is in output pixels (divided by the
    supersampling factor: the label reduction keeps one sub-sample); the other frame is
    rasterized once per frame for validity, with the main pass's culling (unless the frame
    holds its depth already; the rasterized depth is stored on the frame). That raster is
    the main pass's own (kept in ``memo``): when the other frame is rendered next, it is
    not rasterized again."""
    want = plan.requested
    extra: list[dict[str, torch.Tensor]] = [{} for _ in layers]
    dtype = scene.positions.dtype
    for name, flow_ch in (("next_frame", "flow_forward"), ("previous_frame", "flow_backward")):
        valid_ch = flow_ch + "_valid"
        mv = "motion" in want and name == "previous_frame"
        if not (flow_ch in want or valid_ch in want or mv):
            continue
        frame = frames[name]
        other = None
        if valid_ch in want:
            other = frame.depth
            if other is None:  # stored on the frame: passing it again skips this raster
                with torch.no_grad():
                    clip = _clip_positions(frame.positions.detach(), frame.view.detach(),
                                           frame.proj.detach(), b)
                    seen = memo.rasterize(clip, scene.faces, plan, _cull_mask(plan, scene),
                                          face_ranges, objects=_amodal_objects(plan, scene),
                                          keep=True)
                    other = other_depth(seen.depth, frame.proj)
                frame.depth = other
        for k, f in enumerate(layers):
            rep = reproject(f, scene.faces, frame.positions, frame.view, frame.proj)
            if flow_ch in want:
                extra[k][flow_ch] = finish_low_precision(flow_from(rep) / plan.supersample,
                                                         dtype)
            if mv:
                extra[k]["motion"] = finish_low_precision(motion_from(rep), dtype)
            if other is not None:
                extra[k][valid_ch] = validity_from(
                    rep, other, own_slope=lambda where, f=f, frame=frame: face_depth_slope(
                        f, scene.faces, frame.positions, frame.view, frame.proj, where)
                ).to(dtype)
    return [g.replace(**e) for g, e in zip(gbs, extra, strict=True)]


def _clip_positions(positions: torch.Tensor, view: torch.Tensor, proj: torch.Tensor, b: int
                    ) -> torch.Tensor:
    """``(b, V, 4)`` clip positions of ``positions`` ``(V, 3)`` or ``(1 or b, V, 3)`` by
    ``view``, ``proj`` ``(4, 4)`` or ``(1 or b, 4, 4)``: the one way every pass computes
    them (so a frame rasterized as another frame's neighbour is the same raster)."""
    view, proj = view.expand(b, 4, 4), proj.expand(b, 4, 4)
    clip = transform_points(positions, (proj @ view).to(positions.dtype))
    return clip if clip.shape[0] == b else clip.expand(b, -1, -1)


class _RasterMemo:
    """The Fragments of the last two frames rasterized as another frame's neighbour (flow
    validity), by content: the digest of the clip positions, the faces (by identity and
    version), the culling, the face ranges, the resolution and the raster options.
    :meth:`rasterize` returns a kept raster only for inputs without gradients (a kept
    raster has no graph); the result is what ``rasterize`` gives for those inputs."""

    _KEPT = 2

    def __init__(self) -> None:
        self._kept: dict[tuple, tuple] = {}

    def rasterize(self, clip: torch.Tensor, faces: torch.Tensor, plan: RenderPlan,
                  cull: bool | torch.Tensor, face_ranges: torch.Tensor | None, *,
                  objects: torch.Tensor | None = None, keep: bool = False) -> Fragments:
        """``rasterize(clip, faces, plan.resolution, ...)`` with the plan's options, a kept
        raster when the same inputs were kept; ``keep`` keeps this one. ``objects``: the
        ``(F,)`` object id 1..N of each face when the plan wants amodal masks (then in
        ``frags.silhouettes``, ``(B, N, H, W)``)."""
        def draw() -> Fragments:
            return rasterize(clip, faces, plan.resolution, cull_backfaces=cull,
                             face_ranges=face_ranges, derivatives=plan.derivatives,
                             layers=plan.layers,
                             groups=None if objects is None else objects - 1,
                             num_groups=plan.amodal if objects is not None else None)

        if not (keep or self._kept) or clip.requires_grad:
            return draw()
        key = (content_key(clip), plan.resolution, plan.derivatives, plan.layers)
        found = self._kept.get(key)
        if found is not None:
            kept_faces, version, kept_cull, kept_ranges, kept_objects, frags = found
            if (kept_faces is faces and version == faces._version
                    and _same(kept_cull, cull) and _same(kept_ranges, face_ranges)
                    and (objects is None or _same(kept_objects, objects))):
                return frags
        frags = draw()
        if keep:
            self._kept.pop(key, None)
            while len(self._kept) >= self._KEPT:
                self._kept.pop(next(iter(self._kept)))  # the oldest
            self._kept[key] = (faces, faces._version, cull, face_ranges, objects, frags)
        return frags

    def holds(self, frags: Fragments) -> bool:
        """Whether ``frags`` is one of the kept rasters (a later call may reuse it)."""
        return any(kept[-1] is frags for kept in self._kept.values())

    def __deepcopy__(self, memo: dict) -> _RasterMemo:
        return _RasterMemo()  # a copied renderer starts empty


def _check_group(name: str, value: object, kind: type) -> Any:
    """``value`` if it is a ``kind`` settings object, ``kind()`` for None, else a TypeError
    naming the argument ``name``."""
    if value is None:
        return kind()
    if not isinstance(value, kind):
        raise TypeError(f"{name}: expected a torchraster.{kind.__name__} or None, got "
                        f"{type(value).__name__}")
    return value


def pixel_size(position: torch.Tensor, view: torch.Tensor, proj: torch.Tensor, rows: int
               ) -> torch.Tensor:
    """World size of one pixel (its height) at each surface point, for a grid of ``rows``
    pixel rows: ``2 depth / (P[1, 1] rows)`` for a perspective projection (``depth``
    along the view axis), ``2 / (P[1, 1] rows)`` for an orthographic one. No gradient.

    Args:
        position: ``(B, 3, H, W)`` world positions; view, proj: ``(B, 4, 4)``.

    Returns:
        ``(B, 1, H, W)``.
    """
    with torch.no_grad():
        dt = position.dtype
        v, pr = view.to(dt), proj.to(dt)
        depth = -(torch.einsum("bc,bchw->bhw", v[:, 2, :3], position)
                  + v[:, 2, 3, None, None])[:, None]
        scale = (2.0 / (pr[:, 1, 1] * rows)).view(-1, 1, 1, 1)
        persp = (pr[:, 3, 3] == 0).view(-1, 1, 1, 1)
        return scale * torch.where(persp, depth.abs(), torch.ones_like(depth))


def _neutral_channels(materials: Sequence[Material | None]) -> set[str]:
    """The shading channels that hold their neutral value on every material, which the
    shading pass takes as None (the G-buffer skips them): ``"ao"`` (1) when no material
    has an occlusion texture, ``"emissive"`` (0) when no material has a non-zero emissive
    factor or one that takes gradients. An empty list is the glTF default material."""
    mats = [m for m in materials if m is not None]
    out = set()
    if all(m.occlusion_texture is None for m in mats):
        out.add("ao")
    if all(not m.emissive_factor.requires_grad and not bool(m.emissive_factor.any())
           for m in mats):
        out.add("emissive")
    return out


def _amodal_objects(plan: RenderPlan, scene: RenderScene) -> torch.Tensor | None:
    """The faces' object ids when the plan wants amodal masks (the main raster then
    collects each object's silhouette, :attr:`Fragments.silhouettes`), else None."""
    return scene.face_object if plan.amodal else None


def _same(a: bool | torch.Tensor | None, b: bool | torch.Tensor | None) -> bool:
    """Whether two culling flags / face-range tensors are the same values."""
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        return (isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor)
                and a.shape == b.shape and bool(torch.equal(a, b)))
    return a == b


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
           "Renderer", "camera_position", "pixel_size", "view_rays"]
