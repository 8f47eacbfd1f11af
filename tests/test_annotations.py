"""Per-object annotations (torchraster.labels) against independent references: numpy
per-object masks, pycocotools' own box of an RLE, explicit corner lists and pinhole maths."""

import math

import numpy as np
import pytest
import torch

from torchraster import labels


def _random_instances(seed: int, n: int, shape=(2, 23, 31)) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    ids = torch.randint(0, n + 1, shape, generator=g)
    ids[..., :3, :] = 0  # some rows of background
    ids[0][ids[0] == n] = 0  # instance n absent from item 0
    return ids


def _numpy_box(mask: np.ndarray) -> list[float] | None:
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return None
    return [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_instance_boxes_equal_per_object_masks(seed):
    n = 5
    ids = _random_instances(seed, n)
    boxes, counts = labels.instance_boxes(ids, n)
    assert boxes.shape == (2, n, 4) and counts.shape == (2, n)
    for b in range(2):
        for k in range(1, n + 1):
            mask = ids[b].numpy() == k
            ref = _numpy_box(mask)
            assert int(counts[b, k - 1]) == mask.sum()
            if ref is None:
                assert bool(boxes[b, k - 1].isnan().all())
            else:
                assert boxes[b, k - 1].tolist() == ref
    # the same through per-object masks
    masks = torch.stack([ids == k for k in range(1, n + 1)], -3)
    mboxes, mcounts = labels.mask_boxes(masks)
    assert torch.equal(mcounts, counts)
    assert torch.allclose(mboxes, boxes, equal_nan=True)


def test_boxes_match_pycocotools():
    mask_utils = pytest.importorskip("pycocotools.mask")
    ids = _random_instances(7, 3, (40, 50))
    ids[10:20, 5:9] = 2  # a second, disjoint piece of instance 2
    boxes, _ = labels.instance_boxes(ids, 3)
    for k in range(1, 4):
        rle = mask_utils.encode(np.asfortranarray((ids.numpy() == k).astype(np.uint8)))
        x, y, w, h = mask_utils.toBbox(rle).tolist()
        assert boxes[k - 1].tolist() == [x, y, x + w, y + h]


def test_instance_boxes_errors():
    with pytest.raises(ValueError, match=r"instance: ids must be in \[0, 2\]"):
        labels.instance_boxes(torch.tensor([[0, 3]]), 2)
    with pytest.raises(TypeError, match="instance: expected an integer"):
        labels.instance_boxes(torch.zeros(2, 2), 2)


def test_box_corners_oriented():
    center = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    size = torch.tensor([[2.0, 4.0, 6.0]], dtype=torch.float64)
    model = labels.box_corners(center, size)[0]
    expected = {(x, y, z) for x in (0.0, 2.0) for y in (0.0, 4.0) for z in (0.0, 6.0)}
    assert {tuple(c) for c in model.tolist()} == expected
    assert model[0].tolist() == [0.0, 0.0, 0.0] and model[7].tolist() == [2.0, 4.0, 6.0]
    # 90 degrees about +y, then translate: (x, y, z) -> (z, y, -x) + t
    m = torch.eye(4, dtype=torch.float64)
    m[:3, :3] = torch.tensor([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]], dtype=torch.float64)
    m[:3, 3] = torch.tensor([10.0, 0, 0])
    world = labels.box_corners(center, size, m[None])[0]
    ref = torch.stack([model[:, 2] + 10, model[:, 1], -model[:, 0]], -1)
    assert torch.allclose(world, ref)


def test_project_pinhole():
    k = torch.tensor([[100.0, 0, 31.5], [0, 120.0, 23.5], [0, 0, 1]], dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, 3] = torch.tensor([0.5, -0.25, 2.0])
    pts = torch.tensor([[0.1, 0.2, 1.0], [0.0, 0.0, -5.0]], dtype=torch.float64)
    cam, pix = labels.project(pts, w2c, k)
    x, y, z = 0.6, -0.05, 3.0
    assert cam[0].tolist() == pytest.approx([x, y, z])
    assert pix[0].tolist() == pytest.approx([100 * x / z + 31.5, 120 * y / z + 23.5])
    assert bool(pix[1].isnan().all())  # behind the camera
    _, ortho = labels.project(pts, w2c, None)
    assert bool(ortho.isnan().all())


