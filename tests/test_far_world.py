"""Far-away worlds: camera-relative rendering (torchraster/relative.py, issue 22).

The scene (Spot on a floor) and its camera are translated by up to 1e7 with float64 world
positions. References, all independent of the relative path:
- the float64 brute-force rasterizer (testing/reference_raster) on the far WORLD coordinates
  (float64 keeps 1e-9 there) for face ids;
- the ordinary render of the same scene at the world origin (the translation changes
  nothing physical, so every output must match it; float32 at the origin is exact enough);
- the full float64 render without the shift (camera_relative=False, float64 everything) for
  world-space effects (dissolve pattern, fog height);
- float64 world positions of the visible surface (origin render's + the offset) for the
  ``position`` channel.
Mismatching pixels are allowed only where a pixel centre lies within float32 rounding of a
triangle edge (a handful of 64 x 64).
"""

from __future__ import annotations

import warnings

import pytest
import torch

import torchraster as tr
from torchraster import relative
from torchraster.motion import OtherFrame
from torchraster.shading.shadows import ShadowSettings
from torchraster.testing.reference_raster import reference_rasterize, to_clip

RES = 64
EYE = torch.tensor([0.6, 0.9, 2.6], dtype=torch.float64)
TARGET = torch.tensor([0.0, 0.1, 0.0], dtype=torch.float64)
PROJ = tr.camera.perspective(45.0, 1.0, 0.1)[0]  # float32 (4, 4)


def _stage() -> tuple[torch.Tensor, torch.Tensor]:
    """Spot standing on a 4 x 4 floor: float64 positions (V, 3), faces (F, 3)."""
    spot = tr.load_spot()
    pos = spot.positions.double()
    y = float(pos[:, 1].min())
    floor = torch.tensor([[-2.0, y, -2.0], [-2.0, y, 2.0], [2.0, y, 2.0], [2.0, y, -2.0]],
                         dtype=torch.float64)
    n = pos.shape[0]
    faces = torch.cat([spot.faces, torch.tensor([[n, n + 1, n + 2], [n, n + 2, n + 3]])])
    return torch.cat([pos, floor]), faces


POS, FACES = _stage()


def _camera(offset: torch.Tensor) -> torch.Tensor:
    return tr.camera.look_at(EYE + offset, TARGET + offset)[0]  # float64 (4, 4)


def _render(offset: float | tuple, *, dtype=torch.float64, lights=None, channels=(),
            grad: bool = False, **kw):
    """The stage and camera translated by ``offset``; returns (output, positions leaf)."""
    off = torch.as_tensor(offset, dtype=torch.float64).expand(3)
    pos = (POS + off).to(dtype)
    if grad:
        pos = pos.requires_grad_(True)
    view = _camera(off)
    if dtype != torch.float64 and not off.any():
        view = view.to(PROJ.dtype)  # the plain float32 render at the origin
    kw.setdefault("shading", "headlight" if lights is None else "pbr")
    out = tr.Renderer(RES, **kw)(tr.RenderScene(pos, FACES), view, PROJ, lights,
                                 channels=channels)
    return out, pos


@pytest.fixture(scope="module")
def origin():
    """The plain float32 render at the origin (camera-relative not applied)."""
    out, _ = _render(0.0, dtype=torch.float32, channels=("face_id", "position"))
    assert out.image.dtype == torch.float32
    return out


@pytest.mark.parametrize("offset", [0.0, 1e3, 1e5, 1e6, 1e7])
def test_far_headlight_matches_origin_and_reference(origin, offset):
    out, _ = _render(offset, channels=("face_id", "position"))
    assert out.image.dtype == torch.float32  # float64 positions, float32 projection
    assert torch.allclose(torch.tensor(out.plan.origin, dtype=torch.float64), EYE + offset)
    assert "camera-relative origin" in out.plan.steps[0]
    fid = out.gbuffer["face_id"][:, 0]
    # independent: float64 brute force of the far world coordinates
    off = torch.full((3,), offset, dtype=torch.float64)
    clip = to_clip(POS + off, PROJ.double() @ _camera(off))[None]
    ref = reference_rasterize(clip, FACES, (RES, RES)).face_id
    assert int((fid != ref).sum()) <= 3  # centres within float32 rounding of an edge
    assert int((fid != origin.gbuffer["face_id"][:, 0]).sum()) <= 3
    assert torch.equal(out.alpha > 0, fid[:, None] >= 0)
    same = (fid == origin.gbuffer["face_id"][:, 0])[:, None].expand_as(out.image)
    torch.testing.assert_close(out.image[same], origin.image[same], atol=1e-4, rtol=0)
    # the position channel is in world space (float32 absolute rounding at the offset)
    world = origin.gbuffer["position"].double() + off.view(1, 3, 1, 1) * (fid >= 0)[:, None]
    both = (same & (fid >= 0)[:, None])
    err = (out.gbuffer["position"].double() - world)[both].abs().max()
    assert float(err) <= 2e-4 + 2 * torch.finfo(torch.float32).eps * offset


