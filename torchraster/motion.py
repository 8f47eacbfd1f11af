"""Optical flow, flow validity and screen-space motion vectors of the visible surface.

Every covered pixel sees one surface point: its face and perspective-correct barycentrics
(``Fragments``). The same barycentrics applied to the SAME vertices at another frame (their
positions at that frame, :class:`OtherFrame`) give the point's position there; projected by
that frame's camera it lands at a pixel position. Nothing is differenced from depth maps, so
the flow of a rotating or deforming object is exact at every covered pixel, and it is
differentiable with respect to both frames' vertex positions and cameras.

* :func:`reproject`: the point's clip position at the other frame -> :class:`Reprojection`
  (continuous pixel position, linear depth, "in front" and "inside the frustum" masks).
* :func:`optical_flow`: ``(B, 2, H, W)`` pixels, x right, y down: landing position minus this
  pixel's centre. Pixel (row i, col j) has its centre at NDC
  ``x = 2(j + 0.5)/W - 1, y = 1 - 2(i + 0.5)/H`` (docs/design.md), so an NDC point lands at
  column ``(x + 1) W / 2 - 0.5`` and row ``(1 - y) H / 2 - 0.5``.
* :func:`flow_validity`: ``(B, 1, H, W)`` float {0, 1}: the point is in the other frame's
  view frustum and not occluded there (depth test, :data:`DEPTH_TOLERANCE`).
* :func:`motion_vectors`: ``(B, 2, H, W)`` NDC xy now minus NDC xy at the previous frame
  (the TAA convention). With ``F`` the backward flow (to the previous frame):
  ``motion = -F * (2 / W, -2 / H)`` exactly, because NDC x grows by ``2 / W`` per column and
  NDC y falls by ``2 / H`` per row.

Points that cannot be projected into the other frame (behind its camera, ``w <= 0``, or
more than :data:`NDC_LIMIT` half-widths off-centre) get flow / motion 0 and are invalid; no
Inf or NaN is produced, in values or gradients. Empty pixels are 0 everywhere.

Occlusion test (:func:`flow_validity`): the other frame is rasterized depth-only
(``rasterize_depth``, the same faces, culling and face ranges), its NDC depth turned into
linear depth ``d`` (metres along the view axis) by the inverse projection, and the point's
own linear depth ``z`` (the other view's ``-z``) is compared with ``d`` at the pixel it
lands on (the nearest pixel centre). The point is visible iff
``z <= d + DEPTH_TOLERANCE * z + SLOPE_FACTOR * (|dd/dx| + |dd/dy|)``:

* ``DEPTH_TOLERANCE = 1e-3`` relative: float32 NDC depth resolves linear depth to about
  ``3e-8 * z / near`` relative (z / near = 1e3 -> 3e-5), and a curved surface departs from
  its faceted triangles by less than 1e-3 of the depth at the tessellations used; surfaces
  closer than 1 mm per metre to an occluder count as visible.
* the slope term: the point lies up to half a pixel from that centre on each axis, so on a
  planar surface its depth differs from the centre's by up to ``0.5 (|dd/dx| + |dd/dy|)``
  (per-pixel depth derivatives of the other frame's map). The derivatives are the smaller
  one-sided difference on each axis (at a silhouette, the side on the same surface), and
  ``SLOPE_FACTOR = 0.75`` is that 0.5 with a 1.5 margin for the curvature of depth along
  perspective rays. Grazing surfaces get a large tolerance, as they should.
* the own-surface term ``|g . delta|``: ``delta`` is the point's exact offset from that
  centre and ``g`` the screen-space gradient of its own face's depth in the other frame
  (exact: ``1 / w`` and ``depth / w`` are affine in screen space over a triangle). Where the
  centre sees the point's own face, ``d = z - g . delta`` exactly; across a convex crease the
  other face lies behind that plane, so ``d >= z - g . delta``. Without it, the last row of a
  grazing face before a crease (whose centre sees the face beyond it, with a small slope)
  was flagged occluded.

Limits: the other frame is depth-tested as opaque (glTF MASK cut-outs and BLEND surfaces
occlude like solid ones, as in shadow maps); an occluder narrower than about two pixels in
the other frame may be missed (its own one-sided differences are its silhouettes).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch

from ._validate import check_tensor
from .mesh import transform_points
from .numerics import compute_dtype, finish_low_precision, to_compute
from .raster import Fragments, interpolate, rasterize_depth

#: Relative depth tolerance of the occlusion test of :func:`flow_validity` (module docstring).
DEPTH_TOLERANCE: float = 1e-3
#: Pixels of depth slope allowed on each axis (0.5 px to the nearest centre, x 1.5 margin).
SLOPE_FACTOR: float = 0.75
#: A point whose NDC x or y exceeds this many half-widths (w -> 0+) counts as not projectable.
NDC_LIMIT: float = 1e6

#: Channel -> (the Renderer argument it needs, what it is).
MOTION_CHANNELS: dict[str, str] = {
    "flow_forward": "next_frame", "flow_forward_valid": "next_frame",
    "flow_backward": "previous_frame", "flow_backward_valid": "previous_frame",
    "motion": "previous_frame",
}


@dataclass
class OtherFrame:
    """The vertices and camera of another frame (the next or the previous one).

    Attributes:
        positions: ``(B, V, 3)`` or ``(V, 3)`` world positions of the SAME vertices as the
            current frame's (same V, same order), at the other frame's time.
        view: ``(B, 4, 4)`` or ``(4, 4)`` world -> view of the other frame's camera.
        proj: ``(B, 4, 4)`` or ``(4, 4)`` its projection (OpenGL clip).
        depth: the frame's visible depth (:class:`OtherDepth` of :func:`other_frame_depth`,
            ``(B or 1, H, W)`` float64 at the render's resolution, rasterized with the
            render's faces, culling and face ranges) or None: the Renderer rasterizes it for
            ``*_valid`` channels and stores it here, so the same ``OtherFrame`` passed again
            (e.g. frame t + 1's as frame t's ``next_frame``, then as frame t + 2's
            ``previous_frame``) is not rasterized twice. Only pass a depth computed for these
            positions and this camera.

    Checked on construction; errors name the field (``OtherFrame.positions``, ...). A batch
    size of 1 broadcasts.
    """

    positions: torch.Tensor
    view: torch.Tensor
    proj: torch.Tensor
    depth: OtherDepth | None = None

    def __post_init__(self) -> None:
        pos = self.positions
        shape = ("V", 3) if isinstance(pos, torch.Tensor) and pos.dim() == 2 else ("B", "V", 3)
        check_tensor("OtherFrame.positions", pos, shape, floating=True, finite=True)
        for name in ("view", "proj"):
            m = getattr(self, name)
            shape = (4, 4) if isinstance(m, torch.Tensor) and m.dim() == 2 else ("B", 4, 4)
            check_tensor(f"OtherFrame.{name}", m, shape, floating=True, finite=True)
        if self.depth is not None:
            if not isinstance(self.depth, OtherDepth):
                raise TypeError("OtherFrame.depth: expected an OtherDepth (other_frame_depth) "
                                f"or None, got {type(self.depth).__name__}")
            for name in ("depth", "slope"):
                check_tensor(f"OtherFrame.depth.{name}", getattr(self.depth, name),
                             ("B", "H", "W"), floating=True)
            if self.depth.depth.shape != self.depth.slope.shape:
                raise ValueError(f"OtherFrame.depth: depth {tuple(self.depth.depth.shape)} and "
                                 f"slope {tuple(self.depth.slope.shape)} differ in shape")

    def check_against(self, name: str, num_vertices: int, batch: int) -> None:
        """Raise a ValueError naming ``name`` (e.g. ``"next_frame"``) unless the frame holds
        ``num_vertices`` vertices and batch sizes of 1 or ``batch``."""
        got = self.positions.shape[-2]
        if got != num_vertices:
            raise ValueError(f"{name}.positions: V = {got} vertices, but the scene has "
                             f"{num_vertices}; the other frame must hold the same vertices")
        for field in ("positions", "view", "proj"):
            t = getattr(self, field)
            n = t.shape[0] if t.dim() == 3 else 1
            if n not in (1, batch):
                raise ValueError(f"{name}.{field}: batch size {n} does not match the render's "
                                 f"{batch} (use 1 to share)")

    def check_depth(self, name: str, resolution: tuple[int, int], batch: int) -> None:
        """Raise a ValueError naming ``name`` unless :attr:`depth` (when set) is
        ``(1 or batch, *resolution)``."""
        if self.depth is None:
            return
        got = tuple(self.depth.depth.shape)
        if got[1:] != tuple(resolution) or got[0] not in (1, batch):
            raise ValueError(f"{name}.depth: shape {got}, expected ({batch} or 1, "
                             f"{resolution[0]}, {resolution[1]}) (the render's resolution)")


class Reprojection(NamedTuple):
    """Where each pixel's visible point is at the other frame (:func:`reproject`).

    Attributes:
        pixel: ``(B, 2, H, W)`` continuous (column, row) of the point in the other frame's
            image (pixel centres at integers), 0 where not ``front``.
        ndc: ``(B, 2, H, W)`` its NDC x, y there, 0 where not ``front``.
        depth: ``(B, 1, H, W)`` its linear depth in the other view (``-z``), 0 where empty.
        front: ``(B, 1, H, W)`` bool: covered and projectable (``w > 0``, ``|ndc| <=``
            :data:`NDC_LIMIT`).
        inside: ``(B, 1, H, W)`` bool: ``front`` and inside the other frame's view frustum
            (``-w <= x, y, z <= w``: in its image, between its near and far planes).
    """

    pixel: torch.Tensor
    ndc: torch.Tensor
    depth: torch.Tensor
    front: torch.Tensor
    inside: torch.Tensor


def _batched(x: torch.Tensor) -> torch.Tensor:
    return x if x.dim() == 3 else x.unsqueeze(0)


def _to(x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``x`` in the compute ``dtype`` (gradients saturated for float16 / bfloat16 ``x``)."""
    return to_compute(x, dtype)


