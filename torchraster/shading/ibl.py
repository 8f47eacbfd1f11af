"""Image-based lighting from an equirectangular HDR environment (split-sum approximation).

Sources: Karis 2013, "Real Shading in Unreal Engine 4" (split sum, GGX importance sampling,
DFG LUT); Filament, "Physically Based Rendering in Filament", section 5.3 (image based
lights: roughness -> lod mapping, f90, multiple-scattering energy compensation after
Fdez-Aguera 2019); Ramamoorthi & Hanrahan 2001, "An Efficient Representation for Irradiance
Environment Maps" (9 SH coefficients); Colbert & Krivanek 2007, "GPU-Based Importance
Sampling" and Krivanek & Colbert 2008, GPU Gems 3 ch. 20 (filtered importance sampling:
sample lod from the sample's solid angle); Lagarde & de Rousiers 2014, "Moving Frostbite to
PBR" (the specular dominant direction).

Outgoing radiance at a surface point with normal n, view direction v (towards the eye),
reflection r = reflect(-v, n)::

    E    = f0 * A(n.v, rough) + f90 * B(n.v, rough)           # single-scatter DFG
    ms   = 1 + f0 (1 / (A + B) - 1)                           # multiple scattering
    spec = prefiltered(bend(r, n), rough_eff) * E * ms         # lobe_table
    diff = (1 - metallic) albedo * irradiance(n) / pi * (1 - E * ms)
    out  = ao * (diff + spec)

(``bend`` = ``normalize(n + s (r - n))``; ``s`` and ``rough_eff`` from
:func:`lobe_table` at (rough, n.v): the lobe's mean direction and spread.) ``ms`` and the
diffuse reduction are the energy convention of :mod:`torchraster.shading.energy`, the same
for punctual and ambient light; both are off with ``multiscatter=False``. With
``specular="importance"`` the prefiltered lookup is replaced by :func:`specular_importance`,
the lobe's mean radiance by per-pixel filtered importance sampling; with
``specular="table"`` by a table of the exact lobe's mean radiance per environment
(:mod:`torchraster.shading.ibl_table`, roughness >= 0.3; blended into the split sum
between 0.2 and 0.3). With
``Environment(sun_threshold=...)`` the map's sun is split off (:func:`extract_sun`): the
chain holds the residual and ``spec`` gains the sun's exact GGX term
(:func:`sun_specular`) before ``ms``.

Diffuse irradiance comes from a brute-force irradiance map (default, :func:`irradiance_map`)
or from 9 SH coefficients (:func:`sh_project`, :func:`irradiance_sh`); scripts/bench_quality.py
measures both against a full brute-force integral.

All directions are world space, y up; the environment's lat-long layout is that of
:func:`torchraster.texture.latlong_uv` (image centre = -z). The environment can be rotated
(``R``: an env-space direction d appears in the world at ``R d``) and scaled (intensity).
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from functools import lru_cache

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.checkpoint import checkpoint

from torchraster._validate import check_radiance, check_tensor
from torchraster.numerics import (
    DIELECTRIC_F0,
    compute_dtype,
    diffuse_color,
    dot,
    finish_low_precision,
    grid_sample,
    safe_normalize,
    specular_f0,
)
from torchraster.shading.brdf import MIN_ROUGHNESS, d_ggx, v_smith_ggx_correlated
from torchraster.shading.energy import MIN_DFG_ALBEDO, energy_terms
from torchraster.shading.ibl_table import (
    TABLE_BLEND,
    TABLE_MIN_ROUGHNESS,
    lookup_specular_table,
    specular_table,
    table_atlas,
)
from torchraster.shading.lights import (  # one SH basis for ambient lights and IBL
    SH_C0,
    SH_C1,
    SH_C2,
    SH_C20,
    SH_C22,
    sh_basis,
    sh_irradiance,
)
from torchraster.texture import (
    build_mip_pyramid,
    latlong_directions,
    latlong_solid_angles,
    latlong_uv,
    pad_texture,
    sample_latlong,
    sample_padded,
)

__all__ = [
    "ENV_CACHE_BYTES",
    "QUADRATURE_CHUNK",
    "content_key",
    "MIN_N_DOT_V",
    "MIN_DFG_ALBEDO",
    "FIS_LOD_BIAS",
    "MIN_LEVEL_HEIGHT",
    "Environment",
    "yaw_rotation",
    "sh_basis",
    "sh_project",
    "irradiance_sh",
    "irradiance_map",
    "roughness_to_lod",
    "lod_to_roughness",
    "hammersley",
    "prefilter_specular",
    "dfg_lut",
    "lookup_dfg",
    "specular_importance",
    "latlong_atlas",
    "IBL_PIXEL_CHUNK",
    "IMPORTANCE_CHUNK",
    "dominant_direction",
    "lobe_table",
    "fitted_lobe",
    "SPECULAR_MODES",
    "SUN_CONE",
    "extract_sun",
    "sun_specular",
    "shade_ibl",
]

#: IBL specular methods: the split-sum prefiltered chain (one lookup a pixel), the same
#: chain at the lobe's fitted mean and spread, the pre-integrated lobe table
#: (:mod:`torchraster.shading.ibl_table`) or per-pixel filtered importance sampling of the
#: GGX lobe (:func:`specular_importance`).
SPECULAR_MODES: tuple[str, ...] = ("split_sum", "fitted", "table", "importance")

#: Default size and samples of the split-sum DFG table :func:`shade_ibl` reads (coarser than
#: the lighting pass's ``energy.DFG_LUT_SIZE``: its error hides under the prefiltered map's).
IBL_LUT_SIZE: int = 16
IBL_LUT_SAMPLES: int = 32

#: Floor on n.v (Filament clamps NoV to 1e-4): keeps the DFG lookup and the reflection
#: well defined at grazing and back-facing views.
MIN_N_DOT_V: float = 1e-4

#: Extra lod for filtered importance sampling. Colbert & Krivanek 2007 use +1 (one level
#: blurrier than the sample's footprint, to hide noise); measured against a brute-force lobe
#: on venice_sunset_1k that bias costs accuracy (r = 0.24, 32 samples: 4.8 % mean error
#: with +1, 1.3 % with 0), so none is added. The same holds per pixel
#: (:func:`specular_importance`, n != v, 16 samples, r = 0.55: 10 % with 0, 18 % with +1).
FIS_LOD_BIAS: float = 0.0

#: (output texel, source texel) pairs whose weights are formed at once by the brute-force
#: quadratures (:func:`irradiance_map`): 2**22 float32 weights = 16 MB per chunk.
QUADRATURE_CHUNK: int = 2**22

#: Bytes of precomputed environment data (prefiltered specular chains, irradiance maps, SH
#: coefficients) kept across :class:`Environment` objects, keyed by the radiance's content
#: (a hash of its bytes, shape, dtype, device) and the knobs: a new Environment of the same
#: map reuses them. Least recently used entries are dropped first; 0 disables the cache.
ENV_CACHE_BYTES: int = 256 * 2**20

#: Smallest height of a prefiltered level / quadrature source (lat-long rows): even the
#: roughness-1 lobe has features (a sun crossing the horizon of the lobe) that 8 rows
#: (22 degree texels) interpolate with ~2 % error.
MIN_LEVEL_HEIGHT: int = 32


def yaw_rotation(angle: float | torch.Tensor, *, dtype: torch.dtype | None = None) -> torch.Tensor:
    """Rotation about +y by ``angle`` radians (right-handed): ``(3, 3)`` or ``(B, 3, 3)``.

    Evaluated in float64 (so cos(pi/2) is ~1e-17, not ~4e-8) and returned in ``dtype``
    (default: the angle tensor's floating dtype, else torch's default dtype)."""
    if dtype is None:
        is_float = isinstance(angle, torch.Tensor) and angle.is_floating_point()
        dtype = angle.dtype if is_float else torch.get_default_dtype()
    a = angle.to(torch.float64) if isinstance(angle, torch.Tensor) else torch.tensor(
        float(angle), dtype=torch.float64
    )
    c, s = torch.cos(a), torch.sin(a)
    z, o = torch.zeros_like(a), torch.ones_like(a)
    rot = torch.stack(
        (torch.stack((c, z, s), -1), torch.stack((z, o, z), -1), torch.stack((-s, z, c), -1)), -2
    )
    return rot.to(dtype)


# ---------------------------------------------------------------------- spherical harmonics


@lru_cache(maxsize=8)
def _texel_sh_integrals(height: int, width: int) -> torch.Tensor:
    """``(9, H, W)`` float64: the exact integral of each SH basis function over each texel
    of an ``H x W`` lat-long map (theta from +y, x = s sin(phi), y = cos(theta),
    z = -s cos(phi), s = sin(theta)).

    Every basis function is a sum of products f(theta) g(phi), so a texel integral is a sum
    of products of 1-D integrals, each done with 8-point Gauss-Legendre per row / column
    (exact to rounding for these smooth integrands on small intervals)."""
    xg, wg = (torch.from_numpy(a) for a in np.polynomial.legendre.leggauss(8))

    def integrate(n: int, span: float, offset: float, f) -> torch.Tensor:  # noqa: ANN001
        lo = torch.arange(n, dtype=torch.float64) * (span / n) + offset
        t = lo[:, None] + (xg[None] + 1.0) * (0.5 * span / n)
        return (f(t) * wg[None]).sum(1) * (0.5 * span / n)

    def th(f) -> torch.Tensor:  # noqa: ANN001  (the sin(theta) Jacobian is included here)
        return integrate(height, math.pi, 0.0, lambda t: f(t) * torch.sin(t))[:, None]

    def ph(g) -> torch.Tensor:  # noqa: ANN001
        return integrate(width, 2.0 * math.pi, -math.pi, g)[None, :]

    sn, cs = torch.sin, torch.cos
    one = torch.ones_like
    s2 = lambda t: sn(t) ** 2  # noqa: E731
    terms = [
        SH_C0 * th(one) * ph(one),
        SH_C1 * th(cs) * ph(one),  # y
        SH_C1 * th(sn) * ph(lambda p: -cs(p)),  # z
        SH_C1 * th(sn) * ph(sn),  # x
        SH_C2 * th(lambda t: sn(t) * cs(t)) * ph(sn),  # xy
        SH_C2 * th(lambda t: cs(t) * sn(t)) * ph(lambda p: -cs(p)),  # yz
        SH_C20 * (3.0 * th(s2) * ph(lambda p: cs(p) ** 2) - th(one) * ph(one)),  # 3z^2 - 1
        SH_C2 * th(s2) * ph(lambda p: -sn(p) * cs(p)),  # xz
        SH_C22 * (th(s2) * ph(lambda p: sn(p) ** 2) - th(lambda t: cs(t) ** 2) * ph(one)),
    ]
    return torch.stack(terms, 0)


def sh_project(env: torch.Tensor) -> torch.Tensor:
    """Project a lat-long radiance map ``(B, 3, He, We)`` onto 9 SH coefficients ``(B, 9, 3)``.

    ``L_lm = sum_texels L_texel * integral_texel Y_lm dw``: exact for the piecewise-constant
    map (the per-texel basis integrals are computed once per size and cached), so e.g. a
    uniform map has exactly zero bands 1 and 2.
    """
    check_tensor("env", env, ("B", 3, "He", "We"), floating=True)
    he, we = env.shape[-2:]
    basis = _texel_sh_integrals(he, we).to(device=env.device, dtype=env.dtype)
    return torch.einsum("khw,bchw->bkc", basis, env)


def irradiance_sh(sh: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Irradiance (W/m^2) from 9 SH radiance coefficients (Ramamoorthi & Hanrahan 2001).

    Args:
        sh: ``(B, 9, 3)`` coefficients from :func:`sh_project` (B may be 1).
        n: ``(B, 3, H, W)`` normals (normalised here; a zero normal gives the mean
            irradiance ``pi * L_00 * Y_00``).

    Returns:
        ``(B, 3, H, W)`` irradiance, clamped at 0 (order-2 ringing can dip below).
    """
    check_tensor("sh", sh, ("B", 9, 3), floating=True)
    check_tensor("n", n, ("B", 3, "H", "W"), floating=True)
    return sh_irradiance(sh.expand(n.shape[0], -1, -1), safe_normalize(n)).clamp_min(0.0)


