"""Per-object annotations of a rendered view: 2D boxes, pixel counts, 3D boxes, keypoints.

Everything here is computed from label images the renderer already produced (``instance``
ids, ``amodal`` masks, linear ``depth``) and the view's camera, so a record can be recomputed
from the files alone.

Coordinates:

* 2D boxes ``[x0, y0, x1, y1]`` are in pixel-*edge* coordinates, as COCO's: pixel (row i,
  col j) spans ``[j, j + 1) x [i, i + 1)``, so ``x0`` is the leftmost covered column and
  ``x1`` the rightmost plus one (``pycocotools.mask.toBbox`` gives ``[x0, y0, x1 - x0,
  y1 - y0]``).
* Projected points (box corners, keypoints) use the OpenCV pixel convention of ``K``: the
  centre of column j is ``u = j`` (add 0.5 to compare with a box).
* Camera frame: OpenCV (x right, y down, z forward), ``world_to_camera (4, 4)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

#: Order of the 8 corners of a box: corner k has sign (-1 or +1) of bit 2, 1, 0 of k on the
#: x, y, z axes (k = 0: (-, -, -), k = 7: (+, +, +)), as in ``box_corners``.
CORNER_SIGNS = torch.tensor([[(k >> 2 & 1) * 2 - 1, (k >> 1 & 1) * 2 - 1, (k & 1) * 2 - 1]
                             for k in range(8)], dtype=torch.float64)


def mask_boxes(masks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Tight boxes and pixel counts of boolean masks.

    Args:
        masks: ``(..., H, W)`` bool (or 0/1) masks.

    Returns:
        ``boxes (..., 4)`` float64 ``[x0, y0, x1, y1]`` in pixel-edge coordinates (NaN for an
        empty mask) and ``counts (...)`` int64.

    Example:
        >>> m = torch.zeros(4, 5, dtype=torch.bool); m[1:3, 2] = True
        >>> mask_boxes(m)
        (tensor([2., 1., 3., 3.], dtype=torch.float64), tensor(2))
    """
    masks = masks.bool()
    h, w = masks.shape[-2:]
    rows, cols = masks.any(-1), masks.any(-2)  # (..., H), (..., W)
    r = torch.arange(h, device=masks.device, dtype=torch.float64)
    c = torch.arange(w, device=masks.device, dtype=torch.float64)
    inf = torch.tensor(torch.inf, dtype=torch.float64, device=masks.device)
    y0 = torch.where(rows, r, inf).amin(-1)
    y1 = torch.where(rows, r, -inf).amax(-1) + 1
    x0 = torch.where(cols, c, inf).amin(-1)
    x1 = torch.where(cols, c, -inf).amax(-1) + 1
    boxes = torch.stack([x0, y0, x1, y1], -1)
    empty = ~rows.any(-1)
    boxes = torch.where(empty[..., None], torch.nan, boxes)
    return boxes, masks.sum((-2, -1))