def _check(frags: Fragments, faces: torch.Tensor, other_positions: torch.Tensor,
           other_view: torch.Tensor, other_proj: torch.Tensor) -> None:
    """Checks of the arguments of the public functions (errors name the argument)."""
    if not isinstance(frags, Fragments):
        raise TypeError(f"frags: expected Fragments from rasterize, got {type(frags).__name__}")
    check_tensor("faces", faces, ("F", 3), integer=True)
    pos = other_positions
    shape = ("V", 3) if isinstance(pos, torch.Tensor) and pos.dim() == 2 else ("B", "V", 3)
    check_tensor("other_positions", pos, shape, floating=True, finite=True)
    b = frags.face_id.shape[0]
    for name, m in (("other_view", other_view), ("other_proj", other_proj)):
        shape = (4, 4) if isinstance(m, torch.Tensor) and m.dim() == 2 else ("B", 4, 4)
        check_tensor(name, m, shape, floating=True, finite=True)
    for name, t in (("other_positions", pos), ("other_view", other_view),
                    ("other_proj", other_proj)):
        if t.dim() == 3 and t.shape[0] not in (1, b):
            raise ValueError(f"{name}: batch size {t.shape[0]} does not match the fragments' "
                             f"{b} (use 1 to share)")
    if faces.numel() and int(faces.max()) >= pos.shape[-2]:
        raise ValueError(f"other_positions: V = {pos.shape[-2]} is smaller than the mesh "
                         f"(faces index vertex {int(faces.max())}); the other frame must hold "
                         "the same vertices")