def test_near_origin_is_bit_identical():
    """Not applied near the origin: the automatic mode renders exactly as False."""
    pos = POS.float()
    view = _camera(torch.zeros(3)).float()
    outs = [tr.Renderer(RES, shading="headlight", raster=tr.RasterSettings(camera_relative=mode))(
        tr.RenderScene(pos, FACES), view, PROJ, channels=("position",)) for mode in (None, False)]
    assert torch.equal(outs[0].image, outs[1].image)
    assert torch.equal(outs[0].gbuffer["position"], outs[1].gbuffer["position"])
    assert relative.plan_shift(None, pos, view[None], PROJ[None]) is None
    assert outs[0].plan.origin is None
    # a tiny object seen from afar is not "far from the origin" either
    assert relative.plan_shift(None, pos * 0.01, view[None], PROJ[None]) is None
    # forced on at the origin: the same picture up to float32 rounding
    on = tr.Renderer(RES, shading="headlight", raster=tr.RasterSettings(camera_relative=True))(
        tr.RenderScene(pos, FACES), view, PROJ, channels=("position",))
    torch.testing.assert_close(on.image, outs[0].image, atol=1e-4, rtol=0)
    torch.testing.assert_close(on.gbuffer["position"], outs[0].gbuffer["position"],
                               atol=1e-5, rtol=0)


def test_float64_reference_path_kept():
    """float64 positions with a float64 projection stay a float64 render (near the origin
    unchanged; far away shifted, still float64)."""
    for offset in (0.0, 1e6):
        off = torch.full((3,), offset, dtype=torch.float64)
        out = tr.Renderer(RES, shading="headlight")(tr.RenderScene(POS + off, FACES),
                                                    _camera(off), PROJ.double())
        assert out.image.dtype == torch.float64
        if offset == 0.0:
            base = out
    torch.testing.assert_close(out.image, base.image, atol=1e-7, rtol=0)


def test_float32_positions_far_warn():
    with pytest.warns(UserWarning, match=r"positions: torch.float32 .* rounded"):
        out, _ = _render(1e6, dtype=torch.float32)
    assert bool(torch.isfinite(out.image).all())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _render(1e6)  # float64: no warning
        _render(0.0, dtype=torch.float32)


def _lights(offset: torch.Tensor, filt: str) -> tr.Lights:
    """A shadowed sun (3 cascades), a shadowed spot and a shadowed point light, float64."""
    d = torch.float64
    s = ShadowSettings(map_size=128, filter=filt, cascades=3 if filt != "hard" else 1)
    local = ShadowSettings(map_size=64, filter=filt)
    sun = tr.DirectionalLights(direction=torch.tensor([[[0.4, -1.0, 0.3]]], dtype=d),
                               color=torch.ones(1, 1, 3, dtype=d),
                               intensity=torch.tensor([[3.0]], dtype=d),
                               cast_shadows=torch.tensor([[True]]), shadow=s)
    spot = tr.SpotLights(position=(torch.tensor([1.5, 2.5, 1.0], dtype=d) + offset)[None, None],
                         direction=torch.tensor([[[-0.5, -1.0, -0.4]]], dtype=d),
                         color=torch.ones(1, 1, 3, dtype=d),
                         intensity=torch.tensor([[6.0]], dtype=d),
                         cast_shadows=torch.tensor([[True]]), shadow=local)
    point = tr.PointLights(position=(torch.tensor([-1.2, 1.8, 0.8], dtype=d) + offset)[None, None],
                           color=torch.ones(1, 1, 3, dtype=d),
                           intensity=torch.tensor([[4.0]], dtype=d),
                           cast_shadows=torch.tensor([[True]]), shadow=local)
    return tr.Lights(directional=sun, spot=spot, point=point)


