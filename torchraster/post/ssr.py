"""Screen-space reflections (SSR) on a G-buffer: hierarchical depth march, IBL fallback.

For every covered pixel whose roughness is below ``max_roughness`` the mirror direction
``R = reflect(V, N)`` (view space, OpenGL: x right, y up, camera looking down -z) is traced
in screen space through the depth buffer; where it hits, the lit image seen there replaces
the environment's (IBL / ambient) specular radiance of the pixel.

* **Ray setup.** The view-space ray ``P0 + t R`` is clipped (Liang-Barsky) to the view
  frustum's four side planes and to the depth range of the frame (nothing nearer than the
  nearest covered pixel or farther than the farthest plus ``thickness`` can be hit). Its end
  points are projected; screen position and inverse depth ``1 / d`` are then both linear in
  one parameter ``s`` in [0, 1] (perspective-correct depth along the screen segment,
  McGuire & Mara 2014, "Efficient GPU Screen-Space Ray Tracing").
* **Hierarchical march** (Uludag 2014, "Hi-Z Screen-Space Cone-Traced Reflections", GPU Pro
  5, with a min-max chain): level ``l`` of the chain holds the nearest and farthest depth of
  each ``2^l x 2^l`` pixel cell (``max_pool2d``). Each step takes the ray's cell at its
  current level and the segment of the ray inside it; if the ray's depth range there misses
  ``[min, max + thickness]`` (the ray passes in front of everything, or behind everything by
  more than ``thickness``), the ray skips the whole cell and goes one level up; else it first
  advances to the cell's nearest depth if it enters the cell in front of it, and goes one
  level down; at level 0 an overlap is a hit candidate. All rays step at once (packed
  tensors; finished rays are dropped) and the march ends when every ray has finished: hit,
  or missed (its segment ended: it left the frame or the depth range, reached
  ``max_distance``; a ray never goes behind the camera, its segment is clipped in front).
  Every advance ends strictly further on (the nudge), so a ray takes at most
  :func:`march_step_bound` ``(H, W)`` steps; ``max_steps`` only caps rays still going
  then (misses). Rays skimming a large plane (a floor seen at a low angle) go down to level
  0 often: they cost the most.
* **Hit tests.** A candidate is rejected (the march goes on) when the pixel's surface point
  lies on or below the tangent plane of the ray's origin (a mirror ray leaves that plane
  and never comes back to it: no self-intersection on planes, no false hits on the
  surface the ray starts from) or faces away from the ray (its back side is not in the
  depth buffer).
* **Binary refinement.** ``refine_steps`` bisections of the hit cell's segment against the
  bilinearly interpolated depth buffer place the hit to a fraction of a pixel.
* **Surface-only reads.** At level 0 the bilinear colour read keeps only the texels of the
  surface hit (facing the ray, within ``thickness`` of the hit depth), so silhouettes and
  creases do not bleed; a hit with less than half of its read on that surface
  (:data:`MIN_COVERAGE`) is a miss.
* **Cone blur.** The hit colour is read from a mip pyramid of the (coverage-premultiplied)
  lit image at the level of the reflection cone's footprint: half-angle ``2 atan(0.6436
  alpha)`` (where the GGX distribution falls to half its peak, tan^2 = alpha^2 (sqrt 2 - 1),
  doubled for the reflected lobe) times the screen distance travelled (Uludag 2014).
  Roughness 0 reads level 0 bilinearly.
* **Confidence** in [0, 1]: 0 where the ray misses (leaves the frame, ends behind
  everything, runs out of steps), faded to 0 over ``edge_fade`` of the image size at the
  screen border and over the last quarter of ``[0, max_roughness]``.

**Compositing without double counting.** The lighting pass has already put the
environment's specular into the image: ``W * L_env`` with ``W`` the split-sum weight of the
Cook-Torrance lobe (Karis 2013; ``f0 A + f90 B`` times the multiple-scattering factor
``1 + f0 (1 / (A + B) - 1)``, f0 = ``mix(0.04, albedo, metallic)`` as everywhere, the
formula and table of :func:`~torchraster.shading.ibl.shade_ibl`). SSR replaces that term
where it hits::

    out = image + confidence * (W * L_ssr - fallback)

``fallback`` is the specular radiance already in the image (the renderer passes
``W * ao * L_env``, :func:`environment_specular`); None means 0 (reflections are added). At
confidence 1 the pixel's environment specular is exactly replaced by ``W * L_ssr``, at 0
it is untouched, in between blended. The hit radiance is not multiplied by AO (the ray
found the occluder itself). Differentiable with respect to the image (hit colours and the
composite), albedo, metallic, ``fallback`` and roughness (through ``W``, the cone-blur
level of the hit colour and the confidence fade); the march itself is discrete.
"""

from __future__ import annotations