def _pixel_centres(b: int, h: int, w: int, like: torch.Tensor) -> torch.Tensor:
    """``(1, 2, H, W)`` (column, row) of every pixel."""
    cols = torch.arange(w, dtype=like.dtype, device=like.device).view(1, w).expand(h, w)
    rows = torch.arange(h, dtype=like.dtype, device=like.device).view(h, 1).expand(h, w)
    return torch.stack([cols, rows])[None]


def reproject(frags: Fragments, faces: torch.Tensor, other_positions: torch.Tensor,
              other_view: torch.Tensor, other_proj: torch.Tensor) -> Reprojection:
    """Project each pixel's visible point into another frame.

    The point is the visible face's barycentric combination of the other frame's vertex
    positions (perspective-correct barycentrics of ``frags``: the same material point,
    moved with its triangle); its clip position there is interpolated like any linear
    attribute (:func:`~torchraster.interpolate`). Differentiable with respect to
    ``other_positions``, ``other_view``, ``other_proj`` and, through the barycentrics, the
    current frame's clip positions.

    Args:
        frags: :class:`~torchraster.raster.Fragments` of the current frame.
        faces: ``(F, 3)`` int64, those rasterized.
        other_positions: ``(B, V, 3)`` or ``(V, 3)`` world positions at the other frame.
        other_view, other_proj: ``(B, 4, 4)`` or ``(4, 4)`` the other frame's camera.

    Returns:
        :class:`Reprojection` of ``(B, C, H, W)`` images (float ones in the compute dtype:
        float16 / bfloat16 inputs are evaluated in float32).
    """
    _check(frags, faces, other_positions, other_view, other_proj)
    b, h, w = frags.face_id.shape
    dtype = compute_dtype(other_positions, frags.bary_packed)
    pos = _to(_batched(other_positions), dtype)
    view, proj = _to(_batched(other_view), dtype), _to(_batched(other_proj), dtype)
    eye = transform_points(pos, view)  # (B', V, 4) other view space
    clip = transform_points(pos, proj @ view)
    attrs = torch.cat([clip, -eye[..., 2:3]], -1)  # (B', V, 5): clip xyzw, linear depth
    img = interpolate(attrs, frags, faces)  # (B, 5, H, W), 0 where empty
    xy, z, wc, depth = img[:, :2], img[:, 2:3], img[:, 3:4], img[:, 4:5]
    covered = (frags.face_id >= 0).unsqueeze(1)
    front = covered & (wc > 0) & (xy.abs() <= NDC_LIMIT * wc).all(1, keepdim=True)
    safe_w = torch.where(front, wc, torch.ones_like(wc))  # no division by w <= 0
    ndc = torch.where(front, xy, torch.zeros_like(xy)) / safe_w
    scale = ndc.new_tensor([w / 2, -h / 2]).view(1, 2, 1, 1)
    offset = ndc.new_tensor([(w - 1) / 2, (h - 1) / 2]).view(1, 2, 1, 1)
    pixel = torch.where(front, ndc * scale + offset, torch.zeros_like(ndc))
    inside = front & (xy.abs() <= wc).all(1, keepdim=True) & (z.abs() <= wc)
    return Reprojection(pixel, ndc, depth, front, inside)


