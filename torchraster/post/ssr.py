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
  each ``2^l x 2^l`` pixel cell (the frame padded with empty pixels to a multiple of the
  top cell, so a cell's index is arithmetic in its size). Each step takes the ray's cell at its
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
  0 often: they cost the most. Only covered pixels below ``max_roughness`` with a usable
  normal are marched (packed once); the march is written for CPU tensor speed (contiguous
  per-ray rows, 0 / 1 float masks, exact ``lerp`` selects, int32 ``index_select`` lookups,
  inverse-depth comparisons, no per-level tables: :func:`_march`), and the composite is
  evaluated at the hit pixels only.
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

import math
import operator
from typing import NamedTuple

import torch
from torch import nn

from .._validate import check_bool, check_float, check_tensor
from ..mip import mip_sizes
from ..numerics import NORMALIZE_EPS, compute_dtype, safe_normalize, smoothstep, specular_f0
from ..shading.ibl import (
    IBL_LUT_SAMPLES,
    IBL_LUT_SIZE,
    MIN_N_DOT_V,
    Environment,
    dfg_lut,
    lookup_dfg,
)
from ..shading.surface import Surface
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
    lut = dfg_lut(IBL_LUT_SIZE, IBL_LUT_SAMPLES, device=albedo.device, dtype=albedo.dtype)
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


def _bilinear(flat: torch.Tensor | list[torch.Tensor], b: torch.Tensor, x: torch.Tensor,
              y: torch.Tensor, h: int, w: int, tap_weight=None) -> torch.Tensor:
    """Bilinear lookup in ``flat``, C channel rows ``(B * h * w,)``, at texel coordinates
    x, y ``(M,)`` (texel centres at integers, clamped to the edge) of batch items ``b``
    -> ``(C, M)``. ``tap_weight(texel indices (M,)) -> (M,)`` optionally scales each tap."""
    x = x.clamp(0.0, w - 1.0)
    y = y.clamp(0.0, h - 1.0)
    x0, y0 = x.floor(), y.floor()
    fx, fy = x - x0, y - y0
    ix = torch.int32 if flat[0].shape[-1] < (1 << 31) else torch.int64  # faster gathers
    x0l, y0l = x0.to(ix), y0.to(ix)
    x1l, y1l = (x0l + 1).clamp_max_(w - 1), (y0l + 1).clamp_max_(h - 1)
    base = b.to(ix) * (h * w)
    row0, row1 = base + y0l * w, base + y1l * w
    out = 0.0
    for tap, wt in ((row0 + x0l, (1 - fx) * (1 - fy)), (row0 + x1l, fx * (1 - fy)),
                    (row1 + x0l, (1 - fx) * fy), (row1 + x1l, fx * fy)):
        if tap_weight is not None:
            wt = wt * tap_weight(tap)
        taps = [c.index_select(0, tap) for c in flat]
        out = out + (taps[0][None] if len(taps) == 1 else torch.stack(taps)) * wt.to(
            flat[0].dtype)
    return out


#: Chain indices are computed in the march's float dtype while exact (below 2^24 in float32).
_FLOAT_INDEX_LIMIT = 1 << 24


def _dot(a: list[torch.Tensor], b: list[torch.Tensor]) -> torch.Tensor:
    """Row-wise dot product of two vectors given as lists of 3 rows ``(M,)``."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _rows_at(vec: list[torch.Tensor], index: torch.Tensor) -> torch.Tensor:
    """The columns ``index`` ``(K,)`` of a vector given as a list of rows -> ``(3, K)``."""
    return torch.stack([c.index_select(0, index) for c in vec])


def _top_cell(h: int, w: int) -> int:
    """Side of the top cell of the min-max chain: the largest power of two up to
    ``2^ceil(log2 max(h, w))`` whose padding of the frame to multiples of it adds at most
    half the frame's area (a 640 x 480 frame: 256, padded to 768 x 512)."""
    top = 1 << max(0, math.ceil(math.log2(max(h, w))))
    while top > 1 and -(-h // top) * -(-w // top) * top * top > 1.5 * h * w:
        top //= 2
    return top


def _min_max_chain(depth: torch.Tensor, valid: torch.Tensor,
                   top: int) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """Nearest and farthest depth of every ``2^l x 2^l`` cell, l = 0 .. log2(top), of the
    frame padded (empty: +inf / -inf) to ``(ph, pw)``, multiples of ``top``.

    Returns flat ``(B * 2 ph pw,)`` min and max chains, ``ph``, ``pw``. Item b's level l
    (``ph_l x pw_l`` cells, ``ph_l = ph / 2^l``, row-major) starts at ``2 ph pw (b + 1 -
    2^-l)``: a cell's index is one multiply-add in its level's cell size (the gaps between
    levels, a third of the chain, hold the empty value and are never read).
    """
    b, _, h, w = depth.shape
    ph, pw = -(-h // top) * top, -(-w // top) * top
    chains = []
    for empty, op in ((math.inf, torch.minimum), (-math.inf, torch.maximum)):
        chain = depth.new_full((b, 2 * ph * pw), empty)  # padding and gaps: empty
        levels = [chain[:, 2 * ph * pw - (2 * ph * pw >> lv):][:, :(ph * pw) >> (2 * lv)]
                  .view(b, ph >> lv, pw >> lv) for lv in range(top.bit_length())]
        levels[0][:, :h, :w] = depth[:, 0].masked_fill(~valid[:, 0], empty)
        for x, nxt in zip(levels[:-1], levels[1:], strict=True):  # 2 x 2 reductions
            op(op(x[:, ::2, ::2], x[:, 1::2, ::2]), op(x[:, ::2, 1::2], x[:, 1::2, 1::2]),
               out=nxt)
        chains.append(chain.reshape(-1))
    return chains[0], chains[1], ph, pw


def _march(st: list[torch.Tensor], rid: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
           zmin: torch.Tensor, frame: tuple[int, int, int], max_steps: int,
           accept, stats: dict | None):  # noqa: ANN202
    """Hierarchical march of packed rays (see the module docstring).

    ``st``: 16 rows ``(M,)`` (s and size are updated in place): u0, v0 (screen start),
    u0 + nudge, v0 + nudge, du, dv, k0, dk, 1/du, 1/dv (1e30 for 0), "cell boundary ahead"
    flags (0 / 1) along u and v, 1/dk where dk < 0 (receding rays; else 0), s (start),
    cell size (1), batch item;
    ``rid`` ``(M,)`` ray ids; ``near``, ``far``: the inverse depth chains ``1 / min`` and
    ``1 / (max + thickness)`` of :func:`_min_max_chain`, ``zmin`` its min chain;
    ``frame`` = (ph, pw, top) of the chains. ``accept(rid, cu, cv, zmin)``
    -> bool ``(K,)`` tests level-0 candidates. Returns the ray ids, start and exit s of
    the hit cells (lists of 1-D tensors).

    Written for CPU speed (about 60 tensor ops a step): every row is contiguous, masks
    are 0 / 1 floats (comparisons and logic on bool tensors cost several float ops),
    selections are exact (``lerp`` with 0 / 1 weights, ``maximum``), chain lookups are
    ``index_select`` at an int32 index computed from the cell size (no per-level
    tables), and finished rays are dropped whenever a quarter of those stepped are.
    """
    ph, pw, top = frame
    dt = st[0].dtype
    # chain indices are integers: exact in float32 below 2^24, else computed in float64
    idt = dt if dt == torch.float64 or near.numel() < _FLOAT_INDEX_LIMIT else torch.float64
    ix = torch.int32 if near.numel() < (1 << 31) else torch.int64
    area2 = 2.0 * ph * pw  # level l of item b starts at area2 (b + 1 - 2^-l)
    if idt == dt:  # the batch row becomes the cells' base index
        st[15] = st[15] * area2 + area2
    live = torch.ones_like(st[0])
    hit_ray, hit_sa, hit_sb = [], [], []
    for step in range(max_steps):
        if stats is not None:
            stats["steps"] = step + 1
            stats["ray_steps"] += st[0].shape[0]
        u0, v0, u0n, v0n, du, dv, k0, dk, idu, idv, fu, fv, idk, s, size, bi = st
        isz = size.reciprocal()
        # the ray's cell at its level, clamped to the padded frame (cells of side size)
        cu = torch.addcmul(u0n, s, du).clamp_(0.0, pw - 0.5).mul_(isz).floor_()
        cv = torch.addcmul(v0n, s, dv).clamp_(0.0, ph - 0.5).mul_(isz).floor_()
        s_exit = torch.minimum(((cu + fu) * size - u0) * idu,
                               ((cv + fv) * size - v0) * idv).clamp_(max=1.0)
        ka, kb = torch.addcmul(k0, s, dk), torch.addcmul(k0, s_exit, dk)
        if idt == dt:  # (bi: base index)
            flat = torch.addcmul(cu, cv, isz * pw).add_(bi).add_(isz, alpha=-area2)
        else:
            flat = torch.addcmul(cu.to(idt), cv.to(idt), (isz * pw).to(idt))
            flat.add_(bi.to(idt) + 1.0, alpha=area2).add_(isz.to(idt), alpha=-area2)
        flat = flat.to(ix)
        inear, ifar = near.index_select(0, flat), far.index_select(0, flat)
        # the ray's inverse-depth range over the cell overlaps [1 / (max + thickness),
        # 1 / min]: it neither passes in front of everything nor behind by > thickness
        overlap = torch.le(torch.minimum(ka, kb), inear, out=torch.empty_like(s))
        overlap *= torch.ge(torch.maximum(ka, kb), ifar, out=torch.empty_like(s))
        ov0 = overlap * torch.le(size, 1.0, out=torch.empty_like(s))  # ... at level 0
        hit = ov0 * live
        if float(hit.sum()) > 0:  # reject the origin's own plane and back sides
            cand = hit.nonzero().squeeze(1)
            good = accept(rid.index_select(0, cand), cu.index_select(0, cand),
                          cv.index_select(0, cand), zmin.index_select(0, flat[cand]))
            hit.index_fill_(0, cand[~good], 0.0)
            found = cand[good]
            if found.numel():
                hit_ray.append(rid.index_select(0, found))
                hit_sa.append(s.index_select(0, found))
                hit_sb.append(s_exit.index_select(0, found))
        # advance (skip the cell, go up) where no overlap or a rejected level-0 candidate;
        # else descend, or stay (a hit: the ray is finished)
        advance = (1.0 - overlap).add_(ov0).sub_(hit)
        # a ray ends past its last cell (s = 1: left the frame, the depth range or
        # max_distance); inside the frame the nudge puts every cell exit strictly ahead,
        # so an exit not ahead (cell index clamped to the frame, or s rounded to just
        # under 1) means the ray has left the screen: without this it would stall there
        ended = torch.maximum(torch.ge(s_exit, 1.0, out=torch.empty_like(s)),
                              torch.le(s_exit, s, out=torch.empty_like(s)))
        # descending: first move a receding ray up to the cell's nearest depth if it is in
        # front of it at the cell's entry (Uludag 2014): nothing in the cell is hit before
        # that (the crossing is behind s when the ray enters behind that depth)
        cross = (inear - k0).mul_(idk).clamp_(max=1.0).mul_(overlap - ov0)
        torch.lerp(torch.maximum(s, cross), s_exit, advance, out=s)
        # cell size: doubled (up to top) on advancing, else halved (down to 1)
        size.mul_(advance * 1.5 + 0.5).clamp_(1.0, top)
        live.addcmul_(advance, ended, value=-1.0).sub_(hit).clamp_(min=0.0)
        n_live = int(live.sum())
        if n_live == 0:
            break
        if 4 * n_live < 3 * live.shape[0]:  # compact when a quarter is dead
            keep = live.nonzero().squeeze(1)
            st = [t.index_select(0, keep) for t in st]
            rid = rid.index_select(0, keep)
            live = torch.ones_like(st[0])
    return hit_ray, hit_sa, hit_sb


class _Hits(NamedTuple):
    """Packed hits of :func:`_trace_packed`: ``pixel`` ``(K,)`` indices into ``B * H * W``,
    ``batch`` ``(K,)`` their batch items, ``rgb`` ``(3, K)`` reflected radiance,
    ``confidence`` ``(K,)``."""

    pixel: torch.Tensor
    batch: torch.Tensor
    rgb: torch.Tensor
    confidence: torch.Tensor


def _channels(hits: _Hits, hw: int) -> torch.Tensor:
    """Indices ``(3 K,)`` of the hits' 3 channels in a flat ``(B, 3, H, W)`` tensor, channel
    by channel (channel c of pixel p of item b: ``(3 b + c) hw + p - b hw``)."""
    at = hits.pixel + hits.batch * (2 * hw)
    return torch.cat([at, at + hw, at + 2 * hw])


def _composite(image: torch.Tensor, hits: _Hits | None, normals: torch.Tensor,
               intrinsics: torch.Tensor, albedo: torch.Tensor, metallic: torch.Tensor,
               roughness: torch.Tensor, fallback: torch.Tensor | None,
               weight: torch.Tensor | None, want_maps: bool):  # noqa: ANN202
    """``image + confidence * (W * L_ssr - fallback)`` evaluated at the hits only.

    Args: as :meth:`SSR.forward` (all in the compute dtype; ``intrinsics`` ``(B, 4)``).
    Returns ``(out, (reflection, confidence, weight) maps or None)``.
    """
    b, _, h, w = image.shape
    hw = h * w
    if hits is None:
        if not want_maps:
            return image, None
        z = image.new_zeros(b, 3, h, w)
        return image, (z, image.new_zeros(b, 1, h, w), z)
    at3 = _channels(hits, hw)

    def gather(t: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        return t.reshape(-1).index_select(0, index).reshape(-1, hits.pixel.shape[0])

    marched = (hits.confidence > 0).to(image.dtype)  # (inputs are finite: 0 / 1 masks)
    if weight is None:  # split-sum weight at the hit pixels: n.v of their eye rays
        pix = hits.pixel - hits.batch * hw
        i = torch.div(pix, w, rounding_mode="floor")
        fx, fy, cx, cy = intrinsics.reshape(-1, 4).expand(b, 4).t().index_select(
            1, hits.batch).unbind(0)
        j, i = (pix - i * w).to(image.dtype), i.to(image.dtype)
        ray = torch.stack([(j - cx) / fx, -(i - cy) / fy, -torch.ones_like(fx)])
        nrm = safe_normalize(gather(normals, at3), dim=0)
        n_dot_v = (nrm * safe_normalize(ray, dim=0)).sum(0).abs()
        weight_k = specular_weight(
            n_dot_v.view(1, 1, -1, 1), gather(albedo, at3).view(1, 3, -1, 1),
            gather(metallic, hits.pixel).view(1, 1, -1, 1),
            gather(roughness, hits.pixel).view(1, 1, -1, 1)).view(3, -1)
    else:
        weight_k = gather(weight, at3)
    weight_k = weight_k * marched
    delta = weight_k * hits.rgb
    if fallback is not None:
        delta = delta - gather(fallback, at3)
    add = hits.confidence * marched * delta
    out = image.reshape(-1).index_add(0, at3, add.reshape(-1)).reshape(b, 3, h, w)
    if not want_maps:
        return out, None
    maps = (image.new_zeros(b * 3 * hw).index_copy_(0, at3, hits.rgb.reshape(-1)),
            image.new_zeros(b * hw).index_copy_(0, hits.pixel, hits.confidence),
            image.new_zeros(b * 3 * hw).index_copy_(0, at3, weight_k.reshape(-1)))
    return out, tuple(m.reshape(b, -1, h, w) for m in maps)


def _trace_packed(
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
) -> _Hits | None:
    """:func:`trace_reflections` without the maps: the hits, packed (None: no hit)."""
    max_steps = _check_steps("max_steps", max_steps, 1, MAX_STEPS)
    refine_steps = _check_steps("refine_steps", refine_steps, 0, MAX_REFINE_STEPS)
    if stats is not None:
        stats.update(rays=0, steps=0, ray_steps=0)
    # the march is discrete (where a ray hits carries no gradient): its state is built from
    # detached geometry, so the in-place updates of the march never reach autograd
    depth, normals, intrinsics = depth.detach(), normals.detach(), intrinsics.detach()
    b, _, h, w = depth.shape
    dt = depth.dtype
    valid = torch.isfinite(depth) & (depth > 0)
    march = valid & (roughness < max_roughness)
    bi, pi, pj = march[:, 0].nonzero().t().contiguous()  # batch, row, column (M,) each
    if bi.numel() == 0:
        return None
    hw = h * w
    idx = (bi * h + pi) * w + pj  # into B*H*W
    # per-ray values are (M,) rows, vectors lists of 3 rows (contiguous, no broadcasting:
    # the fast layout on CPU); gathers are index_select
    if b == 1:  # one camera: Python scalars (the fastest operands)
        fx, fy, cx, cy = intrinsics.to(dt).reshape(4).tolist()
    else:
        kt = intrinsics.to(dt).reshape(-1, 4).expand(b, 4).t().contiguous()
        fx, fy, cx, cy = (c.index_select(0, bi) for c in kt)
    d0 = depth.reshape(-1).index_select(0, idx)
    pif, pjf = pi.to(dt), pj.to(dt)
    p0 = [d0 * (pjf - cx) / fx, -d0 * (pif - cy) / fy, -d0]
    ncomp = normals.transpose(0, 1).reshape(3, -1)  # (3, B*H*W), a view for B = 1
    n = [c.index_select(0, idx) for c in ncomp]
    nn = _dot(n, n)
    ok = nn > NORMALIZE_EPS  # zero normals: not marched
    scale = nn.clamp_min_(NORMALIZE_EPS).rsqrt_().mul_(ok)
    n = [c * scale for c in n]  # as safe_normalize
    dist0 = torch.stack(p0, 1).norm(dim=1)  # (M, 3): rounded as the reference code
    v = [c / dist0 for c in p0]  # eye -> point
    n_dot_v = _dot(n, v)
    flip = 1.0 - 2.0 * (n_dot_v > 0).to(dt)  # normals facing the camera
    n = [c * flip for c in n]
    n_dot_v = n_dot_v.abs_().mul_(2.0)
    r = [vc + n_dot_v * nc for vc, nc in zip(v, n, strict=True)]  # reflect(V, N)

    top = _top_cell(h, w)
    cmin, cmax, ph, pw = _min_max_chain(depth, valid, top)
    # depth range of each batch item (its top chain level): the ray cannot hit outside it
    top_start = 2 * ph * pw - 2 * ph * pw // top
    top_at = slice(top_start, top_start + ph * pw // (top * top))
    d_near = cmin.view(b, -1)[:, top_at].amin(1).index_select(0, bi) * (1 - 1e-6)
    d_far = cmax.view(b, -1)[:, top_at].amax(1).index_select(0, bi) + thickness
    # Liang-Barsky against planes a . X + c >= 0 (view space; d = -z); a ray not leaving
    # a plane is not limited by it (x / +0 = inf: the numerator is kept > 0)
    px, py, pz = p0
    rx, ry, rz = r
    ex, ey = -(cx + 0.5), -(cy + 0.5)
    ex1, ey1 = -(w - cx - 0.5), -(h - cy - 0.5)
    planes = [  # (a . p0 + c, a . r)
        (fx * px + ex * pz, fx * rx + ex * rz),            # u >= 0
        (-fx * px + ex1 * pz, -fx * rx + ex1 * rz),        # u <= W
        (-fy * py + ey * pz, -fy * ry + ey * rz),          # v >= 0
        (fy * py + ey1 * pz, fy * ry + ey1 * rz),          # v <= H
        (-pz - d_near, -rz),                               # d >= d_near
        (pz + d_far, rz),                                  # d <= d_far
    ]
    t_end = torch.full_like(d0, max_distance)
    for f0, fr in planes:
        t_end = torch.minimum(t_end, (f0.clamp_min(0.0) + 1e-30) / ((-fr).clamp_min(0.0) + 0.0))
    t_end = torch.nan_to_num(t_end, posinf=0.0)  # parallel to every plane: cannot happen
    p1 = [pc + t_end * rc for pc, rc in zip(p0, r, strict=True)]

    def project(p: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        d = (-p[2]).clamp_min(1e-30)
        return fx * p[0] / d + cx + 0.5, cy - fy * p[1] / d + 0.5, 1.0 / d

    u0, v0, k0 = project(p0)
    u1, v1, k1 = project(p1)
    du, dv, dk = u1 - u0, v1 - v0, k1 - k0
    # packed per-ray state (rows, see _march): 1 / delta is 1e30 for 0
    inv_du = du.reciprocal().masked_fill_(du == 0, 1e30)
    inv_dv = dv.reciprocal().masked_fill_(dv == 0, 1e30)
    fwd_u, fwd_v = (du >= 0).to(dt), (dv >= 0).to(dt)
    # the ray starts where it leaves its own pixel
    s0 = torch.minimum((pjf + fwd_u - u0) * inv_du, (pif + fwd_v - v0) * inv_dv).clamp(max=1.0)
    alive = ok & (s0 < 1.0) & (t_end > 0)
    n_alive = int(alive.sum())
    alive = (torch.arange(n_alive, device=idx.device) if n_alive == idx.numel() else
             alive.nonzero().squeeze(1))
    recede = dk.reciprocal().masked_fill_(dk >= 0, 0.0)
    st = [u0, v0, u0 + torch.sign(du) * NUDGE_PX, v0 + torch.sign(dv) * NUDGE_PX,
          du, dv, k0, dk, inv_du, inv_dv, fwd_u, fwd_v, recede, s0, torch.ones_like(du),
          bi.to(dt)]
    if n_alive < idx.numel():
        st = [t.index_select(0, alive) for t in st]
    if stats is not None:
        stats["rays"] = int(alive.numel())
    if alive.numel() == 0:
        return None

    def facing(pix: torch.Tensor, ray: torch.Tensor) -> torch.Tensor:
        """Pixels ``pix`` ``(K,)`` (into B*H*W) whose normal faces ``ray`` ``(3, K)``
        (zero normals face nothing)."""
        nrm = [c.index_select(0, pix) for c in ncomp]
        dot = nrm[0] * ray[0] + nrm[1] * ray[1] + nrm[2] * ray[2]
        return (dot < 0) & (nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2] > NORMALIZE_EPS)

    def accept(rid: torch.Tensor, cu: torch.Tensor, cv: torch.Tensor,
               zc: torch.Tensor) -> torch.Tensor:
        """Level-0 candidates (pixel cu, cv at depth zc) not on the origin's tangent plane
        and facing the ray."""
        fxr, fyr, cxr, cyr, rb = (t if isinstance(t, float) else t.index_select(0, rid)
                                  for t in (fx, fy, cx, cy, bi))
        ps = torch.stack([zc * (cu - cxr) / fxr, -zc * (cv - cyr) / fyr, -zc])
        dist = ((ps - _rows_at(p0, rid)) * _rows_at(n, rid)).sum(0)
        pix = rb * hw + cv.long() * w + cu.long()
        min_f = (min(abs(fxr), abs(fyr)) if isinstance(fxr, float) else
                 torch.minimum(fxr.abs(), fyr.abs()))
        plane_tol = PLANE_TOL_PX * zc / min_f
        return (dist > plane_tol) & facing(pix, _rows_at(r, rid))

    near, far = cmin.reciprocal(), (cmax + thickness).reciprocal_()  # inverse depths
    hit_ray, hit_sa, hit_sb = _march(st, alive, near, far, cmin,
                                     (ph, pw, top), max_steps, accept,
                                     stats)
    if not hit_ray:
        return None
    hr, sa, sb = torch.cat(hit_ray), torch.cat(hit_sa), torch.cat(hit_sb)

    # binary refinement against the bilinear depth buffer
    hb, hu0, hv0, hdu, hdv, hk0, hdk = (t.index_select(0, hr) for t in (bi, u0, v0, du, dv,
                                                                         k0, dk))
    dfill = torch.where(valid, depth, FAR_DEPTH).reshape(1, -1)

    hu0m, hv0m = hu0 - 0.5, hv0 - 0.5  # texel coordinates: centres at integers

    def behind(sp: torch.Tensor) -> torch.Tensor:
        scene = _bilinear(dfill, hb, hu0m + sp * hdu, hv0m + sp * hdv, h, w)[0]
        return torch.ge((hk0 + sp * hdk).reciprocal_(), scene, out=torch.empty_like(sp))

    for _ in range(refine_steps):  # exact selects: lerp with 0 / 1 weights
        mid = 0.5 * (sa + sb)
        bh = behind(mid)
        sb, sa = torch.lerp(sb, mid, bh), torch.lerp(mid, sa, bh)
    s_hit = sb
    hu, hv = hu0 + s_hit * hdu, hv0 + s_hit * hdv
    d_hit = 1.0 / (hk0 + s_hit * hdk)

    # colour: premultiplied pyramid at the cone footprint's level
    target = idx.index_select(0, hr)
    rough = roughness.reshape(-1).index_select(0, target).clamp(0.0, 1.0)
    if blur:
        travel = torch.hypot(hu - hu0, hv - hv0)
        half = 2.0 * torch.atan(GGX_HALF_MAX_TAN * rough * rough)
        lod = torch.log2((2.0 * travel * torch.tan(half)).clamp_min(1.0))
        lod = lod.clamp(0.0, len(mip_sizes(h, w)) - 1.0)
    else:
        lod = torch.zeros_like(hu)
    lv_lo, lv_hi = int(lod.floor().min()), int(lod.ceil().max())
    # level 0: the image's channel rows and coverage (views for B = 1); coarser levels:
    # the premultiplied pyramid (built only if read: mirrors read level 0 alone)
    rows0 = [*image[:, :3].transpose(0, 1).reshape(3, -1), valid.to(image.dtype).reshape(-1)]
    pyramid = [rows0]
    if lv_hi > 0:
        rgba = torch.cat([image[:, :3] * valid, valid.to(image.dtype)], 1)
        pyramid += [p.transpose(0, 1).reshape(4, -1) for p in build_mip_pyramid(rgba)[1:]]
    col = image.new_zeros(4, hu.shape[0])
    for lv in range(lv_lo, lv_hi + 1):
        wgt = (1.0 - (lod - lv).abs()).clamp_min(0.0)
        use = (wgt > 0).nonzero().squeeze(1)
        if use.numel() == 0:
            continue
        every = use.numel() == hu.shape[0]

        def pick(t: torch.Tensor, use=use, every=every) -> torch.Tensor:
            return t if every else t.index_select(-1, use)
        th, tw = (h, w) if lv == 0 else mip_sizes(h, w)[lv]
        x = pick(hu) * (tw / w) - 0.5
        y = pick(hv) * (th / h) - 0.5
        surface = None
        if lv == 0:  # read only the surface the ray hit: facing it, at its depth
            r_use, d_use = pick(_rows_at(r, hr)), pick(d_hit)

            # depth of the pixels a ray can see (a zero normal faces nothing)
            dsurf = dfill[0].masked_fill(_dot(ncomp, ncomp) <= NORMALIZE_EPS, FAR_DEPTH)

            def surface(tap: torch.Tensor, r_use=r_use, d_use=d_use,
                        dsurf=dsurf) -> torch.Tensor:
                nrm = [c.index_select(0, tap) for c in ncomp]
                near = torch.le((dsurf.index_select(0, tap) - d_use).abs_(), thickness,
                                out=torch.empty_like(d_use))
                return near.mul_(torch.lt(_dot(nrm, r_use), 0.0, out=torch.empty_like(d_use)))
        read = _bilinear(pyramid[lv], pick(hb), x, y, th, tw, surface)
        read = read * pick(wgt).to(image.dtype)
        col = col + read if every else col.index_add(1, use, read)
    cov = col[3]
    seen = (cov >= MIN_COVERAGE).to(col.dtype)
    rgb = col[:3] / cov.clamp_min(MIN_COVERAGE) * seen

    edge = torch.minimum(torch.minimum(hu, w - hu), torch.minimum(hv, h - hv))
    conf = smoothstep(edge / (edge_fade * min(h, w))) if edge_fade > 0 else torch.ones_like(hu)
    conf = conf * smoothstep((max_roughness - rough) / (0.25 * max_roughness)) * seen
    return _Hits(target, hb, rgb, conf)


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
        stats: optional dict, filled with ``"rays"`` (rays marched), ``"steps"`` (march
            iterations run: the march ends when every ray has hit or missed, so this is
            at most :func:`march_step_bound` ``(H, W)`` whatever ``max_steps``) and
            ``"ray_steps"`` (ray-steps computed: the march's work).

    Returns:
        ``(reflection (B, 3, H, W), confidence (B, 1, H, W))``; both 0 where the ray missed
        or was not marched.
    """
    hits = _trace_packed(image, depth, normals, roughness, intrinsics, max_steps=max_steps,
                         thickness=thickness, max_roughness=max_roughness,
                         edge_fade=edge_fade, refine_steps=refine_steps,
                         max_distance=max_distance, blur=blur, stats=stats)
    b, _, h, w = depth.shape
    reflection = image.new_zeros(b, 3, h, w)
    confidence = depth.new_zeros(b, 1, h, w)
    if hits is None:
        return reflection, confidence
    reflection = reflection.reshape(-1).index_copy(
        0, _channels(hits, h * w), hits.rgb.to(reflection.dtype).reshape(-1)).reshape(b, 3, h, w)
    confidence = confidence.reshape(-1).index_copy(
        0, hits.pixel, hits.confidence.to(confidence.dtype)).reshape(b, 1, h, w)
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
        >>> from torchraster.shading.surface import Surface
        >>> metal = Surface(albedo=image, metallic=torch.ones_like(rough), roughness=rough)
        >>> out = SSR()(image, depth, normals, metal, projection=proj)
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
        surface: Surface,
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
            surface: the material, by name: a
                :class:`~torchraster.shading.surface.Surface` (or the lighting pass's
                ``PixelSurface``) with ``albedo`` ``(B, 3, H, W)``, ``metallic`` and
                ``roughness`` ``(B, 1, H, W)``.
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
        if not isinstance(surface, Surface):
            raise TypeError(f"surface: expected a torchraster.shading.Surface (albedo, "
                            f"metallic, roughness), got {type(surface).__name__}")
        roughness = check_tensor("surface.roughness", surface.roughness, (b, 1, h, w),
                                 floating=True, finite=True)
        metallic = check_tensor("surface.metallic", surface.metallic, (b, 1, h, w),
                                floating=True, finite=True)
        albedo = check_tensor("surface.albedo", surface.albedo, (b, 3, h, w), floating=True,
                              finite=True)
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
        intrinsics = intrinsics.to(device=image.device, dtype=dt)
        hits = _trace_packed(
            img, dep, normals.to(dt), roughness.to(dt), intrinsics, max_steps=self.max_steps,
            thickness=self.thickness, max_roughness=self.max_roughness,
            edge_fade=self.edge_fade, refine_steps=self.refine_steps,
            max_distance=self.max_distance, blur=self.blur)
        out, maps = _composite(  # at the hit pixels only
            img, hits, normals.to(dt), intrinsics, albedo.to(dt), metallic.to(dt),
            roughness.to(dt), None if fallback is None else fallback.to(dt),
            None if weight is None else weight.to(dt), return_maps)
        out = out.to(image.dtype)
        if return_maps:
            return SSRMaps(out, *(m.to(image.dtype) for m in maps))
        return out