import inspect
import math
import operator
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from .._validate import check_bool, check_float, check_tensor
from ..numerics import compute_dtype, safe_normalize, smoothstep, specular_f0
from ..shading.ibl import MIN_N_DOT_V, Environment, dfg_lut, lookup_dfg, shade_ibl
from ..texture import build_mip_pyramid
from .ssao import camera_intrinsics

#: Screen-space nudge (pixels) along the ray's direction when finding the cell it is in, so a
#: ray sitting exactly on a cell boundary is placed in the cell ahead.
NUDGE_PX = 1e-2
#: A candidate hit whose surface point is closer than this many pixel footprints to the
#: ray origin's tangent plane is the origin's own surface (rejected).
PLANE_TOL_PX = 0.25
#: Depth substituted for empty pixels in bilinear depth lookups (in front of it = no hit).
FAR_DEPTH = 1e10
#: A hit whose colour lookup has less coverage than this (bilinear weight of the texels of
#: the hit surface) lies outside that surface's silhouette: a miss. 0.5 puts the
#: silhouette half-way between a covered and an uncovered pixel centre.
MIN_COVERAGE = 0.5
#: Largest accepted ``max_steps`` (the march ends when every ray has finished, after at most
#: :func:`march_step_bound` steps: 2^20 covers frames up to 2^17 pixels on a side).
MAX_STEPS = 1 << 20
#: Largest accepted ``refine_steps`` (each halves the hit segment: 64 exhaust float64).
MAX_REFINE_STEPS = 64
#: Half-maximum tangent of GGX: D(theta_h) = D(0) / 2 at tan(theta_h) = alpha sqrt(sqrt 2 - 1).
GGX_HALF_MAX_TAN = math.sqrt(math.sqrt(2.0) - 1.0)

_IBL = inspect.signature(shade_ibl).parameters
_LUT_SIZE, _LUT_SAMPLES = _IBL["lut_size"].default, _IBL["lut_samples"].default


class SSRMaps(NamedTuple):
    """What :meth:`SSR.forward` returns with ``return_maps=True``.

    Attributes:
        image: ``(B, 3, H, W)`` the image with reflections composited.
        reflection: ``(B, 3, H, W)`` radiance seen along the reflected ray (0 where missed).
        confidence: ``(B, 1, H, W)`` in [0, 1] (0 where missed or not marched).
        weight: ``(B, 3, H, W)`` split-sum specular weight ``W`` (0 where confidence is 0).
    """

    image: torch.Tensor
    reflection: torch.Tensor
    confidence: torch.Tensor
    weight: torch.Tensor


def march_step_bound(height: int, width: int) -> int:
    """Most march steps any ray of an ``height x width`` frame can take: ``2 (H + W + 3) + 1``.

    Each step either advances the ray to the exit of its cell (and goes a level up),
    descends a level, or ends it (hit or miss). An advance ends on a pixel-grid line the
    screen segment crosses further on (at most ``W + 1`` vertical and ``H + 1`` horizontal
    ones) or at the segment's end, so a ray advances at most ``H + W + 3`` times; it
    descends at most as often as it went up, and ends once. ``max_steps`` at or above this
    never cuts a ray short.
    """
    return 2 * (int(height) + int(width) + 3) + 1


def _check_steps(name: str, value: object, lo: int, hi: int) -> int:
    """``value`` as an int in ``[lo, hi]``, else a ValueError naming ``name``."""
    try:
        n = None if isinstance(value, bool) else operator.index(value)  # int-like, not 2.0
    except TypeError:
        n = None
    if n is None or not lo <= n <= hi:
        raise ValueError(f"{name}: expected an int in [{lo}, {hi}], got {value!r}")
    return n


def specular_weight(
    n_dot_v: torch.Tensor,
    albedo: torch.Tensor,
    metallic: torch.Tensor,
    roughness: torch.Tensor,
    multiscatter: bool = True,
) -> torch.Tensor:
    """Split-sum weight ``W`` of incoming specular radiance, as in ``shade_ibl``.

    ``W = (f0 A + f90 B) (1 + f0 (1 / (A + B) - 1))`` with the DFG table (A, B) of
    :func:`~torchraster.shading.ibl.dfg_lut` at ``shade_ibl``'s default size, f0 =
    ``mix(0.04, albedo, metallic)``, f90 = ``saturate(16.5 mean(f0))`` (Filament).

    Args:
        n_dot_v: ``(B, 1, H, W)`` cosine between normal and the direction to the eye.
        albedo: ``(B, 3, H, W)``; metallic, roughness: ``(B, 1, H, W)``.
        multiscatter: include the multiple-scattering factor (``shade_ibl(multiscatter=)``).

    Returns:
        ``(B, 3, H, W)``, dimensionless, in [0, 1].
    """
    f0 = specular_f0(albedo, metallic.clamp(0.0, 1.0))
    f90 = (f0.mean(1, keepdim=True) * (3 * 50.0 * 0.33)).clamp(0.0, 1.0)
    lut = dfg_lut(_LUT_SIZE, _LUT_SAMPLES, device=albedo.device, dtype=albedo.dtype)
    a, b = lookup_dfg(lut, n_dot_v.clamp(MIN_N_DOT_V, 1.0), roughness.clamp(0.0, 1.0))
    single = f0 * a + f90 * b
    if not multiscatter:
        return single
    return single * (1.0 + f0 * (1.0 / (a + b).clamp_min(1e-4) - 1.0))