def face_depth_slope(frags: Fragments, faces: torch.Tensor, other_positions: torch.Tensor,
                     other_view: torch.Tensor, other_proj: torch.Tensor,
                     where: torch.Tensor) -> torch.Tensor:
    """The gradient of the linear depth of each pixel's own face per pixel of the other
    frame (column, row), at the pixels ``where`` ``(B, 1, H, W)`` bool (0 elsewhere).

    Over a triangle ``q = 1 / w`` and ``r = depth / w`` are affine in screen space, so
    ``d = r / q`` has the gradient ``w (g_r - d g_q)`` at the point, whose clip ``w`` and
    depth are its barycentric combinations of the corners'. 0 where a corner has ``w <= 0``
    or the face is seen edge-on there. No gradient.

    Returns:
        ``(B, 2, H, W)`` in the compute dtype.
    """
    b, h, w = frags.face_id.shape
    dtype = compute_dtype(other_positions, frags.bary_packed)
    with torch.no_grad():
        out = torch.zeros(b, 2, h * w, dtype=dtype, device=frags.face_id.device)
        item, pix = (where.view(b, -1) & (frags.face_id.view(b, -1) >= 0)).nonzero(
            as_tuple=True)
        if item.numel() == 0:
            return out.view(b, 2, h, w)
        pos = _to(_batched(other_positions.detach()), dtype)
        view = _to(_batched(other_view.detach()), dtype)
        proj = _to(_batched(other_proj.detach()), dtype)
        eye = transform_points(pos, view)
        clip = transform_points(pos, proj @ view)
        corner = faces.index_select(0, frags.face_id.view(b, -1)[item, pix])  # (N, 3)
        src = (item if clip.shape[0] == b else torch.zeros_like(item))[:, None]
        c, lin = clip[src, corner], -eye[..., 2][src, corner]  # (N, 3, 4), (N, 3)
        bary = frags.bary.reshape(b, -1, 3)[item, pix].to(dtype)  # (N, 3)
        wv = c[..., 3]
        ok = (wv > 0).all(-1)
        q = 1 / torch.where(wv > 0, wv, torch.ones_like(wv))
        px = (c[..., 0] * q + 1) * (w / 2)  # screen position in pixels (column, row):
        py = (1 - c[..., 1] * q) * (h / 2)  # the offsets of pixel centres cancel
        e1x, e1y = px[:, 1] - px[:, 0], py[:, 1] - py[:, 0]
        e2x, e2y = px[:, 2] - px[:, 0], py[:, 2] - py[:, 0]
        det = e1x * e2y - e2x * e1y
        ok = ok & (det.abs() > 1e-6 * (e1x.abs() + e1y.abs()) * (e2x.abs() + e2y.abs()))
        inv = torch.where(ok, 1 / torch.where(ok, det, torch.ones_like(det)),
                          torch.zeros_like(det))

        def gradient(v: torch.Tensor) -> torch.Tensor:  # (N, 2) of a value affine on screen
            d1, d2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
            return torch.stack([(d1 * e2y - d2 * e1y) * inv, (e1x * d2 - e2x * d1) * inv], 1)

        w_at, d_at = (bary * wv).sum(1, keepdim=True), (bary * lin).sum(1, keepdim=True)
        grad = w_at * (gradient(lin * q) - d_at * gradient(q))
        out[item, :, pix] = torch.where(torch.isfinite(grad), grad, torch.zeros_like(grad))
        return out.view(b, 2, h, w)


