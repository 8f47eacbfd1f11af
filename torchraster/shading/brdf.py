"""Microfacet BRDF terms: GGX distribution, height-correlated Smith visibility, Schlick
Fresnel, Lambert diffuse, and the Cook-Torrance metallic-roughness BRDF built from them.

Formulas follow Filament, "Physically Based Rendering in Filament" (sections 4.4-4.6), and
Karis 2013, "Real Shading in Unreal Engine 4". ``roughness`` is always the *perceptual*
roughness of glTF / Filament; the GGX parameter is ``alpha = roughness ** 2``.

All functions take broadcastable tensors (or Python floats where noted). Vector arguments
keep their xyz components on dim ``-3`` so that image-like ``(B, 3, H, W)`` and
light-batched ``(B, L, 3, H, W)`` tensors both work. float16 / bfloat16 inputs are
evaluated in float32 and the result is cast back, saturated to the dtype's finite range
(as Filament's ``saturateMediump``), so low-precision inputs never produce Inf.
"""

from __future__ import annotations

import math

import torch

from torchraster.numerics import (  # noqa: F401 (safe_normalize: re-exported)
    NORMALIZE_EPS,
    compute_dtype,
    diffuse_color,
    dot,
    finish_low_precision,
    safe_normalize,
    specular_f0,
)

#: Smallest perceptual roughness (alpha = 0.045**2 ~ 2.0e-3). Filament's value: below it
#: the GGX peak ``1 / (pi * alpha**2)`` (~7.8e4 here) grows past what float16 can hold,
#: ``1 - (n.h)**2`` near the peak loses all precision in low-precision formats, and the
#: highlight of a punctual light becomes far narrower than a pixel (pure aliasing).
#: Roughness 0 (a perfect mirror) is mapped to this value.
MIN_ROUGHNESS: float = 0.045

#: Floor for the cosines n.v and n.l inside the visibility term (Filament adds 1e-5 to
#: |n.v|). Keeps ``V`` finite at grazing and back-facing angles; the cosine factor that
#: multiplies the BRDF is clamped at 0, not at this floor, so grazing light still gives 0.
MIN_COS: float = 1e-4

Scalar = float | torch.Tensor



def _out_dtype(*xs: object) -> torch.dtype:
    """dtype the result is returned in: the promoted floating dtype of the tensor inputs."""
    tensors = [x for x in xs if isinstance(x, torch.Tensor) and x.is_floating_point()]
    if not tensors:
        return torch.float32
    dtype = tensors[0].dtype
    for t in tensors[1:]:
        dtype = torch.promote_types(dtype, t.dtype)
    return dtype


