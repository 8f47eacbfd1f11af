"""config/objects.py: a config's scene as instances posed over time, against hand-written
matrices (scale, then rotate, then translate) applied in numpy."""

import math

import numpy as np
import pytest

import torchraster as tr
from torchraster.config import build_objects

CONFIG = """\
scene:
  objects:
    - name: box
      primitive: box
      size: 1
      transform: {translate: [1, 0, 0], rotate_deg: [0, 30, 0], scale: 2}
      animation:
        keys:
          - {time: 0}
          - {time: 1, translate: [3, 0, 0]}
          - {time: 2, rotate_deg: [0, 90, 0], scale: 1}
    - {name: ball, primitive: sphere, size: 1, transform: {translate: [0, 0, -2]}}
"""


def _ry(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def _pose(t: np.ndarray, deg: float, s: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = _ry(deg) * s
    m[:3, 3] = t
    return m


@pytest.fixture(scope="module")
def objects():
    return build_objects(tr.parse_config(CONFIG))


def test_keys_take_what_they_leave_out_from_the_transform(objects):
    """A key without rotation / scale / translation keeps the transform's (not identity)."""
    m = objects.object_to_world
    assert np.allclose(m(0.0)[0], _pose([1, 0, 0], 30, 2), atol=1e-6)
    assert np.allclose(m(1.0)[0], _pose([3, 0, 0], 30, 2), atol=1e-6)
    assert np.allclose(m(2.0)[0], _pose([1, 0, 0], 90, 1), atol=1e-6)  # translate from rest
    # halfway between keys 1 and 2: lerp translation and scale, slerp 30 -> 90 degrees
    assert np.allclose(m(1.5)[0], _pose([2, 0, 0], 60, 1.5), atol=1e-6)
    assert np.allclose(m(5.0)[0], m(2.0)[0])  # held after the last key
    assert np.allclose(m(0.7)[1], _pose([0, 0, -2], 0, 1), atol=1e-6)  # not animated


def test_posed_vertices_are_the_pose_applied_to_the_model(objects):
    for t in (0.0, 0.4, 1.5):
        pos = objects.at(t).positions.double().numpy()
        mats = objects.object_to_world(t).numpy()
        model = objects.model_positions.double().numpy()
        for (s, e), m in zip(objects.vertex_ranges.tolist(), mats, strict=True):
            expect = model[s:e] @ m[:3, :3].T + m[:3, 3]
            assert np.allclose(pos[s:e], expect, atol=1e-5)
    nocs = objects.scene.object_coords
    assert float(nocs.min()) >= 0 and float(nocs.max()) <= 1
    assert objects.scene.face_object.unique().tolist() == [1, 2]


def test_prepared_times_pose_the_same():
    """``prepare`` (the keyframes of all frames in one evaluation) gives the poses, vertices
    and normals of posing each time alone; the normals are the inverse-transposed model
    normals (numpy)."""
    times = [0.0, 0.4, 1.5, 2.5]
    alone = build_objects(tr.parse_config(CONFIG))
    ahead = build_objects(tr.parse_config(CONFIG))
    ahead.prepare(times)
    assert set(ahead._prepared) == set(times)
    for t in times:
        np.testing.assert_allclose(ahead.object_to_world(t), alone.object_to_world(t),
                                   rtol=0, atol=1e-12)
        a, b = ahead.at(t), alone.at(t)
        np.testing.assert_allclose(a.positions, b.positions, rtol=0, atol=1e-6)
        np.testing.assert_allclose(a.normals, b.normals, rtol=0, atol=1e-6)
        mats = alone.object_to_world(t).numpy()
        model = alone.model_normals.double().numpy()
        for (s, e), m in zip(alone.vertex_ranges.tolist(), mats, strict=True):
            n = model[s:e] @ np.linalg.inv(m[:3, :3])
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            assert np.allclose(b.normals[s:e].double().numpy(), n, atol=1e-5)
