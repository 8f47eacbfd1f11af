"""Pre-integrated GGX lobes of an environment: the specular of ``specular="table"``.

The split sum reads one isotropic kernel of the prefiltered chain, which cannot follow the
true single-scattering lobe ``D(n.h) V(n.v, n.l) (n.l)`` once it is stretched in the plane
of incidence and cut by the horizon (12 % mean error at roughness 0.6 on venice_sunset_1k,
docs/benchmarks.md, ibl-specular). This module tabulates the lobe's mean radiance
exactly instead, per environment, for a few roughness levels.

For a unit normal n and view v, with ``c = n.v`` and ``R = reflect(-v, n)``, the normal
lies at angle ``acos(c)`` from R (``n.R = n.v``) in some direction ``psi`` of R's tangent
plane, measured from the lat-long frame at R (``e_theta`` towards the south pole,
``e_phi`` east). ``(R, c, psi)`` fix n and v, hence the lobe. The table holds

    T(R, c, psi) = sum_l L(l) w(l) / sum_l w(l),   w = D(n.h) V(n.v, n.l) (n.l)^+ dw_l

summed over every texel l of the map resampled to the level's grid, for R at the texel
centres of that grid, ``views`` nodes of ``theta_v = acos(c)`` in [0, pi/2] and
``azimuths`` nodes of psi in [0, 2 pi). The yaw symmetry of the lat-long layout makes the
weight between the texels of rows (i, j) depend only on the column offset, so each output
row is a sum over source rows of circular correlations along the rows (real FFTs, like
the chain's :func:`~torchraster.shading.ibl._prefilter_rows`), and mirroring psi mirrors
the offset (half the azimuths are conjugate transforms of the others).

A lookup is trilinear over (R's texel, psi) within a (level, view node) block of one 3-D
atlas, and linear across the two levels and the two view nodes around the pixel's
roughness and ``c``: four points of one ``grid_sample``. The first view interval is
interpolated in ``1 - c`` (the table is even in theta_v there), the others in theta_v, so
the coordinate has a finite derivative everywhere.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from torchraster._validate import check_tensor
from torchraster.numerics import compute_dtype, dot, grid_sample
from torchraster.shading.brdf import MIN_COS, MIN_ROUGHNESS
from torchraster.texture import (
    latlong_directions,
    latlong_solid_angles,
    latlong_uv,
    pad_texture,
    sample_latlong,
)

__all__ = [
    "TABLE_MIN_ROUGHNESS",
    "TABLE_BLEND",
    "table_roughness",
    "table_rows",
    "lobe_radiance_level",
    "specular_table",
    "table_atlas",
    "lookup_specular_table",
]

#: Roughness of the table's sharpest level. Below it the lobe is narrow enough for the
#: split sum (the table's grid would need ~ 4.4 / r^2 rows).
TABLE_MIN_ROUGHNESS: float = 0.3
#: Width of the roughness band below :data:`TABLE_MIN_ROUGHNESS` over which ``shade_ibl``
#: blends from the split sum to the table.
TABLE_BLEND: float = 0.1
#: Normal-to-reflection angle's squared tangent length below which psi is undefined (the
#: table does not depend on it there).
_PSI_EPS: float = 1e-12


def table_roughness(levels: int) -> list[float]:
    """Perceptual roughness of the table's ``levels`` levels: evenly spaced from
    :data:`TABLE_MIN_ROUGHNESS` to 1."""
    if isinstance(levels, bool) or not isinstance(levels, int) or levels < 2:
        raise ValueError(f"levels: expected an int >= 2, got {levels!r}")
    step = (1.0 - TABLE_MIN_ROUGHNESS) / (levels - 1)
    return [TABLE_MIN_ROUGHNESS + k * step for k in range(levels)]


def table_rows(roughness: float, min_rows: int = 24) -> int:
    """Rows of a level's ``h x 2h`` grid: ``max(min_rows, ceil(4.4 / r^2))``, about two
    texels per half-width of the reflected lobe (``~1.3 r^2`` rad)."""
    return max(int(min_rows), math.ceil(4.4 / max(roughness, 1e-3) ** 2))


def _frame(theta: torch.Tensor, phi: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Lat-long direction and its tangent frame (e_theta south, e_phi east), ``(..., 3)``
    each, in the layout of :func:`~torchraster.texture.latlong_directions`."""
    st, ct, sp, cp = torch.sin(theta), torch.cos(theta), torch.sin(phi), torch.cos(phi)
    d = torch.stack((st * sp, ct, -st * cp), -1)
    e_theta = torch.stack((ct * sp, -st, -ct * cp), -1)
    e_phi = torch.stack((cp, torch.zeros_like(cp), sp), -1)
    return d, e_theta, e_phi


