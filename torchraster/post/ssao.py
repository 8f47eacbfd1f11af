"""Screen-space ambient occlusion from linear depth and view-space normals.

Normal-oriented hemisphere SSAO (Crytek 2007 / Chapman's and LearnOpenGL's variant):
for every pixel, view-space position P = d * ((j - cx) / fx, -(i - cy) / fy, -1) (OpenGL
view space: x right, y up, camera looking down -z; d = linear depth = -z). ``samples``
points in the normal-oriented hemisphere of radius ``radius`` (a fixed low-discrepancy
kernel, scaled toward P) are rotated about the normal by a per-pixel angle from a fixed 4x4
tile (ordered-dither/Bayer order) and projected back; a sample is occluded when the scene
depth there lies in front of it by more than ``bias``. The occlusion test is a linear ramp
of width ``softness`` (instead of a step, so depth gets gradients) and is weighted by the
range check smoothstep(radius / |d_P - d_scene|) against far-away occluders. Samples
that project off-screen count as unoccluded. The raw AO is
box-blurred over 4x4 pixels, which averages exactly the 16 rotations of the tile.

Output: AO (B, 1, H, W) in [0, 1], 1 = unoccluded, to multiply into ambient/indirect light.
Pixels without geometry (depth +inf, 0 or negative) get AO = 1.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .._validate import check_tensor
from ..numerics import compute_dtype, smoothstep

#: Depth substituted for empty pixels (+inf/<=0) before bilinear depth lookups (inf * 0
#: weights would give NaN); any sample is in front of it, and its range weight is ~0.
FAR_DEPTH = 1e10
#: Sample points closer to the camera plane than this (scene units) are ignored.
NEAR_EPS = 1e-6
#: Normals shorter than this are replaced by the "facing the camera" normal (0, 0, 1).
NORMAL_EPS = 1e-12

# 4x4 ordered-dither (Bayer) matrix: neighbouring pixels get well-spread rotation angles.
_BAYER4 = ((0, 8, 2, 10), (12, 4, 14, 6), (3, 11, 1, 9), (15, 7, 13, 5))


def hemisphere_kernel(samples: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Deterministic sample offsets ``(samples, 3)`` in the unit +z hemisphere.

    Directions: cosine-weighted golden-angle spiral. Lengths: lerp(0.1, 1, h^2) with h the
    base-2 radical inverse of the index (more samples close to the shaded point).
    """
    i = torch.arange(samples, dtype=torch.float64)
    u = (i + 0.5) / samples
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    r, z = torch.sqrt(u), torch.sqrt(1.0 - u)
    h = torch.tensor([_radical_inverse(k + 1) for k in range(samples)], dtype=torch.float64)
    scale = 0.1 + 0.9 * h * h
    d = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)
    return (d * scale[:, None]).to(dtype)


def _radical_inverse(k: int) -> float:
    out, f = 0.0, 0.5
    while k:
        out += f * (k & 1)
        k >>= 1
        f *= 0.5
    return out


def projection_to_intrinsics(projection: torch.Tensor, resolution: tuple[int, int]) -> torch.Tensor:
    """OpenGL projection (B, 4, 4) (or (4, 4)) -> pixel intrinsics (B, 4) = fx, fy, cx, cy.

    For perspective matrices with P[3] = (0, 0, -1, 0) and P01 = P03 = P13 = 0 (symmetric
    or off-centre frusta). Pixel (i, j) centre is NDC x = 2(j + .5)/W - 1, y = 1 - 2(i + .5)/H,
    giving j = fx x/d + cx and i = cy - fy y/d with d = -z.
    """
    h, w = resolution
    p = projection if projection.dim() == 3 else projection[None]
    fx, fy = p[:, 0, 0] * (w / 2.0), p[:, 1, 1] * (h / 2.0)
    cx = (1.0 - p[:, 0, 2]) * (w / 2.0) - 0.5
    cy = (1.0 + p[:, 1, 2]) * (h / 2.0) - 0.5
    return torch.stack([fx, fy, cx, cy], dim=-1)


