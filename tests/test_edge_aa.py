"""Edge antialiasing (``Renderer(edge_supersample=k)``, torchraster/edge_aa.py).

References: ``supersample=k`` (the same passes on every sub-sample: with every pixel
flagged the two must agree to float tolerance), ``supersample=8`` (the pixel-area average
of a shadow scene), the 1x render (labels and G-buffer must be identical), finite
differences (float64 gradients through the packed sub-samples).
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

import torchraster as tr
from torchraster import edge_aa
from torchraster.testing import raytrace as rt

MAT = tr.Material(metallic_factor=0.0, roughness_factor=0.6)


def _scene(dtype=torch.float32, subdivisions: int = 2):
    """A sphere and a box-ish icosphere on a floor; face_object 1, 2 (casters), 3 (floor)."""
    a = rt.icosphere(0.5, (-0.3, 0.5, 0.0), subdivisions)
    b = rt.icosphere(0.3, (0.7, 0.3, 0.4), 1)
    pos, faces, cast = rt.ground_scene([a, b], 4.0, dtype=dtype)
    obj = torch.cat([torch.full((a[1].shape[0],), 1), torch.full((b[1].shape[0],), 2),
                     torch.full((2,), 3)])
    scene = tr.RenderScene(pos, faces, materials=[MAT], cast_shadows=cast, face_object=obj)
    view = tr.camera.look_at([0.5, 2.2, 3.5], [0.0, 0.3, 0.0]).to(dtype)
    proj = tr.camera.perspective(45.0, 1.0, 0.1).to(dtype)
    return scene, view, proj


def _lights(kinds=("directional", "point"), dtype=torch.float32):
    parts = {k: getattr(rt.make_lights(k), k) for k in kinds}
    amb = torch.zeros(1, 9, 3)
    amb[0, 0] = 0.3
    return tr.Lights(ambient=amb, **parts).to(dtype=dtype)


@pytest.mark.parametrize("k, pixel_radius", [(2, 0.0), (3, 0.0), (2, 0.56)])
def test_every_pixel_flagged_equals_supersample(k, pixel_radius, monkeypatch):
    """Every pixel re-shaded at k x k sub-samples = supersample=k (image and alpha); with
    ``ShadowSettings(pixel_radius=...)`` the sub-samples' footprint is their own (1 / k of
    a pixel), as in the supersampled frame."""
    scene, view, proj = _scene()
    lights = _lights()
    if pixel_radius:
        settings = tr.shading.shadows.ShadowSettings(pixel_radius=pixel_radius)
        lights = tr.Lights(ambient=lights.ambient, **{
            kind: dataclasses.replace(getattr(lights, kind), shadow=settings)
            for kind in ("directional", "point")})
    monkeypatch.setattr(edge_aa, "CONTRAST_THRESHOLD", -1.0)
    kw = {"background": (0.2, 0.3, 0.4)}
    with torch.no_grad():
        ref = tr.Renderer(24, **kw, raster=tr.RasterSettings(supersample=k))(
            scene, view, proj, lights, channels={"alpha"})
        out = tr.Renderer(24, **kw, raster=tr.RasterSettings(edge_supersample=k))(
            scene, view, proj, lights, channels={"alpha"})
    assert out.plan.edge_pixels == 24 * 24
    torch.testing.assert_close(out.image, ref.image, atol=2e-6, rtol=1e-5)
    torch.testing.assert_close(out.alpha, ref.alpha, atol=1e-6, rtol=0)


def _error(a: torch.Tensor, ref: torch.Tensor) -> float:
    return float((a.clamp(0, 1) - ref.clamp(0, 1)).abs().mean())


def test_default_thresholds_approach_the_reference():
    """Shadow scene (sun + point light): the edge pass removes most of the 1x error against
    supersample=8, re-shading a small fraction of the pixels."""
    scene, view, proj = _scene()
    lights = _lights()
    res = 48
    with torch.no_grad():
        ref = tr.Renderer(res, raster=tr.RasterSettings(supersample=8))(
            scene, view, proj, lights).image
        one = tr.Renderer(res)(scene, view, proj, lights).image
        out = tr.Renderer(res, raster=tr.RasterSettings(edge_supersample=4))(
            scene, view, proj, lights)
        ss4 = tr.Renderer(res, raster=tr.RasterSettings(supersample=4))(
            scene, view, proj, lights).image
    e1, ee, es = _error(one, ref), _error(out.image, ref), _error(ss4, ref)
    assert ee < 0.3 * e1, (e1, ee)
    assert ee < 1.5 * es, (es, ee)  # close to supersampling at the same factor
    assert 0 < out.plan.edge_pixels < 0.4 * res * res


def test_labels_and_gbuffer_are_the_1x_frame():
    scene, view, proj = _scene()
    lights = _lights()
    channels = {"instance", "face_id", "albedo", "normal", "depth", "mask"}
    with torch.no_grad():
        one = tr.Renderer(32)(scene, view, proj, lights, channels=channels)
        out = tr.Renderer(32, raster=tr.RasterSettings(edge_supersample=3))(
            scene, view, proj, lights, channels=channels)
    assert set(out.gbuffer) == channels
    for ch in channels:
        assert torch.equal(out.gbuffer[ch], one.gbuffer[ch]), ch
    edge = (out.image != one.image).any(1)
    assert bool(edge.any())
    # only pixels the pass flagged change: never more than it reports
    assert int(edge.sum()) <= out.plan.edge_pixels


def test_plan_reports_the_pass():
    scene, view, proj = _scene()
    r = tr.Renderer(16, raster=tr.RasterSettings(edge_supersample=2))
    assert "edge supersample 2x" in r.plan(scene, _lights())
    with torch.no_grad():
        out = r(scene, view, proj, _lights())
    n = out.plan.edge_pixels
    assert n > 0 and f"edge supersample 2x: {n} pixels" in out.plan
    assert not any("edge" in s for s in tr.Renderer(16).plan(scene, _lights()))


def test_batch_chunks_sum_the_edge_pixels():
    scene, view, proj = _scene()
    views = torch.cat([view.view(1, 4, 4), tr.camera.look_at([-1.0, 2.0, 3.0], [0.0, 0.3, 0.0])])
    lights = _lights(("directional",))
    with torch.no_grad():
        whole = tr.Renderer(16, raster=tr.RasterSettings(edge_supersample=2))(
            scene, views, proj, lights)
        parts = tr.Renderer(16, raster=tr.RasterSettings(edge_supersample=2, max_batch=1))(
            scene, views, proj, lights)
    assert parts.plan.edge_pixels == whole.plan.edge_pixels
    torch.testing.assert_close(parts.image, whole.image)


def test_background_image_and_batch():
    """A shared background image behind a batch of two views: empty sub-samples take the
    pixel's 1x background, so an edge pixel stays between the object and the image."""
    scene, view, proj = _scene()
    views = torch.cat([view.view(1, 4, 4), tr.camera.look_at([0.0, 1.0, 2.0], [0.0, 0.3, 0.0])])
    image = torch.rand(3, 10, 10, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        one = tr.Renderer(16, background=tr.BackgroundSettings(image=image))(
            scene, views, proj, _lights())
        out = tr.Renderer(16,
                          raster=tr.RasterSettings(edge_supersample=2),
                          background=tr.BackgroundSettings(image=image))(scene, views, proj,
                                                                          _lights())
    assert out.image.shape == (2, 3, 16, 16) and bool(torch.isfinite(out.image).all())
    changed = (out.image != one.image).any(1)
    assert bool(changed.any()) and int(changed.sum()) <= out.plan.edge_pixels
    assert bool(((out.alpha > 0) & (out.alpha < 1)).any())  # antialiased silhouettes


@pytest.mark.parametrize("bad", [0, True, 1.5, "x", 9, None])
def test_bad_values_name_the_option(bad):
    with pytest.raises(ValueError, match="edge_supersample"):
        tr.Renderer(8, raster=tr.RasterSettings(edge_supersample=bad))


def test_unsupported_combinations_say_so():
    with pytest.raises(ValueError, match="edge_supersample.*supersample"):
        tr.Renderer(8, raster=tr.RasterSettings(edge_supersample=2, supersample=2))
    with pytest.raises(ValueError, match="edge_supersample.*antialias"):
        tr.Renderer(8, raster=tr.RasterSettings(edge_supersample=2, antialias=True))
    with pytest.raises(NotImplementedError, match="edge_supersample.*ssao"):
        tr.Renderer(8, ssao=tr.post.SSAO(), raster=tr.RasterSettings(edge_supersample=2))
    scene, view, proj = _scene()
    scene.materials = [tr.Material(alpha_mode="MASK")]
    with pytest.raises(NotImplementedError, match="edge_supersample.*MASK"):
        tr.Renderer(8, raster=tr.RasterSettings(edge_supersample=2)).plan(scene, _lights())


def test_contrast_and_geometric_edges():
    v = torch.zeros(1, 1, 4, 6)
    v[..., 3:] = 1.0
    flagged = edge_aa.contrast_edges(v, 0.5)
    assert flagged[0, :, 2:4].all() and not flagged[0, :, :2].any() and not flagged[0, :, 4:].any()
    assert edge_aa.contrast_edges(v, -1.0).all()
    faces = torch.tensor([[0, 1, 2], [1, 2, 3], [4, 5, 6]])
    fid = torch.tensor([[[0, 1, 0, 0], [0, 1, 2, 0]]])  # 2x4 raster at k = 2: pixels (1, 2)
    got = edge_aa.geometric_edges(fid, faces, 2)
    # pixel 0 mixes faces 0 and 1 (they share vertices 1, 2): smooth; pixel 1 sees face 2
    # next to face 0 (no shared vertex): an edge
    assert got.tolist() == [[[False, True]]]
    fid[0, 0, 0] = -1  # coverage next to empty: a silhouette
    assert edge_aa.geometric_edges(fid, faces, 2).tolist() == [[[True, True]]]
    mat = torch.tensor([0, 1, 0])  # faces 0 and 1 of different materials: an edge
    fid[0, 0, 0] = 0
    assert edge_aa.geometric_edges(fid, faces, 2, mat).tolist() == [[[True, True]]]


def test_gradients_through_the_packed_subsamples():
    """float64 finite differences of a weighted image sum w.r.t. a light's direction and
    the base colour (sun without shadow maps: the image is smooth in both)."""
    scene, view, proj = _scene(torch.float64, subdivisions=1)
    weights = torch.rand(1, 3, 12, 12, dtype=torch.float64,
                         generator=torch.Generator().manual_seed(0))
    renderer = tr.Renderer(12, shadows=False, raster=tr.RasterSettings(edge_supersample=2))

    def f(direction, color):
        sun = tr.DirectionalLights(direction=direction.view(1, 1, 3),
                                   intensity=torch.full((1, 1), 3.0, dtype=torch.float64),
                                   color=torch.ones(1, 1, 3, dtype=torch.float64))
        scene.materials = [tr.Material(base_color_factor=torch.cat([color, color.new_ones(1)]),
                                       metallic_factor=0.0, roughness_factor=0.6)]
        out = renderer(scene, view, proj, tr.Lights(directional=sun))
        assert out.plan.edge_pixels > 0
        return (out.image * weights).sum()

    d = torch.tensor([-1.0, -2.0, -0.5], dtype=torch.float64, requires_grad=True)
    c = torch.tensor([0.8, 0.6, 0.4], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(f, (d, c), eps=1e-6, atol=1e-6, rtol=1e-5)