def _view_nodes(views: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """theta_v of the view nodes, evenly spaced over [0, pi / 2], ``(views,)``."""
    return torch.linspace(0.0, math.pi / 2, views, dtype=dtype, device=device)


def lobe_radiance_level(
    src: torch.Tensor, roughness: float, views: int = 8, azimuths: int = 16,
    chunk: int = 2**22,
) -> torch.Tensor:
    """One level of the table on the grid of ``src`` itself.

    Args:
        src: ``(B, 3, h, 2h)`` lat-long radiance (already resampled to the level's grid).
        roughness: perceptual roughness of the level.
        views: nodes of theta_v = acos(n.v) over [0, pi / 2] (>= 2).
        azimuths: nodes of psi over [0, 2 pi) (even, >= 2).
        chunk: kernel weights evaluated at once (memory bound).

    Returns:
        ``(B, views, 3, azimuths, h, 2h)``: the lobe's mean radiance for R at each texel
        centre, differentiable w.r.t. ``src``.
    """
    b, _, h, w = src.shape
    if w != 2 * h:
        raise ValueError(f"src: expected a (B, 3, h, 2h) lat-long map, got {tuple(src.shape)}")
    if azimuths < 2 or azimuths % 2:
        raise ValueError(f"azimuths: expected an even int >= 2, got {azimuths!r}")
    dt, dev = src.dtype, src.device
    theta = (torch.arange(h, device=dev, dtype=dt) + 0.5) * (math.pi / h)
    phi = ((torch.arange(w, device=dev, dtype=dt) + 0.5) / w - 0.5) * (2 * math.pi)
    r_dir, e_t, e_p = _frame(theta, phi[:1].expand(h))  # R at column 0 of each row, (h, 3)
    l_dir = _frame(theta[:, None].expand(h, w), phi[None, :].expand(h, w))[0]  # (h, w, 3)
    dw = latlong_solid_angles(h, w, device=dev, dtype=dt).view(1, h, 1)
    # every slice's n.l and |l + v|^2 from l - R (exact differences of unit vectors, so the
    # half vector stays accurate in float32 where l + v -> 0: grazing views, l near R):
    # q = |l - R|^2, t_l / p_l = e_t / e_p . (l - R), with n = c R + s (cos psi e_t +
    # sin psi e_p) and v = 2 c n - R:  n.l = c (1 - q / 2) + s tang_l,
    # |l + v|^2 = q (1 - 2 c^2) + 4 c s tang_l + 4 c^2
    diff = l_dir[None] - r_dir[:, None, None]  # (h_o, h_s, w, 3)
    q = diff.square().sum(-1)
    t_l, p_l = (torch.einsum("oi,ojwi->ojw", e, diff) for e in (e_t, e_p))
    del diff
    a = max(roughness, MIN_ROUGHNESS) ** 2
    spec = torch.fft.rfft(src, dim=-1)  # (B, 3, h, w/2 + 1)
    half = azimuths // 2
    psi = torch.arange(half + 1, device=dev, dtype=dt) * (2 * math.pi / azimuths)
    out = src.new_empty(b, views, 3, azimuths, h, w)
    per = max(1, chunk // (h * h * w))
    for k, tv in enumerate(_view_nodes(views, dt, dev).tolist()):
        c = max(math.cos(tv), 1e-4)  # MIN_N_DOT_V of shade_ibl
        s = math.sqrt(1.0 - c * c)
        slices = psi[:1] if k == 0 else psi  # n = R: psi does not matter
        for i0 in range(0, slices.numel(), per):
            ps = slices[i0 : i0 + per].view(-1, 1, 1, 1)
            tang_l = torch.cos(ps) * t_l + torch.sin(ps) * p_l
            n_dot_l = c * (1.0 - 0.5 * q) + s * tang_l
            lv2 = q * (1.0 - 2.0 * c * c) + (4.0 * c * s) * tang_l + 4.0 * c * c
            n_dot_h = ((n_dot_l + c) * torch.rsqrt(lv2.clamp_min(1e-30))).clamp(0.0, 1.0)
            # GGX D and height-correlated Smith V (Filament's forms, as shading/brdf.py)
            k_d = a / (1.0 - n_dot_h * n_dot_h + (n_dot_h * a) ** 2)
            nl = n_dot_l.clamp(MIN_COS, 1.0)
            vis = 0.5 / (nl * math.sqrt(c * c * (1.0 - a * a) + a * a)
                         + c * torch.sqrt(nl * nl * (1.0 - a * a) + a * a))
            weight = (k_d * k_d) * vis * (n_dot_l.clamp_min(0.0) * dw) * (1.0 / math.pi)
            total = weight.sum((-1, -2))  # (S, h_o)
            ker = torch.fft.rfft(weight, dim=-1)
            spec_c = spec.to(ker.dtype)
            # correlation along the row: conj(K) E; the mirrored psi (2 pi - psi, offsets
            # negated) is the conjugate kernel, K E
            fwd = torch.fft.irfft(torch.einsum("sojf,bcjf->bscof", ker.conj(), spec_c), n=w)
            fwd = fwd / total[None, :, None, :, None]
            idx = torch.arange(i0, i0 + ps.numel(), device=dev)
            if k == 0:
                out[:, 0] = fwd[:, :1].expand(-1, azimuths, -1, -1, -1).transpose(1, 2)
                continue
            out[:, k, :, idx] = fwd.transpose(1, 2)
            mirror = (idx > 0) & (idx < half)
            if bool(mirror.any()):
                bwd = torch.fft.irfft(torch.einsum("sojf,bcjf->bscof", ker[mirror], spec_c),
                                      n=w) / total[mirror][None, :, None, :, None]
                out[:, k, :, azimuths - idx[mirror]] = bwd.transpose(1, 2)
    return out


def specular_table(
    env: torch.Tensor, *, levels: int = 8, views: int = 8, azimuths: int = 16,
    min_rows: int = 24,
) -> list[torch.Tensor]:
    """The table's levels for a lat-long radiance map.

    Args:
        env: ``(B, 3, He, We)`` lat-long radiance.
        levels: roughness levels, :func:`table_roughness` (>= 2).
        views, azimuths: nodes of theta_v and psi (:func:`lobe_radiance_level`).
        min_rows: fewest rows of a level's grid (:func:`table_rows`).

    Returns:
        list of ``levels`` tensors ``(B, views, 3, azimuths, h_k, 2 h_k)`` in the compute
        dtype of ``env`` (float32 for half precision), differentiable w.r.t. ``env``.
    """
    check_tensor("env", env, ("B", 3, "He", "We"), floating=True)
    for name, val, lo in (("views", views, 2), ("azimuths", azimuths, 2),
                          ("min_rows", min_rows, 2)):
        if isinstance(val, bool) or not isinstance(val, int) or val < lo:
            raise ValueError(f"{name}: expected an int >= {lo}, got {val!r}")
    env = env.to(compute_dtype(env))
    out = []
    for rough in table_roughness(levels):
        h = table_rows(rough, min_rows)
        if h < env.shape[-2]:
            src = F.adaptive_avg_pool2d(env, (h, 2 * h))
        elif h > env.shape[-2] or env.shape[-1] != 2 * h:  # bilinear, as the lookups
            d = latlong_directions(h, 2 * h, device=env.device, dtype=env.dtype)
            src = sample_latlong(env, d.expand(env.shape[0], -1, -1, -1))
        else:
            src = env
        out.append(lobe_radiance_level(src, rough, views, azimuths))
    return out


def table_atlas(levels: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Pack the table's levels into one lat-long atlas for bilinear lookups.

    Each (level, view node, azimuth) slice ``(B, 3, h, 2h)`` is padded by one texel (wrap
    in u, clamp in v, :func:`~torchraster.texture.pad_texture`); a level's slices form a
    grid of ``views`` rows by ``azimuths`` columns, and the levels are stacked below each
    other. (A 2-D atlas: ``grid_sample`` in 2-D is several times faster on the CPU than
    a 3-D lookup of the same points.)

    Args:
        levels: :func:`specular_table` output.

    Returns:
        ``(B, 3, Ha, Wa)`` atlas and a ``(levels, views, azimuths, 4)`` table of each
        unpadded slice's (row offset, column offset, height, width), same dtype.
    """
    b, views, _, az, _, _ = levels[0].shape
    wa = max(az * (lv.shape[-1] + 2) for lv in levels)
    ha = sum(views * (lv.shape[-2] + 2) for lv in levels)
    atlas = levels[0].new_zeros(b, 3, ha, wa)
    rows, y = [], 0
    for lv in levels:
        h, w = lv.shape[-2:]
        pad = pad_texture(lv.permute(0, 1, 3, 2, 4, 5).reshape(-1, 3, h, w), "wrap", "clamp")
        grid = pad.view(b, views, az, 3, h + 2, w + 2).permute(0, 3, 1, 4, 2, 5)
        atlas[:, :, y:y + views * (h + 2), : az * (w + 2)] = grid.reshape(
            b, 3, views * (h + 2), az * (w + 2))
        rows += [[y + k * (h + 2), a * (w + 2), h, w] for k in range(views) for a in range(az)]
        y += views * (h + 2)
    table = torch.tensor(rows, dtype=atlas.dtype, device=atlas.device)
    return atlas, table.view(len(levels), views, az, 4)


def _view_coordinate(c: torch.Tensor, views: int) -> torch.Tensor:
    """Fractional view node of ``c = n.v``: linear in ``1 - c`` on the first interval
    (the table is even in theta_v at 0), linear in theta_v beyond; finite derivative."""
    step = (math.pi / 2) / (views - 1)
    c1 = math.cos(step)
    near = (1.0 - c) / (1.0 - c1)
    far = 1.0 + (torch.acos(torch.where(c < c1, c, c1).clamp(-1.0, 1.0)) - step) / step
    return torch.where(c >= c1, near, far).clamp(0.0, views - 1.0)


def lookup_specular_table(
    volume: torch.Tensor, blocks: torch.Tensor, n: torch.Tensor, v: torch.Tensor,
    roughness: torch.Tensor,
) -> torch.Tensor:
    """Mean radiance of the GGX lobe of env-space unit normals / views from a
    :func:`table_atlas`.

    Args:
        volume, blocks: :func:`table_atlas` output.
        n, v: ``(B, 3, H, W)`` unit normal and view direction, env space.
        roughness: ``(B, 1, H, W)`` perceptual roughness (clamped to the table's range).

    Returns:
        ``(B, 3, H, W)`` in the compute dtype of ``n``; differentiable w.r.t. ``volume``,
        ``n``, ``v`` and ``roughness`` (whose level fraction is linear).
    """
    b, _, hh, ww = n.shape
    p = hh * ww
    n_levels, views, az = blocks.shape[:3]
    dt = compute_dtype(n)
    n, v, roughness = n.to(dt), v.to(dt), roughness.to(dt)
    c = dot(n, v).clamp(1e-4, 1.0)
    r_dir = 2.0 * c * n - v
    uv = latlong_uv(r_dir)  # (B, 2, H, W)
    # psi = atan2(t.e_phi, t.e_theta) for the tangent t = n - c R and R's lat-long frame
    # e_phi = (-z, 0, x) / rho, e_theta = R x e_phi = (x y, -rho^2, y z) / rho (the common
    # 1 / rho cancels in atan2)
    rx, ry, rz = r_dir[:, 0:1], r_dir[:, 1:2], r_dir[:, 2:3]
    tang = n - c * r_dir
    tx, ty, tz = tang[:, 0:1], tang[:, 1:2], tang[:, 2:3]
    x = ry * (tx * rx + tz * rz) - ty * (rx * rx + rz * rz)
    y = tz * rx - tx * rz
    small = x * x + y * y < _PSI_EPS  # n = R or R at a pole: psi is free (double where)
    psi = torch.atan2(torch.where(small, 0.0, y), torch.where(small, 1.0, x))
    fa = torch.remainder(psi, 2 * math.pi) * (az / (2 * math.pi))  # (B, 1, H, W)
    fl = ((roughness.clamp(TABLE_MIN_ROUGHNESS, 1.0) - TABLE_MIN_ROUGHNESS)
          / (1.0 - TABLE_MIN_ROUGHNESS) * (n_levels - 1))
    fc = _view_coordinate(c, views)
    l0 = fl.detach().floor().clamp(0, n_levels - 2)
    c0 = fc.detach().floor().clamp(0, views - 2)
    a0 = fa.detach().floor().clamp(0, az - 1)
    wl, wc, wa = (fl - l0).clamp(0.0, 1.0), (fc - c0).clamp(0.0, 1.0), (fa - a0).clamp(0.0, 1.0)
    lv = torch.stack((l0, l0 + 1)).long()  # (2, B, 1, H, W): the two levels
    per_level = blocks[:, 0, 0].to(dt)  # (L, 4): row offset, -, h, w of each level
    oy, h, w = per_level[:, 0][lv], per_level[:, 2][lv] + 2.0, per_level[:, 3][lv] + 2.0
    u = torch.remainder(uv[:, :1], 1.0)
    vv = 1.0 - uv[:, 1:].clamp(0.0, 1.0)  # row 0 of the map is v = 1
    # slices of a level form a (views, az) grid of padded (h + 2, w + 2) blocks
    x0 = u * (w - 2.0) + 0.5 + a0 * w
    y0 = oy + vv * (h - 2.0) + 0.5 + c0 * h
    wrap = torch.where(a0 == az - 1, 1.0 - az, 1.0)  # azimuth a0 + 1 (mod az)
    xs = torch.stack((x0, x0 + wrap * w), 1)  # (2 levels, 2 azimuths, B, 1, H, W)
    ys = torch.stack((y0, y0 + h), 1)  # (2 levels, 2 views, ...)
    grid = torch.stack((xs[:, None].expand(-1, 2, -1, -1, -1, -1, -1),
                        ys[:, :, None].expand(-1, -1, 2, -1, -1, -1, -1)), -1)
    ha, wa_ = volume.shape[-2:]
    grid = grid * grid.new_tensor([2.0 / (wa_ - 1), 2.0 / (ha - 1)]) - 1.0
    grid = grid.permute(3, 0, 1, 2, 4, 5, 6, 7).reshape(b, 1, 8 * p, 2)
    src = volume.to(dt)
    if src.shape[0] != b:
        src = src.expand(b, -1, -1, -1)
    s = grid_sample(src, grid, mode="bilinear", padding_mode="border",
                    align_corners=True)[:, :, 0]  # (B, 3, 8P): (level, view, azimuth) major
    w_l, w_c, w_a = (torch.stack((1.0 - t, t)) for t in (wl, wc, wa))
    wts = w_l[:, None, None] * w_c[None, :, None] * w_a[None, None, :]  # (2, 2, 2, B, 1, H, W)
    out = (s.view(b, 3, 8, p) * wts.permute(3, 4, 0, 1, 2, 5, 6).reshape(b, 1, 8, p)).sum(2)
    return out.view(b, 3, hh, ww)

