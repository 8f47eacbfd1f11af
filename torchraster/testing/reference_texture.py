"""Independent float64 reference for texture filtering: a box-filtered checkerboard plane.

The scene of the texture-quality benchmark and tests: the ground plane y = 0 seen from
height 1 by a camera pitched down, so the view runs from near the camera to a few degrees
above the horizon (strong, varying anisotropy). UV = (x, z) / 4 of the ray-plane hit.

The reference is the exact pixel-area (box) average of a checkerboard texture, computed
without any texture sampler: the camera has no roll, so along one screen row the hit's z
(hence v) is constant and x (hence u) is linear in the column. Each pixel is cut into
``row_samples`` horizontal lines; along each line the checkerboard is a square wave in u
whose average over the pixel's u interval is integrated in closed form. The only error is
the stratification in y (< ``1 / row_samples`` of the contrast where an edge crosses).
Shares no code with torchraster.
"""

from __future__ import annotations

import math

import torch

F64 = torch.float64

#: Vertical field of view of the benchmark camera (degrees).
FOV_DEG: float = 50.0


def _rays(h: int, w: int, rows: torch.Tensor, cols: torch.Tensor, tilt_deg: float
          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """For continuous pixel coordinates (rows, cols), the plane hit's x and z, and the
    terms of their derivatives: returns (x, z, ny, dz, f)."""
    f = math.tan(math.radians(FOV_DEG / 2))
    p = math.radians(90.0 - tilt_deg)
    c, s = math.cos(p), math.sin(p)
    big_x = (2 * cols / w - 1) * f * (w / h)
    big_y = (1 - 2 * rows / h) * f
    ny = -(big_y * c - s)  # the ray's downward y component (camera pitched down by p)
    dz = -big_y * s - c  # its z component
    return big_x / ny, dz / ny, ny, dz, f


def steep_plane(h: int, w: int, tilt_deg: float = 60.0, offset: tuple[float, float] = (0.0, 0.0)
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """UVs and their analytic screen-space derivatives at the pixel centres.

    Args:
        h, w: image size in pixels.
        tilt_deg: 90 minus the camera's downward pitch (60: pitched 30 degrees down, so the
            top row looks 5 degrees below the horizon with the 50 degree field of view).
        offset: ``(down, right)`` shift of the sample points from the pixel centres, in
            pixels (supersampling).

    Returns:
        ``(uv, duv_dx, duv_dy)``, float64; derivatives per pixel step right (x) and down (y).

    Shape:
        - each: ``(1, 2, h, w)``
    """
    c = math.cos(math.radians(90.0 - tilt_deg))
    s = math.sin(math.radians(90.0 - tilt_deg))
    i = torch.arange(h, dtype=F64).view(h, 1) + 0.5 + offset[0]
    j = torch.arange(w, dtype=F64).view(1, w) + 0.5 + offset[1]
    x, z, ny, dz, f = _rays(h, w, i, j, tilt_deg)
    dbx_dj, dby_di = 2 * f / h, -2 * f / h  # d(screen X)/d column, d(screen Y)/d row
    dny_di = -c * dby_di
    dx_dj, dz_dj = dbx_dj / ny, torch.zeros_like(x)
    dx_di = -x * dny_di / ny
    dz_di = (-s * dby_di * ny - dz * dny_di) / ny**2
    uv = torch.stack((x, z.expand_as(x)), 0)[None] / 4
    return (uv, torch.stack((dx_dj.expand_as(x), dz_dj), 0)[None] / 4,
            torch.stack((dx_di, dz_di.expand_as(x)), 0)[None] / 4)


def checkerboard(size: int = 512, checks: int = 32, low: float = 0.1, high: float = 0.9,
                 dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The checkerboard texture ``(1, 1, size, size)``: ``checks x checks`` squares of
    ``low`` / ``high``, ``low`` in the top-left square."""
    k = torch.arange(size) * checks // size
    board = ((k.view(-1, 1) + k.view(1, -1)) % 2).to(dtype)
    return (low + (high - low) * board).view(1, 1, size, size)


def _odd_length(x: torch.Tensor) -> torch.Tensor:
    """Length of ``{t in [0, x]: floor(t) odd}`` (negative for x < 0): the antiderivative
    of the unit square wave."""
    half = torch.floor(x / 2)
    return half + (x - 2 * half - 1).clamp(0, 1)


def checkerboard_plane_reference(h: int, w: int, tilt_deg: float = 60.0, *, checks: int = 32,
                                 low: float = 0.1, high: float = 0.9, row_samples: int = 256
                                 ) -> torch.Tensor:
    """Pixel-area average of the :func:`checkerboard` texture (wrapped) on the steep plane.

    UV (u, v) reads the texture at column ``u * size``, row ``(1 - v) * size`` (v up), so
    the square of a point is ``(floor(checks u), floor(checks (1 - v)))`` and its value
    is ``high`` when their sum is odd.

    Args:
        h, w, tilt_deg: the view of :func:`steep_plane`.
        checks, low, high: the texture of :func:`checkerboard` (its size does not matter).
        row_samples: horizontal lines a pixel (exact integration along each).

    Returns:
        ``(1, 1, h, w)`` float64.
    """
    out = torch.zeros(h, w, dtype=F64)
    edges = torch.arange(w + 1, dtype=F64).view(1, w + 1)
    for k in range(row_samples):
        rows = torch.arange(h, dtype=F64).view(h, 1) + (k + 0.5) / row_samples
        x, z, _, _, _ = _rays(h, w, rows, edges, tilt_deg)  # x at the pixel edges
        a = checks * x[:, :-1] / 4  # u interval of each pixel, in squares
        b = checks * x[:, 1:] / 4
        odd_u = (_odd_length(b) - _odd_length(a)) / (b - a)  # fraction with floor(.) odd
        kv = torch.floor(checks * (1 - z / 4))  # (h, 1): v is constant along the line
        frac = torch.where(torch.remainder(kv, 2) == 0, odd_u, 1 - odd_u)
        out += low + (high - low) * frac
    return (out / row_samples).view(1, 1, h, w)
