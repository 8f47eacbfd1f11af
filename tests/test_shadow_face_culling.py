"""Culled shadow views (issue 23): point-light cube faces and spot maps that no receiver
can read are not rendered, and the image does not change.

The reference is the same render with culling off (``shadows.CULL_VIEWS = False``: every
view rendered, as before culling): images, alphas and gradients must be bit-identical
(``torch.equal``), and the face counts of known configurations are checked against the
geometry (which cube faces a floor under a light can select).
"""

from __future__ import annotations

import dataclasses
import math
import re

import pytest
import torch

import torchraster as tr
from torchraster import renderer as renderer_module
from torchraster.settings import RasterSettings
from torchraster.shading import shadows
from torchraster.shading.shadows import (
    ShadowSettings,
    cull_local_views,
    local_views,
    merge_shadow_steps,
)
from torchraster.shading.volumetric import Fog
from torchraster.testing import raytrace as rt

MATERIAL = tr.Material(metallic_factor=0.0, roughness_factor=0.7)
FILTERS = ("hard", "pcf", "pcss", "vsm")


def _floor_scene() -> tr.RenderScene:
    """A 6 m floor with a sphere and a small sphere on it (a typical view's content)."""
    casters = [rt.icosphere(0.5, (0.0, 0.5, 0.0)), rt.icosphere(0.3, (1.2, 0.3, -0.8))]
    pos, faces, cast = rt.ground_scene(casters, 6.0)
    return tr.RenderScene(pos, faces, materials=[MATERIAL], cast_shadows=cast)


