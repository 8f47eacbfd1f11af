"""Renderer API: what it accepts, what it refuses, what it warns about, and the plan it ran."""

import gc
import warnings

import pytest
import torch
import trimesh

import torchraster as tr
from torchraster import camera

VIEW = camera.look_at([0.0, 0.0, 4.0], [0.0, 0.0, 0.0])
PROJ = camera.perspective(40.0, 1.0, 0.1)


def _quad(z: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """A unit quad in the z plane, counter-clockwise seen from +z (front faces the camera)."""
    pos = torch.tensor([[-1, -1, z], [1, -1, z], [1, 1, z], [-1, 1, z]], dtype=torch.float32)
    return pos, torch.tensor([[0, 1, 2], [0, 2, 3]])


def _ico(subdivisions: int = 2, radius: float = 1.0) -> tr.Mesh:
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return tr.Mesh(torch.tensor(ico.vertices, dtype=torch.float32), torch.tensor(ico.faces))


def test_single_sided_materials_cull_their_back_faces():
    pos, faces = _quad()
    behind = camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, 0.0])
    renderer = tr.Renderer(16, shading="unlit")
    seen = {}
    for name, mats in [("none", []), ("double", [tr.Material(double_sided=True)]),
                       ("single", [tr.Material(double_sided=False)])]:
        out = renderer(tr.RenderScene(pos, faces, materials=mats), behind, PROJ)
        seen[name] = float(out.alpha.sum())
        front = renderer(tr.RenderScene(pos, faces, materials=mats), VIEW, PROJ)
        assert float(front.alpha.sum()) > 50  # seen from the front: drawn in every case
    assert seen["none"] > 50 and seen["double"] == seen["none"] and seen["single"] == 0
    # per face: a two-material scene culls only the single-sided material's faces
    scene = tr.RenderScene(pos, faces, face_material=torch.tensor([0, 1]), materials=[
        tr.Material(double_sided=False), tr.Material(double_sided=True)])
    out = renderer(scene, behind, PROJ)
    assert 0 < float(out.alpha.sum()) < seen["none"]
    assert "cull single-sided" in str(out.plan)


def test_pbr_without_light_says_so_and_plans_unlit():
    pos, faces = _quad()
    with pytest.warns(UserWarning, match="no lights and no environment"):
        out = tr.Renderer(8, shading="pbr")(tr.RenderScene(pos, faces), VIEW, PROJ)
    assert out.plan.shading == "unlit" and "unlit" in out.plan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tr.Renderer(8, shading="unlit")(tr.RenderScene(pos, faces), VIEW, PROJ)


@pytest.mark.parametrize("background, match", [
    ((0.1, 0.2), "^BackgroundSettings.color: expected 3"),
    ((0.0, float("nan"), 0.0), "^BackgroundSettings.color: expected 3 finite"),
    ((-1.0, 0.0, 0.0), "^BackgroundSettings.color: expected 3 finite, non-negative"),
    ("red", "^background: expected a BackgroundSettings or 3 floats")])
def test_background_is_checked(background, match):
    with pytest.raises((ValueError, TypeError), match=match):
        tr.Renderer(8, background=background)


@pytest.mark.parametrize("face_material, match", [
    (torch.tensor([0, 2]), r"\[0, 2\)"), (torch.tensor([-1, 0]), r"\[0, 2\)"),
    (torch.tensor([0, 1, 1]), "face_material"), (torch.tensor([0.0, 1.0]), "integer")])
def test_face_material_is_checked(face_material, match):
    pos, faces = _quad()
    with pytest.raises((ValueError, TypeError), match=match):
        tr.RenderScene(pos, faces, face_material=face_material,
                       materials=[tr.Material(), tr.Material()])


@pytest.mark.parametrize("name", ["view", "proj"])
def test_singular_cameras_are_refused(name):
    pos, faces = _quad()
    cams = {"view": VIEW, "proj": PROJ}
    cams[name] = torch.zeros(4, 4)
    with pytest.raises(ValueError, match=f"{name}: .*singular"):
        tr.Renderer(8, shading="unlit")(tr.RenderScene(pos, faces), cams["view"], cams["proj"])


def test_scene_mismatches_name_the_field():
    pos, faces = _quad()
    with pytest.raises(ValueError, match="RenderScene.faces"):
        tr.RenderScene(pos, faces + 4)
    with pytest.raises(ValueError, match="RenderScene.uvs"):
        tr.RenderScene(pos, faces, uvs=torch.zeros(3, 2))
    with pytest.raises(TypeError, match="scene"):
        tr.Renderer(8, shading="unlit")("mesh.obj", VIEW, PROJ)
    with pytest.raises(ValueError, match="batch size"):
        tr.Renderer(8, shading="unlit")(tr.RenderScene(pos[None].expand(3, 4, 3), faces),
                                        VIEW.expand(2, 4, 4), PROJ)


