"""Shadow-map memory (issue 23): views rendered in chunks and written into the maps one
chunk at a time give the same maps as one call, bit for bit, and the same as an
independent assembly (one :func:`rasterize_depth` per view, the linear-depth formula);
``key_depth`` (chunked) against its one-line definition."""

from __future__ import annotations

import pytest
import torch

import torchraster as tr
from torchraster.raster import rasterize_depth
from torchraster.raster.rasterize import EMPTY_KEY, depth_key, key_depth
from torchraster.shading.shadows import (
    ShadowMapCache,
    ShadowSettings,
    directional_views,
    local_views,
    render_shadow_maps,
)
from torchraster.testing import raytrace as rt


def _scene():
    verts, faces = rt.icosphere(0.5, (0.0, 0.5, 0.0), subdivisions=1)
    pos, faces, _ = rt.ground_scene([(verts, faces)], 4.0)
    pos = torch.stack([pos.float(), pos.float() + 0.1])  # batch of 2
    bounds = torch.stack([pos.amin(1), pos.amax(1)], 1)
    view = tr.camera.look_at([0.0, 2.5, 4.0], [0.0, 0.3, 0.0]).expand(2, 4, 4)
    proj = tr.camera.perspective(45.0, 1.0, 0.1).expand(2, 4, 4)
    return pos, faces, bounds, view, proj


def _groups(filt: str, bounds, view, proj, size: int = 48):
    st = ShadowSettings(map_size=size, filter=filt)
    point = local_views("point", torch.tensor([[[1.0, 2.0, 0.5], [0.2, 1.5, -0.3]]]).expand(
        2, 2, 3), None, None, st, bounds)
    sun = directional_views(torch.tensor([[[0.3, -1.0, 0.2]]]).expand(2, 1, 3),
                            ShadowSettings(map_size=size, filter=filt, cascades=3), bounds,
                            view, proj)
    spot = local_views("spot", torch.tensor([[[1.0, 2.0, 0.5]]]).expand(2, 1, 3),
                       torch.tensor([[[-0.5, -1.0, -0.2]]]).expand(2, 1, 3),
                       torch.tensor([[0.6]]).expand(2, 1), st, bounds)
    return [point, sun, spot]


@pytest.mark.parametrize("filt", ["pcf", "vsm"])
def test_maps_do_not_depend_on_the_chunking(filt):
    pos, faces, bounds, view, proj = _scene()
    size = 48
    maps = []
    for budget, cache in ((2**30, None), (size * size * 16 * 3, None),
                          (size * size * 16, ShadowMapCache())):
        groups = _groups(filt, bounds, view, proj, size)
        render_shadow_maps(groups, pos, faces, memory_budget=budget, cache=cache)
        maps.append([g.depth for g in groups])
    for other in maps[1:]:
        for a, b in zip(maps[0], other, strict=True):
            assert torch.equal(a, b)


def test_maps_equal_one_rasterize_depth_per_view():
    """Independent assembly: each view rasterized alone, NDC -> linear depth by the
    OpenGL formulas (perspective: 2 f n / ((f + n) - z (f - n)); orthographic:
    (z (f - n) + f + n) / 2), +inf where nothing was drawn."""
    pos, faces, bounds, view, proj = _scene()
    groups = _groups("pcf", bounds, view, proj)
    render_shadow_maps(groups, pos, faces, memory_budget=48 * 48 * 16 * 2)
    for g in groups:
        b, n_l, nv = g.view.shape[:3]
        for i in range(b):
            for li in range(n_l):
                for v in range(nv):
                    got = g.depth[i, li, v]
                    if not bool(g.rendered[v]):
                        assert torch.isinf(got).all()
                        continue
                    m = g.proj[i, li, v] @ g.view[i, li, v]
                    homo = torch.cat([pos[i], torch.ones(pos.shape[1], 1)], -1)
                    z = rasterize_depth((homo @ m.T)[None], faces, (48, 48))[0]
                    n, f = g.near[i, li, v], g.far[i, li, v]
                    if g.perspective:
                        lin = 2 * f * n / ((f + n) - z * (f - n))
                    else:
                        lin = (z * (f - n) + f + n) / 2
                    want = torch.where(torch.isfinite(z), lin, float("inf"))
                    assert torch.equal(got, want), (g.kind, i, li, v)


def test_vsm_maps_with_autograd_equal_maps_without():
    """The differentiable VSM path (rasterize + antialiased moments, straight through)
    gives the values of the no-grad path (rasterize_depth), up to rasterize's depth
    recomputation (~1e-6)."""
    pos, faces, bounds, view, proj = _scene()
    with torch.no_grad():
        plain = _groups("vsm", bounds, view, proj)
        render_shadow_maps(plain, pos, faces)
    grad_pos = pos.clone().requires_grad_(True)
    diff = _groups("vsm", bounds, view, proj)
    render_shadow_maps(diff, grad_pos, faces)
    for a, b in zip(plain, diff, strict=True):
        assert b.depth.requires_grad
        torch.testing.assert_close(b.depth.detach(), a.depth, atol=1e-5, rtol=0)