def flow_from(rep: Reprojection) -> torch.Tensor:
    """Optical flow ``(B, 2, H, W)`` (pixels, x right, y down) of a :class:`Reprojection`:
    its landing position minus each pixel's centre, 0 where not ``front``."""
    b, _, h, w = rep.pixel.shape
    centres = _pixel_centres(b, h, w, rep.pixel)
    return torch.where(rep.front, rep.pixel - centres, torch.zeros_like(rep.pixel))


def motion_from(rep: Reprojection) -> torch.Tensor:
    """Motion vectors ``(B, 2, H, W)``: NDC of each pixel centre minus the point's NDC at
    the previous frame (``rep`` must reproject into the previous frame), 0 where not
    ``front``."""
    b, _, h, w = rep.ndc.shape
    centres = _pixel_centres(b, h, w, rep.ndc)
    scale = rep.ndc.new_tensor([2 / w, -2 / h]).view(1, 2, 1, 1)
    now = (centres + 0.5) * scale + rep.ndc.new_tensor([-1.0, 1.0]).view(1, 2, 1, 1)
    return torch.where(rep.front, now - rep.ndc, torch.zeros_like(rep.ndc))


def optical_flow(frags: Fragments, faces: torch.Tensor, other_positions: torch.Tensor,
                 other_view: torch.Tensor, other_proj: torch.Tensor) -> torch.Tensor:
    """Optical flow of the visible surface into another frame, in pixels.

    For each covered pixel (row i, col j), the visible point is moved to the other frame
    (:func:`reproject`) and projected by its camera; the flow is that pixel position minus
    ``(j, i)``: x right, y down. Use the next frame's positions and camera for forward flow,
    the previous frame's for backward flow. The resolution is that of ``frags`` (the other
    frame is assumed to be rendered at the same one).

    Args:
        frags: :class:`~torchraster.raster.Fragments` of the current frame.
        faces: ``(F, 3)`` int64, those rasterized.
        other_positions: ``(B, V, 3)`` or ``(V, 3)`` world positions of the same vertices
            at the other frame.
        other_view, other_proj: ``(B, 4, 4)`` or ``(4, 4)`` the other frame's camera.

    Returns:
        ``(B, 2, H, W)`` flow in pixels, ``frags``' float dtype; 0 where empty and where the
        point is behind the other camera (``w <= 0``). Differentiable with respect to both
        frames' positions and cameras.

    Example:
        >>> from torchraster.raster import rasterize
        >>> pos = torch.tensor([[-1.0, -1, 0], [3, -1, 0], [-1, 3, 0]])
        >>> faces, camera = torch.tensor([[0, 1, 2]]), torch.eye(4)  # clip = world
        >>> frags = rasterize(torch.cat([pos, torch.ones(3, 1)], 1)[None], faces, (4, 4))
        >>> flow = optical_flow(frags, faces, pos + torch.tensor([0.5, -0.5, 0]), camera, camera)
        >>> flow.shape, flow[0, :, 0, 0].round()  # 0.5 NDC = 1 pixel: right, and down
        (torch.Size([1, 2, 4, 4]), tensor([1., 1.]))
    """
    rep = reproject(frags, faces, other_positions, other_view, other_proj)
    return finish_low_precision(flow_from(rep), frags.bary_packed.dtype)