@pytest.mark.parametrize("filt", ["pcf", "vsm"])
def test_far_shadows_and_fog_finite_and_close(filt):
    fog = tr.Fog(density=0.05, height_falloff=0.5, steps=4, jitter=False, blur=0.0)
    outs, grads = {}, {}
    for offset in (0.0, 1e6):  # (1e6, 0, 1e6): the fog's base height stays where it is
        off = torch.tensor([offset, 0.0, offset], dtype=torch.float64)
        out, pos = _render(off, lights=_lights(off, filt), grad=True, fog=fog)
        assert out.image.dtype == torch.float32
        assert bool(torch.isfinite(out.image).all())
        (g,) = torch.autograd.grad((out.image * torch.linspace(0, 1, RES)).sum(), pos)
        assert bool(torch.isfinite(g).all()) and bool(g.abs().sum() > 0)
        outs[offset], grads[offset] = out.image.detach(), g
    # translation invariance: the same gradients with respect to the vertices
    err = (grads[1e6] - grads[0.0]).norm() / grads[0.0].norm()
    assert float(err) < 1e-2, float(err)
    assert out.plan.origin is not None and any("cascade" in st for st in out.plan.steps), \
        out.plan.steps
    diff = (outs[1e6] - outs[0.0]).abs()
    assert float(diff.mean()) < 1e-3 * float(outs[0.0].mean())
    assert int((diff > 1e-2 * outs[0.0].max()).sum()) <= 3  # shadow-edge texels may flip


def test_fog_height_follows_the_world():
    """Offset in y too: the fog's base height stays at world y = 0, so the far render
    equals the full float64 render without the shift (world coordinates)."""
    fog = tr.Fog(density=0.2, height_falloff=1.0, base_height=1e3, ambient=(0.5, 0.5, 0.5))
    off = torch.tensor([1e6, 1e3, -1e6], dtype=torch.float64)
    scene = tr.RenderScene(POS + off, FACES)
    kw = dict(shading="headlight", fog=fog)
    rel = tr.Renderer(RES, **kw)(scene, _camera(off), PROJ)
    ref = tr.Renderer(RES, **kw, raster=tr.RasterSettings(camera_relative=False))(
        scene, _camera(off), PROJ.double())
    assert ref.image.dtype == torch.float64
    torch.testing.assert_close(rel.image.double(), ref.image, atol=2e-4, rtol=0)


def test_dissolve_pattern_is_the_world_pattern():
    """The noise is evaluated at world positions: the same cut-out as the float64 render
    without the shift, at an offset that is not a multiple of the noise period."""
    d = tr.Dissolve(threshold=0.4, scale=4.0)
    off = torch.tensor([1e5 + 12.3, 0.0, -3e5 + 7.7], dtype=torch.float64)
    scene = tr.RenderScene(POS + off, FACES)
    rel = tr.Renderer(RES, shading="headlight", dissolve=d)(scene, _camera(off), PROJ)
    ref = tr.Renderer(RES,
                      shading="headlight",
                      dissolve=d,
                      raster=tr.RasterSettings(camera_relative=False))(
        scene, _camera(off), PROJ.double())
    cut = (ref.alpha < 1) & (ref.alpha.new_ones(1) > 0)
    assert int(((rel.alpha > 0.5) != (ref.alpha > 0.5)).sum()) <= 3  # noise == threshold
    assert bool(cut.any())
    diff = (rel.image.double() - ref.image).abs()
    assert float(diff.max()) < 1e-2  # float32 noise in the steep glow band


def test_far_motion_and_depth_cache():
    """Flow of a far scene (float64 other frame) equals the origin's; the other frame's
    rasterized depth is stored on the caller's OtherFrame."""
    flows = {}
    for offset in (0.0, 1e6):
        off = torch.full((3,), offset, dtype=torch.float64)
        step = torch.tensor([0.05, 0.0, -0.03], dtype=torch.float64)
        nxt = OtherFrame(POS + off + step, _camera(off + step / 2).to(torch.float64),
                         PROJ)
        out = tr.Renderer(RES, shading="unlit")(
            tr.RenderScene(POS + off, FACES), _camera(off), PROJ,
            channels=("flow_forward", "flow_forward_valid"), next_frame=nxt)
        assert nxt.depth is not None
        flows[offset] = out.gbuffer
    for name in ("flow_forward", "flow_forward_valid"):
        bad = (flows[1e6][name] - flows[0.0][name]).abs() > 1e-3
        assert int(bad.sum()) <= 6, name


