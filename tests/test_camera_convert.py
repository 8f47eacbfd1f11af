"""Camera conventions (camera.convert, PyTorch3D R/T, K from a projection) against each
convention's own textbook projection formula, in float64."""

import itertools
import math

import pytest
import torch

from torchraster import camera

NAMES = ["opencv", "COLMAP", "opengl", "Blender", "nerf", "PyTorch3D"]
H, W = 48, 80  # non-square on purpose (PyTorch3D scales NDC by the shorter side)


def _cameras():
    """Two cameras (world -> OpenGL view) and a projection with an off-centre principal
    point, plus world points in front of both."""
    view = camera.look_at(torch.tensor([[1.0, 2.0, 3.0], [-2.0, 0.5, -1.5]], dtype=torch.float64),
                          torch.tensor([[0.1, 0.0, -0.2], [0.3, 0.2, 0.1]], dtype=torch.float64))
    proj = camera.from_intrinsics(70.0, 66.0, 37.3, 26.1, W, H, 0.1).double()
    points = torch.tensor([[0.1, 0.2, -0.1], [0.3, -0.2, 0.2], [-0.25, 0.1, 0.05]],
                          dtype=torch.float64)
    return view, proj, points


def _homog(p):
    return torch.cat([p, p.new_ones(p.shape[0], 1)], dim=-1)


@pytest.mark.parametrize("src, dst", list(itertools.product(NAMES, NAMES)))
@pytest.mark.parametrize("kind", ["world_to_camera", "camera_to_world"])
def test_round_trip_every_pair(src, dst, kind):
    view, _, _ = _cameras()
    m = view if kind == "world_to_camera" else torch.linalg.inv(view)
    there = camera.convert(m, src, dst, kind)
    torch.testing.assert_close(camera.convert(there, dst, src, kind), m, rtol=0, atol=1e-12)
    # the two kinds describe the same camera: converting the pose = inverting the extrinsics
    other = "camera_to_world" if kind == "world_to_camera" else "world_to_camera"
    torch.testing.assert_close(camera.convert(torch.linalg.inv(m), src, dst, other),
                               torch.linalg.inv(there), rtol=0, atol=1e-12)
    # a conversion moves neither the camera centre nor the world frame
    c2w = there if kind == "camera_to_world" else torch.linalg.inv(there)
    torch.testing.assert_close(c2w[:, :3, 3], torch.linalg.inv(view)[:, :3, 3], rtol=0,
                               atol=1e-12)


def test_axes_of_each_convention():
    """A point straight ahead, one to the right and one above the camera, expressed in each
    convention's camera frame, has the signs the convention documents."""
    view = camera.look_at([0.0, 0.0, 5.0], [0.0, 0.0, 0.0])  # OpenGL: world axes = view axes
    ahead, right, above = [0.0, 0.0, 0.0, 1.0], [1.0, 0.0, 5.0, 1.0], [0.0, 1.0, 5.0, 1.0]
    expect = {  # (z of ahead, x of right, y of above)
        "opencv": (5.0, 1.0, -1.0), "opengl": (-5.0, 1.0, 1.0), "pytorch3d": (5.0, -1.0, 1.0)}
    for name, (z, x, y) in expect.items():
        m = camera.convert(view, "opengl", name)[0]
        assert float((m @ torch.tensor(ahead))[2]) == pytest.approx(z)
        assert float((m @ torch.tensor(right))[0]) == pytest.approx(x)
        assert float((m @ torch.tensor(above))[1]) == pytest.approx(y)


def test_all_conventions_project_to_the_same_pixel():
    view, proj, points = _cameras()
    k = camera.intrinsics_from_projection(proj, (H, W))[0]
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    for b in range(view.shape[0]):
        # OpenGL: through our projection and the contract's NDC -> pixel rule
        clip = _homog(points) @ (proj[0] @ view[b]).T
        assert bool((clip[:, 3] > 0).all())
        u_gl = (clip[:, 0] / clip[:, 3] + 1) * W / 2 - 0.5
        v_gl = (1 - clip[:, 1] / clip[:, 3]) * H / 2 - 0.5
        # OpenCV: u = fx X/Z + cx with Z forward, pixel centres at integers
        cam = _homog(points) @ camera.convert(view[b], "opengl", "opencv").T
        u_cv, v_cv = fx * cam[:, 0] / cam[:, 2] + cx, fy * cam[:, 1] / cam[:, 2] + cy
        torch.testing.assert_close(u_cv, u_gl, rtol=0, atol=1e-9)
        torch.testing.assert_close(v_cv, v_gl, rtol=0, atol=1e-9)
        # COLMAP: same axes, pixel centres at +0.5
        cam = _homog(points) @ camera.convert(view[b], "opengl", "colmap").T
        u_cm = fx * cam[:, 0] / cam[:, 2] + (cx + 0.5)
        torch.testing.assert_close(u_cm - 0.5, u_gl, rtol=0, atol=1e-9)
        # NeRF / Blender: camera-to-world pose, rays x right y up looking down -z, pixel
        # centres at +0.5: the ray through (x, y) is ((x - cx)/fx, -(y - cy)/fy, -1)
        c2w = camera.convert(torch.linalg.inv(view[b]), "opengl", "nerf", "camera_to_world")
        cam = _homog(points) @ torch.linalg.inv(c2w).T
        x_nerf = fx * cam[:, 0] / -cam[:, 2] + (cx + 0.5)
        y_nerf = -fy * cam[:, 1] / -cam[:, 2] + (cy + 0.5)
        torch.testing.assert_close(x_nerf - 0.5, u_gl, rtol=0, atol=1e-9)
        torch.testing.assert_close(y_nerf - 0.5, v_gl, rtol=0, atol=1e-9)
        # PyTorch3D: X_cam = X_world @ R + T (x left, y up, z forward); NDC x = f X/Z + p;
        # documented screen space: (0, 0) = top-left corner of the top-left pixel, NDC +x
        # left / +y up, the shorter side spanning [-1, 1]
        r, t = camera.pytorch3d_rt(view[b])
        cam = points @ r + t
        focal, pp = camera.pytorch3d_intrinsics(k, (H, W))
        x_ndc = focal[0] * cam[:, 0] / cam[:, 2] + pp[0]
        y_ndc = focal[1] * cam[:, 1] / cam[:, 2] + pp[1]
        s = min(H, W)
        x_screen, y_screen = W / 2 - x_ndc * s / 2, H / 2 - y_ndc * s / 2
        torch.testing.assert_close(x_screen - 0.5, u_gl, rtol=0, atol=1e-9)
        torch.testing.assert_close(y_screen - 0.5, v_gl, rtol=0, atol=1e-9)


