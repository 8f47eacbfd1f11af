"""Perspective-correct interpolation of vertex attributes (docs/design.md, "Public contract").

:func:`interpolate` returns the interpolated image, :func:`interpolate_with_derivatives`
also its screen-space derivatives (for texture level of detail); both always return the same
types. :func:`interpolate_packed` works on the covered pixels only (the G-buffer pass).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .._validate import check_tensor
from .rasterize import Fragments


def to_image(packed: torch.Tensor, frags: Fragments, fill: float = 0.0) -> torch.Tensor:
    """Scatter (C, N) per-covered-pixel values into a (B, C, H, W) image, ``fill`` elsewhere."""
    b, h, w = frags.face_id.shape
    flat = packed.new_full((packed.shape[0], b * h * w), fill).index_copy(1, frags.pixels, packed)
    return flat.view(-1, b, h, w).transpose(0, 1)


def interpolate_packed(
    vertex_attrs: torch.Tensor, frags: Fragments, derivatives: bool = False
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """Interpolate at the covered pixels only: (B, V, C) or (V, C) -> (C, N).

    N = ``frags.pixels.numel()``; with ``derivatives`` also d/d col and d/d row, each
    (C, N) (else None). Used by the G-buffer pass, which works on covered pixels only.
    """
    b = frags.face_id.shape[0]
    if isinstance(vertex_attrs, torch.Tensor) and vertex_attrs.dim() == 2:
        vertex_attrs = vertex_attrs.unsqueeze(0)
    check_tensor("vertex_attrs", vertex_attrs, (None, "V", "C"), floating=True)
    if vertex_attrs.shape[0] not in (1, b):
        raise ValueError(
            f"vertex_attrs: batch size {vertex_attrs.shape[0]} does not match the fragments' "
            f"batch size {b} (use (V, C) or (1, V, C) to share attributes)")
    if derivatives and frags.bary_dx_packed is None:
        raise ValueError("derivatives=True needs fragments from rasterize(..., derivatives=True)")
    n_vert, n_chan = vertex_attrs.shape[1:]
    if n_chan == 0:
        raise ValueError("vertex_attrs: expected at least one channel (C >= 1), got C = 0")
    if frags.corners.numel() and int(frags.corners.max()) >= n_vert:
        raise ValueError(
            f"vertex_attrs: V={n_vert} is smaller than the mesh the fragments came from")
    ids = frags.corners
    if vertex_attrs.shape[0] == b and b > 1:
        ids = ids + frags.items * n_vert
    # Component-major gather (C, 3, N): every row a contiguous vector.
    attrs_t = vertex_attrs.permute(2, 0, 1).reshape(n_chan, -1)
    flat_ids = ids.reshape(-1)
    # One 1-D gather per channel (faster than a dim-1 gather of the (C, B*V) table).
    corner = torch.stack([a.index_select(0, flat_ids) for a in attrs_t]).view(n_chan, 3, -1)

    def weigh(weights: torch.Tensor) -> torch.Tensor:  # (C, 3, N) x (3, N) -> (C, N)
        wt = weights.T.to(corner.dtype)
        return corner[:, 0] * wt[0] + corner[:, 1] * wt[1] + corner[:, 2] * wt[2]

    value = weigh(frags.bary_packed)
    if not derivatives:
        return value, None, None
    return value, weigh(frags.bary_dx_packed), weigh(frags.bary_dy_packed)


class Interpolated(NamedTuple):
    """An interpolated attribute image and its screen-space derivatives, each ``(B, C, H, W)``.

    Attributes:
        value: the interpolated attributes, 0 where nothing is covered.
        ddx: d value / d column: the change per pixel step to the right.
        ddy: d value / d row: the change per pixel step down (rows grow downwards).
    """

    value: torch.Tensor
    ddx: torch.Tensor
    ddy: torch.Tensor


def _check_interpolate_args(vertex_attrs: torch.Tensor, frags: Fragments,
                            faces: torch.Tensor) -> None:
    if not isinstance(frags, Fragments):
        raise TypeError(f"frags: expected Fragments from rasterize, got {type(frags).__name__}")
    check_tensor("faces", faces, ("F", 3), integer=True)
    if isinstance(vertex_attrs, torch.Tensor) and vertex_attrs.dim() in (2, 3):
        n_vert = vertex_attrs.shape[-2]
        if faces.numel() and int(faces.max()) >= n_vert:
            raise ValueError(
                f"faces: index {int(faces.max())} out of range for vertex_attrs with V={n_vert}")


def interpolate(vertex_attrs: torch.Tensor, frags: Fragments, faces: torch.Tensor) -> torch.Tensor:
    """Interpolate vertex attributes over the visible faces, perspective-correctly.

    Each covered pixel gets the barycentric combination of its visible face's three vertex
    attributes (the barycentrics of ``frags`` are perspective-correct); empty pixels get 0.
    Differentiable with respect to ``vertex_attrs`` and, through the barycentrics, the
    clip-space positions given to :func:`~torchraster.rasterize`. For the screen-space
    derivatives as well, use :func:`interpolate_with_derivatives`.

    Args:
        vertex_attrs: float attributes per vertex, per batch item or shared by the batch.
        frags: the :class:`~torchraster.raster.Fragments` of :func:`~torchraster.rasterize`
            called with the same ``faces``.
        faces: int64 vertex indices (checked against ``vertex_attrs``; the fragments already
            hold each visible face's vertex ids).

    Returns:
        The interpolated attributes, 0 where nothing is covered. The result is a view of a
        channel-major buffer; call ``.contiguous()`` if a copy in NCHW order is needed.

    Shape:
        - vertex_attrs: :math:`(B, V, C)` or :math:`(V, C)` (shared by the batch).
        - faces: :math:`(F, 3)`.
        - Output: :math:`(B, C, H, W)`, with B, H, W those of ``frags.face_id``.

    Example:
        >>> import torch, torchraster as tr
        >>> clip = torch.tensor([[[-1.0, -1, 0, 1], [3, -1, 0, 1], [-1, 3, 0, 1]]])
        >>> faces = torch.tensor([[0, 1, 2]])
        >>> frags = tr.rasterize(clip, faces, (4, 4))
        >>> tr.interpolate(torch.eye(3), frags, faces).shape
        torch.Size([1, 3, 4, 4])
    """
    _check_interpolate_args(vertex_attrs, frags, faces)
    value, _, _ = interpolate_packed(vertex_attrs, frags)
    return to_image(value, frags)


def interpolate_with_derivatives(
    vertex_attrs: torch.Tensor, frags: Fragments, faces: torch.Tensor
) -> Interpolated:
    """Interpolate vertex attributes and their screen-space derivatives per pixel step.

    Like :func:`interpolate`, plus the exact derivatives of the (perspective-correct)
    interpolated attributes with respect to the pixel column and row, as used for texture
    level of detail (mip-mapping). The derivatives come from the barycentric derivatives of
    ``rasterize(..., derivatives=True)``; they are analytic (not finite differences between
    neighbouring pixels), so they are defined at silhouettes and on one-pixel triangles.

    Args:
        vertex_attrs: float attributes per vertex, per batch item or shared by the batch.
        frags: the :class:`~torchraster.raster.Fragments` of
            ``rasterize(..., derivatives=True)`` called with the same ``faces``.
        faces: int64 vertex indices.

    Returns:
        :class:`Interpolated` ``(value, ddx, ddy)``: the attributes, their change per pixel
        step right (``ddx``) and per pixel step down (``ddy``); all 0 where nothing is
        covered. Differentiable like :func:`interpolate`.

    Raises:
        ValueError: if ``frags`` were rasterized without ``derivatives=True``.

    Shape:
        - vertex_attrs: :math:`(B, V, C)` or :math:`(V, C)`.
        - faces: :math:`(F, 3)`.
        - Output: three :math:`(B, C, H, W)` tensors.

    Example:
        >>> import torch, torchraster as tr
        >>> clip = torch.tensor([[[-1.0, -1, 0, 1], [3, -1, 0, 1], [-1, 3, 0, 1]]])
        >>> faces = torch.tensor([[0, 1, 2]])
        >>> frags = tr.rasterize(clip, faces, (4, 4), derivatives=True)
        >>> uv = torch.tensor([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0]])
        >>> value, ddx, ddy = tr.interpolate_with_derivatives(uv, frags, faces)
        >>> ddx[0, :, 0, 0], ddy[0, :, 0, 0]  # u grows to the right, v upwards
        (tensor([0.2500, 0.0000]), tensor([ 0.0000, -0.2500]))
    """
    _check_interpolate_args(vertex_attrs, frags, faces)
    value, ddx, ddy = interpolate_packed(vertex_attrs, frags, derivatives=True)
    return Interpolated(to_image(value, frags), to_image(ddx, frags), to_image(ddy, frags))