def test_chunked_far_batch_matches():
    views = torch.stack([_camera(torch.full((3,), 1e6, dtype=torch.float64)),
                         tr.camera.look_at(EYE * 1.2 + 1e6, TARGET + 1e6)[0]])
    scene = tr.RenderScene(POS + 1e6, FACES)
    whole = tr.Renderer(RES, shading="headlight")(scene, views, PROJ, channels=("position",))
    parts = tr.Renderer(RES, shading="headlight", raster=tr.RasterSettings(max_batch=1))(
        scene, views, PROJ, channels=("position",))
    assert torch.equal(whole.image, parts.image)
    assert torch.equal(whole.gbuffer["position"], parts.gbuffer["position"])


def test_camera_relative_checked():
    with pytest.raises(TypeError, match="camera_relative"):
        tr.Renderer(RES, raster=tr.RasterSettings(camera_relative="yes"))


CONFIG = """\
scene:
  objects:
    - {name: floor, primitive: box, transform: {translate: [%(x)s, -0.05, %(x)s],
       scale: [4, 0.1, 4]}}
    - {name: box, primitive: box, size: 1,
       transform: {translate: [%(x1)s, 0.5, %(x)s], rotate_deg: [0, 30, 0]}}
    - {name: ball, primitive: sphere, size: 1, transform: {translate: [%(x2)s, 0.5, %(x)s]}}
lights:
  - {type: directional, direction: [0.4, -1.0, 0.3], intensity: 3.0,
     shadows: {map_size: 128}}
cameras:
  - {name: near, look_at: {eye: [%(ex)s, 2.0, %(ez)s], target: [%(x)s, 0.3, %(x)s]}}
  - {name: orbit, orbit: {azimuth_deg: 30, elevation_deg: 20}}
render: {resolution: [48, 48], shading: pbr}
outputs: {channels: [color, instance]}
"""


def test_config_objects_far_away(tmp_path):
    """YAML objects translated by 1e6 (and a camera there): world positions and cameras
    are posed in float64 and render like the same config at the origin (float32, the
    ordinary path)."""
    from torchraster.config import load_config
    from torchraster.config.build import build_camera, build_setup

    images = {}
    for x in (0.0, 1e6):
        path = tmp_path / f"far{int(x)}.yaml"
        path.write_text(CONFIG % dict(x=x, x1=x - 0.8, x2=x + 0.8, ex=x + 1.0, ez=x + 4.0))
        cfg = load_config(path)
        setup = build_setup(cfg)
        assert setup.scene.positions.dtype == (torch.float64 if x else torch.float32)
        for cam in cfg.cameras:
            view, proj = build_camera(cam, setup.scene.positions, (48, 48))
            assert view.dtype == setup.scene.positions.dtype
            images[x, cam.name] = setup.renderer(setup.scene, view, proj, setup.lights,
                                                 channels=("instance",))
    for name in ("near", "orbit"):
        far, near = images[1e6, name], images[0.0, name]
        assert torch.equal(far.gbuffer["instance"], near.gbuffer["instance"])
        torch.testing.assert_close(far.image, near.image, atol=2e-4, rtol=0)


def test_far_area_light_matches_origin():
    """An area light (PCSS shadows) 1e6 m from the origin with its scene: the image of the
    same light and scene at the origin (its centre shifted like the positions)."""
    images = {}
    for offset in (0.0, 1e6):
        off = torch.tensor([offset, 0.0, offset], dtype=torch.float64)
        u, v = tr.area_light_axes(torch.tensor([0.2, -1.0, 0.1], dtype=torch.float64),
                                  torch.tensor(0.6, dtype=torch.float64),
                                  torch.tensor(0.4, dtype=torch.float64))
        lights = tr.Lights(area=tr.AreaLights(
            position=(torch.tensor([0.3, 1.2, 0.4], dtype=torch.float64) + off).view(1, 1, 3),
            u=u.view(1, 1, 3), v=v.view(1, 1, 3), color=torch.ones(1, 1, 3, dtype=torch.float64),
            intensity=torch.tensor([[5.0]], dtype=torch.float64),
            cast_shadows=torch.tensor([[True]])))
        out, _ = _render(off, lights=lights)
        assert out.image.dtype == torch.float32 and bool(torch.isfinite(out.image).all())
        images[offset] = out.image
    assert out.plan.origin is not None and any(s.startswith("shadow area") for s in
                                               out.plan.steps), out.plan.steps
    diff = (images[1e6] - images[0.0]).abs()
    assert float(images[0.0].mean()) > 0
    assert float(diff.mean()) < 1e-3 * float(images[0.0].mean())
    assert int((diff > 1e-2 * images[0.0].max()).sum()) <= 3  # shadow-edge texels may flip
