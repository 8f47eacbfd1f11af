"""Batched cameras: view matrices (world -> view) and projections (view -> clip).

Conventions (OpenGL): the camera looks down -z of its view space with +y up; clip space
follows the rasterizer contract (a point is visible iff w > 0 and -w <= x, y, z <= w, NDC +x
right, +y up, pixel row 0 at the top). Every function returns ``(B, 4, 4)`` matrices; scalar
arguments broadcast against tensor ones, and all-scalar calls give ``B = 1``.

Depth mappings of :func:`perspective` (d = distance along the view axis = clip w):

* standard:  NDC z = (f + n)/(f - n) - 2fn / ((f - n) d), near -> -1, far -> +1.
  float32 resolves little beyond d ~ 1e3 n: most of its precision sits next to -1.
* reverse_z: NDC z = n/(f - n) - nf / ((f - n) d), near -> -1, far -> 0, and with
  ``far=inf`` simply z = -n / d. Depth then lives near 0 where float32 is dense, giving
  about constant *relative* precision at every distance. The sign is chosen (unlike D3D's
  near -> 1) so that nearer is still smaller: the contract's visibility rule and the
  rasterizer's "nearest wins" test stay unchanged. Use it with ``far=math.inf`` for the best
  precision (a finite far reintroduces cancellation next to the far plane).
"""

from __future__ import annotations

import math

import torch

from ._validate import check_tensor
from .mesh import transform_points  # noqa: F401  (re-exported: model/view/clip transforms)

Scalar = float | torch.Tensor


def _batch_args(*args: Scalar) -> tuple[torch.Tensor, ...]:
    """Turn floats / (B,) tensors into broadcast (B,) tensors of one dtype and device."""
    ref = next((a for a in args if isinstance(a, torch.Tensor)), None)
    dtype = ref.dtype if ref is not None and ref.is_floating_point() else torch.float32
    device = ref.device if ref is not None else None
    tensors = [torch.as_tensor(a, dtype=dtype, device=device).reshape(-1) for a in args]
    return torch.broadcast_tensors(*tensors)


def _vec3(name: str, value: object, dtype: torch.dtype | None = None) -> torch.Tensor:
    t = torch.as_tensor(value, dtype=dtype if dtype is not None else torch.float32)
    if t.dim() == 1:
        t = t.unsqueeze(0)
    return check_tensor(name, t, ("B", 3), floating=True, finite=True)


def look_at(
    eye: torch.Tensor | list[float],
    target: torch.Tensor | list[float],
    up: torch.Tensor | list[float] | None = None,
) -> torch.Tensor:
    """World -> view matrices of cameras at ``eye`` looking at ``target``.

    eye, target, up: ``(B, 3)`` or ``(3,)``; up defaults to +y (a fallback axis is used where
    the view direction is parallel to up). Returns ``(B, 4, 4)``.
    """
    ref = eye if isinstance(eye, torch.Tensor) else target
    dtype = ref.dtype if isinstance(ref, torch.Tensor) and ref.is_floating_point() else None
    eye_t = _vec3("eye", eye, dtype)
    target_t = _vec3("target", target, eye_t.dtype).to(eye_t.device)
    up_t = _vec3("up", [0.0, 1.0, 0.0] if up is None else up, eye_t.dtype).to(eye_t.device)
    eye_t, target_t, up_t = torch.broadcast_tensors(eye_t, target_t, up_t)
    forward = target_t - eye_t
    if bool((forward.norm(dim=-1) == 0).any()):
        raise ValueError("look_at: eye and target must differ")
    back = torch.nn.functional.normalize(-forward, dim=-1)  # view +z points backwards
    right = torch.linalg.cross(up_t, back, dim=-1)
    # Where up is parallel to the view direction, fall back to +z (or +x) as up.
    alt = torch.where(back[:, 2:3].abs() < 0.9, back.new_tensor([0.0, 0.0, 1.0]),
                      back.new_tensor([1.0, 0.0, 0.0]))
    degenerate = right.norm(dim=-1, keepdim=True) < 1e-6
    right = torch.where(degenerate, torch.linalg.cross(alt, back, dim=-1), right)
    right = torch.nn.functional.normalize(right, dim=-1)
    true_up = torch.linalg.cross(back, right, dim=-1)
    rot = torch.stack([right, true_up, back], dim=1)  # (B, 3, 3) rows = view axes
    view = torch.zeros(eye_t.shape[0], 4, 4, dtype=eye_t.dtype, device=eye_t.device)
    view[:, :3, :3] = rot
    view[:, :3, 3] = -(rot @ eye_t.unsqueeze(-1)).squeeze(-1)
    view[:, 3, 3] = 1.0
    return view