def test_pytorch3d_rt_matches_its_look_at_view_transform():
    """PyTorch3D's look_at_view_transform(dist=2.7, elev=0, azim=0) (a camera on +z looking
    at the origin, y up) is R = diag(-1, 1, -1), T = (0, 0, 2.7) (its documented example)."""
    r, t = camera.pytorch3d_rt(camera.look_at([0.0, 0.0, 2.7], [0.0, 0.0, 0.0]).double())
    torch.testing.assert_close(r[0], torch.diag(torch.tensor([-1.0, 1.0, -1.0],
                                                             dtype=torch.float64)))
    torch.testing.assert_close(t[0], torch.tensor([0.0, 0.0, 2.7], dtype=torch.float64))


@pytest.mark.parametrize("dst", ["opencv", "opengl", "pytorch3d"])
def test_from_pytorch3d_rt_inverts_pytorch3d_rt(dst):
    view, _, _ = _cameras()
    m = camera.convert(view, "opengl", dst).reshape(2, 1, 4, 4)  # extra batch dims kept
    r, t = camera.pytorch3d_rt(m, src=dst)
    assert r.shape == (2, 1, 3, 3) and t.shape == (2, 1, 3)
    torch.testing.assert_close(camera.from_pytorch3d_rt(r, t, dst=dst), m, rtol=0, atol=1e-12)


def test_intrinsics_round_trip_batched():
    fx = torch.tensor([500.0, 220.5], dtype=torch.float64)
    proj = camera.from_intrinsics(fx, fx * 0.9, 300.3, torch.tensor([201.7, 10.0]), 640, 400,
                                  0.1, math.inf)
    k = camera.intrinsics_from_projection(proj, (400, 640))
    expect = torch.tensor([[[500.0, 0, 300.3], [0, 450.0, 201.7], [0, 0, 1]],
                           [[220.5, 0, 300.3], [0, 198.45, 10.0], [0, 0, 1]]],
                          dtype=torch.float64)
    torch.testing.assert_close(k, expect)
    # perspective(): square pixels, principal point between the two middle pixels
    k = camera.intrinsics_from_projection(camera.perspective(90.0, 2.0, 0.1), (50, 100))[0]
    torch.testing.assert_close(k, torch.tensor([[25.0, 0, 49.5], [0, 25.0, 24.5], [0, 0, 1]]))


def test_errors_name_the_argument():
    m = torch.eye(4)
    with pytest.raises(ValueError, match=r"'vulkan'.*colmap.*opengl.*pytorch3d"):
        camera.convert(m, "vulkan", "opencv")
    with pytest.raises(ValueError, match="kind 'pose'"):
        camera.convert(m, "opencv", "opengl", kind="pose")
    with pytest.raises(ValueError, match=r"matrix: expected shape \(\.\.\., 4, 4\)"):
        camera.convert(torch.eye(3), "opencv", "opengl")
    with pytest.raises(TypeError, match="matrix: expected a torch.Tensor"):
        camera.convert([[1.0]], "opencv", "opengl")
    with pytest.raises(ValueError, match="orthographic one has no K"):
        camera.intrinsics_from_projection(camera.orthographic(-1, 1, -1, 1, 0.1, 9), (8, 8))
    with pytest.raises(ValueError, match="resolution"):
        camera.intrinsics_from_projection(camera.perspective(60.0, 1.0, 0.1), (0, 8))
    with pytest.raises(ValueError, match="T: expected"):
        camera.from_pytorch3d_rt(torch.eye(3), torch.zeros(4))
