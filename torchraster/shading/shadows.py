"""Shadow maps: light visibility for directional, spot and point lights.

One shadow pass renders, with our own depth-only :func:`~torchraster.raster.rasterize_depth`,
every view of every shadow-casting light of a batch in as few calls as the memory budget
allows (all views of one map size are one batch). The lighting pass then asks
:func:`shadow_visibility` for the fraction of each light that reaches each pixel.

Views per light:

* **directional**: orthographic maps; ``cascades`` (1-4) split the camera's depth range
  (practical split scheme, Zhang et al. 2006: ``lambda`` blends logarithmic and uniform
  splits). Each cascade is fitted to the bounding sphere of its frustum slice (its size does
  not change as the camera turns) and its origin is snapped to the texel grid, so shadows do
  not shimmer when the camera moves; when the casters' bounds are smaller than that sphere
  the map is fitted to them instead. A cascade whose slice misses the scene is not
  rendered. Depth spans every caster (also those outside the camera's frustum).
* **spot**: a perspective map around the spot axis covering the outer cone (cones wider
  than :data:`MAX_SPOT_FOV_DEG` use a cube map like point lights).
* **point**: a cube map (6 perspective faces, each widened by a few texels so filter taps
  near a face edge stay inside the face).

The renderer renders only the point / spot views that something reads
(:func:`cull_local_views`, after the G-buffer pass): a cube face that no receiver selects
(surfaces of every depth layer, fog samples along the view rays, with edge antialiasing
anything in the scene's box) or whose frustum holds no caster, a spot map no receiver's
filter footprint touches. The others keep their initial maps, which no lookup reads (or,
without casters, which equal the rendered ones), so the image is bit-identical;
``ShadowMaps.needed`` holds the choice and the steps say how many were rendered.

Maps hold *linear* depth (distance along the light's view axis, metres), so biases are in
world units: ``bias`` and ``slope_bias`` are multiples of the world size of one shadow-map
texel at the receiver (constant + slope-scaled, Lengyel / "Common techniques to improve
shadow depth maps", Microsoft 2011), and ``normal_bias`` moves the receiver along its normal
by that many texels (normal-offset shadows, Holbert 2011). A PCF / PCSS tap ``r`` texels
from the receiver's own map position adds ``r + 1`` more texels of the slope term (the depth
of the receiver's plane there, conservatively), so filtered lookups do not shadow a tilted
receiver. Defaults are measured in docs/benchmarks.md ("Shadows").

Filters (``ShadowSettings.filter``):

* ``"hard"``: one nearest-texel comparison.
* ``"pcf"``: percentage-closer filtering: ``pcf_taps`` taps on a Poisson disc (or a grid)
  of radius ``pcf_radius`` texels, each a bilinearly weighted comparison of 4 texels (like
  hardware PCF), so the result is continuous and differentiable in the receiver's map
  position (light position and direction, receiver geometry).
* ``"pcss"``: percentage-closer soft shadows (Fernando 2005): a blocker search over the
  light's footprint, penumbra width from the light size (``light_size``: radius in metres for
  point / spot lights, angular diameter in degrees for directional lights) and the
  blocker/receiver distances, then PCF with that radius.
* ``"vsm"``: variance shadow maps (Donnelly & Lauritzen 2006): depth moments blurred with a
  Gaussian (kornia), Chebyshev's upper bound with a minimum variance and light-bleeding
  reduction. Smooth in the receiver depth *and* in the occluders' depth: with autograd on
  the maps are rendered by the differentiable :func:`~torchraster.raster.rasterize`, so
  gradients reach occluder geometry too.

Gradients (measured against finite differences of the visibility averaged over sub-texel
offsets of the map grid, the converged quantity: docs/benchmarks.md "shadow-gradients",
docs/design.md "Shadows", Gradients): the visibility factor multiplies the illuminance, so
receivers' shading, materials and light intensity get exact gradients through it always.
Through the visibility itself, a map rendered without gradients is piecewise constant,
but the shadow edges it holds move with the light: PCF / PCSS lookups take the map's own
motion out of each tap (:func:`_blocker_motion`: the tap's blocker reprojected through the
differentiable view), so they are differentiable with respect to the light position and
direction and the receiver positions; with autograd on the caster positions the maps also
record each texel's caster face (one more, non-differentiable, :func:`rasterize` per map)
and the blocker point follows that face's vertices, so caster vertices get gradients too.
The PCSS penumbra width carries none (its blocker search is not differentiated). VSM
maps are rendered with the differentiable :func:`rasterize` when autograd needs them and
their moments antialiased (silhouettes moving across texels), so VSM also follows caster
vertices and occluder depth. ``"hard"`` has zero gradient. What a
tiny finite difference at one map position (``gradcheck``) sees is the derivative of a map
glued to the light, which is not the image's: measured, it has the wrong sign for a point
light over a sphere half-way to the floor.
"""

from __future__ import annotations

import functools
import hashlib
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import torch
from torch.utils.checkpoint import checkpoint

from torchraster._validate import check_float, check_int, check_tensor
from torchraster.numerics import compute_dtype, safe_normalize
from torchraster.raster import antialias, rasterize, rasterize_depth
from torchraster.raster.rasterize import DEFAULT_MEMORY_BUDGET

FILTERS = ("hard", "pcf", "pcss", "vsm")
PATTERNS = ("poisson", "grid")
#: Spot lights with a wider outer cone (full angle, degrees) are rendered as cube maps.
MAX_SPOT_FOV_DEG: float = 120.0
#: Bytes of shadow-map memory rendered per rasterize call (views are chunked to fit).
SHADOW_MEMORY_BUDGET: int = 256 * 2**20
#: Bytes of candidate temporaries per chunk of the depth resolve of maps rendered straight
#: into the group's maps (over :data:`DIRECT_MAP_TEXELS`; other maps use rasterize_depth's
#: 96 MB, whose fewer, larger chunks are faster with many views per call).
DIRECT_RASTER_BUDGET: int = 32 * 2**20
#: Receiver-light-tap corners evaluated at once by the filters: bounds the temporaries of
#: one chunk (in float32 4 MB for the four texels of every tap, 1 MB for the others), which
#: then stay in the CPU's caches. 2**22 made lookups 1.2-1.9x slower (docs/benchmarks.md,
#: section shadow-tap-chunks); 2**18 was slower again with many lights (smaller chunks).
TAP_CHUNK_ELEMENTS: int = 2**20

#: With autograd, lookups of more receiver-light taps than this recompute their receiver
#: chunks in backward (checkpoints) instead of keeping every tap's temporaries (~200 B a
#: tap: 16 PCF point lights at 256² x 4 kept 6 kB a pixel; backward then costs one more
#: lookup pass, ~1.4x the forward + backward time of a shadowed frame).
RECOMPUTE_TAPS: int = 2**20
#: Largest tan(angle) between normal and light used by the slope-scaled bias (~84 deg).
MAX_SLOPE: float = 10.0
#: Largest shadow-map side: one 8192^2 float32 view is the whole SHADOW_MEMORY_BUDGET.
MAX_MAP_SIZE: int = 8192
#: Most cascades of a directional light.
MAX_CASCADES: int = 4
#: Most PCF / PCSS taps.
MAX_PCF_TAPS: int = 256
#: The integer fields of :class:`ShadowSettings` (bools are refused for them).
SHADOW_INT_FIELDS = ("map_size", "pcf_taps", "cascades")
#: Closed bounds ``(lo, hi)`` of every numeric :class:`ShadowSettings` field: the one source
#: of the limits that ``ShadowSettings`` checks and the YAML schema (``ShadowConfig``) states.
SHADOW_BOUNDS: dict[str, tuple[float, float]] = {
    "map_size": (8, MAX_MAP_SIZE), "pcf_taps": (1, MAX_PCF_TAPS),
    "cascades": (1, MAX_CASCADES), "pcf_radius": (0, 64), "bias": (0, 1e3),
    "slope_bias": (0, 1e3), "normal_bias": (0, 1e3), "intensity": (0, 1),
    "split_lambda": (0, 1), "cascade_blend": (0, 0.5), "light_size": (0, 1e6),
    "max_penumbra": (0.5, 64), "vsm_blur": (0, 64), "vsm_bleed": (0, 0.99),
    "vsm_min_variance": (0, 1), "pixel_radius": (0, 8),
}


@dataclass(frozen=True)
class ShadowSettings:
    """How one light's shadows are rendered and filtered (defaults: docs/benchmarks.md).

    Args:
        map_size: side of each shadow map (and cube face / cascade) in texels.
        filter: ``"hard"``, ``"pcf"``, ``"pcss"`` or ``"vsm"`` (see the module docstring).
        pcf_radius: PCF filter radius in texels.
        pcf_taps: PCF (and PCSS) taps.
        pcf_pattern: ``"poisson"`` (a fixed, well-spread disc) or ``"grid"``.
        bias: constant depth bias, in texels (world size of one texel at the receiver).
        slope_bias: slope-scaled depth bias, in texels per unit tan(angle to the light).
        normal_bias: normal offset of the receiver, in texels.
        intensity: shadow strength: 0 = no darkening, 1 = fully occluded light is black.
        cascades: cascaded maps of a directional light (1-4; must be 1 for other lights).
        split_lambda: cascade split blend: 0 uniform, 1 logarithmic.
        cascade_blend: fraction of a cascade's depth range blended into the next one.
        max_distance: directional cascades cover camera depths up to this (m); None = the
            farthest scene point.
        light_size: PCSS light size: radius (m) of point / spot lights, angular diameter
            (degrees) of directional lights (the sun: 0.53).
        max_penumbra: largest PCSS filter radius and blocker-search radius, in texels.
        vsm_blur: standard deviation (texels) of the Gaussian blur of VSM moments.
        vsm_bleed: VSM light-bleeding reduction (0 = none; cut Chebyshev's bound below it).
        vsm_min_variance: VSM variance floor, relative to the squared depth range.
        pixel_radius: PCF / PCSS: the filter also spans this many pixels of the frame at
            each receiver, its radius ``sqrt(r^2 + (pixel_radius * pixel / texel)^2)``
            texels (at most ``max_penumbra``): 0.56, a disc of one pixel's area, makes
            shadow edges about as soft as averaging over the pixel (what supersampling
            does), for no more taps. 0 = off. Needs the receivers' pixel size
            (``shadow_visibility(pixel_size=...)``; the Renderer passes it).
    """

    map_size: int = 1024
    filter: str = "pcf"
    pcf_radius: float = 1.5
    pcf_taps: int = 4
    pcf_pattern: str = "poisson"
    bias: float = 1.0
    slope_bias: float = 2.0
    normal_bias: float = 0.0
    intensity: float = 1.0
    cascades: int = 1
    split_lambda: float = 0.75
    cascade_blend: float = 0.1
    max_distance: float | None = None
    light_size: float = 0.5
    max_penumbra: float = 24.0
    vsm_blur: float = 1.5
    vsm_bleed: float = 0.2
    vsm_min_variance: float = 1e-7
    pixel_radius: float = 0.0

    def __post_init__(self) -> None:
        def bad(name: str, expected: str) -> None:
            raise ValueError(f"ShadowSettings.{name}: expected {expected}, got "
                             f"{getattr(self, name)!r}")

        for name, (lo, hi) in SHADOW_BOUNDS.items():
            prefixed = f"ShadowSettings.{name}"
            if name in SHADOW_INT_FIELDS:
                object.__setattr__(self, name, check_int(prefixed, getattr(self, name), lo, hi))
            else:
                check_float(prefixed, getattr(self, name), lo, hi)
        if self.filter not in FILTERS:
            bad("filter", f"one of {FILTERS}")
        if self.pcf_pattern not in PATTERNS:
            bad("pcf_pattern", f"one of {PATTERNS}")
        if self.max_distance is not None:
            check_float("ShadowSettings.max_distance", self.max_distance, 0.0, lo_open=True)
        if self.pixel_radius > 0 and self.filter in ("hard", "vsm"):
            raise NotImplementedError(f"ShadowSettings.pixel_radius: not implemented for "
                                      f"filter {self.filter!r} (pcf and pcss only)")


@dataclass
class ShadowMaps:
    """The rendered maps of one group of shadow-casting lights of one kind.

    Attributes:
        kind: ``"directional"``, ``"point"`` or ``"spot"``.
        lights: indices (into the kind's lights) of the Ls lights of the group.
        settings: their :class:`ShadowSettings`.
        layout: ``"single"`` (one map), ``"cascades"`` or ``"cube"`` (6 faces +X -X +Y -Y
            +Z -Z).
        view: ``(B, Ls, NV, 4, 4)`` world -> light view matrices (light looks along -z).
        proj: ``(B, Ls, NV, 4, 4)`` OpenGL projections (orthographic or perspective).
        near, far: ``(B, Ls, NV)`` linear depth range of each view (m).
        texel: ``(B, Ls, NV)`` world size of one texel: metres (orthographic) or metres
            per metre of depth (perspective).
        depth: ``(B, Ls, NV, S, S)`` linear depth of the nearest caster (``+inf`` where
            none), or for VSM the blurred moments ``(B, Ls, NV, 2, S, S)`` of the depth
            normalised to [0, 1] over ``[near, far]``.
        splits: ``(B, Ls, C + 1)`` camera view depths bounding the cascades, or None.
        rendered: ``(NV,)`` bool: views that were rendered (a cascade that covers nothing
            is skipped; its pixels fall to the next cascade or are unshadowed).
    """

    kind: str
    lights: list[int]
    settings: ShadowSettings
    layout: str
    view: torch.Tensor
    proj: torch.Tensor
    near: torch.Tensor
    far: torch.Tensor
    texel: torch.Tensor
    depth: torch.Tensor | None = None
    splits: torch.Tensor | None = None
    rendered: torch.Tensor | None = None
    light_position: torch.Tensor | None = None  # (B, Ls, 3) point / spot
    light_direction: torch.Tensor | None = None  # (B, Ls, 3) unit, travel direction
    steps: list[str] = field(default_factory=list)
    #: PCF / PCSS with autograd to caster vertices: ``(B, Ls, NV, S, S)`` int32 caster face
    #: of each texel (-1: none) and the casters (positions ``(B or 1, V, 3)``, faces)
    face_id: torch.Tensor | None = None
    casters: tuple[torch.Tensor, torch.Tensor] | None = None
    #: ``(B, Ls, NV)`` bool: the views of each item's light that some receiver can read
    #: (:func:`cull_local_views`); only those are rendered (the others stay empty: no
    #: lookup reads them). None: every view in ``rendered``.
    needed: torch.Tensor | None = None

    @property
    def perspective(self) -> bool:
        return self.kind != "directional"