def _as_tensor(name: str, x: object, ref: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Python number or floating tensor -> tensor on ref's device in ``dtype``."""
    if isinstance(x, torch.Tensor):
        if x.is_complex():
            raise TypeError(f"{name}: expected a real tensor, got {x.dtype}")
        return x.to(device=ref.device, dtype=dtype)
    if isinstance(x, (int, float)) and not isinstance(x, bool):
        return torch.tensor(float(x), device=ref.device, dtype=dtype)
    raise TypeError(f"{name}: expected a float or a torch.Tensor, got {type(x).__name__}")


def _first_tensor(*xs: object) -> torch.Tensor:
    for x in xs:
        if isinstance(x, torch.Tensor):
            return x
    return torch.zeros(())


def _check_vector(name: str, x: object) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got {x.dtype}")
    if x.dim() < 3 or x.shape[-3] != 3:
        raise ValueError(
            f"{name}: expected xyz on dim -3, e.g. (B, 3, H, W), got {tuple(x.shape)}"
        )
    return x


def _alpha(roughness: torch.Tensor) -> torch.Tensor:
    """GGX alpha = perceptual roughness**2, roughness clamped to [MIN_ROUGHNESS, 1]."""
    r = roughness.clamp(MIN_ROUGHNESS, 1.0)
    return r * r


def ggx_lobe(n_dot_h: torch.Tensor, alpha: torch.Tensor, alpha2: torch.Tensor) -> torch.Tensor:
    """``pi D_GGX``: the GGX distribution without its ``1 / pi`` (the one GGX kernel of
    :func:`d_ggx` and the fused lighting pass). ``k = alpha / (1 - c^2 + (c alpha)^2)``,
    ``c = clamp(n.h, 0, 1)``, result ``k^2``, 0 where ``n.h <= 0`` (Filament eq. 4).
    ``alpha2 = alpha^2`` is passed in (callers reuse it); broadcastable tensors."""
    c2 = n_dot_h.clamp(0.0, 1.0).square()
    k = alpha / torch.addcmul(torch.ones_like(c2), c2, alpha2 - 1.0)  # 1 - c^2 + (c a)^2
    return k * k * (n_dot_h > 0)


def schlick_weight(cos: torch.Tensor) -> torch.Tensor:
    """Schlick's ``(1 - cos)^5`` with ``cos`` clamped to [0, 1] (the Fresnel weight of
    :func:`f_schlick`: ``F = f0 + (f90 - f0) schlick_weight(v.h)``)."""
    m = 1.0 - cos.clamp(0.0, 1.0)
    m2 = m * m
    return m2 * m2 * m


def d_ggx(n_dot_h: torch.Tensor, roughness: Scalar) -> torch.Tensor:
    """GGX / Trowbridge-Reitz normal distribution D(h) (Filament eq. 4, Walter et al. 2007).

    ``D = alpha^2 / (pi * ((n.h)^2 (alpha^2 - 1) + 1)^2)``, written as in Filament,
    ``k = alpha / (1 - (n.h)^2 + (n.h * alpha)^2)``, ``D = k^2 / pi``; the denominator is
    >= alpha^2 > 0. D = 0 for n.h <= 0 (microfacets facing away). Normalised so that
    ``integral of D(h) (n.h) dw_h over the hemisphere = 1``.

    Args:
        n_dot_h: cosine between normal and half vector, any shape, dimensionless.
        roughness: perceptual roughness in [0, 1] (clamped to [MIN_ROUGHNESS, 1]),
            float or tensor broadcastable with ``n_dot_h``.

    Returns:
        D in 1/sr, broadcast shape of the inputs.
    """
    if not isinstance(n_dot_h, torch.Tensor) or not n_dot_h.is_floating_point():
        raise TypeError("n_dot_h: expected a floating-point torch.Tensor")
    out = _out_dtype(n_dot_h, roughness)
    dt = compute_dtype(n_dot_h, roughness)
    nh = n_dot_h.to(dt)
    a = _alpha(_as_tensor("roughness", roughness, nh, dt))
    return finish_low_precision(ggx_lobe(nh, a, a * a) / math.pi, out)


def v_smith_ggx_correlated(
    n_dot_v: torch.Tensor, n_dot_l: torch.Tensor, roughness: Scalar
) -> torch.Tensor:
    """Height-correlated Smith-GGX visibility ``V = G / (4 (n.v)(n.l))`` (Filament eq. 15).

    ``V = 0.5 / (n.l sqrt((n.v)^2 (1 - a^2) + a^2) + n.v sqrt((n.l)^2 (1 - a^2) + a^2))``
    with both cosines clamped to ``[MIN_COS, 1]`` (finite at grazing / back-facing
    angles) and ``a = alpha = roughness^2``. Symmetric in n.v and n.l.

    Args:
        n_dot_v, n_dot_l: cosines, broadcastable tensors.
        roughness: perceptual roughness, float or broadcastable tensor.

    Returns:
        V (dimensionless, includes the 1/(4 n.v n.l) of the Cook-Torrance denominator).
    """
    for name, x in (("n_dot_v", n_dot_v), ("n_dot_l", n_dot_l)):
        if not isinstance(x, torch.Tensor) or not x.is_floating_point():
            raise TypeError(f"{name}: expected a floating-point torch.Tensor")
    out = _out_dtype(n_dot_v, n_dot_l, roughness)
    dt = compute_dtype(n_dot_v, n_dot_l, roughness)
    nv = n_dot_v.to(dt).clamp(MIN_COS, 1.0)
    nl = n_dot_l.to(dt).clamp(MIN_COS, 1.0)
    a2 = _alpha(_as_tensor("roughness", roughness, nv, dt)) ** 2
    ggx_v = nl * torch.sqrt(nv * nv * (1.0 - a2) + a2)
    ggx_l = nv * torch.sqrt(nl * nl * (1.0 - a2) + a2)
    return finish_low_precision(0.5 / (ggx_v + ggx_l), out)


def f_schlick(v_dot_h: torch.Tensor, f0: Scalar, f90: Scalar = 1.0) -> torch.Tensor:
    """Schlick's Fresnel approximation ``F = f0 + (f90 - f0) (1 - v.h)^5`` (Filament eq. 18).

    Args:
        v_dot_h: cosine between view (or light) and half vector, clamped to [0, 1].
        f0: reflectance at normal incidence, float or tensor (e.g. ``(B, 3, H, W)``).
        f90: reflectance at grazing incidence (1 for physical materials).

    Returns:
        F, broadcast shape of the inputs, dimensionless in [min(f0, f90), max(f0, f90)].
    """
    if not isinstance(v_dot_h, torch.Tensor) or not v_dot_h.is_floating_point():
        raise TypeError("v_dot_h: expected a floating-point torch.Tensor")
    out = _out_dtype(v_dot_h, f0, f90)
    dt = compute_dtype(v_dot_h, f0, f90)
    vh = v_dot_h.to(dt)
    f0t = _as_tensor("f0", f0, vh, dt)
    f90t = _as_tensor("f90", f90, vh, dt)
    return finish_low_precision(f0t + (f90t - f0t) * schlick_weight(vh), out)


def fd_lambert() -> float:
    """Lambertian diffuse BRDF for unit albedo, ``1 / pi`` (1/sr), a Python float."""
    return 1.0 / math.pi


def cook_torrance(
    n: torch.Tensor,
    v: torch.Tensor,
    l: torch.Tensor,
    albedo: Scalar,
    metallic: Scalar,
    roughness: Scalar,
    *,
    include_cosine: bool = True,
) -> torch.Tensor:
    """Metallic-roughness Cook-Torrance BRDF (Filament standard model, glTF semantics).

    ``f = diffuse + D V F`` with ``f0 = mix(0.04, albedo, metallic)``,
    ``diffuse = (1 - metallic) albedo / pi``, D = :func:`d_ggx`, V =
    :func:`v_smith_ggx_correlated`, F = :func:`f_schlick` (f90 = 1), ``h = normalize(v + l)``.

    Returns ``f * max(n.l, 0)`` by default: the outgoing radiance (W/(sr m^2) per unit
    of light irradiance normal to the light, i.e. multiply by a directional light's
    illuminance E in lux to get luminance). With ``include_cosine=False`` the bare BRDF
    ``f`` (1/sr) is returned; it is reciprocal (f(v, l) = f(l, v)) for n.v, n.l > 0.
    n.v <= 0 (a view below the shading normal) is shaded as grazing (cosine floor MIN_COS),
    light from below (n.l <= 0) gives 0.

    Args:
        n, v, l: unit normal, direction to the viewer and direction to the light, xyz on
            dim -3: ``(B, 3, H, W)`` or ``(B, L, 3, H, W)`` (broadcastable). Must be unit
            length (or zero); not re-normalised (use :func:`safe_normalize`).
        albedo: base colour (linear RGB), ``(B, 3, H, W)``-broadcastable or float.
        metallic: in [0, 1], ``(B, 1, H, W)``-broadcastable or float.
        roughness: perceptual roughness in [0, 1], ``(B, 1, H, W)``-broadcastable or float.
        include_cosine: multiply by ``max(n.l, 0)`` (default True).

    Returns:
        ``(..., 3, H, W)`` RGB in the broadcast shape of the inputs.
    """
    for name, x in (("n", n), ("v", v), ("l", l)):
        _check_vector(name, x)
    out = _out_dtype(n, v, l, albedo, metallic, roughness)
    dt = compute_dtype(n, v, l, albedo, metallic, roughness)
    n, v, l = n.to(dt), v.to(dt), l.to(dt)
    base = _as_tensor("albedo", albedo, n, dt)
    metal = _as_tensor("metallic", metallic, n, dt)
    rough = _as_tensor("roughness", roughness, n, dt)

    # Half-vector cosines without forming h (unit v, l): |v + l|^2 = 2 + 2 v.l,
    # n.h = (n.l + n.v) / |v + l|, v.h = (1 + v.l) / |v + l|; v = -l gives 0 ("double where").
    n_dot_v = dot(n, v)
    n_dot_l = dot(n, l)
    len2 = 2.0 + 2.0 * dot(v, l)
    ok = len2 > NORMALIZE_EPS
    inv_len = torch.where(ok, torch.rsqrt(torch.where(ok, len2, 1.0)), 0.0)
    n_dot_h = (n_dot_l + n_dot_v) * inv_len
    v_dot_h = 0.5 * len2 * inv_len

    f0 = specular_f0(base, metal)
    spec = (
        d_ggx(n_dot_h, rough)
        * v_smith_ggx_correlated(n_dot_v, n_dot_l, rough)
        * f_schlick(v_dot_h, f0)
    )
    f = diffuse_color(base, metal) * fd_lambert() + spec
    if include_cosine:
        f = f * n_dot_l.clamp(0.0, 1.0)
    return finish_low_precision(f, out)