def instance_boxes(instance: torch.Tensor, n_objects: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Visible boxes and pixel counts of instances 1..N from an instance-id image, in one
    pass over the pixels (no per-object masks).

    Args:
        instance: ``(..., H, W)`` integer ids, 0 = background; ids outside ``[0, N]`` raise.
        n_objects: N.

    Returns:
        ``boxes (..., N, 4)`` float64 (row n - 1 is instance n; NaN where absent) and
        ``counts (..., N)`` int64, as :func:`mask_boxes` of ``instance == n``.

    Example:
        >>> boxes, counts = instance_boxes(torch.tensor([[0, 1, 1], [0, 2, 0]]), 3)
        >>> boxes  # x0, y0, x1, y1 (exclusive); instance 3 is not visible
        tensor([[1., 0., 3., 1.],
                [1., 1., 2., 2.],
                [nan, nan, nan, nan]], dtype=torch.float64)
        >>> counts
        tensor([2, 1, 0])
    """
    if instance.is_floating_point() or instance.is_complex():
        raise TypeError(f"instance: expected an integer tensor, got {instance.dtype}")
    if instance.dim() < 2:
        raise ValueError(f"instance: expected (..., H, W), got shape {tuple(instance.shape)}")
    ids = instance.long()
    if ids.numel() and (int(ids.min()) < 0 or int(ids.max()) > n_objects):
        raise ValueError(f"instance: ids must be in [0, {n_objects}], got "
                         f"[{int(ids.min())}, {int(ids.max())}]")
    lead, (h, w) = ids.shape[:-2], ids.shape[-2:]
    flat = ids.reshape(-1, h * w)  # (M, HW)
    m = flat.shape[0]
    rows = torch.arange(h, device=ids.device).repeat_interleave(w).double().expand(m, -1)
    cols = torch.arange(w, device=ids.device).repeat(h).double().expand(m, -1)
    n1 = n_objects + 1

    def reduce(values: torch.Tensor, how: str, init: float) -> torch.Tensor:
        out = torch.full((m, n1), init, dtype=torch.float64, device=ids.device)
        return out.scatter_reduce(1, flat, values, how, include_self=True)[:, 1:]

    x0, x1 = reduce(cols, "amin", torch.inf), reduce(cols, "amax", -torch.inf) + 1
    y0, y1 = reduce(rows, "amin", torch.inf), reduce(rows, "amax", -torch.inf) + 1
    counts = torch.zeros(m, n1, dtype=torch.int64, device=ids.device).scatter_add(
        1, flat, torch.ones_like(flat))[:, 1:]
    boxes = torch.stack([x0, y0, x1, y1], -1)
    boxes = torch.where(counts[..., None] > 0, boxes, torch.nan)
    return boxes.reshape(*lead, n_objects, 4), counts.reshape(*lead, n_objects)


def box_corners(center: torch.Tensor, size: torch.Tensor,
                object_to_world: torch.Tensor | None = None) -> torch.Tensor:
    """The 8 corners of boxes given in model space, optionally moved to world space.

    Args:
        center, size: ``(N, 3)`` model-space box centre and edge lengths.
        object_to_world: ``(N, 4, 4)`` or None (model-space corners).

    Returns:
        ``(N, 8, 3)`` in the order of :data:`CORNER_SIGNS` (an oriented box in world space when
        ``object_to_world`` rotates / scales).
    """
    signs = CORNER_SIGNS.to(center.device, center.dtype)
    corners = center[:, None] + signs * size[:, None] / 2
    if object_to_world is not None:
        m = object_to_world.to(corners.dtype)
        corners = corners @ m[:, :3, :3].transpose(1, 2) + m[:, None, :3, 3]
    return corners


def project(points_world: torch.Tensor, world_to_camera: torch.Tensor,
            k: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Points in the OpenCV camera frame and their pixels.

    Args:
        points_world: ``(..., 3)``.
        world_to_camera: ``(4, 4)`` OpenCV (x right, y down, z forward).
        k: ``(3, 3)`` intrinsics, or None for an orthographic camera (pixels are then NaN).

    Returns:
        ``camera (..., 3)`` and ``pixels (..., 2)`` (u right, v down; NaN where z <= 0).
    """
    m = world_to_camera.to(points_world.dtype)
    cam = points_world @ m[:3, :3].T + m[:3, 3]
    if k is None:
        return cam, torch.full_like(cam[..., :2], torch.nan)
    k = k.to(points_world.dtype)
    z = cam[..., 2:]
    front = z > 0
    uvw = cam @ k.T
    pixels = torch.where(front, uvw[..., :2] / torch.where(front, z, torch.ones_like(z)),
                         torch.nan)
    return cam, pixels


def depth_slope(depth: torch.Tensor) -> torch.Tensor:
    """``(H, W)`` how much linear depth changes per pixel step: the sum over x and y of the
    smaller one-sided difference (so a silhouette's far side does not count; inf where both
    neighbours are empty or missing, 0 for an empty pixel)."""
    d = depth.double()
    inf = torch.full_like(d, torch.inf)

    def one_sided(dim: int) -> torch.Tensor:
        n = d.shape[dim]
        fwd, bwd = inf.clone(), inf.clone()
        a, b = d.narrow(dim, 1, n - 1), d.narrow(dim, 0, n - 1)
        diff = torch.where((a > 0) & (b > 0), (a - b).abs(), torch.inf)
        fwd.narrow(dim, 0, n - 1).copy_(diff)
        bwd.narrow(dim, 1, n - 1).copy_(diff)
        return torch.minimum(fwd, bwd)

    return torch.where(d > 0, one_sided(0) + one_sided(1), 0.0)


def keypoint_visibility(pixels: torch.Tensor, camera_z: torch.Tensor, instance_id: int,
                        instance: torch.Tensor, depth: torch.Tensor | None,
                        rel_tol: float = 1e-3, slope_px: float = 0.75) -> torch.Tensor:
    """Whether projected points of one object are seen: in front of the camera, inside the
    image, the pixel they fall in shows that object, and (with ``depth``) the point is not
    behind the visible surface there: ``z <= d + rel_tol z + slope_px * slope`` with
    ``slope`` of :func:`depth_slope` (the point lies up to half a pixel from the pixel
    centre on each axis; 0.75 allows for perspective and creases, as the flow's validity
    test in :mod:`torchraster.motion`). A keypoint on the object's hidden side fails this.

    Args:
        pixels: ``(K, 2)`` OpenCV pixels; camera_z: ``(K,)`` depth along the view axis.
        instance: ``(H, W)`` ids; depth: ``(H, W)`` linear depth or None.
    """
    h, w = instance.shape
    col = torch.floor(pixels[:, 0] + 0.5)
    row = torch.floor(pixels[:, 1] + 0.5)
    inside = (camera_z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    inside = inside & pixels.isfinite().all(-1)
    r = row.clamp(0, h - 1).nan_to_num(0).long()
    c = col.clamp(0, w - 1).nan_to_num(0).long()
    seen = inside & (instance[r, c] == instance_id)
    if depth is not None:
        slope = depth_slope(depth)[r, c].to(camera_z)
        tol = rel_tol * camera_z.abs() + slope_px * slope
        seen = seen & (camera_z <= depth[r, c].to(camera_z) + tol)
    return seen


def _rows(t: torch.Tensor | None) -> list | None:
    """A tensor as nested lists of float (None for None or any NaN)."""
    if t is None or bool(t.isnan().any()):
        return None
    return [[float(x) for x in row] for row in t.tolist()] if t.dim() == 2 else [
        float(x) for x in t.tolist()]


def object_records(*, instance: torch.Tensor, object_to_world: torch.Tensor,
                   box_center: torch.Tensor, box_size: torch.Tensor,
                   names: Sequence[str], categories: Sequence[str | None],
                   category_ids: Sequence[int], world_to_camera: torch.Tensor,
                   k: torch.Tensor | None, amodal: torch.Tensor | None = None,
                   depth: torch.Tensor | None = None,
                   keypoints: Sequence[torch.Tensor | None] | None = None) -> list[dict]:
    """The manifest's ``objects`` list of one view (JSON-ready dicts, one per instance).

    Args:
        instance: ``(H, W)`` ids (0 background, n = object n).
        object_to_world: ``(N, 4, 4)`` at this view's frame.
        box_center, box_size: ``(N, 3)`` model-space boxes.
        names, categories, category_ids: per object (category None and id 0 when unset).
        world_to_camera: ``(4, 4)`` OpenCV; k: ``(3, 3)`` or None (orthographic).
        amodal: ``(N, H, W)`` bool unoccluded masks, or None (amodal box / fraction null).
        depth: ``(H, W)`` linear depth (keypoint occlusion test), or None.
        keypoints: per object a ``(K, 3)`` model-space tensor or None.

    Returns:
        One dict per object: ``instance_id, name, category, category_id, object_to_world,
        bbox_visible, bbox_amodal, pixels, pixels_amodal, visible_fraction, box3d
        {center_model, size_model, corners_world, corners_camera, corners_pixels}`` and
        ``keypoints {model, pixels, visible}`` when given. Boxes are null when empty.
    """
    n = object_to_world.shape[0]
    o2w = object_to_world.double().cpu()
    vis_boxes, vis_counts = instance_boxes(instance.cpu(), n)
    am_boxes = am_counts = None
    if amodal is not None:
        am_boxes, am_counts = mask_boxes(amodal.cpu())
    corners = box_corners(box_center.double().cpu(), box_size.double().cpu(), o2w)
    cam, pix = project(corners, world_to_camera.double().cpu(),
                       None if k is None else k.double().cpu())
    out = []
    for i in range(n):
        rec = {"instance_id": i + 1, "name": names[i], "category": categories[i],
               "category_id": int(category_ids[i]), "object_to_world": _rows(o2w[i]),
               "bbox_visible": _rows(vis_boxes[i]), "pixels": int(vis_counts[i])}
        if am_boxes is not None:
            total = int(am_counts[i])
            rec.update(bbox_amodal=_rows(am_boxes[i]), pixels_amodal=total,
                       visible_fraction=float(vis_counts[i]) / total if total else 0.0)
        else:
            rec.update(bbox_amodal=None, pixels_amodal=None, visible_fraction=None)
        rec["box3d"] = {"center_model": _rows(box_center[i].double()),
                        "size_model": _rows(box_size[i].double()),
                        "corners_world": _rows(corners[i]), "corners_camera": _rows(cam[i]),
                        "corners_pixels": _rows(pix[i])}
        if keypoints is not None and keypoints[i] is not None:
            kp = keypoints[i].double().cpu()
            kw = kp @ o2w[i, :3, :3].T + o2w[i, :3, 3]
            kc, kpix = project(kw, world_to_camera.double().cpu(),
                               None if k is None else k.double().cpu())
            seen = keypoint_visibility(kpix, kc[:, 2], i + 1, instance.cpu(),
                                       None if depth is None else depth.cpu().double())
            rec["keypoints"] = {"model": _rows(kp), "pixels": [
                None if not bool(p.isfinite().all()) else [float(p[0]), float(p[1])]
                for p in kpix], "visible": [bool(s) for s in seen]}
        out.append(rec)
    return out


__all__ = ["CORNER_SIGNS", "box_corners", "depth_slope", "instance_boxes", "keypoint_visibility",
           "mask_boxes", "object_records", "project"]
