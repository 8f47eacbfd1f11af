"""Perspective-correct interpolation of vertex attributes (docs/design.md, "Public contract").

:func:`interpolate` returns the interpolated image, :func:`interpolate_with_derivatives`
also its screen-space derivatives (for texture level of detail); both always return the same
types. :func:`interpolate_packed` works on the covered pixels only (the G-buffer pass).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from .. import frame_pool
from .._validate import check_tensor
from ..numerics import compute_dtype, finish_low_precision, take_columns
from .rasterize import PIXEL_CHUNK, Fragments, pixel_slices


class _Scatter(torch.autograd.Function):
    """``frame[:, pixels] = packed`` into a new (C, P) frame of ``fill``, in place (one frame,
    not a filled frame and its scattered copy). Backward: d packed = grad at ``pixels``; only
    the indices are saved (autograd's ``index_copy`` also keeps ``packed`` alive)."""

    @staticmethod
    def forward(ctx, packed, pixels, frame, fill):
        flat = packed.new_full((packed.shape[0], frame), fill)
        flat.index_copy_(1, pixels, packed)
        ctx.save_for_backward(pixels)
        ctx.set_materialize_grads(False)
        return flat

    @staticmethod
    def backward(ctx, grad):
        if grad is None or not ctx.needs_input_grad[0]:
            return None, None, None, None
        (pixels,) = ctx.saved_tensors
        return grad.index_select(1, pixels), None, None, None


def to_image(packed: torch.Tensor, frags: Fragments, fill: float = 0.0) -> torch.Tensor:
    """Scatter (C, N) per-covered-pixel values into a (B, C, H, W) image, ``fill`` elsewhere.

    ``packed`` may be an expanded (C, 1) -> (C, N) view (a constant per channel).
    Differentiable with respect to ``packed``, which it does not keep alive for backward."""
    return scatter_image(packed, frags.pixels, frags.face_id.shape, fill)


def scatter_image(packed: torch.Tensor, pixels: torch.Tensor, shape: tuple[int, int, int],
                  fill: float = 0.0) -> torch.Tensor:
    """:func:`to_image` by the pixels' flat indices: (C, N) values at ``pixels`` (N,)
    (b*H*W + i*W + j) of a (B, C, H, W) image of ``shape`` (B, H, W), ``fill`` elsewhere."""
    b, h, w = shape
    flat = _Scatter.apply(packed, pixels, b * h * w, fill)
    return flat.view(-1, b, h, w).transpose(0, 1)


def _check_attrs(vertex_attrs: torch.Tensor, frags: Fragments, derivatives: bool) -> torch.Tensor:
    """Checked (B or 1, V, C) attributes (a (V, C) input gains the batch dimension)."""
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
    if frags.rows is not None:
        used = frags.faces.index_select(0, frags.row_face) if frags.row_face.numel() else None
    else:
        used = frags.corners
    if used is not None and used.numel() and int(used.max()) >= n_vert:
        raise ValueError(
            f"vertex_attrs: V={n_vert} is smaller than the mesh the fragments came from")
    return vertex_attrs


def _corner_table(vertex_attrs: torch.Tensor, frags: Fragments) -> torch.Tensor:
    """(3, C, M) attributes of the three corners of every face row of ``frags``
    (differentiable with respect to ``vertex_attrs`` (B or 1, V, C))."""
    n_batch, n_vert, n_chan = vertex_attrs.shape
    ids = frags.faces.index_select(0, frags.row_face).T  # (3, M)
    if n_batch > 1:
        ids = ids + frags.row_item * n_vert
    attrs_t = vertex_attrs.permute(2, 0, 1).reshape(n_chan, -1)
    flat = ids.reshape(-1)
    # One 1-D gather per channel: differentiable (take_columns writes into out=), and 3x
    # faster than a dim-1 gather of the (C, B*V) table in float64 (about even in float32).
    corner = torch.stack([a.index_select(0, flat) for a in attrs_t])  # (C, 3 M)
    return corner.view(n_chan, 3, -1).transpose(0, 1).contiguous()


class _Weigh(torch.autograd.Function):
    """``value[c, p] = sum_i weights[i, p] table[i, c, rows[p]]``: the per-pixel gather and
    weighted sum of :func:`interpolate_packed`, in cache-sized chunks, written either
    packed (C, N) or straight into a (C, P) frame at ``pixels`` (zeros elsewhere).

    Backward (closed form): d table = index_add over rows of ``weights_i * grad``, d weights
    = the per-pixel dot product of ``grad`` with the gathered corners.
    """

    @staticmethod
    def forward(ctx, table, weights, rows, pixels, frame):
        three, n_chan, _ = table.shape
        n = rows.numel()
        weights = weights.to(table.dtype)
        out = frame_pool.empty((n_chan, frame) if frame else (n_chan, n), table.dtype,
                               table.device)
        if frame:
            out.zero_()
        c = min(n, PIXEL_CHUNK)
        buf = table.new_empty(three * n_chan * c)  # flat: contiguous chunk views
        val = table.new_empty(n_chan, c) if frame else None
        flat = table.view(three * n_chan, -1)
        for sl in pixel_slices(n):
            m = sl.stop - sl.start
            g = take_columns(flat, rows[sl], buf[:three * n_chan * m].view(-1, m))
            g = g.view(three, n_chan, m)
            wt = weights[:, sl]
            dest = out[:, sl] if not frame else val[:, :m]
            torch.mul(g[0], wt[0], out=dest).addcmul_(g[1], wt[1]).addcmul_(g[2], wt[2])
            if frame:
                out.index_copy_(1, pixels[sl], dest)
        ctx.save_for_backward(table, weights, rows, pixels if frame else None)
        ctx.set_materialize_grads(False)
        return out

    @staticmethod
    def backward(ctx, grad):
        table, weights, rows, pixels = ctx.saved_tensors
        if grad is None:
            return None, None, None, None, None
        if pixels is not None:
            grad = grad.index_select(1, pixels)  # (C, N)
        # half precision: sums in float32, saturated on the way out (finish_low_precision)
        dtype, dt = table.dtype, compute_dtype(table, grad)
        table, weights, grad = table.to(dt), weights.to(dt), grad.to(dt)
        three, n_chan, _ = table.shape
        g_table = torch.zeros_like(table) if ctx.needs_input_grad[0] else None
        g_w = torch.empty_like(weights) if ctx.needs_input_grad[1] else None
        flat = table.view(three * n_chan, -1)
        for sl in pixel_slices(rows.numel()):
            r, gr = rows[sl], grad[:, sl]
            if g_table is not None:
                for i in range(three):
                    contrib = gr * weights[i, sl]
                    for ch in range(n_chan):
                        g_table[i, ch].index_add_(0, r, contrib[ch])
            if g_w is not None:
                g = flat.index_select(1, r).view(three, n_chan, -1)
                g_w[:, sl] = (g * gr).sum(1)
        if dtype != dt:
            g_table = None if g_table is None else finish_low_precision(g_table, dtype)
            g_w = None if g_w is None else finish_low_precision(g_w, dtype)
        return g_table, g_w, None, None, None


def interpolate_packed(
    vertex_attrs: torch.Tensor, frags: Fragments, derivatives: bool = False
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """Interpolate at the covered pixels only: (B, V, C) or (V, C) -> (C, N).

    N = ``frags.pixels.numel()``; with ``derivatives`` also d/d col and d/d row, each
    (C, N) (else None). Used by the G-buffer pass, which works on covered pixels only.
    """
    return _interpolate(vertex_attrs, frags, derivatives, image=False)


def _interpolate(vertex_attrs, frags, derivatives, image):
    """Values (and derivatives) packed (C, N) or as (B, C, H, W) images."""
    if frags.bary_packed is None:
        raise ValueError("frags: released by Fragments.release_interpolation() (no "
                         "barycentrics left); interpolate before releasing, or rasterize again")
    vertex_attrs = _check_attrs(vertex_attrs, frags, derivatives)
    weights = [frags.bary_packed] + ([frags.bary_dx_packed, frags.bary_dy_packed]
                                     if derivatives else [])
    if frags.rows is None:  # Fragments built by hand: gather every pixel's corners
        outs = [_weigh_corners(vertex_attrs, frags, wt) for wt in weights]
        outs = [to_image(o, frags) for o in outs] if image else outs
    else:
        table = _corner_table(vertex_attrs, frags)
        b, h, w = frags.face_id.shape
        frame = b * h * w if image else 0
        outs = [_Weigh.apply(table, wt.T, frags.rows, frags.pixels, frame) for wt in weights]
        if image:
            outs = [o.view(-1, b, h, w).transpose(0, 1) for o in outs]
    return (outs[0], None, None) if not derivatives else tuple(outs)


def _weigh_corners(vertex_attrs: torch.Tensor, frags: Fragments,
                   weights: torch.Tensor) -> torch.Tensor:
    """(C, N) weighted sums of each pixel's corner attributes (``frags.corners``)."""
    b = frags.face_id.shape[0]
    n_vert, n_chan = vertex_attrs.shape[1:]
    ids = frags.corners
    if vertex_attrs.shape[0] == b and b > 1:
        ids = ids + frags.items * n_vert
    attrs_t = vertex_attrs.permute(2, 0, 1).reshape(n_chan, -1)
    flat_ids = ids.reshape(-1)
    corner = torch.stack([a.index_select(0, flat_ids) for a in attrs_t]).view(n_chan, 3, -1)
    wt = weights.T.to(corner.dtype)
    return corner[:, 0] * wt[0] + corner[:, 1] * wt[1] + corner[:, 2] * wt[2]


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
    return _interpolate(vertex_attrs, frags, False, image=True)[0]


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
    return Interpolated(*_interpolate(vertex_attrs, frags, True, image=True))
