"""Renderer(max_batch=...): a batch rendered in chunks equals the batch rendered at once.

The reference is the same Renderer without ``max_batch`` (one call over the whole batch);
values and per-item gradients must be bit-identical (torch.equal). Gradients of inputs
shared by every item are sums over the items, which the chunked path adds up in another
order: those are compared within float32 rounding.
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

import torchraster as tr
from torchraster.dissolve import Dissolve
from torchraster.shading.shadows import ShadowSettings

B = 5
RES = 40


def _setup(per_item_positions: bool = True):
    mesh = tr.load_spot(max_texture_size=64)
    scene = tr.RenderScene.from_mesh(mesh)
    g = torch.Generator().manual_seed(0)
    pos = mesh.positions
    if per_item_positions:  # each item its own deformation
        pos = pos + 0.02 * torch.randn(B, *pos.shape, generator=g)
    view = tr.camera.orbit(torch.arange(B) * 70.0, 15.0, 2.4)
    proj = tr.camera.perspective(45.0, 1.0, 0.1)
    lights = tr.Lights(
        ambient=0.05 * torch.rand(B, 9, 3, generator=g),
        point=tr.PointLights(position=torch.tensor([[2.0, 2.0, 3.0], [-2.0, 1.0, 1.0]]
                                                   ).expand(B, 2, 3).clone(),
                             color=torch.ones(B, 2, 3),
                             intensity=10 + 10 * torch.rand(B, 2, generator=g),
                             cast_shadows=torch.tensor([[True, False]]).expand(B, 2).clone(),
                             shadow=ShadowSettings(map_size=64)))
    return mesh, scene, pos, view, proj, lights


def _render(max_batch, scene, pos, view, proj, lights, channels=(), alpha_layers=4, **kw):
    raster = tr.RasterSettings(max_batch=max_batch, alpha_layers=alpha_layers)
    renderer = tr.Renderer(RES, **kw, raster=raster)
    sc = tr.RenderScene(**{**vars(scene), "positions": pos})
    return renderer(sc, view, proj, lights, channels=channels)


def test_chunked_forward_bit_identical():
    mesh, scene, pos, view, proj, lights = _setup()
    ch = {"depth", "normal", "face_id", "albedo"}
    ref = _render(None, scene, pos, view, proj, lights, ch)
    with torch.no_grad():
        out = _render(2, scene, pos, view, proj, lights, ch)
    assert out.plan.chunks == (2, 2, 1)
    assert "batch 5 in 3 chunks of <= 2" in out.plan
    assert ref.plan.chunks == ()
    assert ref.plan.shadow_maps and set(out.plan.shadow_maps) == set(ref.plan.shadow_maps)
    assert torch.equal(out.image, ref.image) and torch.equal(out.alpha, ref.alpha)
    assert set(out.gbuffer) == ch
    for k in ch:
        assert torch.equal(out.gbuffer[k], ref.gbuffer[k]), k
    assert float(ref.alpha.mean()) > 0.2  # the frame is not empty


def test_chunked_gradients():
    mesh, scene, pos, view, proj, lights = _setup()
    grads = []
    for max_batch in (None, 2):
        p = pos.clone().requires_grad_(True)
        inten = lights.point.intensity.clone().requires_grad_(True)
        amb = lights.ambient.clone().requires_grad_(True)
        lit = tr.Lights(ambient=amb, point=tr.PointLights(
            position=lights.point.position, color=lights.point.color, intensity=inten,
            cast_shadows=lights.point.cast_shadows, shadow=lights.point.shadow))
        out = _render(max_batch, scene, p, view, proj, lit)
        (out.image.square().sum() + out.alpha.sum()).backward()
        grads.append((out.image.detach(), p.grad, inten.grad, amb.grad))
    for a, b in zip(*grads, strict=True):  # all per-item: bit-identical
        assert torch.equal(a, b)
    assert grads[0][1].abs().sum() > 0


def test_chunked_shared_inputs_and_effects():
    """Shared (V, 3) positions and batch-1 lights; a per-item background image and dissolve
    threshold; mesh-list scenes (face_ranges)."""
    mesh, scene, pos, view, proj, lights = _setup(per_item_positions=False)
    shared = tr.Lights(point=tr.PointLights(position=torch.tensor([[[2.0, 2.0, 3.0]]]),
                                            color=torch.ones(1, 1, 3),
                                            intensity=torch.tensor([[20.0]])))
    bg = torch.rand(B, 3, 8, 8, generator=torch.Generator().manual_seed(1))
    kw = {"background": tr.BackgroundSettings(image=bg),
          "dissolve": Dissolve(threshold=torch.linspace(0.1, 0.6, B)),
          "alpha_layers": 2}
    outs = []
    for max_batch in (None, 3):
        p = pos.clone().requires_grad_(True)
        out = _render(max_batch, scene, p, view, proj, shared, **kw)
        out.image.square().sum().backward()
        outs.append((out, p.grad))
    (ref, g_ref), (out, g_out) = outs
    assert out.plan.chunks == (3, 2)
    assert torch.equal(out.image, ref.image) and torch.equal(out.alpha, ref.alpha)
    # the shared positions' gradient sums the items in another order: float rounding only
    assert torch.allclose(g_out, g_ref, rtol=1e-5, atol=1e-6 * float(g_ref.abs().max()))

    small = dataclasses.replace(mesh, positions=mesh.positions * 0.6)
    meshes = [mesh, small, mesh]  # face_ranges (3, 2)
    r_all = tr.Renderer(RES, shading="headlight")
    r_chunk = tr.Renderer(RES, shading="headlight", raster=tr.RasterSettings(max_batch=1))
    a = r_all(meshes, view[:3], proj)
    b = r_chunk(meshes, view[:3], proj)
    assert b.plan.chunks == (1, 1, 1)
    assert torch.equal(a.image, b.image)


def test_max_batch_errors():
    with pytest.raises(ValueError, match="max_batch"):
        tr.Renderer(16, raster=tr.RasterSettings(max_batch=0))
    with pytest.raises(ValueError, match="max_batch"):
        tr.Renderer(16, raster=tr.RasterSettings(max_batch=True))
    mesh = tr.load_spot(max_texture_size=16)
    env = tr.Environment(torch.rand(2, 3, 8, 16), intensity=torch.tensor([1.0, 2.0]))
    view = tr.camera.orbit(torch.tensor([0.0, 90.0]), 15.0, 2.4)
    proj = tr.camera.perspective(45.0, 1.0, 0.1)
    with pytest.raises(NotImplementedError, match="max_batch"):
        tr.Renderer(16, raster=tr.RasterSettings(max_batch=1))(mesh, view, proj, environment=env)
    # within max_batch nothing is split: the per-item environment works
    out = tr.Renderer(16, raster=tr.RasterSettings(max_batch=2))(mesh, view, proj, environment=env)
    assert out.plan.chunks == () and math.isfinite(float(out.image.sum()))
