"""Shadow lookups: the fast paths of ``shadow_visibility`` (padded maps gathered once per
call, int32 indices) against the general ones (unpadded maps), each receiver's view
transform against float64, the cube face against argmax, and a batch against its items one
by one."""

from __future__ import annotations

import dataclasses
import types

import pytest
import torch

import torchraster as tr
from torchraster.shading import shadows
from torchraster.shading.shadows import (
    ShadowSettings,
    directional_views,
    local_views,
    render_shadow_maps,
    shadow_visibility,
)
from torchraster.testing import raytrace as rt


def _setup(kind: str, filt: str, batch: int = 2, normal_bias: float = 0.0, lights: int = 2):
    verts, faces = rt.icosphere(0.5, (0.0, 0.5, 0.0), subdivisions=2)
    pos, faces, cast = rt.ground_scene([(verts, faces)], 4.0)
    pos = torch.stack([pos.float() + 0.05 * i for i in range(batch)])
    casters = faces[cast]
    bounds = torch.stack([pos.amin(1), pos.amax(1)], 1)
    view = tr.camera.look_at([0.0, 2.5, 4.0], [0.0, 0.3, 0.0]).expand(batch, 4, 4)
    proj = tr.camera.perspective(45.0, 1.0, 0.1).expand(batch, 4, 4)
    st = ShadowSettings(map_size=64, filter=filt, normal_bias=normal_bias,
                        cascades=2 if kind == "directional" else 1, pcf_taps=8)
    if kind == "directional":
        g = directional_views(torch.tensor([[[0.4, -1.0, 0.3], [-0.3, -1.0, 0.1]]])[:, :lights]
                              .expand(batch, lights, 3), st, bounds, view, proj)
    elif kind == "spot":  # one map per light
        pos_l = torch.tensor([[[1.0, 2.0, 0.5], [-0.8, 1.6, 0.2]]])[:, :lights] + torch.tensor(
            [0.3, 0.0, 0.0]) * torch.arange(batch)[:, None, None]  # each item its own
        g = local_views("spot", pos_l.expand(batch, lights, 3),
                        (torch.tensor([0.0, 0.5, 0.0]) - pos_l).expand(batch, lights, 3),
                        torch.full((batch, lights), 0.7), st, bounds)
    else:
        g = local_views("point", torch.tensor([[[1.0, 2.0, 0.5], [-0.8, 1.6, 0.2]]])[:, :lights]
                        .expand(batch, lights, 3), None, None, st, bounds)
    render_shadow_maps([g], pos, casters)
    # receivers: a grid on the floor and points on the sphere, facing up / outwards
    xs = torch.linspace(-1.5, 1.5, 24)
    gx, gz = torch.meshgrid(xs, xs, indexing="ij")
    p = torch.stack([gx, torch.zeros_like(gx), gz])[None].expand(batch, 3, 24, 24).clone()
    p[:, :, :4] = verts[:96].T.float().reshape(3, 4, 24)
    n = torch.zeros_like(p)
    n[:, 1] = 1
    n[:, :, :4] = torch.nn.functional.normalize(p[:, :, :4] - torch.tensor(
        [0.0, 0.5, 0.0])[:, None, None], dim=1)
    recv = torch.rand(batch, 1, 24, 24, generator=torch.Generator().manual_seed(0)) < 0.8
    return g, p, n, recv, view


@pytest.mark.parametrize("kind", ["point", "directional"])
@pytest.mark.parametrize("filt", ["hard", "pcf", "pcss", "vsm"])
@pytest.mark.parametrize("normal_bias", [0.0, 1.0])
def test_fast_paths_agree_with_general_ones(kind, filt, normal_bias, monkeypatch):
    # views: 1 x 1 x 6 (cube) or 1 x 2 x 2 (cascades)
    g, p, n, recv, view = _setup(kind, filt, batch=1, normal_bias=normal_bias,
                                 lights=1 if kind == "point" else 2)
    fast = shadow_visibility(g, p, n, recv, view)
    monkeypatch.setattr(shadows, "PAD_MAP_ELEMENTS", 0)
    general = shadow_visibility(g, p, n, recv, view)
    partial = ((general > 0.01) & (general < 0.99)).float().mean()
    assert partial > 0.01 or filt == "hard"  # penumbrae are looked up
    assert ((fast - general).abs() > 1e-3).float().mean() < 0.002  # float rounding only
    torch.testing.assert_close(fast, general, atol=0.02, rtol=0)


@pytest.mark.parametrize("kind", ["point", "directional", "spot"])
def test_batch_equals_items_one_by_one(kind):
    g, p, n, recv, view = _setup(kind, "pcf")
    both = shadow_visibility(g, p, n, recv, view)
    for i in range(2):
        one = shadows.ShadowMaps(
            g.kind, g.lights, g.settings, g.layout, g.view[i:i + 1], g.proj[i:i + 1],
            g.near[i:i + 1], g.far[i:i + 1], g.texel[i:i + 1], g.depth[i:i + 1],
            None if g.splits is None else g.splits[i:i + 1], g.rendered,
            None if g.light_position is None else g.light_position[i:i + 1],
            None if g.light_direction is None else g.light_direction[i:i + 1])
        alone = shadow_visibility(one, p[i:i + 1], n[i:i + 1], recv[i:i + 1], view[i:i + 1])
        torch.testing.assert_close(both[i:i + 1], alone, atol=1e-5, rtol=0)
        assert (both[i:i + 1][~recv[i:i + 1, None].expand_as(alone)] == 1).all()