def _plane_view():
    """Instance 1 a square at z = 4 covering the image centre, camera at the origin."""
    h = w = 32
    f = 40.0
    k = torch.tensor([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]], dtype=torch.float64)
    inst = torch.zeros(h, w, dtype=torch.int64)
    inst[8:24, 8:24] = 1
    depth = torch.where(inst > 0, 4.0, 0.0).double()
    return k, inst, depth


def test_keypoint_visibility():
    k, inst, depth = _plane_view()
    w2c = torch.eye(4, dtype=torch.float64)
    pts = torch.tensor([[0.0, 0.0, 4.0],      # on the square: seen
                        [0.0, 0.0, 5.0],      # behind the square (hidden side): not seen
                        [3.0, 0.0, 4.0],      # off the square (background pixel)
                        [100.0, 0.0, 4.0],    # outside the image
                        [0.0, 0.0, -1.0]],    # behind the camera
                       dtype=torch.float64)
    cam, pix = labels.project(pts, w2c, k)
    seen = labels.keypoint_visibility(pix, cam[:, 2], 1, inst, depth)
    assert seen.tolist() == [True, False, False, False, False]
    no_depth = labels.keypoint_visibility(pix, cam[:, 2], 1, inst, None)
    assert no_depth.tolist() == [True, True, False, False, False]


def test_object_records_json_ready():
    import json

    k, inst, depth = _plane_view()
    inst[8:12, 8:12] = 2  # instance 2 hides part of 1
    amodal = torch.zeros(2, 32, 32, dtype=torch.bool)
    amodal[0, 8:24, 8:24] = True
    amodal[1, 6:12, 6:12] = True
    o2w = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    o2w[:, 2, 3] = 4.0
    recs = labels.object_records(
        instance=inst, object_to_world=o2w, box_center=torch.zeros(2, 3),
        box_size=torch.ones(2, 3), names=["a", "b"], categories=["cube", None],
        category_ids=[1, 0], world_to_camera=torch.eye(4), k=k, amodal=amodal, depth=depth,
        keypoints=[torch.tensor([[0.0, 0.0, 0.0]]), None])
    json.dumps(recs, allow_nan=False)
    a, b = recs
    assert a["instance_id"] == 1 and b["instance_id"] == 2
    assert a["pixels"] == 16 * 16 - 16 and a["pixels_amodal"] == 256
    assert a["visible_fraction"] == pytest.approx(240 / 256)
    assert a["bbox_visible"] == [8, 8, 24, 24] and b["bbox_amodal"] == [6, 6, 12, 12]
    assert len(a["box3d"]["corners_pixels"]) == 8
    # the unit box at z = 4 spans +-0.5 / 3.5 .. 4.5 in the camera: its corner pixels
    u = [p[0] for p in a["box3d"]["corners_pixels"]]
    assert min(u) == pytest.approx(15.5 - 40 * 0.5 / 3.5)
    assert a["keypoints"]["visible"] == [True] and "keypoints" not in b
    assert not math.isnan(a["visible_fraction"])


def test_depth_slope_is_the_smaller_one_sided_step():
    d = torch.tensor([[1.0, 1.1, 1.2, 0.0],
                      [1.0, 1.1, 5.0, 0.0]], dtype=torch.float64)
    s = labels.depth_slope(d)
    # (0, 1): x steps 0.1 / 0.1 -> 0.1; y step 0.0 -> total 0.1
    assert s[0, 1] == pytest.approx(0.1)
    # (1, 2) sits on a silhouette: its x neighbours differ by 3.9 and (empty) -> 3.9; y 3.8
    assert s[1, 2] == pytest.approx(3.9 + 3.8)
    assert s[0, 3] == 0 and s[1, 3] == 0  # empty pixels
    # the test forgives a point half a pixel along a slanted surface, not one behind it
    inst = torch.ones(2, 4, dtype=torch.int64)
    pix = torch.tensor([[1.4, 0.0], [1.0, 0.0]], dtype=torch.float64)
    z = torch.tensor([1.14, 1.5], dtype=torch.float64)
    seen = labels.keypoint_visibility(pix, z, 1, inst, d)
    assert seen.tolist() == [True, False]
