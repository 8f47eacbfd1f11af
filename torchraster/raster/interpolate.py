"""Perspective-correct interpolation of vertex attributes (see DESIGN.md contract)."""

from __future__ import annotations

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


def interpolate(
    vertex_attrs: torch.Tensor,
    frags: Fragments,
    faces: torch.Tensor,
    derivatives: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Interpolate vertex attributes over the visible faces, perspective-correctly.

    vertex_attrs: (B, V, C) or (V, C) (shared by the batch) float attributes.
    frags: from :func:`torchraster.rasterize` with the same ``faces``.
    faces: (F, 3) int64 (checked; the fragments already hold each visible face's vertex ids).
    Returns (B, C, H, W), 0 where nothing is covered; differentiable with respect to
    vertex_attrs and, through the barycentrics, the clip positions. With ``derivatives``
    (needs ``rasterize(..., derivatives=True)``) also returns the screen-space derivatives
    d attr / d col and d attr / d row, each (B, C, H, W), per pixel step (row axis down).
    The result is a view of a channel-major buffer; call ``.contiguous()`` if a copy in
    NCHW order is needed.
    """
    if not isinstance(frags, Fragments):
        raise TypeError(f"frags: expected Fragments from rasterize, got {type(frags).__name__}")
    check_tensor("faces", faces, ("F", 3), integer=True)
    if isinstance(vertex_attrs, torch.Tensor) and vertex_attrs.dim() in (2, 3):
        n_vert = vertex_attrs.shape[-2]
        if faces.numel() and int(faces.max()) >= n_vert:
            raise ValueError(
                f"faces: index {int(faces.max())} out of range for vertex_attrs with V={n_vert}")
    value, ddx, ddy = interpolate_packed(vertex_attrs, frags, derivatives)
    if not derivatives:
        return to_image(value, frags)
    return to_image(value, frags), to_image(ddx, frags), to_image(ddy, frags)