@pytest.mark.parametrize("translate", [True, False])
def test_affine_is_each_pairs_own_matrix(translate):
    """Each (receiver, light) pair transformed by its own view's matrix, against float64
    matrix products (and a batch of pairs gives each pair the bits it gets alone)."""
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(500, 3, generator=gen) * 10
    for m in (1, 6, 24):
        mats = torch.randn(m, 4, 4, generator=gen)
        sel = torch.randint(0, m, (500, 2), generator=gen)
        got = shadows._affine(mats, x, sel, translate)
        homo = torch.cat([x, torch.full_like(x[:, :1], float(translate))], 1).double()
        want = (mats.double()[sel] @ homo[:, None, :, None])[..., 0]
        torch.testing.assert_close(got.double(), want, rtol=1e-5, atol=1e-4)
        assert torch.equal(shadows._affine(mats, x[7:8], sel[7:8], translate), got[7:8])


def test_cube_face_is_the_dominant_axis_with_argmax_ties():
    d = torch.tensor([[1.0, 1.0, 1.0], [-2.0, 2.0, 0.0], [0.0, -3.0, 3.0], [0.5, 0.1, -0.7],
                      [-0.0, 0.0, 0.0], [4.0, -4.0, 1.0]])
    g = types.SimpleNamespace(layout="cube", view=torch.zeros(1, 1, 6, 4, 4),
                              light_position=torch.zeros(1, 1, 3))
    face, _ = shadows._select_view(g, d, torch.zeros(6, dtype=torch.int64), None)
    axis = d.abs().argmax(-1)
    want = axis * 2 + (d.gather(1, axis[:, None])[:, 0] < 0).long()
    assert torch.equal(face[:, 0], want)


@pytest.mark.parametrize("filt", ["pcf", "pcss"])
def test_culled_views_read_one_shared_empty_slot(filt, monkeypatch):
    # render_shadow_maps leaves views nobody reads (culled cube faces) at +inf; the padded
    # copy holds only the rendered maps and one +inf slot for the rest: the same bits as
    # padding every map, and the unpadded lookup up to float rounding
    g, p, n, recv, view = _setup("point", filt)
    needed = torch.zeros(g.view.shape[:3], dtype=torch.bool)
    needed[0, 0, :3] = needed[1, 1, 2:] = True  # 7 of 24 maps
    g.depth = torch.where(needed[..., None, None], g.depth, float("inf"))
    padded, slot = shadows._pad_rendered_maps(dataclasses.replace(g, needed=needed))
    sp = g.settings.map_size + 4
    assert padded.numel() == 8 * sp * sp  # 7 rendered maps and the empty slot
    assert slot.view(2, 2, 6)[needed].tolist() == list(range(7))
    assert bool((slot.view(2, 2, 6)[~needed] == 7).all())
    compact = shadow_visibility(dataclasses.replace(g, needed=needed), p, n, recv, view)
    every = shadow_visibility(g, p, n, recv, view)  # every map padded
    assert torch.equal(compact, every)
    monkeypatch.setattr(shadows, "PAD_MAP_ELEMENTS", 0)
    general = shadow_visibility(dataclasses.replace(g, needed=needed), p, n, recv, view)
    torch.testing.assert_close(compact, general, atol=0.02, rtol=0)


@pytest.mark.parametrize("filt", ["pcf", "pcss"])
def test_lights_looked_up_in_slices_that_fit_the_padding_bound(filt, monkeypatch):
    # when the rendered maps of all lights padded exceed PAD_MAP_ELEMENTS, the lights are
    # looked up in slices whose padded maps fit (padded lookups, not the unpadded ones):
    # the same bits as all lights at once
    g, p, n, recv, view = _setup("point", filt)  # 2 lights x 2 items x 6 faces of 64²
    once = shadow_visibility(g, p, n, recv, view)
    one_light = (12 + 1) * 68 * 68  # a light's 12 maps padded and the empty slot
    monkeypatch.setattr(shadows, "PAD_MAP_ELEMENTS", one_light)
    assert shadows._light_slices(g) == [slice(0, 1), slice(1, 2)]
    sliced = shadow_visibility(g, p, n, recv, view)
    assert torch.equal(sliced, once)
    monkeypatch.setattr(shadows, "PAD_MAP_ELEMENTS", one_light - 1)  # nothing fits:
    assert shadows._light_slices(g) == [slice(0, 1), slice(1, 2)]  # unpadded, by light
    torch.testing.assert_close(shadow_visibility(g, p, n, recv, view), once, atol=0.02,
                               rtol=0)


@pytest.mark.parametrize("kind", ["point", "directional", "spot"])
@pytest.mark.parametrize("filt", ["hard", "pcf", "pcss", "vsm"])
def test_receiver_chunks_give_the_same_bits(kind, filt, monkeypatch):
    # receivers are looked up in chunks of TAP_CHUNK_ELEMENTS receiver-light-tap corners
    # (cache-sized); chunks of 1 to 7 receivers, straddling nothing, give the same bits
    g, p, n, recv, view = _setup(kind, filt)
    whole = shadow_visibility(g, p, n, recv, view)
    taps = {"hard": 1, "vsm": 1, "pcf": 8, "pcss": 16}[filt]
    for receivers in (1, 7):
        monkeypatch.setattr(shadows, "TAP_CHUNK_ELEMENTS", receivers * 2 * taps * 4)
        assert torch.equal(shadow_visibility(g, p, n, recv, view), whole)