def _cameras(b: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """``b`` different cameras looking down at the floor (45-70 degrees)."""
    eyes = [[0.0, 3.0, 3.5], [-2.5, 4.0, 1.0], [1.5, 2.0, 3.0]][:b]
    view = torch.cat([tr.camera.look_at(e, [0.0, 0.2, 0.0]) for e in eyes])
    return view, tr.camera.perspective(50.0, 1.0, 0.1)


def _lights(st: ShadowSettings, b: int = 2) -> tr.Lights:
    """Two point lights above the floor, a wide spot (a cube map) and a narrow spot
    (one map) aimed at the floor, and a narrow spot aimed at the sky (read by nothing)."""
    narrow = dataclasses.replace(st, map_size=st.map_size // 2)
    def full(rows):
        return torch.tensor(rows, dtype=torch.float32).expand(b, *torch.tensor(rows).shape
                                                               ).clone()

    point = tr.PointLights(position=full([[0.8, 1.6, 0.6], [-1.0, 2.2, -0.5]]),
                           color=full([[1.0, 0.9, 0.8], [0.7, 0.8, 1.0]]),
                           intensity=full([6.0, 4.0]), cast_shadows=torch.ones(b, 2, dtype=bool),
                           shadow=st)
    spot = tr.SpotLights(position=full([[-0.5, 2.0, 1.0], [1.0, 2.5, 0.5], [0.0, 2.5, 0.0]]),
                         direction=full([[0.2, -1.0, -0.3], [-0.3, -1.0, -0.2],
                                         [0.0, 1.0, 0.0]]),
                         color=torch.ones(b, 3, 3), intensity=full([8.0, 8.0, 8.0]),
                         outer_cone_angle=full([math.radians(70.0), math.radians(30.0),
                                                math.radians(30.0)]),
                         cast_shadows=torch.ones(b, 3, dtype=bool),
                         shadow=(st, narrow, narrow))  # the narrow ones: a group of maps
    return tr.Lights(point=point, spot=spot)


def _both(render):
    """``render()`` with culling on and off: (culled, reference)."""
    assert shadows.CULL_VIEWS
    culled = render()
    shadows.CULL_VIEWS = False
    try:
        ref = render()
    finally:
        shadows.CULL_VIEWS = True
    return culled, ref


def _rendered_counts(plan) -> list[str]:
    return [s for s in plan.shadow_maps if "rendered" in s]


@pytest.mark.parametrize("filt", FILTERS)
def test_images_bit_identical(filt):
    scene = _floor_scene()
    view, proj = _cameras(2)
    st = ShadowSettings(map_size=64, filter=filt, light_size=0.2, max_penumbra=8.0)
    r = tr.Renderer(40)
    with torch.no_grad():
        a, ref = _both(lambda: r(scene, view, proj, _lights(st)))
    assert torch.equal(a.image, ref.image) and torch.equal(a.alpha, ref.alpha)
    culled = _rendered_counts(a.plan)
    # every cube group skipped something: 2 point lights, the wide spot's cube; the single
    # spot maps are all rendered (the renderer culls cube maps only)
    assert len(culled) == 2 and not _rendered_counts(ref.plan), a.plan.shadow_maps
    for step in culled:
        k, n = (int(v) for v in re.search(r"(\d+) of (\d+) \w+ rendered", step).groups())
        assert 0 < k < n, step
    assert any(s.startswith("shadow spot[1, 2] 1 map") for s in a.plan.shadow_maps)
    # the shadows are there: the lights' shadows darken the frame
    no_shadows = tr.Renderer(40, shadows=False)
    with torch.no_grad():
        lit = no_shadows(scene, view, proj, _lights(st)).image
    assert float((lit - a.image).abs().amax()) > 0.05


def test_shared_lights_batch_and_cache():
    """Lights of batch size 1 shared by 3 cameras; a second call reuses cached maps."""
    scene = _floor_scene()
    view, proj = _cameras(3)
    st = ShadowSettings(map_size=64)
    r = tr.Renderer(32)
    with torch.no_grad():
        first, ref = _both(lambda: r(scene, view, proj, _lights(st, 1)))
        again = r(scene, view, proj, _lights(st, 1))
    assert torch.equal(first.image, ref.image) and torch.equal(again.image, ref.image)


@pytest.mark.parametrize("filt", ("pcf", "vsm"))
def test_fog_and_edge_supersampling_bit_identical(filt):
    """Fog samples along the view rays and edge sub-samples read the maps too."""
    scene = _floor_scene()
    view, proj = _cameras(2)
    st = ShadowSettings(map_size=64, filter=filt)
    fog = Fog(density=0.3, steps=6, blur=0.0)
    for kw in ({"fog": fog}, {"raster": RasterSettings(edge_supersample=2)}):
        r = tr.Renderer(32, **kw)
        with torch.no_grad():
            a, ref = _both(lambda r=r: r(scene, view, proj, _lights(st)))
        assert torch.equal(a.image, ref.image), kw


def test_fog_keeps_the_faces_its_samples_read():
    """A camera straight above the floor, a light beside the view 2 m high: the fog near
    the eye lies in the light's +Y face, which no surface selects (all are below the
    light); a small sphere out of view casts a light shaft from that face into the fog
    the camera sees (a face without casters is not rendered either)."""
    casters = [rt.icosphere(0.5, (0.0, 0.5, 0.0)), rt.icosphere(0.15, (1.4, 2.65, 0.0))]
    pos, faces, cast = rt.ground_scene(casters, 6.0)
    scene = tr.RenderScene(pos, faces, materials=[MATERIAL], cast_shadows=cast)
    view = tr.camera.look_at([0.0, 5.0, 1e-3], [0.0, 0.0, 0.0])
    proj = tr.camera.perspective(40.0, 1.0, 0.1)
    light = tr.Lights(point=tr.PointLights(
        position=torch.tensor([[[2.0, 2.0, 0.0]]]), color=torch.ones(1, 1, 3),
        intensity=torch.tensor([[30.0]]), cast_shadows=torch.tensor([[True]]),
        shadow=ShadowSettings(map_size=64)))
    seen = _spy_needed()
    fog = Fog(density=0.5, steps=16, blur=0.0)
    with torch.no_grad():
        plain, _ = _both(lambda: tr.Renderer(32)(scene, view, proj, light))
        foggy, ref = _both(lambda: tr.Renderer(32, fog=fog)(scene, view, proj, light))
        # the shaft is in the image: the fog without the small sphere differs
        open_sky = tr.RenderScene(pos, faces, materials=[MATERIAL],
                                  cast_shadows=cast & (torch.arange(len(cast)) < 1280))
        unshadowed = tr.Renderer(32, fog=fog)(open_sky, view, proj, light)
    assert torch.equal(foggy.image, ref.image)
    assert not torch.equal(unshadowed.image, ref.image)
    surface, fogged = seen[0][0], seen[2][0]
    assert not bool(surface[0, 0, 2]) and bool(fogged[0, 0, 2])  # +Y: the fog's only
    assert bool(surface[0, 0, 3])


def test_gradients_bit_identical():
    """Forward and backward through culled maps: positions (casters and receivers), light
    positions and intensities, for PCF (caster face ids) and VSM (differentiable maps)."""
    base = _floor_scene()
    view, proj = _cameras(2)
    for filt in ("pcf", "vsm"):
        st = ShadowSettings(map_size=32, filter=filt)
        results = []
        for cull in (True, False):
            shadows.CULL_VIEWS = cull
            try:
                pos = base.positions.clone().requires_grad_(True)
                lights = _lights(st)
                lights.point.position.requires_grad_(True)
                lights.spot.intensity.requires_grad_(True)
                scene = tr.RenderScene(pos, base.faces, materials=[MATERIAL],
                                       cast_shadows=base.cast_shadows)
                out = tr.Renderer(24)(scene, view, proj, lights)
                (out.image.square().sum() + out.image.mean()).backward()
                results.append((out.image.detach(), pos.grad, lights.point.position.grad,
                                lights.spot.intensity.grad, out.plan.shadow_maps))
            finally:
                shadows.CULL_VIEWS = True
        (img, *grads, steps), (img_ref, *grads_ref, _) = results
        assert _rendered_counts_steps(steps), steps
        assert torch.equal(img, img_ref), filt
        for k, (g, g_ref) in enumerate(zip(grads, grads_ref, strict=True)):
            assert g is not None
            if filt == "vsm" and k == 0:
                # the casters' gradient sums over every rendered VSM view (the maps are
                # differentiable): fewer views, another summation order (zeros of the unread
                # views added or not), so equal within float32 rounding of the sum
                assert float((g - g_ref).abs().max()) <= 1e-6 * float(g_ref.abs().max())
            else:
                assert torch.equal(g, g_ref), (filt, k)
        assert float(grads[1].abs().sum()) > 0  # the light positions get a gradient


def _rendered_counts_steps(steps) -> list[str]:
    return [s for s in steps if "rendered" in s]


def _spy_needed() -> list:
    """Record ``g.needed`` of the point / spot groups the renderer renders (a list filled
    by later renders of this test; the original function restored by the fixture below)."""
    seen: list = []
    orig = renderer_module.render_shadow_maps

    def spy(groups, *args, **kwargs):
        seen.append([g.needed.clone() if g.needed is not None else None for g in groups
                     if g.kind != "directional"])
        return orig(groups, *args, **kwargs)

    _SPIES.append((orig, spy))
    renderer_module.render_shadow_maps = spy
    return seen


_SPIES: list = []


@pytest.fixture(autouse=True)
def _restore_spies():
    yield
    while _SPIES:
        orig, _ = _SPIES.pop()
        renderer_module.render_shadow_maps = orig


def test_floor_below_light_renders_down_face_only():
    """A camera straight above a floor, a point light over its middle: every visible floor
    point lies within 45 degrees of straight down from the light, so -Y is the only face
    rendered; +Y (nothing above the light) is never."""
    pos, faces, _ = rt.ground_scene([], 2.0)  # the floor, |x|, |z| <= 1
    scene = tr.RenderScene(pos, faces, materials=[MATERIAL])
    view = tr.camera.look_at([0.0, 4.0, 1e-3], [0.0, 0.0, 0.0])
    proj = tr.camera.perspective(40.0, 1.0, 0.1)
    light = tr.Lights(point=tr.PointLights(
        position=torch.tensor([[[0.0, 1.5, 0.0]]]), color=torch.ones(1, 1, 3),
        intensity=torch.tensor([[5.0]]),
        cast_shadows=torch.tensor([[True]]), shadow=ShadowSettings(map_size=32)))
    seen = _spy_needed()
    with torch.no_grad():
        a, ref = _both(lambda: tr.Renderer(32)(scene, view, proj, light))
    assert torch.equal(a.image, ref.image)
    needed = seen[0][0]
    assert needed.tolist() == [[[False, False, False, True, False, False]]]
    assert seen[1][0] is None  # culling off: every face
    assert any("1 of 6 faces rendered" in s for s in a.plan.shadow_maps), a.plan.shadow_maps
    # a light beside the floor's corner, low: -Y no longer holds every point
    light.point.position = torch.tensor([[[1.2, 0.5, 1.2]]])
    with torch.no_grad():
        tr.Renderer(32)(scene, view, proj, light)
    needed = seen[2][0][0, 0]
    assert bool(needed[3]) and not bool(needed[2]) and not bool(needed[0])
    assert bool(needed[1]) and bool(needed[5])  # -X and -Z: towards the floor's middle


def test_cull_local_views_points_and_boxes(monkeypatch):
    """The low-level test against the face each point selects (dominant axis of its
    direction from the light), and the conservative box test."""
    gen = torch.Generator().manual_seed(0)
    light = torch.tensor([[[0.5, 1.0, -0.5]]])
    g = local_views("point", light, None, None, ShadowSettings(map_size=32),
                    torch.tensor([[[-3.0, -3.0, -3.0], [3.0, 3.0, 3.0]]]))
    for trial in range(40):
        pts = torch.randn(1, 3, 4, 5, generator=gen) * torch.rand(3, 1, 1, generator=gen) * 3
        mask = torch.rand(1, 1, 4, 5, generator=gen) > 0.3
        g.needed = None
        tiles = trial % 2 == 0  # the default tiles: conservative; 1-pixel tiles: exact
        if not tiles:
            monkeypatch.setattr(shadows, "CULL_TILE", 1)
        cull_local_views(g, [(pts, mask)])
        monkeypatch.undo()
        d = pts.flatten(2)[0].T[mask.flatten()] - light[0]  # (R, 3)
        axis = d.abs().argmax(-1)
        face = axis * 2 + (d.gather(1, axis[:, None])[:, 0] < 0).long()
        want = torch.zeros(6, dtype=torch.bool)
        want[face] = True
        if tiles:  # one box over the 4 x 5 points: every face they select, maybe more
            assert bool((g.needed[0, 0] | ~want).all()), (g.needed, want)
        else:
            assert torch.equal(g.needed[0, 0], want), (g.needed, want)
    # a box wholly above the light: +Y and no other face; one around it: every face
    g.needed = None
    cull_local_views(g, boxes=torch.tensor([[[0.0, 3.0, -1.0], [1.0, 4.0, 0.0]]]))
    assert g.needed[0, 0].tolist() == [False, False, True, False, False, False]
    g.needed = None
    cull_local_views(g, boxes=torch.tensor([[[0.0, 0.0, -1.0], [1.0, 2.0, 0.0]]]))
    assert bool(g.needed.all())
    # a single spot map (what cull_local_views does for them; the renderer culls cube maps
    # only): aimed at the sky it is read by no floor point, aimed down it is
    for down, want in ((-1.0, True), (1.0, False)):
        spot = local_views("spot", light, torch.tensor([[[0.0, down, 0.0]]]),
                           torch.tensor([[0.5]]), ShadowSettings(map_size=32),
                           torch.tensor([[[-3.0, -3.0, -3.0], [3.0, 3.0, 3.0]]]))
        floor = torch.stack(torch.meshgrid(torch.linspace(-2, 2, 8), torch.tensor([-1.0]),
                                           torch.linspace(-2, 2, 8), indexing="xy"))
        cull_local_views(spot, [(floor.reshape(1, 3, 8, 8), torch.ones(1, 1, 8, 8) > 0)])
        assert spot.layout == "single" and bool(spot.needed.all()) == want, down
    # culling off: nothing is marked
    shadows.CULL_VIEWS = False
    try:
        g.needed = None
        cull_local_views(g, [(pts, mask)])
        assert g.needed is None
    finally:
        shadows.CULL_VIEWS = True


def test_chunked_steps_merge_to_the_whole_batch():
    """The steps of a batch rendered item by item, merged, say what the whole batch's say
    (the counts of rendered faces add up; Renderer(max_batch=...) merges its chunks)."""
    scene = _floor_scene()
    view, proj = _cameras(3)
    lights = _lights(ShadowSettings(map_size=32), 3)  # per item: each item its own maps
    r = tr.Renderer(24)
    with torch.no_grad():
        whole = r(scene, view, proj, lights)
        parts = [r(scene, view[i:i + 1], proj, _lights(ShadowSettings(map_size=32), 1))
                 for i in range(3)]
    merged = merge_shadow_steps(s for p in parts for s in p.plan.shadow_maps)
    assert merged == whole.plan.shadow_maps
    assert torch.equal(torch.cat([p.image for p in parts]), whole.image)


def test_lights_and_casters_shared_by_the_batch_share_their_maps():
    """One scene seen by B cameras under lights of batch 1: the point / spot maps are
    rendered once for the batch (the faces any item reads), read by every item: the same
    image as per-item maps (lights given per item) and as each item alone; gradients to
    the vertices and the light positions agree."""
    scene = _floor_scene()
    view, proj = _cameras(3)
    st = ShadowSettings(map_size=32)
    r = tr.Renderer(24)

    def render(lights_b: int, items=slice(None)):
        lights = _lights(st, lights_b)
        pos = scene.positions.clone().requires_grad_(True)
        light_pos = lights.point.position.clone().requires_grad_(True)
        lights = dataclasses.replace(lights, point=dataclasses.replace(
            lights.point, position=light_pos))
        out = r(dataclasses.replace(scene, positions=pos), view[items], proj, lights)
        grads = torch.autograd.grad(out.image.square().sum(), (pos, light_pos))
        return out, grads

    shared, (g_pos, g_light) = render(1)
    per_item, (p_pos, p_light) = render(3)
    assert torch.equal(shared.image, per_item.image)
    torch.testing.assert_close(g_pos, p_pos, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(g_light, p_light.sum(0, keepdim=True), rtol=1e-4, atol=1e-6)
    alone = torch.cat([render(1, slice(i, i + 1))[0].image for i in range(3)])
    assert torch.equal(shared.image.detach(), alone.detach())
    def faces(out):  # (rendered, views) of the point group's step
        step = next(s for s in out.plan.shadow_maps if s.startswith("shadow point"))
        return tuple(int(x) for x in re.search(r"(\d+) of (\d+) faces rendered", step).groups())

    (rendered, views), (rendered_b, views_b) = faces(shared), faces(per_item)
    assert (views, views_b) == (12, 36) and 0 < rendered <= rendered_b


def test_face_ranges_per_item_casters():
    """Items drawing different faces (face_ranges): each item's views hold its own casters
    and receivers only."""
    base = _floor_scene()
    n_f = base.faces.shape[0]
    # item 0 draws everything; item 1 the floor and the small sphere only (the big sphere's
    # faces come first, 80 * 4**2 = 1280 of them)
    ranges = torch.tensor([[0, n_f], [1280, n_f]])
    scene = tr.RenderScene(base.positions, base.faces, materials=[MATERIAL],
                           cast_shadows=base.cast_shadows, face_ranges=ranges)
    view, proj = _cameras(2)
    for filt in ("hard", "pcss"):
        st = ShadowSettings(map_size=48, filter=filt)
        with torch.no_grad():
            a, ref = _both(lambda st=st: tr.Renderer(32)(scene, view, proj, _lights(st)))
        assert torch.equal(a.image, ref.image), filt
        assert _rendered_counts(a.plan), a.plan.shadow_maps


def test_views_without_casters_are_not_rendered():
    """Receivers all around a light, one caster triangle under it: only -Y holds a caster
    (the other maps would be +inf, as they start); VSM maps start as blurred moments, so
    VSM keeps every face the receivers read."""
    light = torch.tensor([[[0.0, 2.0, 0.0]]])
    pos = torch.tensor([[-0.2, 0.5, -0.2], [0.2, 0.5, -0.2], [0.0, 0.5, 0.3]])
    faces = torch.tensor([[0, 2, 1]])
    around = torch.tensor([[[-5.0, -5.0, -5.0], [5.0, 5.0, 5.0]]])
    for filt, want in (("pcf", [False, False, False, True, False, False]),
                       ("vsm", [True] * 6)):
        g = local_views("point", light, None, None, ShadowSettings(map_size=32, filter=filt),
                        around)
        cull_local_views(g, boxes=around, casters=(pos, faces, None))
        assert g.needed[0, 0].tolist() == want, filt
    # a caster just outside the -Y pyramid but inside the face's widened frustum (filter
    # taps near the border read it there): -Y keeps it, and so does -X (its own pyramid)
    g = local_views("point", light, None, None, ShadowSettings(map_size=32), around)
    edge = torch.tensor([[-1.52, 0.5, 0.0], [-1.52, 0.5, 0.01], [-1.53, 0.5, 0.0]])
    cull_local_views(g, boxes=around, casters=(edge, faces, None))
    assert g.needed[0, 0].tolist() == [False, True, False, True, False, False]


@pytest.mark.parametrize("dtype", (torch.float16, torch.bfloat16))
def test_half_precision_bit_identical(dtype):
    """Half-precision positions (maps and lookups in float32): the same culled views."""
    base = _floor_scene()
    scene = tr.RenderScene(base.positions.to(dtype), base.faces, materials=[MATERIAL],
                           cast_shadows=base.cast_shadows)
    view, proj = _cameras(2)
    st = ShadowSettings(map_size=32, filter="pcf", normal_bias=1.0)
    with torch.no_grad():
        a, ref = _both(lambda: tr.Renderer(24)(scene, view, proj, _lights(st)))
    assert torch.equal(a.image, ref.image)
    assert _rendered_counts(a.plan), a.plan.shadow_maps


def test_edge_subsamples_keep_the_faces_they_read():
    """Edge antialiasing shades sub-samples that no pixel centre sees: a strip 2.54 m high
    and 0.1 m deep, seen from below by a level camera, lies between two pixel centres of
    the frame (NDC y 0.294-0.300) but holds a sub-sample at 2x; a triangle seen edge-on
    (at the camera's height) shadows it from the point light below. Only the strip reads
    the light's +Y face, and only through its sub-samples."""
    y = 2.54
    pos = torch.tensor([[-1.0, y, -0.05], [1.0, y, -0.05], [1.0, y, 0.05], [-1.0, y, 0.05],
                        [-0.2, 2.0, -0.15], [0.2, 2.0, -0.15], [0.0, 2.0, 0.15]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [4, 5, 6]])
    scene = tr.RenderScene(pos, faces, materials=[MATERIAL])
    view = tr.camera.look_at([0.0, 2.0, 5.0], [0.0, 2.0, 0.0])
    proj = tr.camera.perspective(40.0, 1.0, 0.1)
    light = tr.Lights(point=tr.PointLights(
        position=torch.tensor([[[0.0, 1.0, 0.0]]]), color=torch.ones(1, 1, 3),
        intensity=torch.tensor([[20.0]]), cast_shadows=torch.tensor([[True]]),
        shadow=ShadowSettings(map_size=64)))
    r = tr.Renderer(32, raster=RasterSettings(edge_supersample=2))
    seen = _spy_needed()
    with torch.no_grad():
        a, ref = _both(lambda: r(scene, view, proj, light))
        plain = tr.Renderer(32)(scene, view, proj, light)
    assert float(plain.alpha.sum()) == 0  # no pixel centre sees the strip
    assert float(a.alpha.sum()) > 0 and a.plan.edge_pixels > 0
    assert torch.equal(a.image, ref.image)
    needed = seen[0][0][0, 0]  # the scene's box: +Y, and the side faces its corners touch
    assert bool(needed[2]) and not bool(needed[3])
    # the shadow is in the image: without the triangle the strip is brighter
    lit = r(tr.RenderScene(pos, faces[:2], materials=[MATERIAL]), view, proj, light)
    assert float(lit.image.sum()) > float(a.image.sum()) * 1.05


@pytest.mark.parametrize("case", ["lights per item", "positions per item", "face ranges",
                                  "fog"])
def test_maps_are_shared_only_when_every_item_reads_the_same(case):
    """Maps are shared by the batch for lights of batch 1 over one mesh without face
    ranges (also read by the fog march); per-item lights, per-item vertices and different
    meshes keep per-item maps. Every case renders each item as it renders alone."""
    scene = _floor_scene()
    view, proj = _cameras(2)
    st = ShadowSettings(map_size=32)
    lights = _lights(st, 1)
    fog = None
    if case == "lights per item":  # the second item's point lights moved
        lights = _lights(st, 2)
        pos = lights.point.position.clone()
        pos[1] += torch.tensor([0.7, 0.3, -0.4])
        lights = dataclasses.replace(lights, point=dataclasses.replace(lights.point,
                                                                       position=pos))
    elif case == "positions per item":  # the second item's casters raised
        lifted = scene.positions.clone()
        lifted[scene.positions[:, 1] > 0.01] += torch.tensor([0.3, 0.2, 0.0])
        scene = dataclasses.replace(scene, positions=torch.stack([scene.positions, lifted]))
    elif case == "face ranges":  # item 1 draws the floor only
        floor = int((~scene.cast_shadows).nonzero().max()) + 1
        first = int((~scene.cast_shadows).nonzero().min())
        scene = dataclasses.replace(scene, face_ranges=torch.tensor(
            [[0, scene.faces.shape[0]], [first, floor]]))
    else:
        fog = tr.Fog(density=0.2, steps=4, jitter=False)
    r = tr.Renderer(24, fog=fog)
    one_by_one = tr.Renderer(24, fog=fog, raster=tr.RasterSettings(max_batch=1))
    with torch.no_grad():
        whole = r(scene, view, proj, lights)
        alone = one_by_one(scene, view, proj, lights).image
    torch.testing.assert_close(whole.image, alone, rtol=1e-6, atol=1e-6)
    assert not torch.allclose(alone[0], alone[1])


def test_a_shared_group_needs_the_faces_any_item_reads(monkeypatch):
    """A group of batch 1 culled against receivers of two items keeps the union of the
    faces each item's points select (1-pixel tiles: exact); a group of another batch
    size is refused."""
    monkeypatch.setattr(shadows, "CULL_TILE", 1)
    light = torch.tensor([[[0.0, 0.0, 0.0]]])
    box = torch.tensor([[[-3.0, -3.0, -3.0], [3.0, 3.0, 3.0]]])
    g = local_views("point", light, None, None, ShadowSettings(map_size=32), box)
    pts = torch.zeros(2, 3, 1, 1)
    pts[0, :, 0, 0] = torch.tensor([2.0, 0.1, 0.2])  # item 0: the +X face
    pts[1, :, 0, 0] = torch.tensor([0.1, -0.2, -2.0])  # item 1: the -Z face
    cull_local_views(g, [(pts, torch.ones(2, 1, 1, 1, dtype=torch.bool))])
    assert g.needed.shape == (1, 1, 6)
    assert g.needed[0, 0].tolist() == [True, False, False, False, False, True]
    three = local_views("point", light.expand(3, 1, 3), None, None,
                        ShadowSettings(map_size=32), box.expand(3, 2, 3))
    with pytest.raises(ValueError, match=r"batch sizes \[2, 3\]"):
        cull_local_views(three, [(pts, torch.ones(2, 1, 1, 1, dtype=torch.bool))])
