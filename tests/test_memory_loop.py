"""A deforming-mesh training loop holds its memory flat (issue 23).

200 optimisation steps of per-vertex offsets of Spot (the positions change every step, so
every shadow map is new), a shadow-casting point light, 2 views, forward + backward. After a
warm-up, the loop must not accumulate: the number of live tensors (gc) outside the
renderer's caches stays the same, the caches stay within their bounds and the resident
memory grows, besides what the shadow-map cache added within its bound, by less than a
tolerance (malloc may keep a few freed blocks; a leak of one 32² frame's G-buffer a step
would add > 10 MB over the 150 measured steps).
"""

from __future__ import annotations

import gc
import math

import pytest
import torch

import torchraster as tr
from torchraster import frame_pool
from torchraster.shading.shadows import ShadowSettings


def _rss() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise KeyError("VmRSS")


def _live_tensors(*caches) -> int:
    """Live tensor objects, not counting those the caches hold (bounded by their max_bytes;
    a deforming mesh fills the shadow-map cache with maps it will not ask for again)."""
    held = {id(x) for c in caches for e in c._entries for t in e
            if isinstance(t, torch.Tensor) for x in (t, t._base)}  # maps are views
    return sum(1 for o in gc.get_objects() if isinstance(o, torch.Tensor) and id(o) not in held)


@pytest.mark.slow
def test_deforming_training_loop_memory_is_flat():
    torch.manual_seed(0)
    mesh = tr.load_spot(max_texture_size=64)
    scene = tr.RenderScene.from_mesh(mesh)
    view = tr.camera.orbit(torch.tensor([20.0, 140.0]), 15.0, 2.4)
    proj = tr.camera.perspective(45.0, 1.0, 0.1)
    lights = tr.Lights(point=tr.PointLights(
        position=torch.tensor([[[2.0, 2.0, 3.0]]]), color=torch.ones(1, 1, 3),
        intensity=torch.tensor([[20.0]]), cast_shadows=torch.tensor([[True]]),
        shadow=ShadowSettings(map_size=64)))
    renderer = tr.Renderer(32)
    target = renderer(scene, view, proj, lights).image.detach() * 0.8
    offset = torch.zeros_like(mesh.positions, requires_grad=True)
    opt = torch.optim.Adam([offset], lr=1e-3)

    def step() -> float:
        opt.zero_grad(set_to_none=True)
        sc = tr.RenderScene(**{**vars(scene), "positions": mesh.positions + offset})
        out = renderer(sc, view, proj, lights, channels={"depth"})
        loss = (out.image - target).square().mean() + 1e-3 * out.gbuffer["depth"].mean()
        loss.backward()
        opt.step()
        return float(loss.detach())

    for _ in range(50):  # warm-up: caches fill, malloc settles
        step()
    gc.collect()
    cache = renderer.shadow_cache
    tensors, rss, cached = _live_tensors(cache), _rss(), cache.nbytes
    renders = renderer.shadow_cache.renders
    losses = [step() for _ in range(150)]
    gc.collect()
    # the positions need gradients through PCF: every step renders new cube maps with the
    # casters' face ids (for those gradients), outside the cache, which keeps no face ids
    assert renderer.shadow_cache.renders == renders
    assert renderer.shadow_cache.nbytes <= renderer.shadow_cache.max_bytes
    assert len(renderer.mip_cache) <= 2
    assert frame_pool.pooled_bytes() <= frame_pool.POOL_BYTES
    assert _live_tensors(cache) - tensors <= 2, "tensors accumulate across steps"
    grown = _rss() - rss - (cache.nbytes - cached)
    assert grown < 16 * 2**20, f"RSS grew by {grown / 2**20:.1f} MB besides the cache"
    assert all(math.isfinite(v) for v in losses)
