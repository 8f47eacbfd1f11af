"""Texture sampling: nearest / bilinear / trilinear / anisotropic filtering (the last in
:mod:`torchraster.anisotropic`; mip pyramids and level lookups in :mod:`torchraster.mip`,
re-exported here), wrap / clamp / mirror addressing, lat-long (equirectangular) and cube
environment lookups.

Conventions (fixed for the project):

* Textures are image-like ``(B, C, Ht, Wt)`` tensors, row 0 = top of the image.
* UVs ``(B, 2, H, W)`` follow OBJ / trimesh: origin at the bottom-left, v up. uv (u, v)
  samples image column ``u * Wt`` and row ``(1 - v) * Ht`` (texel centres at half
  integers), i.e. grid_sample's ``x = 2u - 1``, ``y = 1 - 2v`` with align_corners=False.
* Directions ``(B, 3, H, W)`` are world-space, y up; they need not be unit length.

Sampling is ``torch.nn.functional.grid_sample`` on a texture padded by one texel (circular
for wrap, edge-replicate for clamp and mirror), after remapping u, v into [0, 1] with
``frac`` (wrap) or a triangle wave (mirror). The remaps have derivative +-1 almost
everywhere, so sampling is differentiable w.r.t. both texture and UVs (and, for trilinear,
w.r.t. the UV derivatives through the level of detail).

Mip levels: level k has size ``max(1, floor(size / 2**k))`` per axis (OpenGL). The pyramid
is built with a box filter (``adaptive_avg_pool2d``: an exact 2x2 average for even sizes,
overlapping windows that still cover every texel for odd sizes). Box is the default because
it is what ``glGenerateMipmap`` does on common drivers, it keeps the mean of even-sized
levels exactly, and it matches the one-texel footprint the OpenGL lod formula assumes;
kornia's ``pyrdown`` (Gaussian 5x5, ``pyramid="gaussian"``) blurs about one level more:
on the steep checkerboard plane of ``scripts/bench_quality.py`` trilinear filtering has
6.2 % mean error with the box pyramid and 17 % with pyrdown (anisotropic 16x: 0.8 %),
against the exact pixel-area average (docs/benchmarks.md, section quality-texture).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import torch
import torch.nn.functional as F

from torchraster._validate import check_tensor
from torchraster.anisotropic import sample_anisotropic
from torchraster.mip import (  # noqa: F401  (re-exported: part of this module's API)
    ADDRESS_MODES,
    LOD_RHO2_FLOOR,
    address_pair,
    build_mip_pyramid,
    compute_lod,
    mip_sizes,
    pad_texture,
    remap_address,
    sample_level,
    sample_levels,
    sample_padded,
)
from torchraster.numerics import compute_dtype, finish_low_precision, grid_sample

__all__ = [
    "FILTERS",
    "ADDRESS_MODES",
    "LOD_RHO2_FLOOR",
    "DIR_EPS2",
    "CUBE_FACES",
    "mip_sizes",
    "build_mip_pyramid",
    "compute_lod",
    "sample_texture",
    "MipTexture",
    "latlong_uv",
    "latlong_directions",
    "latlong_solid_angles",
    "sample_latlong",
    "cube_directions",
    "cube_uv",
    "sample_cube",
    "latlong_to_cube",
]

Filter = Literal["nearest", "bilinear", "trilinear", "anisotropic"]
Address = Literal["wrap", "clamp", "mirror"]
FILTERS = ("nearest", "bilinear", "trilinear", "anisotropic")

#: Squared length below which a direction counts as zero in the environment lookups. Such
#: directions are replaced by +y ("up") with zero gradient ("double where" trick).
DIR_EPS2: float = 1e-24

#: Cube face order (OpenGL): +X, -X, +Y, -Y, +Z, -Z. Each face is stored like an image (row 0
#: = top) and oriented as in the OpenGL spec, table "Selection of cube map images", with s
#: running left -> right along the columns and t top -> bottom along the rows:
#: +X: (sc, tc) = (-z, -y), -X: (+z, -y), +Y: (+x, +z), -Y: (+x, -z), +Z: (+x, -y),
#: -Z: (-x, -y), and ``s = (sc / |ma| + 1) / 2``, ``t = (tc / |ma| + 1) / 2``.
CUBE_FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")


def _check_uv_inputs(
    texture_shape: tuple[int, ...],
    uv: torch.Tensor,
    filter: str,
    duv_dx: torch.Tensor | None,
    duv_dy: torch.Tensor | None,
    lod: torch.Tensor | None,
) -> None:
    check_tensor("uv", uv, ("B", 2, "H", "W"), floating=True)
    if uv.shape[0] != texture_shape[0] and texture_shape[0] != 1:
        raise ValueError(
            f"uv: batch size {uv.shape[0]} does not match the texture's {texture_shape[0]}"
        )
    if filter not in FILTERS:
        raise ValueError(f"filter: expected one of {FILTERS}, got {filter!r}")
    if filter == "anisotropic" and lod is not None:
        raise ValueError("lod: not used by filter='anisotropic' (its lod comes from duv_dx "
                         "and duv_dy; shift it with lod_bias)")
    if filter in ("trilinear", "anisotropic") and lod is None:
        if duv_dx is None or duv_dy is None:
            raise ValueError(f"duv_dx, duv_dy: required for filter={filter!r}"
                             + (" (or give lod)" if filter == "trilinear" else ""))
        for name, d in (("duv_dx", duv_dx), ("duv_dy", duv_dy)):
            check_tensor(name, d, ("B", 2, "H", "W"), floating=True, finite=True)
            if d.shape != uv.shape:
                raise ValueError(f"{name}: expected shape {tuple(uv.shape)}, got {tuple(d.shape)}")
    if lod is not None:
        check_tensor("lod", lod, ("B", 1, "H", "W"), floating=True, finite=True)
        if lod.shape[-2:] != uv.shape[-2:]:
            want = f"(B, 1, {uv.shape[2]}, {uv.shape[3]})"
            raise ValueError(f"lod: expected {want}, got {tuple(lod.shape)}")


def _expand_batch(tex: torch.Tensor, b: int) -> torch.Tensor:
    return tex.expand(b, *tex.shape[1:]) if tex.shape[0] != b else tex


def _sample(
    levels: Sequence[torch.Tensor],
    uv: torch.Tensor,
    filter: str,
    address: tuple[str, str],
    duv_dx: torch.Tensor | None,
    duv_dy: torch.Tensor | None,
    lod: torch.Tensor | None,
    lod_bias: float | torch.Tensor,
    padded: Sequence[torch.Tensor] | None = None,
    max_anisotropy: int = 16,
) -> torch.Tensor:
    # half precision: texel coordinates and lookups in float32, the result cast back
    # (numerics' policy; grid_sample's half backward crashes on CPU)
    out_dtype = uv.dtype
    dt = compute_dtype(uv)
    levels = [t.to(dt) for t in levels]
    padded = None if padded is None else [t.to(dt) for t in padded]
    uv = uv.to(dt)
    duv_dx = None if duv_dx is None else duv_dx.to(dt)
    duv_dy = None if duv_dy is None else duv_dy.to(dt)
    lod = None if lod is None else lod.to(dt)
    if isinstance(lod_bias, torch.Tensor):
        lod_bias = lod_bias.to(dt)
    u, v = uv[:, 0], uv[:, 1]
    if filter in ("nearest", "bilinear"):
        if padded is None:
            out = sample_level(levels[0], u, v, filter, address)
        else:
            out = sample_padded(padded[0], u, v, filter, address)
    elif filter == "anisotropic":
        assert duv_dx is not None and duv_dy is not None
        out = sample_anisotropic(levels, uv, duv_dx, duv_dy, address, max_anisotropy,
                                 lod_bias, padded)
    else:
        if lod is None:
            assert duv_dx is not None and duv_dy is not None
            lod = compute_lod(duv_dx, duv_dy, tuple(levels[0].shape[-2:]), lod_bias)
        else:
            lod = lod + lod_bias
        out = sample_levels(levels, u, v, lod, address, padded)
    return finish_low_precision(out, out_dtype)


def sample_texture(
    texture: torch.Tensor,
    uv: torch.Tensor,
    *,
    filter: Filter = "bilinear",
    address: Address | tuple[Address, Address] = "wrap",
    duv_dx: torch.Tensor | None = None,
    duv_dy: torch.Tensor | None = None,
    lod: torch.Tensor | None = None,
    lod_bias: float | torch.Tensor = 0.0,
    pyramid: Literal["box", "gaussian"] = "box",
    max_anisotropy: int = 16,
) -> torch.Tensor:
    """Sample a texture at per-pixel UVs.

    For repeated trilinear lookups into the same texture use :class:`MipTexture`, which
    builds the pyramid once; this function rebuilds it on every trilinear call.

    Args:
        texture: ``(B, C, Ht, Wt)`` or ``(1, C, Ht, Wt)`` (shared by the batch), float.
        uv: ``(B, 2, H, W)`` texture coordinates (channel 0 = u, 1 = v; v up).
        filter: ``"nearest"``, ``"bilinear"`` (level 0), ``"trilinear"`` (mip-mapped;
            needs ``duv_dx`` and ``duv_dy``, or an explicit ``lod``) or ``"anisotropic"``
            (up to ``max_anisotropy`` trilinear probes along the footprint's major axis,
            :mod:`torchraster.anisotropic`; needs ``duv_dx`` and ``duv_dy``).
        address: ``"wrap"`` (repeat), ``"clamp"`` (to edge) or ``"mirror"`` (mirrored
            repeat), or a ``(u_mode, v_mode)`` pair.
        duv_dx, duv_dy: ``(B, 2, H, W)`` UV derivatives along screen x and y (UV / pixel).
        lod: ``(B, 1, H, W)`` explicit level of detail (overrides the derivatives).
        lod_bias: added to the level of detail.
        pyramid: mip filter for trilinear, ``"box"`` or ``"gaussian"`` (kornia pyrdown).
        max_anisotropy: largest number of probes a pixel for ``"anisotropic"`` (1 to 64;
            GPUs offer 2 to 16), ignored by the other filters.

    Returns:
        ``(B, C, H, W)`` filtered texels in the texture's units, dtype of ``uv``.
    """
    check_tensor("texture", texture, ("B", "C", "Ht", "Wt"), floating=True)
    _check_uv_inputs(tuple(texture.shape), uv, filter, duv_dx, duv_dy, lod)
    pair = address_pair(address)
    mipmapped = filter in ("trilinear", "anisotropic")
    levels = build_mip_pyramid(texture, pyramid=pyramid) if mipmapped else [texture]
    return _sample(levels, uv, filter, pair, duv_dx, duv_dy, lod, lod_bias,
                   max_anisotropy=max_anisotropy)


class MipTexture:
    """A texture with its mip pyramid built once at construction and reused by ``sample``.

    The pyramid is part of the autograd graph of ``texture``: if the texture is being
    optimised, build a new ``MipTexture`` after each optimizer step (it is cheap: 4/3 of
    the texture size), since one graph can only be back-propagated once.

    Args:
        texture: ``(B, C, Ht, Wt)`` float texture (B may be 1 to share it).
        address: default address mode(s) for :meth:`sample`.
        pyramid: ``"box"`` (default) or ``"gaussian"``, see :func:`build_mip_pyramid`.
    """

    def __init__(
        self,
        texture: torch.Tensor,
        *,
        address: Address | tuple[Address, Address] = "wrap",
        pyramid: Literal["box", "gaussian"] = "box",
    ) -> None:
        check_tensor("texture", texture, ("B", "C", "Ht", "Wt"), floating=True)
        self.address = address_pair(address)
        # Each level is padded once for the default address mode (sampling reads padded
        # levels); the levels are views into the padded tensors, so memory is not doubled.
        self._padded = [pad_texture(t, *self.address)
                        for t in build_mip_pyramid(texture, pyramid=pyramid)]
        self.levels: list[torch.Tensor] = [p[..., 1:-1, 1:-1] for p in self._padded]

    @property
    def num_levels(self) -> int:
        """Number of mip levels (down to 1x1)."""
        return len(self.levels)

    def sample(
        self,
        uv: torch.Tensor,
        duv_dx: torch.Tensor | None = None,
        duv_dy: torch.Tensor | None = None,
        *,
        filter: Filter = "trilinear",
        address: Address | tuple[Address, Address] | None = None,
        lod: torch.Tensor | None = None,
        lod_bias: float | torch.Tensor = 0.0,
        max_anisotropy: int = 16,
    ) -> torch.Tensor:
        """Sample at ``uv`` ``(B, 2, H, W)`` -> ``(B, C, H, W)``; see :func:`sample_texture`."""
        _check_uv_inputs(tuple(self.levels[0].shape), uv, filter, duv_dx, duv_dy, lod)
        pair = self.address if address is None else address_pair(address)
        padded = self._padded if pair == self.address else None
        return _sample(self.levels, uv, filter, pair, duv_dx, duv_dy, lod, lod_bias, padded,
                       max_anisotropy)


# ------------------------------------------------------------------ environment lookups


def _safe_dir(direction: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """x, y, z components ``(B, H, W)``; zero-length directions become +y (zero gradient)."""
    ok = (direction * direction).sum(1) > DIR_EPS2
    x, y, z = direction.unbind(1)
    zero, one = torch.zeros_like(x), torch.ones_like(y)
    return torch.where(ok, x, zero), torch.where(ok, y, one), torch.where(ok, z, zero)


def latlong_uv(direction: torch.Tensor) -> torch.Tensor:
    """UV of a direction in a lat-long (equirectangular) map: ``(B, 3, H, W) -> (B, 2, H, W)``.

    Layout: +y (up) is the top row (v = 1), -y the bottom row (v = 0); the image centre
    (u = 0.5) looks along -z (the default camera forward), u grows towards +x, so the map
    appears unmirrored when seen from inside the sphere. ``u = 0.5 + atan2(x, -z) / 2 pi``,
    ``v = 1 - theta / pi`` with theta the angle from +y. Directions need not be unit length;
    the poles and zero vectors get finite gradients ("double where").
    """
    check_tensor("direction", direction, ("B", 3, "H", "W"), floating=True)
    x, y, z = _safe_dir(direction)
    rxz2 = x * x + z * z
    pole = rxz2 <= DIR_EPS2
    xs = torch.where(pole, torch.zeros_like(x), x)
    zs = torch.where(pole, -torch.ones_like(z), z)  # azimuth 0 at the poles
    rxz = torch.sqrt(torch.where(pole, torch.ones_like(rxz2), rxz2))
    rxz = torch.where(pole, torch.zeros_like(rxz), rxz)
    u = 0.5 + torch.atan2(xs, -zs) / (2.0 * math.pi)
    theta = torch.atan2(rxz, y)
    return torch.stack((u, 1.0 - theta / math.pi), 1)


def latlong_directions(
    height: int, width: int, *, device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Unit directions of the texel centres of an ``H x W`` lat-long map: ``(1, 3, H, W)``."""
    theta = (torch.arange(height, device=device, dtype=dtype) + 0.5) * (math.pi / height)
    phi = ((torch.arange(width, device=device, dtype=dtype) + 0.5) / width - 0.5) * (2 * math.pi)
    st, ct = torch.sin(theta)[:, None], torch.cos(theta)[:, None]
    x = st * torch.sin(phi)[None, :]
    z = -st * torch.cos(phi)[None, :]
    y = ct.expand(height, width)
    return torch.stack((x, y, z), 0)[None]


