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

Other conventions: :func:`convert` re-expresses pose matrices between OpenCV / COLMAP
(x right, y down, z forward), OpenGL / Blender / NeRF (ours) and PyTorch3D (x left, y up,
z forward; row-vector ``R, T`` through :func:`pytorch3d_rt`); :func:`intrinsics_from_projection`
gives OpenCV's ``K`` of a projection (the inverse of :func:`from_intrinsics`).
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

    Example:
        >>> view = look_at([0.0, 0, 3], [0.0, 0, 0])  # B = 1
        >>> transform_points(torch.zeros(1, 3), view)  # the target lies 3 along view -z
        tensor([[[ 0.,  0., -3.,  1.]]])
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

    Example:
        >>> orbit(torch.tensor([0.0, 90, 180, 270]), 30.0, 2.0).shape  # scalars broadcast
        torch.Size([4, 4, 4])
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

    Example:
        >>> proj = perspective(90.0, 1.0, near=1.0, far=3.0)
        >>> clip = transform_points(torch.tensor([[0.0, 0, -1], [0, 0, -3]]), proj)
        >>> clip[..., 2] / clip[..., 3]  # NDC z: the near plane -> -1, the far plane -> +1
        tensor([[-1.,  1.]])
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


# --- Camera conventions -------------------------------------------------------------------
#
# A convention fixes the axes of the camera frame. Each is written as the diagonal sign matrix
# S that maps OpenCV camera coordinates (x right, y down, z forward) to its own, so
# world_to_camera_dst = S_dst S_src world_to_camera_src (S is its own inverse).
_CONVENTION_SIGNS = {
    "opencv": (1.0, 1.0, 1.0),  # x right, y down, z forward (COLMAP, OpenCV)
    "opengl": (1.0, -1.0, -1.0),  # x right, y up, z backward (Blender, NeRF, our view space)
    "pytorch3d": (-1.0, -1.0, 1.0),  # x left, y up, z forward
}
#: Accepted names (case-insensitive) of each camera convention of :func:`convert`.
CONVENTION_ALIASES = {
    "opencv": "opencv", "colmap": "opencv",
    "opengl": "opengl", "blender": "opengl", "nerf": "opengl",
    "pytorch3d": "pytorch3d",
}
_KINDS = ("world_to_camera", "camera_to_world")


def convention(name: str) -> str:
    """The canonical name (``"opencv"``, ``"opengl"`` or ``"pytorch3d"``) of a camera
    convention or one of its aliases (:data:`CONVENTION_ALIASES`, case-insensitive).

    Raises:
        ValueError: an unknown name, listing the valid ones.
    """
    canon = CONVENTION_ALIASES.get(str(name).lower()) if isinstance(name, str) else None
    if canon is None:
        raise ValueError(f"camera convention {name!r}: expected one of "
                         f"{sorted(CONVENTION_ALIASES)} (case-insensitive)")
    return canon


def _check_matrices(name: str, m: object) -> torch.Tensor:
    if not isinstance(m, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(m).__name__}")
    if m.dim() < 2 or tuple(m.shape[-2:]) != (4, 4):
        raise ValueError(f"{name}: expected shape (..., 4, 4), got {tuple(m.shape)}")
    if not m.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got {m.dtype}")
    return m


def _signs(name: str, like: torch.Tensor) -> torch.Tensor:
    """The (4, 4) diagonal axis flip from OpenCV camera axes to convention ``name``'s."""
    return torch.diag(like.new_tensor([*_CONVENTION_SIGNS[convention(name)], 1.0]))