def motion_vectors(frags: Fragments, faces: torch.Tensor, previous_positions: torch.Tensor,
                   previous_view: torch.Tensor, previous_proj: torch.Tensor) -> torch.Tensor:
    """Screen-space motion vectors: NDC xy now minus NDC xy at the previous frame.

    The TAA convention (a history buffer is read at ``ndc - motion``). Equal to
    ``-flow_backward * (2 / W, -2 / H)`` (module docstring), with ``flow_backward`` the
    :func:`optical_flow` into the previous frame.

    Args:
        frags, faces: as in :func:`optical_flow`.
        previous_positions: ``(B, V, 3)`` or ``(V, 3)`` positions at the previous frame.
        previous_view, previous_proj: ``(B, 4, 4)`` or ``(4, 4)`` its camera.

    Returns:
        ``(B, 2, H, W)`` NDC offsets (x right, y up), 0 where empty or behind the previous
        camera; differentiable like :func:`optical_flow`.
    """
    rep = reproject(frags, faces, previous_positions, previous_view, previous_proj)
    return finish_low_precision(motion_from(rep), frags.bary_packed.dtype)


def linear_depth(ndc_depth: torch.Tensor, proj: torch.Tensor) -> torch.Tensor:
    """Linear view depth (``-z`` of view space) ``(B, H, W)`` float64 of an NDC depth map
    ``(B, H, W)`` (``rasterize_depth``) under projections ``(B or 1, 4, 4)``, each pixel
    centre unprojected by the inverse projection (any invertible projection:
    perspective, reverse-Z, orthographic); ``+inf`` stays ``+inf`` (empty)."""
    b, h, w = ndc_depth.shape
    f64 = torch.float64
    inv = torch.linalg.inv(proj.detach().to(f64))  # (B', 4, 4)
    xs = ((2 * torch.arange(w, dtype=f64, device=ndc_depth.device) + 1) / w - 1).view(1, 1, w)
    ys = (1 - (2 * torch.arange(h, dtype=f64, device=ndc_depth.device) + 1) / h).view(1, h, 1)
    z = ndc_depth.to(f64)
    finite = torch.isfinite(z)
    zs = torch.where(finite, z, torch.zeros_like(z))
    # rows 2 and 3 of inv @ (x, y, z, 1): view z and w, broadcast over the pixel grid
    r2, r3 = (inv[:, i].reshape(-1, 4, 1, 1) for i in (2, 3))
    num = (r2[:, 0] * xs + r2[:, 1] * ys + r2[:, 3]) + r2[:, 2] * zs
    den = (r3[:, 0] * xs + r3[:, 1] * ys + r3[:, 3]) + r3[:, 2] * zs
    depth = -num / den
    return torch.where(finite, depth, torch.full_like(depth, float("inf")))


