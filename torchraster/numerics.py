"""The small shared math of the renderer: one definition (and one constant) each.

* :func:`safe_normalize` / :func:`dot`: unit vectors and dot products over any axis, with
  finite values and gradients for zero vectors ("double where").
* :func:`specular_f0` / :func:`diffuse_color`: the metallic-roughness split of a base
  colour (glTF 2.0 appendix B, Filament section 4.8.3).
* :func:`compute_dtype` / :func:`finish_low_precision`: the half-precision policy: float16
  and bfloat16 inputs are evaluated in float32 and cast back, saturated to the finite range
  (Filament's ``saturateMediump``), so low-precision inputs never produce Inf.
* :func:`grid_sample`: ``F.grid_sample`` in the compute dtype (never in half precision).
* :func:`take_columns`: ``table.index_select(1, index)`` of a 2-D table by the fastest
  gather on CPU (torch's float32 dim-1 path for contiguous float32, else one 1-D gather per
  row).
* :func:`floor_div_exact`: integer floor division of non-negative indices through float64
  (faster than int64 division on CPU), exact within its stated bound.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

#: Squared length below which a vector counts as zero for :func:`safe_normalize`
#: (|x| < 1e-6): it then maps to the zero vector with a zero (finite) gradient.
NORMALIZE_EPS: float = 1e-12

#: Dielectric reflectance at normal incidence (4 %, IOR 1.5): f0 of a metallic = 0 surface.
DIELECTRIC_F0: float = 0.04

#: dtypes evaluated in float32 and saturated on output (see :func:`finish_low_precision`).
LOW_PRECISION: tuple[torch.dtype, ...] = (torch.float16, torch.bfloat16)

#: :func:`floor_div_exact` is exact for dividends below this (see its docstring).
FLOOR_DIV_EXACT_LIMIT: int = 2**50


def dot(a: torch.Tensor, b: torch.Tensor, dim: int = -3) -> torch.Tensor:
    """Dot product over ``dim`` (kept with size 1).

    Args:
        a, b: broadcastable tensors, vector components on ``dim``, e.g. ``(B, 3, H, W)``.
        dim: the component axis (-3 for image-like tensors, -1 for vertex data).

    Returns:
        The dot products, ``a``'s shape with ``dim`` of size 1, e.g. ``(B, 1, H, W)``.
    """
    return (a * b).sum(dim=dim, keepdim=True)


def safe_normalize(x: torch.Tensor, dim: int = -3, eps: float = NORMALIZE_EPS,
                   inplace: bool = False) -> torch.Tensor:
    """Unit vectors along ``dim``; vectors with squared length <= ``eps`` map to 0.

    "Double where": the reciprocal square root only sees safe values, so neither the value
    nor the gradient is ever NaN/Inf. float16 / bfloat16 are normalised in float32 and cast
    back.

    Args:
        x: any shape, vector components on ``dim``, e.g. ``(B, 3, H, W)`` or ``(B, V, 3)``.
        dim: the component axis.
        eps: squared length treated as zero (default :data:`NORMALIZE_EPS`).
        inplace: scale ``x`` itself (the same products; memory) when autograd is off and
            ``x`` is in its compute dtype (else a new tensor, as without it).

    Returns:
        Tensor of ``x``'s shape and dtype.
    """
    dtype = x.dtype
    xc = to_compute(x)
    sq = (xc * xc).sum(dim=dim, keepdim=True)
    ok = sq > eps
    inv = torch.where(ok, torch.rsqrt(torch.where(ok, sq, torch.ones_like(sq))),
                      torch.zeros_like(sq))
    if inplace and xc is x and not torch.is_grad_enabled():
        return x.mul_(inv)
    return (xc * inv).to(dtype)


def specular_f0(albedo: torch.Tensor, metallic: torch.Tensor,
                dielectric: float = DIELECTRIC_F0) -> torch.Tensor:
    """Reflectance at normal incidence, ``mix(dielectric, albedo, metallic)``.

    Args:
        albedo: base colour, linear RGB, e.g. ``(B, 3, H, W)``.
        metallic: in [0, 1], broadcastable to ``albedo``, e.g. ``(B, 1, H, W)``.
        dielectric: f0 of metallic = 0 (0.04: IOR 1.5).

    Returns:
        f0 with ``albedo``'s shape.
    """
    return dielectric * (1.0 - metallic) + albedo * metallic


def diffuse_color(albedo: torch.Tensor, metallic: torch.Tensor) -> torch.Tensor:
    """Lambertian colour of a metallic-roughness surface, ``(1 - metallic) * albedo``.

    Shapes as in :func:`specular_f0`.
    """
    return (1.0 - metallic) * albedo


def compute_dtype(*xs: object) -> torch.dtype:
    """The dtype to evaluate in: the promoted floating dtype of the tensor arguments, with
    float16 / bfloat16 (and non-floating types) raised to float32."""
    dtype = torch.float32
    tensors = [x for x in xs if isinstance(x, torch.Tensor)]
    if tensors:
        dtype = tensors[0].dtype
        for t in tensors[1:]:
            dtype = torch.promote_types(dtype, t.dtype)
        if not dtype.is_floating_point or dtype in LOW_PRECISION:
            dtype = torch.float32
    return dtype


def finish_low_precision(y: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Cast ``y`` to ``dtype``, saturating to its finite range for float16 / bfloat16."""
    if dtype in LOW_PRECISION:
        big = torch.finfo(dtype).max
        y = y.clamp(-big, big)
    return y.to(dtype)