def convert(matrix: torch.Tensor, src: str, dst: str, kind: str = "world_to_camera"
            ) -> torch.Tensor:
    """Re-express a camera pose matrix in another camera-axis convention.

    Conventions (aliases case-insensitive): ``"opencv"`` = ``"colmap"`` (x right, y down,
    z forward), ``"opengl"`` = ``"blender"`` = ``"nerf"`` (x right, y up, z backward: the
    renderer's view space, :func:`look_at`), ``"pytorch3d"`` (x left, y up, z forward; see
    :func:`pytorch3d_rt` for its row-vector ``R, T``). Only the camera's axes change: the
    camera centre, the viewing direction and the world frame stay. Intrinsics are not
    touched (COLMAP and NeRF tools place pixel centres at +0.5, OpenCV at integers: their
    principal points differ by half a pixel, see :func:`intrinsics_from_projection`).

    Args:
        matrix: ``(..., 4, 4)`` column-vector matrices (``p' = M @ [p, 1]``).
        src, dst: the conventions of the input and of the result.
        kind: ``"world_to_camera"`` (extrinsics, view matrices) or ``"camera_to_world"``
            (poses, e.g. NeRF's ``transform_matrix``).

    Returns:
        ``(..., 4, 4)``, same dtype and device.

    Raises:
        ValueError: an unknown convention or kind (listing the valid ones), a bad shape.

    Example:
        >>> view = look_at([0.0, 0, 3], [0.0, 0, 0])  # OpenGL: the target is at z = -3
        >>> convert(view, "opengl", "opencv")[0] @ torch.tensor([0.0, 0, 0, 1])  # z forward
        tensor([0., 0., 3., 1.])
    """
    m = _check_matrices("matrix", matrix)
    if kind not in _KINDS:
        raise ValueError(f"kind {kind!r}: expected one of {list(_KINDS)}")
    flip = _signs(dst, m) @ _signs(src, m)  # src camera axes -> dst camera axes
    return flip @ m if kind == "world_to_camera" else m @ flip