def test_key_depth_matches_its_definition():
    """Chunked (2**20 keys at a time) against ``bits = key >> 32``, the flip undone,
    ``+inf`` for EMPTY_KEY."""
    gen = torch.Generator().manual_seed(0)
    d = torch.cat([torch.randn(2**21 + 77, generator=gen) * 3,
                   torch.tensor([0.0, -0.0, 1.0, -1.0, float("inf"), -float("inf")])])
    faces = torch.randint(0, 2**31 - 1, d.shape, generator=gen, dtype=torch.int64)
    keys = depth_key(d) | faces
    keys[::5] = EMPTY_KEY
    bits = (keys >> 32).to(torch.int32)
    bits = bits ^ ((bits >> 31) & 0x7FFFFFFF)
    want = torch.where(keys == EMPTY_KEY, float("inf"), bits.view(torch.float32))
    for k in (keys, keys[:1000], keys[:2**21].view(1024, -1)[:, :1500]):
        got = key_depth(k)
        w = want[:k.numel()] if k.dim() == 1 else torch.where(
            k == EMPTY_KEY, float("inf"),
            ((k >> 32).to(torch.int32) ^ (((k >> 32).to(torch.int32) >> 31) & 0x7FFFFFFF)
             ).view(torch.float32))
        assert got.shape == k.shape and got.dtype == torch.float32
        assert torch.equal(got.view(torch.int32), w.reshape(k.shape).view(torch.int32))
    # finite depths round-trip
    fin = torch.isfinite(d) & (keys != EMPTY_KEY)
    assert torch.equal(key_depth(keys)[fin], d[fin])


@pytest.mark.parametrize("budget", [2**30, 48 * 48 * 16, 48 * 48 * 16 * 2])
def test_maps_rendered_in_place_and_in_bands_are_the_same(monkeypatch, budget):
    """Large maps go straight into the group's maps (``_map_rows``: no chunk buffer) and
    their depth is resolved in bands of rows (``DEPTH_BAND_PIXELS``); forced on 48² maps,
    every map is bit-identical to the ordinary path's (chunks of one view, of two, all)."""
    import importlib

    shadows = importlib.import_module("torchraster.shading.shadows")
    raster = importlib.import_module("torchraster.raster.rasterize")
    pos, faces, bounds, view, proj = _scene()
    groups = _groups("pcf", bounds, view, proj)
    render_shadow_maps(groups, pos, faces, memory_budget=budget)
    want = [g.depth.clone() for g in groups]
    calls = []
    direct = shadows._map_rows

    def spy(*args):
        got = direct(*args)
        calls.append(got is not None)
        return got

    monkeypatch.setattr(shadows, "DIRECT_MAP_TEXELS", 0)
    monkeypatch.setattr(shadows, "_map_rows", spy)
    monkeypatch.setattr(raster, "DEPTH_BAND_PIXELS", 48 * 20)
    groups = _groups("pcf", bounds, view, proj)
    render_shadow_maps(groups, pos, faces, memory_budget=budget)
    assert any(calls) == (budget < 2**30)  # one chunk of every group's views: not in place
    for a, g in zip(want, groups, strict=True):
        assert torch.equal(a, g.depth)
    assert sum(int(torch.isfinite(a).sum()) for a in want) > 1000


@pytest.mark.parametrize("perspective", [True, False])
def test_linear_depth_in_place_is_the_formula_bit_for_bit(perspective):
    """``_linear_depth_inplace`` (masks, large maps in 2**20-texel pieces) against the
    out-of-place ``_linear_depth`` on rasterize_depth-like input: [-1, 1] and +inf."""
    from torchraster.shading.shadows import _linear_depth, _linear_depth_inplace

    g = torch.Generator().manual_seed(3)
    for shape in ((3, 17, 23), (2, 1100, 1000)):  # the second is chunked
        ndc = torch.rand(shape, generator=g) * 2 - 1
        ndc[torch.rand(shape, generator=g) < 0.3] = float("inf")
        ndc[0, 0, :3] = torch.tensor([-1.0, 1.0, 0.0])
        near = torch.rand(shape[0], 1, 1, generator=g) + 0.1
        far = near + torch.rand(shape[0], 1, 1, generator=g) * 100
        want = _linear_depth(ndc, near, far, perspective)
        want = torch.where(torch.isfinite(ndc), want, torch.full_like(want, float("inf")))
        got = _linear_depth_inplace(ndc.clone(), near, far, perspective)
        assert torch.equal(got, want)
        assert torch.isposinf(got).sum() == torch.isposinf(ndc).sum()


@pytest.mark.parametrize("filt", ["pcf", "pcss", "hard"])
def test_lookups_recomputed_in_backward_equal_the_kept_graph(monkeypatch, filt):
    # with autograd, shadow_visibility checkpoints its receiver chunks: the same image and
    # gradients (positions, light positions) as keeping every chunk's graph, far fewer bytes
    # saved for backward
    from torchraster.shading import shadows

    pos, faces, _, view, proj = _scene()
    settings = ShadowSettings(map_size=48, filter=filt)
    renderer = tr.Renderer(24, shading="pbr", shadows=settings)

    def render():
        p = pos.clone().requires_grad_(True)
        light = torch.tensor([[[1.0, 2.0, 0.5], [0.2, 1.5, -0.3]]], requires_grad=True)
        lights = tr.Lights(point=tr.PointLights(
            light, torch.ones(1, 2, 3), torch.full((1, 2), 8.0),
            cast_shadows=torch.ones(1, 2, dtype=torch.bool), shadow=settings))
        saved = []

        def pack(t):
            saved.append(t.untyped_storage().nbytes())
            return t

        scene = tr.RenderScene(p, faces)
        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            image = renderer(scene, view, proj, lights).image
        grads = torch.autograd.grad((image * image).sum(), (p, light))
        return image.detach(), grads, sum(saved)

    monkeypatch.setattr(shadows, "RECOMPUTE_TAPS", 0)  # this small frame recomputes too
    image, grads, saved = render()
    monkeypatch.setattr(shadows, "checkpoint", lambda fn, *args, **kw: fn(*args))
    kept_image, kept_grads, kept_saved = render()
    assert torch.equal(image, kept_image)
    for a, b in zip(grads, kept_grads, strict=True):
        assert torch.equal(a, b)
    assert bool(grads[1].abs().sum() > 0)
    assert saved < 0.8 * kept_saved, (saved, kept_saved)