def orbit(
    azimuth_deg: Scalar,
    elevation_deg: Scalar,
    distance: Scalar,
    target: torch.Tensor | list[float] | None = None,
) -> torch.Tensor:
    """World -> view matrices of cameras orbiting ``target`` (y up), ``(B, 4, 4)``.

    Azimuth 0 looks from +z towards the target; elevation is above the xz-plane.
    """
    az, el, dist = _batch_args(azimuth_deg, elevation_deg, distance)
    az, el = torch.deg2rad(az), torch.deg2rad(el)
    offset = torch.stack(
        [dist * torch.cos(el) * torch.sin(az), dist * torch.sin(el),
         dist * torch.cos(el) * torch.cos(az)], dim=-1)
    tgt = _vec3("target", [0.0, 0.0, 0.0] if target is None else target, offset.dtype)
    return look_at(tgt + offset, tgt.expand_as(offset))


def perspective(
    fov_y_deg: Scalar,
    aspect: Scalar,
    near: Scalar,
    far: Scalar = math.inf,
    reverse_z: bool = False,
) -> torch.Tensor:
    """OpenGL perspective projection(s), ``(B, 4, 4)``.

    fov_y_deg: vertical field of view in degrees, in (0, 180). aspect: width / height.
    near > 0; far > near or ``math.inf``. See the module docstring for ``reverse_z``.
    """
    fov, asp, n, f = _batch_args(fov_y_deg, aspect, near, far)
    if bool(((fov <= 0) | (fov >= 180)).any()):
        raise ValueError(f"fov_y_deg: expected values in (0, 180), got {fov.tolist()}")
    if bool((asp <= 0).any()) or not bool(torch.isfinite(asp).all()):
        raise ValueError(f"aspect: expected positive finite values, got {asp.tolist()}")
    if bool((n <= 0).any()) or not bool(torch.isfinite(n).all()):
        raise ValueError(f"near: expected positive finite values, got {n.tolist()}")
    if bool((f <= n).any()):
        raise ValueError(f"far: expected values > near, got far={f.tolist()} near={n.tolist()}")
    focal = 1.0 / torch.tan(torch.deg2rad(fov) / 2)
    proj = torch.zeros(fov.shape[0], 4, 4, dtype=fov.dtype, device=fov.device)
    proj[:, 0, 0] = focal / asp
    proj[:, 1, 1] = focal
    proj[:, 3, 2] = -1.0
    proj[:, 2, 2], proj[:, 2, 3] = _depth_rows(n, f, reverse_z)
    return proj


def _depth_rows(n: torch.Tensor, f: torch.Tensor, reverse_z: bool):
    """Third row (z_clip = a * z_view + b) of a perspective matrix; w_clip = -z_view."""
    inf = torch.isinf(f)
    f_safe = torch.where(inf, n * 2, f)
    if reverse_z:  # z_ndc = n/(f-n) - nf/((f-n) d)
        a = torch.where(inf, torch.zeros_like(n), -n / (f_safe - n))
        b = torch.where(inf, -n, -n * f_safe / (f_safe - n))
    else:  # z_ndc = (f+n)/(f-n) - 2fn/((f-n) d)
        a = torch.where(inf, -torch.ones_like(n), (f_safe + n) / (n - f_safe))
        b = torch.where(inf, -2 * n, 2 * f_safe * n / (n - f_safe))
    return a, b


