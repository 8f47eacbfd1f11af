"""Reuse across consecutive frames (issue 20, dataset speed): the pipeline's posed scenes
and other frames, and ``OtherFrame.depth``. Every cached result is compared bit for bit with
the same frame rendered from scratch (a fresh view renderer, or the renderer rasterizing
the other frame itself), and the reuse is checked to happen (raster counts)."""

from __future__ import annotations

import pytest
import torch

import torchraster as tr
from torchraster import pipeline
from torchraster import renderer as renderer_mod
from torchraster.motion import OtherDepth, OtherFrame, other_frame_depth
from torchraster.raster import rasterize

#: A cube sliding and turning and a ball, floor, orbiting camera, both flows with validity.
CONFIG = """\
categories: [ground, cube]
frames: {count: 6, fps: 12}
scene:
  objects:
    - {name: floor, primitive: plane, size: 5, category: ground}
    - name: cube
      primitive: box
      size: 0.8
      category: cube
      animation:
        keys:
          - {time: 0, translate: [-0.6, 0.45, 0], rotate_deg: [0, 0, 0]}
          - {time: 0.5, translate: [0.6, 0.45, 0.2], rotate_deg: [0, 90, 0]}
    - {name: ball, primitive: sphere, size: 0.6, transform: {translate: [0.4, 0.3, 0.6]}}
cameras:
  - name: cam
    orbit: {azimuth_deg: 10, elevation_deg: 25, distance: 4, target: [0, 0.3, 0],
            degrees_per_second: 40}
render:
  resolution: 24
lights:
  - {type: directional, direction: [-1, -1, -1]}
outputs:
  channels: [color, depth, normal, instance, object_coords, flow_forward, flow_backward,
             flow_forward_valid, flow_backward_valid, motion]
  formats: [npy]
"""


@pytest.fixture(scope="module")
def cfg(tmp_path_factory):
    path = tmp_path_factory.mktemp("cache") / "c.yaml"
    path.write_text(CONFIG)
    cfg = tr.load_config(path)
    plan = pipeline.plan_objects(cfg)[0]
    return plan.config, plan.views


def _same(a: pipeline.ViewResult, b: pipeline.ViewResult) -> None:
    assert a.images.keys() == b.images.keys()
    for k in a.images:
        assert torch.equal(a.images[k], b.images[k]), k
    assert repr(a.objects) == repr(b.objects)
    assert a.time == b.time and torch.equal(a.view, b.view)


def _counting(monkeypatch) -> list[int]:
    calls = [0]
    real = renderer_mod.rasterize

    def counted(*args, **kwargs):
        calls[0] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(renderer_mod, "rasterize", counted)
    return calls


def test_frames_in_order_equal_fresh_renders(cfg, monkeypatch):
    config, views = cfg
    fresh = [pipeline.view_renderer(config)(v.camera_config, v.folder, v.frame) for v in views]
    calls = _counting(monkeypatch)
    render = pipeline.view_renderer(config)
    for v, ref in zip(views, fresh, strict=True):
        _same(render(v.camera_config, v.folder, v.frame), ref)
    # frame 0 rasterizes itself and both other frames, frame 1 both other frames (its own
    # raster was kept from frame 0's flow validity), later ones only the next frame
    assert calls[0] == 3 + 2 + (len(views) - 2)
    assert bool((fresh[2].images["flow_backward_valid"] == 0).any())  # occlusion happens
    # any order gives the same images (reverse order: nothing reusable from the last frame)
    for v, ref in zip(views[::-1], fresh[::-1], strict=True):
        _same(render(v.camera_config, v.folder, v.frame), ref)


def test_scene_objects_pose_cache(cfg):
    config, _ = cfg
    objects = tr.config.build_objects(config)
    times = [0.25, 0.0, 1 / 12, 0.25, 2 / 12, 3 / 12, 0.0, 5 / 12, 0.25]
    for t in times:  # interleaved, more times than kept
        ref = tr.config.build_objects(config)  # nothing cached
        assert torch.equal(objects.object_to_world(t), ref.object_to_world(t))
        assert torch.equal(objects.positions_at(t), ref.positions_at(t))
        got, want = objects.at(t), ref.at(t)
        for name in ("positions", "normals"):
            assert torch.equal(getattr(got, name), getattr(want, name)), (t, name)
    m = objects.object_to_world(0.25)
    m.zero_()  # a copy: the cache is not changed
    assert torch.equal(objects.object_to_world(0.25),
                       tr.config.build_objects(config).object_to_world(0.25))


