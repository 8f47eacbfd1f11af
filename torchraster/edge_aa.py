"""Edge antialiasing: re-shade only the pixels on edges, at k x k sub-samples.

``Renderer(raster=RasterSettings(edge_supersample=k))`` renders the frame at 1x as usual, then:

1. rasterizes the scene once more at ``k x`` the resolution: the visibility pass over the
   whole ``k x`` frame, the barycentric pass only over the sub-samples of the edge pixels
   (``rasterize(select=...)``);
2. flags *edge pixels* (:func:`geometric_edges`, :func:`contrast_edges`): pixels whose
   ``k^2`` sub-samples see faces that share no vertex (occlusion edges, creases of meshes
   with split vertices, object boundaries), faces of different materials, or coverage and
   background (silhouettes); and pixels whose shadow visibility differs from a 4-neighbour's
   by more than :data:`CONTRAST_THRESHOLD` (shadow edges);
3. packs the covered sub-samples of the edge pixels into a G-buffer of shape
   ``(B, C, 1, M)`` (``M = k^2 x`` the most edge pixels of an item; :func:`pack_subsamples`)
   that goes through the same geometry, shadow and shading passes as the frame;
4. averages each edge pixel's sub-samples (box filter, like ``supersample=k``) and puts the
   average in place of the pixel's 1x value (:func:`resolve_edges`).

Labels and every G-buffer channel are the 1x frame's (exact, never blended); ``image`` and
``alpha`` are antialiased. With every pixel flagged the result is ``supersample=k``'s image.

The second raster's visibility pass is the pass's main cost (it grows with ``k^2``). Resolving the
sub-samples against the faces seen at the 3 x 3 neighbourhood's pixel centres instead
(no second raster) was tried: it misses the sliver faces of finely tessellated
silhouettes and distant objects (holes; PSNR below the 1x frame's on a field of spheres).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .numerics import safe_normalize
from .raster import Fragments

#: Largest per-axis factor of ``RasterSettings(edge_supersample=...)``.
MAX_EDGE_SUPERSAMPLE: int = 8
#: A pixel whose shadow visibility (any shadowed light, in [0, 1]) differs from a
#: 4-neighbour's by more than this is an edge pixel (both pixels are flagged). Tests set
#: it below 0 to flag every pixel.
CONTRAST_THRESHOLD: float = 0.1


@dataclass
class PackedSubsamples:
    """The sub-samples of the edge pixels, packed per batch item.

    Attributes:
        frags: :class:`~torchraster.raster.Fragments` of image shape ``(B, 1, M)``,
            ``M = P k^2``: column ``r k^2 + s`` of item b is sub-sample s (row-major in the
            pixel) of the item's r-th edge pixel; columns past the item's edge pixels and
            uncovered sub-samples are empty (``face_id`` -1).
        edge: ``(B, H, W)`` bool, the edge pixels.
        rank: ``(B, H * W)`` int64: an edge pixel's r (0 elsewhere).
        pixel: ``(B, P)`` int64: the flat index ``i W + j`` of each item's r-th edge
            pixel (0 past the item's count).
        ndc: ``(B, 2, 1, M)`` NDC x, y of every sub-sample (for background rays).
        k: the per-axis factor.
    """

    frags: Fragments
    edge: torch.Tensor
    rank: torch.Tensor
    pixel: torch.Tensor
    ndc: torch.Tensor
    k: int

    @property
    def count(self) -> int:
        """Edge pixels of the whole batch."""
        return int(self.edge.sum())


def _subsamples(face_id_k: torch.Tensor, k: int, where: tuple[torch.Tensor, ...]
                ) -> torch.Tensor:
    """The ``k^2`` sub-sample face ids ``(P, k^2)`` (row-major per pixel) of the pixels
    ``where`` (``(b, i, j)`` index tensors) of a ``(B, kH, kW)`` raster."""
    bb, i, j = where
    s = torch.arange(k * k, device=face_id_k.device)
    return face_id_k[bb[:, None], i[:, None] * k + s // k, j[:, None] * k + s % k]


def geometric_edges(face_id_k: torch.Tensor, faces: torch.Tensor, k: int,
                    face_material: torch.Tensor | None = None) -> torch.Tensor:
    """Pixels whose ``k x k`` sub-samples cross a geometric discontinuity.

    A pixel is flagged when its sub-samples mix covered and empty (silhouettes), or when
    one of them sees a face that shares no vertex with the face of the centre sub-sample
    (index ``(k - 1) // 2`` per axis), or has another material. Faces sharing a vertex
    meet there with the same position, normal and UV: the inside of a smooth mesh is not
    an edge.

    Args:
        face_id_k: ``(B, kH, kW)`` int64 face ids of the ``k x`` raster (-1 empty).
        faces: ``(F, 3)`` int64.
        k: the per-axis factor.
        face_material: optional ``(F,)`` int64 material of each face.

    Returns:
        ``(B, H, W)`` bool.
    """
    b, hk, wk = face_id_k.shape
    blocks = face_id_k.view(b, hk // k, k, wk // k, k)
    # any sub-sample unlike the block's first: compare and reduce the bools (3-4x faster
    # than max != min over the strided block axes of int64 ids)
    mixed = (blocks != blocks[:, :, :1, :, :1]).any(4).any(2)  # (B, H, W)
    out = torch.zeros_like(mixed)
    where = mixed.nonzero(as_tuple=True)
    if where[0].numel() == 0:
        return out
    sub = _subsamples(face_id_k, k, where)  # (P, k^2)
    c = (k - 1) // 2
    ref = sub[:, c * k + c]
    empty = (sub < 0).any(-1) | (ref < 0)
    fv = faces.to(sub.device).index_select(0, sub.clamp_min(0).reshape(-1)).view(*sub.shape, 3)
    rv = faces.to(sub.device).index_select(0, ref.clamp_min(0))  # (P, 3)
    shared = (fv[:, :, :, None] == rv[:, None, None, :]).flatten(-2).any(-1)  # (P, k^2)
    apart = (sub != ref[:, None]) & ~shared
    if face_material is not None:
        fm = face_material.to(sub.device)
        apart = apart | (fm.index_select(0, sub.clamp_min(0).reshape(-1)).view_as(sub)
                         != fm.index_select(0, ref.clamp_min(0))[:, None])
    out[where] = empty | apart.any(-1)
    return out


def contrast_edges(values: torch.Tensor, threshold: float) -> torch.Tensor:
    """Pixels whose value differs from a 4-neighbour's by more than ``threshold``.

    Args:
        values: ``(B, C, H, W)`` (e.g. the shadow visibility of C lights).
        threshold: largest difference (any channel) that is not an edge; below 0 flags
            every pixel.

    Returns:
        ``(B, H, W)`` bool: both pixels of every such pair.
    """
    b, _, h, w = values.shape
    if threshold < 0:
        return torch.ones(b, h, w, dtype=torch.bool, device=values.device)
    v = values.detach()
    out = torch.zeros(b, h, w, dtype=torch.bool, device=v.device)
    dx = (v[..., :, 1:] - v[..., :, :-1]).abs().amax(1) > threshold  # (B, H, W-1)
    dy = (v[..., 1:, :] - v[..., :-1, :]).abs().amax(1) > threshold  # (B, H-1, W)
    out[..., :, 1:] |= dx
    out[..., :, :-1] |= dx
    out[..., 1:, :] |= dy
    out[..., :-1, :] |= dy
    return out


def pack_subsamples(frags_k: Fragments, edge: torch.Tensor, k: int) -> PackedSubsamples:
    """Gather the sub-samples of the edge pixels from a ``k x`` raster.

    Args:
        frags_k: Fragments of the ``(kH, kW)`` raster (one layer) from ``rasterize``
            (whose covered ``pixels`` are ascending).
        edge: ``(B, H, W)`` bool edge pixels.
        k: the per-axis factor.

    Returns:
        :class:`PackedSubsamples`; its Fragments carry the ``k x`` raster's barycentrics
        (and derivatives, and gradients to the clip positions) of the kept sub-samples.
    """
    b, h, w = edge.shape
    hk, wk = h * k, w * k
    kk = k * k
    device = edge.device
    flat = edge.reshape(b, h * w)
    p = max(int(flat.sum(1).max()), 1) if b else 1
    m = p * kk
    rank = (flat.cumsum(1) - 1).clamp_min(0)
    where = flat.nonzero(as_tuple=True)
    pixel = torch.zeros(b, p, dtype=torch.int64, device=device)
    pixel[where[0], rank[where]] = where[1]
    # NDC of every sub-sample (row-major within its pixel), as rasterize samples them
    s = torch.arange(kk, device=device)
    row = (pixel // w)[:, :, None] * k + (s // k)  # (B, P, k^2)
    col = (pixel % w)[:, :, None] * k + (s % k)
    dtype = torch.promote_types(frags_k.bary_packed.dtype, torch.float32)  # not half
    x = (2 * col.to(dtype) + 1) / wk - 1
    y = 1 - (2 * row.to(dtype) + 1) / hk
    ndc = torch.stack([x, y], 1).reshape(b, 2, 1, m)
    # the packed rows of the covered sub-samples: rasterize's pixels are ascending
    items = torch.arange(b, device=device)[:, None, None].expand(b, p, kk)
    q = items * (hk * wk) + row * wk + col  # (B, P, k^2) flat index in the k x raster
    valid = torch.arange(p, device=device)[None, :] < flat.sum(1)[:, None]  # (B, P)
    pk = frags_k.pixels
    if pk.numel() == 0:
        pk = pk.new_full((1,), -1)  # nothing covered: no sub-sample matches
    at = torch.searchsorted(pk, q.reshape(-1)).clamp_max(pk.numel() - 1)
    hit = valid[:, :, None].expand(b, p, kk).reshape(-1) & (pk.index_select(0, at)
                                                            == q.reshape(-1))
    new = hit.nonzero().flatten()  # packed column b * M + r k^2 + s, ascending
    keep = at.index_select(0, new)
    face = frags_k.face_id.reshape(-1).index_select(0, pk.index_select(0, keep))
    face_id = torch.full((b * m,), -1, dtype=torch.int64, device=device).index_copy(
        0, new, face).view(b, 1, m)
    corners = frags_k.faces.index_select(0, face).T.contiguous() if frags_k.faces is not None \
        else frags_k.corners.index_select(1, keep)

    def pick(t: torch.Tensor | None) -> torch.Tensor | None:
        return None if t is None else t.index_select(0, keep)

    sub = Fragments(face_id, new, torch.div(new, m, rounding_mode="floor"), corners,
                    pick(frags_k.bary_packed), None, pick(frags_k.bary_dx_packed),
                    pick(frags_k.bary_dy_packed), faces=frags_k.faces,
                    depth_fn=lambda: frags_k.depth_packed.index_select(0, keep))
    front = frags_k.front_facing
    if front is not None:
        sub.front_facing = front.index_select(0, keep)
    return PackedSubsamples(sub, edge, rank, pixel, ndc, k)


def rays_at(view: torch.Tensor, proj: torch.Tensor, ndc: torch.Tensor) -> torch.Tensor:
    """Unit world-space directions from the eye through NDC points.

    Args:
        view: ``(B, 4, 4)`` world -> view; proj: ``(B, 4, 4)``.
        ndc: ``(B, 2, H, W)`` NDC x, y.

    Returns:
        ``(B, 3, H, W)`` (as ``renderer.view_rays`` at the pixel centres).
    """
    b, _, h, w = ndc.shape
    dtype = ndc.dtype
    inv = torch.linalg.inv(proj.to(torch.float64)).to(dtype)
    xy = ndc.reshape(b, 2, -1)

    def unproject(z: float) -> torch.Tensor:
        p = torch.cat([xy, torch.full_like(xy[:, :1], z), torch.ones_like(xy[:, :1])], 1)
        q = inv @ p  # (B, 4, HW)
        return q[:, :3] / q[:, 3:]

    d = unproject(-0.5) - unproject(-1.0)
    d = view[:, :3, :3].transpose(1, 2).to(dtype) @ d
    return safe_normalize(d.view(b, 3, h, w), dim=1)


def per_subsample(values: torch.Tensor, packed: PackedSubsamples) -> torch.Tensor:
    """A 1x image ``(B, C, H, W)`` read at each sub-sample's pixel -> ``(B, C, 1, M)``."""
    b, c, h, w = values.shape
    kk = packed.k * packed.k
    at = values.reshape(b, c, h * w).gather(
        2, packed.pixel[:, None].expand(b, c, -1))  # (B, C, P)
    return at.repeat_interleave(kk, 2).unsqueeze(2)


def resolve_edges(image: torch.Tensor, sub: torch.Tensor, packed: PackedSubsamples
                  ) -> torch.Tensor:
    """Replace the edge pixels of ``image`` ``(B, C, H, W)`` by the mean of their
    sub-samples ``sub`` ``(B, C, 1, M)`` (a box filter); the other pixels are kept."""
    b, c, h, w = image.shape
    kk = packed.k * packed.k
    mean = sub.reshape(b, c, -1, kk).mean(-1).to(image.dtype)  # (B, C, P)
    spread = mean.gather(2, packed.rank[:, None].expand(b, c, h * w)).view(b, c, h, w)
    return torch.where(packed.edge[:, None], spread, image)


__all__ = ["CONTRAST_THRESHOLD", "MAX_EDGE_SUPERSAMPLE", "PackedSubsamples", "contrast_edges",
           "geometric_edges", "pack_subsamples", "per_subsample", "rays_at", "resolve_edges"]