# ----------------------------------------------------------------------------- matrices


def _basis_from_forward(forward: torch.Tensor) -> torch.Tensor:
    """``(..., 3, 3)`` rotation rows (right, up, back) of a view looking along ``forward``
    (unit, ``(..., 3)``); the up hint is world +y unless forward is nearly vertical."""
    up_hint = torch.zeros_like(forward)
    vertical = forward.detach()[..., 1].abs() > 0.99
    up_hint[..., 1] = torch.where(vertical, 0.0, 1.0)
    up_hint[..., 2] = torch.where(vertical, 1.0, 0.0)
    back = -forward
    right = safe_normalize(torch.linalg.cross(up_hint, back), dim=-1)
    up = torch.linalg.cross(back, right)
    return torch.stack([right, up, back], dim=-2)


def _view_matrix(rot: torch.Tensor, eye: torch.Tensor) -> torch.Tensor:
    """World -> view ``(..., 4, 4)`` from rotation rows ``(..., 3, 3)`` and eye ``(..., 3)``."""
    top = torch.cat([rot, -(rot @ eye[..., None])], dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom = bottom + torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=top.dtype, device=top.device)
    return torch.cat([top, bottom], dim=-2)


def _ortho(lo: torch.Tensor, hi: torch.Tensor, near: torch.Tensor, far: torch.Tensor
           ) -> torch.Tensor:
    """OpenGL orthographic ``(..., 4, 4)`` of the box ``lo``/``hi`` ``(..., 2)`` (view x, y)
    and linear depths ``near``..``far``."""
    m = torch.zeros(*near.shape, 4, 4, dtype=near.dtype, device=near.device)
    m[..., 0, 0] = 2 / (hi[..., 0] - lo[..., 0])
    m[..., 1, 1] = 2 / (hi[..., 1] - lo[..., 1])
    m[..., 2, 2] = -2 / (far - near)
    m[..., 0, 3] = -(hi[..., 0] + lo[..., 0]) / (hi[..., 0] - lo[..., 0])
    m[..., 1, 3] = -(hi[..., 1] + lo[..., 1]) / (hi[..., 1] - lo[..., 1])
    m[..., 2, 3] = -(far + near) / (far - near)
    m[..., 3, 3] = 1
    return m


def _perspective(tan_half: float, near: torch.Tensor, far: torch.Tensor) -> torch.Tensor:
    """OpenGL perspective ``(..., 4, 4)``, square, ``tan(fov / 2) = tan_half``."""
    m = torch.zeros(*near.shape, 4, 4, dtype=near.dtype, device=near.device)
    m[..., 0, 0] = 1 / tan_half
    m[..., 1, 1] = 1 / tan_half
    m[..., 2, 2] = -(far + near) / (far - near)
    m[..., 2, 3] = -2 * far * near / (far - near)
    m[..., 3, 2] = -1
    return m


def _linear_depth(ndc: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                  perspective: bool) -> torch.Tensor:
    """Linear depth (m) from NDC z of :func:`_ortho` / :func:`_perspective`; ``far`` where
    ``ndc`` is not finite (nothing rendered)."""
    empty = ~torch.isfinite(ndc)
    z = torch.where(empty, 1.0, ndc)
    if perspective:
        d = 2 * far * near / ((far + near) - z * (far - near))
    else:
        d = (z * (far - near) + far + near) / 2
    return torch.where(empty, far, d)


def _linear_depth_inplace(ndc: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                          perspective: bool) -> torch.Tensor:
    """:func:`_linear_depth` overwriting ``ndc`` (no full-size temporaries: the maps of
    a 4096² cube are 6 x 64 MB), ``+inf`` where ``ndc`` is ``+inf`` (``ndc`` from
    :func:`rasterize_depth`: in [-1, 1] or ``+inf`` where empty); the same operations in the
    same order, so bit-identical to it elsewhere. Orthographic maps need no mask (``+inf``
    stays ``+inf`` through ``(z (f - n) + f + n) / 2``); perspective ones find it with
    ``isposinf`` (~6x cheaper than ``~isfinite`` on the CPU)."""
    if ndc.dim() == 3 and ndc[0].numel() > 2**20:  # large maps: 2**20 texels at a time
        step = max(1, 2**20 // ndc.shape[-1])
        for i in range(ndc.shape[0]):
            for r in range(0, ndc.shape[1], step):
                _linear_depth_inplace(ndc[i:i + 1, r:r + step], near[i:i + 1], far[i:i + 1],
                                      perspective)
        return ndc
    if not perspective:  # (z (f - n) + f + n) / 2
        return ndc.mul_(far - near).add_(far).add_(near).div_(2)
    empty = torch.isposinf(ndc)
    ndc.mul_(far - near)  # 2 f n / ((f + n) - z (f - n))
    ndc.neg_().add_(far + near)
    torch.div(2 * far * near, ndc, out=ndc)
    return ndc.masked_fill_(empty, float("inf"))


_CUBE_FORWARD = ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))


