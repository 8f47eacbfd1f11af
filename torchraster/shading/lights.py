"""Batched lights: ambient (constant or 9 SH coefficients), directional, point, spot and
area (rectangles and discs).

Many lights are a tensor dimension: every per-light tensor is ``(B, L, ...)`` and the
lighting pass evaluates all lights of a type with one set of tensor ops. Names and units
follow glTF ``KHR_lights_punctual`` (and pyrender):

* ``color``: linear RGB, ``(B, L, 3)``.
* ``intensity``: directional lights in lux (lm/m^2), point and spot lights in candela
  (lm/sr), ``(B, L)``.
* ``range``: distance (m) at which a point / spot light's contribution reaches 0,
  ``(B, L)``; ``inf`` = no range (pure inverse-square falloff).
* ``inner_cone_angle`` / ``outer_cone_angle``: radians from the spot axis, ``(B, L)``,
  ``0 <= inner <= outer <= pi/2``.
* ``direction``: the direction the light *travels* (a glTF light's local -Z axis),
  ``(B, L, 3)``, need not be unit length. ``position``: world space, ``(B, L, 3)``.
* area lights (:class:`AreaLights`, not in glTF): ``position`` the centre, ``u`` / ``v``
  ``(B, L, 3)`` half-extent vectors (a rectangle's corners are ``position +- u +- v``, a
  disc (ellipse) is ``position + s u + t v`` with ``s^2 + t^2 <= 1``), emitting towards
  ``u x v`` (both sides if ``two_sided``); ``intensity`` is the emitted *luminance* in nits
  (cd/m^2): the surface radiance is ``color * intensity`` everywhere on the light.
* ``cast_shadows``: ``(B, L)`` bool: the light casts shadows (shadow maps, see
  :mod:`torchraster.shading.shadows`); ``shadow``: how (one
  :class:`~torchraster.shading.shadows.ShadowSettings` for all L lights, a sequence of L
  settings or None entries, or None: the renderer's default settings).

Ambient light is a distant environment of incident *radiance* given by 9 real SH
coefficients ``(B, 9, 3)`` (order and normalisation of Ramamoorthi & Hanrahan 2001:
``Y00, Y1-1, Y10, Y11, Y2-2, Y2-1, Y20, Y21, Y22``); a constant colour ``c`` is
``sh[:, 0] = c / Y00``. The incidence functions return, per light and pixel, the unit
direction ``l`` to the light and the illuminance ``E`` (lux, RGB) arriving perpendicular
to ``l``; a shading model turns them into radiance.

The YAML schema of lights lives in :mod:`torchraster.config` (``lights_from_config``
builds these containers from it); the defaults below are the one place both use.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from torchraster._validate import check_radiance, check_tensor
from torchraster.numerics import safe_normalize
from torchraster.shading.shadows import ShadowSettings

#: Closest distance (m) a point / spot light is evaluated at: ``E = I / max(d^2, 1e-4)``
#: (Filament ``getDistanceAttenuation``, 1 cm). Keeps E finite at the light's position.
MIN_LIGHT_DISTANCE: float = 0.01

#: Defaults of glTF KHR_lights_punctual: white light of intensity 1, travelling along -Z,
#: spot cone from 0 to pi/4 (radians).
DEFAULT_COLOR: tuple[float, float, float] = (1.0, 1.0, 1.0)
DEFAULT_INTENSITY: float = 1.0
DEFAULT_DIRECTION: tuple[float, float, float] = (0.0, 0.0, -1.0)
DEFAULT_INNER_CONE_ANGLE: float = 0.0
DEFAULT_OUTER_CONE_ANGLE: float = math.pi / 4

#: Floor of ``cos(inner) - cos(outer)`` in the spot falloff (glTF KHR_lights_punctual's
#: reference implementation and Filament use 1e-3); makes inner == outer a hard edge.
MIN_CONE_COS_DELTA: float = 1e-3

# Real SH basis constants, bands 0-2 (Ramamoorthi & Hanrahan 2001, eq. 3).
SH_C0 = 0.5 * math.sqrt(1.0 / math.pi)  # 0.282095
SH_C1 = math.sqrt(3.0 / (4.0 * math.pi))  # 0.488603
SH_C2 = 0.5 * math.sqrt(15.0 / math.pi)  # 1.092548
SH_C20 = 0.25 * math.sqrt(5.0 / math.pi)  # 0.315392
SH_C22 = 0.25 * math.sqrt(15.0 / math.pi)  # 0.546274
#: Clamped-cosine convolution factors A_l per SH band (Ramamoorthi & Hanrahan 2001, eq. 8).
SH_COSINE_LOBE = (math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0)


# --------------------------------------------------------------------------- containers


def _check_common(lights: object, batch: int | None = None) -> tuple[int, int]:
    """Validate the per-light tensors of a light container; return (B, L)."""
    first = None
    for f in _tensor_fields(lights):
        value = getattr(lights, f.name)
        name = f"{type(lights).__name__}.{f.name}"
        if f.name in _FLAG_FIELDS:
            continue
        vec = f.name in ("color", "position", "direction", "u", "v")
        t = check_tensor(name, value, ("B", "L", 3) if vec else ("B", "L"), floating=True,
                         finite=f.name != "range")  # range may be inf (= no range)
        if first is None:
            first = (t.shape[0], t.shape[1])
        elif (t.shape[0], t.shape[1]) != first:
            raise ValueError(f"{name}: expected (B, L) = {first}, got {tuple(t.shape[:2])}")
    assert first is not None
    for flag in _FLAG_FIELDS:
        value = getattr(lights, flag, None)
        if value is not None:
            check_tensor(f"{type(lights).__name__}.{flag}", value, first)
            if value.dtype != torch.bool:
                raise TypeError(f"{type(lights).__name__}.{flag}: expected a bool tensor")
    for name in ("color", "intensity"):
        check_radiance(f"{type(lights).__name__}.{name}", getattr(lights, name))
    _check_shadow_settings(lights, first[1])
    if hasattr(lights, "direction"):
        norm2 = (lights.direction.detach() ** 2).sum(-1)  # type: ignore[attr-defined]
        if bool((norm2 <= 0).any()):
            raise ValueError(f"{type(lights).__name__}.direction: zero vector for light(s) "
                             f"{(norm2 <= 0).nonzero()[:, 1].tolist()}; expected a direction")
    return first


#: The light containers of :class:`Lights`, by field name.
LIGHT_KINDS: tuple[str, ...] = ("directional", "point", "spot", "area")

#: Per-light ``(B, L)`` bool fields of the containers.
_FLAG_FIELDS = ("cast_shadows", "disc", "two_sided")


def _tensor_fields(lights: object) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(lights) if f.name != "shadow"]  # type: ignore[arg-type]


def _check_shadow_settings(lights: object, count: int) -> None:
    shadow = lights.shadow  # type: ignore[attr-defined]
    name = f"{type(lights).__name__}.shadow"
    if shadow is None or isinstance(shadow, ShadowSettings):
        return
    if not isinstance(shadow, (list, tuple)) or len(shadow) != count or not all(
            s is None or isinstance(s, ShadowSettings) for s in shadow):
        raise TypeError(f"{name}: expected a ShadowSettings, None, or a sequence of {count} "
                        f"ShadowSettings / None (one per light), got {shadow!r}")
    lights.shadow = tuple(shadow)  # type: ignore[attr-defined]


class _LightSet:
    """Shared helpers for the light containers (all fields are ``(B, L, ...)`` tensors)."""

    @property
    def count(self) -> int:
        """Number of lights L."""
        return self.color.shape[1]  # type: ignore[attr-defined]

    @property
    def batch_size(self) -> int:
        return self.color.shape[0]  # type: ignore[attr-defined]

    def settings_of(self, i: int) -> ShadowSettings | None:
        """The shadow settings of light ``i`` (None: the renderer's default)."""
        shadow = self.shadow  # type: ignore[attr-defined]
        return shadow if shadow is None or isinstance(shadow, ShadowSettings) else shadow[i]

    def select(self, index: slice | torch.Tensor):
        """The lights ``[:, index]`` (a slice or an int64 index tensor) as a container of
        the same type."""
        if isinstance(index, torch.Tensor):
            ids = index.tolist()
            pick = {f.name: getattr(self, f.name).index_select(1, index.to(self.color.device))
                    for f in _tensor_fields(self)}
        else:
            ids = list(range(self.count))[index]
            pick = {f.name: getattr(self, f.name)[:, index] for f in _tensor_fields(self)}
        shadow = self.shadow  # type: ignore[attr-defined]
        if isinstance(shadow, tuple):
            shadow = tuple(shadow[i] for i in ids)
        return dataclasses.replace(self, shadow=shadow, **pick)  # type: ignore[arg-type]

    def expand(self, batch: int):
        """The same lights for ``batch`` scenes: ``(1, L, ...)`` -> ``(batch, L, ...)``."""
        if self.batch_size == batch:
            return self
        if self.batch_size != 1:
            raise ValueError(f"{type(self).__name__}: cannot expand batch size "
                             f"{self.batch_size} to {batch} (only 1 broadcasts)")
        return dataclasses.replace(
            self,  # type: ignore[arg-type]
            **{f.name: getattr(self, f.name).expand(batch, *getattr(self, f.name).shape[1:])
               for f in _tensor_fields(self)})

    def to(self, device=None, dtype: torch.dtype | None = None):
        """Move to ``device`` and cast floating tensors to ``dtype``."""
        out = {}
        for f in _tensor_fields(self):
            t = getattr(self, f.name)
            out[f.name] = t.to(device=device, dtype=dtype if t.is_floating_point() else None)
        return dataclasses.replace(self, **out)  # type: ignore[arg-type]


@dataclass
class DirectionalLights(_LightSet):
    """Directional (sun-like) lights: ``direction`` / ``color`` ``(B, L, 3)``,
    ``intensity`` ``(B, L)`` in lux, ``cast_shadows`` ``(B, L)`` bool (default False)."""

    direction: torch.Tensor
    color: torch.Tensor
    intensity: torch.Tensor
    cast_shadows: torch.Tensor | None = None
    shadow: ShadowSettings | tuple[ShadowSettings | None, ...] | None = None

    def __post_init__(self) -> None:
        b, n = _check_common(self)
        if self.cast_shadows is None:
            self.cast_shadows = torch.zeros(b, n, dtype=torch.bool, device=self.color.device)


@dataclass
class PointLights(_LightSet):
    """Point lights: ``position`` / ``color`` ``(B, L, 3)``, ``intensity`` ``(B, L)`` in
    candela, ``range`` ``(B, L)`` in m (``inf`` = unlimited; default inf), ``cast_shadows``."""

    position: torch.Tensor
    color: torch.Tensor
    intensity: torch.Tensor
    range: torch.Tensor | None = None
    cast_shadows: torch.Tensor | None = None
    shadow: ShadowSettings | tuple[ShadowSettings | None, ...] | None = None

    def __post_init__(self) -> None:
        if self.range is None:
            self.range = torch.full_like(self.intensity, math.inf)
        b, n = _check_common(self)
        if bool((self.range <= 0).any()) or bool(torch.isnan(self.range).any()):
            raise ValueError("PointLights.range: must be > 0 (inf for no range)")
        if self.cast_shadows is None:
            self.cast_shadows = torch.zeros(b, n, dtype=torch.bool, device=self.color.device)


@dataclass
class SpotLights(_LightSet):
    """Spot lights: point lights restricted to a cone around ``direction`` (``(B, L, 3)``)
    with a smooth falloff between ``inner_cone_angle`` and ``outer_cone_angle`` (radians,
    ``(B, L)``, defaults 0 and pi/4 as glTF)."""

    position: torch.Tensor
    direction: torch.Tensor
    color: torch.Tensor
    intensity: torch.Tensor
    range: torch.Tensor | None = None
    inner_cone_angle: torch.Tensor | None = None
    outer_cone_angle: torch.Tensor | None = None
    cast_shadows: torch.Tensor | None = None
    shadow: ShadowSettings | tuple[ShadowSettings | None, ...] | None = None

    def __post_init__(self) -> None:
        if self.range is None:
            self.range = torch.full_like(self.intensity, math.inf)
        if self.inner_cone_angle is None:
            self.inner_cone_angle = torch.full_like(self.intensity, DEFAULT_INNER_CONE_ANGLE)
        if self.outer_cone_angle is None:
            self.outer_cone_angle = torch.full_like(self.intensity, DEFAULT_OUTER_CONE_ANGLE)
        b, n = _check_common(self)
        if bool((self.range <= 0).any()) or bool(torch.isnan(self.range).any()):
            raise ValueError("SpotLights.range: must be > 0 (inf for no range)")
        inner, outer = self.inner_cone_angle, self.outer_cone_angle
        if not bool(((inner >= 0) & (inner <= outer) & (outer <= math.pi / 2)).all()):
            raise ValueError(
                "SpotLights.inner_cone_angle / outer_cone_angle: expected "
                "0 <= inner <= outer <= pi/2 (radians)"
            )
        if self.cast_shadows is None:
            self.cast_shadows = torch.zeros(b, n, dtype=torch.bool, device=self.color.device)


#: PCSS taps of an area light's shadow unless its settings say otherwise: wide penumbrae
#: need many (4 taps show 4 shifted copies of the shadow's edge; docs/benchmarks.md, area).
AREA_SHADOW_TAPS: int = 16


@dataclass
class AreaLights(_LightSet):
    """Area lights: rectangles (parallelograms) and discs (ellipses) of constant luminance.

    ``position`` ``(B, L, 3)`` the centre; ``u``, ``v`` ``(B, L, 3)`` half-extent vectors
    (rectangle: corners ``position +- u +- v``, area ``4 |u x v|``; disc: ``position + s u
    + t v``, ``s^2 + t^2 <= 1``, area ``pi |u x v|``), emitting towards ``u x v``;
    ``color`` ``(B, L, 3)``; ``intensity`` ``(B, L)`` the emitted luminance in nits
    (cd/m^2), so a light of area A seen face on is as bright as a point light of
    ``intensity * A`` candela; ``disc`` ``(B, L)`` bool (default False: rectangles);
    ``two_sided`` ``(B, L)`` bool (default False: only the ``u x v`` side emits);
    ``cast_shadows`` / ``shadow`` as for point lights (the shadow of an area light is
    filtered with PCSS of :data:`AREA_SHADOW_TAPS` taps by default, its light size the
    light's own, see :func:`area_equivalent_radius`). :func:`area_light_axes` makes ``u``
    and ``v`` from a facing direction and a size.
    """

    position: torch.Tensor
    u: torch.Tensor
    v: torch.Tensor
    color: torch.Tensor
    intensity: torch.Tensor
    disc: torch.Tensor | None = None
    two_sided: torch.Tensor | None = None
    cast_shadows: torch.Tensor | None = None
    shadow: ShadowSettings | tuple[ShadowSettings | None, ...] | None = None

    def __post_init__(self) -> None:
        for flag in ("disc", "two_sided", "cast_shadows"):
            if getattr(self, flag) is None:
                setattr(self, flag, torch.zeros(self.intensity.shape, dtype=torch.bool,
                                                device=self.color.device))
        _check_common(self)
        cross2 = (torch.linalg.cross(self.u.detach(), self.v.detach()) ** 2).sum(-1)
        scale2 = ((self.u.detach() ** 2).sum(-1) * (self.v.detach() ** 2).sum(-1))
        flat = ~(cross2 > 1e-12 * scale2) | (scale2 <= 0)
        if bool(flat.any()):
            raise ValueError(f"AreaLights.u / v: parallel or zero half-extents for light(s) "
                             f"{sorted(set(flat.nonzero()[:, 1].tolist()))}; expected two "
                             "independent vectors spanning the light")


def area_light_axes(direction: torch.Tensor, width: torch.Tensor, height: torch.Tensor,
                    up: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Half-extent vectors ``u``, ``v`` of :class:`AreaLights` facing ``direction``.

    Args:
        direction: ``(..., 3)`` the direction the light emits into (its normal; need not
            be unit).
        width, height: ``(...)`` full side lengths (m); a disc of radius r is
            ``width = height = 2 r``.
        up: ``(..., 3)`` the in-plane direction of the ``height`` side (projected onto the
            light's plane); default world +Y, or +Z for a light facing along Y.

    Returns:
        ``u`` (along the width) and ``v`` (along the height), each ``(..., 3)``, with
        ``u x v`` along ``direction``.

    Example:
        >>> u, v = area_light_axes(torch.tensor([0.0, -1, 0]), torch.tensor(2.0),
        ...                        torch.tensor(1.0))
        >>> (u + 0.0).tolist(), v.tolist()  # a 2 x 1 m panel facing down
        ([1.0, 0.0, 0.0], [0.0, 0.0, 0.5])
    """
    n = safe_normalize(direction, dim=-1)
    if up is None:
        y = torch.tensor([0.0, 1.0, 0.0], dtype=n.dtype, device=n.device)
        z = torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype, device=n.device)
        up = torch.where((n[..., 1:2].abs() > 0.999), z, y).expand_as(n)
    up = up.to(n.dtype)
    b = safe_normalize(up - (up * n).sum(-1, keepdim=True) * n, dim=-1)
    if bool(((b * b).sum(-1) < 0.5).any()):
        raise ValueError("area_light_axes: up is parallel to direction")
    a = torch.linalg.cross(b, n)  # a x b = n
    return a * (0.5 * width)[..., None], b * (0.5 * height)[..., None]


def area_equivalent_radius(lights: AreaLights) -> torch.Tensor:
    """``(B, L)`` radius of the disc with each light's area (m): the light size of its
    PCSS shadows."""
    area = torch.linalg.cross(lights.u, lights.v).norm(dim=-1)
    return torch.sqrt(area * torch.where(lights.disc, 1.0, 4.0 / math.pi))


@dataclass
class Lights:
    """All lights of a batch of scenes. Any part may be None (or hold L = 0 lights).

    Attributes:
        ambient: ``(B, 9, 3)`` SH coefficients of the ambient incident radiance, or None.
        directional, point, spot, area: light containers, or None.
    """

    ambient: torch.Tensor | None = None
    directional: DirectionalLights | None = None
    point: PointLights | None = None
    spot: SpotLights | None = None
    area: AreaLights | None = None

    def __post_init__(self) -> None:
        sizes = {}
        if self.ambient is not None:
            check_tensor("Lights.ambient", self.ambient, ("B", 9, 3), floating=True,
                         finite=True)
            sizes["ambient"] = self.ambient.shape[0]
        for name, kind in (
            ("directional", DirectionalLights),
            ("point", PointLights),
            ("spot", SpotLights),
            ("area", AreaLights),
        ):
            part = getattr(self, name)
            if part is not None:
                if not isinstance(part, kind):
                    raise TypeError(
                        f"Lights.{name}: expected {kind.__name__}, got {type(part).__name__}"
                    )
                sizes[name] = part.batch_size
        if len(set(sizes.values())) > 1:
            raise ValueError(f"Lights: batch sizes differ: {sizes}")

    @property
    def batch_size(self) -> int | None:
        """B, or None when there are no lights at all."""
        if self.ambient is not None:
            return self.ambient.shape[0]
        for part in (self.directional, self.point, self.spot, self.area):
            if part is not None:
                return part.batch_size
        return None

    def expand(self, batch: int) -> Lights:
        """The same lights for ``batch`` scenes (every part of batch size 1 or ``batch``)."""
        return Lights(
            ambient=None if self.ambient is None else self.ambient.expand(batch, 9, 3),
            directional=None if self.directional is None else self.directional.expand(batch),
            point=None if self.point is None else self.point.expand(batch),
            spot=None if self.spot is None else self.spot.expand(batch),
            area=None if self.area is None else self.area.expand(batch),
        )

    def to(self, device=None, dtype: torch.dtype | None = None) -> Lights:
        """Move all tensors to ``device`` / cast floating ones to ``dtype``."""
        return Lights(
            ambient=None if self.ambient is None else self.ambient.to(device=device, dtype=dtype),
            directional=None if self.directional is None else self.directional.to(device, dtype),
            point=None if self.point is None else self.point.to(device, dtype),
            spot=None if self.spot is None else self.spot.to(device, dtype),
            area=None if self.area is None else self.area.to(device, dtype),
        )


# --------------------------------------------------------------------------- ambient (SH)


def sh_basis(d: torch.Tensor) -> torch.Tensor:
    """Real SH basis Y_k(d), bands 0-2, for unit directions with xyz on dim -3.

    ``(..., 3, H, W) -> (..., 9, H, W)`` in the order Y00, Y1-1, Y10, Y11, Y2-2, Y2-1,
    Y20, Y21, Y22 (Ramamoorthi & Hanrahan 2001). Also the basis of image-based lighting
    (``ibl.sh_project``), so its output can be used as ``Lights.ambient``.
    """
    x, y, z = d.unbind(dim=-3)
    r2 = x * x + y * y + z * z  # 1 for unit d; makes Y20 vanish for d = 0
    ys = [
        torch.full_like(x, SH_C0),
        SH_C1 * y,
        SH_C1 * z,
        SH_C1 * x,
        SH_C2 * x * y,
        SH_C2 * y * z,
        SH_C20 * (3.0 * z * z - r2),
        SH_C2 * x * z,
        SH_C22 * (x * x - y * y),
    ]
    return torch.stack(ys, dim=-3)


def sh_from_color(color: torch.Tensor) -> torch.Tensor:
    """SH coefficients ``(B, 9, 3)`` of a constant incident radiance ``color`` ``(B, 3)``."""
    check_tensor("color", color, ("B", 3), floating=True)
    sh = color.new_zeros(color.shape[0], 9, 3)
    return sh.index_copy(1, torch.zeros(1, dtype=torch.long, device=color.device),
                         (color / SH_C0)[:, None])


def sh_irradiance(sh: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Irradiance E(n) (lux, RGB) from SH radiance coefficients (Ramamoorthi & Hanrahan 2001).

    ``E(n) = sum_k A_band(k) L_k Y_k(n)`` with ``A = (pi, 2pi/3, pi/4)``; a Lambertian
    surface then reflects ``albedo / pi * E``. A constant radiance c gives ``E = pi c``.

    Args:
        sh: ``(B, 9, 3)`` radiance coefficients.
        n: ``(B, 3, H, W)`` unit normals (or any direction, e.g. the reflection vector).

    Returns:
        ``(B, 3, H, W)`` irradiance, not clamped (order-2 SH may ring slightly below 0).
    """
    check_tensor("sh", sh, ("B", 9, 3), floating=True)
    check_tensor("n", n, ("B", 3, None, None), floating=True)
    lobe = sh.new_tensor([SH_COSINE_LOBE[0]] + [SH_COSINE_LOBE[1]] * 3 + [SH_COSINE_LOBE[2]] * 5)
    coeff = sh * lobe[:, None]  # (B, 9, 3)
    return torch.einsum("bkhw,bkc->bchw", sh_basis(n), coeff)


# --------------------------------------------------------------------------- punctual


def distance_attenuation(dist2: torch.Tensor, range_: torch.Tensor) -> torch.Tensor:
    """Inverse-square falloff with a smooth range window (Karis 2013, Filament).

    ``window = saturate(1 - (d / range)^4)^2``; returns ``window / max(d^2, 0.01^2)``
    (``MIN_LIGHT_DISTANCE``). ``range = inf`` gives the pure inverse-square law.
    Shapes broadcast; ``dist2`` in m^2, result in 1/m^2.
    """
    finite = torch.isfinite(range_)  # "double where": 0 (not NaN) gradient for range = inf
    safe = torch.where(finite, range_, 1.0)
    inv_r2 = torch.where(finite, 1.0 / (safe * safe), 0.0)
    factor = dist2 * inv_r2
    window = (1.0 - factor * factor).clamp(0.0, 1.0) ** 2
    return window / dist2.clamp_min(MIN_LIGHT_DISTANCE**2)


def spot_attenuation(
    cos_angle: torch.Tensor, inner_cone_angle: torch.Tensor, outer_cone_angle: torch.Tensor
) -> torch.Tensor:
    """Smooth spot cone falloff (glTF KHR_lights_punctual reference, Filament).

    ``t = saturate((cos_angle - cos(outer)) / max(cos(inner) - cos(outer), 1e-3))``,
    returns ``t^2``: 1 inside the inner cone, 0 outside the outer cone. Shapes broadcast.
    """
    cos_outer = torch.cos(outer_cone_angle)
    scale = 1.0 / (torch.cos(inner_cone_angle) - cos_outer).clamp_min(MIN_CONE_COS_DELTA)
    t = ((cos_angle - cos_outer) * scale).clamp(0.0, 1.0)
    return t * t


def _per_light(x: torch.Tensor) -> torch.Tensor:
    """(B, L, C) -> (B, L, C, 1, 1), to broadcast against (B, L, C, H, W)."""
    return x[..., None, None]


def directional_incidence(lights: DirectionalLights) -> tuple[torch.Tensor, torch.Tensor]:
    """Direction to the light and illuminance for directional lights.

    Returns:
        ``l``: ``(B, L, 3, 1, 1)`` unit vectors towards the light (``-direction``).
        ``E``: ``(B, L, 3, 1, 1)`` illuminance (lux, RGB) = color * intensity.
    """
    l = -safe_normalize(lights.direction, dim=-1)
    e = lights.color * lights.intensity[..., None]
    return _per_light(l), _per_light(e)


def _punctual(
    light_pos: torch.Tensor, color_intensity: torch.Tensor, range_: torch.Tensor,
    position: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    check_tensor("position", position, (light_pos.shape[0], 3, None, None), floating=True)
    to_light = _per_light(light_pos) - position[:, None]  # (B, L, 3, H, W)
    dist2 = (to_light * to_light).sum(dim=-3, keepdim=True)
    l = safe_normalize(to_light, dim=-3)
    att = distance_attenuation(dist2, _per_light(range_[..., None]))
    return l, _per_light(color_intensity) * att


def point_incidence(
    lights: PointLights, position: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Direction to the light and illuminance of point lights at surface points.

    Args:
        lights: L point lights of a batch of B scenes.
        position: ``(B, 3, H, W)`` world-space surface positions (m).

    Returns:
        ``l``: ``(B, L, 3, H, W)`` unit vectors towards each light (0 at the light itself).
        ``E``: ``(B, L, 3, H, W)`` illuminance (lux, RGB) ``= color I window / d^2``.
    """
    ci = lights.color * lights.intensity[..., None]
    return _punctual(lights.position, ci, lights.range, position)


def spot_incidence(
    lights: SpotLights, position: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Like :func:`point_incidence`, times the cone falloff :func:`spot_attenuation`.

    The cone angle is measured between the spot ``direction`` and the ray from the light
    to the surface point. Shapes as in :func:`point_incidence`.
    """
    ci = lights.color * lights.intensity[..., None]
    l, e = _punctual(lights.position, ci, lights.range, position)
    axis = _per_light(safe_normalize(lights.direction, dim=-1))  # (B, L, 3, 1, 1)
    cos_angle = -(axis * l).sum(dim=-3, keepdim=True)
    cone = spot_attenuation(
        cos_angle,
        _per_light(lights.inner_cone_angle[..., None]),
        _per_light(lights.outer_cone_angle[..., None]),
    )
    return l, e * cone