def orthographic(
    left: Scalar, right: Scalar, bottom: Scalar, top: Scalar, near: Scalar, far: Scalar
) -> torch.Tensor:
    """OpenGL orthographic projection(s) of the view box, ``(B, 4, 4)`` (w = 1)."""
    l, r, b, t, n, f = _batch_args(left, right, bottom, top, near, far)
    if bool(((r <= l) | (t <= b) | (f <= n)).any()):
        raise ValueError("orthographic: expected left < right, bottom < top and near < far")
    proj = torch.zeros(l.shape[0], 4, 4, dtype=l.dtype, device=l.device)
    proj[:, 0, 0] = 2 / (r - l)
    proj[:, 1, 1] = 2 / (t - b)
    proj[:, 2, 2] = -2 / (f - n)
    proj[:, 0, 3] = -(r + l) / (r - l)
    proj[:, 1, 3] = -(t + b) / (t - b)
    proj[:, 2, 3] = -(f + n) / (f - n)
    proj[:, 3, 3] = 1.0
    return proj


def from_intrinsics(
    fx: Scalar,
    fy: Scalar,
    cx: Scalar,
    cy: Scalar,
    width: int,
    height: int,
    near: Scalar,
    far: Scalar = math.inf,
    reverse_z: bool = False,
) -> torch.Tensor:
    """Projection(s) ``(B, 4, 4)`` from pinhole intrinsics in pixels (OpenCV convention).

    OpenCV puts the centre of pixel (row v, col u) at image coordinates (u, v), so a
    view-space point projects to u = fx X/Z + cx. Our contract samples NDC
    x = 2(u + 0.5)/W - 1 and y = 1 - 2(v + 0.5)/H at that pixel, which gives the matrix
    below. It acts on OpenGL view coordinates; convert an OpenCV pose with
    :func:`view_from_opencv`.
    """
    fx_, fy_, cx_, cy_, n, f = _batch_args(fx, fy, cx, cy, near, far)
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"width, height: expected positive ints, got {width}, {height}")
    proj = perspective(90.0, 1.0, n, f, reverse_z).expand(fx_.shape[0], 4, 4).clone()
    proj[:, 0, 0] = 2 * fx_ / width
    proj[:, 1, 1] = 2 * fy_ / height
    proj[:, 0, 2] = 1 - 2 * (cx_ + 0.5) / width
    proj[:, 1, 2] = 2 * (cy_ + 0.5) / height - 1
    return proj


def view_from_opencv(rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """World -> OpenGL view matrices from OpenCV extrinsics.

    rotation: ``(B, 3, 3)`` rotation matrix, ``(B, 3)`` axis-angle or ``(B, 4)`` quaternion
    (w, x, y, z); translation ``(B, 3)``; X_cam = R X_world + t with x right, y down, z
    forward. OpenGL's view flips y and z: view = diag(1, -1, -1, 1) [R | t]. Returns
    ``(B, 4, 4)``.
    """
    if rotation.dim() == 2 and rotation.shape[-1] == 3:
        from kornia.geometry.conversions import axis_angle_to_rotation_matrix  # lazy: ~0.2 s

        rotation = axis_angle_to_rotation_matrix(rotation)
    elif rotation.dim() == 2 and rotation.shape[-1] == 4:
        from kornia.geometry.quaternion import Quaternion  # lazy: ~0.2 s

        rotation = Quaternion(rotation).matrix()
    check_tensor("rotation", rotation, ("B", 3, 3), floating=True, finite=True)
    check_tensor("translation", translation, (rotation.shape[0], 3), floating=True, finite=True)
    view = torch.zeros(rotation.shape[0], 4, 4, dtype=rotation.dtype, device=rotation.device)
    view[:, :3, :3] = rotation
    view[:, :3, 3] = translation
    view[:, 3, 3] = 1.0
    flip = torch.diag(rotation.new_tensor([1.0, -1.0, -1.0, 1.0]))
    return flip @ view