def test_renderer_takes_meshes_scenes_and_batches_of_different_meshes():
    small, large = _ico(1, 0.5), _ico(2, 1.0)
    renderer = tr.Renderer(24, shading="headlight")
    alone = [renderer(m, VIEW, PROJ).image for m in (small, large)]
    both = renderer([small, large], VIEW, PROJ)  # item i draws mesh i
    assert both.image.shape == (2, 3, 24, 24)
    torch.testing.assert_close(both.image[0], alone[0][0], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(both.image[1], alone[1][0], rtol=1e-5, atol=1e-5)
    assert float(both.alpha[0].sum()) < float(both.alpha[1].sum())
    scene = tr.Scene([small, small], torch.stack([torch.eye(4), torch.eye(4)]), ["a", "b"])
    scene.transforms[1, 0, 3] = 1.5
    out = renderer(scene, VIEW, PROJ)
    assert float(out.alpha.sum()) > float(alone[0][0].ne(0).any(0).sum())


def test_plan_is_what_forward_ran():
    mesh = _ico(1)
    lights = tr.Lights(point=tr.PointLights(torch.tensor([[[0.0, 0, 3], [1, 1, 3]]]),
                                            torch.ones(1, 2, 3), torch.ones(1, 2)))
    r = tr.Renderer(8, shading="pbr", raster=tr.RasterSettings(supersample=2))
    plan = r.plan(tr.RenderScene.from_mesh(mesh), lights, None, {"depth"})
    out = r(mesh, VIEW, PROJ, lights, channels={"depth"})
    assert out.plan == plan
    assert list(out.plan) == plan.steps and str(out.plan) == "; ".join(plan.steps)
    assert plan.lights == (("point", 2),) and "light point x2" in plan
    assert set(out.gbuffer) == {"depth"} and plan.resolution == (16, 16)


def test_mip_cache_is_bounded_and_sees_in_place_edits():
    from torchraster.gbuffer import MipCache

    pos, faces = _quad()
    uvs = (pos[:, :2] + 1) / 2
    renderer = tr.Renderer(16, shading="unlit", textures=tr.TextureSettings(filter="bilinear"))
    tex = torch.full((3, 8, 8), 0.25)
    scene = tr.RenderScene(pos, faces, uvs=uvs, materials=[tr.Material(base_color_texture=tex)])
    first = renderer(scene, VIEW, PROJ).image
    tex.mul_(2.0)  # edited in place: the cached pyramid is stale
    second = renderer(scene, VIEW, PROJ).image
    torch.testing.assert_close(second, first * 2)
    cache = MipCache(max_bytes=3 * 8 * 8 * 4 * 2)  # room for about one pyramid
    renderer.mip_cache = cache
    for _ in range(5):
        texture = torch.rand(3, 8, 8)
        renderer(tr.RenderScene(pos, faces, uvs=uvs,
                                materials=[tr.Material(base_color_texture=texture)]), VIEW, PROJ)
    assert len(cache) == 1 and cache.nbytes <= cache.max_bytes
    del texture
    gc.collect()
    renderer(tr.RenderScene(pos, faces), VIEW, PROJ)
    cache.get(torch.zeros(1), lambda: None, torch.float32, torch.device("cpu"))
    assert len(cache) == 1  # the freed texture dropped out; the new one is in


def test_antialias_gives_silhouette_gradients_to_geometry():
    """d(sum alpha)/d(scale) of a square = 2 * area / scale (area in pixels ~ scale^2);
    without antialias the coverage has no gradient at all."""
    view = tr.camera.look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0])
    proj = tr.camera.perspective(40.0, 1.0, 0.1)
    base = torch.tensor([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0],
                         [-1.0, 1.0, 0.0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    scale = torch.tensor(0.37, dtype=torch.float64, requires_grad=True)
    scene = tr.RenderScene(base * scale, faces)
    out = tr.Renderer(64, shading="unlit", raster=tr.RasterSettings(antialias=True))(
        scene, view.double(), proj.double())
    assert "antialias" in out.plan
    area = out.alpha.sum()
    (grad,) = torch.autograd.grad(area, scale)
    assert float(grad) == pytest.approx(2 * float(area.detach()) / 0.37, rel=0.03)
    plain = tr.Renderer(64, shading="unlit")(tr.RenderScene(base * scale, faces), view.double(),
                                              proj.double())
    assert not plain.alpha.requires_grad


def test_antialias_topology_is_kept_only_for_equal_faces():
    """The Renderer keeps the edge adjacency of the last faces it antialiased: an equal
    faces tensor (a scene rebuilt every frame) reuses it, faces edited in place or new
    faces get their own, so every call equals a fresh Renderer's."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    pos = torch.tensor(mesh.vertices, dtype=torch.float32)
    faces = torch.tensor(mesh.faces)
    view = tr.camera.look_at([0.0, 0.4, 3.0], [0.0, 0.0, 0.0])
    proj = tr.camera.perspective(40.0, 1.0, 0.1)
    aa = tr.RasterSettings(antialias=True)
    renderer = tr.Renderer(48, shading="unlit", raster=aa)

    def same_as_fresh(scene):
        out = renderer(scene, view, proj)
        fresh = tr.Renderer(48, shading="unlit", raster=aa)(scene, view, proj)
        assert torch.equal(out.alpha, fresh.alpha) and torch.equal(out.image, fresh.image)
        return out

    first = same_as_fresh(tr.RenderScene(pos, faces))
    kept = renderer._kept_topology[1]
    same_as_fresh(tr.RenderScene(pos, faces.clone()))  # equal faces: the kept adjacency
    assert renderer._kept_topology[1] is kept
    faces[::2] = faces[::2].flip(1)  # edited in place (winding of every other face)
    same_as_fresh(tr.RenderScene(pos, faces))
    assert renderer._kept_topology[1] is not kept
    half = tr.RenderScene(pos, faces[: len(faces) // 2])  # other faces: a hole, new edges
    assert not torch.equal(same_as_fresh(half).alpha, first.alpha)


@pytest.mark.parametrize("shading", ["pbr", "unlit"])
def test_neutral_ao_and_emissive_are_not_computed(shading):
    """Without occlusion textures and emissive factors the G-buffer skips ``ao`` and
    ``emissive`` (the shading pass takes None as 1 and 0): the image equals the one with
    both channels computed (requested), bit for bit; a material that emits, has an
    occlusion texture, or takes gradients through its emissive factor gets them."""
    mesh = _ico(2)
    sun = tr.DirectionalLights(torch.tensor([[[0.3, -1.0, -0.4]]]), torch.ones(1, 1, 3),
                               torch.full((1, 1), 2.0))
    sh = torch.zeros(1, 9, 3)
    sh[0, 0] = 0.3
    lights = tr.Lights(directional=sun, ambient=sh)
    env = tr.Environment(torch.rand(1, 3, 16, 32) * 2)
    mats = [tr.Material(base_color_factor=(0.8, 0.4, 0.2, 1.0), roughness_factor=0.5,
                        metallic_factor=0.3)]
    scene = tr.RenderScene(mesh.positions, mesh.faces, materials=mats)
    r = tr.Renderer(24, shading=shading)
    plan = r.plan(scene, lights, env)
    assert "ao" not in plan.channels and "emissive" not in plan.channels
    with torch.no_grad():
        out = r(scene, VIEW, PROJ, lights, env)
        both = r(scene, VIEW, PROJ, lights, env, channels={"ao", "emissive"})
    assert torch.equal(out.image, both.image) and torch.equal(out.alpha, both.alpha)
    assert bool((both.gbuffer["ao"][both.alpha > 0] == 1).all())
    glow = torch.zeros(3, requires_grad=True)
    for mat, need in ((tr.Material(emissive_factor=torch.tensor([0.0, 0.5, 0.0])), "emissive"),
                      (tr.Material(emissive_factor=glow), "emissive"),
                      (tr.Material(occlusion_texture=torch.rand(1, 4, 4)), "ao")):
        if shading == "unlit" and need == "ao":
            continue  # unlit reads no ao
        other = tr.RenderScene(mesh.positions, mesh.faces, materials=[mats[0], mat],
                               face_material=torch.arange(len(mesh.faces)) % 2)
        assert need in r.plan(other, lights, env).channels
    out = r(tr.RenderScene(mesh.positions, mesh.faces, materials=[tr.Material(
        emissive_factor=glow)]), VIEW, PROJ, lights, env)
    (grad,) = torch.autograd.grad(out.image.sum(), glow)
    assert bool((grad > 0).all())  # every covered pixel emits: d image / d glow = coverage


def test_unlit_image_is_not_the_albedo_channel():
    """Unlit without emission shades the albedo itself: the image is a new frame, so the
    background and masking done in place on the image leave the albedo channel alone."""
    mesh = _ico(1)
    scene = tr.RenderScene(mesh.positions, mesh.faces,
                           materials=[tr.Material(base_color_factor=(0.2, 0.4, 0.6, 1.0))])
    with torch.no_grad():
        out = tr.Renderer(16, shading="unlit", background=(0.5, 0.5, 0.5))(
            scene, VIEW, PROJ, channels={"albedo"})
    albedo, covered = out.gbuffer["albedo"], out.alpha > 0
    assert bool(covered.any()) and bool((~covered).any())
    assert bool((albedo * ~covered == 0).all())  # no background in the channel
    assert torch.allclose(albedo[:, 2][covered[:, 0]], torch.tensor(0.6))
    assert torch.allclose(out.image[:, 0][~covered[:, 0]], torch.tensor(0.5))
