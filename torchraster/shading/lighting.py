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
* Energy (``multiscatter=True``, default): the Cook-Torrance specular of punctual and
  ambient light is scaled for multiple scattering and the diffuse gets what the specular
  does not reflect, the convention of :mod:`torchraster.shading.energy` (also used by
  ``shade_ibl``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import torch
from torch.utils.checkpoint import checkpoint

from torchraster._validate import check_tensor
from torchraster.gbuffer import GBuffer
from torchraster.numerics import (
    LOW_PRECISION,
    diffuse_color,
    finish_low_precision,
    safe_normalize,
    specular_f0,
    to_compute,
)
from torchraster.shading.area import area_incidence, area_lights, polygon_sides
from torchraster.shading.brdf import (
    MIN_COS,
    MIN_ROUGHNESS,
    NORMALIZE_EPS,
    ggx_lobe,
    schlick_weight,
)
from torchraster.shading.energy import DFG_LUT_SAMPLES, DFG_LUT_SIZE, energy_terms
from torchraster.shading.ibl import dfg_lut, lookup_dfg
from torchraster.shading.lights import (
    MIN_LIGHT_DISTANCE,
    AreaLights,
    DirectionalLights,
    Lights,
    PointLights,
    SpotLights,
    directional_incidence,
    distance_attenuation,
    point_incidence,
    sh_irradiance,
    spot_attenuation,
    spot_incidence,
)
from torchraster.shading.models import ShadingModel, get_model
from torchraster.shading.models import cook_torrance as _cook_torrance_model
from torchraster.shading.surface import PixelSurface, Surface, pixel_surface

#: Pixel-lights (B * L_chunk * H * W) evaluated at once. 2**22 keeps one float32 RGB
#: temporary at 48 MB; at 512x512, batch 4 that is 4 lights per chunk.
LIGHT_CHUNK_ELEMENTS: int = 2**22

#: Pixel-lights evaluated at once by the fused Cook-Torrance pass (:func:`cook_torrance_lights`):
#: its ~30 temporaries of this many elements then stay in the CPU's cache.
PIXEL_LIGHT_CHUNK: int = 2**16

#: With autograd on, the fused pass takes this many times larger chunks (fewer, larger
#: autograd graphs; memory stays bounded by the chunk when chunks are checkpointed: 16
#: lights at 512² x 8 hold the same with 1 or 8, docs/benchmarks.md, memory).
GRAD_CHUNK_FACTOR: int = 8

#: Pixel-lights of one band of image rows of the other shading models (:func:`_direct`):
#: their per-light RGB temporaries then stay in the CPU's caches instead of spanning whole
#: frames (docs/benchmarks.md, section model-bands).
MODEL_BAND_ELEMENTS: int = 2**17

#: The fused pass evaluates the BRDF only at the pixel-lights a light reaches (n.l > 0,
#: inside its range and cone, visible) when fewer than this fraction of them are reached;
#: above it, evaluating all of them is cheaper than gathering the reached ones.
SPARSE_FRACTION: float = 0.4

#: Pixel-lights of an area light cost about this many of a point light's (its polygon's
#: edges, twice): the fused pass's chunks hold that many times fewer of them.
AREA_LIGHT_COST: int = 8

#: ``visibility(kind, lights_slice) -> (B, L, 1, H, W) | None``: the fraction of each light
#: of ``kind`` ("directional", "point", "spot" or "area") in ``lights_slice`` that reaches
#: each pixel (shadows); None = all of it.
VisibilityHook = Callable[[str, slice], "torch.Tensor | None"]

#: ``ibl(surface) -> (B, 3, H, W)``: radiance from an environment at each pixel of the
#: :class:`~torchraster.shading.surface.PixelSurface` (before AO).
IBLHook = Callable[[PixelSurface], torch.Tensor]

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
    Evaluated over bands of image rows of about :data:`MODEL_BAND_ELEMENTS` pixel-lights
    (the model sees ``(B, L, C, rows, W)`` tensors: it is per pixel).
    """
    b, h, w = n.shape[0], n.shape[-2], n.shape[-1]
    rows = max(1, MODEL_BAND_ELEMENTS // max(1, b * lights.count * w))
    if rows < h:
        def band(t: torch.Tensor, r0: int) -> torch.Tensor:
            return t[..., r0:r0 + rows, :]

        return torch.cat([_direct_rows(
            model, kind, lights, band(position, r0), band(n, r0), band(v, r0),
            Surface(*(band(t, r0) for t in (surface.albedo, surface.metallic,
                                             surface.roughness))),
            None if visibility is None else band(visibility, r0)) for r0 in range(0, h, rows)],
            dim=-2)
    return _direct_rows(model, kind, lights, position, n, v, surface, visibility)


def _direct_rows(model: ShadingModel, kind: type,
                 lights: DirectionalLights | PointLights | SpotLights | AreaLights,
                 position: torch.Tensor, n: torch.Tensor, v: torch.Tensor, surface: Surface,
                 visibility: torch.Tensor | None) -> torch.Tensor:
    """:func:`_direct` of one band of rows (the whole frame or part of it)."""
    if kind is DirectionalLights:
        l, e = directional_incidence(lights)  # type: ignore[arg-type]
    elif kind is PointLights:
        l, e = point_incidence(lights, position)  # type: ignore[arg-type]
    elif kind is AreaLights:  # its vector irradiance L |Phi| along Phi: exact for Lambert
        l, e, spread = area_incidence(lights, position)  # while the light is above the
        e = e * spread  # horizon (fluence L Omega times |Phi| / Omega)
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


def cook_torrance_lights(
    kind: type,
    lights: DirectionalLights | PointLights | SpotLights,
    item: int,
    position: torch.Tensor,
    normal: torch.Tensor,
    view: torch.Tensor,
    albedo: torch.Tensor,
    metallic: torch.Tensor,
    roughness: torch.Tensor,
    visibility: torch.Tensor | None = None,
    multiscatter: bool = True,
) -> torch.Tensor:
    """Sum over the L lights of batch item ``item`` of the Cook-Torrance BRDF times the
    cosine and the illuminance, at M packed pixels of that item: the fused form of ``_direct`` with
    :func:`~torchraster.shading.models.cook_torrance` (same formulas and floors as
    :func:`~torchraster.shading.brdf.cook_torrance` and the light functions of
    :mod:`~torchraster.shading.lights`).

    Lights stay a tensor dimension and colour is applied last: with ``w = E max(n.l, 0)``
    (E the scalar attenuation x visibility), ``s1 = D V w`` and ``s2 = s1 (1 - v.h)^5``,
    ``radiance = kd (C^T w) + f0 (C^T s1) + (1 - f0) (C^T s2)`` where C (L, 3) is colour x
    intensity, three small matmuls instead of per-light RGB tensors. Terms that do not
    depend on the light (f0, kd, the view half of the Smith term) are computed once per
    pixel. Pixel-lights the light cannot reach (n.l <= 0, outside the range or cone,
    visibility 0) contribute exactly 0 (also to gradients); when fewer than
    :data:`SPARSE_FRACTION` are reached, the BRDF is evaluated at those only.

    Args:
        kind: ``DirectionalLights``, ``PointLights`` or ``SpotLights``.
        lights: that kind's lights, ``(B, L, ...)``.
        item: the batch item whose lights shade these pixels.
        position, normal, view: ``(3, M)`` world position, unit normal, unit direction to
            the eye.
        albedo: ``(3, M)``; metallic, roughness: ``(1, M)``.
        visibility: ``(L, M)`` fraction of each light reaching each pixel, or None.
        multiscatter: energy compensation (specular x ``spec_scale``, diffuse x
            ``diffuse_scale`` of :func:`~torchraster.shading.energy.energy_terms`).

    Returns:
        ``(3, M)`` outgoing radiance.
    """
    if kind is AreaLights:  # linearly transformed cosines (shading/area.py)
        return area_lights(lights, item, position, normal, view, albedo, metallic, roughness,
                           visibility, multiscatter)
    n_v = (normal * view).sum(0, keepdim=True)  # (1, M)
    nv = n_v.clamp(MIN_COS, 1.0)
    r = roughness.clamp(MIN_ROUGHNESS, 1.0)
    a = r * r
    a2 = a * a
    lam_v = torch.sqrt(torch.addcmul(a2, nv * nv, 1.0 - a2))
    f0, kd = specular_f0(albedo, metallic), diffuse_color(albedo, metallic)
    ms = None
    if multiscatter:  # Kulla-Conty / Fdez-Aguera energy terms (shading/energy.py)
        lut = dfg_lut(DFG_LUT_SIZE, DFG_LUT_SAMPLES, device=f0.device, dtype=f0.dtype)
        ms, kd_scale = energy_terms(f0, nv, r, lut)
        kd = kd * kd_scale
    color = lights.color[item] * lights.intensity[item][:, None]  # (L, 3)
    if kind is DirectionalLights:
        l = -safe_normalize(lights.direction[item], dim=-1)  # (L, 3)
        n_l = l @ normal  # (L, M)
        v_l = l @ view
        e = None
    else:
        lp = lights.position[item]  # (L, 3)
        to_light = lp[:, :, None] - position  # (L, 3, M)
        d2 = (to_light * to_light).sum(1)  # (L, M)
        ok = d2 > NORMALIZE_EPS  # a light at the surface point: l = 0 (finite gradients)
        inv_d = torch.rsqrt(d2.clamp_min(NORMALIZE_EPS)) * ok
        # n.(p_light - p) = n.p_light - n.p: one small matmul instead of a (L, 3, M) pass
        n_l = (lp @ normal - (normal * position).sum(0)) * inv_d
        v_l = (lp @ view - (view * position).sum(0)) * inv_d
        rng = lights.range[item][:, None]
        if bool(torch.isinf(rng).all()):
            e = 1.0 / d2.clamp_min(MIN_LIGHT_DISTANCE**2)  # no range window
        else:
            e = distance_attenuation(d2, rng)
        if kind is SpotLights:
            axis = safe_normalize(lights.direction[item], dim=-1)  # (L, 3)
            cos_angle = ((axis * lp).sum(1, keepdim=True) - axis @ position) * inv_d
            e = e * spot_attenuation(-cos_angle, lights.inner_cone_angle[item][:, None],
                                     lights.outer_cone_angle[item][:, None])
    if visibility is not None:
        e = visibility if e is None else e * visibility
    w = n_l.clamp(0.0, 1.0)
    if e is not None:
        w = w * e
    reached = w > 0
    count = int(reached.sum())
    if count == 0:  # no light reaches: 0, still connected to the inputs (zero gradients)
        return albedo * 0.0 + w.sum() * 0.0 if torch.is_grad_enabled() else torch.zeros_like(
            albedo)
    v_l = v_l.expand_as(w)
    n_l = n_l.expand_as(w)
    if count < SPARSE_FRACTION * w.numel():  # evaluate the BRDF where it matters only
        idx = reached.reshape(-1).nonzero().squeeze(1)
        pix = idx % w.shape[1]
        per_pixel = [t[0].index_select(0, pix) for t in (n_v, nv, a, a2, lam_v)]
        s1, s2 = _ct_lobe(*(t.reshape(-1).index_select(0, idx) for t in (n_l, v_l, w)),
                          *per_pixel)
        s1 = w.new_zeros(w.numel()).index_put((idx,), s1).view(w.shape)
        s2 = w.new_zeros(w.numel()).index_put((idx,), s2).view(w.shape)
    else:
        s1, s2 = _ct_lobe(n_l, v_l, w, n_v, nv, a, a2, lam_v)
    c_t = color.T  # (3, L)
    # D and V carry 1 / pi and 1 / 2 (folded in here), and kd its 1 / pi
    spec = f0 * (c_t @ s1) + (1.0 - f0) * (c_t @ s2)
    if ms is not None:
        spec = spec * ms
    return (kd * (c_t @ w) + 0.5 * spec) * (1.0 / math.pi)


def _ct_lobe(n_l, v_l, w, n_v, nv, a, a2, lam_v):
    """Specular lobe weights of :func:`cook_torrance_lights` (any broadcastable shapes):
    ``s1 = pi D 2 V w`` and ``s2 = s1 (1 - v.h)^5`` (the constants pi and 2 are applied by the
    caller), as in :func:`~torchraster.shading.brdf.cook_torrance`: half-vector cosines
    without forming h (|v + l|^2 = 2 + 2 v.l, 0 for v = -l), GGX D (0 for n.h <= 0),
    height-correlated Smith V with the cosines floored at MIN_COS, Schlick's (1 - v.h)^5.
    ``n_v``: n.v; ``nv``: n.v floored; ``a``, ``a2``: GGX alpha and its square;
    ``lam_v``: sqrt((n.v)^2 (1 - a2) + a2)."""
    len2 = 2.0 + 2.0 * v_l
    inv_len = torch.rsqrt(len2.clamp_min(NORMALIZE_EPS)) * (len2 > NORMALIZE_EPS)
    n_h = (n_l + n_v) * inv_len
    v_h = (1.0 + v_l) * inv_len
    d = ggx_lobe(n_h, a, a2)  # pi D
    nl = n_l.clamp(MIN_COS, 1.0)
    g = torch.addcmul(nl * lam_v, nv, torch.sqrt(torch.addcmul(a2, nl * nl, 1.0 - a2)))
    s1 = d * w / g
    return s1, s1 * schlick_weight(v_h)


def _pack_item(item, covered, dt, position, normal, albedo, metallic, roughness,
               camera_position):
    """Batch item ``item``: (covered pixel indices (M,) or None for all, then packed
    position, unit normal, unit view direction, albedo ``(3, M)``, metallic, roughness
    ``(1, M)`` in ``dt``). Only covered pixels are read, so garbage in empty G-buffer pixels
    cannot reach values or gradients."""
    _, _, h, w = position.shape
    flat = [t[item].reshape(t.shape[1], h * w)
            for t in (position, normal, albedo, metallic, roughness)]
    sel = None
    if covered is not None:
        sel = covered[item].reshape(-1).nonzero().squeeze(1)
        flat = [t.index_select(1, sel) for t in flat]
    return _item_surface(item, sel, flat, dt, camera_position)


def _item_surface(item, sel, flat, dt, camera_position):
    """:func:`_pack_item`'s tuple from the item's packed ``flat`` channels (position,
    normal, albedo, metallic, roughness): (sel, position, normal (not yet unit), eye
    ``(3, 1)``, albedo, metallic, roughness); :func:`_unit_nv` makes n and v."""
    # half precision: shaded in float32, gradients back saturated (to_compute)
    pos, nrm, base, metal, rough = (to_compute(t, dt) for t in flat)
    return sel, pos, nrm, camera_position[item].to(dt)[:, None], base, metal, rough


def _unit_nv(pos, nrm, eye):
    """Unit normal and unit direction to the eye ``(3, M)`` of packed pixels."""
    return safe_normalize(nrm, dim=0), safe_normalize(eye - pos, dim=0)


def _lit_chunk(kind, lights, item, pos, nrm, eye, base, metal, rough, vis, multiscatter):
    """:func:`cook_torrance_lights` of packed pixels from their raw normal and the eye (the
    unit vectors made inside: a checkpoint of this keeps only its inputs, memory)."""
    n, v = _unit_nv(pos, nrm, eye)
    return cook_torrance_lights(kind, lights, item, pos, n, v, base, metal, rough, vis,
                                multiscatter=multiscatter)


def _pack_items(covered, dt, position, normal, albedo, metallic, roughness, camera_position):
    """:func:`_pack_item` of every batch item, a list."""
    return [_pack_item(item, covered, dt, position, normal, albedo, metallic, roughness,
                       camera_position) for item in range(position.shape[0])]


def _fused_direct(kind, lights, packed, vis, use_ckpt, acc, multiscatter=True, done=None):
    """Add one chunk of lights of ``kind`` to the packed radiance ``acc`` (a list of
    ``(3, M)`` per batch item, None until lit) through :func:`cook_torrance_lights`, in
    chunks of about :data:`PIXEL_LIGHT_CHUNK` pixel-lights, each recomputed in backward
    when ``use_ckpt``. ``packed(item)``: the item's :func:`_pack_item` tuple; ``done(item)``
    (or None) is called once the item is lit. ``vis``: ``(B, L, 1, H, W)`` visibility or
    None."""
    per = PIXEL_LIGHT_CHUNK * (GRAD_CHUNK_FACTOR if torch.is_grad_enabled() else 1)
    cost = lights.count * (AREA_LIGHT_COST if kind is AreaLights else 1)
    per = max(1024, per // max(1, cost))
    for item in range(len(acc)):
        sel, *attrs = packed(item)
        if attrs[0].shape[1] > 0:
            vis_i = None
            if vis is not None:
                vis_i = vis[item].reshape(vis.shape[1], -1)
                vis_i = vis_i if sel is None else vis_i.index_select(1, sel)
            _fused_item(kind, lights, item, attrs, vis_i, per, use_ckpt, acc, multiscatter)
        del sel, attrs
        if done is not None:
            done(item)


class _RecomputedChunk(torch.autograd.Function):
    """:func:`_lit_chunk` evaluated without a graph, recomputed with one in backward (a
    checkpoint whose forward records no autograd nodes: those small, long-lived objects,
    kept until backward between the chunk's large temporaries, stopped malloc from reusing
    the freed temporaries, so resident memory grew chunk after chunk). ``tensors``: the
    lights' tensor fields, then the chunk's inputs."""

    @staticmethod
    def forward(ctx, run, n_light, *tensors):
        ctx.run, ctx.n_light = run, n_light
        ctx.save_for_backward(*tensors)
        with torch.no_grad():
            return run(tensors[:n_light], *tensors[n_light:])

    @staticmethod
    def backward(ctx, grad):
        # create_graph (grad mode on here): the recomputation from the inputs themselves, so
        # the gradients stay functions of them (second derivatives); else detached copies
        double = torch.is_grad_enabled()
        tensors = list(ctx.saved_tensors) if double else [
            t.detach().requires_grad_(t.requires_grad) for t in ctx.saved_tensors]
        with torch.enable_grad():
            out = ctx.run(tensors[:ctx.n_light], *tensors[ctx.n_light:])
        wrt = [t for t in tensors if t.requires_grad]
        got = iter(torch.autograd.grad(out, wrt, grad, allow_unused=True,
                                       create_graph=double) if wrt else ())
        return (None, None) + tuple(next(got) if t.requires_grad else None for t in tensors)


def _recomputed_chunk(kind, lights, item, pos, nrm, eye, base, metal, rough, vis,
                      multiscatter):
    """:func:`_lit_chunk` through :class:`_RecomputedChunk` (gradients to every input and
    light tensor)."""
    fields = [f.name for f in dataclasses.fields(lights) if isinstance(
        getattr(lights, f.name), torch.Tensor)]
    inputs = [pos, nrm, eye, base, metal, rough] + ([] if vis is None else [vis])

    def run(light_tensors, *xs):
        part = dataclasses.replace(lights, **dict(zip(fields, light_tensors, strict=True)))
        return _lit_chunk(kind, part, item, *xs[:6], xs[6] if len(xs) > 6 else None,
                          multiscatter)

    return _RecomputedChunk.apply(run, len(fields), *[getattr(lights, f) for f in fields],
                                  *inputs)


def _fused_item(kind, lights, item, attrs, vis_i, per, use_ckpt, acc, multiscatter):
    """:func:`_fused_direct` of one batch item: its packed ``attrs`` (position, raw normal,
    eye, albedo, metallic, roughness), visibility ``(L, M)`` or None, pixel chunks of
    ``per``. Checkpointed chunks make n and v inside (backward keeps only the inputs)."""
    pos, nrm, eye, base, metal, rough = attrs
    m = pos.shape[1]
    inplace = not torch.is_grad_enabled()  # no graph: add each chunk in place
    if inplace and acc[item] is None:
        acc[item] = pos.new_zeros(3, m)
    if not use_ckpt:  # once for the item
        n, v = _unit_nv(pos, nrm, eye)
    parts = []
    for s0 in range(0, m, per):
        cut = slice(s0, s0 + per)
        vis = None if vis_i is None else vis_i[:, cut]
        if use_ckpt:
            rad = _recomputed_chunk(kind, lights, item, pos[:, cut], nrm[:, cut], eye,
                                    base[:, cut], metal[:, cut], rough[:, cut], vis,
                                    multiscatter)
        else:
            rad = cook_torrance_lights(kind, lights, item, pos[:, cut], n[:, cut], v[:, cut],
                                       base[:, cut], metal[:, cut], rough[:, cut], vis,
                                       multiscatter=multiscatter)
        if inplace:
            acc[item][:, s0:s0 + per] += rad
        else:
            parts.append(rad)
    if not inplace:
        rad = torch.cat(parts, 1) if len(parts) > 1 else parts[0]
        acc[item] = rad if acc[item] is None else acc[item] + rad


def _scatter_item(frame, item, sel, rad):
    """Write item ``item``'s packed radiance ``rad`` ``(3, M)`` (None: unlit) into ``frame``
    ``(B, 3, H * W)`` at its pixels ``sel`` (None: all), in place (no autograd graph)."""
    if rad is None:
        return
    if sel is None:
        frame[item].copy_(rad)
    else:
        frame[item].index_copy_(1, sel, rad)


class _UnpackItems(torch.autograd.Function):
    """``(B, 3, H, W)`` frame of zeros with item i's packed radiance ``rads[i]`` ``(3, M_i)``
    written at its pixels ``sels[i]`` (None: all), in place into one frame. Backward: item
    i's gradient gathered at its pixels; only the indices are saved (memory: indexed
    assignment into views of one frame made autograd clone the whole frame's gradient
    once per item, a frame-sized copy each)."""

    @staticmethod
    def forward(ctx, shape, sels, *rads):
        b, _, h, w = shape
        frame = rads[0].new_zeros(b, 3, h * w)
        for item, (sel, rad) in enumerate(zip(sels, rads, strict=True)):
            if sel is None:
                frame[item].copy_(rad)
            else:
                frame[item].index_copy_(1, sel, rad)
        ctx.save_for_backward(*(s for s in sels if s is not None))
        ctx.all_pixels = [s is None for s in sels]
        ctx.set_materialize_grads(False)
        return frame.view(b, 3, h, w)

    @staticmethod
    def backward(ctx, grad):
        if grad is None:
            return (None, None) + (None,) * len(ctx.all_pixels)
        b, _, h, w = grad.shape
        flat = grad.reshape(b, 3, h * w)
        saved = iter(ctx.saved_tensors)
        return (None, None) + tuple(flat[i] if whole else flat[i].index_select(1, next(saved))
                                    for i, whole in enumerate(ctx.all_pixels))


def _unpack_items(acc, packed, shape, like):
    """``(B, 3, H, W)`` image of packed per-item radiance (0 at uncovered pixels), recorded
    by autograd (without a graph, :func:`shade` scatters into one frame in place)."""
    b, _, h, w = shape
    sels, rads = [], []
    for rad, (sel, *attrs) in zip(acc, packed, strict=True):
        if rad is None:  # unlit: 0, still connected to the inputs (zero gradients)
            m = h * w if sel is None else sel.numel()
            rad = (sum(t.sum() for t in attrs) * 0.0).to(like.dtype).expand(3, m)
        sels.append(sel)
        rads.append(rad)
    return _UnpackItems.apply(shape, sels, *rads)


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
    multiscatter: bool = True,
    reuse_albedo: bool = False,
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
        ibl: optional ``ibl(surface) -> (B, 3, H, W)`` radiance from an environment (before
            AO), given the frame's :class:`~torchraster.shading.surface.PixelSurface` (unit
            ``n``, ``v`` towards the eye, material, f0, ...), e.g. ``lambda s:
            shade_ibl(s.n, s.v, s.albedo, s.metallic, s.roughness, None, env)``.
        visibility: optional ``visibility(kind, lights) -> (B, L, 1, H, W)`` (or None for
            unshadowed), called per chunk of lights of ``kind`` (``"directional"``,
            ``"point"``, ``"spot"``, ``"area"``) with the slice of light indices: the fraction
            of each light that reaches each pixel (e.g. shadow maps). Multiplies the
            illuminance.
        light_chunk: lights evaluated at once (default: from LIGHT_CHUNK_ELEMENTS).
            ``1`` is the plain Python loop over lights.
        checkpoint_chunks: recompute chunks in backward (default: when autograd is on
            and there is more than one chunk).
        multiscatter: multiple-scattering energy compensation of the Cook-Torrance
            specular and the matching diffuse reduction, for punctual and ambient light
            (:mod:`torchraster.shading.energy`; the ``ibl`` hook applies its own, e.g.
            ``shade_ibl(multiscatter=...)``). False: the single-scattering BRDF of
            :func:`~torchraster.shading.brdf.cook_torrance`. Other shading models ignore it.
        reuse_albedo: the radiance may be written into ``gbuffer.albedo``'s frame (memory:
            one frame fewer) when nothing reads that albedo after this call. Taken only
            without autograd, on the Cook-Torrance pass that packs, lights and writes one
            batch item at a time (no ambient or IBL light, which read the frame later), for
            a 3-channel albedo in the shading dtype whose pixels are rows of one frame
            (not expanded); otherwise ignored.

    Returns:
        ``(B, 3, H, W)`` linear HDR radiance, 0 where ``mask`` is 0, in the G-buffer's
        dtype (float16 / bfloat16 inputs are shaded in float32 and saturated on output).

    Example:
        >>> from torchraster.shading.lights import DirectionalLights, Lights
        >>> z, one = torch.tensor([0.0, 0, 1]).view(1, 3, 1, 1), torch.ones(1, 1, 2, 2)
        >>> gb = GBuffer(position=0 * z * one, normal=z * one, albedo=one.expand(1, 3, 2, 2),
        ...              metallic=0 * one, roughness=one)
        >>> sun = DirectionalLights(direction=torch.tensor([[[0.0, 0, -1]]]),
        ...                         color=torch.ones(1, 1, 3), intensity=torch.ones(1, 1))
        >>> rad = shade(gb, camera_position=torch.tensor([[0.0, 0, 1]]),
        ...             lights=Lights(directional=sun), model="half_lambert")
        >>> rad.shape, rad[0, :, 0, 0]  # albedo / pi * 1 lux, the sun straight above
        (torch.Size([1, 3, 2, 2]), tensor([0.3183, 0.3183, 0.3183]))
    """
    if not isinstance(gbuffer, GBuffer):
        raise TypeError(f"gbuffer: expected a torchraster.GBuffer, got {type(gbuffer).__name__}"
                        " (build one with GBuffer(position=..., normal=..., ...))")
    gbuffer.require("position", "normal", "albedo", "metallic", "roughness", by="shade")
    store = gbuffer.packed  # channels held packed (covered pixels only), or None
    if store is not None and gbuffer.mask is None:
        raise ValueError("gbuffer: a GBuffer with packed channels needs its mask channel")
    b, _, h, w = (gbuffer.position if gbuffer.position is not None else gbuffer.mask).shape
    if store is not None:  # ao and emissive are applied to frames: made here
        gbuffer = gbuffer.replace(**{ch: store.image(ch, (b, h, w)) for ch in (
            "ao", "emissive") if getattr(gbuffer, ch) is None and ch in store.values})
    surface_names = ("position", "normal", "albedo", "metallic", "roughness")
    position, normal, albedo, metallic, roughness = (getattr(gbuffer, ch)
                                                      for ch in surface_names)
    ao, emissive, mask = gbuffer.ao, gbuffer.emissive, gbuffer.mask
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

    inputs = [getattr(gbuffer, ch) if getattr(gbuffer, ch) is not None else store.values[ch]
              for ch in surface_names] + [camera_position]
    inputs += [t for t in (ao, emissive) if t is not None]
    out_dtype = inputs[0].dtype
    for t in inputs[1:]:
        out_dtype = torch.promote_types(out_dtype, t.dtype)
    dt = torch.float32 if out_dtype in LOW_PRECISION else out_dtype
    dev = mask.device if position is None else position.device

    covered = None if mask is None else (mask > 0)

    def prep(t: torch.Tensor) -> torch.Tensor:
        # Zero uncovered pixels *before* any op ("double where"): garbage (NaN/Inf) in empty
        # G-buffer pixels can then not leak into values or gradients.
        t = to_compute(t, dt)  # half precision: gradients back saturated
        return t if covered is None else torch.where(covered, t, 0.0)

    lights = lights.to(device=dev, dtype=dt)
    kinds = [(kind, part) for kind, part in ((DirectionalLights, lights.directional),
                                             (PointLights, lights.point),
                                             (SpotLights, lights.spot),
                                             (AreaLights, lights.area))
             if part is not None and part.count > 0]
    # The fused Cook-Torrance pass works on the covered pixels only, packed once per frame;
    # the full-frame tensors are built only for other models, ambient light and IBL.
    fused = shading_model is _cook_torrance_model
    full_frame = (kinds and not fused) or lights.ambient is not None or ibl is not None
    if full_frame and store is not None:  # frames of the packed channels
        position, normal, albedo, metallic, roughness = (
            store.image(ch, (b, h, w)) if t is None else t for ch, t in zip(
                surface_names, (position, normal, albedo, metallic, roughness), strict=True))
        store = None
    if full_frame:  # the per-pixel surface, built once for every light, ambient and IBL
        pos, nrm, base, metal, rough = (prep(t) for t in (position, normal, albedo, metallic,
                                                           roughness))
        surf = pixel_surface(safe_normalize(nrm),
                             safe_normalize(camera_position.to(dt)[:, :, None, None] - pos),
                             albedo=base, metallic=metal, roughness=rough)
    no_grad = not torch.is_grad_enabled()  # no graph: the frame is finished in place

    # Direct light: lights as a tensor dimension, in chunks.
    per_chunk = light_chunk or max(1, LIGHT_CHUNK_ELEMENTS // max(1, b * h * w))
    if fused and light_chunk is None and visibility is None:
        per_chunk = max(part.count for _, part in kinds) if kinds else 1  # memory: per pixel chunk
    fused_direct = fused and bool(kinds)
    # the fused pass writes its own frame; the others add to zeros
    radiance = None if fused_direct else torch.zeros(b, 3, h, w, device=dev, dtype=dt)
    items: dict[int, tuple] = {}  # batch item -> its _pack_item tuple, packed on first use
    acc: list[torch.Tensor | None] = [None] * b
    # memory: with one pass over the lights and no graph, each item is packed, lit and
    # written to the frame in turn (its packed copies are dropped before the next one)
    one_pass = fused_direct and no_grad and sum(len(_chunks(part.count, per_chunk))
                                                for _, part in kinds) == 1
    frame = None
    if one_pass and reuse_albedo and not full_frame and albedo is not None and (
            albedo.shape[1] == 3) and (
            albedo.dtype == dt and albedo.stride(3) == 1 and albedo.stride(2) == w
            and min(albedo.stride()) > 0 and not albedo.requires_grad):  # rows of pixels
        # item i's albedo is packed (copied) before item i's radiance overwrites it, and the
        # uncovered pixels are zeroed below (an item without light keeps its albedo there)
        frame = albedo.view(b, 3, h * w)
    elif fused_direct and no_grad:
        frame = torch.zeros(b, 3, h * w, device=dev, dtype=dt)

    n_covered = b * h * w if covered is None else int(covered.sum())
    pieces = starts = None
    if store is not None:  # each item's columns of the packed channels (views)
        starts = store.item_starts(b, h, w)
        if starts[-1] != n_covered or starts[0] != 0:
            raise ValueError(f"gbuffer.packed: {store.pixels.numel()} pixels of which "
                             f"{starts[-1] - starts[0]} in the frame, but the mask covers "
                             f"{n_covered}")
        counts = [e - s for s, e in zip(starts[:-1], starts[1:], strict=True)]
        pieces = [store.values[ch].split(counts, dim=1) if t is None else None
                  for ch, t in zip(surface_names, (position, normal, albedo, metallic,
                                                   roughness), strict=True)]

    def packed(item: int) -> tuple:
        if item in items:
            return items[item]
        if pieces is None:
            items[item] = _pack_item(item, covered, dt, position, normal, albedo, metallic,
                                     roughness, camera_position)
            return items[item]
        sel = store.pixels[starts[item]:starts[item + 1]] - item * h * w
        flat = [p[item] if p is not None else t[item].reshape(t.shape[1], h * w).index_select(
            1, sel) for p, t in zip(pieces, (position, normal, albedo, metallic, roughness),
                                    strict=True)]
        items[item] = _item_surface(item, sel, flat, dt, camera_position)
        return items[item]

    def done(item: int) -> None:
        _scatter_item(frame, item, items.pop(item)[0], acc[item])
        acc[item] = None

    for kind, part in kinds:
        name = {DirectionalLights: "directional", PointLights: "point", SpotLights: "spot",
                AreaLights: "area"}[kind]
        # the other models' area lights hold (B, L, K, 3, H, W) polygons: K times fewer
        slices = _chunks(part.count, per_chunk if fused or kind is not AreaLights
                         else max(1, per_chunk // polygon_sides(part)))
        use_ckpt = checkpoint_chunks
        if use_ckpt is None:
            if fused:  # recompute pixel chunks in backward when there are several: the
                # graph then holds the chunks' inputs, not their ~30 temporaries (memory:
                # docs/benchmarks.md, section memory)
                use_ckpt = torch.is_grad_enabled() and (
                    min(per_chunk, part.count) * n_covered > PIXEL_LIGHT_CHUNK * GRAD_CHUNK_FACTOR)
            else:
                use_ckpt = torch.is_grad_enabled() and len(slices) > 1
        for sl in slices:
            chunk = part if len(slices) == 1 else part.select(sl)
            vis = visibility(name, sl) if visibility is not None else None
            if vis is not None:
                check_tensor(f"visibility({name!r}) result", vis,
                             (b, chunk.count, 1, h, w), floating=True)
                vis = vis.to(dt)
            if fused:
                _fused_direct(kind, chunk, packed, vis, use_ckpt, acc, multiscatter,
                              done if one_pass else None)
                continue
            surface = Surface(albedo=surf.albedo[:, None], metallic=surf.metallic[:, None],
                              roughness=surf.roughness[:, None])
            args = (shading_model, kind, chunk, pos, surf.n[:, None], surf.v[:, None], surface,
                    vis)
            if use_ckpt:
                radiance = radiance + checkpoint(_direct, *args, use_reentrant=False)
            else:
                radiance = radiance + _direct(*args)
    if fused_direct:
        if frame is not None:
            for item in list(items):
                done(item)
            radiance = frame.view(b, 3, h, w)
        else:
            radiance = _unpack_items(acc, [packed(i) for i in range(b)], (b, 3, h, w),
                                     camera_position.new_zeros((), dtype=dt))
        items.clear()  # memory: the packed copies are not needed past this point
        acc.clear()

    # Ambient (SH) and image-based light, scaled by AO.
    indirect = None
    if lights.ambient is not None:
        r = 2.0 * surf.n_dot_v * surf.n - surf.v  # reflect(-v, n)
        e_n = sh_irradiance(lights.ambient, surf.n).clamp_min(0.0)
        e_r = sh_irradiance(lights.ambient, r).clamp_min(0.0)
        kd = surf.diffuse * e_n
        spec = env_brdf(surf.f0, surf.roughness, surf.n_dot_v) * e_r
        if multiscatter:  # the same energy terms as punctual lights (shading/energy.py)
            ms, kd_scale = surf.energy(dfg_lut(DFG_LUT_SIZE, DFG_LUT_SAMPLES,
                                               device=dev, dtype=dt))
            kd, spec = kd * kd_scale, spec * ms
        indirect = (kd + spec) / torch.pi
    if ibl is not None:
        env = ibl(surf)
        check_tensor("ibl(...) result", env, (b, 3, h, w), floating=True)
        env = env.to(dt)
        indirect = env if indirect is None else indirect + env
    if indirect is not None:
        if ao is not None:
            indirect = indirect * prep(ao)
        radiance = radiance.add_(indirect) if no_grad else radiance + indirect

    # Without a graph, in place (no extra frames); uncovered pixels are zeroed below, so
    # emissive is not masked first (the covered pixels get the same sums)
    if emissive is not None and no_grad:
        radiance.add_(emissive.to(dt))
    elif emissive is not None:
        radiance = radiance + prep(emissive)
    if covered is not None and no_grad:
        radiance.masked_fill_(~covered, 0.0)
    elif covered is not None and not (fused_direct and indirect is None):
        # (the fused pass writes covered pixels only, into zeros, and emissive was masked by
        # prep: no masked copy)
        radiance = torch.where(covered, radiance, 0.0)
    return finish_low_precision(radiance, out_dtype)
