"""Deferred lighting pass: G-buffer + lights -> linear HDR radiance.

``radiance = emissive + ao * (ambient + ibl) + sum over lights of model(n, v, l) * E_light``

* Punctual lights (directional, point, spot) are evaluated with the lights as a tensor
  dimension ``(B, L, C, H, W)``, in chunks of lights bounded by a memory budget
  (:data:`LIGHT_CHUNK_ELEMENTS`); light types that are absent (None or L = 0) cost nothing.
  With autograd on and more than one chunk, each chunk is recomputed in backward
  (``torch.utils.checkpoint``), so memory does not grow with the number of lights.
* Ambient (SH) light: Lambert diffuse from the SH irradiance at n, plus a specular term
  from the SH irradiance at the reflection vector weighted by the split-sum environment
  BRDF of our Cook-Torrance BRDF (Karis 2013; the cached split-sum table
  :func:`torchraster.shading.ibl.dfg_lut`, shared with image-based lighting). Exact for a
  constant ambient up to the table's accuracy; applied whatever the shading model.
* Image-based lighting is a hook: pass ``ibl=callable`` (e.g. a closure over
  ``torchraster.shading.ibl.shade_ibl`` and an environment) or None.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch.utils.checkpoint import checkpoint

from torchraster._validate import check_tensor
from torchraster.gbuffer import GBuffer
from torchraster.numerics import (
    LOW_PRECISION,
    diffuse_color,
    dot,
    finish_low_precision,
    safe_normalize,
    specular_f0,
)
from torchraster.shading.brdf import MIN_COS, MIN_ROUGHNESS
from torchraster.shading.ibl import dfg_lut, lookup_dfg
from torchraster.shading.lights import (
    DirectionalLights,
    Lights,
    PointLights,
    SpotLights,
    directional_incidence,
    point_incidence,
    sh_irradiance,
    spot_incidence,
)
from torchraster.shading.models import ShadingModel, Surface, get_model

#: Pixel-lights (B * L_chunk * H * W) evaluated at once. 2**22 keeps one float32 RGB
#: temporary at 48 MB; at 512x512, batch 4 that is 4 lights per chunk.
LIGHT_CHUNK_ELEMENTS: int = 2**22

#: Size and sample count of the split-sum DFG table (built by ``ibl.dfg_lut``, the same
#: function as image-based lighting) for the ambient light's specular term. Finer than
#: ``shade_ibl``'s default 16 x 32: the ambient specular has no prefiltered-map error to
#: hide the table's, and 32 x 96 brings its mean error from 0.58 % to 0.13 %
#: (docs/benchmarks.md, "DFG LUT").
DFG_LUT_SIZE: int = 32
DFG_LUT_SAMPLES: int = 96

#: ``visibility(kind, lights_slice) -> (B, L, 1, H, W) | None``: the fraction of each light
#: of ``kind`` ("directional", "point" or "spot") in ``lights_slice`` that reaches each
#: pixel (shadows); None = all of it.
VisibilityHook = Callable[[str, slice], "torch.Tensor | None"]

IBLHook = Callable[
    [torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor
]

def env_brdf(
    f0: torch.Tensor, roughness: torch.Tensor, n_dot_v: torch.Tensor
) -> torch.Tensor:
    """Directional albedo of the Cook-Torrance specular lobe, ``f0 * A + B`` (split sum).

    Karis 2013's environment BRDF, tabulated for *this* BRDF (height-correlated Smith) by
    ``ibl.dfg_lut`` and looked up bilinearly (differentiable in roughness and n.v).

    Args:
        f0: ``(B, 3, H, W)`` specular colour.
        roughness: ``(B, 1, H, W)`` perceptual roughness.
        n_dot_v: ``(B, 1, H, W)`` cosine of the view angle.

    Returns:
        ``(B, 3, H, W)``, dimensionless, in [0, 1].
    """
    lut = dfg_lut(DFG_LUT_SIZE, DFG_LUT_SAMPLES, device=roughness.device, dtype=roughness.dtype)
    scale, bias = lookup_dfg(lut, n_dot_v.clamp(MIN_COS, 1.0), roughness.clamp(MIN_ROUGHNESS, 1.0))
    return f0 * scale + bias


def _chunks(count: int, per_chunk: int) -> list[slice]:
    return [slice(i, min(i + per_chunk, count)) for i in range(0, count, per_chunk)]


def _direct(
    model: ShadingModel,
    kind: type,
    lights: DirectionalLights | PointLights | SpotLights,
    position: torch.Tensor,
    n: torch.Tensor,
    v: torch.Tensor,
    surface: Surface,
    visibility: torch.Tensor | None = None,
) -> torch.Tensor:
    """Sum over this chunk of lights of ``model(n, v, l) * E * visibility``: ``(B, 3, H, W)``.

    ``visibility``: ``(B, L_chunk, 1, H, W)`` light visibility (shadows) or None (= 1).
    """
    if kind is DirectionalLights:
        l, e = directional_incidence(lights)  # type: ignore[arg-type]
    elif kind is PointLights:
        l, e = point_incidence(lights, position)  # type: ignore[arg-type]
    else:
        l, e = spot_incidence(lights, position)  # type: ignore[arg-type]
    out = model(n, v, l, surface)
    if out.dim() != 5 or out.shape[-3] != 3:
        raise ValueError(
            f"model: expected a (B, L, 3, H, W) result for l of shape {tuple(l.shape)}, "
            f"got {tuple(out.shape)}"
        )
    if visibility is not None:
        e = e * visibility
    return (out * e).sum(dim=1)


def shade(
    gbuffer: GBuffer,
    *,
    camera_position: torch.Tensor,
    lights: Lights | None = None,
    model: str | ShadingModel = "cook_torrance",
    ibl: IBLHook | None = None,
    visibility: VisibilityHook | None = None,
    light_chunk: int | None = None,
    checkpoint_chunks: bool | None = None,
) -> torch.Tensor:
    """Deferred lighting of a G-buffer.

    Args:
        gbuffer: a :class:`~torchraster.gbuffer.GBuffer` with ``position`` (world, m),
            ``normal`` (re-normalised here; zero -> unlit), ``albedo`` (linear RGB),
            ``metallic`` and ``roughness`` (perceptual), each ``(B, C, H, W)``; optional
            ``ao`` (multiplies ambient and IBL only; None = 1), ``emissive`` (radiance added
            as is; None = 0) and ``mask`` (> 0 = covered; None = all).
        camera_position: ``(B, 3)`` world-space eye positions.
        lights: :class:`~torchraster.shading.lights.Lights` of batch size B or 1 (broadcast),
            or None (no punctual or ambient light).
        model: name in :data:`~torchraster.shading.models.MODELS` or a callable
            ``model(n, v, l, surface)`` (see :mod:`torchraster.shading.models`).
        ibl: optional ``ibl(n, v, albedo, metallic, roughness) -> (B, 3, H, W)`` radiance
            from an environment (before AO; unit ``n`` and ``v`` (towards the eye)
            ``(B, 3, H, W)``), e.g. ``lambda n, v, a, m, r: shade_ibl(n, v, a, m, r,
            None, env)``.
        visibility: optional ``visibility(kind, lights) -> (B, L, 1, H, W)`` (or None for
            unshadowed), called per chunk of lights of ``kind`` (``"directional"``,
            ``"point"``, ``"spot"``) with the slice of light indices: the fraction of each
            light that reaches each pixel (e.g. shadow maps). Multiplies the illuminance.
        light_chunk: lights evaluated at once (default: from LIGHT_CHUNK_ELEMENTS).
            ``1`` is the plain Python loop over lights.
        checkpoint_chunks: recompute chunks in backward (default: when autograd is on
            and there is more than one chunk).

    Returns:
        ``(B, 3, H, W)`` linear HDR radiance, 0 where ``mask`` is 0, in the G-buffer's
        dtype (float16 / bfloat16 inputs are shaded in float32 and saturated on output).

    Example:
        >>> gb = GBuffer(position=pos, normal=n, albedo=a, metallic=m, roughness=r)
        >>> radiance = shade(gb, camera_position=eye, lights=lights)
    """
    if not isinstance(gbuffer, GBuffer):
        raise TypeError(f"gbuffer: expected a torchraster.GBuffer, got {type(gbuffer).__name__}"
                        " (build one with GBuffer(position=..., normal=..., ...))")
    gbuffer.require("position", "normal", "albedo", "metallic", "roughness", by="shade")
    position, normal, albedo = gbuffer.position, gbuffer.normal, gbuffer.albedo
    metallic, roughness = gbuffer.metallic, gbuffer.roughness
    ao, emissive, mask = gbuffer.ao, gbuffer.emissive, gbuffer.mask
    b, _, h, w = position.shape
    check_tensor("camera_position", camera_position, (b, 3), floating=True)
    if lights is None:
        lights = Lights()
    if not isinstance(lights, Lights):
        raise TypeError(f"lights: expected a Lights, got {type(lights).__name__}")
    if lights.batch_size not in (None, 1, b):
        raise ValueError(f"lights: batch size {lights.batch_size} != G-buffer batch size {b} "
                         "(use batch size 1 to share lights)")
    if lights.batch_size == 1 and b > 1:
        lights = lights.expand(b)
    shading_model = get_model(model)
    if visibility is not None and not callable(visibility):
        raise TypeError(f"visibility: expected a callable or None, got {type(visibility).__name__}")
    if ibl is not None and not callable(ibl):
        raise TypeError(f"ibl: expected a callable or None, got {type(ibl).__name__}")
    if light_chunk is not None and (not isinstance(light_chunk, int) or light_chunk < 1):
        raise ValueError(f"light_chunk: expected a positive int or None, got {light_chunk!r}")

    inputs = [position, normal, albedo, metallic, roughness, camera_position]
    inputs += [t for t in (ao, emissive) if t is not None]
    out_dtype = inputs[0].dtype
    for t in inputs[1:]:
        out_dtype = torch.promote_types(out_dtype, t.dtype)
    dt = torch.float32 if out_dtype in LOW_PRECISION else out_dtype
    dev = position.device

    covered = None if mask is None else (mask > 0)

    def prep(t: torch.Tensor) -> torch.Tensor:
        # Zero uncovered pixels *before* any op ("double where"): garbage (NaN/Inf) in empty
        # G-buffer pixels can then not leak into values or gradients.
        t = t.to(dtype=dt)
        return t if covered is None else torch.where(covered, t, 0.0)

    pos, nrm, base, metal, rough = (prep(t) for t in (position, normal, albedo, metallic,
                                                       roughness))
    n = safe_normalize(nrm)
    v = safe_normalize(camera_position.to(dt)[:, :, None, None] - pos)
    lights = lights.to(device=dev, dtype=dt)

    radiance = torch.zeros(b, 3, h, w, device=dev, dtype=dt)

    # Direct light: lights as a tensor dimension, in chunks.
    n5, v5 = n[:, None], v[:, None]
    surface = Surface(albedo=base[:, None], metallic=metal[:, None], roughness=rough[:, None])
    per_chunk = light_chunk or max(1, LIGHT_CHUNK_ELEMENTS // max(1, b * h * w))
    for kind, part in (
        (DirectionalLights, lights.directional),
        (PointLights, lights.point),
        (SpotLights, lights.spot),
    ):
        name = {DirectionalLights: "directional", PointLights: "point", SpotLights: "spot"}[kind]
        if part is None or part.count == 0:
            continue
        slices = _chunks(part.count, per_chunk)
        use_ckpt = checkpoint_chunks
        if use_ckpt is None:
            use_ckpt = torch.is_grad_enabled() and len(slices) > 1
        for sl in slices:
            chunk = part if len(slices) == 1 else part.select(sl)
            vis = visibility(name, sl) if visibility is not None else None
            if vis is not None:
                check_tensor(f"visibility({name!r}) result", vis,
                             (b, chunk.count, 1, h, w), floating=True)
                vis = vis.to(dt)
            args = (shading_model, kind, chunk, pos, n5, v5, surface, vis)
            if use_ckpt:
                radiance = radiance + checkpoint(_direct, *args, use_reentrant=False)
            else:
                radiance = radiance + _direct(*args)

    # Ambient (SH) and image-based light, scaled by AO.
    indirect = None
    if lights.ambient is not None:
        n_dot_v = dot(n, v)
        r = 2.0 * n_dot_v * n - v  # reflect(-v, n)
        e_n = sh_irradiance(lights.ambient, n).clamp_min(0.0)
        e_r = sh_irradiance(lights.ambient, r).clamp_min(0.0)
        f0 = specular_f0(base, metal)
        indirect = (diffuse_color(base, metal) * e_n + env_brdf(f0, rough, n_dot_v) * e_r) / (
            torch.pi
        )
    if ibl is not None:
        env = ibl(n, v, base, metal, rough)
        check_tensor("ibl(...) result", env, (b, 3, h, w), floating=True)
        env = env.to(dt)
        indirect = env if indirect is None else indirect + env
    if indirect is not None:
        if ao is not None:
            indirect = indirect * prep(ao)
        radiance = radiance + indirect

    if emissive is not None:
        radiance = radiance + prep(emissive)
    if covered is not None:
        radiance = torch.where(covered, radiance, 0.0)
    return finish_low_precision(radiance, out_dtype)