def _slope(depth: torch.Tensor) -> torch.Tensor:
    """``|dd/dx| + |dd/dy|`` ``(B, H, W)`` per pixel of a linear depth map ``(B, H, W)``:
    on each axis the smaller one-sided difference (the side on the same surface at a
    silhouette); 0 where neither side is finite."""
    def axis(d: torch.Tensor, dim: int) -> torch.Tensor:
        pad = [0, 0, 1, 1] if dim == 1 else [1, 1]
        p = torch.nn.functional.pad(d, pad, value=float("inf"))
        n = d.shape[dim]
        # a difference with an empty side is inf (or NaN: both empty): fmin takes the
        # other side, and a pixel with neither side finite gets 0
        g = torch.fmin((p.narrow(dim, 0, n) - d).abs(), (p.narrow(dim, 2, n) - d).abs())
        return torch.where(torch.isfinite(g), g, torch.zeros_like(g))

    return axis(depth, 2) + axis(depth, 1)


class OtherDepth(NamedTuple):
    """The visible depth of the other frame (:func:`other_frame_depth`).

    Attributes:
        depth: ``(B, H, W)`` float64 linear depth, ``+inf`` where empty.
        slope: ``(B, H, W)`` float64 ``|dd/dx| + |dd/dy|`` per pixel (:func:`_slope`).
    """

    depth: torch.Tensor
    slope: torch.Tensor


def other_frame_depth(other_clip: torch.Tensor, faces: torch.Tensor,
                      resolution: tuple[int, int], other_proj: torch.Tensor, *,
                      cull_backfaces: bool | torch.Tensor = False,
                      face_ranges: torch.Tensor | None = None) -> OtherDepth:
    """Rasterize the other frame depth-only: ``other_clip`` ``(B, V, 4)`` its clip
    positions, ``other_proj`` ``(B or 1, 4, 4)`` or ``(4, 4)`` its projection (to linearise
    the depth); culling and face ranges as in ``rasterize``. No gradient."""
    if face_ranges is not None and other_clip.shape[0] != face_ranges.shape[0]:
        other_clip = other_clip.expand(face_ranges.shape[0], -1, -1)  # a shared frame
    with torch.no_grad():
        ndc_depth = rasterize_depth(other_clip.detach(), faces, resolution, cull_backfaces,
                                    face_ranges)
        return other_depth(ndc_depth, other_proj)


def other_depth(ndc_depth: torch.Tensor, other_proj: torch.Tensor) -> OtherDepth:
    """The :class:`OtherDepth` of the other frame's rasterized NDC depth ``(B, H, W)``
    (``+inf`` where empty; e.g. ``rasterize(...).depth``), ``other_proj`` its projection
    ``(B or 1, 4, 4)`` or ``(4, 4)``. No gradient."""
    with torch.no_grad():
        seen = linear_depth(ndc_depth.detach(), _batched(other_proj.detach()))
        return OtherDepth(seen, _slope(seen))


