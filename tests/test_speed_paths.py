"""The fast paths of issue 10 agree with the plain ones they replace.

* occlusion culling of hidden back faces (rasterize.OCCLUSION_CULLING) leaves every key,
  face id, barycentric and depth bit for bit unchanged;
* the per-pixel pass (a custom autograd Function with a closed-form backward) and the fused
  interpolation have exact gradients, with and without screen-space derivatives;
* the fused Cook-Torrance lighting pass equals the generic model path (values and
  gradients), dense and sparse, with checkpointing, visibility and views from below;
* image-based lighting: the chunked irradiance map equals one big product, f0 = 0 skips the
  specular chain, and environments are shared by content.
"""

from __future__ import annotations

import importlib
import math

import pytest
import torch
import trimesh

import torchraster as tr
from torchraster.config import lights_from_config
from torchraster.gbuffer import GBuffer
from torchraster.raster.interpolate import interpolate_packed
from torchraster.shading import ibl, lighting
from torchraster.shading.models import cook_torrance
from torchraster.testing.reference_raster import random_soup

rasterize_module = importlib.import_module("torchraster.raster.rasterize")
F64 = torch.float64


def _sphere_clip(b: int = 2, subdiv: int = 3, dtype: torch.dtype = torch.float32):
    mesh = trimesh.creation.icosphere(subdivisions=subdiv)
    verts = torch.tensor(mesh.vertices, dtype=dtype)
    faces = torch.tensor(mesh.faces, dtype=torch.int64)
    view = tr.camera.orbit(torch.linspace(0.0, 300.0, b), torch.linspace(-40.0, 50.0, b),
                           torch.full((b,), 2.6))
    proj = tr.camera.perspective(45.0, 1.0, 0.1)
    return tr.camera.transform_points(verts, (proj @ view).to(dtype)), faces, verts