def _moving_quad():
    pos = torch.tensor([[-1.0, -1, 0.5], [1, -1, 0.5], [-1, 1, 0.5], [1, 1, 0.5],
                        [-0.3, -0.3, 0.2], [0.3, -0.3, 0.2], [0, 0.4, 0.2]])
    faces = torch.tensor([[0, 1, 2], [1, 3, 2], [4, 5, 6]])
    return tr.RenderScene(positions=pos, faces=faces), pos


def test_renderer_stores_and_reuses_depth(monkeypatch):
    scene, pos = _moving_quad()
    eye = torch.eye(4)
    shifted = pos.clone()
    shifted[4:, 0] += 0.4  # the small triangle moves right: occludes / reveals the quad
    rend = tr.Renderer(resolution=(16, 16), shading="unlit")
    chans = ["flow_forward", "flow_forward_valid"]
    ref = rend(scene, eye, eye, channels=chans, next_frame=OtherFrame(shifted, eye, eye))
    calls = _counting(monkeypatch)
    frame = OtherFrame(shifted, eye, eye)
    a = rend(scene, eye, eye, channels=chans, next_frame=frame)
    # its own raster only: the other frame's was kept from the call before (same content)
    assert calls[0] == 1 and isinstance(frame.depth, OtherDepth)
    b = rend(scene, eye, eye, channels=chans, next_frame=frame)  # the stored depth reused
    assert calls[0] == 2
    # a depth computed by hand (independent of the renderer's call) gives the same too
    clip = torch.cat([shifted, torch.ones(7, 1)], 1)[None]
    given = OtherFrame(shifted, eye, eye, other_frame_depth(clip, scene.faces, (16, 16), eye))
    c = rend(scene, eye, eye, channels=chans, next_frame=given)
    assert bool((ref.gbuffer["flow_forward_valid"] == 0).any())
    for out in (a, b, c):
        for k in chans:
            assert torch.equal(out.gbuffer[k], ref.gbuffer[k]), k
    # the depth the renderer stored is the other frame's own visible depth
    frags = rasterize(clip, scene.faces, (16, 16))
    d = frame.depth.depth[0]
    covered = frags.face_id[0] >= 0
    assert torch.equal(covered, torch.isfinite(d))
    # identity camera: linear depth = -(NDC z), the rasterized depth of the other frame
    assert torch.equal(d[covered], -frags.depth[0][covered].double())


def test_chunked_render_with_depth_equals_whole():
    scene, pos = _moving_quad()
    eye = torch.eye(4)
    shifted = pos.clone()
    shifted[4:, 1] += 0.3
    views = torch.stack([eye, eye, eye])
    chans = ["flow_backward_valid"]
    whole = tr.Renderer(resolution=(12, 12), shading="unlit")
    chunked = tr.Renderer(resolution=(12, 12),
                          shading="unlit",
                          raster=tr.RasterSettings(max_batch=2))
    clip = torch.cat([shifted, torch.ones(7, 1)], 1)[None].expand(3, -1, -1)
    depth = other_frame_depth(clip, scene.faces, (12, 12), eye)
    ref = whole(scene, views, eye, channels=chans, previous_frame=OtherFrame(shifted, eye, eye))
    got = chunked(scene, views, eye, channels=chans,
                  previous_frame=OtherFrame(shifted, eye, eye, depth))
    assert torch.equal(got.gbuffer[chans[0]], ref.gbuffer[chans[0]])


def test_other_frame_depth_checked():
    scene, pos = _moving_quad()
    eye = torch.eye(4)
    with pytest.raises(TypeError, match=r"OtherFrame\.depth: expected an OtherDepth"):
        OtherFrame(pos, eye, eye, torch.zeros(1, 8, 8))
    with pytest.raises(ValueError, match=r"OtherFrame\.depth: depth .* and slope .* differ"):
        OtherFrame(pos, eye, eye, OtherDepth(torch.zeros(1, 8, 8), torch.zeros(1, 8, 9)))
    with pytest.raises(ValueError, match=r"OtherFrame\.depth\.depth"):
        OtherFrame(pos, eye, eye, OtherDepth(torch.zeros(8, 8), torch.zeros(8, 8)))
    wrong = OtherFrame(pos, eye, eye, OtherDepth(torch.zeros(1, 8, 8), torch.zeros(1, 8, 8)))
    rend = tr.Renderer(resolution=(16, 16), shading="unlit")
    with pytest.raises(ValueError, match=r"next_frame\.depth: shape \(1, 8, 8\), expected"):
        rend(scene, eye, eye, channels=["flow_forward_valid"], next_frame=wrong)