def validity_from(rep: Reprojection, other: OtherDepth,
                  depth_tolerance: float = DEPTH_TOLERANCE, *,
                  own_slope: Callable[[torch.Tensor], torch.Tensor] | None = None
                  ) -> torch.Tensor:
    """Flow validity ``(B, 1, H, W)`` float {0, 1} of a :class:`Reprojection` against the
    other frame's visible depth (see :func:`flow_validity`). ``own_slope(where)`` gives the
    depth gradient of the points' own faces (:func:`face_depth_slope`) at the pixels the
    test would reject; without it the own-face term is left out."""
    b, _, h, w = rep.pixel.shape
    with torch.no_grad():
        seen, slope = (t.expand(b, h, w) for t in other)
        col = torch.floor(rep.pixel[:, 0] + 0.5).long().clamp(0, w - 1)  # nearest centre
        row = torch.floor(rep.pixel[:, 1] + 0.5).long().clamp(0, h - 1)
        flat = (row * w + col).view(b, -1)
        d = seen.reshape(b, -1).gather(1, flat).view(b, 1, h, w)
        s = slope.reshape(b, -1).gather(1, flat).view(b, 1, h, w)
        z = rep.depth.detach().to(torch.float64)
        visible = z <= d + depth_tolerance * z.abs() + SLOPE_FACTOR * s
        doubt = rep.inside & ~visible
        if own_slope is not None and bool(doubt.any()):  # the point's own face across its
            offset = rep.pixel.detach().to(torch.float64) - torch.stack(  # offset from the
                [col, row], 1).to(torch.float64)  # centre, where the test above fails only
            g = own_slope(doubt).to(torch.float64)
            visible = visible | (doubt & (z <= d + depth_tolerance * z.abs() + SLOPE_FACTOR * s
                                          + (g * offset).sum(1, keepdim=True).abs()))
        return (rep.inside & visible).to(rep.depth.dtype)


def flow_validity(frags: Fragments, faces: torch.Tensor, other_positions: torch.Tensor,
                  other_view: torch.Tensor, other_proj: torch.Tensor, *,
                  cull_backfaces: bool | torch.Tensor = False,
                  face_ranges: torch.Tensor | None = None,
                  depth_tolerance: float = DEPTH_TOLERANCE) -> torch.Tensor:
    """Whether each pixel's visible point is seen in the other frame (its flow is valid).

    Valid = covered, projectable, inside the other frame's view frustum (in its image,
    between its near and far planes) and not occluded there: the other frame is rasterized
    depth-only with the same ``faces`` (and ``cull_backfaces`` / ``face_ranges``) and the
    point's linear depth is compared with the visible one at the pixel it lands on, with
    the tolerance of the module docstring (``depth_tolerance`` relative plus the depth
    slope over half a pixel).

    Args:
        frags, faces, other_positions, other_view, other_proj: as in :func:`optical_flow`.
        cull_backfaces, face_ranges: as given to ``rasterize`` for the current frame.
        depth_tolerance: relative depth tolerance (default :data:`DEPTH_TOLERANCE`).

    Returns:
        ``(B, 1, H, W)`` float {0, 1} in the compute dtype; no gradient (a discrete test).
    """
    rep = reproject(frags, faces, other_positions, other_view, other_proj)
    dtype = rep.depth.dtype
    clip = transform_points(_batched(other_positions).to(dtype),
                            (_batched(other_proj) @ _batched(other_view)).to(dtype))
    h, w = frags.face_id.shape[1:]  # a shared other frame (batch 1) is rasterized once
    other = other_frame_depth(clip, faces, (h, w), other_proj, cull_backfaces=cull_backfaces,
                              face_ranges=face_ranges)
    return validity_from(rep, other, depth_tolerance, own_slope=lambda where: face_depth_slope(
        frags, faces, other_positions, other_view, other_proj, where))


__all__ = ["DEPTH_TOLERANCE", "MOTION_CHANNELS", "NDC_LIMIT", "SLOPE_FACTOR", "OtherDepth",
           "OtherFrame", "Reprojection", "face_depth_slope", "flow_from", "flow_validity",
           "linear_depth", "motion_from", "motion_vectors", "optical_flow", "other_depth",
           "other_frame_depth", "reproject", "validity_from"]