def _keys(clip, faces, res, **kw):
    return rasterize_module.resolve_keys(clip, faces, res, kw.get("cull", False), None,
                                         kw.get("tile", 16), 2**20, 320)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_block_classification_matches_per_centre_tests(dtype: torch.dtype) -> None:
    """Interior-block acceptance of large triangles (binning._classify_blocks, an (R, S)
    broadcast): a block called full has every centre pass the per-centre edge test of
    covered_keys, and a block called empty has none; checked centre by centre on random
    triangles (slivers, huge ones, vertices on pixel centres) and blocks."""
    from torchraster.raster import binning
    from torchraster.raster.clip import ScreenTriangles

    gen = torch.Generator().manual_seed(3)
    n, s = 400, binning.SUB_BLOCK
    pos = torch.rand(3, 3, n, generator=gen, dtype=F64) * 96 - 16
    pos[:2, :, : n // 4] = pos[:2, :, : n // 4].round()  # vertices on pixel centres
    pos[:2, 2, n // 4: n // 2] = (pos[:2, 0, n // 4: n // 2] + pos[:2, 1, n // 4: n // 2]) / 2 \
        + 1e-3 * torch.rand(2, n // 4, generator=gen, dtype=F64)  # slivers
    pos = pos.to(dtype)
    x, y = pos[0], pos[1]
    area = (x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0])
    tris = ScreenTriangles(pos=pos, area=area, box=torch.zeros(4, n, dtype=torch.int64),
                           face=torch.arange(n), batch=torch.zeros(n, dtype=torch.int64))
    coef = binning.setup_triangles(tris).coef
    ox = torch.randint(-8, 72, (n, 6), generator=gen)
    oy = torch.randint(-8, 72, (n, 6), generator=gen)
    full, may = binning._classify_blocks(coef, ox.to(dtype), oy.to(dtype), s)
    # per-centre test: the same float ops as covered_keys (block_edge vs EDGE_MIN)
    d = torch.arange(s)
    px = (ox[:, :, None] + d).to(dtype)  # (n, 6, s) columns
    py = (oy[:, :, None] + d).to(dtype)
    inside = torch.ones(n, 6, s, s, dtype=torch.bool)
    for e in range(3):
        a, b = coef[binning.EDGE_A][e][:, None, None], coef[binning.EDGE_B][e][:, None, None]
        c, t = coef[binning.EDGE_C][e][:, None, None, None], coef[binning.EDGE_MIN][e]
        edge = (b * py + c[..., 0])[..., :, None] + (a * px)[..., None, :]
        inside &= edge >= t[:, None, None, None]
    count = inside.sum((2, 3))
    assert bool((count[full] == s * s).all())
    assert bool((count[~may] == 0).all())
    # not vacuous: all three kinds occur
    assert int(full.sum()) > 50 and int((~may).sum()) > 50 and int((may & ~full).sum()) > 50


@pytest.mark.parametrize("case", ["sphere", "soup", "soup_tile4", "big_triangles",
                                  "subpixel"])
def test_occlusion_culling_changes_nothing(case: str, monkeypatch) -> None:
    gen = torch.Generator().manual_seed(5)
    tile = 4 if case == "soup_tile4" else 16
    if case == "sphere":
        clip, faces, _ = _sphere_clip()
        res = (40, 56)
    elif case == "subpixel":  # back faces' boxes of one pixel: a mean box side of 0
        clip, faces, _ = _sphere_clip(b=2, subdiv=5)
        res = (24, 20)
    elif case == "big_triangles":  # a few huge faces in front of and behind others
        clip, faces, _ = random_soup(gen, 2, 12, weights=(1, 0, 0, 0, 0, 0))
        clip = clip.float() * torch.tensor([4.0, 4.0, 1.0, 1.0])
        res = (48, 48)
    else:
        clip, faces, _ = random_soup(gen, 2, 300)
        clip = clip.float()
        res = (37, 45)
    monkeypatch.setattr(rasterize_module, "OCCLUSION_CULLING", True)
    monkeypatch.setattr(rasterize_module, "OCCLUSION_MIN_WORK", 0)  # even small scenes
    with_cull = _keys(clip, faces, res, tile=tile)
    frags = tr.rasterize(clip, faces, res, tile=tile)
    depth = tr.raster.rasterize_depth(clip, faces, res, tile=tile)
    monkeypatch.setattr(rasterize_module, "OCCLUSION_CULLING", False)
    plain = _keys(clip, faces, res, tile=tile)
    ref = tr.rasterize(clip, faces, res, tile=tile)
    assert torch.equal(with_cull, plain)
    assert torch.equal(frags.face_id, ref.face_id)
    assert torch.equal(frags.bary, ref.bary) and torch.equal(frags.depth, ref.depth)
    assert torch.equal(depth, tr.raster.rasterize_depth(clip, faces, res, tile=tile))
    assert (frags.face_id >= 0).any()


def _plane_and_back_faces(gen: torch.Generator, b: int, n: int) -> tuple[torch.Tensor,
                                                                        torch.Tensor]:
    """A front-facing plane at NDC depth 0.5 over the frame above a slanted line, and ``n``
    small back faces per item around that line at depths within 1e-3 of the plane (a
    quarter of them in front of it): those behind it are hidden above the line and visible
    below it. An occlusion test that is too bold by 1e-5 of depth, or misses a tile of a
    box, drops a visible face here."""
    plane = torch.tensor([[-1.0, -0.5, 0.5, 1.0], [1.0, 0.3, 0.5, 1.0], [1.0, 1.0, 0.5, 1.0],
                          [-1.0, 1.0, 0.5, 1.0]])
    x = torch.rand(b, n, 1, 1, generator=gen) * 2.2 - 1.1
    y = -0.1 + 0.4 * x + 0.2 * torch.randn(b, n, 1, 1, generator=gen)  # about the line
    size = 0.02 + 0.2 * torch.rand(b, n, 1, 1, generator=gen)
    # right triangles with the right angle at any of the four corners, clockwise in NDC
    flip = torch.randint(0, 2, (b, n, 1, 2), generator=gen) * 2 - 1
    corner = torch.tensor([[0.0, 0.0], [0.0, 1.0], [1.0, 0.0]]) * flip
    odd = (flip.prod(-1) < 0).squeeze(-1)  # one axis flipped: the winding too, so swap
    corner[odd] = corner[odd][:, [0, 2, 1]]
    xy = torch.cat([x, y], -1) + size * corner
    z = 0.5 + 1e-3 * (torch.rand(b, n, 1, 1, generator=gen) - 0.25) + 1e-4 * torch.rand(
        b, n, 3, 1, generator=gen)
    tris = torch.cat([xy, z, torch.ones_like(z)], -1).view(b, 3 * n, 4)
    clip = torch.cat([plane.expand(b, -1, -1), tris], 1)
    quarter = torch.tensor([[0.0, 1.0], [-1.0, 0.0]])  # a rotation: windings stay
    for item in range(b):  # item k turned by k quarter turns: the line runs every way
        clip[item, :, :2] = clip[item, :, :2] @ torch.linalg.matrix_power(quarter, item % 4)
    faces = torch.cat([torch.tensor([[0, 1, 2], [0, 2, 3]]), 4 + torch.arange(3 * n).view(n, 3)])
    return clip, faces


@pytest.mark.parametrize("case", ["soup", "plane"])
def test_occlusion_culls_only_hidden_triangles(case: str, monkeypatch) -> None:
    """Every back face the occlusion test drops (rasterize._visible_subset) is hidden: each
    of its keys, rasterized alone, is larger than the final key of its pixel; and it drops
    many (400 of them checked). A direct check of the test's soundness, independent of
    whether a wrongly dropped face would have changed the picture (on a closed mesh no
    back face is ever visible, so none can be dropped wrongly there)."""
    gen = torch.Generator().manual_seed(4)
    if case == "soup":
        clip, faces, _ = random_soup(gen, 2, 2000, weights=(1, 0.2, 0, 0, 0, 0))
        clip, res = clip.float(), (67, 80)
    else:
        clip, faces = _plane_and_back_faces(gen, 8, 300)
        res = (91, 100)
    dropped = []
    orig = rasterize_module._visible_subset

    def spy(screen, idx, keys, shape, tile):
        out = orig(screen, idx, keys, shape, tile)
        gone = torch.ones(len(screen), dtype=torch.bool)
        gone[out] = False
        gone = idx[gone[idx]]
        dropped.append(torch.stack([screen.batch[gone], screen.face[gone]]))
        return out

    monkeypatch.setattr(rasterize_module, "OCCLUSION_MIN_WORK", 0)
    monkeypatch.setattr(rasterize_module, "_visible_subset", spy)
    final = _keys(clip, faces, res)[0].view(clip.shape[0], -1)
    pairs = torch.cat(dropped, 1).unique(dim=1)
    assert pairs.shape[1] > 100
    monkeypatch.setattr(rasterize_module, "OCCLUSION_CULLING", False)
    for item, face in pairs.T[torch.randperm(pairs.shape[1], generator=gen)[:400]].tolist():
        alone = _keys(clip[item:item + 1], faces[face:face + 1], res)[0]
        hit = alone != rasterize_module.EMPTY_KEY
        key = (alone[hit] >> 32 << 32) | face
        assert (key > final[item][hit]).all(), (item, face)


@pytest.mark.parametrize("case", ["soup64", "soup32_tile12", "sphere_layers", "small_budget"])
def test_ragged_pass_equals_block_passes(case: str, monkeypatch) -> None:
    """The ragged pass over runs of few candidates (rasterize.ragged_keys: every block shape
    in one candidate list) gives bit for bit the keys of one broadcast pass per block shape
    (covered_keys): random soups in float32 and float64, a tile that is not a power of two
    (blocks clamped at the image border), depth layers, and a tiny memory budget (many
    ragged chunks)."""
    gen = torch.Generator().manual_seed(11)
    tile, layers, budget = 16, 1, 2**20
    if case == "sphere_layers":
        clip, faces, _ = _sphere_clip(b=2, subdiv=3)
        res, layers = (52, 44), 2
    else:
        clip, faces, _ = random_soup(gen, 2, 400)
        clip = clip if case == "soup64" else clip.float()
        res = (37, 45)
        tile = 12 if case == "soup32_tile12" else 16
        budget = 2**14 if case == "small_budget" else budget

    def keys() -> torch.Tensor:
        return rasterize_module.resolve_keys(clip, faces, res, False, None, tile, budget,
                                             320, layers=layers)

    calls = []
    orig = rasterize_module.ragged_keys

    def spy(setup, runs, *args):
        for found in orig(setup, runs, *args):
            calls.append(found[0].numel())
            yield found

    monkeypatch.setattr(rasterize_module, "ragged_keys", spy)
    monkeypatch.setattr(rasterize_module, "RAGGED_RUN_CANDIDATES", 2**40)  # every run
    ragged = keys()
    assert len(calls) >= (4 if case == "small_budget" else 1) and sum(calls) > 100
    monkeypatch.setattr(rasterize_module, "RAGGED_RUN_CANDIDATES", 0)  # never
    calls.clear()
    plain = keys()
    assert not calls
    assert torch.equal(ragged, plain)
    assert (plain[-1] != rasterize_module.EMPTY_KEY).any()


@pytest.mark.parametrize("shape,tile", [((2, 37, 45), 4), ((1, 64, 64), 4), ((3, 9, 70), 2),
                                        ((1, 33, 16), 8)])
def test_tile_maxima_bound_every_box(shape, tile) -> None:
    """The occlusion test's lookup (rasterize._box_maxima: rasterize._tile_maxima read at a
    box's four corners, at the finest level whose tiles are larger than its side - 1) is
    exactly the largest depth of the keys in the tiles the box touches, so at least that
    of the box, for boxes of every side, position and item (brute force); empty pixels
    read +inf."""
    b, h, w = shape
    gen = torch.Generator().manual_seed(2)
    depth = torch.rand(b, h, w, generator=gen) * 2 - 1
    depth[torch.rand(b, h, w, generator=gen) < 0.05] = float("inf")  # empty pixels
    keys = rasterize_module.depth_key(depth) | torch.randint(0, 99, (b, h, w), generator=gen)
    keys[depth == float("inf")] = rasterize_module.EMPTY_KEY
    maxima, by_extent = rasterize_module._tile_maxima(keys, tile)
    n = 3000
    item = torch.randint(0, b, (n,), generator=gen)
    side = (torch.rand(n, generator=gen) ** 2 * max(h, w)).long().clamp(min=1)
    x0 = (torch.rand(n, generator=gen) * (w - side.clamp(max=w) + 1)).long()
    y0 = (torch.rand(n, generator=gen) * (h - side.clamp(max=h) + 1)).long()
    x1, y1 = (x0 + side - 1).clamp(max=w - 1), (y0 + side - 1).clamp(max=h - 1)
    ext = torch.maximum(x1 - x0, y1 - y0)
    got = rasterize_module._box_maxima(maxima, by_extent, torch.stack([x0, x1, y0, y1]), ext,
                                       item)
    s = by_extent[0][ext]  # log2 of the level's tile side
    # the finest level whose tiles hold the box's side - 1
    assert ((2 ** s >= ext) & ((2 ** s == tile) | (2 ** s < 2 * ext))).all()
    for k in range(n):
        t = 2 ** int(s[k])  # the level's tile side
        ty0, tx0 = int(y0[k]) // t * t, int(x0[k]) // t * t
        ty1, tx1 = int(y1[k]) // t * t + t, int(x1[k]) // t * t + t
        assert ty1 - ty0 <= 2 * t and tx1 - tx0 <= 2 * t
        assert got[k] == depth[item[k], ty0:ty1, tx0:tx1].max()
        assert got[k] >= depth[item[k], y0[k]:y1[k] + 1, x0[k]:x1[k] + 1].max()


@pytest.mark.parametrize("res,tile", [((37, 45), 16), ((64, 64), 4), ((20, 90), 12), ((9, 9), 16),
                                      ((5, 30), 16)])
def test_tested_boxes_hold_every_binned_centre(res, tile) -> None:
    """binning.tested_boxes (the occlusion test's box per triangle) holds every pixel centre
    that bin_triangles hands to the coverage test, for small and large triangles, blocks
    clamped at the frame's edge and tiles that are not powers of two."""
    from torchraster.raster import binning
    from torchraster.raster import clip as clip_mod

    gen = torch.Generator().manual_seed(8)
    pos, faces, _ = random_soup(gen, 2, 400)
    pos = pos.float() * torch.tensor([1.5, 1.5, 1.0, 1.0])
    h, w = res
    b = pos.shape[0]
    screen = clip_mod.clip_and_project(
        pos, clip_mod.project(pos, res).view(-1, 3).T.contiguous(), clip_mod.outcodes(pos),
        faces.T.contiguous(), torch.arange(faces.shape[0]).repeat(b),
        torch.arange(b).repeat_interleave(faces.shape[0]), res, False)
    screen, runs, n_small = binning.sort_by_block(screen, res, tile)
    setup = binning.setup_triangles(screen)
    boxes = binning.tested_boxes(setup.box, res, tile)
    seen = torch.zeros(len(screen), dtype=torch.bool)
    for rec in binning.bin_triangles(setup, runs, n_small, res, tile, 2**12):
        tri = torch.arange(len(screen))[rec.tri]
        seen[tri] = True
        box = boxes[:, tri]
        assert (rec.x0 >= box[0]).all() and (rec.x0 + rec.kw - 1 <= box[1]).all()
        assert (rec.y0 >= box[2]).all() and (rec.y0 + rec.kh - 1 <= box[3]).all()
    # not vacuous: small triangles are all binned, and some large ones (others may lie in
    # tiles an edge proves empty)
    assert seen[:n_small].all() and (seen[n_small:].any() or max(res) <= tile)


def test_triangle_chunks_keep_items_whole() -> None:
    """Triangle chunks (rasterize._triangle_chunks) list every (item, face) pair once, in
    order, hold at most the budget, and split an item only when it is larger than that."""
    for counts, per in [([10, 10, 10], 25), ([3, 3, 3, 3], 7), ([1000, 10, 500], 300),
                        ([5, 0, 5], 5), ([7], 7)]:
        b, total = len(counts), sum(counts)
        starts = torch.tensor([sum(counts[:i]) for i in range(b)])
        ranges = torch.stack([starts, starts + torch.tensor(counts)], 1)
        chunks = list(rasterize_module._triangle_chunks(b, total, ranges, "cpu", per))
        pairs = [(int(i), int(f)) for bi, fi in chunks for i, f in zip(bi, fi, strict=True)]
        assert pairs == [(i, f) for i in range(b) for f in range(starts[i], starts[i] + counts[i])]
        assert all(0 < bi.numel() <= per for bi, _ in chunks)
        for item, count in enumerate(counts):
            holding = sum(bool((bi == item).any()) for bi, _ in chunks)
            assert holding == (0 if count == 0 else -(-count // per) if count > per else 1)


def test_occlusion_culling_skips_hidden_back_faces(monkeypatch) -> None:
    """On a closed sphere most back faces are proven hidden and never binned (when their
    boxes hold enough centres to pay for the test: rasterize.OCCLUSION_MIN_WORK)."""
    clip, faces, _ = _sphere_clip(b=1, subdiv=4)
    seen = {}
    orig = rasterize_module._visible_subset

    def spy(screen, idx, keys, shape, tile):
        out = orig(screen, idx, keys, shape, tile)
        seen["in"] = seen.get("in", 0) + idx.numel()
        seen["out"] = seen.get("out", 0) + out.numel()
        return out

    monkeypatch.setattr(rasterize_module, "_visible_subset", spy)
    tr.rasterize(clip, faces, (256, 256))
    assert not seen, "a small scene's back faces are binned without the occlusion test"
    tr.rasterize(clip, faces, (1024, 1024))
    assert seen["in"] > 1000 and seen["out"] < 0.5 * seen["in"]


def test_pixel_pass_and_fused_interpolation_gradients() -> None:
    clip = torch.tensor([[[-0.8, -0.7, 0.1, 1.0], [0.9, -0.5, 0.3, 1.4], [0.1, 0.8, -0.2, 0.9],
                          [-0.9, 0.6, 0.5, 1.1], [0.7, 0.9, 0.2, 2.0]]], dtype=F64)
    clip = torch.cat([clip, clip * torch.tensor([1.1, 0.9, 1.0, 1.05], dtype=F64)])
    faces = torch.tensor([[0, 1, 2], [2, 4, 3], [0, 2, 3]])
    attrs = torch.randn(2, 5, 2, dtype=F64)
    res = (7, 6)

    def with_derivatives(c, a):
        frags = tr.rasterize(c, faces, res, derivatives=True)
        value, ddx, ddy = tr.interpolate_with_derivatives(a, frags, faces)
        return value, ddx, ddy, frags.depth.nan_to_num(posinf=0.0), frags.bary_dx

    def shared_attrs(c, a):
        return tr.interpolate(a, tr.rasterize(c, faces, res), faces)

    def packed(c, a):
        return interpolate_packed(a, tr.rasterize(c, faces, res, derivatives=True), True)

    c = clip.clone().requires_grad_()
    assert torch.autograd.gradcheck(with_derivatives, (c, attrs.clone().requires_grad_()))
    assert torch.autograd.gradcheck(shared_attrs, (c, attrs[0].clone().requires_grad_()))
    assert torch.autograd.gradcheck(packed, (c, attrs.clone().requires_grad_()))


def test_fused_interpolation_matches_per_pixel_corners() -> None:
    """The per-face-row path equals gathering every pixel's corners (Fragments by hand)."""
    clip, faces, verts = _sphere_clip(b=3, subdiv=2, dtype=F64)
    frags = tr.rasterize(clip, faces, (24, 20), derivatives=True)
    attrs = torch.randn(3, verts.shape[0], 4, dtype=F64)
    manual = tr.raster.Fragments(frags.face_id, frags.pixels, frags.items, frags.corners,
                                 frags.bary_packed, frags.depth_packed, frags.bary_dx_packed,
                                 frags.bary_dy_packed)
    for a in (attrs, attrs[0]):
        fast = tr.interpolate_with_derivatives(a, frags, faces)
        slow = tr.interpolate_with_derivatives(a, manual, faces)
        for x, y in zip(fast, slow, strict=True):
            torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-14)
    assert torch.equal(frags.items, frags.pixels // (24 * 20))
    assert torch.equal(frags.corners, faces[frags.face_id.view(-1)[frags.pixels]].T)


def _gbuffer(h: int = 10, w: int = 12, b: int = 2, seed: int = 3):
    g = torch.Generator().manual_seed(seed)
    pos = torch.randn(b, 3, h, w, generator=g, dtype=F64) * 0.5
    nrm = torch.randn(b, 3, h, w, generator=g, dtype=F64)  # some face away from the eye
    albedo = torch.rand(b, 3, h, w, generator=g, dtype=F64)
    metal = torch.rand(b, 1, h, w, generator=g, dtype=F64)
    rough = torch.rand(b, 1, h, w, generator=g, dtype=F64)
    mask = torch.rand(b, 1, h, w, generator=g) > 0.2
    return pos, nrm, albedo, metal, rough, mask


LIGHTS = [
    {"type": "point", "position": [1.0, 1.5, 2.0], "intensity": 5.0, "range": 3.0},
    {"type": "point", "position": [-1.0, 0.2, 1.0], "intensity": 3.0, "color": [1, 0.5, 0.2]},
    {"type": "spot", "position": [0, 0, 2], "direction": [0.1, 0, -1], "intensity": 9.0,
     "inner_cone_angle": 0.2, "outer_cone_angle": 0.6, "range": 4.0},
    {"type": "directional", "direction": [-1, -0.5, -1], "intensity": 2.0},
    {"type": "directional", "direction": [1, 0.2, -0.3], "intensity": 1.0},
]


@pytest.mark.parametrize("sparse", [0.0, 1.0])
@pytest.mark.parametrize("ckpt", [None, True])
def test_fused_lighting_matches_generic_model(sparse: float, ckpt, monkeypatch) -> None:
    monkeypatch.setattr(lighting, "SPARSE_FRACTION", sparse)
    pos, nrm, albedo, metal, rough, mask = _gbuffer()
    lights = lights_from_config(LIGHTS, batch=2, dtype=F64)
    eye = torch.tensor([[0.0, 0.0, 3.0], [0.5, 1.0, 2.5]], dtype=F64)

    def vis(kind, sl):
        return torch.linspace(0.0, 1.0, 2 * 10 * 12, dtype=F64).view(2, 1, 1, 10, 12).expand(
            2, sl.stop - sl.start, 1, 10, 12)

    def run(model, rough_in, light_chunk=None):
        gb = GBuffer(position=pos, normal=nrm, albedo=albedo, metallic=metal,
                     roughness=rough_in, mask=mask)
        # multiscatter=False: the generic model is the single-scattering BRDF
        return lighting.shade(gb, camera_position=eye, lights=lights, model=model,
                              visibility=vis, light_chunk=light_chunk, checkpoint_chunks=ckpt,
                              multiscatter=False)

    def generic(n, v, l, surface):  # same BRDF, through the per-light generic path
        return cook_torrance(n, v, l, surface)

    outs, grads = [], []
    for model, chunk in ((generic, None), ("cook_torrance", None), ("cook_torrance", 1)):
        r = rough.clone().requires_grad_()
        out = run(model, r, chunk)
        out.square().sum().backward()
        outs.append(out.detach())
        grads.append(r.grad)
    for o, g in zip(outs[1:], grads[1:], strict=True):
        torch.testing.assert_close(o, outs[0], rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(g, grads[0], rtol=1e-8, atol=1e-10)
    assert (outs[0] > 0).any()


def test_fused_lighting_gradcheck_lights_and_geometry() -> None:
    pos, nrm, albedo, metal, rough, mask = _gbuffer(3, 4, 1)
    eye = torch.tensor([[0.0, 0.0, 3.0]], dtype=F64)
    base = lights_from_config(LIGHTS, dtype=F64)

    def fn(position, intensity, normal, direction):
        point = base.point
        lights = tr.Lights(
            point=tr.PointLights(position, point.color, intensity, point.range),
            spot=base.spot,
            directional=tr.DirectionalLights(direction, base.directional.color,
                                             base.directional.intensity))
        gb = GBuffer(position=pos, normal=normal, albedo=albedo, metallic=metal,
                     roughness=rough, mask=mask)
        return lighting.shade(gb, camera_position=eye, lights=lights)

    args = (base.point.position.clone(), base.point.intensity.clone(), nrm.clone(),
            base.directional.direction.clone())
    assert torch.autograd.gradcheck(fn, tuple(a.requires_grad_() for a in args))


def test_irradiance_map_chunks_match_one_product(monkeypatch) -> None:
    env = torch.rand(2, 3, 16, 32, dtype=F64)
    whole = ibl.irradiance_map(env, height=8, source_height=None)
    monkeypatch.setattr(ibl, "QUADRATURE_CHUNK", 700)  # many uneven chunks
    torch.testing.assert_close(ibl.irradiance_map(env, height=8, source_height=None), whole,
                               rtol=1e-12, atol=1e-12)
    const = ibl.irradiance_map(torch.ones(1, 3, 32, 64, dtype=F64), height=8,
                               source_height=None)
    torch.testing.assert_close(const, torch.full_like(const, math.pi), rtol=2e-3, atol=0)
    grad_env = torch.rand(1, 3, 4, 8, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda e: ibl.irradiance_map(e, height=2, source_height=None), (grad_env,))


def test_zero_f0_skips_the_specular_chain() -> None:
    env = ibl.Environment(torch.rand(3, 16, 32, dtype=F64) + 0.1)
    n = torch.randn(1, 3, 4, 5, dtype=F64)
    v = torch.randn(1, 3, 4, 5, dtype=F64)
    albedo = torch.rand(1, 3, 4, 5, dtype=F64)
    zero = torch.zeros(1, 1, 4, 5, dtype=F64)
    rough = torch.rand(1, 1, 4, 5, dtype=F64)
    out = ibl.shade_ibl(n, v, albedo, zero, rough, None, env, f0_dielectric=0.0)
    assert env._spec is None  # never prefiltered
    spec_on = ibl.shade_ibl(n, v, albedo, zero, rough, None, env, f0_dielectric=1e-30)
    torch.testing.assert_close(out, spec_on, rtol=1e-12, atol=1e-12)
    assert env._spec is not None


def test_environments_are_shared_by_content(monkeypatch) -> None:
    monkeypatch.setattr(ibl, "_ENV_CACHE", ibl._ContentCache())
    radiance = torch.rand(3, 16, 32)
    a, b = ibl.Environment(radiance), ibl.Environment(radiance.clone())
    assert a.specular_chain is b.specular_chain
    assert a.irradiance_latlong is b.irradiance_latlong
    other = ibl.Environment(radiance + 1e-3)
    assert other.specular_chain is not a.specular_chain
    knobs = ibl.Environment(radiance, specular_levels=4)
    assert len(knobs.specular_chain) == 4
    grad = ibl.Environment(radiance.clone().requires_grad_())
    assert grad.specular_chain is not a.specular_chain and grad.specular_chain[1].requires_grad
    monkeypatch.setattr(ibl, "ENV_CACHE_BYTES", 0)
    assert ibl.Environment(radiance).specular_chain is not a.specular_chain


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_and_per_edge_tests_agree(dtype: torch.dtype, monkeypatch) -> None:
    """covered_keys tests the three edges in one broadcast for small chunks and one edge at
    a time for large ones: bit-identical keys either way (soup with slivers and shared
    edges, and a sphere)."""
    gen = torch.Generator().manual_seed(21)
    soup, soup_faces, _ = random_soup(gen, 2, 300)
    sphere, sphere_faces, _ = _sphere_clip(b=2, subdiv=3)
    for clip, faces in ((soup.to(dtype), soup_faces), (sphere.to(dtype), sphere_faces)):
        keys = {}
        for name, limit in (("fused", 2**40), ("per_edge", 0)):
            monkeypatch.setattr(rasterize_module, "FUSED_EDGE_CANDIDATES", limit)
            monkeypatch.setattr(rasterize_module, "RAGGED_RUN_CANDIDATES", 0)  # all blocks
            keys[name] = rasterize_module.resolve_keys(clip, faces, (41, 37), False, None, 16,
                                                       2**20, 320)
        assert torch.equal(keys["fused"], keys["per_edge"])
        assert (keys["fused"] != rasterize_module.EMPTY_KEY).sum() > 200


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.int64])
@pytest.mark.parametrize("layout", ["contiguous", "transposed"])
def test_take_columns_never_copies_the_table(dtype: torch.dtype, layout: str) -> None:
    """take_columns equals index_select(1, ...) and copies only the columns it takes: a
    transposed (non-contiguous) table must not be copied whole per call (torch's float32
    dim-1 gather does that internally; it made 1.3M faces at batch 8 3.5x slower, as
    clipping gathers from the (3, B*V) screen table once per triangle chunk)."""
    from torch.profiler import ProfilerActivity, profile

    from torchraster.numerics import take_columns

    n = 5000
    table = (torch.randn(n, 3) * 100).to(dtype)
    table = table.T if layout == "transposed" else table.T.contiguous()
    index = torch.tensor([4999, 0, 17, 17, 2500])
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        got = take_columns(table, index)
        got_out = take_columns(table, index, torch.empty(3, 5, dtype=dtype))
    expected = table.index_select(1, index)
    assert torch.equal(got, expected) and torch.equal(got_out, expected)
    copies = [(e.name, e.input_shapes) for e in prof.events()
              if e.name in ("aten::clone", "aten::copy_", "aten::contiguous")
              and any(math.prod(shape) >= n for shape in e.input_shapes if shape)]
    assert not copies, copies