def pytorch3d_rt(world_to_camera: torch.Tensor, src: str = "opengl"
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """PyTorch3D's ``R, T`` of a camera: ``X_cam = X_world @ R + T`` (row vectors).

    Args:
        world_to_camera: ``(..., 4, 4)`` rigid world -> camera matrices in convention
            ``src`` (default: the renderer's view matrices).
        src: the convention of ``world_to_camera`` (see :func:`convert`).

    Returns:
        ``R`` ``(..., 3, 3)`` and ``T`` ``(..., 3)`` for ``pytorch3d.renderer.cameras``
        (``R`` is the transpose of the column-vector rotation).
    """
    m = convert(world_to_camera, src, "pytorch3d")
    return m[..., :3, :3].transpose(-1, -2), m[..., :3, 3]


def from_pytorch3d_rt(R: torch.Tensor, T: torch.Tensor, dst: str = "opengl") -> torch.Tensor:
    """World -> camera matrices ``(..., 4, 4)`` in convention ``dst`` from PyTorch3D's
    ``R (..., 3, 3)``, ``T (..., 3)`` (``X_cam = X_world @ R + T``); inverse of
    :func:`pytorch3d_rt`."""
    if not isinstance(R, torch.Tensor) or R.dim() < 2 or tuple(R.shape[-2:]) != (3, 3):
        raise ValueError(f"R: expected a tensor of shape (..., 3, 3), got "
                         f"{tuple(R.shape) if isinstance(R, torch.Tensor) else type(R).__name__}")
    if not isinstance(T, torch.Tensor) or T.dim() < 1 or T.shape[-1] != 3:
        raise ValueError(f"T: expected a tensor of shape (..., 3), got "
                         f"{tuple(T.shape) if isinstance(T, torch.Tensor) else type(T).__name__}")
    if not R.is_floating_point():
        raise TypeError(f"R: expected a floating-point tensor, got {R.dtype}")
    batch = torch.broadcast_shapes(R.shape[:-2], T.shape[:-1])
    m = R.new_zeros(*batch, 4, 4)
    m[..., :3, :3] = R.transpose(-1, -2)
    m[..., :3, 3] = T.to(R)
    m[..., 3, 3] = 1.0
    return convert(m, "pytorch3d", dst)


def intrinsics_from_projection(proj: torch.Tensor, resolution: tuple[int, int]) -> torch.Tensor:
    """OpenCV intrinsics ``K`` of perspective projection(s); inverse of
    :func:`from_intrinsics`.

    OpenCV places the centre of pixel (row v, col u) at (u, v) and projects a camera-frame
    point (z forward) to ``u = fx X/Z + s Y/Z + cx``, ``v = fy Y/Z + cy``. With our pixel rule
    (column j samples NDC x = 2(j + 0.5)/W - 1, row i samples y = 1 - 2(i + 0.5)/H) and
    w_clip = -z_view = Z: fx = P00 W/2, s = -P01 W/2, cx = (1 - P02) W/2 - 1/2,
    fy = P11 H/2, cy = (1 + P12) H/2 - 1/2. (COLMAP / NeRF put pixel centres at +0.5:
    their cx, cy are these plus 0.5.)

    Args:
        proj: ``(..., 4, 4)`` perspective projections (bottom row ``(0, 0, -1, 0)``).
        resolution: ``(H, W)`` in pixels.

    Returns:
        ``K``: ``(..., 3, 3)``, same dtype and device.

    Raises:
        ValueError: a projection that is not a perspective one of this form (e.g.
            orthographic), or a skewed y axis (``P10 != 0``) that K cannot hold.

    Example:
        >>> intrinsics_from_projection(perspective(90.0, 1.0, 0.1), (64, 64))[0]
        tensor([[32.0000,  0.0000, 31.5000],
                [ 0.0000, 32.0000, 31.5000],
                [ 0.0000,  0.0000,  1.0000]])
    """
    p = _check_matrices("proj", proj)
    h, w = (int(s) for s in resolution)
    if h <= 0 or w <= 0:
        raise ValueError(f"resolution: expected positive (H, W), got {tuple(resolution)}")
    bottom = p.new_tensor([0.0, 0.0, -1.0, 0.0])
    if not bool((p[..., 3, :] == bottom).all()):
        raise ValueError("proj: expected perspective projections with bottom row "
                         "(0, 0, -1, 0) (w_clip = -z_view); an orthographic one has no K")
    if bool((p[..., 1, 0] != 0).any()):
        raise ValueError("proj: P[1, 0] != 0 (y depends on x) cannot be written as a K matrix")
    k = p.new_zeros(*p.shape[:-2], 3, 3)
    k[..., 0, 0] = p[..., 0, 0] * w / 2
    k[..., 0, 1] = -p[..., 0, 1] * w / 2 + 0.0  # + 0.0: no -0.0 in files
    k[..., 0, 2] = (1 - p[..., 0, 2]) * w / 2 - 0.5
    k[..., 1, 1] = p[..., 1, 1] * h / 2
    k[..., 1, 2] = (1 + p[..., 1, 2]) * h / 2 - 0.5
    k[..., 2, 2] = 1.0
    return k


def pytorch3d_intrinsics(K: torch.Tensor, resolution: tuple[int, int]
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """PyTorch3D NDC ``focal_length`` and ``principal_point`` (``PerspectiveCameras``,
    ``in_ndc=True``) of OpenCV intrinsics.

    PyTorch3D's documented screen space puts (0, 0) at the top-left corner of the top-left
    pixel, so its pixel centres sit at +0.5 (OpenCV: at integers); its NDC is +x left, +y
    up, the shorter image side spanning [-1, 1]: ``x_ndc = (W/2 - x_screen) 2/S`` with
    S = min(H, W). Hence ``f_ndc = f 2/S`` and ``p_ndc = -(c + 0.5 - size/2) 2/S``.
    (PyTorch3D's own ``cameras_from_opencv_projection`` omits the 0.5.)

    Args:
        K: ``(..., 3, 3)`` OpenCV intrinsics without skew.
        resolution: ``(H, W)``.

    Returns:
        ``focal_length`` ``(..., 2)`` and ``principal_point`` ``(..., 2)`` (x, y).
    """
    if not isinstance(K, torch.Tensor) or K.dim() < 2 or tuple(K.shape[-2:]) != (3, 3):
        raise ValueError("K: expected a tensor of shape (..., 3, 3)")
    if not K.is_floating_point():
        raise TypeError(f"K: expected a floating-point tensor, got {K.dtype}")
    if bool((K[..., 0, 1] != 0).any()):
        raise ValueError("K: PyTorch3D cameras have no skew (K[0, 1] must be 0)")
    h, w = (int(s) for s in resolution)
    if h <= 0 or w <= 0:
        raise ValueError(f"resolution: expected positive (H, W), got {tuple(resolution)}")
    half = min(h, w) / 2
    focal = torch.stack([K[..., 0, 0], K[..., 1, 1]], dim=-1) / half
    centre = torch.stack([K[..., 0, 2] + 0.5 - w / 2, K[..., 1, 2] + 0.5 - h / 2], dim=-1)
    return focal, -centre / half
