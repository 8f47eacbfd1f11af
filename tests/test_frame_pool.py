"""frame_pool: large CPU buffers are reused only once nothing references them, so results
of earlier calls never change, and rasterize + interpolate give the same images with it."""

from __future__ import annotations

import gc

import pytest
import torch
import trimesh

import torchraster as tr
from torchraster import frame_pool


@pytest.fixture
def small_pool(monkeypatch):
    """Pool every buffer of 1 KB and up (the default starts at 32 MB), from an empty pool."""
    monkeypatch.setattr(frame_pool, "MIN_BYTES", 1024)
    frame_pool.clear()
    yield
    frame_pool.clear()


def test_released_buffer_is_reused(small_pool) -> None:
    a = frame_pool.empty((64, 64), torch.float32, "cpu")
    ptr = a.data_ptr()
    del a
    gc.collect()
    assert frame_pool.pooled_bytes() == 64 * 64 * 4
    b = frame_pool.empty((32, 128), torch.int32, "cpu")  # same bytes, other dtype and shape
    assert b.data_ptr() == ptr and b.shape == (32, 128) and b.dtype == torch.int32
    assert frame_pool.pooled_bytes() == 0


def test_live_views_keep_their_buffer(small_pool) -> None:
    """A view (or anything holding the storage) keeps the buffer out of the pool."""
    a = frame_pool.empty((64, 64), torch.float32, "cpu").fill_(1.0)
    view = a[3]
    del a
    gc.collect()
    assert frame_pool.pooled_bytes() == 0
    b = frame_pool.empty((64, 64), torch.float32, "cpu").fill_(2.0)
    assert b.data_ptr() != view.data_ptr() - 3 * 64 * 4
    assert bool((view == 1.0).all())


def test_small_other_devices_and_dtypes_are_plain(monkeypatch) -> None:
    frame_pool.clear()
    assert frame_pool.empty((4, 4), torch.float32, "cpu").shape == (4, 4)  # below MIN_BYTES
    monkeypatch.setattr(frame_pool, "MIN_BYTES", 8)
    t = frame_pool.empty((16,), torch.bfloat16, "cpu")  # no numpy dtype: torch.empty
    assert t.dtype == torch.bfloat16 and t.shape == (16,)
    monkeypatch.setattr(frame_pool, "POOL_BYTES", 0)  # off: released buffers are dropped
    a = frame_pool.empty((64,), torch.float32, "cpu")
    del a
    gc.collect()
    assert frame_pool.pooled_bytes() == 0


def test_pool_keeps_at_most_pool_bytes_newest_first(small_pool, monkeypatch) -> None:
    monkeypatch.setattr(frame_pool, "POOL_BYTES", 3000)
    bufs = [frame_pool.empty((256,), torch.float32, "cpu") for _ in range(3)]  # 1 KB each
    ptrs = [b.data_ptr() for b in bufs]
    for k in range(3):  # released oldest first
        bufs[k] = None
        gc.collect()
    assert frame_pool.pooled_bytes() == 2048
    again = frame_pool.empty((256,), torch.float32, "cpu")
    assert again.data_ptr() in ptrs[1:]  # the first released buffer was dropped