def environment_specular(
    normal: torch.Tensor,
    view_dir: torch.Tensor,
    roughness: torch.Tensor,
    weight: torch.Tensor,
    ao: torch.Tensor | None = None,
    environment: Environment | None = None,
    ambient_sh: torch.Tensor | None = None,
) -> torch.Tensor:
    """The environment's specular radiance in a lit image: SSR's ``fallback``.

    ``weight * ao * (prefiltered(d, roughness) + E_ambient(r) / pi)``, r = reflect(-v, n),
    d = :func:`~torchraster.shading.ibl.dominant_direction` ``(n, r, roughness)``:
    the specular term of :func:`~torchraster.shading.ibl.shade_ibl` plus the specular of an
    SH ambient light (whose own table is finer; they differ by < 1 %).

    Args:
        normal, view_dir: ``(B, 3, H, W)`` world-space unit normal and direction to the eye.
        roughness: ``(B, 1, H, W)``; weight: ``(B, 3, H, W)`` from :func:`specular_weight`.
        ao: ``(B, 1, H, W)`` or None; environment: an Environment or None;
        ambient_sh: ``(B, 9, 3)`` SH radiance coefficients of an ambient light, or None.

    Returns:
        ``(B, 3, H, W)``.
    """
    from ..shading.ibl import dominant_direction
    from ..shading.lights import sh_irradiance

    n_dot_v = (normal * view_dir).sum(1, keepdim=True)
    r = 2.0 * n_dot_v * normal - view_dir
    incoming = torch.zeros_like(weight)
    if environment is not None:  # read where shade_ibl reads: the lobe's dominant direction
        rough = roughness.clamp(0.0, 1.0)
        incoming = incoming + environment.specular(dominant_direction(normal, r, rough), rough)
    if ambient_sh is not None:
        incoming = incoming + sh_irradiance(ambient_sh.to(r.dtype), r).clamp_min(0.0) / math.pi
    out = weight * incoming
    return out * ao if ao is not None else out


def _bilinear(flat: torch.Tensor, b: torch.Tensor, x: torch.Tensor, y: torch.Tensor,
              h: int, w: int, tap_weight=None) -> torch.Tensor:  # noqa: ANN001
    """Bilinear lookup in ``flat`` ``(B * h * w, C)`` at texel coordinates x, y ``(M,)``
    (texel centres at integers, clamped to the edge) of batch items ``b`` -> ``(M, C)``.
    ``tap_weight(texel indices (M,)) -> (M,)`` optionally scales each of the 4 taps."""
    x = x.clamp(0.0, w - 1.0)
    y = y.clamp(0.0, h - 1.0)
    x0, y0 = x.floor(), y.floor()
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0l, y0l = x0.long(), y0.long()
    x1l, y1l = (x0l + 1).clamp_max(w - 1), (y0l + 1).clamp_max(h - 1)
    base = b * (h * w)
    out = 0.0
    for yy, xx, wt in ((y0l, x0l, (1 - fx) * (1 - fy)), (y0l, x1l, fx * (1 - fy)),
                       (y1l, x0l, (1 - fx) * fy), (y1l, x1l, fx * fy)):
        tap = base + yy * w + xx
        if tap_weight is not None:
            wt = wt * tap_weight(tap)[:, None]
        out = out + flat.index_select(0, tap) * wt.to(flat.dtype)
    return out


def _min_max_chain(depth: torch.Tensor, valid: torch.Tensor, levels: int):
    """Flattened min / max depth chains of ``levels`` levels and their (offset, h, w)."""
    near = torch.where(valid, depth, torch.full_like(depth, math.inf))
    far = torch.where(valid, depth, torch.full_like(depth, -math.inf))
    mins, maxs = [near], [far]
    for _ in range(levels - 1):
        mins.append(-F.max_pool2d(-mins[-1], 2, ceil_mode=True))
        maxs.append(F.max_pool2d(maxs[-1], 2, ceil_mode=True))
    shapes = [m.shape[-2:] for m in mins]
    sizes = [m.numel() for m in mins]
    offsets = [0]
    for s in sizes[:-1]:
        offsets.append(offsets[-1] + s)
    cat_min = torch.cat([m.reshape(-1) for m in mins])
    cat_max = torch.cat([m.reshape(-1) for m in maxs])
    return cat_min, cat_max, offsets, shapes