def _cube_rotations(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``(6, 3, 3)`` view rotations of the cube faces +X -X +Y -Y +Z -Z."""
    fwd = torch.tensor(_CUBE_FORWARD, dtype=dtype, device=device)
    return _basis_from_forward(fwd)


def _depth_range(bounds: torch.Tensor, eye: torch.Tensor, axis: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Near / far (m) along unit ``axis`` ``(B, L, 3)`` from ``eye`` ``(B, L, 3)`` enclosing
    the box ``bounds`` ``(B, 2, 3)``; near > 0 is kept >= far * 1e-4."""
    corners = _box_corners(bounds)  # (B, 8, 3)
    rel = corners[:, None] - eye[:, :, None]  # (B, L, 8, 3)
    along = (rel * axis[:, :, None]).sum(-1)
    far = along.amax(-1).clamp_min(1e-3) * 1.01
    # nearest distance from the eye to the box (0 inside): the near plane cannot be beyond it
    gap = (bounds[:, None, 0] - eye).clamp_min(0) + (eye - bounds[:, None, 1]).clamp_min(0)
    dist = gap.norm(dim=-1)
    near = torch.maximum(0.9 * dist, far * 1e-4)
    return near, torch.maximum(far, near * 1.01)


def _box_corners(bounds: torch.Tensor) -> torch.Tensor:
    """``(B, 8, 3)`` corners of boxes ``(B, 2, 3)`` (row 0 min, row 1 max)."""
    idx = torch.tensor([[(k >> a) & 1 for a in range(3)] for k in range(8)],
                       device=bounds.device)
    return torch.gather(bounds, 1, idx[None].expand(bounds.shape[0], 8, 3))


def _poisson_disc(n: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``(n, 2)`` points in the unit disc: a Vogel (golden-angle) spiral, which is evenly
    spread like a Poisson disc and deterministic."""
    k = torch.arange(n, dtype=torch.float64)
    r = torch.sqrt((k + 0.5) / n)
    theta = k * math.pi * (3 - math.sqrt(5))
    return torch.stack([r * torch.cos(theta), r * torch.sin(theta)], -1).to(dtype=dtype,
                                                                           device=device)


def _grid(n: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``(m*m, 2)`` points of an m x m grid in [-1, 1]^2 with m*m >= n... m = round(sqrt(n))."""
    m = max(1, round(math.sqrt(n)))
    t = torch.linspace(-1, 1, m, dtype=torch.float64) if m > 1 else torch.zeros(1,
                                                                               dtype=torch.float64)
    gy, gx = torch.meshgrid(t, t, indexing="ij")
    return torch.stack([gx.flatten(), gy.flatten()], -1).to(dtype=dtype, device=device)


@functools.lru_cache(maxsize=32)
def _taps(count: int, pattern: str, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """:func:`tap_pattern`, kept (read-only) per settings, dtype and device."""
    return tap_pattern(ShadowSettings(pcf_taps=count, pcf_pattern=pattern), dtype, device)


def tap_pattern(settings: ShadowSettings, dtype: torch.dtype = torch.float32,
                device: torch.device | str | None = None) -> torch.Tensor:
    """The PCF tap offsets ``(T, 2)`` in units of the filter radius."""
    if settings.pcf_taps == 1:
        return torch.zeros(1, 2, dtype=dtype, device=device)
    if settings.pcf_pattern == "grid":
        return _grid(settings.pcf_taps, dtype, device)
    return _poisson_disc(settings.pcf_taps, dtype, device)


# ------------------------------------------------------------------------------- views


def cascade_splits(near: torch.Tensor, far: torch.Tensor, count: int, lam: float
                   ) -> torch.Tensor:
    """Practical split scheme (Zhang et al. 2006): ``(..., count + 1)`` view depths from
    ``near`` to ``far`` (``(...,)``), ``lam * log + (1 - lam) * uniform``."""
    i = torch.arange(count + 1, dtype=near.dtype, device=near.device) / count
    n, f = near[..., None], far[..., None]
    log = n * (f / n) ** i
    uni = n + (f - n) * i
    return lam * log + (1 - lam) * uni


def _frustum_points(view: torch.Tensor, proj: torch.Tensor, depths: torch.Tensor
                    ) -> torch.Tensor:
    """World positions ``(B, K, 4, 3)`` of the camera frustum's 4 corner rays at view depths
    ``depths`` ``(B, K)`` (works for perspective and orthographic cameras)."""
    dtype = torch.float64
    inv_proj = torch.linalg.inv(proj.to(dtype))
    inv_view = torch.linalg.inv(view.to(dtype))
    xy = torch.tensor([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=dtype, device=view.device)

    def unproject(z: float) -> torch.Tensor:
        p = torch.cat([xy, torch.full((4, 1), z, dtype=dtype, device=view.device),
                       torch.ones(4, 1, dtype=dtype, device=view.device)], 1)  # (4, 4)
        q = torch.einsum("bij,kj->bki", inv_proj, p)
        return q[..., :3] / q[..., 3:]  # (B, 4, 3) view space

    a, b = unproject(-0.5), unproject(0.0)  # two points on each corner ray
    t = (-depths[..., None].to(dtype) - a[:, None, :, 2]) / (b[:, None, :, 2] - a[:, None, :, 2])
    pts = a[:, None] + t[..., None] * (b - a)[:, None]  # (B, K, 4, 3) view space
    world = torch.einsum("bij,bkcj->bkci", inv_view[:, :3, :3], pts) + inv_view[:, None, None,
                                                                                :3, 3]
    return world


def _camera_depth_range(view: torch.Tensor, bounds: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """View depth range ``(B,)`` of the scene box in front of the camera."""
    corners = _box_corners(bounds.to(torch.float64))
    z = -(torch.einsum("bij,bkj->bki", view[:, :3, :3].to(torch.float64), corners)
          + view[:, None, :3, 3].to(torch.float64))[..., 2]
    far = z.amax(-1).clamp_min(1e-3)
    near = z.amin(-1).clamp_min(far * 1e-4)
    return near, far


def directional_views(direction: torch.Tensor, settings: ShadowSettings, bounds: torch.Tensor,
                      view: torch.Tensor, proj: torch.Tensor,
                      receiver_bounds: torch.Tensor | None = None) -> ShadowMaps:
    """Cascaded orthographic views of directional lights.

    The map windows are differentiable functions of ``direction`` (texel snapping passes
    the gradient straight through), so gradients with respect to the light direction
    account for the window turning with the light.

    Args:
        direction: ``(B, Ls, 3)`` travel directions (need not be unit).
        settings: shared by the Ls lights.
        bounds: ``(B, 2, 3)`` world bounds of the casters (row 0 min, row 1 max).
        view, proj: ``(B, 4, 4)`` the camera (the cascades split its depth range).
        receiver_bounds: ``(B, 2, 3)`` world bounds of the surfaces that may be shadowed
            (the cascades cover the camera depths of this box; default ``bounds``). Casters
            outside the camera's view (e.g. behind it) still cast onto these.

    Returns:
        :class:`ShadowMaps` without depth (see :func:`render_shadow_maps`).
    """
    b, n_lights, _ = direction.shape
    c = settings.cascades
    # half precision: the views are built (and the maps kept) in float32
    dtype = compute_dtype(direction)
    direction, bounds, view, proj = (t.to(dtype) for t in (direction, bounds, view, proj))
    fwd = safe_normalize(direction, dim=-1)
    rot = _basis_from_forward(fwd)  # (B, Ls, 3, 3), differentiable in direction
    with torch.no_grad():
        near_c, far_c = _camera_depth_range(
            view, bounds if receiver_bounds is None else receiver_bounds)
        if settings.max_distance is not None:
            far_c = far_c.clamp_max(settings.max_distance)
            near_c = torch.minimum(near_c, far_c * 0.5)
        splits = cascade_splits(near_c, far_c, c, settings.split_lambda)  # (B, C+1)
        # each cascade covers its slice extended by the blend band into the previous one
        lo_d = splits[:, :-1] - settings.cascade_blend * (splits[:, 1:] - splits[:, :-1])
        lo_d = torch.maximum(lo_d, splits[:, :1])
        slice_lo = _frustum_points(view, proj, lo_d)  # (B, C, 4, 3)
        slice_hi = _frustum_points(view, proj, splits[:, 1:])
        pts = torch.cat([slice_lo, slice_hi], 2)  # (B, C, 8, 3) float64
        centre = pts.mean(2)  # (B, C, 3)
        radius = (pts - centre[:, :, None]).norm(dim=-1).amax(-1)  # (B, C)
        corners = _box_corners(bounds.to(torch.float64))  # (B, 8, 3)
    r64 = rot.to(torch.float64)  # (B, Ls, 3, 3)
    centre_l = torch.einsum("blij,bcj->blci", r64, centre)  # light-space centres
    texel = 2 * radius[:, None].expand(b, n_lights, c) / settings.map_size
    # whole texels (no shimmer), gradient straight through
    xy = centre_l[..., :2]
    snapped = xy + (torch.floor(xy.detach() / texel[..., None]) * texel[..., None] - xy.detach())
    lo = snapped - radius[:, None, :, None]
    hi = snapped + radius[:, None, :, None]
    # casters' box in light space
    corners_l = torch.einsum("blij,bkj->blki", r64, corners)  # (B, Ls, 8, 3)
    box_lo, box_hi = corners_l.amin(2), corners_l.amax(2)  # (B, Ls, 3)
    box_size = (box_hi[..., :2] - box_lo[..., :2]).amax(-1)  # (B, Ls)
    use_box = (box_size.detach()[..., None] <= 2 * radius[:, None]).expand(b, n_lights, c)
    pad = box_size[..., None].expand(b, n_lights, c)[..., None] * 1e-3 + 1e-6
    blo = (box_lo[..., None, :2] - pad).expand(b, n_lights, c, 2)
    bhi = (box_hi[..., None, :2] + pad).expand(b, n_lights, c, 2)
    lo = torch.where(use_box[..., None], blo, lo)
    hi = torch.where(use_box[..., None], bhi, hi)
    texel = torch.where(use_box, (bhi - blo).amax(-1) / settings.map_size, texel)
    # a cascade that does not overlap the casters' box covers nothing
    covers = ((lo < box_hi[..., None, :2]) & (hi > box_lo[..., None, :2])).all(-1).detach()
    # light-space depth: the light looks along -z (back = -fwd), depth = -z_light
    depth_lo = -box_hi[..., 2]  # (B, Ls)
    depth_hi = -box_lo[..., 2]
    span = (depth_hi - depth_lo).clamp_min(1e-6)
    # the view's eye sits a margin in front of the nearest caster
    eye_depth = depth_lo - 0.01 * span - 1e-4
    near = torch.zeros_like(texel) + (depth_lo - eye_depth)[..., None] * 0.5
    far = (depth_hi - eye_depth)[..., None].expand_as(texel) * 1.01 + 1e-6
    far = torch.maximum(far, near * 2)
    # eye in light space: x = y = 0, z = -eye_depth (depth = -z)
    eye_l = torch.stack([torch.zeros_like(eye_depth), torch.zeros_like(eye_depth),
                         -eye_depth], -1)
    # world eye = rot^T eye_l (rot is orthonormal), differentiable through rot
    eye = (rot.transpose(-1, -2) @ eye_l.to(dtype)[..., None])[..., 0]  # (B, Ls, 3)
    v = _view_matrix(rot, eye)[:, :, None].expand(b, n_lights, c, 4, 4)
    p = _ortho(lo.to(dtype), hi.to(dtype), near.to(dtype), far.to(dtype))
    rendered = covers.any(0).any(0)  # (C,)
    return ShadowMaps("directional", [], settings, "cascades" if c > 1 else "single", v, p,
                      near.to(dtype), far.to(dtype), texel.to(dtype),
                      splits=splits.to(dtype)[:, None].expand(b, n_lights, c + 1),
                      rendered=rendered, light_direction=fwd)


def local_views(kind: str, position: torch.Tensor, direction: torch.Tensor | None,
                outer_cone: torch.Tensor | None, settings: ShadowSettings,
                bounds: torch.Tensor) -> ShadowMaps:
    """Perspective views of point lights (cube maps) or spot lights (one map, or a cube map
    for cones wider than :data:`MAX_SPOT_FOV_DEG`).

    Args:
        kind: ``"point"`` or ``"spot"``.
        position: ``(B, Ls, 3)``; direction: ``(B, Ls, 3)`` spot axes (spot only).
        outer_cone: ``(B, Ls)`` outer cone angles in radians (spot only).
        settings: shared by the Ls lights; bounds: ``(B, 2, 3)`` casters' world bounds.

    Returns:
        :class:`ShadowMaps` without depth.
    """
    b, n_lights, _ = position.shape
    dtype, device = compute_dtype(position), position.device  # half precision: float32
    position, bounds = position.to(dtype), bounds.to(dtype)
    direction = None if direction is None else direction.to(dtype)
    outer_cone = None if outer_cone is None else outer_cone.to(dtype)
    size = settings.map_size
    if settings.cascades != 1 or settings.max_distance is not None:
        raise ValueError(f"ShadowSettings.cascades / max_distance: cascades are for directional "
                         f"lights; a {kind} light's settings must keep cascades=1, "
                         "max_distance=None")
    # widen each view by a margin of texels so that filter taps stay inside it
    margin = (settings.max_penumbra if settings.filter == "pcss" else settings.pcf_radius) + 2
    margin = min(margin, size / 4)
    cube = kind == "point"
    fov_half = None
    if kind == "spot":
        widest = float(outer_cone.detach().amax()) if outer_cone.numel() else 0.0
        cube = 2 * math.degrees(widest) > MAX_SPOT_FOV_DEG
        fov_half = max(widest, math.radians(1.0))
    if cube:
        tan_half = size / (size - 2 * margin)  # 90 degrees plus the margin
        rot = _cube_rotations(dtype, device)[None, None].expand(b, n_lights, 6, 3, 3)
        axes = torch.tensor(_CUBE_FORWARD, dtype=dtype, device=device)[None, None]
        axes = axes.expand(b, n_lights, 6, 3)
        layout = "cube"
    else:
        tan_half = math.tan(fov_half) * size / (size - 2 * margin)
        fwd = safe_normalize(direction, dim=-1)
        rot = _basis_from_forward(fwd)[:, :, None]
        axes = fwd[:, :, None]
        layout = "single"
    nv = rot.shape[2]
    with torch.no_grad():
        near, far = _depth_range(bounds, position.detach().repeat_interleave(nv, 1),
                                 axes.detach().reshape(b, n_lights * nv, 3))
        near, far = near.view(b, n_lights, nv), far.view(b, n_lights, nv)
    view = _view_matrix(rot, position[:, :, None].expand(b, n_lights, nv, 3))
    proj = _perspective(tan_half, near, far)
    texel = torch.full_like(near, 2 * tan_half / size)
    maps = ShadowMaps(kind, [], settings, layout, view, proj, near, far, texel,
                      rendered=torch.ones(nv, dtype=torch.bool, device=device),
                      light_position=position)
    if kind == "spot":
        maps.light_direction = safe_normalize(direction, dim=-1)
    return maps


# ---------------------------------------------------------------------------- culling

#: Render only the views of point / spot lights that some receiver can read
#: (:func:`cull_local_views`); False renders every view (the reference of
#: tests/test_shadow_face_culling.py and of scripts/bench_shadows.py's culling rows).
CULL_VIEWS: bool = True
#: Relative widening of the tested pyramids and absolute slack (times the largest
#: coordinate of the light, the receivers and the camera): a receiver within rounding of a
#: face border counts for both faces (the lookup's float32 selection may pick either).
CULL_WIDEN: float = 1e-3
CULL_SLACK: float = 1e-5
#: Side (pixels) of the tiles whose bounding boxes stand for their receivers.
CULL_TILE: int = 8
#: Tiles x view planes tested at once (bounds the temporaries of the culling test).
CULL_CHUNK_ELEMENTS: int = 2**22


def _read_planes(g: ShadowMaps) -> torch.Tensor | None:
    """``(B, Ls, NV, 4, 3)`` inward normals of the planes through each light that bound
    the region its view can be read from (``n . (x - light) >= 0`` for all four), or None
    when any receiver may read every view.

    A cube face is read by the receivers whose direction from the light has it as its
    dominant axis (:func:`_select_view`; filter taps stay inside the selected face, which
    is widened for them). A single spot map is read by receivers whose filter footprint
    (the widest tap, +2 texels for bilinear weights and rounding) touches the map, after
    the normal offset (which moves a receiver at view depth D by at most
    ``normal_bias * texel * D``)."""
    s = g.settings
    b, n_l, nv = g.view.shape[:3]
    dt, dev = torch.float64, g.view.device
    w = 1 + CULL_WIDEN
    if g.layout == "cube":
        rows = []
        for k, sign in ((0, 1), (0, -1), (1, 1), (1, -1), (2, 1), (2, -1)):
            for j in (a for a in range(3) if a != k):
                for side in (1, -1):
                    n = [0.0, 0.0, 0.0]
                    n[k], n[j] = sign * w, -side
                    rows.append(n)
        planes = torch.tensor(rows, dtype=dt, device=dev).view(1, 1, 6, 4, 3)
        return planes.expand(b, n_l, nv, 4, 3)
    if g.layout != "single":
        return None
    size = s.map_size
    reach = (s.max_penumbra if s.filter == "pcss" else s.pcf_radius) + 2
    tan_half = 1 / g.proj.detach().to(dt)[..., 0, 0]  # (B, Ls, 1)
    e = s.normal_bias * 2 * tan_half / size  # normal offset per metre of depth
    if bool((e >= 0.5).any()):
        return None
    tan_w = (tan_half * (1 + 2 * reach / size) * (1 + e) + e) * w
    rot = g.view.detach().to(dt)[..., :3, :3]  # rows right, up, back
    right, up, fwd = rot[..., 0, :], rot[..., 1, :], -rot[..., 2, :]
    t = tan_w[..., None]
    return torch.stack([t * fwd - right, t * fwd + right, t * fwd - up, t * fwd + up], -2)


def _tile_boxes(values: torch.Tensor, mask: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per :data:`CULL_TILE` square tile of ``values`` ``(B, 3, H, W)`` where ``mask``
    ``(B, 1, H, W)`` bool: the min and max ``(B, T, 3)`` of the masked pixels (exact: no
    rounding) and ``(B, T)`` bool, tiles with any."""
    x = values.detach()
    if x.dtype not in (torch.float32, torch.float64):
        x = x.float()  # half precision: reduced in float32 (min / max are exact)
    b, _, h, w = x.shape
    t = CULL_TILE
    # max of (x, -x) per tile: one masked copy, one reduction (min = -max of -x); the mask
    # as an added 0 / -inf (a broadcast masked_fill_ or where was ~3x slower on CPU)
    off = torch.zeros((), dtype=x.dtype, device=x.device)
    both = torch.cat([x, -x], 1) + torch.where(mask, off, float("-inf")).expand(b, 1, h, w)
    ph, pw = (-h) % t, (-w) % t
    if ph or pw:
        both = torch.nn.functional.pad(both, (0, pw, 0, ph), value=float("-inf"))
    red = both.view(b, 6, (h + ph) // t, t, (w + pw) // t, t).amax(5).amax(3).flatten(2)
    hi, lo = red[:, :3].transpose(1, 2), -red[:, 3:].transpose(1, 2)
    return lo, hi, hi[..., 0] > float("-inf")


def _support(planes: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
             origin: torch.Tensor | None = None) -> torch.Tensor:
    """``max n . (q - origin)`` over the boxes ``lo``..``hi`` ``(T, 3)`` of each plane ``n``
    ``(Ls, P, 3)`` (``origin`` ``(Ls, 3)`` or None: 0): ``(T, Ls, P)``, as
    ``n . centre + |n| . half extent`` (two small matrix products; float64)."""
    n_l, n_p = planes.shape[:2]
    flat = planes.reshape(n_l * n_p, 3)
    out = ((hi + lo) / 2) @ flat.T + ((hi - lo) / 2) @ flat.abs().T  # (T, Ls * P)
    if origin is not None:
        out = out - (planes * origin[:, None]).sum(-1).reshape(-1)
    return out.view(-1, n_l, n_p)


def _reach(planes: torch.Tensor, light: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
           slack: torch.Tensor, eye: torch.Tensor | None = None,
           dlo: torch.Tensor | None = None, dhi: torch.Tensor | None = None,
           rays: torch.Tensor | None = None) -> torch.Tensor:
    """``(Ls, NV)`` bool: some box ``lo``..``hi`` ``(T, 3)`` of one item may reach each
    view's region: no single plane of the view has the whole box outside (conservative;
    boxes alone against cube faces are tested exactly by :func:`_cube_reach`).

    With ``eye`` ``(3,)``: the receivers are the convex hulls of the eye and each box
    (segments from the eye), plus where ``rays`` ``(T,)`` the rays from the eye along the
    directions in ``dlo``..``dhi`` ``(T, 3)`` (unbounded segments)."""
    n_l, nv = planes.shape[:2]
    if eye is None and nv == 6:  # cube faces: exact (and cheaper) on the coordinates
        return _cube_reach(light, lo, hi, slack)
    flat = planes.reshape(n_l, nv * 4, 3)
    tol = slack * flat.abs().sum(-1)  # (Ls, P)
    base = None if eye is None else (flat * (eye - light)[:, None]).sum(-1)  # (Ls, P)
    out = torch.zeros(n_l, nv, dtype=torch.bool, device=planes.device)
    per = max(1, CULL_CHUNK_ELEMENTS // (n_l * nv * 4 * 3))
    for k in range(0, lo.shape[0], per):
        sl = slice(k, k + per)
        sup = _support(flat, lo[sl], hi[sl], light)  # (T, Ls, P)
        if base is not None:
            sup = torch.maximum(sup, base)
            if rays is not None:  # an unbounded ray with n . d > 0 leaves no plane behind
                up = _support(flat, dlo[sl], dhi[sl]) > 0
                sup = torch.where(up & rays[sl, None, None], float("inf"), sup)
        out |= (sup + tol >= 0).view(-1, n_l, nv, 4).all(-1).any(0)
    return out


def _cube_reach(light: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
                slack: torch.Tensor, tan_half: float = 1.0) -> torch.Tensor:
    """``(Ls, 6)`` bool: some box ``lo``..``hi`` ``(T, 3)`` holds a point whose dominant
    axis from the light ``(Ls, 3)`` is each cube face's (+X -X +Y -Y +Z -Z), or with
    ``tan_half`` > 1 that lies in each face's frustum widened to it. Face (k, s) needs
    ``tan_half s q_k >= |q_j|`` (j != k) at one point: take ``s q_k`` at its largest over
    the box, then each ``|q_j|`` at its smallest (the coordinates are independent);
    widened by :data:`CULL_WIDEN` and ``slack`` (m), like the planes of
    :func:`_read_planes`."""
    w = tan_half * (1 + CULL_WIDEN)
    tol = slack * (w + 1)
    out = []
    per = max(1, CULL_CHUNK_ELEMENTS // (light.shape[0] * 3))
    for k in range(0, lo.shape[0], per):
        qlo, qhi = lo[k:k + per, None] - light, hi[k:k + per, None] - light  # (T, Ls, 3)
        near = torch.maximum(torch.maximum(qlo, -qhi), torch.zeros_like(qlo))  # min |q_j|
        faces = []
        for axis in range(3):
            others = near[..., [a for a in range(3) if a != axis]].amax(-1)
            for ext in (qhi[..., axis], -qlo[..., axis]):  # +axis, -axis
                faces.append((w * ext + tol >= others) & (ext * w + tol >= 0))
        out.append(torch.stack(faces, -1).any(0))
    return torch.stack(out).any(0)


#: Consecutive caster triangles bounded by one box in the casters' test.
CULL_CASTER_RUN: int = 16


def _caster_boxes(positions: torch.Tensor, faces: torch.Tensor,
                  face_range: tuple[int, int] | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounds ``(T, 3)`` (min, max) of runs of :data:`CULL_CASTER_RUN` consecutive
    triangles ``faces`` (``face_range`` of them) over ``positions`` ``(V, 3)``."""
    if face_range is not None:
        faces = faces[face_range[0]:face_range[1]]
    tri = positions.detach().index_select(0, faces.reshape(-1)).view(-1, 3, 3)
    pad = (-len(tri)) % CULL_CASTER_RUN  # the last run repeats its last triangle
    if pad and len(tri):
        tri = torch.cat([tri, tri[-1:].expand(pad, 3, 3)])
    runs = tri.view(-1, CULL_CASTER_RUN * 3, 3)
    return runs.amin(1), runs.amax(1)


def _caster_reach(g: ShadowMaps, casters: tuple, planes: torch.Tensor, light: torch.Tensor,
                  slack: torch.Tensor) -> torch.Tensor:
    """``(B, Ls, NV)`` bool: some caster triangle may lie in each view's frustum (a view
    without any renders ``+inf`` everywhere, the value its maps start with)."""
    positions, faces, face_ranges = casters
    b, n_l, nv = g.view.shape[:3]
    pos = positions if positions.dim() == 3 else positions[None]
    out = torch.zeros(b, n_l, nv, dtype=torch.bool, device=g.view.device)
    tan_half = float(1 / g.proj.detach()[0, 0, 0, 0, 0]) if g.layout == "cube" else 1.0
    for i in range(b):
        rng = None if face_ranges is None else tuple(face_ranges[i].tolist())
        lo, hi = _caster_boxes(pos[min(i, pos.shape[0] - 1)], faces, rng)
        if lo.shape[0] == 0:
            continue
        lo, hi = lo.to(light.dtype), hi.to(light.dtype)
        if g.layout == "cube":
            out[i] = _cube_reach(light[i], lo, hi, slack[i], tan_half)
        else:  # the spot's read region holds its frustum (the taps' reach added)
            out[i] = _reach(planes[i], light[i], lo, hi, slack[i])
    return out


def cull_local_views(groups: ShadowMaps | Sequence[ShadowMaps],
                     points: Sequence[tuple[torch.Tensor, torch.Tensor]] = (),
                     segments: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
                     boxes: torch.Tensor | None = None,
                     casters: tuple[torch.Tensor, torch.Tensor, torch.Tensor | None] | None
                     = None) -> None:
    """Mark the views of point / spot groups that some receiver can read (sets each
    group's ``needed``; :func:`render_shadow_maps` renders only those, so with every
    receiver given the lookups, and the image, are bit-identical to rendering every view).

    A cube face is read by the receivers whose dominant direction from the light is its
    axis; a spot map by those whose filter footprint touches it (:func:`_read_planes`).
    Receivers are tested in boxes: one per :data:`CULL_TILE` square tile of pixels (the
    bounds of its surface points, or the hull of the eye and its segments' ends). A box is
    kept for a view unless one of the view's planes has it wholly outside: exact for boxes
    and cube faces, conservative otherwise (a view near a border is kept). The regions are
    widened by :data:`CULL_WIDEN` and their planes moved by :data:`CULL_SLACK` times the
    item's largest coordinate (the lookup's own rounding). Does nothing with
    :data:`CULL_VIEWS` False or when no receiver set is given.

    Args:
        groups: from :func:`local_views` (directional groups are left alone), one or
            several of the same batch (the receivers are boxed once for all).
        points: surface receivers: pairs of positions ``(B, 3, H, W)`` and ``(B, 1, H, W)``
            masks (bool or {0, 1}) of the pixels that are surfaces.
        segments: receivers along view rays (fog samples): eyes ``(B, 3)``, unit directions
            ``(B, 3, H, W)``, lengths ``(B, 1, H, W)`` (``inf``: the whole ray; <= 0: none).
        boxes: ``(B, 2, 3)`` world boxes (row 0 min, row 1 max) anywhere in which a
            receiver may lie (e.g. sub-samples not known yet).
        casters: the shadow casters as given to :func:`render_shadow_maps` (positions
            ``(B, V, 3)`` or ``(V, 3)``, faces ``(F, 3)``, face ranges ``(B, 2)`` or None):
            views whose frustum holds no caster triangle are not rendered either (their
            maps stay ``+inf``, exactly what rendering them gives; not for VSM, whose
            empty maps are blurred moments).
    """
    groups = [groups] if isinstance(groups, ShadowMaps) else list(groups)
    groups = [g for g in groups if g.kind != "directional"]
    if not CULL_VIEWS or not groups or not (points or segments is not None
                                            or boxes is not None):
        return
    # the batch; receivers or a group of batch 1 are shared by every item (a group's maps
    # then read by all)
    sizes = ([g.view.shape[0] for g in groups] + [pos.shape[0] for pos, _ in points]
             + ([segments[0].shape[0]] if segments is not None else [])
             + ([boxes.shape[0]] if boxes is not None else []))
    b = max(sizes)
    if any(n not in (1, b) for n in sizes):
        raise ValueError(f"cull_local_views: batch sizes {sorted(set(sizes))} of the groups "
                         "and receivers; expected 1 (shared) or one common size")
    dt = torch.float64
    dev = groups[0].view.device
    scale = torch.zeros(b, dtype=dt, device=dev)  # (B,) the largest coordinate of each item
    tests = []  # (item, lo, hi, extra keyword arguments of _reach)

    def add(i: int, lo: torch.Tensor, hi: torch.Tensor, **extra) -> None:
        scale[i] = torch.maximum(scale[i], torch.maximum(lo.abs().amax(), hi.abs().amax()))
        tests.append((i, lo, hi, extra))

    for pos, mask in points:
        lo, hi, on = _tile_boxes(pos.expand(b, 3, *pos.shape[-2:]),
                                 (mask.detach() > 0).expand(b, 1, *mask.shape[-2:]))
        for i in range(b):
            if bool(on[i].any()):
                add(i, lo[i][on[i]].to(dt), hi[i][on[i]].to(dt))
    if segments is not None:
        eye, rays, length = (t.detach() for t in segments)
        h, w = rays.shape[-2:]
        eye = eye.to(dt).expand(b, 3)
        rays, length = rays.expand(b, 3, h, w), length.expand(b, 1, h, w)
        finite, endless = torch.isfinite(length) & (length > 0), torch.isinf(length)
        # the march's own rounding: its segments end within a relative 1e-5 of these
        start = eye.to(rays.dtype)[:, :, None, None]
        ends = start + rays * torch.where(finite, length * (1 + 1e-5), torch.zeros_like(length))
        lo, hi, on = _tile_boxes(torch.where(finite, ends, start), finite | endless)
        dlo, dhi, ray_on = _tile_boxes(rays, endless)
        dlo = torch.where(ray_on[..., None], dlo, 0.0).to(dt)  # tiles without rays: unused
        dhi = torch.where(ray_on[..., None], dhi, 0.0).to(dt)
        for i in range(b):
            keep = on[i]
            if bool(keep.any()):
                add(i, lo[i][keep].to(dt), hi[i][keep].to(dt), eye=eye[i], dlo=dlo[i][keep],
                    dhi=dhi[i][keep], rays=ray_on[i][keep])
                scale[i] = torch.maximum(scale[i], eye[i].abs().amax())
    if boxes is not None:
        boxes = boxes.detach().to(dt).expand(b, 2, 3)
        for i in range(b):
            add(i, boxes[i, :1], boxes[i, 1:])
    for g in groups:
        planes = _read_planes(g)
        if planes is None:
            continue
        b_g, n_l, nv = g.view.shape[:3]
        light = g.light_position.detach().to(dt).expand(b_g, n_l, 3)
        # shared maps (b_g = 1 < b): any item's receivers; the largest item's slack
        scale_g = scale if b_g == b else scale.amax().reshape(1)
        slack = CULL_SLACK * torch.maximum(scale_g, light.abs().amax((1, 2)))
        needed = torch.zeros(b_g, n_l, nv, dtype=torch.bool, device=dev)
        for i, lo, hi, extra in tests:
            j = i if b_g == b else 0
            needed[j] |= _reach(planes[j], light[j], lo, hi, slack[j], **extra)
        if casters is not None and g.settings.filter != "vsm":
            needed &= _caster_reach(g, casters, planes, light, slack)
        g.needed = needed


# ------------------------------------------------------------------------------- render


def _digest(t: torch.Tensor) -> tuple:
    """A key identifying a tensor by value: a 128-bit BLAKE2 digest of its bytes, with its
    shape and dtype (as ``ibl.content_key``; equal keys hold the same numbers)."""
    data = t.detach().contiguous().cpu()
    digest = hashlib.blake2b(data.view(torch.uint8).numpy().tobytes(), digest_size=16)
    return digest.hexdigest(), tuple(t.shape), str(t.dtype)


class ShadowMapCache:
    """Rendered depth maps kept across calls, keyed by content (static casters and lights:
    a moving camera re-renders no map).

    A view's key is its map size, its 4x4 world -> clip matrix and the casters it draws
    (a 128-bit digest of its batch item's positions and of the faces, its face range), so
    any change (also an in-place edit) renders anew. Views of one call with equal keys (e.g.
    a batch of cameras sharing a sun whose map is fitted to the casters) are rendered once.
    Only the non-differentiable depth pass is cached (not VSM maps with autograd on).
    The keys hold digests, not copies of the casters, so what the cache holds is bounded
    by ``max_bytes`` (maps and matrices) however the geometry changes from call to call.

    Args:
        max_bytes: bound on the bytes held (maps and key matrices; least recently used
            dropped first).
    """

    def __init__(self, max_bytes: int = 64 * 2**20) -> None:
        self.max_bytes = int(max_bytes)
        self._entries: list[tuple] = []  # (size, matrix, positions digest, faces digest,
        #                                    range, depth)
        self.renders = 0  # views rendered (not found in the cache), for tests and benches

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def nbytes(self) -> int:
        """Bytes of the tensors the cache holds (maps and key matrices)."""
        return sum(self._entry_bytes(e) for e in self._entries)

    @staticmethod
    def _entry_bytes(e: tuple) -> int:
        return sum(t.numel() * t.element_size() for t in e if isinstance(t, torch.Tensor))

    @staticmethod
    def _same(a: tuple, b: tuple) -> bool:
        return (a[0] == b[0] and a[2] == b[2] and a[3] == b[3] and a[4] == b[4]
                and torch.equal(a[1], b[1]))

    def render(self, pos: torch.Tensor, faces: torch.Tensor, face_ranges: torch.Tensor | None,
               items: torch.Tensor, mats: torch.Tensor, size: int, per_call: int
               ) -> torch.Tensor:
        """NDC depth ``(N, S, S)`` of the N views ``mats`` ``(N, 4, 4)`` of batch items
        ``items`` ``(N,)`` (positions ``(B or 1, V, 3)``), as :func:`rasterize_depth`."""
        pos, mats = pos.detach(), mats.detach()
        shared = pos.shape[0] == 1
        pos_keys = [_digest(pos[0])] if shared else [_digest(p) for p in pos]
        faces_key = _digest(faces)
        keys, found = [], []
        for j, it in enumerate(items.tolist()):
            rng = None if face_ranges is None else tuple(face_ranges[it].tolist())
            key = (size, mats[j].clone(), pos_keys[0 if shared else it], faces_key, rng)
            hit = next((k for k, e in enumerate(self._entries) if self._same(e, key)), None)
            if hit is None:  # an equal view earlier in this call
                hit = next((-1 - i for i, k in enumerate(keys[:j]) if found[i] is None
                            and self._same(k, key)), None)
            keys.append(key)
            found.append(hit)
        todo = [j for j, f in enumerate(found) if f is None]
        fresh: dict[int, torch.Tensor] = {}
        for k in range(0, len(todo), per_call):
            idx = torch.tensor(todo[k:k + per_call], device=items.device)
            src = pos.index_select(0, items.index_select(0, idx)) if not shared else pos.expand(
                idx.numel(), -1, -1)
            homo = torch.cat([src, torch.ones_like(src[..., :1])], -1)
            clip = homo @ mats.index_select(0, idx).to(homo.dtype).transpose(1, 2)
            ranges = None if face_ranges is None else face_ranges.index_select(
                0, items.index_select(0, idx))
            depth = rasterize_depth(clip, faces, (size, size), face_ranges=ranges)
            fresh.update(zip(todo[k:k + per_call], depth, strict=True))
        self.renders += len(todo)
        out = [fresh[j] if f is None else fresh[-1 - f] if f < 0 else self._entries[f][5]
               for j, f in enumerate(found)]
        hits = list(dict.fromkeys(f for f in found if f is not None and f >= 0))
        self._entries = ([e for k, e in enumerate(self._entries) if k not in hits]
                         + [self._entries[k] for k in hits]  # most recently used last
                         + [keys[j] + (fresh[j],) for j in todo])
        nbytes = self.nbytes
        while nbytes > self.max_bytes and self._entries:
            nbytes -= self._entry_bytes(self._entries.pop(0))
        return torch.stack(out) if out else pos.new_empty(0, size, size)


def render_shadow_maps(groups: Sequence[ShadowMaps], positions: torch.Tensor,
                       faces: torch.Tensor, face_ranges: torch.Tensor | None = None,
                       memory_budget: int = SHADOW_MEMORY_BUDGET,
                       cache: ShadowMapCache | None = None) -> None:
    """Render the depth of every view of ``groups`` (in place: sets ``group.depth``).

    All views of one map size go through :func:`rasterize_depth` in chunks of
    ``memory_budget`` bytes of maps; each chunk is converted to linear depth (or VSM
    moments) and written into the group's map before the next is rendered, so the peak is
    the maps plus one chunk's temporaries. VSM groups with autograd on use the
    differentiable :func:`rasterize`.

    Args:
        groups: from :func:`directional_views` / :func:`local_views`.
        positions: ``(B, V, 3)`` or ``(V, 3)`` world positions; faces: ``(F, 3)`` the
            shadow casters; face_ranges: ``(B, 2)`` as in ``rasterize`` or None.
        memory_budget: bytes of shadow maps (and per-pixel buffers) rendered per call.
        cache: a :class:`ShadowMapCache`: maps of views seen before (same casters, same
            matrix) are reused, and equal views of this call rendered once. Maps larger
            than its ``max_bytes`` bypass it (it could not keep them).
    """
    positions = positions.to(compute_dtype(positions))  # half precision: maps in float32
    by_size: dict[tuple[int, bool], list[ShadowMaps]] = {}
    for g in groups:
        grad = g.settings.filter == "vsm" and torch.is_grad_enabled() and (
            positions.requires_grad or g.view.requires_grad)
        by_size.setdefault((g.settings.map_size, grad), []).append(g)
    pos = positions if positions.dim() == 3 else positions[None]
    for (size, grad), members in by_size.items():
        mats, owners, slots, spans = [], [], [], []
        for g in members:
            b, n_lights, nv = g.view.shape[:3]
            # flat (B * Ls * NV) index of each rendered view in the group's maps (b, light,
            # view order, as the maps are laid out)
            flat = _views_to_render(g).reshape(-1).nonzero().flatten()
            mats.append((g.proj @ g.view).reshape(-1, 4, 4).index_select(0, flat))
            owners.append(torch.div(flat, n_lights * nv, rounding_mode="floor"))
            slots.append(flat)
            start = spans[-1][1] if spans else 0
            spans.append((start, start + slots[-1].numel()))
            g.depth = _empty_maps(g, size, positions.dtype)
            g.face_id, g.casters = None, None
            if (g.settings.filter in ("pcf", "pcss") and torch.is_grad_enabled()
                    and positions.requires_grad):  # for the casters' gradient
                g.face_id = torch.full(g.depth.shape, -1, dtype=torch.int32,
                                       device=g.depth.device)
                g.casters = (pos, faces)
        all_m = torch.cat(mats) if grad else torch.cat(mats).detach()
        if grad:  # near / far / projection of every view, for _vsm_render
            near_rows = torch.cat([g.near.reshape(-1).index_select(0, sl)
                                   for g, sl in zip(members, slots, strict=True)])
            far_rows = torch.cat([g.far.reshape(-1).index_select(0, sl)
                                  for g, sl in zip(members, slots, strict=True)])
            persp_rows = torch.cat([torch.full((sl.numel(),), g.perspective,
                                               device=sl.device)
                                    for g, sl in zip(members, slots, strict=True)])
        items = torch.cat(owners)
        per_view = size * size * (16 if not grad else 400)
        per_call = max(1, memory_budget // per_view)
        cached = (cache is not None and not grad and size * size * 4 <= cache.max_bytes
                  and size * size <= DIRECT_MAP_TEXELS  # larger: straight into the maps
                  and all(g.face_id is None for g in members))  # the cache keeps no face ids
        for k in range(0, all_m.shape[0], per_call):
            sl = slice(k, k + per_call)
            into = None  # the group's own maps when rendered in place (_map_rows)
            if cached:
                ndc = cache.render(pos, faces, face_ranges, items[sl], all_m[sl], size,
                                   per_call)
            else:
                src = pos.index_select(0, items[sl]) if pos.shape[0] > 1 else pos.expand(
                    all_m[sl].shape[0], -1, -1)
                homo = torch.cat([src, torch.ones_like(src[..., :1])], -1)
                clip = homo @ all_m[sl].to(homo.dtype).transpose(1, 2)
                del src, homo
                ranges = None if face_ranges is None else face_ranges.index_select(0, items[sl])
                if grad:
                    ndc = _vsm_render(clip, faces, size, ranges, near_rows[sl], far_rows[sl],
                                      persp_rows[sl])
                else:  # large maps: rendered straight into the group's maps
                    into = _map_rows(members, spans, slots, k, clip.shape[0])
                    budget = DEFAULT_MEMORY_BUDGET if into is None else DIRECT_RASTER_BUDGET
                    ndc = rasterize_depth(clip, faces, (size, size), face_ranges=ranges,
                                          out=into, memory_budget=budget)
                    if any(g.face_id is not None for g in members):
                        with torch.no_grad():  # the same winners as rasterize_depth
                            fid = rasterize(clip.detach(), faces, (size, size),
                                            face_ranges=ranges).face_id.to(torch.int32)
                        for g, (lo, hi), slot in zip(members, spans, slots, strict=True):
                            a, z = max(lo, k), min(hi, k + fid.shape[0])
                            if a < z and g.face_id is not None:
                                g.face_id.view(-1, size, size).index_copy_(
                                    0, slot[a - lo:z - lo], fid[a - k:z - k])
                del clip
            for g, (lo, hi), slot in zip(members, spans, slots, strict=True):
                a, z = max(lo, k), min(hi, k + ndc.shape[0])
                if a < z:
                    _store_maps(g, ndc[a - k:z - k].to(positions.dtype),
                                slot[a - lo:z - lo], in_place=into is not None)
            del ndc
        for g, slot in zip(members, slots, strict=True):
            nv = g.view.shape[2]
            keep = int(g.rendered.sum())
            what = {"cascades": f"{nv} cascades", "cube": "cube 6 faces",
                    "single": "1 map"}[g.layout]
            if keep < nv:
                what = f"{keep} of {nv} " + ("cascades" if nv > 1 else "maps")
            culled = ""
            if g.needed is not None:  # culled (cull_local_views): views of all items, lights
                culled = f", {slot.numel()} of {g.needed.numel()} " + (
                    "faces rendered" if g.layout == "cube" else "maps rendered")
            g.steps.append(f"shadow {g.kind}{g.lights} {what} {size}x{size} {g.settings.filter}"
                           + culled)


_RENDERED = re.compile(r"^(.*), (\d+) of (\d+) (faces|maps) rendered$")


def merge_shadow_steps(steps: Iterable[str]) -> tuple[str, ...]:
    """The shadow steps of several calls (e.g. the chunks of one batch) as one call's:
    equal steps once, and the counts of ``", k of n faces rendered"`` (culled views)
    added up per group.

    Example:
        >>> merge_shadow_steps(["shadow point[0] cube 6 faces 64x64 pcf, 5 of 12 faces "
        ...                     "rendered", "shadow point[0] cube 6 faces 64x64 pcf, 3 of 6 "
        ...                     "faces rendered"])
        ('shadow point[0] cube 6 faces 64x64 pcf, 8 of 18 faces rendered',)
    """
    merged: dict[tuple[str, str], list[int]] = {}
    for step in steps:
        m = _RENDERED.match(step)
        key = (step, "") if m is None else (m[1], m[4])
        counts = merged.setdefault(key, [0, 0])
        if m is not None:
            counts[0] += int(m[2])
            counts[1] += int(m[3])
    return tuple(step if not unit else f"{step}, {k} of {n} {unit} rendered"
                 for (step, unit), (k, n) in merged.items())


def _views_to_render(g: ShadowMaps) -> torch.Tensor:
    """``(B, Ls, NV)`` bool: the views of ``g`` that :func:`render_shadow_maps` renders."""
    shape = g.view.shape[:3]
    todo = g.rendered.view(1, 1, -1).expand(shape)
    return todo if g.needed is None else todo & g.needed.to(todo.device).expand(shape)


def _empty_maps(g: ShadowMaps, size: int, dtype: torch.dtype) -> torch.Tensor:
    """The maps of group ``g`` before any view is rendered: ``+inf`` (no caster), or for
    VSM the moments of depth at the far plane."""
    b, n_lights, nv = g.view.shape[:3]
    if g.settings.filter != "vsm":
        return torch.full((b, n_lights, nv, size, size), float("inf"), dtype=dtype,
                          device=g.view.device)
    one = torch.ones(1, size, size, dtype=dtype, device=g.view.device)
    far = _vsm_moments(one, one[:, :1, :1] * 0, one[:, :1, :1], g.settings)  # z = 1
    return far.expand(b * n_lights * nv, 2, size, size).reshape(
        b, n_lights, nv, 2, size, size).contiguous()


def _map_rows(members: list[ShadowMaps], spans: list[tuple[int, int]],
              slots: list[torch.Tensor], k: int, n: int) -> torch.Tensor | None:
    """The maps that views ``k .. k + n`` of a render chunk go to, as one ``(n, S, S)``
    float32 view of a group's maps when they are consecutive maps of a group without
    moments and larger than :data:`DIRECT_MAP_TEXELS` (rendered in place: no frame-sized
    temporary), else None."""
    for g, (lo, hi), slot in zip(members, spans, slots, strict=True):
        if lo <= k and k + n <= hi and g.settings.filter != "vsm" \
                and g.depth.dtype == torch.float32 and g.face_id is None \
                and g.settings.map_size ** 2 > DIRECT_MAP_TEXELS:
            part = slot[k - lo:k - lo + n]
            first = int(part[0])
            if torch.equal(part, torch.arange(first, first + n, device=part.device)):
                size = g.settings.map_size
                return g.depth.view(-1, size, size)[first:first + n]
    return None


#: Maps of more texels than this are rendered straight into the group's maps (their
#: NDC depth converted in place there) instead of through a chunk-sized buffer.
DIRECT_MAP_TEXELS = 2048**2


def _store_maps(g: ShadowMaps, ndc: torch.Tensor, slot: torch.Tensor,
                in_place: bool = False) -> None:
    """Write rendered NDC depth ``(N, S, S)`` of views ``slot`` ``(N,)`` (flat indices
    into ``(B * Ls * NV)``) into ``g.depth`` as linear depth, or VSM moments; ``ndc`` may
    also be the unblurred moments ``(N, 2, S, S)`` of :func:`_vsm_render`, or, with
    ``in_place``, already be those maps (:func:`_map_rows`: converted where they are)."""
    if ndc.dim() == 4:  # VSM moments with autograd: blurred, out of place
        val = _vsm_blur(ndc, g.settings)
        shape = g.depth.shape
        g.depth = g.depth.reshape(-1, *val.shape[1:]).index_copy(0, slot, val).view(shape)
        return
    near = g.near.reshape(-1).index_select(0, slot)[:, None, None]
    far = g.far.reshape(-1).index_select(0, slot)[:, None, None]
    if g.settings.filter != "vsm" and not (ndc.requires_grad or near.requires_grad
                                           or far.requires_grad):
        lin = _linear_depth_inplace(ndc, near, far, g.perspective)
        if not in_place:
            g.depth.view(-1, *ndc.shape[1:]).index_copy_(0, slot, lin)
        return
    lin = _linear_depth(ndc, near, far, g.perspective)
    if g.settings.filter == "vsm":
        val = _vsm_moments(lin, near, far, g.settings)
        size = ndc.shape[-1]
        flat = g.depth.view(-1, 2, size, size) if not val.requires_grad else None
    else:  # receivers beyond the casters' far plane are lit where nothing was drawn
        val = torch.where(torch.isfinite(ndc), lin, torch.full_like(lin, float("inf")))
        flat = g.depth.view(-1, *ndc.shape[1:])
    del lin
    if flat is not None:
        flat.index_copy_(0, slot, val)
        return
    # with autograd: out of place (the maps are small; the graph keeps every chunk anyway)
    shape = g.depth.shape
    g.depth = g.depth.reshape(-1, *val.shape[1:]).index_copy(0, slot, val).view(shape)


def _vsm_render(clip: torch.Tensor, faces: torch.Tensor, size: int,
                face_ranges: torch.Tensor | None, near: torch.Tensor, far: torch.Tensor,
                perspective: torch.Tensor) -> torch.Tensor:
    """Differentiable VSM moments ``(N, 2, S, S)`` (not blurred) of N views (``near``,
    ``far`` ``(N,)``, ``perspective`` ``(N,)`` bool) whose gradient includes the casters'
    silhouettes moving across texels: the moments are antialiased
    (:func:`~torchraster.raster.antialias`) straight through, so the values are those of
    :func:`rasterize`'s depth and the gradient with respect to ``clip`` (light pose, caster
    vertices) is that of the edges' motion as well as of the covered depths. (Antialiasing
    the moments, not the depth: a texel an edge half covers has the variance of a mix.)"""
    frags = rasterize(clip, faces, (size, size), face_ranges=face_ranges)
    d = frags.depth
    near, far = near[:, None, None], far[:, None, None]
    persp = perspective[:, None, None]
    lin = torch.where(persp, _linear_depth(d, near, far, True),
                      _linear_depth(d, near, far, False))
    moments = _raw_moments(lin, near, far)
    if face_ranges is not None:  # antialias takes one face list shared by the batch
        return moments
    aa = antialias(moments, frags, clip, faces)
    return aa + (moments - aa).detach()  # values of moments, gradients of aa


def _vsm_moments(lin: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                 settings: ShadowSettings) -> torch.Tensor:
    """``(..., 2, S, S)`` blurred moments (z, z^2) of depth ``(..., S, S)`` normalised to
    [0, 1] over ``near``..``far`` (broadcast)."""
    return _vsm_blur(_raw_moments(lin, near, far), settings)


def _raw_moments(lin: torch.Tensor, near: torch.Tensor, far: torch.Tensor) -> torch.Tensor:
    """``(..., 2, S, S)`` moments (z, z^2) of depth normalised to [0, 1], not blurred."""
    z = ((lin - near) / (far - near)).clamp(0, 1)
    return torch.stack([z, z * z], dim=-3)


def _vsm_blur(moments: torch.Tensor, settings: ShadowSettings) -> torch.Tensor:
    """Gaussian blur (``settings.vsm_blur`` texels) of moments ``(..., 2, S, S)``."""
    if settings.vsm_blur > 0:
        import kornia  # noqa: PLC0415 (lazy: kornia is slow to import)

        shape = moments.shape
        flat = moments.reshape(-1, 2, shape[-2], shape[-1])
        sigma = float(settings.vsm_blur)
        k = 2 * math.ceil(3 * sigma) + 1
        flat = kornia.filters.gaussian_blur2d(flat, (k, k), (sigma, sigma),
                                              border_type="replicate")
        moments = flat.view(shape)
    return moments


# ------------------------------------------------------------------------------ lookup


def _select_view(g: ShadowMaps, p: torch.Tensor, item: torch.Tensor,
                 cam_depth: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per pixel and light, the view to sample: ``(P, Ls)`` int64 and the blend weight of
    the next cascade ``(P, Ls)`` (0 outside blend bands); view -1 = not covered (lit)."""
    n_p, n_l = p.shape[0], g.view.shape[1]
    zero = torch.zeros(n_p, n_l, dtype=p.dtype, device=p.device)
    if g.layout == "single":
        return torch.zeros(n_p, n_l, dtype=torch.int64, device=p.device), zero
    if g.layout == "cube":  # (3, P, Ls): components in contiguous planes
        light = g.light_position.detach()
        light = light[0].T[:, None] if light.shape[0] == 1 else light.index_select(
            0, item).permute(2, 0, 1)
        d = p.detach().T[:, :, None] - light
        ax, ay, az = d.abs()  # the dominant axis, ties to the lower (argmax's rule)
        x_major = (ax >= ay) & (ax >= az)
        y_major = ay >= az
        axis = torch.where(x_major, 0, torch.where(y_major, 1, 2))
        neg = torch.where(x_major, d[0], torch.where(y_major, d[1], d[2])) < 0
        return axis * 2 + neg.long(), zero
    splits = g.splits.detach().index_select(0, item)  # (P, Ls, C + 1)
    c = splits.shape[-1] - 1
    z = cam_depth[:, None].expand(n_p, n_l)
    idx = (z[..., None] >= splits[..., 1:]).sum(-1)  # first split end beyond z
    # the splits span the casters' depths, not the receivers': a receiver nearer than the
    # nearest caster uses the first cascade, one beyond the farthest the last (shadows are
    # cut off only at max_distance)
    max_d = g.settings.max_distance
    inside = torch.ones_like(idx, dtype=torch.bool) if max_d is None else z < max_d
    idx = idx.clamp_max(c - 1)
    lo = torch.gather(splits, 2, idx[..., None])[..., 0]
    hi = torch.gather(splits, 2, idx[..., None] + 1)[..., 0]
    band = g.settings.cascade_blend * (hi - lo)
    t = ((z - (hi - band)) / band.clamp_min(1e-12)).clamp(0, 1)
    t = torch.where((idx < c - 1) & (band > 0), t, torch.zeros_like(t))
    # a skipped cascade falls through to the next rendered one
    rendered = g.rendered
    if not bool(rendered.all()):
        nxt = torch.full((c,), -1, dtype=torch.int64, device=p.device)
        for k in range(c - 1, -1, -1):
            nxt[k] = k if bool(rendered[k]) else (nxt[k + 1] if k + 1 < c else -1)
        idx = nxt.index_select(0, idx.flatten()).view_as(idx)
    idx = torch.where(inside, idx, torch.full_like(idx, -1))
    return idx, t


def _affine(mats: torch.Tensor, x: torch.Tensor, sel: torch.Tensor, translate: bool,
            first: int | None = None) -> torch.Tensor:
    """``mats[sel] @ (x, 1)`` (or ``@ (x, 0)`` without ``translate``): ``(P, Ls, R)`` rows
    of the ``(M, R, 4)`` matrices ``sel`` ``(P, Ls)`` applied to points ``x`` ``(P, 3)``;
    ``first``: ``sel[:, l] == first + l`` (one view per light, receivers of one batch item:
    the Ls matrices broadcast, no gather) or None."""
    # elementwise products in a fixed order (not a BLAS product, whose rounding depends on
    # the matrix shapes): any batch size gives the same bits per receiver
    r = mats.shape[1]
    # each pair's matrix gathered (a (4, R, P, Ls) temporary): 19x faster for a cube map
    # than transforming every receiver by all 6 views and picking its own (1.9 vs 36 ms
    # for 115k receivers, one thread); the receivers last in memory (the result is a view
    # of (R, P, Ls)), so that every product runs over contiguous rows: 1.3x faster than
    # (P, Ls, R, 4), 4x with a single matrix (not gathered, unless it needs a gradient: the
    # sum of an expand's gradient has another order than the gather's)
    cols = mats.permute(2, 1, 0).reshape(4 * r, -1)  # (4R, M)
    if (cols.shape[1] == 1 or first is not None) and not (torch.is_grad_enabled()
                                                          and mats.requires_grad):
        if cols.shape[1] > 1:  # no gather (~10 ms a chunk of 16384 receivers x 16 lights)
            cols = cols[:, first:first + sel.shape[1]]
        sub = cols.view(4, r, 1, -1).expand(4, r, *sel.shape)
    else:
        sub = cols.index_select(1, sel.flatten()).view(4, r, *sel.shape)
    xs = x.T[:, None, :, None]  # (3, 1, P, 1)
    out = xs[0] * sub[0] + xs[1] * sub[1] + xs[2] * sub[2]
    return (out + sub[3] if translate else out).permute(1, 2, 0)


def _project(g: ShadowMaps, p: torch.Tensor, n: torch.Tensor, item: torch.Tensor,
             view_idx: torch.Tensor, item0: int | None = None):
    """Map coordinates of receivers: texel x, y ``(P, Ls)`` (continuous, texel centres at
    integers), receiver depth with bias ``(P, Ls)``, texel size at the receiver (m), the
    flat map index ``(P, Ls)``, validity and the slope-scaled depth ramp ``(P, Ls)`` (m per
    texel of lookup offset: a filter tap ``r`` texels away compares against the receiver's
    depth minus ``r`` ramps, so a tilted receiver does not shadow itself). ``item0``: the
    batch item of every receiver, when they are of one item (else None)."""
    n_l, nv = g.view.shape[1], g.view.shape[2]
    size = g.settings.map_size
    v_safe = view_idx.clamp_min(0)
    sel = (item[:, None] * n_l + torch.arange(n_l, device=p.device)) * nv + v_safe  # (P, Ls)
    texel = g.texel.reshape(-1).index_select(0, sel.flatten()).view(sel.shape)
    # direction to the light and its slope on the receiver
    light = g.light_direction if g.kind == "directional" else g.light_position  # (B, Ls, 3)
    light = light.expand(p.shape[0], -1, -1) if light.shape[0] == 1 else light.index_select(
        0, item)
    # component-major (3, P, Ls): sums over a leading axis of 3 are plain elementwise adds
    # of contiguous planes (a sum over a last axis of 3 was 3-10x slower)
    light = light.permute(2, 0, 1)
    to_light = -light if g.kind == "directional" else safe_normalize(
        light - p.T[:, :, None], 0)
    nt = n.T[:, :, None]  # (3, P, 1)
    cos = (to_light[0] * nt[0] + to_light[1] * nt[1] + to_light[2] * nt[2]).clamp(1e-3, 1.0)
    # tan = sin / cos; "double where" on sin^2: sqrt's derivative is infinite at 0 (a light
    # straight along the normal), which gave NaN gradients w.r.t. the light direction
    sin2 = 1 - cos * cos
    flat = sin2 > 1e-12
    sin = torch.where(flat, torch.sqrt(torch.where(flat, sin2, torch.ones_like(sin2))),
                      torch.zeros_like(sin2))
    tan = (sin / cos).clamp_max(MAX_SLOPE)
    # view-space z and clip x, y, w of every receiver: rows of view and proj @ view
    view = g.view.reshape(-1, 4, 4)
    mats = torch.cat([view[:, 2:3], (g.proj.reshape(-1, 4, 4) @ view)[:, (0, 1, 3)]], 1)
    first = None if g.layout != "single" or item0 is None else item0 * n_l  # nv = 1
    zc = _affine(mats, p, sel, True, first)  # (P, Ls, 4): z, clip x, y, w
    depth = -zc[..., 0]
    world_texel = texel * depth.abs() if g.perspective else texel
    s = g.settings
    if s.normal_bias:  # receiver moved along its normal (the transforms are affine)
        zc = zc + _affine(mats, n, sel, False, first) * (
            s.normal_bias * world_texel)[..., None]
    w = zc[..., 3]
    w_safe = torch.where(w.abs() > 1e-12, w, torch.ones_like(w))
    x_ndc, y_ndc = zc[..., 1] / w_safe, zc[..., 2] / w_safe
    tx = (x_ndc + 1) * (size / 2) - 0.5
    ty = (1 - y_ndc) * (size / 2) - 0.5
    z_ref = -zc[..., 0] - world_texel * (s.bias + s.slope_bias * tan)
    valid = (view_idx >= 0) & (w > 1e-12)
    return tx, ty, z_ref, world_texel, sel, valid, world_texel * s.slope_bias * tan


def _map_xy(view: torch.Tensor, proj: torch.Tensor, x: torch.Tensor, size: int
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """Continuous texel coordinates ``(P, Ls, T)`` of world points ``x`` ``(P, Ls, T, 3)``
    in the views ``view`` / ``proj`` ``(P, Ls, 4, 4)``."""
    q = torch.einsum("plij,pltj->plti", view[..., :3, :3], x) + view[..., None, :3, 3]
    clip = torch.einsum("plij,pltj->plti", proj[..., :, :3], q) + proj[..., None, :, 3]
    w = clip[..., 3]
    w = torch.where(w.abs() > 1e-12, w, torch.ones_like(w))
    return (clip[..., 0] / w + 1) * (size / 2) - 0.5, (1 - clip[..., 1] / w) * (size / 2) - 0.5


def _blocker_motion(maps: torch.Tensor, sel: torch.Tensor, view: torch.Tensor,
                    proj: torch.Tensor, tx: torch.Tensor, ty: torch.Tensor,
                    z_ref: torch.Tensor, size: int, perspective: bool,
                    casters: tuple | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Filter tap positions ``tx``, ``ty`` ``(P, Ls, T)`` with the map's own motion taken
    out of their gradient (same values).

    A map rendered under ``torch.no_grad`` is piecewise constant in the light's pose, but
    the shadow edges it holds move with the light as much as the receiver does: a tap's
    comparison depends on the receiver's position *relative to the occluder's edge*. Each
    tap's blocker (the farthest blocking one of its 4 bilinear texels, at depth ``d``: the
    one at the occluder's silhouette, for a convex occluder) is put back into
    the world at the tap's texel position and depth ``d`` and projected again through the
    (differentiable) view; its map motion is subtracted from the tap's (straight through:
    the values do not change). Without it the gradient w.r.t. the light position or
    direction is that of a map glued to the light (measured: wrong sign for a point light
    over a caster half-way to the floor; docs/benchmarks.md, "shadow-gradients").

    ``casters``: ``(face ids (M, S*S), positions (B or 1, V, 3), faces (F, 3), item (P,))``
    when the casters' vertices need gradients: the blocker point is then the barycentric
    combination (fixed weights) of its face's vertices, so it also follows them.
    """
    with torch.no_grad():
        x0, y0 = torch.floor(tx).long(), torch.floor(ty).long()
        d = torch.full_like(tx, -float("inf"))
        fid = torch.full(tx.shape, -1, dtype=torch.int32, device=tx.device)
        z_ref = z_ref.expand_as(tx)
        for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
            v, inside = _fetch(maps, sel, x0 + dx, y0 + dy, size)
            v = torch.where(inside & (v < z_ref), v, -float("inf"))
            if casters is not None:
                f, _ = _fetch(casters[0], sel, x0 + dx, y0 + dy, size)
                fid = torch.where(v > d, f, fid)
            d = torch.maximum(d, v)
        d = torch.where(torch.isfinite(d), d, z_ref)
        vd, pd = view.detach(), proj.detach()
        # view-space point at the tap, depth d: x_ndc = (P00 x + P02 z + P03) / w with
        # z = -d and w = d (perspective) or 1 (orthographic)
        w = d if perspective else torch.ones_like(d)
        x_ndc = (tx + 0.5) * (2 / size) - 1
        y_ndc = 1 - (ty + 0.5) * (2 / size)
        qx = (x_ndc * w + pd[..., None, 0, 2] * d - pd[..., None, 0, 3]) / pd[..., None, 0, 0]
        qy = (y_ndc * w + pd[..., None, 1, 2] * d - pd[..., None, 1, 3]) / pd[..., None, 1, 1]
        q = torch.stack([qx, qy, -d], -1) - vd[..., None, :3, 3]
        x = torch.einsum("plji,pltj->plti", vd[..., :3, :3], q)  # R^T (q - t)
    if casters is not None:
        x = _on_caster(x, fid, *casters[1:])
    bx, by = _map_xy(view, proj, x, size)
    return tx - (bx - bx.detach()), ty - (by - by.detach())


def _on_caster(x: torch.Tensor, fid: torch.Tensor, positions: torch.Tensor,
               faces: torch.Tensor, item: torch.Tensor) -> torch.Tensor:
    """World points ``x`` ``(P, Ls, T, 3)`` on caster faces ``fid`` ``(P, Ls, T)`` (-1:
    none, kept) as barycentric combinations of the faces' vertices (weights fixed, from
    the detached geometry), differentiable in ``positions`` ``(B or 1, V, 3)``."""
    has = fid >= 0
    tri = faces.index_select(0, fid.clamp_min(0).flatten()).view(*fid.shape, 3)
    if positions.shape[0] == 1:
        vert = positions[0].index_select(0, tri.flatten())
    else:  # the receiver's batch item
        items = item.view(-1, *([1] * (tri.dim() - 1))).expand_as(tri)
        vert = positions.reshape(-1, 3).index_select(
            0, (items * positions.shape[1] + tri).flatten())
    vert = vert.view(*tri.shape, 3)  # (P, Ls, T, 3, 3)
    with torch.no_grad():  # barycentrics of x in its triangle (Ericson, RTCD 3.4)
        a, b, c = vert.detach().to(x.dtype).unbind(-2)
        v0, v1, v2 = b - a, c - a, x - a
        d00, d01, d11 = (v0 * v0).sum(-1), (v0 * v1).sum(-1), (v1 * v1).sum(-1)
        d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
        den = d00 * d11 - d01 * d01
        den = torch.where(den.abs() > 0, den, torch.ones_like(den))
        wb = (d11 * d20 - d01 * d21) / den
        wc = (d00 * d21 - d01 * d20) / den
        wts = torch.stack([1 - wb - wc, wb, wc], -1)
    on = (wts[..., None] * vert.to(x.dtype)).sum(-2)
    # same value as x (to rounding), the vertices' gradient
    return torch.where(has[..., None], x + (on - on.detach()), x)


def _fetch(maps: torch.Tensor, sel: torch.Tensor, x: torch.Tensor, y: torch.Tensor,
           size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Texel values at integer texel coordinates ``x``, ``y`` (any shape ``(P, Ls, ...)``)
    of map ``sel`` ``(P, Ls)``: (values, inside-the-map mask). ``maps``: ``(M, S*S)``."""
    inside = (x >= 0) & (x < size) & (y >= 0) & (y < size)
    xc, yc = x.clamp(0, size - 1), y.clamp(0, size - 1)
    extra = x.dim() - sel.dim()
    s = sel.view(*sel.shape, *([1] * extra))
    flat = (s * (size * size) + yc * size + xc).flatten()
    return maps.reshape(-1).index_select(0, flat).view(x.shape), inside


def _pcf(maps: torch.Tensor, sel: torch.Tensor, tx: torch.Tensor, ty: torch.Tensor,
         z_ref: torch.Tensor, size: int, bilinear: bool = True) -> torch.Tensor:
    """Visibility of comparisons at map positions ``tx``, ``ty`` ``(P, Ls, T)`` against
    ``z_ref`` ``(P, Ls, 1)`` or per tap ``(P, Ls, T)``: bilinearly weighted 4-texel
    comparisons (or the nearest texel), averaged over T. Outside the map = lit."""
    if not bilinear:
        d, inside = _fetch(maps, sel, torch.round(tx).long(), torch.round(ty).long(), size)
        lit = ((z_ref <= d) | ~inside).to(tx.dtype)
        return lit.mean(-1)
    x0f, y0f = torch.floor(tx.detach()), torch.floor(ty.detach())
    fx, fy = tx - x0f, ty - y0f
    x0, y0 = x0f.long(), y0f.long()
    out = 0
    for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                        (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        d, inside = _fetch(maps, sel, x0 + dx, y0 + dy, size)
        lit = ((z_ref <= d) | ~inside).to(tx.dtype)
        out = out + wgt * lit
    return out.mean(-1)


#: PCF lookups pad the maps (:func:`_pcf_padded`) when the padded copy has at most this many
#: texels (a bound on the copy's memory; larger maps are looked up unpadded, 1.5x slower).
PAD_MAP_ELEMENTS: int = 2**24


def _pad_maps(maps: torch.Tensor, size: int) -> torch.Tensor:
    """Maps ``(M, S*S)`` padded by 2 texels of ``+inf`` on every side, flat ``(M*(S+4)^2,)``
    (for :func:`_pcf_padded`)."""
    return torch.nn.functional.pad(maps.view(-1, size, size), (2, 2, 2, 2),
                                   value=float("inf")).reshape(-1)


def _pad_rendered_maps(g: ShadowMaps) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """The maps of ``g`` that hold depth, padded for :func:`_pcf_padded`, and ``(M,)``
    int32 the padded slot of each of the group's M maps (None: every map, in order).

    Views :func:`render_shadow_maps` did not render (culled cube faces, skipped cascades)
    are ``+inf`` throughout: they all read one shared ``+inf`` slot instead of a padded
    copy each (16 point lights at 512²: 44 of 96 cube faces are rendered, and the padded
    copy fits :data:`PAD_MAP_ELEMENTS`, 1.5x faster lookups than unpadded maps).
    (None, None) when the copy would exceed :data:`PAD_MAP_ELEMENTS` texels."""
    size = g.settings.map_size
    sp = size + 4
    maps = g.depth  # (B, Ls, NV, S, S); a light slice (_lights_of) is not contiguous
    keep = None if g.rendered is None else _views_to_render(g)
    if (keep is None or bool(keep.all())) and maps.is_contiguous():
        if maps[..., 0, 0].numel() * sp * sp > PAD_MAP_ELEMENTS:
            return None, None
        return _pad_maps(maps.reshape(-1, size * size), size), None
    if keep is None:
        keep = torch.ones(maps.shape[:3], dtype=torch.bool, device=maps.device)
    ids = keep.reshape(-1).nonzero().squeeze(1)
    if (ids.numel() + 1) * sp * sp > PAD_MAP_ELEMENTS:
        return None, None
    with torch.no_grad():  # compared, never differentiated (_pcf_padded)
        padded = maps.new_full((ids.numel() + 1, sp, sp), float("inf"))  # last: no caster
        for j, (b, light, v) in enumerate(keep.nonzero().tolist()):  # ids' order
            padded[j, 2:-2, 2:-2] = maps[b, light, v]
    slot = torch.full((keep.numel(),), ids.numel(), dtype=torch.int32, device=maps.device)
    slot[ids] = torch.arange(ids.numel(), dtype=torch.int32, device=maps.device)
    return padded.reshape(-1), slot


def _pcf_padded(padded: torch.Tensor, sel: torch.Tensor, tx: torch.Tensor, ty: torch.Tensor,
                z_ref: torch.Tensor, size: int) -> torch.Tensor:
    """:func:`_pcf` (bilinear, the same bits) with one index computation per tap instead of
    four: the maps are padded by 2 texels of ``+inf`` (:func:`_pad_maps`, or here when given
    ``(M, S*S)`` maps; no caster: lit, like the outside of a map), and the clamped top-left
    corner (in [-2, S]) reaches the other three at +1, +row.

    Fastest with the taps leading in memory (``(T, P, Ls)`` tensors viewed as ``(P, Ls, T)``,
    as :func:`_visibility_of_view` makes them): every operation then runs over contiguous
    rows, not over a last dimension of T."""
    sp = size + 4
    if padded.dim() == 2:  # (M, S*S) maps, not yet padded
        padded = _pad_maps(padded, size)
    tx, ty, z_ref = tx.movedim(-1, 0), ty.movedim(-1, 0), z_ref.movedim(-1, 0)  # (T, P, Ls)
    x0f, y0f = torch.floor(tx.detach()), torch.floor(ty.detach())
    fx, fy = tx - x0f, ty - y0f
    # int32 indices (the padded maps hold < 2**31 texels): half the index traffic, and
    # index_select is ~2x faster with them on CPU
    top = torch.add(x0f.clamp_(-2, size).to(torch.int32), y0f.clamp_(-2, size).to(torch.int32),
                    alpha=sp)
    if padded.numel() > sp * sp:  # several maps
        top += sel.to(torch.int32).view(*sel.shape, *([1] * (top.dim() - 1 - sel.dim()))) * (
            sp * sp)
    # the four texels gathered corner by corner (no index tensor of 4 per tap) into one
    # (4, T, P, Ls) tensor and compared in place as 0 / 1 floats (a bool result and where()
    # on it are ~3x slower): w * lit is where(lit, w, 0) exactly (w >= 0), and the weights'
    # graph is _pcf's (the same gradient bits)
    top, src = top.reshape(-1), padded.detach()
    d = padded.new_empty((4, *tx.shape))
    idx = torch.empty_like(top)
    for k, c in enumerate((0, 1, sp, sp + 1)):
        torch.index_select(src, 0, torch.add(top, c + 2 * sp + 2, out=idx), out=d[k].view(-1))
    lit = torch.le(z_ref.detach(), d, out=d).to(tx.dtype)
    out = (1 - fx) * (1 - fy) * lit[0]
    out = torch.addcmul(out, fx * (1 - fy), lit[1])
    out = torch.addcmul(out, (1 - fx) * fy, lit[2])
    out = torch.addcmul(out, fx * fy, lit[3])
    n = out.shape[0]
    if n > 4:  # _pcf's mean over a row-major last dimension (more than 4: another order)
        return out.movedim(0, -1).contiguous().mean(-1)
    acc = out[0]
    for k in range(1, n):
        acc = acc + out[k]
    return acc / n  # = out.mean(0) for n <= 4, and a mean over a last dimension of n


def _bilinear(maps: torch.Tensor, sel: torch.Tensor, tx: torch.Tensor, ty: torch.Tensor,
              size: int) -> torch.Tensor:
    """Bilinear samples ``(P, Ls, C)`` of C-channel maps ``(M, C, S*S)`` (clamped edges)."""
    x0f, y0f = torch.floor(tx.detach()), torch.floor(ty.detach())
    fx, fy = (tx - x0f)[..., None], (ty - y0f)[..., None]
    x0, y0 = x0f.long(), y0f.long()
    n_c = maps.shape[1]
    out = 0
    for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                        (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        xc, yc = (x0 + dx).clamp(0, size - 1), (y0 + dy).clamp(0, size - 1)
        flat = ((sel * n_c)[..., None] * (size * size)
                + torch.arange(n_c, device=sel.device) * (size * size)
                + (yc * size + xc)[..., None])
        vals = maps.reshape(-1).index_select(0, flat.flatten()).view(flat.shape)
        out = out + wgt * vals
    return out


def _light_slices(g: ShadowMaps) -> list[slice]:
    """Consecutive slices of the lights of a PCF / PCSS group whose rendered maps, padded,
    fit :data:`PAD_MAP_ELEMENTS` each (one slice for every light when they all fit, or for
    other filters): lookups slice by slice use padded maps (16 point lights x batch 4:
    176 rendered cube faces of 512² do not fit at once)."""
    n_l = g.view.shape[1]
    if g.settings.filter not in ("pcf", "pcss") or n_l < 2:
        return [slice(0, n_l)]
    sp = g.settings.map_size + 4
    keep = _views_to_render(g) if g.rendered is not None else torch.ones(
        g.view.shape[:3], dtype=torch.bool)
    counts = keep.sum((0, 2)).tolist()  # rendered maps of each light (all items)
    if (sum(counts) + 1) * sp * sp <= PAD_MAP_ELEMENTS:
        return [slice(0, n_l)]
    out, start, total = [], 0, 0
    for k, c in enumerate(counts):
        if k > start and (total + c + 1) * sp * sp > PAD_MAP_ELEMENTS:
            out.append(slice(start, k))
            start, total = k, 0
        total += c
    return [*out, slice(start, n_l)]


def _lights_of(g: ShadowMaps, sl: slice) -> ShadowMaps:
    """The group ``g`` restricted to its lights ``sl`` (views, maps and light data)."""
    per_light = {f: getattr(g, f) for f in ("view", "proj", "near", "far", "texel", "depth",
                                            "splits", "light_position", "light_direction",
                                            "face_id", "needed")}
    return replace(g, lights=g.lights[sl], steps=[], **{
        f: None if t is None else t[:, sl] for f, t in per_light.items()})


def _visibility_of_view(g: ShadowMaps, p, n, item, view_idx, padded=None, pixel=None,
                        slot=None, item0=None) -> torch.Tensor:
    """``(P, Ls)`` visibility of receivers in the views ``view_idx`` ``(P, Ls)``;
    ``padded``, ``slot``: :func:`_pad_rendered_maps` of ``g`` (PCF / PCSS) or None;
    ``pixel``: ``(P,)`` world size of a frame pixel at each receiver (``pixel_radius``)."""
    s = g.settings
    size = s.map_size
    tx, ty, z_ref, world_texel, sel, valid, ramp = _project(g, p, n, item, view_idx, item0)
    if s.filter == "vsm":
        maps = g.depth.reshape(-1, 2, size * size)
        m = _bilinear(maps, sel, tx, ty, size)
        near = g.near.reshape(-1).index_select(0, sel.flatten()).view(sel.shape)
        far = g.far.reshape(-1).index_select(0, sel.flatten()).view(sel.shape)
        z = ((z_ref - near) / (far - near)).clamp(0, 1)
        mean, sq = m[..., 0], m[..., 1]
        var = (sq - mean * mean).clamp_min(s.vsm_min_variance)
        d = z - mean
        p_max = var / (var + d * d)
        p_max = ((p_max - s.vsm_bleed) / (1 - s.vsm_bleed)).clamp(0, 1)
        vis = torch.where(z <= mean, torch.ones_like(p_max), p_max)
        inside = (tx > -0.5) & (tx < size - 0.5) & (ty > -0.5) & (ty < size - 0.5)
        vis = torch.where(inside, vis, torch.ones_like(vis))
        return torch.where(valid, vis, torch.ones_like(vis))
    maps = None  # (M, S*S): read by all but the padded PCF lookup (a slice's reshape copies)
    if s.filter != "pcf" or padded is None or torch.is_grad_enabled():
        maps = g.depth.reshape(-1, size * size)
    if s.filter == "hard":
        vis = _pcf(maps, sel, tx[..., None], ty[..., None], z_ref[..., None], size,
                   bilinear=False)
        return torch.where(valid, vis, torch.ones_like(vis))
    taps = _taps(s.pcf_taps, s.pcf_pattern, p.dtype, p.device)  # (T, 2)
    radius = torch.full_like(tx, float(s.pcf_radius))
    if s.filter == "pcss":
        radius = _pcss_radius(g, maps, sel, tx, ty, z_ref, world_texel, taps, ramp)
    if pixel is not None and s.pixel_radius > 0:  # the pixel's footprint, in texels (a
        # filter width like a texture's LOD: no gradient)
        grow = (s.pixel_radius * pixel.detach()[:, None] / world_texel.detach()).to(radius)
        radius = torch.sqrt(radius * radius + grow * grow).clamp_max(
            max(s.max_penumbra, s.pcf_radius))
    # each tap against the receiver plane's depth there (+1 texel: the bilinear footprint);
    # (T, P, Ls) in memory, seen as (P, Ls, T): broadcasting the per-receiver values over
    # rows is ~4x faster than over a last dimension of T
    tap_r = taps.T[..., None, None] * radius  # (2, T, P, Ls)
    z_taps = (z_ref - ramp * (taps.norm(dim=-1)[:, None, None] * radius + 1)).movedim(0, -1)
    tap_x, tap_y = (tx + tap_r[0]).movedim(0, -1), (ty + tap_r[1]).movedim(0, -1)
    casters = None
    if torch.is_grad_enabled() and g.face_id is not None:
        casters = (g.face_id.reshape(-1, size * size), *g.casters, item)
    if torch.is_grad_enabled() and (g.view.requires_grad or g.proj.requires_grad
                                    or casters is not None):
        view = g.view.reshape(-1, 4, 4).index_select(0, sel.flatten()).view(*sel.shape, 4, 4)
        proj = g.proj.reshape(-1, 4, 4).index_select(0, sel.flatten()).view(*sel.shape, 4, 4)
        tap_x, tap_y = _blocker_motion(maps, sel, view, proj, tap_x, tap_y, z_taps, size,
                                       g.perspective, casters)
    if padded is not None:
        if slot is not None:  # the rendered maps' slots (the others: the +inf slot)
            sel = slot.index_select(0, sel.flatten()).view(sel.shape)
        vis = _pcf_padded(padded, sel, tap_x, tap_y, z_taps, size)
    else:  # row-major taps: _pcf's mean over more than 4 leading ones sums in another order
        vis = _pcf(maps, sel, tap_x.contiguous(), tap_y.contiguous(), z_taps.contiguous(), size)
    return torch.where(valid, vis, torch.ones_like(vis))


def _pcss_radius(g: ShadowMaps, maps, sel, tx, ty, z_ref, world_texel, taps, ramp
                 ) -> torch.Tensor:
    """PCSS filter radius (texels) ``(P, Ls)`` from a blocker search (Fernando 2005); the
    receiver itself is no blocker (each search tap compares against the receiver plane's
    depth there, ``ramp`` m per texel, see :func:`_project`)."""
    s = g.settings
    size = s.map_size
    with torch.no_grad():
        if g.perspective:
            near = g.near.reshape(-1).index_select(0, sel.flatten()).view(sel.shape)
            # the light's disc seen from the receiver, on the near plane, in texels there
            texel_near = g.texel.reshape(-1).index_select(0, sel.flatten()).view(sel.shape)
            search = s.light_size * (z_ref - near).clamp_min(0) / z_ref.clamp_min(1e-9) / (
                texel_near * near)
        else:
            tan_half = math.tan(math.radians(s.light_size) / 2)
            search = (z_ref - g.near.reshape(-1).index_select(0, sel.flatten()).view(
                sel.shape)).clamp_min(0) * tan_half / world_texel
        search = search.clamp(1.0, s.max_penumbra)
        x = torch.round(tx[..., None] + taps[:, 0] * search[..., None]).long()
        y = torch.round(ty[..., None] + taps[:, 1] * search[..., None]).long()
        d, inside = _fetch(maps, sel, x, y, size)
        z_taps = z_ref[..., None] - ramp[..., None] * (taps.norm(dim=-1) * search[..., None] + 1)
        blocker = inside & (d < z_taps)
        count = blocker.sum(-1)
        d_blk = torch.where(blocker, d, torch.zeros_like(d)).sum(-1) / count.clamp_min(1)
        if g.perspective:
            width = s.light_size * (z_ref - d_blk).clamp_min(0) / d_blk.clamp_min(1e-9)
        else:
            width = (z_ref - d_blk).clamp_min(0) * math.tan(math.radians(s.light_size) / 2)
        radius = (width / world_texel).clamp(0.5, s.max_penumbra)
        return torch.where(count > 0, radius, torch.full_like(radius, 0.5))


def shadow_visibility(g: ShadowMaps, position: torch.Tensor, normal: torch.Tensor,
                      receive: torch.Tensor, camera_view: torch.Tensor | None = None,
                      pixel_size: torch.Tensor | None = None) -> torch.Tensor:
    """The fraction of each light of a group that reaches each pixel.

    Args:
        g: rendered :class:`ShadowMaps` (``g.depth`` set).
        position: ``(B, 3, H, W)`` world positions; normal: ``(B, 3, H, W)`` unit normals.
        receive: ``(B, 1, H, W)`` bool: pixels that receive shadows (covered, and their
            face's ``receive_shadows``).
        camera_view: ``(B, 4, 4)`` world -> view of the camera (cascade selection).
        pixel_size: ``(B, 1, H, W)`` world size of one frame pixel at each receiver, for
            ``settings.pixel_radius``; None: the filter ignores it.

    Returns:
        ``(B, Ls, 1, H, W)`` visibility in [0, 1] (1 where not receiving), already scaled
        by ``settings.intensity``; float32 for float16 / bfloat16 inputs.
    """
    parts = _light_slices(g)
    if len(parts) > 1:  # each slice's padded maps within PAD_MAP_ELEMENTS (the same bits)
        return torch.cat([shadow_visibility(_lights_of(g, sl), position, normal, receive,
                                            camera_view, pixel_size) for sl in parts], 1)
    b, _, h, w = position.shape
    n_l = g.view.shape[1]
    shared = g.view.shape[0] == 1 < b  # maps of batch 1: every item reads them
    dt = compute_dtype(position, normal, g.view)  # half precision: looked up in float32
    position, normal = position.to(dt), normal.to(dt)
    out = position.new_ones(b * h * w, n_l)
    pix = receive.reshape(-1).nonzero().flatten()
    if pix.numel() == 0:
        return out.T.reshape(n_l, b, 1, h, w).permute(1, 0, 2, 3, 4)
    # (3, B*H*W): gathering receivers along dim 1 reads rows (for B = 1 a view; the rows
    # of ``permute(0, 2, 3, 1).reshape(-1, 3)`` are column-strided and index_select of
    # them was ~8 ms per 50k receivers, most of a 256² frame's lookup)
    p_all = position.transpose(0, 1).reshape(3, -1)
    n_all = normal.transpose(0, 1).reshape(3, -1)
    px_all = None
    if pixel_size is not None and g.settings.pixel_radius > 0:
        check_tensor("pixel_size", pixel_size, (b, 1, h, w), floating=True)
        px_all = pixel_size.reshape(-1).to(dt)
    taps = 1 if g.settings.filter in ("hard", "vsm") else g.settings.pcf_taps * (
        2 if g.settings.filter == "pcss" else 1)
    per = max(1, TAP_CHUNK_ELEMENTS // (n_l * taps * 4))
    padded = slot = None  # padded once for every chunk
    if g.settings.filter in ("pcf", "pcss"):
        padded, slot = _pad_rendered_maps(g)
    if not g.depth.is_contiguous() and (padded is None or g.settings.filter == "pcss"
                                        or torch.is_grad_enabled()):
        g = replace(g, depth=g.depth.contiguous())  # a light slice: the maps read as
        # (M, S*S) below, gathered once here, not by every chunk's reshape
    parts = []
    # chunks of at most `per` receivers that do not straddle batch items (pix is sorted)
    ends = torch.searchsorted(pix, torch.arange(1, b + 1, device=pix.device) * (h * w))
    cuts, k = [], 0
    for i, end in enumerate(ends.tolist()):
        cuts += [(j, min(j + per, end), i) for j in range(k, end, per)]
        k = end
    def chunk(idx: torch.Tensor, item0: int) -> torch.Tensor:
        """(P, Ls) visibility of the receivers ``idx`` (of batch item ``item0``)."""
        p, n = p_all.index_select(1, idx).T, n_all.index_select(1, idx).T  # (P, 3)
        item = torch.div(idx, h * w, rounding_mode="floor")
        if shared:  # one set of maps read by every item
            item, item0 = torch.zeros_like(item), 0
        cam_depth = None
        if g.layout == "cascades":
            cv = camera_view.to(p.dtype).index_select(0, item)
            cam_depth = -((cv[:, 2, :3] * p).sum(-1) + cv[:, 2, 3]).detach()
        view_idx, t = _select_view(g, p, item, cam_depth)
        px = None if px_all is None else px_all.index_select(0, idx)
        vis = _visibility_of_view(g, p, n, item, view_idx, padded, px, slot, item0)
        if g.layout == "cascades" and bool((t > 0).any()):
            nxt = torch.where(t > 0, (view_idx + 1).clamp_max(g.view.shape[2] - 1), view_idx)
            if not bool(g.rendered.all()):
                nxt = torch.where(g.rendered.index_select(0, nxt.clamp_min(0).flatten()).view_as(
                    nxt), nxt, view_idx)
            vis = torch.lerp(vis, _visibility_of_view(g, p, n, item, nxt, padded, px, slot,
                                                      item0), t)
        return vis

    # with autograd and more than RECOMPUTE_TAPS receiver-light taps, each chunk is
    # recomputed in backward: the graph keeps its receivers, not the per-tap temporaries
    # of every receiver-light pair (~200 B a tap; memory, docs/benchmarks.md)
    recompute = torch.is_grad_enabled() and pix.numel() * n_l * taps > RECOMPUTE_TAPS and any(
        t is not None and t.requires_grad for t in (p_all, n_all, px_all, g.depth, g.view,
                                                    padded))
    for k, stop, item0 in cuts:
        idx = pix[k:stop]
        parts.append(checkpoint(chunk, idx, item0, use_reentrant=False) if recompute
                     else chunk(idx, item0))
    vis = torch.cat(parts)
    vis = 1 - g.settings.intensity * (1 - vis)
    out = out.index_copy(0, pix, vis.to(out.dtype))
    return out.T.reshape(n_l, b, 1, h, w).permute(1, 0, 2, 3, 4)


def check_face_flags(name: str, flags: torch.Tensor | None, n_faces: int) -> None:
    """Check an ``(F,)`` bool per-face flag tensor (``cast_shadows`` / ``receive_shadows``)."""
    if flags is None:
        return
    check_tensor(name, flags, (n_faces,))
    if flags.dtype != torch.bool:
        raise TypeError(f"{name}: expected an (F,) bool tensor, got {flags.dtype}")


__all__ = ["FILTERS", "ShadowMapCache", "ShadowMaps", "ShadowSettings", "cascade_splits",
           "cull_local_views", "directional_views", "local_views", "merge_shadow_steps",
           "render_shadow_maps", "shadow_visibility", "tap_pattern"]
