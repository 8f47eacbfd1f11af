"""Perspective-correct interpolation of vertex attributes (see DESIGN.md contract)."""

from __future__ import annotations

import torch

from .._validate import check_tensor
from .rasterize import Fragments


def _to_image(packed: torch.Tensor, frags: Fragments) -> torch.Tensor:
    """Scatter (C, N) per-covered-pixel values into a zero (B, C, H, W) image."""
    b, h, w = frags.face_id.shape
    flat = packed.new_zeros(packed.shape[0], b * h * w).index_copy(1, frags.pixels, packed)
    return flat.view(-1, b, h, w).transpose(0, 1)


def interpolate(
    vertex_attrs: torch.Tensor,
    frags: Fragments,
    faces: torch.Tensor,
    derivatives: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Interpolate vertex attributes over the visible faces, perspective-correctly.

    vertex_attrs: (B, V, C) or (V, C) (shared by the batch) float attributes.
    frags: from :func:`torchraster.rasterize` with the same ``faces``.
    faces: (F, 3) int64 (checked for shape; the fragments already hold each visible face's
    vertex ids).
    Returns (B, C, H, W), 0 where nothing is covered; differentiable with respect to
    vertex_attrs and, through the barycentrics, the clip positions. With ``derivatives``
    (needs ``rasterize(..., derivatives=True)``) also returns the screen-space derivatives
    d attr / d col and d attr / d row, each (B, C, H, W), per pixel step (row axis down).
    The result is a view of a channel-major buffer; call ``.contiguous()`` if a copy in
    NCHW order is needed.
    """
    if not isinstance(frags, Fragments):
        raise TypeError(f"frags: expected Fragments from rasterize, got {type(frags).__name__}")
    b = frags.face_id.shape[0]
    if isinstance(vertex_attrs, torch.Tensor) and vertex_attrs.dim() == 2:
        vertex_attrs = vertex_attrs.unsqueeze(0)
    check_tensor("vertex_attrs", vertex_attrs, (None, "V", "C"), floating=True)
    if vertex_attrs.shape[0] not in (1, b):
        raise ValueError(
            f"vertex_attrs: batch size {vertex_attrs.shape[0]} does not match the fragments' "
            f"batch size {b} (use (V, C) or (1, V, C) to share attributes)")
    check_tensor("faces", faces, ("F", 3), integer=True)
    faces = faces.to(device=vertex_attrs.device, dtype=torch.int64)
    if faces.numel() and int(faces.max()) >= vertex_attrs.shape[1]:
        raise ValueError(
            f"faces: index {int(faces.max())} out of range for vertex_attrs with "
            f"V={vertex_attrs.shape[1]}")
    if derivatives and frags.bary_dx_packed is None:
        raise ValueError("derivatives=True needs fragments from rasterize(..., derivatives=True)")

    n_vert, n_chan = vertex_attrs.shape[1:]
    if frags.corners.numel() and int(frags.corners.max()) >= n_vert:
        raise ValueError(f"vertex_attrs: V={n_vert} is smaller than the mesh the fragments came from")
    ids = frags.corners
    if vertex_attrs.shape[0] == b and b > 1:
        ids = ids + frags.items * n_vert
    # Component-major gather (C, 3, N): every row a contiguous vector.
    attrs_t = vertex_attrs.permute(2, 0, 1).reshape(n_chan, -1)
    corner = attrs_t.index_select(1, ids.reshape(-1)).view(n_chan, 3, -1)
    bary = frags.bary_packed.T.to(vertex_attrs.dtype)  # (3, N)
    image = _to_image((corner * bary).sum(1), frags)
    if not derivatives:
        return image
    ddx = (corner * frags.bary_dx_packed.T.to(corner.dtype)).sum(1)
    ddy = (corner * frags.bary_dy_packed.T.to(corner.dtype)).sum(1)
    return image, _to_image(ddx, frags), _to_image(ddy, frags)