def trace_reflections(
    image: torch.Tensor,
    depth: torch.Tensor,
    normals: torch.Tensor,
    roughness: torch.Tensor,
    intrinsics: torch.Tensor,
    *,
    max_steps: int = 64,
    thickness: float = 0.1,
    max_roughness: float = 0.6,
    edge_fade: float = 0.05,
    refine_steps: int = 4,
    max_distance: float = math.inf,
    blur: bool = True,
    stats: dict | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """March the mirror rays of a frame (see the module docstring).

    Args:
        image: ``(B, 3, H, W)`` lit radiance (read at the hits).
        depth: ``(B, 1, H, W)`` linear view depth; 0, negative or +inf = empty.
        normals: ``(B, 3, H, W)`` view-space normals (normalised here; flipped to face
            the camera).
        roughness: ``(B, 1, H, W)`` perceptual roughness.
        intrinsics: ``(B, 4)`` or ``(4,)`` fx, fy, cx, cy in pixels (pixel centres at
            integers, row 0 at the top).
        max_steps, thickness, max_roughness, edge_fade, refine_steps, max_distance, blur:
            as in :class:`SSR`.
        stats: optional dict, filled with ``"rays"`` (rays marched) and ``"steps"`` (march
            iterations run: the march ends when every ray has hit or missed, so this is
            at most :func:`march_step_bound` ``(H, W)`` whatever ``max_steps``).

    Returns:
        ``(reflection (B, 3, H, W), confidence (B, 1, H, W))``; both 0 where the ray missed
        or was not marched.
    """
    max_steps = _check_steps("max_steps", max_steps, 1, MAX_STEPS)
    refine_steps = _check_steps("refine_steps", refine_steps, 0, MAX_REFINE_STEPS)
    if stats is not None:
        stats.update(rays=0, steps=0)
    # the march is discrete (where a ray hits carries no gradient): its state is built from
    # detached geometry, so the in-place updates of the march never reach autograd
    depth, normals, intrinsics = depth.detach(), normals.detach(), intrinsics.detach()
    b, _, h, w = depth.shape
    dev, dt = depth.device, depth.dtype
    valid = torch.isfinite(depth) & (depth > 0)
    reflection = image.new_zeros(b, 3, h, w)
    confidence = depth.new_zeros(b, 1, h, w)
    march = valid & (roughness < max_roughness)
    idx = march.reshape(-1).nonzero().squeeze(1)  # (M,) into B*H*W
    if idx.numel() == 0:
        return reflection, confidence
    k = intrinsics.to(dt).reshape(-1, 4).expand(b, 4)
    hw = h * w
    bi, pix = idx // hw, idx % hw
    pi, pj = pix // w, pix % w
    fx, fy, cx, cy = (k[bi, c] for c in range(4))
    d0 = depth.reshape(-1)[idx]
    p0 = torch.stack([d0 * (pj - cx) / fx, -d0 * (pi - cy) / fy, -d0], 1)  # (M, 3)
    n = safe_normalize(normals.permute(0, 2, 3, 1).reshape(-1, 3)[idx], dim=1)
    v = p0 / p0.norm(dim=1, keepdim=True)  # eye -> point
    n_dot_v = (n * v).sum(1, keepdim=True)
    n = torch.where(n_dot_v > 0, -n, n)  # face the camera
    n_dot_v = -n_dot_v.abs()
    r = v - 2.0 * n_dot_v * n  # reflect(V, N)
    ok = (n * n).sum(1) > 0.5  # zero normals: not marched

    # depth range of each batch item: the ray cannot hit outside it
    dflat = torch.where(valid, depth, torch.full_like(depth, math.nan)).reshape(b, -1)
    d_near = torch.nan_to_num(dflat, nan=math.inf).amin(1)[bi] * (1 - 1e-6)
    d_far = torch.nan_to_num(dflat, nan=-math.inf).amax(1)[bi] + thickness
    # Liang-Barsky against planes a . X + c >= 0 (view space; d = -z)
    zero = torch.zeros_like(fx)
    planes = [  # (a_x, a_y, a_z, c)
        (fx, zero, -(cx + 0.5), zero),                 # u >= 0
        (-fx, zero, -(w - cx - 0.5), zero),            # u <= W
        (zero, -fy, -(cy + 0.5), zero),                # v >= 0
        (zero, fy, -(h - cy - 0.5), zero),             # v <= H
        (zero, zero, -torch.ones_like(fx), -d_near),   # d >= d_near
        (zero, zero, torch.ones_like(fx), d_far),      # d <= d_far
    ]
    t_end = torch.full_like(fx, max_distance)
    for ax, ay, az, c in planes:
        f0 = ax * p0[:, 0] + ay * p0[:, 1] + az * p0[:, 2] + c
        fr = ax * r[:, 0] + ay * r[:, 1] + az * r[:, 2]
        leaving = fr < 0
        t_exit = torch.where(leaving, f0.clamp_min(0) / torch.where(leaving, -fr, 1.0),
                             torch.full_like(f0, math.inf))
        t_end = torch.minimum(t_end, t_exit)
    t_end = torch.nan_to_num(t_end, posinf=0.0)  # parallel to every plane: cannot happen
    p1 = p0 + t_end[:, None] * r

    def project(p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        d = (-p[:, 2]).clamp_min(1e-30)
        return fx * p[:, 0] / d + cx + 0.5, cy - fy * p[:, 1] / d + 0.5, 1.0 / d

    u0, v0, k0 = project(p0)
    u1, v1, k1 = project(p1)
    du, dv, dk = u1 - u0, v1 - v0, k1 - k0
    # packed per-ray state (one index op compacts it): screen start, screen delta, inverse
    # depth start and delta, 1 / delta (1e30 for 0), nudge, "cell boundary ahead" flags, s
    big = torch.full_like(du, 1e30)
    inv_du = torch.where(du != 0, 1.0 / torch.where(du != 0, du, 1.0), big)
    inv_dv = torch.where(dv != 0, 1.0 / torch.where(dv != 0, dv, 1.0), big)
    fwd_u, fwd_v = (du >= 0).to(dt), (dv >= 0).to(dt)
    st = torch.stack([u0, v0, du, dv, k0, dk, inv_du, inv_dv, torch.sign(du) * NUDGE_PX,
                      torch.sign(dv) * NUDGE_PX, fwd_u, fwd_v, torch.zeros_like(du)], 1)

    def cell_exit(st: torch.Tensor, cu: torch.Tensor, cv: torch.Tensor,
                  size: torch.Tensor) -> torch.Tensor:
        """Parameter s where the rays of ``st`` leave the cell (cu, cv) of side ``size``."""
        sx = ((cu.to(dt) + st[:, 10]) * size - st[:, 0]) * st[:, 6]
        sy = ((cv.to(dt) + st[:, 11]) * size - st[:, 1]) * st[:, 7]
        return torch.minimum(sx, sy).clamp(max=1.0)

    st[:, 12] = cell_exit(st, pj, pi, torch.ones_like(du))  # start past the ray's own pixel
    levels = max(1, math.ceil(math.log2(max(h, w))) + 1)
    cmin, cmax, offs, shapes = _min_max_chain(depth, valid, levels)
    # per level: offset into the chain, height, width, cell size (one gather a step)
    table = torch.tensor([[o, hh, ww, 2**lv] for lv, (o, (hh, ww)) in enumerate(
        zip(offs, shapes, strict=True))], device=dev)
    nflat = safe_normalize(normals, dim=1).permute(0, 2, 3, 1).reshape(-1, 3)
    min_f = torch.minimum(fx.abs(), fy.abs())
    alive = ok & (st[:, 12] < 1.0) & (t_end > 0)
    ray = torch.arange(idx.numel(), device=dev)
    ist = torch.stack([ray, torch.zeros_like(ray), bi], 1)[alive]  # ray id, level, batch
    st = st[alive]
    live = torch.ones(st.shape[0], dtype=torch.bool, device=dev)  # finished rays stay a
    hit_ray, hit_sa, hit_sb = [], [], []                           # while, marked dead
    if stats is not None:
        stats["rays"] = int(st.shape[0])
    for step in range(max_steps):
        if ist.shape[0] == 0:
            break
        if stats is not None:
            stats["steps"] = step + 1
        lvl = ist[:, 1]
        s = st[:, 12]
        off, hl, wl, size_i = table[lvl].unbind(1)
        size = size_i.to(dt)
        pu = torch.addcmul(st[:, 0], s, st[:, 2]) + st[:, 8]
        pv = torch.addcmul(st[:, 1], s, st[:, 3]) + st[:, 9]
        cu = torch.minimum(torch.div(pu, size, rounding_mode="floor").clamp_min(0).long(), wl - 1)
        cv = torch.minimum(torch.div(pv, size, rounding_mode="floor").clamp_min(0).long(), hl - 1)
        s_exit = cell_exit(st, cu, cv, size)
        ka = torch.addcmul(st[:, 4], s, st[:, 5])
        kb = torch.addcmul(st[:, 4], s_exit, st[:, 5])
        lo, hi = 1.0 / torch.maximum(ka, kb), 1.0 / torch.minimum(ka, kb)
        flat = off + (ist[:, 2] * hl + cv) * wl + cu
        zmin = cmin[flat]
        overlap = (hi >= zmin) & (lo <= cmax[flat] + thickness)
        at0 = lvl == 0
        hit = overlap & at0 & live
        if bool(hit.any()):  # reject the origin's own plane and back sides
            cand = hit.nonzero().squeeze(1)
            rid, zc = ist[cand, 0], cmin[flat[cand]]
            cuc, cvc = cu[cand].to(dt), cv[cand].to(dt)
            ps = torch.stack([zc * (cuc - cx[rid]) / fx[rid], -zc * (cvc - cy[rid]) / fy[rid],
                              -zc], 1)
            dist = ((ps - p0[rid]) * n[rid]).sum(1)
            facing = (nflat[flat[cand]] * r[rid]).sum(1) < 0  # level 0: flat = pixel index
            good = (dist > PLANE_TOL_PX * zc / min_f[rid]) & facing
            hit = torch.zeros_like(hit).index_put((cand,), good)
        advance = ~overlap | hit.logical_not() & at0
        ist[:, 1] = torch.where(advance, (lvl + 1).clamp_max(levels - 1),
                                torch.where(at0, lvl, lvl - 1))
        # a ray ends past its last cell (s = 1: left the frame, the depth range or
        # max_distance); inside the frame the nudge puts every cell exit strictly ahead,
        # so an exit not ahead (cell index clamped to the frame, or s rounded to just
        # under 1) means the ray has left the screen: without this it would stall there
        miss = advance & ((s_exit >= 1.0) | (s_exit <= s)) & live
        if bool(hit.any()):
            hit_ray.append(ist[hit, 0])
            hit_sa.append(s[hit])
            hit_sb.append(s_exit[hit])
        # descending: first move the ray up to the cell's nearest depth if it is in front of
        # it at the cell's entry (Uludag 2014): nothing in the cell is hit before that
        cross = (1.0 / zmin - st[:, 4]) / torch.where(st[:, 5] != 0, st[:, 5], 1.0)
        ahead = ~advance & ~at0 & (ka > 1.0 / zmin) & (cross > s)
        st[:, 12] = torch.where(advance, s_exit, torch.where(ahead, cross.clamp(max=1.0), s))
        live &= (hit | miss).logical_not_()
        n_live = int(live.sum())
        if n_live == 0:
            break
        if 4 * n_live < 3 * live.shape[0]:  # compact when a quarter is dead
            ist, st, live = ist[live], st[live], live[live]
    if not hit_ray:
        return reflection, confidence
    hr, sa, sb = torch.cat(hit_ray), torch.cat(hit_sa), torch.cat(hit_sb)

    # binary refinement against the bilinear depth buffer
    hb = bi[hr]
    dfill = torch.where(valid, depth, torch.full_like(depth, FAR_DEPTH)).reshape(-1, 1)

    def behind(sp: torch.Tensor) -> torch.Tensor:
        x = u0[hr] + sp * du[hr] - 0.5
        y = v0[hr] + sp * dv[hr] - 0.5
        scene = _bilinear(dfill, hb, x, y, h, w)[:, 0]
        return 1.0 / (k0[hr] + sp * dk[hr]) >= scene

    for _ in range(refine_steps):
        mid = 0.5 * (sa + sb)
        bh = behind(mid)
        sb = torch.where(bh, mid, sb)
        sa = torch.where(bh, sa, mid)
    s_hit = sb
    hu, hv = u0[hr] + s_hit * du[hr], v0[hr] + s_hit * dv[hr]
    d_hit = 1.0 / (k0[hr] + s_hit * dk[hr])

    # colour: premultiplied pyramid at the cone footprint's level
    rgba = torch.cat([image[:, :3] * valid, valid.to(image.dtype)], 1)
    rough = roughness.reshape(-1)[idx[hr]].clamp(0.0, 1.0)
    if blur:
        travel = torch.hypot(hu - u0[hr], hv - v0[hr])
        half = 2.0 * torch.atan(GGX_HALF_MAX_TAN * rough * rough)
        lod = torch.log2((2.0 * travel * torch.tan(half)).clamp_min(1.0))
        pyramid = build_mip_pyramid(rgba)
    else:
        lod = torch.zeros_like(hu)
        pyramid = [rgba]
    lod = lod.clamp(0.0, len(pyramid) - 1.0)
    col = hu.new_zeros(hu.shape[0], 4).to(image.dtype)
    for lv in range(int(lod.floor().min()), int(lod.ceil().max()) + 1):
        wgt = (1.0 - (lod - lv).abs()).clamp_min(0.0)
        use = (wgt > 0).nonzero().squeeze(1)
        if use.numel() == 0:
            continue
        tex = pyramid[lv]
        th, tw = tex.shape[-2:]
        flat_tex = tex.permute(0, 2, 3, 1).reshape(-1, 4)
        x = hu[use] * (tw / w) - 0.5
        y = hv[use] * (th / h) - 0.5
        surface = None
        if lv == 0:  # read only the surface the ray hit: facing it, at its depth
            r_use, d_use = r[hr[use]], d_hit[use]

            def surface(tap: torch.Tensor, r_use=r_use, d_use=d_use) -> torch.Tensor:  # noqa: ANN001
                facing = (nflat[tap] * r_use).sum(1) < 0
                near = (dfill[tap, 0] - d_use).abs() <= thickness
                return (facing & near).to(dt)
        col = col.index_add(0, use, _bilinear(flat_tex, hb[use], x, y, th, tw, surface)
                            * wgt[use, None].to(image.dtype))
    cov = col[:, 3:]
    seen = cov[:, 0] >= MIN_COVERAGE
    rgb = torch.where(seen[:, None], col[:, :3] / cov.clamp_min(MIN_COVERAGE), 0.0)

    edge = torch.minimum(torch.minimum(hu, w - hu), torch.minimum(hv, h - hv))
    conf = smoothstep(edge / (edge_fade * min(h, w))) if edge_fade > 0 else torch.ones_like(hu)
    conf = conf * smoothstep((max_roughness - rough) / (0.25 * max_roughness)) * seen
    target = idx[hr]
    reflection = reflection.permute(0, 2, 3, 1).reshape(-1, 3).index_copy(
        0, target, rgb.to(reflection.dtype)).reshape(b, h, w, 3).permute(0, 3, 1, 2)
    confidence = confidence.reshape(-1).index_copy(0, target, conf.to(dt)).reshape(b, 1, h, w)
    return reflection, confidence


class SSR(nn.Module):
    """Screen-space reflections: lit image + G-buffer + camera -> image with reflections.

    Args:
        max_steps: cap on the march steps (hierarchical: one step skips a whole cell); an
            int in ``[1, MAX_STEPS]``. The march stops earlier when every ray has finished,
            at the latest after :func:`march_step_bound` ``(H, W)`` steps; rays still
            going at the cap are misses.
        thickness: assumed thickness of the surfaces in the depth buffer (scene units): a
            ray passing behind a surface by more than this is not stopped by it.
        max_roughness: pixels at least this rough are not marched (the IBL stays); the
            confidence fades out over the last quarter of ``[0, max_roughness]``.
        edge_fade: width of the fade of hits near the screen border, as a fraction of
            ``min(H, W)`` (0: no fade).
        refine_steps: bisections of the hit cell against the bilinear depth buffer, an
            int in ``[0, MAX_REFINE_STEPS]``.
        max_distance: longest ray (scene units), ``inf`` = up to the frame's depth range.
        blur: roughness-dependent cone blur of the reflected colour (mip pyramid).
        enabled: ``False`` returns the image unchanged.

    Example:
        >>> image, depth = torch.rand(1, 3, 8, 8), torch.full((1, 1, 8, 8), 2.0)
        >>> normals = torch.tensor([0.0, 0, 1]).view(1, 3, 1, 1).expand(1, 3, 8, 8)
        >>> from torchraster.camera import perspective
        >>> rough, proj = torch.full((1, 1, 8, 8), 0.1), perspective(90.0, 1.0, 0.1)
        >>> out = SSR()(image, depth, normals, rough, torch.ones_like(rough), image,
        ...             projection=proj)
        >>> out.shape, torch.equal(out, image)  # a mirror facing the camera: rays leave
        (torch.Size([1, 3, 8, 8]), True)
    """

    def __init__(
        self,
        max_steps: int = 64,
        thickness: float = 0.1,
        max_roughness: float = 0.6,
        edge_fade: float = 0.05,
        refine_steps: int = 4,
        max_distance: float = math.inf,
        blur: bool = True,
        enabled: bool = True,
    ):
        super().__init__()
        max_steps = _check_steps("max_steps", max_steps, 1, MAX_STEPS)
        refine_steps = _check_steps("refine_steps", refine_steps, 0, MAX_REFINE_STEPS)
        self.max_steps, self.refine_steps = max_steps, refine_steps
        # thickness must be finite (inf: every ray behind a surface hits it); max_distance
        # may be inf (= up to the frame's depth range)
        self.thickness = check_float("thickness", thickness, 0.0, lo_open=True)
        self.max_distance = check_float("max_distance", max_distance, 0.0, lo_open=True,
                                        finite=False)
        self.max_roughness = check_float("max_roughness", max_roughness, 0.0, 1.0,
                                         lo_open=True)
        self.edge_fade = check_float("edge_fade", edge_fade, 0.0, 0.5)
        self.blur, self.enabled = check_bool("blur", blur), check_bool("enabled", enabled)

    def forward(
        self,
        image: torch.Tensor,
        depth: torch.Tensor,
        normals: torch.Tensor,
        roughness: torch.Tensor,
        metallic: torch.Tensor,
        albedo: torch.Tensor,
        projection: torch.Tensor | None = None,
        intrinsics: torch.Tensor | None = None,
        fallback: torch.Tensor | None = None,
        weight: torch.Tensor | None = None,
        return_maps: bool = False,
    ) -> torch.Tensor | SSRMaps:
        """Composite the reflections (see the module docstring for the formula).

        Args:
            image: ``(B, 3, H, W)`` linear radiance of the lit frame.
            depth: ``(B, 1, H, W)`` linear view depth (``-z_view``); 0 / inf = empty.
            normals: ``(B, 3, H, W)`` view-space normals.
            roughness, metallic: ``(B, 1, H, W)``; albedo: ``(B, 3, H, W)``.
            projection: ``(B, 4, 4)`` / ``(4, 4)`` OpenGL matrix, or ``intrinsics``
                ``(B, 4)`` / ``(4,)`` fx, fy, cx, cy (pixels): exactly one of them.
            fallback: ``(B, 3, H, W)`` environment specular already in ``image`` (replaced
                where the ray hits), or None (= 0).
            weight: ``(B, 3, H, W)`` specular weight ``W`` of the hits, or None for
                :func:`specular_weight` of albedo, metallic, roughness and n.v.
            return_maps: also return the reflection, confidence and weight maps.

        Returns:
            ``(B, 3, H, W)``, or :class:`SSRMaps` when ``return_maps``.
        """
        image = check_tensor("image", image, ("B", 3, "H", "W"), floating=True, finite=True)
        b, _, h, w = image.shape
        depth = check_tensor("depth", depth, (b, 1, h, w), floating=True)
        if bool(torch.isnan(depth).any()):
            raise ValueError("depth: contains NaN")
        normals = check_tensor("normals", normals, (b, 3, h, w), floating=True, finite=True)
        roughness = check_tensor("roughness", roughness, (b, 1, h, w), floating=True,
                                 finite=True)
        metallic = check_tensor("metallic", metallic, (b, 1, h, w), floating=True, finite=True)
        albedo = check_tensor("albedo", albedo, (b, 3, h, w), floating=True, finite=True)
        for name, t in (("fallback", fallback), ("weight", weight)):
            if t is not None:
                check_tensor(name, t, (b, 3, h, w), floating=True, finite=True)
        if not self.enabled:
            if return_maps:
                z = image.new_zeros(b, 3, h, w)
                return SSRMaps(image, z, image.new_zeros(b, 1, h, w), z)
            return image
        intrinsics = camera_intrinsics(projection, intrinsics, (b, h, w))
        dt = compute_dtype(image)
        img = image.to(dt)
        with torch.no_grad():
            dep = depth.to(dt)
        refl, conf = trace_reflections(
            img, dep, normals.to(dt), roughness.to(dt),
            intrinsics.to(device=image.device, dtype=dt), max_steps=self.max_steps,
            thickness=self.thickness, max_roughness=self.max_roughness,
            edge_fade=self.edge_fade, refine_steps=self.refine_steps,
            max_distance=self.max_distance, blur=self.blur)
        if weight is None:
            weight = specular_weight(self._n_dot_v(normals.to(dt), intrinsics.to(dt)),
                                     albedo.to(dt), metallic.to(dt), roughness.to(dt))
        weight = weight.to(dt)
        marched = conf > 0
        weight = torch.where(marched, weight, torch.zeros_like(weight))
        delta = weight * refl
        if fallback is not None:
            delta = delta - fallback.to(dt)
        out = img + torch.where(marched, conf * delta, torch.zeros_like(delta))
        out = out.to(image.dtype)
        if return_maps:
            return SSRMaps(out, refl.to(image.dtype), conf.to(image.dtype),
                           weight.to(image.dtype))
        return out

    @staticmethod
    def _n_dot_v(normals: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
        """``|n . v|`` ``(B, 1, H, W)`` of view-space normals and the pixels' eye rays."""
        b, _, h, w = normals.shape
        k = intrinsics.to(normals.device).reshape(-1, 4).expand(b, 4).reshape(b, 4, 1, 1)
        jj = torch.arange(w, device=normals.device, dtype=normals.dtype).view(1, 1, 1, w)
        ii = torch.arange(h, device=normals.device, dtype=normals.dtype).view(1, 1, h, 1)
        ray = torch.cat([((jj - k[:, 2:3]) / k[:, 0:1]).expand(b, 1, h, w),
                         (-(ii - k[:, 3:4]) / k[:, 1:2]).expand(b, 1, h, w),
                         -torch.ones(b, 1, h, w, device=normals.device, dtype=normals.dtype)], 1)
        n = safe_normalize(normals, dim=1)
        return (n * safe_normalize(ray, dim=1)).sum(1, keepdim=True).abs()
