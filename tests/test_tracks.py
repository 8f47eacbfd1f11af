"""Point tracks (exports: [tracks]) against the flow channel: two independent paths to where a
surface point goes (tracks: the query pixel's NOCS back to the model frame, moved by the
records' poses and projected by their cameras; flow: the pixel's barycentric point
reprojected by motion.py)."""

from __future__ import annotations

import numpy as np
import pytest

from torchraster import manifest
from torchraster.cli import main

CONFIG = """\
frames: {count: 3, fps: 4}
scene:
  objects:
    - {name: floor, primitive: plane, size: 6, cast_shadows: false}
    - name: box
      primitive: box
      size: 0.8
      transform: {translate: [-0.6, 0.4, 0]}
      animation:
        keys:
          - {time: 0, translate: [-0.6, 0.4, 0]}
          - {time: 0.5, translate: [0.4, 0.4, 0.2], rotate_deg: [0, 30, 0]}
    - {name: ball, primitive: sphere, size: 0.7, transform: {translate: [0.5, 0.35, -0.6]}}
cameras:
  - name: cam
    orbit: {azimuth_deg: 20, elevation_deg: 30, distance: 4.5, target: [0, 0.3, 0],
            degrees_per_second: 20}
render: {resolution: 48}
outputs:
  channels: [color, depth, instance, object_coords, flow_forward, flow_forward_valid]
  formats: [npy]
  exports: [tracks]
  track_points: 200
"""


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    root = tmp_path_factory.mktemp("tracks")
    (root / "t.yaml").write_text(CONFIG)
    assert main(["render", str(root / "t.yaml"), "--out", str(root / "out")]) == 0
    data = np.load(root / "out" / "exports" / "tracks" / "t_scene_cam.npz")
    records = sorted(manifest.read_manifest(root / "out"), key=lambda r: r["frame"])
    return root / "out", data, records


def test_layout(tracked):
    _, d, records = tracked
    n, t = d["occluded"].shape
    assert n == 200 and t == 3 and d["tracks"].shape == (200, 3, 2)
    assert d["query_points"].shape == (200, 3) and (d["query_points"][:, 0] == 0).all()
    assert list(d["keys"]) == [r["key"] for r in records]
    assert np.allclose(d["points"], d["tracks"] / 48)


def test_first_frame_is_the_query_pixel(tracked):
    _, d, _ = tracked
    q = d["query_points"]
    assert np.abs(d["tracks"][:, 0, 0] - q[:, 2]).max() < 1e-3  # x
    assert np.abs(d["tracks"][:, 0, 1] - q[:, 1]).max() < 1e-3  # y
    assert not d["occluded"][:, 0].any()


def test_second_frame_equals_the_forward_flow(tracked):
    out, d, records = tracked
    folder = out / records[0]["files"]["flow_forward.npy"].rsplit("/", 1)[0]
    flow = np.load(folder / "flow_forward.npy")
    valid = np.load(folder / "flow_forward_valid.npy")[0] > 0
    rows = (d["query_points"][:, 1] - 0.5).astype(int)
    cols = (d["query_points"][:, 2] - 0.5).astype(int)
    moved = d["tracks"][:, 1] - d["tracks"][:, 0]
    expect = flow[:, rows, cols].T
    assert np.abs(moved - expect).max() < 2e-3
    # occlusion: the tracks' test (instance + depth at the landing pixel) and the flow's
    # (depth with a slope tolerance) agree on nearly every point
    agree = (~d["occluded"][:, 1]) == valid[rows, cols]
    assert agree.mean() > 0.95
    assert d["instance"].min() >= 1 and len(np.unique(d["instance"])) >= 2
