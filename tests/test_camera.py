"""Cameras against hand-derived projections (independent formulas, float64)."""

import math

import pytest
import torch

import torchraster as tr
from torchraster import camera


def _ndc(proj, p_view):
    q = proj[0] @ torch.cat([p_view, p_view.new_ones(1)])
    return q[:3] / q[3], q[3]


def test_look_at_is_rigid_and_looks_down_minus_z():
    eye = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    target = torch.tensor([[-1.0, 0.5, 0.0]], dtype=torch.float64)
    view = camera.look_at(eye, target)
    rot = view[0, :3, :3]
    assert torch.allclose(rot @ rot.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert torch.det(rot) == pytest.approx(1.0)
    p = view[0] @ torch.cat([eye[0], torch.ones(1, dtype=torch.float64)])
    assert torch.allclose(p[:3], torch.zeros(3, dtype=torch.float64), atol=1e-12)
    t = view[0] @ torch.cat([target[0], torch.ones(1, dtype=torch.float64)])
    dist = (target - eye).norm()
    assert torch.allclose(t[:3], torch.tensor([0, 0, -dist], dtype=torch.float64), atol=1e-12)
    # up stays up: a point above the target projects to +y in view space
    up = view[0] @ torch.tensor([-1.0, 1.5, 0.0, 1.0], dtype=torch.float64)
    assert up[1] > 0


def test_look_at_straight_down_is_finite():
    view = camera.look_at([0.0, 5.0, 0.0], [0.0, 0.0, 0.0])
    assert torch.isfinite(view).all()
    assert torch.allclose(view[0, :3, :3] @ view[0, :3, :3].T, torch.eye(3), atol=1e-6)


@pytest.mark.parametrize("far", [10.0, math.inf])
def test_perspective_depth_mapping(far):
    n = 0.5
    proj = camera.perspective(60.0, 1.5, n, far).double()
    z_near, w = _ndc(proj, torch.tensor([0.0, 0.0, -n], dtype=torch.float64))
    assert z_near[2] == pytest.approx(-1.0) and w == pytest.approx(n)
    if math.isfinite(far):
        z_far, _ = _ndc(proj, torch.tensor([0.0, 0.0, -far], dtype=torch.float64))
        assert z_far[2] == pytest.approx(1.0)
    # the top edge of the vertical field of view maps to NDC y = 1
    d = 3.0
    half = d * math.tan(math.radians(30))
    top, _ = _ndc(proj, torch.tensor([0.0, half, -d], dtype=torch.float64))
    assert top[1] == pytest.approx(1.0)
    right, _ = _ndc(proj, torch.tensor([1.5 * d * math.tan(math.radians(30)), 0, -d],
                                       dtype=torch.float64))
    assert right[0] == pytest.approx(1.0)


@pytest.mark.parametrize("far", [1e3, math.inf])
def test_reverse_z_maps_near_to_minus_one_and_far_to_zero(far):
    n = 0.1
    proj = camera.perspective(torch.tensor(45.0, dtype=torch.float64), 1.0, n, far, reverse_z=True)
    for d in [n, 1.0, 37.0, 999.0]:
        z, _ = _ndc(proj, torch.tensor([0.0, 0.0, -d], dtype=torch.float64))
        expected = n / (far - n) - n * far / ((far - n) * d) if math.isfinite(far) else -n / d
        assert z[2] == pytest.approx(expected, rel=1e-6)
    z_near, _ = _ndc(proj, torch.tensor([0.0, 0.0, -n], dtype=torch.float64))
    assert z_near[2] == pytest.approx(-1.0)


def test_orthographic_box_maps_to_unit_cube():
    proj = camera.orthographic(-2, 3, -1, 4, 0.5, 10).double()
    lo, _ = _ndc(proj, torch.tensor([-2.0, -1.0, -0.5], dtype=torch.float64))
    hi, _ = _ndc(proj, torch.tensor([3.0, 4.0, -10.0], dtype=torch.float64))
    assert torch.allclose(lo, -torch.ones(3, dtype=torch.float64))
    assert torch.allclose(hi, torch.ones(3, dtype=torch.float64))


def test_intrinsics_match_opencv_pixel_convention():
    fx, fy, cx, cy, w, h = 500.0, 480.0, 300.3, 201.7, 640, 400
    proj = camera.from_intrinsics(fx, fy, cx, cy, w, h, 0.1).double()
    rot = torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64)  # axis-angle
    t = torch.tensor([[0.2, -0.1, 2.0]], dtype=torch.float64)
    view = camera.view_from_opencv(rot[None], t)
    from kornia.geometry.conversions import axis_angle_to_rotation_matrix
    r = axis_angle_to_rotation_matrix(rot[None])[0]
    for p in torch.tensor([[0.1, 0.2, 0.3], [-0.3, 0.1, -0.2]], dtype=torch.float64):
        pc = r @ p + t[0]  # OpenCV camera frame, z forward
        u, v = fx * pc[0] / pc[2] + cx, fy * pc[1] / pc[2] + cy  # pixel centre at (u, v)
        q = proj[0] @ view[0] @ torch.cat([p, torch.ones(1, dtype=torch.float64)])
        x_ndc, y_ndc = q[0] / q[3], q[1] / q[3]
        # contract: column j samples x = 2(j + 0.5)/W - 1, row i samples y = 1 - 2(i + 0.5)/H
        assert (x_ndc + 1) * w / 2 - 0.5 == pytest.approx(float(u))
        assert (1 - y_ndc) * h / 2 - 0.5 == pytest.approx(float(v))
        assert q[3] > 0


def test_projected_point_lands_on_rasterized_pixel():
    """A tiny triangle around a projected point covers the pixel the camera predicts."""
    view = camera.look_at([0.3, 0.2, 4.0], [0.0, 0.0, 0.0])
    proj = camera.perspective(50.0, 1.0, 0.1)
    p = torch.tensor([0.2, -0.1, 0.3])
    tri = p + torch.tensor([[-0.1, -0.1, 0.0], [0.1, -0.1, 0.0], [0.0, 0.1, 0.0]])
    clip = camera.transform_points(tri, proj @ view)
    frags = tr.rasterize(clip, torch.tensor([[0, 1, 2]]), (64, 64))
    q = clip[0].mean(0)  # convex combination: projects inside the triangle
    col = ((q[0] / q[3] + 1) * 32 - 0.5).round().long()
    row = ((1 - q[1] / q[3]) * 32 - 0.5).round().long()
    assert frags.face_id[0, row, col] == 0


@pytest.mark.parametrize("kwargs, name", [
    (dict(fov_y_deg=0.0, aspect=1.0, near=0.1), "fov_y_deg"),
    (dict(fov_y_deg=45.0, aspect=-1.0, near=0.1), "aspect"),
    (dict(fov_y_deg=45.0, aspect=1.0, near=0.0), "near"),
    (dict(fov_y_deg=45.0, aspect=1.0, near=1.0, far=0.5), "far"),
])
def test_bad_camera_arguments_name_the_argument(kwargs, name):
    with pytest.raises(ValueError, match=name):
        camera.perspective(**kwargs)


def test_look_at_rejects_eye_equal_target():
    with pytest.raises(ValueError, match="eye and target"):
        camera.look_at([1.0, 1.0, 1.0], [1.0, 1.0, 1.0])