def irradiance_map(
    env: torch.Tensor, *, height: int = 16, source_height: int | None = 32
) -> torch.Tensor:
    """Brute-force irradiance map: ``E(n) = sum_texels L max(0, n.w) dw`` for the texel
    centres of an ``height x 2 height`` lat-long map (look it up bilinearly by normal).

    Args:
        env: ``(B, 3, He, We)`` lat-long radiance.
        height: rows of the output map.
        source_height: the env is box-downsampled to this height first (None: full).

    Returns:
        ``(B, 3, height, 2 height)`` irradiance (W/m^2), exact for the (downsampled) map.
    """
    check_tensor("env", env, ("B", 3, "He", "We"), floating=True)
    if source_height is not None and env.shape[-2] > source_height:
        env = F.adaptive_avg_pool2d(env, (int(source_height), 2 * int(source_height)))
    b, _, hs, ws = env.shape
    ds = latlong_directions(hs, ws, device=env.device, dtype=env.dtype).reshape(3, -1)
    dw = latlong_solid_angles(hs, ws, device=env.device, dtype=env.dtype).expand(hs, ws)
    no = latlong_directions(height, 2 * height, device=env.device, dtype=env.dtype)
    no = no.reshape(3, -1).T  # (No, 3)
    src = env.reshape(b * 3, -1).T  # (Ns, 3B)
    # Output directions in chunks of at most QUADRATURE_CHUNK (output, source) pairs: the
    # weight matrix of a 64-row map from a 512-row source alone would be 17 GB.
    step = max(1, QUADRATURE_CHUNK // ds.shape[1])
    dw = dw.reshape(1, -1)
    grad = env.requires_grad and torch.is_grad_enabled()
    w = env.new_empty(min(step, no.shape[0]), ds.shape[1]) if not grad else None  # reused
    e = env.new_empty(no.shape[0], b * 3) if not grad else None
    parts = []
    for i in range(0, no.shape[0], step):
        if grad:  # the weights are recomputed in backward, not kept
            parts.append(checkpoint(_weighted_sum, no[i:i + step], ds, dw, src,
                                    use_reentrant=False))
            continue
        wi = torch.mm(no[i:i + step], ds, out=w[:min(step, no.shape[0] - i)])
        wi.clamp_min_(0.0).mul_(dw)  # (n, Ns) cosine x solid angle
        torch.mm(wi, src, out=e[i:i + step])  # (n, 3B), no allocation per chunk
    if grad:
        e = torch.cat(parts)
    return e.T.reshape(b, 3, height, 2 * height)


def _weighted_sum(normals: torch.Tensor, dirs: torch.Tensor, solid_angle: torch.Tensor,
                  src: torch.Tensor) -> torch.Tensor:
    """``(n, 3B)`` sums over source texels of radiance x max(0, n.w) x solid angle, for
    normals ``(n, 3)``, source directions ``(3, Ns)``, solid angles ``(1, Ns)`` and radiance
    ``(Ns, 3B)``."""
    return ((normals @ dirs).clamp_min(0.0) * solid_angle) @ src


# --------------------------------------------------------------------- specular prefilter


def roughness_to_lod(roughness: torch.Tensor, num_levels: int) -> torch.Tensor:
    """Filament's mapping ``lod = (L - 1) * r (2 - r)`` (denser levels at low roughness)."""
    r = roughness.clamp(0.0, 1.0)
    return (num_levels - 1) * r * (2.0 - r)


def lod_to_roughness(lod: float, num_levels: int) -> float:
    """Inverse of :func:`roughness_to_lod`: ``r = 1 - sqrt(1 - lod / (L - 1))``."""
    t = min(max(lod / max(num_levels - 1, 1), 0.0), 1.0)
    return 1.0 - math.sqrt(1.0 - t)


def hammersley(n: int, *, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """``(n, 2)`` Hammersley points ``(i / n, radical_inverse_2(i))`` in [0, 1)^2."""
    i = torch.arange(n, dtype=torch.int64)
    bits = torch.zeros(n, dtype=torch.float64)
    scale, k = 0.5, i.clone()
    while bool((k > 0).any()):
        bits += (k & 1).double() * scale
        k >>= 1
        scale *= 0.5
    return torch.stack(((i.double() + 0.5) / n, bits), -1).to(dtype)


def _ggx_half_vectors(n: int, roughness: float, dtype: torch.dtype) -> torch.Tensor:
    """GGX-distributed half vectors in the local frame (z = normal), ``(n, 3)`` (Karis)."""
    xi = hammersley(n, dtype=torch.float64)
    a = max(roughness, MIN_ROUGHNESS) ** 2
    phi = 2.0 * math.pi * xi[:, 0]
    cos_t = torch.sqrt((1.0 - xi[:, 1]) / (1.0 + (a * a - 1.0) * xi[:, 1]))
    sin_t = torch.sqrt((1.0 - cos_t * cos_t).clamp_min(0.0))
    return torch.stack((sin_t * torch.cos(phi), sin_t * torch.sin(phi), cos_t), -1).to(dtype)


def _onb(nrm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Tangent frame of unit normals ``(B, 3, ...)`` (Duff et al. 2017, branchless)."""
    x, y, z = nrm[:, 0], nrm[:, 1], nrm[:, 2]
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (sign + z)
    b = x * y * a
    t = torch.stack((1.0 + sign * x * x * a, sign * b, -sign * x), 1)
    bt = torch.stack((b, sign + y * y * a, -y), 1)
    return t, bt


def _lobe_width(roughness: float) -> float:
    """Angular half-width (rad) of the reflected GGX lobe, ~1.3 alpha (n = v = r)."""
    return 1.3 * max(roughness, MIN_ROUGHNESS) ** 2


def _prefilter_quadrature(
    src: torch.Tensor, roughness: float, height: int, max_elems: int = 2**21
) -> torch.Tensor:
    """Brute-force convolution ``sum_j L_j D(n.h_j) (n.l_j)^+ dw_j / sum_j D (n.l)^+ dw_j``
    over every texel of ``src`` ``(B, 3, hs, ws)`` for the texel centres of an output map
    ``(B, 3, height, 2 height)``. With n = v: ``n.h = sqrt((1 + n.l) / 2)``. On the
    source's own grid the sum runs through :func:`_prefilter_rows` (the same weights)."""
    b, _, hs, ws = src.shape
    if height == hs and ws == 2 * hs:
        return _prefilter_rows(src, roughness)
    ds = latlong_directions(hs, ws, device=src.device, dtype=src.dtype).reshape(3, -1)
    dw = latlong_solid_angles(hs, ws, device=src.device, dtype=src.dtype).expand(hs, ws)
    dw = dw.reshape(-1)
    lsrc = src.reshape(b, 3, -1)
    no = latlong_directions(height, 2 * height, device=src.device, dtype=src.dtype)
    no = no.reshape(3, -1).T  # (No, 3)
    step = max(1, max_elems // ds.shape[1])
    outs = []
    for i in range(0, no.shape[0], step):
        c = no[i : i + step] @ ds  # (n, Ns) = n.l
        n_dot_h = torch.sqrt(((1.0 + c) * 0.5).clamp_min(0.0))
        w = d_ggx(n_dot_h, roughness) * c.clamp_min(0.0) * dw
        outs.append(torch.einsum("ns,bcs->bcn", w, lsrc) / w.sum(1))
    return torch.cat(outs, -1).reshape(b, 3, height, 2 * height)


def _prefilter_rows(src: torch.Tensor, roughness: float) -> torch.Tensor:
    """:func:`_prefilter_quadrature` onto the grid of ``src`` ``(B, 3, h, 2h)`` itself.

    Between texel centres of the same lat-long grid, ``n.l = cos t_o cos t_s + sin t_o
    sin t_s cos(p_o - p_s)`` depends on the two rows and the azimuth difference only, and
    that difference is a whole number of columns: each output row is a sum over source
    rows of circular correlations along the row, done with real FFTs (the kernel is even
    in the azimuth, so its transform is real). The weights are the brute force's; h x h x
    2h of them instead of (2 h^2)^2."""
    b, _, h, w = src.shape
    dt, dev = src.dtype, src.device
    theta = (torch.arange(h, device=dev, dtype=dt) + 0.5) * (math.pi / h)
    dphi = torch.arange(w, device=dev, dtype=dt) * (2 * math.pi / w)  # column offsets
    ct, st = torch.cos(theta), torch.sin(theta)
    c = (ct[:, None, None] * ct[None, :, None]
         + (st[:, None] * st[None, :])[..., None] * torch.cos(dphi))  # (h_o, h_s, w) = n.l
    n_dot_h = torch.sqrt(((1.0 + c) * 0.5).clamp_min(0.0))
    dw = latlong_solid_angles(h, w, device=dev, dtype=dt)  # (h, 1) per source row
    kernel = d_ggx(n_dot_h, roughness) * c.clamp_min(0.0) * dw.view(1, h, 1)
    spec = torch.fft.rfft(src, dim=-1)  # (B, 3, h_s, w/2 + 1)
    ker = torch.fft.rfft(kernel, dim=-1).real.to(spec.dtype)  # even kernel: real transform
    out = torch.fft.irfft(torch.einsum("osf,bcsf->bcof", ker, spec), n=w, dim=-1)
    return out / kernel.sum((1, 2)).view(1, 1, h, 1)


def _prefilter_importance(
    src_levels: list[torch.Tensor], roughness: float, height: int, samples: int, chunk: int
) -> torch.Tensor:
    """GGX importance sampling with filtered lookups (Karis 2013; Colbert & Krivanek 2007).

    The lod depends only on the sample (n = v), so samples are grouped by their two mip
    levels and each group is read with two bilinear lookups and scalar weights."""
    env = src_levels[0]
    b, _, he, we = env.shape
    omega_p = (2.0 * math.pi / we) * (math.pi / he)  # equator texel of level 0
    h = height
    nrm = latlong_directions(h, 2 * h, device=env.device, dtype=env.dtype)  # (1, 3, h, 2h)
    t, bt = _onb(nrm)
    hs = _ggx_half_vectors(samples, roughness, env.dtype).to(env.device)
    n_dot_l = 2.0 * hs[:, 2] ** 2 - 1.0  # n = v: n.l = 2 (n.h)^2 - 1
    keep = n_dot_l > 0
    hs, n_dot_l = hs[keep], n_dot_l[keep]
    pdf = d_ggx(hs[:, 2], roughness) / 4.0  # pdf(l) = D (n.h) / (4 v.h), n.h = v.h
    top = len(src_levels) - 1
    lod = (0.5 * torch.log2(1.0 / (samples * pdf * omega_p)) + FIS_LOD_BIAS).clamp(0, top)
    lo = lod.floor().long().clamp_max(max(top - 1, 0))
    frac = (lod - lo).tolist()
    padded: dict[int, torch.Tensor] = {}
    acc = torch.zeros(b, 3, h, 2 * h, device=env.device, dtype=env.dtype)
    for level in sorted(set(lo.tolist())):
        idx = (lo == level).nonzero().squeeze(1)
        for c0 in range(0, idx.numel(), chunk):
            sel = idx[c0 : c0 + chunk]
            m = sel.numel()
            hc = hs[sel]
            half = (
                t[:, :, None] * hc[:, 0].view(1, 1, m, 1, 1)
                + bt[:, :, None] * hc[:, 1].view(1, 1, m, 1, 1)
                + nrm[:, :, None] * hc[:, 2].view(1, 1, m, 1, 1)
            )  # (1, 3, S, h, 2h)
            ldir = 2.0 * hc[:, 2].view(1, 1, m, 1, 1) * half - nrm[:, :, None]
            uv = latlong_uv(ldir.reshape(1, 3, m * h, 2 * h))
            w_hi = torch.tensor([frac[i] for i in sel.tolist()], dtype=env.dtype,
                                device=env.device).view(1, 1, m, 1, 1)
            w = n_dot_l[sel].view(1, 1, m, 1, 1)
            for k, wk in ((level, 1.0 - w_hi), (min(level + 1, top), w_hi)):
                if k not in padded:
                    padded[k] = pad_texture(src_levels[k], "wrap", "clamp")
                vals = sample_padded(padded[k], uv[:, 0], uv[:, 1], "bilinear", ("wrap", "clamp"))
                acc = acc + (vals.view(b, 3, m, h, 2 * h) * (w * wk)).sum(2)
    return acc / n_dot_l.sum()


def prefilter_specular(
    env: torch.Tensor,
    *,
    size: int = 128,
    levels: int = 16,
    samples: int = 32,
    quadrature_budget: int = 2**25,
    texels_per_lobe: float = 4.0,
    source_height: int | None = None,
    chunk: int = 16,
) -> list[torch.Tensor]:
    """Prefiltered specular mip chain of a lat-long radiance map (Karis 2013, n = v = r).

    Level k holds, for roughness ``lod_to_roughness(k, levels)``, the GGX-weighted mean
    ``int L(l) D(n.h) (n.l)^+ dl / int D(n.h) (n.l)^+ dl`` around each texel direction n.
    Two ways to compute a level, chosen per level:

    * quadrature (exact for the source): the source is box-downsampled so that the lobe
      width spans ``texels_per_lobe`` texels (box-downsampled, or bilinearly upsampled when
      the source is coarser), and every output texel sums over every source texel (two
      matrix products). Used when ``out_texels * src_texels <= quadrature_budget`` -- the
      rough levels, where the lobe is wide and the sums are small -- and whenever the
      level has the resampled source's own grid (``h`` = the lobe's rows: the sums are
      then circular correlations along the rows, :func:`_prefilter_rows`, at any size).
    * GGX importance sampling with ``samples`` Hammersley samples, each read from the
      source's box mip pyramid at lod ``0.5 log2(Omega_s / Omega_p) + FIS_LOD_BIAS``
      (filtered importance sampling) -- the sharp levels, where few texels matter.

    Args:
        env: ``(B, 3, He, We)`` lat-long radiance.
        size: max height of the levels k >= 1 (each is ``h x 2h``, h chosen so that the
            lobe half-width spans ``texels_per_lobe`` texels, between MIN_LEVEL_HEIGHT and
            ``size``). Level 0 (roughness 0, a mirror) is the source itself.
        levels: number of roughness levels (>= 2).
        samples: GGX samples per texel for the importance-sampled levels.
        quadrature_budget: max texel pairs for a quadrature level (time / memory knob).
        texels_per_lobe: resolution of the levels and of the quadrature source, in texels
            per lobe half-width.
        source_height: levels k >= 1 are computed from the env box-downsampled to this
            height (None: full resolution). Level 0 always keeps the full map.
        chunk: samples evaluated at once (memory bound).

    Returns:
        list of ``levels`` tensors ``(B, 3, h_k, 2 h_k)``, differentiable w.r.t. ``env``.
    """
    check_tensor("env", env, ("B", 3, "He", "We"), floating=True)
    for name, val, lo in (("size", size, 1), ("levels", levels, 2), ("samples", samples, 1)):
        if int(val) != val or val < lo:
            raise ValueError(f"{name}: expected an int >= {lo}, got {val!r}")
    out = [env]
    if source_height is not None and env.shape[-2] > source_height:
        env = F.adaptive_avg_pool2d(env, (int(source_height), 2 * int(source_height)))
    he = env.shape[-2]
    src_levels: list[torch.Tensor] | None = None
    for k in range(1, levels):
        rough = lod_to_roughness(k, levels)
        need = max(MIN_LEVEL_HEIGHT, math.ceil(texels_per_lobe * math.pi / _lobe_width(rough)))
        h = int(min(size, he, need))  # never finer than the source
        hs = int(need)
        if h == hs or 2 * h * h * 2 * hs * hs <= quadrature_budget:  # (same grid: FFT)
            # quadrature on the source resampled to `need` rows: box-downsampled, or
            # bilinearly upsampled (the same reconstruction the lookups use)
            if hs < he:
                src = F.adaptive_avg_pool2d(env, (hs, 2 * hs))
            elif hs > he:
                d = latlong_directions(hs, 2 * hs, device=env.device, dtype=env.dtype)
                src = sample_latlong(env, d.expand(env.shape[0], -1, -1, -1))
            else:
                src = env
            out.append(_prefilter_quadrature(src, rough, h))
        else:
            if src_levels is None:
                src_levels = build_mip_pyramid(env)
            out.append(_prefilter_importance(src_levels, rough, h, samples, chunk))
    return out


# ------------------------------------------------------------------------------ DFG LUT


@lru_cache(maxsize=8)
def dfg_lut_uncached(size: int, samples: int) -> torch.Tensor:
    """float64 LUT ``(2, size, size)``: rows = roughness, columns = n.v, both from 0 to 1
    with nodes at the ends (n.v floored at 1e-4), looked up with ``align_corners=True``, so
    the common values roughness 1 and n.v 1 are table nodes, not extrapolated.

    Deterministic quadrature over the half vector (``dw_l = 4 (v.h) dw_h``; ``samples``
    nodes in theta_h, graded towards the pole so the GGX peak at MIN_ROUGHNESS is resolved,
    times 16 in phi over the symmetric half), divided by the same quadrature of the GGX
    normalisation integral (exactly 1), which cancels most of the error of resolving the
    peak. Accuracy against a fine table: docs/benchmarks.md, section quality-ibl.
    """
    f64, cpu = torch.float64, "cpu"  # built once on the CPU, cached, then moved
    nodes = torch.linspace(0.0, 1.0, size, dtype=f64, device=cpu)
    nv = nodes.clamp_min(1e-4).view(size, 1, 1)
    theta = 0.5 * math.pi * torch.linspace(0.0, 1.0, samples, dtype=f64, device=cpu) ** 3
    n_phi = 16
    phi = (torch.arange(n_phi, dtype=f64, device=cpu) + 0.5) * (math.pi / n_phi)
    st, ct = theta.sin().view(-1, 1), theta.cos().view(-1, 1)
    hx, hz = st * phi.cos(), ct.expand(-1, n_phi)
    vh = torch.sqrt(1.0 - nv * nv) * hx + nv * hz  # (N, T, P); v = (sin, 0, cos), n = z
    nl = 2.0 * vh * hz - nv
    ok = (vh > 0) & (nl > 0)
    fc = (1.0 - vh.clamp(0.0, 1.0)) ** 5
    table = torch.empty(2, size, size, dtype=f64, device=cpu)
    for i, rough in enumerate(nodes.tolist()):  # one roughness row at a time: bounded memory
        w = d_ggx(hz, rough) * v_smith_ggx_correlated(nv, nl.clamp_min(1e-12), rough)
        w = torch.where(ok, w * nl * 4 * vh, torch.zeros_like(w))
        inner = torch.stack([w * (1.0 - fc), w * fc]).mean(-1) * 2.0 * math.pi  # (2, N, T)
        norm = 2.0 * math.pi * torch.trapezoid(d_ggx(ct[:, 0], rough) * ct[:, 0] * st[:, 0],
                                               theta)
        table[:, i] = torch.trapezoid(inner * theta.sin(), theta, dim=-1) / norm
    return table


def dfg_lut(
    size: int = 16,
    samples: int = 96,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Split-sum DFG table (Karis 2013), computed once per (size, samples) and cached.

    ``samples``: quadrature nodes in the half-vector polar angle (see ``dfg_lut_uncached``).

    Channel 0 is the F0 scale ``A = int (1 - Fc) G_vis``, channel 1 the bias
    ``B = int Fc G_vis`` (``Fc = (1 - v.h)^5``, G_vis = height-correlated Smith visibility
    times ``4 (v.h) (n.l) / (n.h)``); ``A + B`` is the directional albedo for f0 = 1 used by
    the multiple-scattering compensation. Rows index perceptual roughness, columns n.v,
    both from 0 to 1 with nodes at the ends. Stored in ``dtype`` (float32 default).

    Returns:
        ``(2, size, size)`` tensor.
    """
    for name, val in (("size", size), ("samples", samples)):
        if int(val) != val or val < 2:
            raise ValueError(f"{name}: expected an int >= 2, got {val!r}")
    return dfg_lut_uncached(int(size), int(samples)).to(device=device, dtype=dtype)


def lookup_dfg(
    lut: torch.Tensor, n_dot_v: torch.Tensor, roughness: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear LUT lookup: ``n_dot_v``, ``roughness`` ``(B, 1, H, W)`` -> (A, B) each
    ``(B, 1, H, W)``; inputs are clamped to [0, 1], the table's first and last nodes."""
    b = n_dot_v.shape[0]
    x = n_dot_v.clamp(0.0, 1.0) * 2.0 - 1.0
    y = roughness.clamp(0.0, 1.0) * 2.0 - 1.0
    grid = torch.stack((x[:, 0], y[:, 0]), -1)
    dt = compute_dtype(n_dot_v)  # half precision: looked up in float32, cast back
    tab = lut.to(dt)[None].expand(b, -1, -1, -1)
    ab = grid_sample(tab, grid, mode="bilinear", padding_mode="border", align_corners=True)
    ab = finish_low_precision(ab, n_dot_v.dtype)
    return ab[:, :1], ab[:, 1:]


# --------------------------------------------------------------------- content cache


class _ContentCache:
    """Least-recently-used map from (content key, knobs) to lists of tensors, bounded by
    :data:`ENV_CACHE_BYTES` (read at each insertion)."""

    def __init__(self) -> None:
        self._entries: OrderedDict[tuple, list[torch.Tensor]] = OrderedDict()
        self._bytes = 0

    def get(self, key: tuple, build) -> list[torch.Tensor]:  # noqa: ANN001
        if key in self._entries:
            self._entries.move_to_end(key)
            return self._entries[key]
        value = build()
        size = sum(t.numel() * t.element_size() for t in value)
        if size <= ENV_CACHE_BYTES:
            self._entries[key] = value
            self._bytes += size
            while self._bytes > ENV_CACHE_BYTES and self._entries:
                _, old = self._entries.popitem(last=False)
                self._bytes -= sum(t.numel() * t.element_size() for t in old)
        return value

    def clear(self) -> None:
        self._entries.clear()
        self._bytes = 0


_ENV_CACHE = _ContentCache()


def content_key(t: torch.Tensor) -> tuple:
    """A key that identifies a tensor by value: a 128-bit BLAKE2 digest of its bytes, with
    its shape, dtype and device (two tensors with equal keys hold the same numbers)."""
    data = t.detach().contiguous().cpu()
    digest = hashlib.blake2b(data.view(torch.uint8).numpy().tobytes(), digest_size=16)
    return digest.hexdigest(), tuple(t.shape), str(t.dtype), str(t.device)


def _cached(name: str, radiance: torch.Tensor, knobs: tuple, build) -> list[torch.Tensor]:  # noqa: ANN001
    """``build()`` through the content cache, unless the result would carry gradients
    (``radiance`` requires grad) or the cache is disabled."""
    if ENV_CACHE_BYTES <= 0 or (radiance.requires_grad and torch.is_grad_enabled()):
        return build()
    return _ENV_CACHE.get((name, content_key(radiance), knobs), build)


def dominant_direction(n: torch.Tensor, r: torch.Tensor, roughness: torch.Tensor
                       ) -> torch.Tensor:
    """Where the split sum reads the prefiltered chain: the GGX lobe's dominant direction,
    the reflection vector bent towards the normal as the lobe widens (Lagarde & de Rousiers
    2014, "Moving Frostbite to PBR", listing 22): ``normalize(n + s (r - n))``,
    ``s = (1 - a)(sqrt(1 - a) + a)``, ``a = roughness**2``. On a sun-lit map it brings the
    split sum's mean error at roughness 0.8 from 35 % to 9 % (docs/benchmarks.md,
    ibl-specular).

    Args:
        n, r: ``(B, 3, H, W)`` unit normal and reflection vector ``reflect(-v, n)``.
        roughness: ``(B, 1, H, W)`` perceptual roughness in [0, 1].

    Returns:
        ``(B, 3, H, W)`` unit directions (r at roughness 0); finite gradients everywhere.
    """
    alpha = roughness.clamp(0.0, 1.0) ** 2
    bend = (1.0 - alpha) * (torch.sqrt((1.0 - alpha).clamp_min(1e-12)) + alpha)
    return safe_normalize(n + bend * (r - n))


def _lobe_moments(rough: torch.Tensor, nv: torch.Tensor, prefilter: bool, n_u: int = 64,
                  n_phi: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    """Angle from n of the mean direction, and the mean squared tangent-plane spread
    ``(<(l.e_par)^2> + <(l.e_perp)^2>) / 2`` about it, of a GGX lobe in l: ``(R, N)`` each
    for roughness ``(R,)`` x n.v ``(N,)`` (float64).

    ``prefilter=False``: the single-scattering lobe ``D G2 / (4 n.v)`` (f0 = 1);
    ``prefilter=True``: the kernel of the prefiltered chain, ``D (n.l)`` with n = v.
    Midpoint quadrature over GGX-distributed half vectors (``u`` -> theta_h by Karis's
    inversion, so ``D (n.h) dh = du dphi / 2 pi``; ``dl = 4 (v.h) dh``), phi over the half
    plane y >= 0 (the lobes are symmetric in y)."""
    a = rough.clamp_min(MIN_ROUGHNESS).pow(2).view(-1, 1, 1, 1)
    cv = (torch.ones_like(nv) if prefilter else nv.clamp(MIN_N_DOT_V, 1.0)).view(1, -1, 1, 1)
    u = ((torch.arange(n_u, dtype=torch.float64) + 0.5) / n_u).view(1, 1, -1, 1)
    phi = ((torch.arange(n_phi, dtype=torch.float64) + 0.5) * (math.pi / n_phi)).view(1, 1, 1, -1)
    ch = torch.sqrt((1.0 - u) / (1.0 + (a * a - 1.0) * u))
    sh = torch.sqrt((1.0 - ch * ch).clamp_min(0.0))
    hx, hy = sh * torch.cos(phi), sh * torch.sin(phi)
    sv = torch.sqrt(1.0 - cv * cv)  # v = (sin, 0, cos), n = z
    vh = sv * hx + cv * ch
    lx, ly, lz = 2.0 * vh * hx - sv, 2.0 * vh * hy, 2.0 * vh * ch - cv
    if prefilter:
        w = lz * 4.0 * vh / ch
    else:
        w = v_smith_ggx_correlated(cv, lz.clamp_min(1e-12), a.sqrt()) * 4.0 * lz * vh / ch
    w = torch.where((lz > 0) & (vh > 0), w, 0.0)
    ws = w.sum((-1, -2))
    mx, mz = (w * lx).sum((-1, -2)) / ws, (w * lz).sum((-1, -2)) / ws
    norm = torch.sqrt(mx * mx + mz * mz)
    ex, ez = (mz / norm)[..., None, None], (-mx / norm)[..., None, None]  # in-plane tangent
    par2 = (w * (lx * ex + lz * ez) ** 2).sum((-1, -2)) / ws
    perp2 = (w * ly * ly).sum((-1, -2)) / ws
    return torch.atan2(-mx, mz), 0.5 * (par2 + perp2)


@lru_cache(maxsize=4)
def lobe_table(size: int = 17) -> torch.Tensor:
    """float64 ``(2, size, size)`` fit of the reflected GGX lobe by the prefiltered chain:
    rows = perceptual roughness, columns = n.v, both 0..1 with nodes at the ends (looked
    up by :func:`lookup_dfg`, like the DFG table).

    Channel 0 is the bend ``s`` of the read direction ``normalize(n + s (r - n))`` that
    points along the lobe's mean direction; channel 1 the roughness of the chain level
    whose kernel ``D (n.l)`` has the lobe's spread (second moment about the mean
    direction). A moment match (first and second) of the true single-scattering lobe
    ``D G2 / (4 n.v)`` at each (roughness, n.v), independent of any environment; it
    replaces the empirical dominant direction of Lagarde & de Rousiers 2014 (which bends
    towards the lobe's peak, not its mean, and keeps the roughness)."""
    if int(size) != size or size < 2:
        raise ValueError(f"size: expected an int >= 2, got {size!r}")
    nodes = torch.linspace(0.0, 1.0, int(size), dtype=torch.float64)
    ang, spread = _lobe_moments(nodes, nodes, prefilter=False)
    pr = torch.linspace(0.0, 1.0, 129, dtype=torch.float64)
    pf = _lobe_moments(pr, pr[:1], prefilter=True)[1][:, 0]  # increasing with roughness
    theta_v = torch.acos(nodes.clamp(MIN_N_DOT_V, 1.0)).view(1, -1)
    tn = torch.tan(ang)
    # atan2(s sin t, 1 - s + s cos t) = ang  <=>  s = tan(ang) / (sin t + tan(ang)(1 - cos t))
    bend = tn / (torch.sin(theta_v) + tn * (1.0 - torch.cos(theta_v))).clamp_min(1e-12)
    bend[:, -1] = bend[:, -2]  # n.v = 1: r = n, any bend reads n; continue the limit
    bend[0] = 1.0  # a mirror reads r
    idx = torch.searchsorted(pf.contiguous(), spread.clamp(float(pf[0]), float(pf[-1]))
                             .contiguous()).clamp(1, pf.numel() - 1)
    lo, hi = pf[idx - 1], pf[idx]
    frac = ((spread.clamp(float(pf[0]), float(pf[-1])) - lo) / (hi - lo)).clamp(0.0, 1.0)
    rough_eff = pr[idx - 1] + frac * (pr[idx] - pr[idx - 1])
    rough_eff[0] = 0.0  # a mirror reads level 0 (its spread is below the quadrature's)
    return torch.stack((bend.clamp(0.0, 1.0), rough_eff.nan_to_num(0.0)))


def fitted_lobe(n: torch.Tensor, r: torch.Tensor, n_dot_v: torch.Tensor,
                roughness: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Where and at which roughness the split sum reads the prefiltered chain: the lobe's
    mean direction and spread from :func:`lobe_table` (``(B, 3, H, W)`` unit directions,
    ``(B, 1, H, W)`` chain roughness) for unit ``n``, ``r = reflect(-v, n)`` ``(B, 3, H,
    W)``, ``n_dot_v`` and perceptual ``roughness`` ``(B, 1, H, W)``."""
    tab = lobe_table().to(device=n.device, dtype=compute_dtype(n))
    bend, rough_eff = lookup_dfg(tab, n_dot_v, roughness)
    return safe_normalize(n + bend * (r - n)), rough_eff


# ------------------------------------------------- per-pixel filtered importance sampling


def _pixel_rotation(shape: tuple[int, ...], device: torch.device, dtype: torch.dtype
                    ) -> torch.Tensor:
    """``(B, 1, H, W)`` deterministic per-pixel offsets in [0, 1): interleaved gradient
    noise (Jimenez 2014) of the pixel coordinates, the Cranley-Patterson rotation of the
    sample azimuths (decorrelates neighbouring pixels; no state, no RNG)."""
    b, _, h, w = shape
    y = torch.arange(h, device=device, dtype=torch.float64).view(h, 1)
    x = torch.arange(w, device=device, dtype=torch.float64).view(1, w)
    ign = torch.frac(52.9829189 * torch.frac(0.06711056 * x + 0.00583715 * y))
    return ign.to(dtype).expand(b, 1, h, w)


def latlong_atlas(levels: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Pack a lat-long mip chain into one image, so a trilinear lookup of any lod is two
    points of one ``grid_sample`` call (the layout of :mod:`torchraster.mip_atlas`).

    Each level is padded by one texel (wrap in u, clamp in v, :func:`pad_texture`); level 0
    sits at the top left, levels 1, 2, ... are stacked in a column to its right.

    Args:
        levels: mip chain, each ``(B', C, h_k, w_k)``.

    Returns:
        ``(B', C, Ha, Wa)`` atlas and a ``(L, 4)`` table of each unpadded level's (row
        offset, column offset, height, width) in the atlas (same dtype).
    """
    padded = [pad_texture(lv, "wrap", "clamp") for lv in levels]
    h0, w0 = padded[0].shape[-2:]
    col_w = max((t.shape[-1] for t in padded[1:]), default=0)
    height = max(h0, sum(t.shape[-2] for t in padded[1:]))
    atlas = padded[0].new_zeros(*padded[0].shape[:2], height, w0 + col_w)
    atlas[..., :h0, :w0] = padded[0]
    rows, y = [[0, 0, levels[0].shape[-2], levels[0].shape[-1]]], 0
    for lv, t in zip(levels[1:], padded[1:], strict=True):
        atlas[..., y:y + t.shape[-2], w0:w0 + t.shape[-1]] = t
        rows.append([y, w0, lv.shape[-2], lv.shape[-1]])
        y += t.shape[-2]
    return atlas, torch.tensor(rows, dtype=atlas.dtype, device=atlas.device)


def _atlas_lookup(atlas: torch.Tensor, table: torch.Tensor, uv: torch.Tensor,
                  lod: torch.Tensor) -> torch.Tensor:
    """Trilinear lookups of a :func:`latlong_atlas`: ``uv`` ``(B, 2, P)`` (lat-long, v up),
    ``lod`` ``(B, P)`` -> ``(B, C, P)``. The two levels around the lod are two points of one
    bilinear ``grid_sample``; the lod's fraction is differentiable (its floor is not)."""
    b, _, p = uv.shape
    top = table.shape[0] - 1
    lod = lod.clamp(0.0, float(top))
    k0 = lod.detach().floor().clamp_max(max(top - 1, 0))
    frac = (lod - k0).clamp(0.0, 1.0)
    k0 = k0.long()
    k1 = (k0 + 1).clamp_max(top)
    u = torch.remainder(uv[:, 0], 1.0)
    v = 1.0 - uv[:, 1].clamp(0.0, 1.0)  # row 0 of the map is v = 1
    cols = table.to(uv.dtype).T.contiguous()  # (4, L): row offset, column offset, h, w
    pts = []
    for k in (k0, k1):
        oy, ox, h, w = (torch.take(c, k) for c in cols)
        pts.append(torch.stack((ox + u * w + 0.5, oy + v * h + 0.5), -1))  # atlas pixels
    grid = torch.cat(pts, 1)  # (B, 2P, 2)
    ha, wa = atlas.shape[-2:]
    grid = grid * grid.new_tensor([2.0 / (wa - 1), 2.0 / (ha - 1)]) - 1.0
    src = atlas.to(uv.dtype).expand(b, -1, -1, -1) if atlas.shape[0] == 1 else atlas.to(uv.dtype)
    s = grid_sample(src, grid[:, None], mode="bilinear", padding_mode="border",
                    align_corners=True)[:, :, 0]  # (B, C, 2P)
    return torch.lerp(s[..., :p], s[..., p:], frac[:, None])


#: (sample, pixel) pairs evaluated at once by :func:`specular_importance` (its ~40
#: temporaries of 0.5 MB then stay in the caches: 128², 64 samples, one thread, 1.6x faster
#: than 2**19, 256² 1.06x; 2**14 - 2**16 slower again).
IMPORTANCE_CHUNK: int = 2**17


def specular_importance(
    levels: list[torch.Tensor],
    n: torch.Tensor,
    v: torch.Tensor,
    f0: torch.Tensor,
    f90: torch.Tensor | float,
    roughness: torch.Tensor,
    samples: int,
    padded: list[torch.Tensor] | None = None,
    atlas: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """Mean environment radiance under the single-scattering GGX lobe, per pixel, by
    filtered importance sampling (Krivanek & Colbert 2008, GPU Gems 3 ch. 20).

    ``samples`` half vectors per pixel from GGX (Hammersley points, azimuth rotated per
    pixel), ``l = reflect(-v, h)`` with pdf ``D (n.h) / (4 v.h)``; each sample reads the
    mip chain at ``lod = 0.5 log2(Omega_s / Omega_p) + FIS_LOD_BIAS`` (``Omega_s = 1 / (N
    pdf)``, ``Omega_p`` the equator texel of level 0) and is weighted by BRDF x cosine / pdf
    ``= 4 V F (n.l)(v.h) / (n.h)`` (height-correlated Smith V, Schlick F). Returns the
    weighted mean ``sum L w / sum w`` (a ratio estimator): multiplied by the lobe's albedo
    ``f0 A + f90 B`` it converges to ``int L f (n.l) dl`` as N grows, and is exact for a
    uniform environment at any N. Unlike the split sum it keeps the lobe's dependence on
    the view (stretched at grazing angles, no n = v = r assumption).

    Vectorised over samples: chunks of :data:`IMPORTANCE_CHUNK` (sample, pixel) pairs,
    each chunk's trilinear lookups one ``grid_sample`` of a mip atlas
    (:func:`latlong_atlas`).

    Args:
        levels: box mip chain of the lat-long radiance, ``(1 or B, 3, h_k, w_k)``.
        n, v: ``(B, 3, H, W)`` unit normal and direction to the eye, in env space.
        f0: ``(B, 3 or 1, H, W)``; f90: ``(B, 1, H, W)`` or a float (Schlick Fresnel).
        roughness: ``(B, 1, H, W)`` perceptual roughness (clamped to [MIN_ROUGHNESS, 1]).
        samples: N >= 1.
        padded: unused (kept for callers of the per-level version).
        atlas: ``latlong_atlas(levels)`` if already built, or None.

    Returns:
        ``(B, 3, H, W)`` radiance; differentiable w.r.t. the levels and every input.
    """
    check_tensor("n", n, ("B", 3, "H", "W"), floating=True)
    b, _, h, w = n.shape
    check_tensor("v", v, (b, 3, h, w), floating=True)
    check_tensor("roughness", roughness, (b, 1, h, w), floating=True)
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
        raise ValueError(f"samples: expected an int >= 1, got {samples!r}")
    env = levels[0]
    if env.shape[0] not in (1, b):
        raise ValueError(f"levels: batch {env.shape[0]} does not match n's batch {b}")
    tex, table = latlong_atlas(levels) if atlas is None else atlas
    omega_p = (2.0 * math.pi / env.shape[-1]) * (math.pi / env.shape[-2])
    rough = roughness.clamp(MIN_ROUGHNESS, 1.0)[:, :, None]  # (B, 1, 1, H, W)
    a2 = rough ** 4
    t, bt = (x[:, :, None] for x in _onb(n))
    n5, v5 = n[:, :, None], v[:, :, None]
    n_dot_v = dot(n, v).clamp(MIN_N_DOT_V, 1.0)[:, :, None]
    rot = _pixel_rotation(n.shape, n.device, n.dtype)[:, :, None]
    f0_5 = f0[:, :, None]
    f90_5 = f90[:, :, None] if isinstance(f90, torch.Tensor) else f90
    xi = hammersley(samples, dtype=n.dtype).to(n.device)
    step = max(1, IMPORTANCE_CHUNK // max(b * h * w, 1))
    acc = n.new_zeros(b, 3, h, w)
    wsum = n.new_zeros(b, 3, h, w)
    for c0 in range(0, samples, step):
        xs = xi[c0:c0 + step]
        m = xs.shape[0]
        phi = 2.0 * math.pi * torch.frac(xs[:, 0].view(1, 1, m, 1, 1) + rot)  # (B,1,m,H,W)
        u = xs[:, 1].view(1, 1, m, 1, 1)
        den = 1.0 + (a2 - 1.0) * u
        cos_h = torch.sqrt((1.0 - u) / den)  # GGX inversion (Karis); u < 1
        sin_h = torch.sqrt((a2 * u / den).clamp_min(1e-30))  # u = 0: finite gradient
        hv = t * (sin_h * torch.cos(phi)) + bt * (sin_h * torch.sin(phi)) + n5 * cos_h
        v_dot_h = (v5 * hv).sum(1, keepdim=True)
        l = 2.0 * v_dot_h * hv - v5
        n_dot_l = (n5 * l).sum(1, keepdim=True)
        ok = (n_dot_l > 0) & (v_dot_h > 0)
        pdf = d_ggx(cos_h, rough) * cos_h / (4.0 * v_dot_h.clamp_min(MIN_N_DOT_V))
        lod = 0.5 * torch.log2(1.0 / (samples * pdf.clamp_min(1e-30) * omega_p)) + FIS_LOD_BIAS
        uv = latlong_uv(l.reshape(b, 3, m * h, w)).reshape(b, 2, -1)
        rad = _atlas_lookup(tex, table, uv, lod.reshape(b, -1)).reshape(b, -1, m, h, w)
        vis = v_smith_ggx_correlated(n_dot_v, n_dot_l, rough)
        fc = (1.0 - v_dot_h.clamp(0.0, 1.0)) ** 5
        fres = f0_5 + (f90_5 - f0_5) * fc
        g = torch.where(ok, 4.0 * vis * n_dot_l.clamp_min(0.0) * v_dot_h.clamp_min(0.0)
                        / cos_h.clamp_min(MIN_N_DOT_V), 0.0)  # (B, 1, m, H, W)
        gf = g * fres  # (B, 1 or 3, m, H, W)
        acc = acc + (rad * gf).sum(2)
        wsum = wsum + gf.sum(2)
    ok = wsum > 1e-12
    return torch.where(ok, acc / torch.where(ok, wsum, 1.0), 0.0)


# ------------------------------------------------------------------------- sun extraction

#: Angular radius (rad) around the brightest texel within which :func:`extract_sun` takes
#: texels into the sun (5.7 degrees: a sun with its halo, not a second bright source).
SUN_CONE: float = 0.1


def extract_sun(env: torch.Tensor, threshold: float, cone: float = SUN_CONE
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Split a lat-long map into a residual and one small bright source ("the sun").

    A texel belongs to the sun when it lies within ``cone`` rad of the map's brightest
    texel and its luminance (channel mean) exceeds ``threshold`` times the map's mean
    radiance; the sun takes the excess above that level (the texel is scaled down to it,
    keeping its colour), so the residual's dynamic range near the sun is bounded and the
    split sum's lobe-shape error on it is small. The sun is returned as a directional
    light: its power (``sum excess x solid angle``), mean direction and r.m.s. angular
    spread. ``residual`` plus the sun's texels is the input map exactly.

    Args:
        env: ``(B, 3, He, We)`` lat-long radiance.
        threshold: level, in units of the map's mean radiance, above which texels near
            the peak go into the sun (> 0).
        cone: angular radius around the brightest texel (rad).

    Returns:
        ``residual`` ``(B, 3, He, We)``, ``direction`` ``(B, 3)`` (unit; +y when there is
        no sun), ``power`` ``(B, 3)`` (W/m^2 at normal incidence; 0 when no texel exceeds
        the level) and ``spread`` ``(B,)`` (rad). Differentiable w.r.t. ``env`` (the choice
        of texels is not).
    """
    check_tensor("env", env, ("B", 3, "He", "We"), floating=True)
    if isinstance(threshold, bool) or not (isinstance(threshold, (int, float)) and
                                           math.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold: expected a finite number > 0, got {threshold!r}")
    out_dtype = env.dtype
    env = env.to(torch.float64)  # level / lum: its gradient squares lum (denormal maps)
    b, _, he, we = env.shape
    dirs = latlong_directions(he, we, device=env.device, dtype=env.dtype)  # (1, 3, He, We)
    dw = latlong_solid_angles(he, we, device=env.device, dtype=env.dtype)  # (He, 1)
    lum = env.mean(1)  # (B, He, We)
    level = threshold * (lum * dw).sum((-1, -2)) / (4.0 * math.pi)  # (B,)
    peak = lum.detach().reshape(b, -1).argmax(1)
    d_peak = dirs.reshape(3, -1)[:, peak].T  # (B, 3)
    near = torch.einsum("bc,chw->bhw", d_peak, dirs[0]) > math.cos(cone)
    bright = near & (lum.detach() > level.detach()[:, None, None])
    safe = torch.where(bright, lum, torch.ones_like(lum))  # double where: no 0 / 0
    scale = torch.where(bright, level[:, None, None] / safe, torch.ones_like(lum))
    residual = env * scale[:, None]
    sun = env - residual  # (B, 3, He, We), 0 outside the sun
    power = (sun * dw).sum((-1, -2))  # (B, 3)
    wgt = sun.mean(1) * dw  # (B, He, We)
    direction = safe_normalize((dirs * wgt[:, None]).sum((-1, -2)) + torch.tensor(
        [0.0, 1e-30, 0.0], dtype=env.dtype, device=env.device), dim=-1)
    total = wgt.sum((-1, -2))
    dev2 = ((dirs - direction[:, :, None, None]) ** 2).sum(1)  # (B, He, We) chord^2
    spread = torch.sqrt((wgt * dev2).sum((-1, -2)) / torch.where(total > 0, total, 1.0)
                        + 1e-30)
    return tuple(t.to(out_dtype) for t in (residual, direction, power, spread))


def sun_specular(n: torch.Tensor, v: torch.Tensor, f0: torch.Tensor,
                 f90: torch.Tensor | float, roughness: torch.Tensor, direction: torch.Tensor,
                 power: torch.Tensor, spread: torch.Tensor) -> torch.Tensor:
    """Single-scattering GGX specular of a directional light of angular spread ``spread``:
    ``power D(h; alpha_s) V(n.v, n.l) F(v.h) (n.l)^+``, Filament's BRDF (Schlick F with
    ``f0``, ``f90``), the light's size folded into the distribution, ``alpha_s^2 =
    alpha^2 + (spread / 2)^2`` (the half vector moves half as far as l; D stays
    normalised, so the energy is unchanged).

    Args:
        n, v: ``(B, 3, H, W)`` unit normal and direction to the eye.
        f0: ``(B, 3 or 1, H, W)``; f90: ``(B, 1, H, W)`` or a float.
        roughness: ``(B, 1, H, W)`` perceptual roughness.
        direction: ``(B, 3)`` unit directions to the light (same space as n, v).
        power: ``(B, 3)`` irradiance at normal incidence; spread: ``(B,)`` (rad).

    Returns:
        ``(B, 3, H, W)`` reflected radiance.
    """
    ld = direction[:, :, None, None].to(n.dtype)
    n_dot_l = dot(n, ld)
    n_dot_v = dot(n, v).clamp(MIN_N_DOT_V, 1.0)
    hv = safe_normalize(v + ld)
    n_dot_h = dot(n, hv).clamp(0.0, 1.0)
    v_dot_h = dot(v, hv).clamp(0.0, 1.0)
    alpha = roughness.clamp(MIN_ROUGHNESS, 1.0) ** 2
    alpha_s = torch.sqrt(alpha * alpha + 0.25 * spread.to(n.dtype).view(-1, 1, 1, 1) ** 2)
    d = d_ggx(n_dot_h, torch.sqrt(alpha_s))
    vis = v_smith_ggx_correlated(n_dot_v, n_dot_l, roughness.clamp(MIN_ROUGHNESS, 1.0))
    fres = f0 + (f90 - f0) * (1.0 - v_dot_h) ** 5
    lobe = torch.where(n_dot_l > 0, d * vis * n_dot_l.clamp_min(0.0), 0.0)
    return lobe * fres * power[:, :, None, None].to(n.dtype)


# -------------------------------------------------------------------------- environment


class Environment:
    """An HDR environment light: lat-long radiance, rotation, intensity and the cached
    IBL precomputations (SH irradiance, prefiltered specular chain).

    Args:
        radiance: ``(3, He, We)`` or ``(B, 3, He, We)`` linear radiance, lat-long layout of
            :func:`torchraster.texture.latlong_uv`.
        rotation: ``(3, 3)`` or ``(B, 3, 3)``: an env-space direction d is seen in the world
            at ``rotation @ d``. Combined with ``yaw`` as ``rotation @ yaw_rotation(yaw)``.
        yaw: rotation about +y in radians.
        intensity: scale on all radiance (float or ``(B,)`` tensor).
        diffuse: ``"map"`` (brute-force irradiance map, default: 0.4 % mean error on
            venice_sunset_1k, the fastest setting within 1 %) or ``"sh"`` (9 SH
            coefficients, Ramamoorthi & Hanrahan: ~2 % mean, up to ~17 % for a sun on the
            horizon); see :meth:`irradiance`.
        irradiance_height, irradiance_source_height: knobs of :func:`irradiance_map`
            (defaults 16 rows from a 32-row source: fastest within 1 % in the benchmark).
        specular_size, specular_levels, specular_samples, specular_source_height: knobs
            of :func:`prefilter_specular`. Defaults (128, 16, 32, None = full resolution):
            the fastest setting within 1 % mean error (0.96 %) of a brute-force GGX lobe on
            venice_sunset_1k in scripts/bench_quality.py (docs/benchmarks.md,
            section quality-ibl).
        specular: how :func:`shade_ibl` integrates the specular lobe (stored as
            :attr:`specular_mode`): ``"split_sum"`` (the prefiltered chain, one
            lookup a pixel, along the lobe's dominant direction), ``"fitted"`` (the same
            chain read along the lobe's fitted mean direction at its fitted width,
            :func:`fitted_lobe`: lower mean error at roughness 0.4-0.9, larger worst-case
            errors), ``"table"`` (default: the exact single-scattering lobe's mean radiance,
            pre-integrated per map into a table over reflection direction, n.v, the normal's
            azimuth about the reflection and roughness >= 0.3,
            :mod:`~torchraster.shading.ibl_table`; ~1 % mean error at roughness 0.3-1 on
            venice_sunset_1k; built on first use in ~0.5 s, ~35 MB) or ``"importance"``
            (:func:`specular_importance`:
            ``importance_samples`` filtered samples of the GGX lobe a pixel, closer to
            the true integral at high roughness; docs/benchmarks.md, ibl-specular).
        importance_samples: samples a pixel for ``specular="importance"`` (>= 1).
        table_levels, table_views, table_azimuths: knobs of :func:`specular_table`
            (roughness levels from 0.3 to 1, nodes of acos(n.v) and of the normal's azimuth
            about the reflection; defaults 8, 8, 16).
        sun_threshold: None (default) or a level in units of the map's mean radiance:
            the texels near the brightest one that exceed it give their excess to an
            extracted sun (:func:`extract_sun`), shaded per pixel with the exact GGX BRDF
            (:meth:`sun_light`); the specular chain and the mip chain are built from the
            residual. On a map whose sun carries much of the power it removes most of the
            split sum's error (pedestrian_overpass_1k: 17 / 29 % -> 8 / 7 % mean at
            roughness 0.3 / 0.6 with 10; docs/benchmarks.md, ibl-specular); the diffuse
            irradiance keeps the whole map. :meth:`specular` then reads the residual only
            (callers of it that want the sun add :meth:`sun_light`).

    The SH coefficients, the irradiance map and the specular chain are computed on first
    use and kept; without gradients they are also shared by every Environment of the same
    radiance (by content, :data:`ENV_CACHE_BYTES`), so re-creating an Environment of the
    same map does not prefilter it again. If ``radiance`` requires grad, build a new
    Environment per optimisation step.
    """

    def __init__(
        self,
        radiance: torch.Tensor,
        *,
        rotation: torch.Tensor | None = None,
        yaw: float = 0.0,
        intensity: float | torch.Tensor = 1.0,
        specular_size: int = 128,
        specular_levels: int = 16,
        specular_samples: int = 32,
        specular_source_height: int | None = None,
        diffuse: str = "map",
        irradiance_height: int = 16,
        irradiance_source_height: int | None = 32,
        specular: str = "table",
        importance_samples: int = 16,
        table_levels: int = 8,
        table_views: int = 8,
        table_azimuths: int = 16,
        sun_threshold: float | None = None,
    ) -> None:
        if isinstance(radiance, torch.Tensor) and radiance.dim() == 3:
            radiance = radiance[None]
        check_tensor("radiance", radiance, ("B", 3, "He", "We"), floating=True)
        check_radiance("radiance", radiance)
        self.radiance = radiance
        rot = yaw_rotation(yaw, dtype=radiance.dtype).to(radiance.device)
        if rotation is not None:
            if isinstance(rotation, torch.Tensor) and rotation.dim() == 2:
                rotation = rotation[None]
            check_tensor("rotation", rotation, ("B", 3, 3), floating=True, finite=True)
            rot = rotation.to(radiance.dtype) @ rot
        self.rotation = rot if rot.dim() == 3 else rot[None]
        if isinstance(intensity, torch.Tensor):
            check_tensor("intensity", intensity.reshape(-1), ("B",), floating=True)
            check_radiance("intensity", intensity)
            self.intensity = intensity.reshape(-1, 1, 1, 1).to(radiance.dtype)
        else:
            self.intensity = float(intensity)
            if not math.isfinite(self.intensity) or self.intensity < 0:
                raise ValueError(f"intensity: expected a finite float >= 0, got {intensity!r}")
        self.specular_size = specular_size
        self.specular_levels = specular_levels
        self.specular_samples = specular_samples
        self.specular_source_height = specular_source_height
        if diffuse not in ("map", "sh"):
            raise ValueError(f"diffuse: expected 'map' or 'sh', got {diffuse!r}")
        self.diffuse = diffuse
        self.irradiance_height = irradiance_height
        self.irradiance_source_height = irradiance_source_height
        if specular not in SPECULAR_MODES:
            raise ValueError(f"specular: expected one of {SPECULAR_MODES}, got {specular!r}")
        if isinstance(importance_samples, bool) or not isinstance(importance_samples, int) or (
                importance_samples < 1):
            raise ValueError(f"importance_samples: expected an int >= 1, got "
                             f"{importance_samples!r}")
        self.specular_mode = specular
        self.importance_samples = importance_samples
        for name, val in (("table_levels", table_levels), ("table_views", table_views),
                          ("table_azimuths", table_azimuths)):
            if isinstance(val, bool) or not isinstance(val, int) or val < 2:
                raise ValueError(f"{name}: expected an int >= 2, got {val!r}")
        if table_azimuths % 2:
            raise ValueError(f"table_azimuths: expected an even int, got {table_azimuths!r}")
        self.table_knobs = (table_levels, table_views, table_azimuths)
        if sun_threshold is not None and (isinstance(sun_threshold, bool) or not isinstance(
                sun_threshold, (int, float)) or not math.isfinite(sun_threshold) or
                sun_threshold <= 0):
            raise ValueError(f"sun_threshold: expected None or a finite number > 0, got "
                             f"{sun_threshold!r}")
        self.sun_threshold = None if sun_threshold is None else float(sun_threshold)
        self._sun: list[torch.Tensor] | None = None
        self._mips: list[torch.Tensor] | None = None
        self._mips_padded: list[torch.Tensor] | None = None
        self._irr: torch.Tensor | None = None
        self._sh: torch.Tensor | None = None
        self._spec: list[torch.Tensor] | None = None
        self._spec_atlas: tuple[torch.Tensor, torch.Tensor] | None = None
        self._table: list[torch.Tensor] | None = None

    @property
    def sh(self) -> torch.Tensor:
        """``(B, 9, 3)`` SH radiance coefficients (env space, without intensity)."""
        if self._sh is None:
            self._sh = _cached("sh", self.radiance, (), lambda: [sh_project(self.radiance)])[0]
        return self._sh

    @property
    def sun(self) -> list[torch.Tensor] | None:
        """:func:`extract_sun` of the radiance at :attr:`sun_threshold` (env space, without
        intensity): ``[residual, direction, power, spread]``, or None without extraction."""
        if self.sun_threshold is None:
            return None
        if self._sun is None:
            self._sun = _cached("sun", self.radiance, (self.sun_threshold,), lambda: list(
                extract_sun(self.radiance, self.sun_threshold)))
        return self._sun

    @property
    def specular_source(self) -> torch.Tensor:
        """The map the specular chain and the mip chain are built from: the radiance, or
        its residual after :func:`extract_sun` when :attr:`sun_threshold` is set."""
        return self.radiance if self.sun is None else self.sun[0]

    @property
    def specular_chain(self) -> list[torch.Tensor]:
        """Prefiltered specular levels (env space, without intensity; of
        :attr:`specular_source`)."""
        if self._spec is None:
            knobs = (self.specular_size, self.specular_levels, self.specular_samples,
                     self.specular_source_height, self.sun_threshold)
            self._spec = _cached("specular", self.radiance, knobs, lambda: prefilter_specular(
                self.specular_source, size=self.specular_size, levels=self.specular_levels,
                samples=self.specular_samples, source_height=self.specular_source_height))
        return self._spec

    @property
    def irradiance_latlong(self) -> torch.Tensor:
        """``(B, 3, h, 2h)`` brute-force irradiance map (env space, without intensity)."""
        if self._irr is None:
            knobs = (self.irradiance_height, self.irradiance_source_height)
            self._irr = _cached("irradiance", self.radiance, knobs, lambda: [irradiance_map(
                self.radiance, height=self.irradiance_height,
                source_height=self.irradiance_source_height)])[0]
        return self._irr

    def to_env(self, d: torch.Tensor) -> torch.Tensor:
        """World directions ``(B, 3, H, W)`` -> env space (``rotation^T d``)."""
        rot = self.rotation.to(d.dtype)
        return torch.einsum("bji,bjhw->bihw", rot.expand(d.shape[0], -1, -1), d)

    def _scale(self, x: torch.Tensor) -> torch.Tensor:
        if isinstance(self.intensity, float):
            return x * self.intensity if self.intensity != 1.0 else x
        return x * self.intensity.to(x.dtype)

    def background(self, view_dirs: torch.Tensor) -> torch.Tensor:
        """Radiance seen along ``view_dirs`` ``(B, 3, H, W)`` (camera -> scene) ->
        ``(B, 3, H, W)``: a bilinear lookup of the full-resolution map."""
        check_tensor("view_dirs", view_dirs, ("B", 3, "H", "W"), floating=True)
        env = self.radiance.to(view_dirs.dtype)
        return self._scale(sample_latlong(env, self.to_env(view_dirs)))

    def irradiance(self, n: torch.Tensor) -> torch.Tensor:
        """Irradiance (W/m^2) at normals ``(B, 3, H, W)`` -> ``(B, 3, H, W)``.

        ``diffuse="map"``: bilinear lookup of :attr:`irradiance_latlong` (a zero normal
        reads the +y texel); ``diffuse="sh"``: 9 SH coefficients (a zero normal gives the
        mean irradiance)."""
        check_tensor("n", n, ("B", 3, "H", "W"), floating=True)
        if self.diffuse == "map":
            return self._scale(sample_latlong(self.irradiance_latlong.to(n.dtype),
                                              self.to_env(n)))
        return self._scale(irradiance_sh(self.sh.to(n.dtype), self.to_env(n)))

    @property
    def mip_chain(self) -> list[torch.Tensor]:
        """Box mip pyramid of :attr:`specular_source` (env space, without intensity), read
        by :meth:`specular_lobe`."""
        if self._mips is None:
            self._mips = _cached("mips", self.radiance, (self.sun_threshold,),
                                 lambda: build_mip_pyramid(self.specular_source))
        return self._mips

    def specular_lobe(self, n: torch.Tensor, v: torch.Tensor, f0: torch.Tensor,
                      f90: torch.Tensor | float, roughness: torch.Tensor,
                      samples: int | None = None) -> torch.Tensor:
        """Mean radiance under the GGX lobe of world normals / view directions ``n``,
        ``v`` ``(B, 3, H, W)`` by :func:`specular_importance` with ``samples`` (default
        :attr:`importance_samples`) -> ``(B, 3, H, W)``."""
        check_tensor("n", n, ("B", 3, "H", "W"), floating=True)
        chain = [lv.to(n.dtype) for lv in self.mip_chain]
        if chain[0].shape[0] not in (1, n.shape[0]):
            raise ValueError(f"n: batch {n.shape[0]} does not match the environment's")
        if self._mips_padded is None or self._mips_padded[0].dtype != n.dtype:
            self._mips_padded = list(latlong_atlas(chain))  # (atlas, level table)
        rad = specular_importance(chain, self.to_env(n), self.to_env(v), f0, f90, roughness,
                                  self.importance_samples if samples is None else samples,
                                  atlas=tuple(self._mips_padded))
        return self._scale(rad)

    def specular(self, r: torch.Tensor, roughness: torch.Tensor) -> torch.Tensor:
        """Prefiltered radiance along reflection directions ``r`` ``(B, 3, H, W)`` for
        perceptual ``roughness`` ``(B, 1, H, W)``: trilinear between the two nearest
        roughness levels (lod from :func:`roughness_to_lod`), both read as two points of
        one ``grid_sample`` over :func:`latlong_atlas` of the chain -> ``(B, 3, H, W)``.
        With :attr:`sun_threshold` set, the chain is that of the residual (no sun)."""
        check_tensor("r", r, ("B", 3, "H", "W"), floating=True)
        check_tensor("roughness", roughness, ("B", 1, "H", "W"), floating=True)
        b, _, h, w = r.shape
        dt = compute_dtype(r)  # half precision: looked up in float32, cast back
        tex, table = self._chain_atlas(dt)
        if tex.shape[0] not in (1, b):
            raise ValueError(f"r: batch {b} does not match the environment's")
        uv = latlong_uv(self.to_env(r.to(dt))).reshape(b, 2, -1)
        lod = roughness_to_lod(roughness.to(dt), table.shape[0]).reshape(b, -1)
        out = _atlas_lookup(tex, table, uv, lod).reshape(b, -1, h, w)  # both levels: one call
        return self._scale(finish_low_precision(out, r.dtype))

    def sun_light(self, n: torch.Tensor, v: torch.Tensor, f0: torch.Tensor,
                  f90: torch.Tensor | float, roughness: torch.Tensor) -> torch.Tensor | None:
        """Specular of the extracted sun (:func:`sun_specular`, rotated into the world and
        scaled by the intensity) at world normals / view directions ``(B, 3, H, W)`` ->
        ``(B, 3, H, W)``; None when :attr:`sun_threshold` is None."""
        sun = self.sun
        if sun is None:
            return None
        b = n.shape[0]
        dt = compute_dtype(n)  # half precision: evaluated in float32 (the sun's power)
        _, direction, power, spread = (t.to(dt) for t in sun)
        if direction.shape[0] not in (1, b):
            raise ValueError(f"n: batch {b} does not match the environment's")
        rot = self.rotation.to(dt).expand(b, -1, -1)
        world = torch.einsum("bij,bj->bi", rot, direction.expand(b, -1))
        f90 = f90.to(dt) if isinstance(f90, torch.Tensor) else f90
        out = sun_specular(n.to(dt), v.to(dt), f0.to(dt), f90, roughness.to(dt), world,
                           power.expand(b, -1), spread.expand(b))
        return self._scale(finish_low_precision(out, n.dtype))

    @property
    def lobe_table_atlas(self) -> list[torch.Tensor]:
        """:func:`~torchraster.shading.ibl_table.table_atlas` of the
        :func:`~torchraster.shading.ibl_table.specular_table` of :attr:`specular_source`
        (env space, without intensity): ``[volume, blocks]``, built on first use."""
        if self._table is None:
            levels, views, azimuths = self.table_knobs
            self._table = _cached("table", self.radiance, (*self.table_knobs,
                                                           self.sun_threshold),
                                  lambda: list(table_atlas(specular_table(
                                      self.specular_source, levels=levels, views=views,
                                      azimuths=azimuths))))
        return self._table

    def specular_table_lookup(self, n: torch.Tensor, v: torch.Tensor, roughness: torch.Tensor
                              ) -> torch.Tensor:
        """Mean radiance of the single-scattering GGX lobe of world normals / view
        directions ``n``, ``v`` ``(B, 3, H, W)`` at perceptual ``roughness`` ``(B, 1, H, W)``
        (clamped to >= 0.3) from :attr:`lobe_table_atlas` -> ``(B, 3, H, W)``. With
        :attr:`sun_threshold` set, of the residual (no sun)."""
        check_tensor("n", n, ("B", 3, "H", "W"), floating=True)
        volume, blocks = self.lobe_table_atlas
        if volume.shape[0] not in (1, n.shape[0]):
            raise ValueError(f"n: batch {n.shape[0]} does not match the environment's")
        out = lookup_specular_table(volume, blocks, self.to_env(n), self.to_env(v), roughness)
        return self._scale(finish_low_precision(out, n.dtype))

    def prepare(self, dtype: torch.dtype) -> None:
        """Build now what shading in ``dtype`` (the compute dtype of the surfaces) reads
        lazily for this environment's modes: the irradiance map or SH, the extracted sun,
        the specular chain and its atlas, the lobe table (``"table"``), the mip chain
        (``"importance"``). Needed before checkpointed chunks (``Renderer(max_batch=...)``
        with autograd): their recomputation in backward must record the same graph as the
        first forward, which would otherwise build (and record) these on first use."""
        if self.diffuse == "map":
            self.irradiance_latlong  # noqa: B018
        else:
            self.sh  # noqa: B018
        self.sun  # noqa: B018
        self._chain_atlas(dtype)
        if self.specular_mode == "table":
            self.lobe_table_atlas  # noqa: B018
        if self.specular_mode == "importance":
            chain = [lv.to(dtype) for lv in self.mip_chain]
            if self._mips_padded is None or self._mips_padded[0].dtype != dtype:
                self._mips_padded = list(latlong_atlas(chain))

    def _chain_atlas(self, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """:attr:`specular_chain` packed by :func:`latlong_atlas` in ``dtype`` (kept)."""
        if self._spec_atlas is None or self._spec_atlas[0].dtype != dtype:
            self._spec_atlas = latlong_atlas([lv.to(dtype) for lv in self.specular_chain])
        return self._spec_atlas


def shade_ibl(
    normal: torch.Tensor,
    view_dir: torch.Tensor,
    albedo: torch.Tensor,
    metallic: torch.Tensor,
    roughness: torch.Tensor,
    ao: torch.Tensor | None,
    env: Environment,
    *,
    multiscatter: bool = True,
    f0_dielectric: float = DIELECTRIC_F0,
    lut_size: int = IBL_LUT_SIZE,
    lut_samples: int = IBL_LUT_SAMPLES,
    specular: str | None = None,
    importance_samples: int | None = None,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Image-based lighting of a metallic-roughness surface (split sum, see module doc).

    Args:
        normal: ``(B, 3, H, W)`` shading normals (normalised here).
        view_dir: ``(B, 3, H, W)`` directions from the surface towards the eye.
        albedo: ``(B, 3, H, W)`` linear base colour (or ``(B, 1, H, W)``).
        metallic: ``(B, 1, H, W)`` in [0, 1].
        roughness: ``(B, 1, H, W)`` perceptual roughness in [0, 1].
        ao: ``(B, 1, H, W)`` ambient occlusion in [0, 1] applied to diffuse and specular
            IBL (glTF: occlusion of indirect light), or None.
        env: the :class:`Environment`.
        multiscatter: multiple-scattering compensation of the specular lobe and the
            diffuse reduced by the specular's directional albedo (Fdez-Aguera 2019; the
            convention of :mod:`torchraster.shading.energy`, shared with punctual and
            ambient light). False: the single-scattering split sum of the BRDF of
            :func:`~torchraster.shading.brdf.cook_torrance` (no diffuse reduction).
        f0_dielectric: reflectance at normal incidence for metallic = 0. f90 follows
            Filament, ``saturate(50 * 0.33 * f0)``, so f0 = 0 turns specular off: when f0 is
            0 at every pixel (and needs no gradient) the specular term is skipped and the
            prefiltered chain is never built.
        lut_size, lut_samples: knobs of :func:`dfg_lut`; defaults (16, 32): the fastest
            within 1 % mean error in scripts/bench_quality.py.
        specular: ``"split_sum"`` (prefiltered chain along the dominant direction,
            :func:`dominant_direction`), ``"fitted"`` (along the lobe's mean direction, at
            the chain roughness of the lobe's spread: :func:`fitted_lobe`), ``"table"``
            (:meth:`Environment.specular_table_lookup` times the same ``E``, blended into
            the split sum over roughness 0.2-0.3 and the split sum below) or
            ``"importance"`` (the lobe's mean radiance by :meth:`Environment.specular_lobe`
            times the same ``E``); None: ``env.specular_mode``.
        importance_samples: samples a pixel for ``"importance"``; None:
            ``env.importance_samples``.
        mask: ``(B, 1, H, W)``, > 0 = shade this pixel; the others are not evaluated and
            are 0 in the result (their inputs are never read, so they may hold garbage).
            None: every pixel. The covered pixels give the same values as without a mask.

    Returns:
        ``(B, 3, H, W)`` outgoing radiance (same units as the environment).
    """
    check_tensor("normal", normal, ("B", 3, "H", "W"), floating=True)
    b, _, h, w = normal.shape
    check_tensor("view_dir", view_dir, (b, 3, h, w), floating=True)
    check_tensor("albedo", albedo, (b, None, h, w), floating=True)
    if albedo.shape[1] not in (1, 3):
        raise ValueError(f"albedo: expected 1 or 3 channels, got {albedo.shape[1]}")
    check_tensor("metallic", metallic, (b, 1, h, w), floating=True)
    check_tensor("roughness", roughness, (b, 1, h, w), floating=True)
    if ao is not None:
        check_tensor("ao", ao, (b, 1, h, w), floating=True)
    if not isinstance(env, Environment):
        raise TypeError(f"env: expected an Environment, got {type(env).__name__}")
    mode = env.specular_mode if specular is None else specular
    if mode not in SPECULAR_MODES:
        raise ValueError(f"specular: expected one of {SPECULAR_MODES} or None, got {mode!r}")
    if importance_samples is not None and (isinstance(importance_samples, bool) or not
                                           isinstance(importance_samples, int) or
                                           importance_samples < 1):
        raise ValueError(f"importance_samples: expected an int >= 1 or None, got "
                         f"{importance_samples!r}")

    if mask is not None:
        check_tensor("mask", mask, (b, 1, h, w))
        return _shade_covered(mask, normal, view_dir, albedo, metallic, roughness, ao, env,
                              multiscatter=multiscatter, f0_dielectric=f0_dielectric,
                              lut_size=lut_size, lut_samples=lut_samples, specular=mode,
                              importance_samples=importance_samples)
    n = safe_normalize(normal)
    v = safe_normalize(view_dir)
    n_dot_v_raw = dot(n, v)
    n_dot_v = n_dot_v_raw.clamp(MIN_N_DOT_V, 1.0)
    r = 2.0 * n_dot_v_raw * n - v  # reflect(-v, n)
    rough = roughness.clamp(0.0, 1.0)
    metal = metallic.clamp(0.0, 1.0)

    f0 = specular_f0(albedo, metal, f0_dielectric)
    f90 = (f0.mean(1, keepdim=True) * (3 * 50.0 * 0.33)).clamp(0.0, 1.0)  # dot(f0, 16.5)
    lut = dfg_lut(lut_size, lut_samples, device=normal.device, dtype=normal.dtype)
    a, bias = lookup_dfg(lut, n_dot_v, rough)
    e_ss = f0 * a + f90 * bias
    diffuse = diffuse_color(albedo, metal) * env.irradiance(n) * (1.0 / math.pi)
    if multiscatter:  # the energy convention of every light type (shading/energy.py)
        ms, kd_scale = energy_terms(f0, n_dot_v, rough, lut, f90)
        diffuse = diffuse * kd_scale
    if not f0.requires_grad and not bool((f0 != 0).any()):
        return diffuse * ao if ao is not None else diffuse  # f0 = f90 = 0: no specular at all
    if mode == "importance":
        spec = env.specular_lobe(n, v, f0, f90, rough, importance_samples) * e_ss
    elif mode == "fitted":
        spec = env.specular(*fitted_lobe(n, r, n_dot_v, rough)) * e_ss
    elif mode == "table":
        spec = _table_or_split_sum(env, n, v, r, rough) * e_ss
    else:
        spec = env.specular(dominant_direction(n, r, rough), rough) * e_ss
    sun = env.sun_light(n, v, f0, f90, rough)
    if sun is not None:  # the extracted sun: exact single-scattering BRDF, not the split sum
        spec = spec + sun
    if multiscatter:
        spec = spec * ms
    out = diffuse + spec
    return out * ao if ao is not None else out


def _table_or_split_sum(env: Environment, n: torch.Tensor, v: torch.Tensor, r: torch.Tensor,
                        rough: torch.Tensor) -> torch.Tensor:
    """``specular="table"``: the lobe table at roughness >= :data:`TABLE_MIN_ROUGHNESS`; below
    it the split sum plus the table's correction at that level, ``split(rough) + w (table(
    0.3) - split(0.3))``, fading to the plain split sum over :data:`TABLE_BLEND` (``w`` from 1
    to 0; continuous in roughness; closer than blending the two: venice r = 0.25, 2.8 %
    against 3.8 % (split sum) and 5.1 % (lerp)). Each term is evaluated on the pixels that
    need it only."""
    lo = TABLE_MIN_ROUGHNESS - TABLE_BLEND
    w = ((rough - lo) / TABLE_BLEND).clamp(0.0, 1.0)
    table = _on_pixels(rough.detach() >= lo, env.specular_table_lookup, n, v,
                       rough.clamp_min(TABLE_MIN_ROUGHNESS))

    def split_pair(n_: torch.Tensor, r_: torch.Tensor, ro: torch.Tensor) -> torch.Tensor:
        top = torch.full_like(ro, TABLE_MIN_ROUGHNESS)
        return torch.cat((env.specular(dominant_direction(n_, r_, ro), ro),
                          env.specular(dominant_direction(n_, r_, top), top)), 1)

    below = _on_pixels(rough.detach() < TABLE_MIN_ROUGHNESS, split_pair, n, r, rough)
    if below is None:
        return table
    split, split_top = below[:, :3], below[:, 3:]
    if table is None:
        return split
    corrected = (split + w.to(split.dtype) * (table - split_top)).clamp_min(0.0)
    return torch.where(rough >= TABLE_MIN_ROUGHNESS, table, corrected)


def _on_pixels(select: torch.Tensor, fn, *images: torch.Tensor | None  # noqa: ANN001
               ) -> torch.Tensor | None:
    """``fn(*images)`` evaluated on the pixels where ``select`` ``(B, 1, H, W)`` (bool) is
    True only: each item's selected pixels are gathered to the front of a ``(B, C, 1, M)``
    strip (M = the most selected pixels of any item; an item's spare slots get zero inputs
    and are dropped), passed to ``fn`` and scattered back into a zero ``(B, C', H, W)``
    image. None images stay None. Returns None when no pixel is selected; calls ``fn`` on
    the whole images when every pixel is."""
    b, _, h, w = select.shape
    chosen = select.reshape(b, h * w)
    count = int(chosen.sum(1).max()) if chosen.numel() else 0
    if count == 0:
        return None
    if count == h * w and bool(chosen.all()):
        strips = (None if t is None else t.reshape(b, t.shape[1], 1, h * w) for t in images)
        out = _in_chunks(fn, *strips)
        return out.view(b, out.shape[1], h, w)
    if b == 1:
        idx = chosen[0].nonzero().reshape(1, -1)
    else:  # selected pixels first in each row, in pixel order
        idx = torch.argsort((~chosen).to(torch.uint8), dim=1, stable=True)[:, :count]
    keep = torch.gather(chosen, 1, idx).view(b, 1, 1, count)

    def pack(t: torch.Tensor | None) -> torch.Tensor | None:
        if t is None:
            return None
        c = t.shape[1]
        t = torch.gather(t.reshape(b, c, h * w), 2, idx[:, None].expand(b, c, count))
        return torch.where(keep, t.view(b, c, 1, count), 0.0)  # spare slots: zeros

    out = torch.where(keep, _in_chunks(fn, *(pack(t) for t in images)), 0.0)
    c = out.shape[1]
    full = out.new_zeros(b, c, h * w)
    return full.scatter(2, idx[:, None].expand(b, c, count), out.view(b, c, count)
                        ).view(b, c, h, w)


#: Pixels shaded at once by :func:`_on_pixels` (a masked :func:`shade_ibl`): the pass's
#: ~40 per-pixel temporaries then stay in the CPU's caches. 2**20 pixels, one thread:
#: split sum 1.3x and table 1.8x faster than in one piece; 2**14 was slower again
#: (launches). Whole frames: docs/benchmarks.md, section frame-chunks.
IBL_PIXEL_CHUNK: int = 2**17


def _in_chunks(fn, *strips: torch.Tensor | None) -> torch.Tensor:  # noqa: ANN001
    """``fn(*strips)`` of ``(B, C, 1, M)`` pixel strips, evaluated on at most
    :data:`IBL_PIXEL_CHUNK` pixels (B x a slice of M) at a time (``fn`` is per pixel: the
    same values)."""
    b, m = next(t.shape for t in strips if t is not None)[::3]
    step = max(1, IBL_PIXEL_CHUNK // b)
    if m <= step:
        return fn(*strips)
    return torch.cat([fn(*(None if t is None else t[..., k:k + step] for t in strips))
                      for k in range(0, m, step)], -1)


def _shade_covered(mask: torch.Tensor, *maps: torch.Tensor | Environment | None, **kw
                   ) -> torch.Tensor:
    """:func:`shade_ibl` of the pixels where ``mask > 0`` only (:func:`_on_pixels`): the
    others are 0. ``"importance"`` rotates its samples by the pixel position, so it shades
    the whole frame (uncovered inputs zeroed)."""
    *images, env = maps
    covered = mask > 0
    if kw["specular"] == "importance":  # its sample pattern follows the pixel position:
        clean = [None if t is None else torch.where(covered, t, 0.0) for t in images]
        return torch.where(covered, shade_ibl(*clean, env, **kw), 0.0)
    out = _on_pixels(covered, lambda *t: shade_ibl(*t, env, **kw), *images)
    return images[0].new_zeros(mask.shape[0], 3, *mask.shape[2:]) if out is None else out