def latlong_solid_angles(
    height: int, width: int, *, device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Exact solid angle (sr) of each texel of an ``H x W`` lat-long map: ``(H, 1)``.

    ``(2 pi / W) (cos theta_top - cos theta_bottom)`` per row; the total is exactly 4 pi.
    """
    edges = torch.arange(height + 1, device=device, dtype=torch.float64) * (math.pi / height)
    c = torch.cos(edges)
    return ((c[:-1] - c[1:]) * (2 * math.pi / width)).to(dtype)[:, None]


def sample_latlong(
    env: torch.Tensor | Sequence[torch.Tensor],
    direction: torch.Tensor,
    *,
    filter: Filter = "bilinear",
    lod: torch.Tensor | None = None,
) -> torch.Tensor:
    """Look up a lat-long environment map by direction.

    Args:
        env: ``(B, C, He, We)`` (or ``(1, C, He, We)``) map, or a list of mip levels of it
            (level 0 first) for ``filter="trilinear"``.
        direction: ``(B, 3, H, W)`` world directions (any length > 0).
        filter: ``"nearest"``, ``"bilinear"`` or ``"trilinear"`` (needs ``lod``).
        lod: ``(B, 1, H, W)`` level of detail for trilinear (level units).

    Returns:
        ``(B, C, H, W)``. Addressing wraps in u (longitude) and clamps in v (latitude).
    """
    levels = [env] if isinstance(env, torch.Tensor) else list(env)
    check_tensor("env", levels[0], ("B", "C", "He", "We"), floating=True)
    if filter == "anisotropic":
        raise ValueError("filter: expected 'nearest', 'bilinear' or 'trilinear' in "
                         "sample_latlong, got 'anisotropic' (it needs UV derivatives)")
    uv = latlong_uv(direction.to(compute_dtype(direction)))  # half: float32 angles
    if filter == "trilinear" and lod is None:
        raise ValueError("lod: required for filter='trilinear' in sample_latlong")
    _check_uv_inputs(tuple(levels[0].shape), uv, filter, None, None, lod)
    if filter == "trilinear" and len(levels) == 1:
        levels = build_mip_pyramid(levels[0])
    out = _sample(levels, uv, filter, ("wrap", "clamp"), None, None, lod, 0.0)
    return finish_low_precision(out, direction.dtype)


def cube_directions(
    size: int, *, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32,
    border: int = 0,
) -> torch.Tensor:
    """Directions (not unit) of the texel centres of a cube map: ``(6, 3, S + 2b, S + 2b)``.

    Face order and orientation: see :data:`CUBE_FACES`. ``border`` texels beyond each edge
    continue the face plane (used to build seamless aprons).
    """
    n = size + 2 * border
    c = (torch.arange(n, device=device, dtype=dtype) - border + 0.5) / size * 2.0 - 1.0
    tc, sc = torch.meshgrid(c, c, indexing="ij")  # rows = t, columns = s
    one = torch.ones_like(sc)
    faces = [
        (one, -tc, -sc),  # +X: sc = -z, tc = -y
        (-one, -tc, sc),  # -X: sc = +z, tc = -y
        (sc, one, tc),  # +Y: sc = +x, tc = +z
        (sc, -one, -tc),  # -Y: sc = +x, tc = -z
        (sc, -tc, one),  # +Z: sc = +x, tc = -y
        (-sc, -tc, -one),  # -Z: sc = -x, tc = -y
    ]
    return torch.stack([torch.stack(f, 0) for f in faces], 0)


def cube_uv(direction: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Face index ``(B, H, W)`` int64 and face coordinates ``(B, 2, H, W)`` (s, t in [0, 1],
    s along columns left -> right, t along rows top -> bottom) of directions ``(B, 3, H, W)``.
    """
    check_tensor("direction", direction, ("B", 3, "H", "W"), floating=True)
    x, y, z = _safe_dir(direction)
    ax, ay, az = x.abs(), y.abs(), z.abs()
    use_x = (ax >= ay) & (ax >= az)
    use_y = ~use_x & (ay >= az)
    face = torch.where(
        use_x, torch.where(x >= 0, 0, 1), torch.where(use_y, torch.where(y >= 0, 2, 3),
                                                      torch.where(z >= 0, 4, 5))
    )
    ma = torch.where(use_x, ax, torch.where(use_y, ay, az))  # > 0 thanks to _safe_dir
    sc_all = torch.stack((-z, z, x, x, x, -x), 0)
    tc_all = torch.stack((-y, -y, z, -z, -y, -y), 0)
    idx = face[None]
    sc = torch.gather(sc_all, 0, idx)[0]
    tc = torch.gather(tc_all, 0, idx)[0]
    st = torch.stack((sc / ma, tc / ma), 1) * 0.5 + 0.5
    return face.long(), st


def _cube_atlas(cube: torch.Tensor) -> torch.Tensor:
    """Stack the 6 faces with a 1-texel apron fetched from the neighbouring faces (nearest
    texel in the direction of the apron texel centre): ``(B, C, 6 (S + 2), S + 2)``."""
    b, _, c, s, _ = cube.shape
    dirs = cube_directions(s, device=cube.device, dtype=cube.dtype, border=1)  # (6, 3, n, n)
    n = s + 2
    d = dirs.permute(1, 0, 2, 3).reshape(1, 3, 6 * n, n).expand(b, 3, 6 * n, n)
    face, st = cube_uv(d)
    col = (st[:, 0] * s).floor().clamp(0, s - 1).long()
    row = (st[:, 1] * s).floor().clamp(0, s - 1).long()
    flat = cube.permute(0, 2, 1, 3, 4).reshape(b, c, 6 * s * s)
    idx = (face * s * s + row * s + col).reshape(b, 1, -1).expand(b, c, -1)
    apron = torch.gather(flat, 2, idx).reshape(b, c, 6, n, n)
    inner = cube.permute(0, 2, 1, 3, 4)
    apron = apron.clone()
    apron[..., 1:-1, 1:-1] = inner
    return apron.reshape(b, c, 6 * n, n)


def sample_cube(
    cube: torch.Tensor,
    direction: torch.Tensor,
    *,
    filter: Literal["nearest", "bilinear"] = "bilinear",
) -> torch.Tensor:
    """Look up a cube map by direction.

    Args:
        cube: ``(B, 6, C, S, S)`` faces in :data:`CUBE_FACES` order (B may be 1).
        direction: ``(B, 3, H, W)`` world directions (any length > 0).
        filter: ``"nearest"`` or ``"bilinear"``. Bilinear is seamless up to the corner
            texels: each face gets a one-texel apron copied from its neighbours.

    Returns:
        ``(B, C, H, W)``.
    """
    check_tensor("cube", cube, ("B", 6, "C", "S", "S"), floating=True)
    if cube.shape[-1] != cube.shape[-2]:
        raise ValueError(f"cube: faces must be square, got {tuple(cube.shape[-2:])}")
    if filter not in ("nearest", "bilinear"):
        raise ValueError(f"filter: expected 'nearest' or 'bilinear', got {filter!r}")
    dt = compute_dtype(direction)  # half precision: looked up in float32, cast back
    face, st = cube_uv(direction.to(dt))
    b = direction.shape[0]
    if cube.shape[0] not in (1, b):
        raise ValueError(f"cube: batch size {cube.shape[0]} does not match direction's {b}")
    s = cube.shape[-1]
    n = s + 2
    atlas = _cube_atlas(_expand_batch(cube.to(dt), b))
    x = st[:, 0] * s + 0.5  # texel index inside the apron-padded face (centres at ints)
    y = st[:, 1] * s + 0.5 + face.to(st.dtype) * n
    grid = torch.stack((2.0 * x / (n - 1) - 1.0, 2.0 * y / (6 * n - 1) - 1.0), -1)
    out = grid_sample(atlas, grid, mode=filter, padding_mode="border", align_corners=True)
    return finish_low_precision(out, direction.dtype)


def latlong_to_cube(env: torch.Tensor, size: int, *, supersample: int = 2) -> torch.Tensor:
    """Resample a lat-long map ``(B, C, He, We)`` to a cube map ``(B, 6, C, S, S)``.

    Each cube texel averages ``supersample**2`` bilinear lat-long lookups (box filter over
    the texel), using a mip level of the lat-long map matched to the cube texel size.
    """
    check_tensor("env", env, ("B", "C", "He", "We"), floating=True)
    if int(size) != size or size < 1:
        raise ValueError(f"size: expected a positive int, got {size!r}")
    if int(supersample) != supersample or supersample < 1:
        raise ValueError(f"supersample: expected a positive int, got {supersample!r}")
    b, c, he, _ = env.shape
    k = supersample
    dirs = cube_directions(size * k, device=env.device, dtype=env.dtype)  # (6, 3, Sk, Sk)
    d = dirs.permute(1, 0, 2, 3).reshape(1, 3, 6 * size * k, size * k).expand(b, -1, -1, -1)
    # a cube texel spans ~ (pi/2)/size radians; a lat-long texel pi/He at the equator
    lod = math.log2(max(1.0, (he / math.pi) * (math.pi / 2) / (size * k)))
    lodt = torch.full((b, 1, d.shape[2], d.shape[3]), lod, device=env.device, dtype=env.dtype)
    vals = sample_latlong(build_mip_pyramid(env), d, filter="trilinear", lod=lodt)
    vals = F.avg_pool2d(vals, k)  # (B, C, 6 S, S)
    return vals.reshape(b, c, 6, size, size).permute(0, 2, 1, 3, 4).contiguous()