def test_rasterize_results_survive_later_calls(small_pool) -> None:
    """Outputs held by the caller are never reused by the next call; outputs released are,
    and the images equal those of an unpooled run."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    verts = torch.tensor(mesh.vertices, dtype=torch.float32)
    faces = torch.tensor(mesh.faces, dtype=torch.int64)
    views = [tr.camera.orbit(torch.tensor([a]), torch.tensor([20.0]), torch.tensor([3.0]))
             for a in (0.0, 90.0, 180.0)]
    proj = tr.camera.perspective(45.0, 1.0, 0.1)
    clips = [tr.camera.transform_points(verts, proj @ v) for v in views]

    def draw(clip):
        frags = tr.rasterize(clip, faces, (64, 64))
        return frags, tr.interpolate(verts[None], frags, faces)

    first = draw(clips[0])
    kept = (first[0].face_id.clone(), first[0].bary.clone(), first[1].clone())
    second = draw(clips[1])  # while `first` is alive: must not share its buffers
    assert torch.equal(first[0].face_id, kept[0]) and torch.equal(first[0].bary, kept[1])
    assert torch.equal(first[1], kept[2])
    del second
    gc.collect()
    assert frame_pool.pooled_bytes() > 0
    third = draw(clips[2])  # reuses the released buffers
    monkeypatch_off = pytest.MonkeyPatch()
    monkeypatch_off.setattr(frame_pool, "POOL_BYTES", 0)
    try:
        plain = draw(clips[2])
    finally:
        monkeypatch_off.undo()
    assert torch.equal(third[0].face_id, plain[0].face_id)
    assert torch.equal(third[0].bary, plain[0].bary) and torch.equal(third[1], plain[1])
    assert torch.equal(first[0].face_id, kept[0]) and torch.equal(first[1], kept[2])


def test_memory_check_returns_pooled_buffers_before_refusing(small_pool, monkeypatch) -> None:
    """Released buffers the pool holds are reclaimable: the frame memory check frees them
    and looks again before it refuses a frame."""
    from torchraster import _validate

    a = frame_pool.empty((1024,), torch.float32, "cpu")
    del a
    gc.collect()
    assert frame_pool.pooled_bytes() > 0
    freed = []

    def available(device):  # enough only once the pool has been cleared
        freed.append(frame_pool.pooled_bytes() == 0)
        return 10**9 if freed[-1] else 10**3

    monkeypatch.setattr(_validate, "available_memory", available)
    _validate.check_frame_memory("frame", 10**4, 100, torch.device("cpu"))  # 1 MB: fits
    assert freed == [False, True] and frame_pool.pooled_bytes() == 0
    with pytest.raises(MemoryError, match="frame: a frame of 10,000,000 pixels"):
        _validate.check_frame_memory("frame", 10**7, 1000, torch.device("cpu"))


def test_gradients_with_pooled_buffers_match_unpooled(small_pool) -> None:
    """The per-pixel pass saves pooled buffers for backward: gradients of two overlapping
    calls (the second made before the first's backward) equal those without the pool."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    verts = torch.tensor(mesh.vertices, dtype=torch.float32)
    faces = torch.tensor(mesh.faces, dtype=torch.int64)
    proj = tr.camera.perspective(45.0, 1.0, 0.1)
    clips = [tr.camera.transform_points(verts, proj @ tr.camera.orbit(
        torch.tensor([a]), torch.tensor([10.0]), torch.tensor([3.0]))) for a in (0.0, 60.0)]

    def grads() -> list[torch.Tensor]:
        leaves = [c.clone().requires_grad_(True) for c in clips]
        losses = []
        for leaf in leaves:  # both forwards first: their saved buffers coexist
            frags = tr.rasterize(leaf, faces, (48, 48), derivatives=True)
            image = tr.interpolate(verts[None], frags, faces)
            losses.append(image.square().sum() + frags.bary_dx.square().sum())
        for loss in losses:
            loss.backward()
        return [leaf.grad for leaf in leaves]

    pooled = grads()
    pooled_again = grads()  # now from released buffers
    assert frame_pool.pooled_bytes() > 0
    off = pytest.MonkeyPatch()
    off.setattr(frame_pool, "POOL_BYTES", 0)
    try:
        plain = grads()
    finally:
        off.undo()
    for a, b, c in zip(pooled, pooled_again, plain, strict=True):
        assert torch.equal(a, c) and torch.equal(b, c)


@pytest.mark.parametrize("pooled", [True, False])
def test_flatnonzero_matches_nonzero(small_pool, monkeypatch, pooled: bool) -> None:
    if not pooled:
        monkeypatch.setattr(frame_pool, "MIN_BYTES", 2**40)
    mask = torch.rand(3, 50, 40, generator=torch.Generator().manual_seed(3)) < 0.3
    got = frame_pool.flatnonzero(mask)
    assert torch.equal(got, mask.view(-1).nonzero().squeeze(1)) and got.dtype == torch.int64
    assert frame_pool.flatnonzero(torch.zeros(2000, dtype=torch.bool)).shape == (0,)
