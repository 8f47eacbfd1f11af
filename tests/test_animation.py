"""Animation against independent references: closed-form slerp and explicit rotation
matrices in float64 numpy, hand-computed keyframe poses, finite differences (gradcheck) and
torchraster.camera's own look_at / orbit at the interpolated parameters."""

import math

import numpy as np
import pytest
import torch

from torchraster import animation as A
from torchraster import camera


def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


_R = {"x": _rx, "y": _ry, "z": _rz}


def _quat_matrix_np(q):
    """Rotation matrix of a quaternion (w, x, y, z), the textbook formula, float64."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _slerp_np(q0, q1, t):
    q0, q1 = q0 / np.linalg.norm(q0), q1 / np.linalg.norm(q1)
    if q0 @ q1 < 0:
        q1 = -q1
    th = math.acos(min(1.0, q0 @ q1))
    return (math.sin((1 - t) * th) * q0 + math.sin(t * th) * q1) / math.sin(th)


def _random_quats(n, seed=0):
    g = np.random.default_rng(seed)
    q = g.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# --------------------------------------------------------------------------- slerp


def test_slerp_matches_closed_form_float64():
    q0, q1 = _random_quats(64, 1), _random_quats(64, 2)
    t = np.random.default_rng(3).uniform(0, 1, size=64)
    got = A.slerp(torch.tensor(q0), torch.tensor(q1), torch.tensor(t)).numpy()
    want = np.stack([_slerp_np(a, b, s) for a, b, s in zip(q0, q1, t, strict=True)])
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_slerp_ends_and_midpoint_as_rotations():
    q0, q1 = _random_quats(16, 4), _random_quats(16, 5)
    q0t, q1t = torch.tensor(q0), torch.tensor(q1)
    for t, ref in ((0.0, q0), (1.0, q1)):  # q1 may come back as -q1: compare matrices
        m = A.quaternion_to_matrix(A.slerp(q0t, q1t, t)).numpy()
        np.testing.assert_allclose(m, np.stack([_quat_matrix_np(q) for q in ref]), atol=1e-12)
    mid = A.quaternion_to_matrix(A.slerp(q0t, q1t, 0.5)).numpy()
    for a, m, b in zip(q0, mid, q1, strict=True):  # equal relative rotations either side
        r0, r1 = _quat_matrix_np(a), _quat_matrix_np(b)
        np.testing.assert_allclose(r0.T @ m, m.T @ r1, atol=1e-12)


def test_slerp_takes_the_shortest_path():
    # 0 and 350 degrees about z: the short way is -10 degrees, the midpoint at -5 (355).
    q0 = A.quaternion_from_euler(torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64))
    q1 = A.quaternion_from_euler(torch.tensor([0.0, 0.0, 350.0], dtype=torch.float64))
    mid = A.quaternion_to_matrix(A.slerp(q0, q1, 0.5)).numpy()
    np.testing.assert_allclose(mid, _rz(math.radians(-5)), atol=1e-12)


@pytest.mark.parametrize("flip", [1.0, -1.0])
def test_slerp_stable_when_quaternions_coincide(flip):
    q0 = torch.tensor(_random_quats(1, 6)[0], requires_grad=True)
    q1 = (flip * q0.detach()).clone().requires_grad_(True)
    t = torch.tensor([0.0, 0.25, 0.5, 1.0], dtype=torch.float64)
    out = A.slerp(q0.expand(4, 4), q1.expand(4, 4), t)
    assert torch.allclose(out, q0.detach().expand(4, 4), atol=1e-14)
    out.sum().backward()
    assert torch.isfinite(q0.grad).all() and torch.isfinite(q1.grad).all()
    # nearly equal: still the closed form (which is well conditioned at 1e-4 rad)
    q1n = _random_quats(1, 6)[0] + 1e-4 * np.array([0.1, -0.3, 0.2, 0.5])
    got = A.slerp(q0.detach(), torch.tensor(q1n), 0.3).numpy()
    np.testing.assert_allclose(got, _slerp_np(q0.detach().numpy(), q1n, 0.3), atol=1e-12)


def test_slerp_gradcheck():
    q0 = torch.tensor(_random_quats(3, 7), requires_grad=True)
    q1 = torch.tensor(_random_quats(3, 8), requires_grad=True)
    t = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a, b: A.slerp(a, b, t), (q0, q1))


# --------------------------------------------------------------------------- Euler angles


@pytest.mark.parametrize("order", ["xyz", "zyx", "yxz", "zxz", "XYZ", "ZYX", "YZY"])
def test_euler_to_matrix_matches_explicit_products(order):
    angles = np.array([[30.0, -50.0, 110.0], [170.0, 80.0, -20.0], [0.0, 0.0, 0.0]])
    q = A.quaternion_from_euler(torch.tensor(angles), order)
    assert torch.allclose(q.norm(dim=-1), torch.ones(3, dtype=torch.float64))
    got = A.quaternion_to_matrix(q).numpy()
    for m, qi, ang in zip(got, q.numpy(), angles, strict=True):
        mats = [_R[c](math.radians(a)) for c, a in zip(order.lower(), ang, strict=True)]
        if order.isupper():  # intrinsic: body axes, first letter leftmost
            want = mats[0] @ mats[1] @ mats[2]
        else:  # extrinsic: world axes, first letter applied first (rightmost)
            want = mats[2] @ mats[1] @ mats[0]
        np.testing.assert_allclose(m, want, atol=1e-12)
        np.testing.assert_allclose(_quat_matrix_np(qi), want, atol=1e-12)


def test_euler_xyz_agrees_with_kornia_convention():
    from kornia.geometry.conversions import quaternion_from_euler as kq

    a = torch.tensor([0.3, 0.7, 1.1], dtype=torch.float64)
    want = torch.stack(kq(a[0], a[1], a[2]))
    got = A.quaternion_from_euler(torch.rad2deg(a), "xyz")
    assert torch.allclose(got, want, atol=1e-12)


def test_quaternion_to_matrix_matches_textbook_formula():
    q = _random_quats(8, 9) * 3.0  # any non-zero scale is the same rotation
    got = A.quaternion_to_matrix(torch.tensor(q)).numpy()
    np.testing.assert_allclose(got, np.stack([_quat_matrix_np(v) for v in q]), atol=1e-12)


def test_quaternion_errors_name_the_argument():
    with pytest.raises(ValueError, match="order"):
        A.quaternion_from_euler([0.0, 0.0, 0.0], "xxy")
    with pytest.raises(ValueError, match="order"):
        A.quaternion_from_euler([0.0, 0.0, 0.0], "xYz")
    with pytest.raises(ValueError, match="angles_deg"):
        A.quaternion_from_euler([0.0, 0.0])
    with pytest.raises(ValueError, match=r"q: the quaternion at index \[1\] has zero norm"):
        A.quaternion_to_matrix(torch.tensor([[1.0, 0, 0, 0], [0.0, 0, 0, 0]]))


# --------------------------------------------------------------------------- keyframes


def _keys(dtype=torch.float64, **kw):
    return A.Keyframes(
        times=torch.tensor([1.0, 3.0], dtype=dtype),
        translation=torch.tensor([[0.0, 0.0, 0.0], [2.0, 4.0, -6.0]], dtype=dtype),
        rotation=A.quaternion_from_euler(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 90.0]],
                                                      dtype=dtype)),
        scale=torch.tensor([1.0, 3.0], dtype=dtype), **kw)


def test_transform_at_keys_midway_and_outside():
    m = A.transform_at(_keys(), [1.0, 3.0, 2.0, -5.0, 9.0]).numpy()
    # at the keys: exactly the keys
    np.testing.assert_array_equal(m[0, :3, 3], [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(m[1, :3, 3], [2.0, 4.0, -6.0])
    np.testing.assert_allclose(m[0, :3, :3], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(m[1, :3, :3], _rz(math.pi / 2) * 3, atol=1e-15)
    # midway (hand computed): half translation, 45 degrees about z, scale 2
    np.testing.assert_allclose(m[2, :3, 3], [1.0, 2.0, -3.0], atol=1e-15)
    np.testing.assert_allclose(m[2, :3, :3], _rz(math.pi / 4) * 2, atol=1e-14)
    # outside: the end values hold
    np.testing.assert_allclose(m[3], m[0], atol=0)
    np.testing.assert_allclose(m[4], m[1], atol=0)
    np.testing.assert_array_equal(m[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (5, 1)))


def test_transform_order_scale_rotate_translate():
    """A model point p goes to R (s * p) + t (non-uniform scale shows the order)."""
    keys = A.Keyframes(times=[0.0], translation=[[1.0, 2.0, 3.0]],
                       rotation=A.quaternion_from_euler([[0.0, 90.0, 0.0]]),
                       scale=[[2.0, 1.0, 1.0]])
    m = A.transform_at(keys, 0.0)[0].double().numpy()
    p = np.array([1.0, 1.0, 1.0])
    want = _ry(math.pi / 2) @ (np.array([2.0, 1.0, 1.0]) * p) + [1.0, 2.0, 3.0]
    np.testing.assert_allclose(m @ np.append(p, 1.0), np.append(want, 1.0), atol=1e-6)


def test_transform_at_three_keys_matches_piecewise_reference():
    times = [0.0, 1.0, 3.0]
    eul = np.array([[10.0, 20.0, 30.0], [-40.0, 60.0, 5.0], [90.0, -10.0, 45.0]])
    trans = np.array([[0.0, 1.0, 2.0], [3.0, -1.0, 0.5], [1.0, 1.0, 1.0]])
    scale = np.array([[1.0, 2.0, 0.5], [2.0, 2.0, 2.0], [0.25, 1.0, 4.0]])
    q = A.quaternion_from_euler(torch.tensor(eul)).numpy()
    keys = A.Keyframes(times=torch.tensor(times, dtype=torch.float64),
                       translation=torch.tensor(trans), rotation=torch.tensor(q),
                       scale=torch.tensor(scale))
    ts = [0.25, 1.0, 1.5, 2.9]
    got = A.transform_at(keys, torch.tensor(ts, dtype=torch.float64)).numpy()
    for m, t in zip(got, ts, strict=True):
        i = 0 if t < 1.0 else 1
        u = (t - times[i]) / (times[i + 1] - times[i])
        r = _quat_matrix_np(_slerp_np(q[i], q[i + 1], u)) if u > 0 else _quat_matrix_np(q[i])
        s = (1 - u) * scale[i] + u * scale[i + 1]
        np.testing.assert_allclose(m[:3, :3], r * s, atol=1e-12)
        np.testing.assert_allclose(m[:3, 3], (1 - u) * trans[i] + u * trans[i + 1], atol=1e-12)


def test_transform_at_gradcheck_translation_rotation_scale():
    times = torch.tensor([0.0, 1.0, 2.5], dtype=torch.float64)
    trans = torch.randn(3, 3, dtype=torch.float64, requires_grad=True)
    rot = torch.tensor(_random_quats(3, 11), requires_grad=True)
    scale = (torch.rand(3, 3, dtype=torch.float64) + 0.5).requires_grad_(True)
    t = torch.tensor([0.3, 1.0, 1.7, 2.4], dtype=torch.float64)

    def f(tr_, rot_, sc_):
        return A.transform_at(A.Keyframes(times=times, translation=tr_, rotation=rot_,
                                          scale=sc_), t)

    assert torch.autograd.gradcheck(f, (trans, rot, scale))


def test_step_interpolation_holds_until_the_next_key():
    keys = _keys(interpolation="step")
    m = A.transform_at(keys, [0.0, 1.0, 2.0, 2.999, 3.0, 4.0]).numpy()
    for i in (0, 1, 2, 3):
        np.testing.assert_allclose(m[i, :3, :4], np.eye(4)[:3], atol=1e-15)
    for i in (4, 5):
        np.testing.assert_allclose(m[i, :3, :3], _rz(math.pi / 2) * 3, atol=1e-15)
        np.testing.assert_array_equal(m[i, :3, 3], [2.0, 4.0, -6.0])


def test_keyframes_defaults_dtype_and_single_key():
    keys = A.Keyframes(times=[0.5])
    m = A.transform_at(keys, [0.0, 0.5, 7.0])
    assert m.dtype == torch.float32
    assert torch.equal(m, torch.eye(4).expand(3, 4, 4))
    assert _keys().translation.dtype == torch.float64
    assert A.transform_at(_keys(), 2.0).dtype == torch.float64


def test_keyframes_from_records():
    keys = A.Keyframes.from_records([
        {"time": 0.0, "translation": [1, 2, 3]},
        {"time": 2.0, "euler_deg": [0, 0, 90], "scale": 3},
        {"time": 4.0, "rotation": [0, 0, 0, 1], "scale": [1, 2, 3]},
    ], interpolation="linear")
    m = A.transform_at(keys, [0.0, 2.0, 4.0]).double().numpy()
    np.testing.assert_allclose(m[0, :3, 3], [1, 2, 3])
    np.testing.assert_allclose(m[1, :3, :3], _rz(math.pi / 2) * 3, atol=1e-6)
    np.testing.assert_allclose(m[2, :3, :3], _rz(math.pi) * [1, 2, 3], atol=1e-6)


@pytest.mark.parametrize("kwargs,match", [
    ({"times": [0.0, 2.0, 1.0]}, r"times: keyframe 2 \(t = 1.0\) comes before keyframe 1"),
    ({"times": [0.0, 1.0, 1.0]}, r"times: keyframes 1 and 2 have the same time 1.0"),
    ({"times": []}, "times: expected at least one keyframe"),
    ({"times": [0.0, float("nan")]}, r"times\[1\]: expected a finite time"),
    ({"times": [0.0, 1.0], "translation": [[0, 0, 0]]}, "translation: expected shape"),
    ({"times": [0.0, 1.0], "translation": [[0, 0, 0], [0, float("inf"), 0]]},
     r"translation\[1\]: expected finite"),
    ({"times": [0.0, 1.0], "rotation": [[1, 0, 0, 0], [0, 0, 0, 0]]},
     r"rotation\[1\]: zero quaternion"),
    ({"times": [0.0, 1.0], "scale": [1.0, -2.0]}, r"scale\[1\]: expected positive"),
    ({"times": [0.0], "interpolation": "cubic"}, "interpolation: expected one of"),
])
def test_keyframes_errors_name_field_and_index(kwargs, match):
    with pytest.raises(ValueError, match=match):
        A.Keyframes(**kwargs)


def test_from_records_errors():
    with pytest.raises(ValueError, match=r"records\[1\]: unknown field\(s\) \['tranlation'\]"):
        A.Keyframes.from_records([{"time": 0}, {"time": 1, "tranlation": [1, 2, 3]}])
    with pytest.raises(ValueError, match=r"records\[0\]: missing 'time'"):
        A.Keyframes.from_records([{"translation": [1, 2, 3]}])
    with pytest.raises(ValueError, match=r"records\[0\].translation: expected 3 numbers"):
        A.Keyframes.from_records([{"time": 0, "translation": [1, 2]}])
    with pytest.raises(ValueError, match="not both"):
        A.Keyframes.from_records([{"time": 0, "rotation": [1, 0, 0, 0], "euler_deg": [0, 0, 0]}])
    with pytest.raises(ValueError, match="keyframes 0 and 1 have the same time"):
        A.Keyframes.from_records([{"time": 1}, {"time": 1}])


# --------------------------------------------------------------------------- cameras, time


def test_orbit_path_equals_camera_orbit_at_the_azimuth():
    t = torch.tensor([0.0, 0.5, 2.0, 7.25], dtype=torch.float64)
    got = A.orbit_path(t, 30.0, 45.0, 20.0, 4.0, target=[0.0, 1.0, 0.0])
    want = camera.orbit(30.0 + 45.0 * t, torch.full_like(t, 20.0), torch.full_like(t, 4.0),
                        target=[0.0, 1.0, 0.0])
    assert got.shape == (4, 4, 4) and got.dtype == torch.float64
    assert torch.allclose(got, want, atol=1e-12)
    # independent check: the eye sits at the orbit's position (camera at azimuth 30 + 45 t)
    eye = torch.linalg.inv(got)[:, :3, 3]
    az, el = torch.deg2rad(30.0 + 45.0 * t), math.radians(20.0)
    ref = torch.stack([4 * math.cos(el) * torch.sin(az), 1 + 4 * math.sin(el) + 0 * az,
                       4 * math.cos(el) * torch.cos(az)], dim=-1)
    assert torch.allclose(eye, ref, atol=1e-12)


def test_look_at_path_interpolates_eye_and_target():
    times = [0.0, 2.0]
    eyes = torch.tensor([[0.0, 1.0, 5.0], [4.0, 3.0, 1.0]], dtype=torch.float64)
    targets = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, -2.0]], dtype=torch.float64)
    got = A.look_at_path(times, eyes, targets, t=[-1.0, 0.0, 0.5, 2.0, 3.0])
    mid_eye, mid_target = eyes[0] * 0.75 + eyes[1] * 0.25, targets[0] * 0.75 + targets[1] * 0.25
    want = torch.cat([camera.look_at(eyes[0], targets[0]), camera.look_at(eyes[0], targets[0]),
                      camera.look_at(mid_eye, mid_target), camera.look_at(eyes[1], targets[1]),
                      camera.look_at(eyes[1], targets[1])])
    assert torch.allclose(got, want, atol=1e-12)
    step = A.look_at_path(times, eyes, targets, t=[1.9], interpolation="step")
    assert torch.allclose(step, camera.look_at(eyes[0], targets[0]), atol=1e-12)
    ups = A.look_at_path(times, eyes, targets, [1.0, 0.0, 0.0], t=[0.0])
    assert torch.allclose(ups, camera.look_at(eyes[0], targets[0], [1.0, 0.0, 0.0]))


def test_look_at_path_errors():
    with pytest.raises(ValueError, match="times: keyframes 0 and 1 have the same time"):
        A.look_at_path([1.0, 1.0], [[0, 0, 1], [0, 0, 2]], [[0, 0, 0]] * 2, t=[0.0])
    with pytest.raises(ValueError, match="targets: expected shape"):
        A.look_at_path([0.0, 1.0], [[0, 0, 1], [0, 0, 2]], [[0, 0, 0]], t=[0.0])
    with pytest.raises(ValueError, match="eye and the target coincide"):
        A.look_at_path([0.0], [[0, 0, 0]], [[0, 0, 0]], t=[0.0])


def test_frame_times():
    t = A.frame_times(5, 24.0, dtype=torch.float64)
    assert torch.equal(t, torch.tensor([i / 24.0 for i in range(5)], dtype=torch.float64))
    assert A.frame_times(1, 30).tolist() == [0.0]
    assert A.frame_times(3, 10).dtype == torch.float32


@pytest.mark.parametrize("count,fps,err,match", [
    (0, 24.0, ValueError, "count: expected 1 <= count"),
    (A.MAX_FRAMES + 1, 24.0, ValueError, "count: expected 1 <= count"),
    (2.5, 24.0, TypeError, "count: expected an integer"),
    (True, 24.0, TypeError, "count"),
    (5, 0.0, ValueError, "fps: expected a finite value > 0"),
    (5, float("inf"), ValueError, "fps"),
    (5, float("nan"), ValueError, "fps"),
    (5, "24", TypeError, "fps"),
])
def test_frame_times_errors(count, fps, err, match):
    with pytest.raises(err, match=match):
        A.frame_times(count, fps)