def camera_intrinsics(projection: torch.Tensor | None, intrinsics: torch.Tensor | None,
                      shape: tuple[int, int, int]) -> torch.Tensor:
    """The checked pixel intrinsics (4,) or (B, 4) of a screen-space pass given exactly one
    of an OpenGL ``projection`` (4, 4) / (B, 4, 4) or ``intrinsics``; ``shape`` = (B, H, W).
    Raises ValueError naming the argument otherwise."""
    b, h, w = shape
    if (projection is None) == (intrinsics is None):
        raise ValueError("projection, intrinsics: give exactly one of them")
    if projection is not None:
        if not isinstance(projection, torch.Tensor) or projection.shape not in ((4, 4),
                                                                                (b, 4, 4)):
            raise ValueError(f"projection: expected a (4, 4) or ({b}, 4, 4) tensor")
        intrinsics = projection_to_intrinsics(projection, (h, w))
    if not isinstance(intrinsics, torch.Tensor) or intrinsics.shape not in ((4,), (b, 4)):
        raise ValueError(f"intrinsics: expected a (4,) or ({b}, 4) tensor of fx, fy, cx, cy")
    if not bool(torch.isfinite(intrinsics).all()) or bool((intrinsics[..., :2] == 0).any()):
        raise ValueError("intrinsics: must be finite with non-zero fx, fy")
    return intrinsics