class _SaturatingCast(torch.autograd.Function):
    """``x.to(dtype)`` whose gradient goes back to ``x``'s dtype saturated to its finite
    range (the half-precision policy of :func:`finish_low_precision` applied to gradients)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        ctx.source = x.dtype
        return x.to(dtype)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        return finish_low_precision(grad, ctx.source), None


def to_compute(x: torch.Tensor, dtype: torch.dtype | None = None) -> torch.Tensor:
    """``x`` in ``dtype`` (default :func:`compute_dtype` of ``x``: float32 for float16 /
    bfloat16); for half-precision ``x`` its gradient returns saturated to ``x``'s finite
    range, so a large float32 gradient never becomes Inf in half."""
    dtype = compute_dtype(x) if dtype is None else dtype
    return _SaturatingCast.apply(x, dtype) if x.dtype in LOW_PRECISION else x.to(dtype)


def grid_sample(input: torch.Tensor, grid: torch.Tensor, **kwargs) -> torch.Tensor:
    """``F.grid_sample`` evaluated in :func:`compute_dtype` (float32 for float16 / bfloat16).

    torch's CPU ``grid_sampler_2d_backward`` crashes the process (segfault, torch 2.x) on
    contiguous float16 / bfloat16 inputs, and half-precision texel coordinates are off by up
    to a texel (float16) or several (bfloat16) beyond 256 texels: every texture, table and
    map lookup of the renderer goes through here. Same arguments as ``F.grid_sample``;
    ``input`` ``(N, C, H_in, W_in)``, ``grid`` ``(N, H, W, 2)`` -> ``(N, C, H, W)`` in the
    compute dtype (callers cast back with :func:`finish_low_precision`).
    """
    dt = compute_dtype(input, grid)
    return F.grid_sample(input.to(dt), grid.to(dt), **kwargs)


def smoothstep(t: torch.Tensor) -> torch.Tensor:
    """Hermite ``3t^2 - 2t^3`` of ``t`` clamped to [0, 1] (any shape; C1 at both ends)."""
    t = t.clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def floor_div_exact(a: torch.Tensor, d: int) -> torch.Tensor:
    """``a // d`` for non-negative int64 ``a`` < :data:`FLOOR_DIV_EXACT_LIMIT` and ``d >= 1``.

    Computed as ``floor((a + 0.5) * (1 / d))`` in float64, about 3x faster than int64
    division on CPU. Exact: ``(a + 0.5) / d`` is at least ``0.5 / d`` away from an integer,
    while the three roundings (the sum, ``1 / d`` and the product) move it by at most
    ``3 * 2**-53 * (a + 0.5) / d``, which is smaller for ``a < 2**50``.

    Args:
        a: int64 tensor of any shape.
        d: positive int divisor.

    Returns:
        int64 tensor of ``a``'s shape.
    """
    return ((a.to(torch.float64) + 0.5) * (1.0 / d)).long()


def take_columns(table: torch.Tensor, index: torch.Tensor,
                 out: torch.Tensor | None = None) -> torch.Tensor:
    """``table.index_select(1, index)`` of a 2-D ``table`` (rows, N), written into ``out``
    (rows, len(index)) when given. Not differentiable (``out=``).

    A contiguous float32 ``table`` into a contiguous ``out``: one dim-1 gather (torch's
    contiguous float32 fast path, 0.4-0.75x the time of per-row gathers for 4-20 rows);
    anything else: one 1-D gather per row (the dim-1 gather of other dtypes copies element
    by element with memcpy, 3-5x slower for int64 pixel boxes and float64, and it first
    copies a non-contiguous table whole: per call, however few columns are taken).
    """
    if out is None:
        out = table.new_empty(table.shape[0], index.numel())
    if table.dtype == torch.float32 and table.is_contiguous() and out.is_contiguous():
        return torch.index_select(table, 1, index, out=out)
    for k in range(table.shape[0]):
        torch.index_select(table[k], 0, index, out=out[k])
    return out


__all__ = [
    "DIELECTRIC_F0", "FLOOR_DIV_EXACT_LIMIT", "LOW_PRECISION", "NORMALIZE_EPS",
    "compute_dtype", "diffuse_color", "dot", "finish_low_precision", "floor_div_exact",
    "to_compute",
    "grid_sample", "safe_normalize", "specular_f0", "take_columns",
]
