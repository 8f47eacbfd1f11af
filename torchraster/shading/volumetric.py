"""Volumetric light and fog: exponential height fog lit by the scene's lights, with light
shafts marched through the shadow maps.

The medium is an exponential height fog (Wenzel 2006, "Real-time atmospheric effects in
games"; Unreal's "exponential height fog")::

    sigma_t(p) = density * exp(-height_falloff * (p_y - base_height))      (1/m)

with a grey extinction and the scattering coefficient ``sigma_s = color * sigma_t`` (``color``
is the single-scattering albedo). Along a view ray ``o + t v`` the optical depth has a closed
form: the density is ``rho(t) = rho_o exp(-k t)`` with ``k = height_falloff * v_y``, so::

    tau(s) = integral_0^s rho(t) dt = s * rho_max * (1 - exp(-|k| s)) / (|k| s)

(``rho_max`` the denser end of the segment: the logarithmic mean of the end densities times
the length). ``(1 - exp(-u)) / u`` is evaluated with ``expm1`` and a series near 0, so
horizontal rays and homogeneous fog (``k -> 0``) are the exact limit ``s * rho``; an
infinite ray (the sky, ``max_distance = inf``) climbing through the fog has the finite
``tau = rho_o / k``, any other infinite ray is opaque. Transmittance ``T = exp(-tau)``.

A pixel becomes ``T(s) * L_surface + L_in`` (``s`` the distance to the surface, or
``max_distance`` for the background). Single scattering (the light reaching a fog particle is
not itself attenuated by the fog)::

    L_in = integral_0^s T(t) sigma_s(t) S(t) dt,     S(t) = sum_lights p(l . v) E(t) V(t)

with the Henyey-Greenstein phase function ``p`` (:func:`hg_phase`, per steradian; ``l`` the
unit direction to the light, ``v`` the view ray, so ``g > 0`` brightens looking towards a
light), the light's illuminance ``E`` (with the range window and spot cone of
:mod:`~torchraster.shading.lights`) and its shadow-map visibility ``V``.

* **Analytic part.** A source that is constant along the ray integrates exactly, because
  ``integral T sigma_t dt = 1 - T(s)``: ``L_in = color * S * (1 - T(s))``. This holds for the
  ambient light (incident radiance as 9 SH coefficients: by the Funk-Hecke theorem the HG
  lobe scales SH band ``l`` by ``g^l``, :func:`ambient_inscatter`), ``Fog.ambient`` and every
  directional light that casts no shadow.
* **Marched part** (light shafts). Point and spot lights, and directional lights with shadow
  maps, vary along the ray: the ray up to the farthest point of the scene's box (the
  casters and the lights) from the eye is cut into ``steps`` equal segments (beyond it
  point and spot lights are not marched and directional lights in-scatter unshadowed,
  analytically); segment ``i`` contributes
  ``color * S(t_i) * (T(a_i) - T(b_i))`` with the exact transmittance at its ends (so a
  constant source is integrated exactly at any step count, Hillaire 2015, "Physically based
  and unified volumetric rendering in Frostbite") and ``S`` sampled at a per-pixel jittered
  point ``t_i = a_i + j (b_i - a_i)`` (``j`` interleaved gradient noise, Jimenez 2014; 0.5
  without jitter). The shadow lookup of a fog sample is a single comparison (filter
  ``"hard"``, or the VSM moments) without bias (a fog sample has no surface to shadow
  itself, and a bias would leak light into the fog just under an occluder). A separable
  joint bilateral blur guided by the log distance then removes the jitter noise without
  bleeding across depth edges. Area lights are marched too: ``E`` is their radiance times
  the solid angle their polygon subtends from the sample's side (exact,
  :func:`~torchraster.shading.area.area_incidence`), the phase evaluated towards their mean
  direction with the anisotropy scaled by their spread's mean cosine (exact for isotropic
  fog, ``g = 0``), their shadow the cube map from the centre, their light path the segment
  to the centre.

* **Light path** (``Fog.light_transmittance``, default on). The light is dimmed on its way
  in too: each punctual light's illuminance is multiplied by the fog's transmittance from
  the lit point to the light, ``T_l = exp(-tau)`` with the same closed-form optical depth
  (:func:`light_transmittance`): along the segment to a point / spot light, and along the
  infinite ray towards ``-direction`` for a directional light, which is finite only when it
  climbs out of a height fog (``tau = rho_p / (b l_y)``) and opaque otherwise: a sun at or
  below the horizon, and any sun in homogeneous fog (``height_falloff = 0`` fills all
  space), is fully absorbed. It multiplies the surface lighting (the renderer passes it to
  ``shade`` with the shadow factor, :func:`surface_light_hook`) and every fog sample of the
  march. The unshadowed directional in-scattering stays analytic: with
  ``rho(t) = rho_o e^(-k t)`` (``k = b v_y``), ``T_l(t) = exp(-rho(t) / c)`` (``c = b l_y``)
  and the substitution ``u = rho(t)``::

      integral_0^s sigma_t T_v T_l dt = T_l(0) tau_v (1 - e^(-x)) / x,   x = (1 - v_y / l_y) tau_v

  (:func:`directional_inscatter_weight`; ``T_l(0) / (1 - v_y / l_y)`` for an infinite view
  ray that does not climb; without the light path it is ``1 - T_v(s)``).

An environment map lights the fog like the ambient light (``fog_terms(environment=...)``:
its 9 SH coefficients, looked up along the env-space view rays). Not modelled: the
in-scattering of emissive surfaces (give it as ``Fog.ambient``), the dimming of ambient and
environment light on its way in, multiple scattering. Defaults are measured in
docs/benchmarks.md ("Fog", "Fog light path").

Gradients: everything is differentiable with respect to the fog parameters (they may be
tensors), the lights and the image; the shadow lookup of a fog sample is a hard comparison
(VSM: smooth) and the box bounding the march is not differentiated.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch

from torchraster._validate import check_tensor
from torchraster.numerics import LOW_PRECISION, finish_low_precision, safe_normalize
from torchraster.shading.area import area_incidence
from torchraster.shading.ibl import Environment
from torchraster.shading.lights import (
    DirectionalLights,
    Lights,
    PointLights,
    SpotLights,
    point_incidence,
    sh_basis,
    spot_incidence,
)
from torchraster.shading.shadows import ShadowMaps, shadow_visibility

#: Largest exponent of the height term ``-height_falloff * (y - base_height)``, largest
#: ``density`` and longest finite ray (m): with them every optical depth is below 1e37
#: (finite in float32, and so are its gradients); beyond them the fog is opaque anyway.
MAX_HEIGHT_EXPONENT: float = 40.0
MAX_DENSITY: float = 1e4
MAX_RAY_LENGTH: float = 1e12
#: Smallest ``height_falloff * v_y`` of an infinite ray that climbs out of the fog
#: (``tau = rho / k``); flatter infinite rays are opaque.
MIN_CLIMB: float = 1e-12
#: ``(1 - exp(-u)) / u`` uses its Taylor series below this ``u`` (relative error < 1e-12).
SERIES_BELOW: float = 1e-4
#: Largest ``|anisotropy|`` (HG peaks as ``1 / (1 - |g|)^2``).
MAX_ANISOTROPY: float = 0.99
#: Longest marched distance (m): fog samples farther than this are not marched (keeps
#: light distances squared finite in float32).
MAX_MARCH_DISTANCE: float = 1e6
#: Relative log-distance difference of one standard deviation of the blur's range kernel.
BLUR_DEPTH_SIGMA: float = 0.05


@dataclass(frozen=True)
class Fog:
    """Exponential height fog and its light shafts (see the module docstring).

    Args:
        density: extinction coefficient (1/m) at ``base_height``, in [0, 1e4]; a float or a
            tensor (differentiable).
        height_falloff: ``b`` (1/m) of ``exp(-b (y - base_height))``; 0 = homogeneous fog.
        base_height: height (m, world y) where the extinction equals ``density``.
        color: single-scattering albedo, RGB in [0, 1] (the fog's tint; 1 = white fog).
        ambient: constant isotropic radiance (RGB, nits) in-scattered besides the lights
            (e.g. skylight when the scene has no ambient light).
        anisotropy: Henyey-Greenstein ``g`` in [-0.99, 0.99]: > 0 scatters forward (bright
            halo looking towards a light), 0 isotropic.
        steps: march steps per pixel for point / spot lights and shadowed directional lights.
        jitter: per-pixel jittered samples (interleaved gradient noise); False: segment
            midpoints (banding instead of noise).
        blur: standard deviation (pixels) of the depth-aware blur of the marched light;
            0 = none.
        max_distance: distance (m) of the background (sky) behind empty pixels; ``inf`` =
            infinitely far (opaque, unless the ray climbs out of a height fog).
        seed: offset of the jitter pattern (e.g. a frame index, for temporal accumulation).
        light_transmittance: dim each punctual light by the fog between it and the lit
            point (surfaces and fog samples); a directional light is fully absorbed in
            homogeneous fog and when it is at or below the horizon (module docstring).
            False: the light reaches every point undimmed (the fog only attenuates along
            the view ray).
    """

    density: float | torch.Tensor = 0.1
    height_falloff: float | torch.Tensor = 0.0
    base_height: float | torch.Tensor = 0.0
    color: Sequence[float] | torch.Tensor = (1.0, 1.0, 1.0)
    ambient: Sequence[float] | torch.Tensor = (0.0, 0.0, 0.0)
    anisotropy: float | torch.Tensor = 0.0
    steps: int = 16
    jitter: bool = True
    blur: float = 1.0
    max_distance: float = math.inf
    seed: int = 0
    light_transmittance: bool = True

    def __post_init__(self) -> None:
        def bad(name: str, expected: str) -> None:
            raise ValueError(f"Fog.{name}: expected {expected}, got {getattr(self, name)!r}")

        for name, lo, hi, n in (("density", 0, MAX_DENSITY, 1), ("height_falloff", 0, math.inf, 1),
                                ("base_height", -math.inf, math.inf, 1),
                                ("color", 0, 1, 3), ("ambient", 0, math.inf, 3),
                                ("anisotropy", -MAX_ANISOTROPY, MAX_ANISOTROPY, 1)):
            value = getattr(self, name)
            if isinstance(value, bool):
                bad(name, f"{'a number' if n == 1 else f'{n} numbers'} in [{lo}, {hi}]")
            try:
                t = value.detach() if isinstance(value, torch.Tensor) else torch.as_tensor(
                    value, dtype=torch.float64)
                t = t.cpu().flatten().double()
            except (TypeError, ValueError, RuntimeError):
                t = None
            if t is None or t.numel() != n or not bool(torch.isfinite(t).all()) or not bool(
                    ((t >= lo) & (t <= hi)).all()):
                bad(name, f"{'a finite number' if n == 1 else f'{n} finite numbers'} in "
                          f"[{lo}, {hi}]")
        if isinstance(self.steps, bool) or not isinstance(self.steps, int) or not (
                1 <= self.steps <= 1024):
            bad("steps", "an int in [1, 1024]")
        for name in ("jitter", "light_transmittance"):
            if not isinstance(getattr(self, name), bool):
                bad(name, "a bool")
        if isinstance(self.blur, bool) or not isinstance(self.blur, (int, float)) or not (
                0 <= self.blur <= 16):
            bad("blur", "a number in [0, 16] (pixels)")
        if isinstance(self.max_distance, bool) or not isinstance(
                self.max_distance, (int, float)) or not self.max_distance > 0 or math.isnan(
                self.max_distance):
            bad("max_distance", "a positive number (m) or inf")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            bad("seed", "an int >= 0")

    def param(self, name: str, like: torch.Tensor) -> torch.Tensor:
        """Parameter ``name`` as a tensor of ``like``'s dtype and device, shaped to broadcast
        against ``(B, C, H, W)``: ``(1, 1, 1, 1)`` scalars, ``(1, 3, 1, 1)`` colours."""
        v = torch.as_tensor(getattr(self, name), dtype=like.dtype, device=like.device)
        return v.reshape(1, -1, 1, 1)


class FogTerms(NamedTuple):
    """The parts of :func:`fog_terms`, each ``(B, C, H, W)``.

    Attributes:
        transmittance: ``(B, 1, H, W)`` ``T(s)`` from the eye to the surface / background.
        analytic: ``(B, 3, H, W)`` in-scattered radiance of the constant sources (ambient,
            unshadowed directional lights, marched lights outside the march range).
        marched: ``(B, 3, H, W)`` in-scattered radiance of the marched lights (not blurred).
    """

    transmittance: torch.Tensor
    analytic: torch.Tensor
    marched: torch.Tensor


# ---------------------------------------------------------------------------- medium


def hg_phase(cos_theta: torch.Tensor, g: float | torch.Tensor) -> torch.Tensor:
    """Henyey-Greenstein phase function (Henyey & Greenstein 1941; PBRT 3, section 11.3.1).

    ``p = (1 - g^2) / (4 pi (1 + g^2 - 2 g cos_theta)^(3/2))``, normalised over the sphere;
    ``g = 0`` is isotropic ``1 / (4 pi)``.

    Args:
        cos_theta: cosine between the light's travel direction and the scattered direction
            (here ``l . v``: direction to the light dot the view ray), any shape.
        g: anisotropy in (-1, 1), broadcastable.

    Returns:
        The phase (1/sr), the broadcast shape.
    """
    g = torch.as_tensor(g, dtype=cos_theta.dtype, device=cos_theta.device)
    denom = (1 + g * g - 2 * g * cos_theta.clamp(-1, 1)).clamp_min(1e-12)
    return (1 - g * g) / (4 * math.pi * denom * torch.sqrt(denom))


def _one_minus_exp_over(u: torch.Tensor) -> torch.Tensor:
    """``(1 - exp(-u)) / u`` for ``u >= 0``, 1 at 0 (series below :data:`SERIES_BELOW`; finite
    values and gradients everywhere)."""
    small = u < SERIES_BELOW
    u_safe = torch.where(small, torch.ones_like(u), u)
    return torch.where(small, 1 - u / 2 + u * u / 6, -torch.expm1(-u_safe) / u_safe)


def fog_density(y: torch.Tensor, fog: Fog) -> torch.Tensor:
    """Extinction coefficient ``sigma_t`` of the fog at heights ``y``.

    Args:
        y: ``(B, 1, H, W)`` (or any broadcastable shape) world heights (m).
        fog: the medium.

    Returns:
        ``sigma_t`` (1/m), ``y``'s shape: ``density * exp(-height_falloff (y - base_height))``
        (the exponent capped at :data:`MAX_HEIGHT_EXPONENT`).
    """
    a, b, y0 = (fog.param(n, y) for n in ("density", "height_falloff", "base_height"))
    return a * torch.exp((-b * (y - y0)).clamp_max(MAX_HEIGHT_EXPONENT))


def optical_depth(origin_y: torch.Tensor, dir_y: torch.Tensor, length: torch.Tensor,
                  fog: Fog) -> torch.Tensor:
    """Closed-form optical depth of the fog along rays (module docstring, ``tau(s)``).

    Args:
        origin_y: ``(B, 1, H, W)`` height of the ray origins (m); broadcastable.
        dir_y: ``(B, 1, H, W)`` y component of the unit ray directions.
        length: ``(B, 1, H, W)`` ray lengths (m) >= 0, may be ``inf``.
        fog: the medium.

    Returns:
        ``(B, 1, H, W)`` optical depth >= 0 (``inf`` for an infinite ray that does not climb
        out of the fog); finite gradients.
    """
    b = fog.param("height_falloff", dir_y)
    finite = torch.isfinite(length)
    s = torch.where(finite, length, torch.zeros_like(length)).clamp(0, MAX_RAY_LENGTH)
    y_end = origin_y + dir_y * s
    rho_max = fog_density(torch.minimum(origin_y, y_end), fog)
    k = b * dir_y
    tau_finite = rho_max * s * _one_minus_exp_over(k.abs() * s)
    climbs = k > MIN_CLIMB
    rho_o = fog_density(origin_y, fog)
    tau_up = rho_o / torch.where(climbs, k, torch.ones_like(k))
    tau_inf = torch.where(climbs, tau_up, torch.where(rho_o > 0, math.inf, 0.0).to(k.dtype))
    return torch.where(finite, tau_finite, tau_inf)


def fog_transmittance(origin_y: torch.Tensor, dir_y: torch.Tensor, length: torch.Tensor,
                      fog: Fog) -> torch.Tensor:
    """Transmittance ``exp(-tau)`` of the fog along rays.

    Args:
        origin_y, dir_y, length: as in :func:`optical_depth`, ``(B, 1, H, W)``.
        fog: the medium.

    Returns:
        ``(B, 1, H, W)`` in [0, 1].
    """
    return torch.exp(-optical_depth(origin_y, dir_y, length, fog))


def light_optical_depth(points: torch.Tensor, kind: str,
                        lights: DirectionalLights | PointLights | SpotLights, fog: Fog
                        ) -> torch.Tensor:
    """Optical depth of the fog between points and each light (:func:`optical_depth`).

    Directional: the infinite ray from the point towards ``-direction`` (finite only when it
    climbs out of a height fog, ``tau = rho_p / (b l_y)``; a light at or below the horizon,
    or in homogeneous fog, gives ``inf``). Point / spot: the segment from the point to the
    light's position (0 at the light itself); area: to the light's centre.

    Args:
        points: ``(B, 3, H, W)`` world positions (m).
        kind: ``"directional"``, ``"point"``, ``"spot"`` or ``"area"``.
        lights: that kind's L lights, batch size B (or 1).
        fog: the medium.

    Returns:
        ``(B, L, 1, H, W)`` optical depth >= 0 (may be ``inf``); finite gradients.
    """
    check_tensor("points", points, ("B", 3, None, None), floating=True)
    if kind not in ("directional", "point", "spot", "area"):
        raise ValueError(f"kind: expected 'directional', 'point', 'spot' or 'area', got "
                         f"{kind!r}")
    py = points[:, None, 1:2]  # (B, 1, 1, H, W)
    if kind == "directional":
        l_y = -safe_normalize(lights.direction.to(points), dim=-1)[..., 1]  # (B, L)
        inf = torch.full((1, 1, 1, 1, 1), math.inf, dtype=points.dtype, device=points.device)
        return optical_depth(py, l_y[..., None, None, None], inf, fog)
    d = lights.position.to(points)[..., None, None] - points[:, None]  # (B, L, 3, H, W)
    d2 = (d * d).sum(2, keepdim=True)
    ok = d2 > 1e-24
    dist = torch.sqrt(torch.where(ok, d2, torch.ones_like(d2)))  # finite gradients at 0
    dir_y = torch.where(ok, d[:, :, 1:2] / dist, torch.zeros_like(dist))
    return optical_depth(py, dir_y, dist * ok, fog)


def light_transmittance(points: torch.Tensor, kind: str,
                        lights: DirectionalLights | PointLights | SpotLights, fog: Fog
                        ) -> torch.Tensor:
    """Transmittance of the fog between points and each light: ``exp(-tau)`` of
    :func:`light_optical_depth`; 1 where ``fog.light_transmittance`` is False.

    Returns:
        ``(B, L, 1, H, W)`` in [0, 1].
    """
    if not fog.light_transmittance:
        b, _, h, w = points.shape
        return points.new_ones(b, lights.count, 1, h, w)
    return torch.exp(-light_optical_depth(points, kind, lights, fog))


def directional_inscatter_weight(origin_y: torch.Tensor, dir_y: torch.Tensor,
                                 length: torch.Tensor, light_y: torch.Tensor, fog: Fog
                                 ) -> torch.Tensor:
    """``integral_0^s sigma_t(t) T_v(t) T_l(t) dt``: the in-scattering of a directional light
    along a view ray per unit ``color * phase * E`` (module docstring, "Light path").

    ``T_v`` is the transmittance from the eye, ``T_l`` the one towards the light
    (:func:`light_transmittance`). Closed form ``T_l(0) tau_v (1 - e^-x) / x`` with
    ``x = (1 - v_y / l_y) tau_v``, written as ``exp(log T_l(0) + max(-x, 0)) tau_v
    (1 - e^-|x|) / |x|`` so that no factor overflows when ``x < 0`` (the view ray climbs
    faster than the light ray); ``T_l(0) / (1 - v_y / l_y)`` for an infinite view ray that
    does not climb; 0 when the light ray does not climb (opaque). Without the light path
    (``fog.light_transmittance`` False): ``1 - T_v(s)``.

    Args:
        origin_y: ``(B, 1, 1, H, W)`` eye heights; dir_y: ``(B, 1, 1, H, W)`` view ray y.
        length: ``(B, 1, 1, H, W)`` ray lengths (m), may be ``inf``.
        light_y: ``(B, L, 1, 1, 1)`` y of the unit directions towards the lights.
        fog: the medium.

    Returns:
        ``(B, L, 1, H, W)`` in [0, 1]; finite gradients.
    """
    tau_v = optical_depth(origin_y, dir_y, length, fog)
    if not fog.light_transmittance:
        return (-torch.expm1(-tau_v)).expand(*light_y.shape[:2], *tau_v.shape[2:])
    c = fog.param("height_falloff", light_y) * light_y
    climbs = c > MIN_CLIMB
    l_y = torch.where(climbs, light_y, torch.ones_like(light_y))
    log_tl0 = -fog_density(origin_y, fog) / torch.where(climbs, c, torch.ones_like(c))
    one_minus_r = 1 - dir_y / l_y
    inf_v = torch.isinf(tau_v)  # never climbs out: then 1 - r > 0 (v_y <= 0 < l_y)
    tau = torch.where(inf_v, torch.zeros_like(tau_v), tau_v)
    x = one_minus_r * tau
    finite = torch.exp((log_tl0 + (-x).clamp_min(0)).clamp_max(0)) * tau * _one_minus_exp_over(
        x.abs())
    infinite = torch.exp(log_tl0) / torch.where(inf_v, one_minus_r, torch.ones_like(x)
                                                ).clamp_min(1e-30)
    return torch.where(climbs, torch.where(inf_v, infinite, finite), torch.zeros_like(x))


def surface_light_hook(fog: Fog, lights: Lights, position: torch.Tensor,
                       mask: torch.Tensor | None = None,
                       visibility: Callable[[str, slice], torch.Tensor | None] | None = None
                       ) -> Callable[[str, slice], torch.Tensor | None]:
    """A ``shade`` visibility hook that multiplies each punctual light's illuminance at the
    surface by the fog's transmittance to the light (:func:`light_transmittance`), times the
    shadow factor of ``visibility``.

    Args:
        fog: the medium (with ``light_transmittance`` False the hook is ``visibility``).
        lights: the scene's lights, batch size B or 1.
        position: ``(B, 3, H, W)`` world positions of the shaded surfaces.
        mask: ``(B, 1, H, W)`` covered pixels (others are evaluated at the origin, so that
            garbage in empty pixels reaches neither values nor gradients); None = all.
        visibility: the shadow hook of :func:`~torchraster.shading.lighting.shade`, or None.

    Returns:
        ``hook(kind, lights_slice) -> (B, L_slice, 1, H, W)`` (float32 at least).
    """
    if not fog.light_transmittance:
        return visibility  # type: ignore[return-value]
    check_tensor("position", position, ("B", 3, None, None), floating=True)
    b = position.shape[0]
    dt = torch.promote_types(position.dtype, torch.float32)
    p = position.to(dt)
    if mask is not None:
        p = torch.where(mask > 0, p, torch.zeros_like(p))
    lights = lights.expand(b) if lights.batch_size == 1 and b > 1 else lights

    def hook(kind: str, sl: slice) -> torch.Tensor | None:
        t = light_transmittance(p, kind, getattr(lights, kind).select(sl), fog)
        vis = None if visibility is None else visibility(kind, sl)
        return t if vis is None else t * vis.to(t.dtype)

    return hook


def ambient_inscatter(sh: torch.Tensor, rays: torch.Tensor, g: float | torch.Tensor
                      ) -> torch.Tensor:
    """Ambient light scattered towards the eye: ``integral p(w . v) L(w) dw``.

    By the Funk-Hecke theorem the HG lobe (Legendre coefficients ``g^l``) scales SH band
    ``l`` by ``g^l`` (Ramamoorthi & Hanrahan 2001 for the SH; Jarosz 2008, section 2.4.1):
    ``sum_lm g^l L_lm Y_lm(v)``. A constant radiance ``c`` gives ``c`` for any ``g``.

    Args:
        sh: ``(B, 9, 3)`` incident radiance SH coefficients (``Lights.ambient``).
        rays: ``(B, 3, H, W)`` unit view directions.
        g: HG anisotropy.

    Returns:
        ``(B, 3, H, W)`` radiance per unit scattering (nits), clamped at 0 (SH ringing).
    """
    check_tensor("sh", sh, ("B", 9, 3), floating=True)
    g = torch.as_tensor(g, dtype=rays.dtype, device=rays.device).reshape(())
    band = torch.stack([torch.ones_like(g), g, g, g, g * g, g * g, g * g, g * g, g * g])
    return torch.einsum("bkhw,bkc->bchw", sh_basis(rays), sh.to(rays.dtype) * band[:, None]
                        ).clamp_min(0)


def interleaved_gradient_noise(h: int, w: int, seed: int = 0, *, dtype: torch.dtype =
                               torch.float32, device: torch.device | str | None = None,
                               row0: int = 0) -> torch.Tensor:
    """Interleaved gradient noise (Jimenez 2014, "Next generation post processing in Call of
    Duty: Advanced Warfare"): ``frac(52.9829189 frac(0.06711056 x + 0.00583715 y))``, with
    ``x`` offset by ``5.588238 * seed``. Deterministic, well spread in [0, 1).

    Returns:
        ``(1, 1, H, W)``: the rows ``row0 .. row0 + H`` of the pattern.
    """
    y, x = torch.meshgrid(torch.arange(row0, row0 + h, dtype=torch.float64, device=device),
                          torch.arange(w, dtype=torch.float64, device=device), indexing="ij")
    x = x + 5.588238 * seed
    return torch.frac(52.9829189 * torch.frac(0.06711056 * x + 0.00583715 * y)).to(dtype)[
        None, None]


# ---------------------------------------------------------------------------- lights


def _volume_maps(g: ShadowMaps) -> ShadowMaps:
    """The same maps looked up for fog samples: one comparison (VSM: its moments), no
    bias (a fog sample is no surface that could shadow itself; a bias would light the fog
    just under an occluder) and no pixel footprint."""
    s = g.settings
    filt = "vsm" if s.filter == "vsm" else "hard"
    return dataclasses.replace(g, settings=dataclasses.replace(
        s, filter=filt, bias=0.0, slope_bias=0.0, normal_bias=0.0, pixel_radius=0.0))


def marched_lights(lights: Lights | None, shadow_maps: Sequence[ShadowMaps] = ()
                   ) -> dict[str, list[int]]:
    """The lights whose in-scattering is marched: every point, spot and area light, and
    the directional lights that have shadow maps.

    Args:
        lights: the scene's lights or None.
        shadow_maps: the rendered shadow maps.

    Returns:
        ``{kind: [light indices]}`` (empty: nothing to march).
    """
    out: dict[str, list[int]] = {}
    if lights is None:
        return out
    for kind in ("point", "spot", "area"):
        part = getattr(lights, kind)
        if part is not None and part.count:
            out[kind] = list(range(part.count))
    shadowed = sorted({i for g in shadow_maps if g.kind == "directional" for i in g.lights})
    if shadowed and lights.directional is not None:
        out["directional"] = shadowed
    return out


def light_source(lights: Lights, rays: torch.Tensor, g: float | torch.Tensor,
                 shadow_maps: Sequence[ShadowMaps] = (), camera_view: torch.Tensor | None = None,
                 kinds: dict[str, list[int]] | None = None, fog: Fog | None = None
                 ) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """The in-scattering source of the marched lights at fog samples.

    Args:
        lights: the scene's lights, batch size B (or 1).
        rays: ``(B, 3, H, W)`` unit view directions.
        g: HG anisotropy.
        shadow_maps: rendered :class:`ShadowMaps` (their lights are shadowed).
        camera_view: ``(B, 4, 4)`` world -> camera view (cascade selection).
        kinds: the lights to evaluate (default :func:`marched_lights`).
        fog: the medium: with ``fog.light_transmittance`` each light is dimmed by the fog
            between it and the sample (:func:`light_transmittance`); None = undimmed.

    Returns:
        ``source(p, valid)``: ``p`` ``(B, 3, H, W)`` sample positions, ``valid`` ``(B, 1, H,
        W)`` bool (samples to look up in the shadow maps) -> ``(B, 3, H, W)``
        ``sum p_HG(l . v) E T_l V`` (lux per steradian: radiance per unit scattering
        length).
    """
    kinds = marched_lights(lights, shadow_maps) if kinds is None else kinds
    b = rays.shape[0]
    lights = lights.expand(b) if lights.batch_size == 1 and b > 1 else lights
    lights = lights.to(device=rays.device, dtype=rays.dtype)
    groups = [_volume_maps(m) for m in shadow_maps]
    parts = {kind: getattr(lights, kind).select(torch.tensor(ids, device=rays.device))
             for kind, ids in kinds.items()}

    def source(p: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        total = torch.zeros_like(p)
        for kind, ids in kinds.items():
            part = parts[kind]
            spread = 1.0
            if kind == "directional":
                l = -torch.nn.functional.normalize(part.direction, dim=-1)[..., None, None]
                e = (part.color * part.intensity[..., None])[..., None, None]
            elif kind == "point":
                l, e = point_incidence(part, p)
            elif kind == "area":  # its solid angle, mean direction and spread seen from p
                l, e, spread = area_incidence(part, p)
            else:
                l, e = spot_incidence(part, p)
            if fog is not None and fog.light_transmittance:  # dimmed on the way in
                e = e * light_transmittance(p, kind, part, fog)
            # (B, L, 1, H, W); an area light's spread softens the lobe (area_incidence)
            phase = hg_phase((l * rays[:, None]).sum(2, keepdim=True), g * spread)
            vis = torch.ones_like(phase[..., :1, :, :].expand(-1, -1, -1, *p.shape[-2:]))
            for m in groups:
                if m.kind != kind:
                    continue
                pos = [ids.index(i) for i in m.lights if i in ids]
                if not pos:
                    continue
                pm = p.to(m.view.dtype)  # the maps' dtype (e.g. a float64 reference march)
                v = shadow_visibility(m, pm, torch.zeros_like(pm), valid, camera_view)
                keep = torch.tensor([k for k, i in enumerate(m.lights) if i in ids],
                                    device=p.device)
                vis = vis.index_copy(1, torch.tensor(pos, device=p.device),
                                     v.index_select(1, keep).to(vis.dtype))
            total = total + (phase * e * vis).sum(1)
        return total

    return source


# ---------------------------------------------------------------------------- march


def _farthest_corner(eye: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """``(B, 1, 1, 1)`` distance from ``eye`` ``(B, 3)`` to the farthest corner of boxes
    ``(B, 2, 3)``: every point of the box is nearer."""
    far = torch.maximum((bounds[:, 0] - eye).abs(), (bounds[:, 1] - eye).abs())
    return far.norm(dim=-1).view(-1, 1, 1, 1)


#: Pixels (B x rows x W) of one band of rows of the light march (:func:`fog_terms`): each
#: step's per-light temporaries then stay in the CPU's caches instead of spanning the frame
#: (docs/benchmarks.md, section pass-bands).
FOG_BAND_PIXELS: int = 2**17


def march_inscatter(eye: torch.Tensor, rays: torch.Tensor, start: torch.Tensor,
                    end: torch.Tensor, fog: Fog,
                    source: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                    steps: int | None = None, jitter: bool | None = None, row0: int = 0
                    ) -> torch.Tensor:
    """In-scattered radiance of a varying source between ``start`` and ``end`` along each
    ray: ``sum_i color S(t_i) (T(a_i) - T(b_i))`` over ``steps`` equal segments ``[a_i, b_i]``
    with exact transmittances and ``t_i`` jittered per pixel (module docstring).

    Args:
        eye: ``(B, 3)`` ray origins; rays: ``(B, 3, H, W)`` unit directions.
        start, end: ``(B, 1, H, W)`` finite distances (m); nothing where ``end <= start``.
        fog: the medium (``color``, density) and, by default, ``steps`` / ``jitter``.
        source: ``source(p, valid) -> (B, 3, H, W)`` radiance per unit scattering length
            (:func:`light_source`).
        row0: the frame row of the rays' first row (a band of a frame: the jitter pattern
            of those rows).

    Returns:
        ``(B, 3, H, W)``.
    """
    steps = fog.steps if steps is None else steps
    jitter = fog.jitter if jitter is None else jitter
    h, w = rays.shape[-2:]
    valid = end > start
    length = torch.where(valid, end - start, torch.zeros_like(end)).detach()
    start = start.detach()
    oy, dy = eye[:, 1, None, None, None], rays[:, 1:2]
    j = interleaved_gradient_noise(h, w, fog.seed, dtype=rays.dtype, device=rays.device,
                                   row0=row0) if jitter else 0.5
    color = fog.param("color", rays)
    out = torch.zeros_like(rays)
    t_prev = fog_transmittance(oy, dy, start, fog)
    for i in range(steps):
        t_next = fog_transmittance(oy, dy, start + length * ((i + 1) / steps), fog)
        t = start + length * ((i + j) / steps)
        p = eye[:, :, None, None] + rays * t
        out = out + source(p, valid) * (t_prev - t_next)
        t_prev = t_next
    return color * out * valid


def fog_terms(distance: torch.Tensor, eye: torch.Tensor, rays: torch.Tensor, fog: Fog,
              lights: Lights | None = None, shadow_maps: Sequence[ShadowMaps] = (),
              camera_view: torch.Tensor | None = None, bounds: torch.Tensor | None = None,
              environment: Environment | None = None) -> FogTerms:
    """Transmittance and in-scattered light of the fog along the view rays.

    Args:
        distance: ``(B, 1, H, W)`` distance (m) from the eye to the visible surface, ``inf``
            where empty (replaced by ``fog.max_distance``).
        eye: ``(B, 3)`` camera positions; rays: ``(B, 3, H, W)`` unit view directions.
        fog: the :class:`Fog`.
        lights: the scene's lights (ambient SH, directional, point, spot, area) or None.
        shadow_maps: rendered shadow maps: their lights cast light shafts.
        camera_view: ``(B, 4, 4)`` world -> view (cascaded maps need it).
        bounds: ``(B, 2, 3)`` world box of the scene: each ray is marched up to the
            distance of the box's farthest corner from the eye (the box grown to hold the
            point / spot lights and the area lights' centres); None: up to the farthest
            finite distance of the frame (at most :data:`MAX_MARCH_DISTANCE`).
        environment: an :class:`~torchraster.shading.ibl.Environment` lighting the fog
            like the ambient light (its 9 SH coefficients convolved with the phase, not
            dimmed on the way in), or None.

    Returns:
        :class:`FogTerms`.
    """
    check_tensor("rays", rays, ("B", 3, None, None), floating=True)
    b, _, h, w = rays.shape
    check_tensor("distance", distance, (b, 1, h, w), floating=True)
    check_tensor("eye", eye, (b, 3), floating=True, finite=True)
    if bool((distance.detach() < 0).any()) or bool(torch.isnan(distance.detach()).any()):
        raise ValueError("distance: expected distances >= 0 (inf where empty)")
    dtype = rays.dtype
    eye = eye.to(dtype)
    s = torch.where(torch.isfinite(distance), distance,
                    torch.full_like(distance, fog.max_distance)).clamp_max(fog.max_distance)
    oy, dy = eye[:, 1, None, None, None], rays[:, 1:2]
    trans = fog_transmittance(oy, dy, s, fog)
    color, g = fog.param("color", rays), fog.param("anisotropy", rays).reshape(())
    const = fog.param("ambient", rays).expand(b, 3, h, w)
    if lights is not None and lights.ambient is not None:
        sh = lights.ambient.expand(b, 9, 3) if lights.ambient.shape[0] == 1 else lights.ambient
        const = const + ambient_inscatter(sh, rays, g)
    if environment is not None:  # SH in env space: look it up along the env-space rays
        sh = environment.sh.to(dtype)
        env_in = ambient_inscatter(sh.expand(b, 9, 3) if sh.shape[0] == 1 else sh,
                                   environment.to_env(rays), g)
        k = environment.intensity
        const = const + env_in * (k if isinstance(k, float) else k.to(dtype).reshape(-1, 1, 1, 1))
    kinds = marched_lights(lights, shadow_maps)
    dir_analytic = torch.zeros_like(rays)  # unshadowed directional lights
    marched_dir = None  # (B, L, 3, H, W) shadowed ones: marched inside the box
    if lights is not None and lights.directional is not None and lights.directional.count:
        d = lights.directional.expand(b) if lights.directional.batch_size == 1 else (
            lights.directional)
        d = d.to(device=rays.device, dtype=dtype)
        l = -torch.nn.functional.normalize(d.direction, dim=-1)  # (B, L, 3)
        cos = torch.einsum("blc,bchw->blhw", l, rays)
        e = d.color * d.intensity[..., None]  # (B, L, 3)
        per = hg_phase(cos, g)[:, :, None] * e[..., None, None]  # (B, L, 3, H, W)
        shadowed = torch.zeros(d.count, dtype=torch.bool, device=rays.device)
        shadowed[kinds.get("directional", [])] = True
        l_y = l[:, :, 1, None, None, None]  # (B, L, 1, 1, 1)

        def weight(length: torch.Tensor) -> torch.Tensor:  # (B, L, 1, H, W)
            return directional_inscatter_weight(oy[:, None], dy[:, None], length[:, None],
                                                l_y, fog)

        dir_analytic = (per[:, ~shadowed] * weight(s)[:, ~shadowed]).sum(1)
        marched_dir = per[:, shadowed]
    analytic = color * (const * (1 - trans) + dir_analytic)
    marched = torch.zeros_like(rays)
    if kinds:
        with torch.no_grad():
            if bounds is None:
                fin = s[torch.isfinite(s)]
                far = fin.max() if fin.numel() else s.new_tensor(1.0)
            else:
                check_tensor("bounds", bounds, (None, 2, 3), floating=True, finite=True)
                box = bounds.to(dtype).expand(b, 2, 3)
                for kind in ("point", "spot", "area"):
                    part = getattr(lights, kind)
                    if kind in kinds and part is not None:
                        pos = part.position.detach().to(dtype).expand(b, -1, 3)
                        box = torch.stack([torch.minimum(box[:, 0], pos.amin(1)),
                                           torch.maximum(box[:, 1], pos.amax(1))], 1)
                far = _farthest_corner(eye.detach(), box)
            far = torch.as_tensor(far, dtype=dtype, device=s.device).clamp_max(
                MAX_MARCH_DISTANCE)
            start, end = torch.zeros_like(s), torch.minimum(s.detach(), far)
        # bands of rows of FOG_BAND_PIXELS: each step's per-light temporaries stay in the
        # caches (the march is per pixel; the source closes over its band's rays). Not with
        # shadow maps: a band's lookups split into a chunk per batch item, whose fixed cost
        # outweighed the caches' gain (512² x 4, a shadowed point light: 0.87x)
        rows = h if shadow_maps else max(1, FOG_BAND_PIXELS // (b * w))
        bands = [march_inscatter(
            eye, rays[..., r0:r0 + rows, :], start[..., r0:r0 + rows, :],
            end[..., r0:r0 + rows, :], fog,
            light_source(lights, rays[..., r0:r0 + rows, :], g, shadow_maps, camera_view, kinds,
                         fog), row0=r0) for r0 in range(0, h, rows)]
        marched = bands[0] if len(bands) == 1 else torch.cat(bands, dim=-2)
        if "directional" in kinds:  # outside the march range [start, end]: unshadowed
            sel = torch.tensor(kinds["directional"], device=rays.device)
            outside = weight(start) + weight(s) - weight(end)
            analytic = analytic + color * (marched_dir * outside.index_select(1, sel)).sum(1)
    return FogTerms(trans, analytic, marched)


def depth_aware_blur(x: torch.Tensor, distance: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable joint bilateral blur of ``x`` ``(B, C, H, W)`` guided by the log distance
    ``(B, 1, H, W)``: Gaussian spatial weights (``sigma`` pixels, radius ``2 sigma``) times
    ``exp(-(d log dist)^2 / (2 BLUR_DEPTH_SIGMA^2))`` (Tomasi & Manduchi 1998, Petschnigg et
    al. 2004), one pass along x then one along y, so the blur does not mix a foreground
    object's fog with the background's. (kornia's ``joint_bilateral_blur`` gives the
    non-separable filter but unfolds the image: 60x slower at 128 x 128.)"""
    if sigma <= 0:
        return x
    r = math.ceil(2 * sigma)
    guide = torch.log1p(distance.detach().clamp(0, 1e12)).to(x.dtype)
    spatial = [math.exp(-0.5 * (k / sigma) ** 2) for k in range(-r, r + 1)]
    for dim in (-1, -2):
        pad = (r, r, 0, 0) if dim == -1 else (0, 0, r, r)
        xp = torch.nn.functional.pad(x, pad, mode="replicate")
        gp = torch.nn.functional.pad(guide, pad, mode="replicate")
        n = x.shape[dim]
        num, den = torch.zeros_like(x), torch.zeros_like(guide)
        for i, ws in enumerate(spatial):
            xs, gs = xp.narrow(dim, i, n), gp.narrow(dim, i, n)
            wgt = ws * torch.exp(-0.5 * ((gs - guide) / BLUR_DEPTH_SIGMA) ** 2)
            num = num + wgt * xs
            den = den + wgt
        x = num / den  # den >= 1 (the centre tap)
    return x


def apply_fog(image: torch.Tensor, distance: torch.Tensor, eye: torch.Tensor,
              rays: torch.Tensor, fog: Fog, lights: Lights | None = None,
              shadow_maps: Sequence[ShadowMaps] = (), camera_view: torch.Tensor | None = None,
              bounds: torch.Tensor | None = None, environment: Environment | None = None
              ) -> torch.Tensor:
    """Fog a lit image: ``T * image + analytic + blur(marched)`` (:func:`fog_terms`).

    Args:
        image: ``(B, 3, H, W)`` linear radiance (surfaces and background).
        distance, eye, rays, fog, lights, shadow_maps, camera_view, bounds, environment: as
            in :func:`fog_terms`.

    Returns:
        ``(B, 3, H, W)`` fogged radiance in ``image``'s dtype (float16 / bfloat16 inputs are
        fogged in float32 and saturated on output).

    Example:
        >>> image, distance = torch.ones(1, 3, 2, 2), torch.full((1, 1, 2, 2), 2.0)
        >>> rays = torch.tensor([0.0, 0, -1]).view(1, 3, 1, 1).expand(1, 3, 2, 2)
        >>> out = apply_fog(image, distance, torch.zeros(1, 3), rays, Fog(density=0.5))
        >>> out[0, :, 0, 0]  # no lights: only the transmittance exp(-0.5 * 2)
        tensor([0.3679, 0.3679, 0.3679])
    """
    check_tensor("image", image, (rays.shape[0], 3, *rays.shape[-2:]), floating=True)
    out_dtype = image.dtype
    if out_dtype in LOW_PRECISION:  # optical depths and their gradients overflow in half
        image, distance, eye, rays = (t.float() for t in (image, distance, eye, rays))
    terms = fog_terms(distance, eye, rays, fog, lights, shadow_maps, camera_view, bounds,
                      environment)
    marched = depth_aware_blur(terms.marched, distance.clamp_max(fog.max_distance), fog.blur)
    return finish_low_precision(image * terms.transmittance + terms.analytic + marched,
                                out_dtype)


__all__ = ["Fog", "FogTerms", "ambient_inscatter", "apply_fog", "depth_aware_blur",
           "directional_inscatter_weight", "fog_density", "fog_terms", "fog_transmittance",
           "hg_phase", "interleaved_gradient_noise", "light_optical_depth", "light_source",
           "light_transmittance", "march_inscatter", "marched_lights", "optical_depth",
           "surface_light_hook"]