def ssao(
    depth: torch.Tensor,
    normals: torch.Tensor,
    intrinsics: torch.Tensor,
    radius: float = 0.5,
    samples: int = 16,
    bias: float = 0.025,
    softness: float = 0.025,
    blur: bool = True,
) -> torch.Tensor:
    """Ambient occlusion (B, 1, H, W) in [0, 1] from depth (B, 1, H, W) and normals (B, 3, H, W).

    ``intrinsics`` (B, 4) or (4,): fx, fy, cx, cy in pixels (pixel centres at integer
    coordinates, row 0 at the top); ``radius``, ``bias``, ``softness`` in scene units.
    """
    b, _, h, w = depth.shape
    valid = torch.isfinite(depth) & (depth > 0)
    d = torch.where(valid, depth, torch.full_like(depth, FAR_DEPTH))
    k = intrinsics.to(depth.dtype).reshape(-1, 4).expand(b, 4)
    # bands of rows of about SSAO_BAND_ELEMENTS pixel-samples (each pixel's samples read
    # the whole depth image; the blur below needs the whole AO image)
    rows = max(1, SSAO_BAND_ELEMENTS // max(1, b * samples * w))
    occlusion = torch.cat([_occlusion(d, normals[:, :, r0:r0 + rows], k, r0, radius, samples,
                                      bias, softness) for r0 in range(0, h, rows)], dim=2)
    ao = torch.where(valid, 1.0 - occlusion, torch.ones_like(occlusion))
    if blur:
        ao = F.avg_pool2d(F.pad(ao, (1, 2, 1, 2), mode="replicate"), 4, stride=1)
    return ao.clamp(0.0, 1.0)


#: Pixel-samples (B x samples x rows x W) of one band of rows of :func:`ssao`: its ~20
#: per-sample temporaries then stay in the CPU's caches instead of spanning the frame
#: (docs/benchmarks.md, section pass-bands).
SSAO_BAND_ELEMENTS: int = 2**19


def _occlusion(d: torch.Tensor, normals: torch.Tensor, k: torch.Tensor, r0: int,
               radius: float, samples: int, bias: float, softness: float) -> torch.Tensor:
    """Mean occlusion ``(B, 1, rows, W)`` of the rows ``r0 .. r0 + rows`` of a frame of
    view depths ``d`` ``(B, 1, H, W)`` (empty pixels at FAR_DEPTH), their ``normals``
    ``(B, 3, rows, W)`` and intrinsics ``k`` ``(B, 4)`` (see :func:`ssao`)."""
    b, _, h, w = d.shape
    rows = normals.shape[2]
    dev, dt = d.device, d.dtype
    fx, fy, cx, cy = (k[:, n].reshape(b, 1, 1, 1) for n in range(4))
    jj = torch.arange(w, device=dev, dtype=dt).reshape(1, 1, 1, w)
    ii = torch.arange(r0, r0 + rows, device=dev, dtype=dt).reshape(1, 1, rows, 1)
    d_rows = d[:, :, r0:r0 + rows]
    px, py, pz = d_rows * (jj - cx) / fx, -d_rows * (ii - cy) / fy, -d_rows  # (B, 1, rows, W)

    # unit normal (safe: zero vectors -> facing the camera); "double where" keeps grads finite
    nn2 = (normals * normals).sum(dim=1, keepdim=True)
    ok = nn2 > NORMAL_EPS
    inv = torch.rsqrt(torch.where(ok, nn2, torch.ones_like(nn2)))
    facing = torch.tensor((0.0, 0.0, 1.0), device=dev, dtype=dt).reshape(1, 3, 1, 1)
    n = torch.where(ok, normals * inv, facing)
    nx, ny, nz = n[:, 0:1], n[:, 1:2], n[:, 2:3]
    # orthonormal basis (Duff et al. 2017, "Building an Orthonormal Basis, Revisited")
    sign = torch.where(nz >= 0, torch.ones_like(nz), -torch.ones_like(nz))
    a = -1.0 / (sign + nz)
    bb = nx * ny * a
    t = (1.0 + sign * nx * nx * a, sign * bb, -sign * nx)
    s = (bb, sign + ny * ny * a, -ny)
    # per-pixel rotation about the normal from the 4x4 tile
    tile = torch.tensor(_BAYER4, device=dev, dtype=dt)
    ang = (tile + 0.5) * (2.0 * math.pi / 16.0)
    ang = ang.repeat((rows + 3) // 4 + 1, (w + 3) // 4)[r0 % 4:r0 % 4 + rows, :w]
    ang = ang.reshape(1, 1, rows, w)
    ca, sa = torch.cos(ang), torch.sin(ang)
    t, s = (
        tuple(ca * tc + sa * sc for tc, sc in zip(t, s, strict=True)),
        tuple(-sa * tc + ca * sc for tc, sc in zip(t, s, strict=True)),
    )

    kern = hemisphere_kernel(samples, dt).to(dev)  # (N, 3)
    kx, ky, kz = (kern[:, c].reshape(1, -1, 1, 1) for c in range(3))
    pos = [p + radius * (kx * tc + ky * sc + kz * nc) for p, tc, sc, nc in
           zip((px, py, pz), t, s, (nx, ny, nz), strict=True)]  # each (B, N, rows, W)
    ds = -pos[2]
    front = ds > NEAR_EPS
    ds_safe = torch.where(front, ds, torch.ones_like(ds))
    sj = fx * pos[0] / ds_safe + cx
    si = cy - fy * pos[1] / ds_safe
    grid = torch.stack([(2.0 * sj + 1.0) / w - 1.0, (2.0 * si + 1.0) / h - 1.0], dim=-1)
    scene = F.grid_sample(
        d, grid.reshape(b, samples * rows, w, 2), mode="bilinear", padding_mode="border",
        align_corners=False,
    ).reshape(b, samples, rows, w)
    occ = ((ds - bias - scene) / softness).clamp(0.0, 1.0)
    rng = smoothstep(radius / (d_rows - scene).abs().clamp(min=radius))
    # samples behind the camera or projecting off-screen (no depth known there) count as open
    onscreen = (sj >= -0.5) & (sj <= w - 0.5) & (si >= -0.5) & (si <= h - 0.5)
    counted = front & onscreen
    return torch.where(counted, occ * rng, torch.zeros_like(occ)).mean(dim=1, keepdim=True)


class SSAO(nn.Module):
    """Screen-space AO module: depth (B,1,H,W) + normals (B,3,H,W) + camera -> AO (B,1,H,W).

    Camera: ``projection`` (B, 4, 4) or (4, 4) OpenGL matrix, or ``intrinsics`` (B, 4) /
    (4,) = fx, fy, cx, cy in pixels. ``enabled=False`` returns ones (B, 1, H, W) (nothing to
    compute; there is no input image to pass through).
    """

    def __init__(
        self,
        radius: float = 0.5,
        samples: int = 16,
        bias: float = 0.025,
        softness: float = 0.025,
        blur: bool = True,
        enabled: bool = True,
    ):
        super().__init__()
        if not radius > 0 or not bias >= 0 or not softness > 0:
            raise ValueError(
                f"radius, bias, softness: expected > 0, >= 0, > 0; got {radius}, {bias}, {softness}"
            )
        if int(samples) < 1:
            raise ValueError(f"samples: expected a positive int, got {samples}")
        self.radius, self.samples, self.bias = float(radius), int(samples), float(bias)
        self.softness, self.blur, self.enabled = float(softness), blur, enabled

    def forward(
        self,
        depth: torch.Tensor,
        normals: torch.Tensor,
        projection: torch.Tensor | None = None,
        intrinsics: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """AO (B, 1, H, W) in [0, 1]; depth is linear view depth (-z_view, scene units)."""
        depth = check_tensor("depth", depth, ("B", 1, "H", "W"), floating=True)
        b, _, h, w = depth.shape
        normals = check_tensor("normals", normals, (b, 3, h, w), floating=True, finite=True)
        if bool(torch.isnan(depth).any()):
            raise ValueError("depth: contains NaN")
        if not self.enabled:
            return torch.ones_like(depth)
        intrinsics = camera_intrinsics(projection, intrinsics, (b, h, w))
        dt = compute_dtype(depth)
        ao = ssao(
            depth.to(dt), normals.to(dt), intrinsics.to(device=depth.device, dtype=dt),
            self.radius, self.samples, self.bias, self.softness, self.blur,
        )
        return ao.to(depth.dtype)
