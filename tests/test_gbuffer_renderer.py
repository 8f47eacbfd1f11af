"""G-buffer and Renderer against analytic scenes (ray-plane and ray-sphere intersections)."""

import math

import pytest
import torch
import trimesh

import torchraster as tr
from torchraster import camera
from torchraster.config import lights_from_config
from torchraster.gbuffer import geometry_pass, required_inputs
from torchraster.renderer import view_rays
from torchraster.shading.ibl import Environment

H = W = 48


def _quad(z=-5.0, size=3.0):
    pos = torch.tensor([[-size, -size, z], [size, -size, z], [size, size, z], [-size, size, z]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    uvs = (pos[:, :2] + size) / (2 * size)
    normals = torch.tensor([[0.0, 0.0, 1.0]]).expand(4, 3)
    return pos, faces, uvs, normals


def _camera(eye=(0.4, -0.3, 1.0), target=(0.0, 0.2, -5.0), fov=60.0):
    view = camera.look_at(list(eye), list(target))
    proj = camera.perspective(fov, W / H, 0.1)
    return view, proj


def _plane_hits(view, proj, z):
    """Analytic world positions where each pixel's ray meets the plane at height z."""
    eye = torch.linalg.inv(view)[0, :3, 3]
    rays = view_rays(view, proj, (H, W))[0]  # (3, H, W)
    t = (z - eye[2]) / rays[2]
    return eye[:, None, None] + t * rays, t


def test_only_requested_channels_are_computed():
    pos, faces, uvs, normals = _quad()
    view, proj = _camera()
    frags = tr.rasterize(camera.transform_points(pos, proj @ view), faces, (H, W))
    for request in [{"normal"}, {"depth", "mask"}, {"albedo"}, set()]:
        out = geometry_pass(frags, request, positions=pos, view=view, normals=normals, uvs=uvs)
        assert set(out.channels()) == request


def test_required_inputs_follow_material_textures():
    plain = tr.Material()
    textured = tr.Material(base_color_texture=torch.zeros(3, 4, 4, dtype=torch.uint8))
    assert required_inputs({"albedo"}, [plain]) == set()
    assert required_inputs({"albedo"}, [plain, textured]) >= {"uv", "texture:base_color"}
    assert "uv" not in required_inputs({"normal", "depth"}, [textured])
    assert required_inputs({"depth"}, []) == {"position"}
    with pytest.raises(ValueError, match="unknown"):
        required_inputs({"colour"}, [])


def test_position_depth_normal_match_ray_plane_intersection():
    z = -5.0
    pos, faces, uvs, normals = _quad(z)
    view, proj = _camera()
    frags = tr.rasterize(camera.transform_points(pos, proj @ view), faces, (H, W))
    out = geometry_pass(frags, {"position", "depth", "normal", "mask"}, positions=pos,
                        view=view, normals=normals, uvs=uvs)
    hits, _ = _plane_hits(view, proj, z)
    m = out.mask[0, 0] > 0
    assert m.float().mean() > 0.5
    err = (out.position[0] - hits).norm(dim=0)[m]
    assert err.max() < 1e-4 * 6
    # linear view depth = distance along the view axis
    z_view = (view[0, 2, :3, None, None] * hits).sum(0) + view[0, 2, 3]
    assert (out.depth[0, 0][m] + z_view[m]).abs().max() < 1e-4
    assert torch.allclose(out.normal[0][:, m], torch.tensor([0.0, 0.0, 1.0])[:, None], atol=1e-6)


def test_textured_albedo_matches_analytic_uv():
    z, size = -5.0, 3.0
    pos, faces, uvs, normals = _quad(z, size)
    view, proj = _camera()
    # a linear ramp in u (red) and v (green): bilinear filtering reproduces it exactly
    n = 64
    ramp_u = (torch.arange(n) + 0.5) / n
    tex = torch.stack([ramp_u.expand(n, n), ramp_u.flip(0)[:, None].expand(n, n),
                       torch.zeros(n, n)])  # row 0 = top = v near 1
    mat = tr.Material(base_color_texture=tex)
    frags = tr.rasterize(camera.transform_points(pos, proj @ view), faces, (H, W))
    out = geometry_pass(frags, {"albedo", "mask"}, positions=pos, view=view, normals=normals,
                        uvs=uvs, materials=[mat], texture_filter="bilinear")
    hits, _ = _plane_hits(view, proj, z)
    u = (hits[0] + size) / (2 * size)
    v = (hits[1] + size) / (2 * size)
    inner = (out.mask[0, 0] > 0) & (u > 0.02) & (u < 0.98) & (v > 0.02) & (v < 0.98)
    assert (out.albedo[0, 0][inner] - u[inner]).abs().max() < 1e-4
    assert (out.albedo[0, 1][inner] - v[inner]).abs().max() < 1e-4


def _sphere_scene(subdivisions=5):
    ico = trimesh.creation.icosphere(subdivisions=subdivisions)
    pos = torch.tensor(ico.vertices, dtype=torch.float32)
    return tr.RenderScene(pos, torch.tensor(ico.faces), normals=pos.clone())


def test_headlight_sphere_matches_closed_form_lambert():
    scene = _sphere_scene()
    eye = torch.tensor([0.0, 0.0, 4.0])
    view = camera.look_at(eye, [0.0, 0.0, 0.0])
    proj = camera.perspective(40.0, 1.0, 0.1)
    out = tr.Renderer((H, W), shading="headlight")(scene, view, proj)
    # analytic ray-sphere intersection, Lambert lit from the eye with E = pi
    d = view_rays(view, proj, (H, W))[0]
    b = (d * eye[:, None, None]).sum(0)
    disc = b * b - (eye.dot(eye) - 1.0)
    hit_mask = disc > 0.05  # away from the silhouette (tessellation)
    t = -b - disc.clamp(min=0).sqrt()
    hit = eye[:, None, None] + t * d
    expected = (hit * (-d)).sum(0)  # n . to_eye with n = hit on the unit sphere
    img = out.image[0]
    assert (img[0][hit_mask] - expected[hit_mask]).abs().max() < 0.03
    assert img[:, 0, 0].abs().max() == 0  # background black, nothing covered
    assert out.alpha[0, 0][hit_mask].min() == 1


def test_plan_runs_only_what_the_scene_needs():
    scene = _sphere_scene(2)
    view = camera.look_at([0.0, 0.0, 4.0], [0.0, 0.0, 0.0])
    proj = camera.perspective(40.0, 1.0, 0.1)
    r = tr.Renderer((16, 16), shading="pbr")
    out = r(scene, view, proj, lights_from_config([{"type": "directional"}]))
    assert any(p.startswith("light directional") for p in out.plan)
    assert not any("ibl" in p for p in out.plan)
    assert not any("point" in p or "spot" in p for p in out.plan)
    env = Environment(torch.ones(3, 8, 16), specular_size=8, specular_levels=3)
    out = r(scene, view, proj, None, env)
    assert "ibl" in out.plan and "background environment" in out.plan
    assert not any(p.startswith("light") for p in out.plan)


def test_gradients_reach_materials_lights_and_vertices():
    scene = _sphere_scene(2)
    scene.positions.requires_grad_(True)
    color = torch.tensor([0.8, 0.5, 0.3, 1.0], requires_grad=True)
    scene.materials = [tr.Material(base_color_factor=color, metallic_factor=0.0,
                                   roughness_factor=0.5)]
    lights = lights_from_config([{"type": "point", "position": [2, 2, 3], "intensity": 20}])
    lights.point.intensity.requires_grad_(True)
    view = camera.look_at([0.0, 0.0, 4.0], [0.0, 0.0, 0.0])
    proj = camera.perspective(40.0, 1.0, 0.1)
    out = tr.Renderer((24, 24), shading="pbr")(scene, view, proj, lights)
    (out.image * torch.linspace(0, 1, 24)).sum().backward()
    for g in (color.grad[:3], lights.point.intensity.grad, scene.positions.grad):
        assert torch.isfinite(g).all() and g.abs().sum() > 0


def test_supersampling_antialiases_edges():
    scene = _sphere_scene(3)
    view = camera.look_at([0.0, 0.0, 4.0], [0.0, 0.0, 0.0])
    proj = camera.perspective(40.0, 1.0, 0.1)
    alpha1 = tr.Renderer((32, 32), shading="unlit", raster=tr.RasterSettings(supersample=1))(
        scene, view, proj).alpha
    alpha4 = tr.Renderer((32, 32), shading="unlit", raster=tr.RasterSettings(supersample=4))(
        scene, view, proj).alpha
    partial = ((alpha4 > 0) & (alpha4 < 1)).sum()
    assert ((alpha1 > 0) & (alpha1 < 1)).sum() == 0 and partial > 20
    # coverage converges to the analytic disc area: r_px = f * 1/sqrt(d^2 - 1)
    f = 16 / math.tan(math.radians(20))
    area = math.pi * (f / math.sqrt(15)) ** 2
    assert abs(float(alpha4.sum()) - area) / area < 0.02


def test_gradients_reach_textures_and_environment_twice():
    """Optimisation loops call the renderer repeatedly: no stale cached graph."""
    pos, faces, uvs, normals = _quad(-5.0)
    view, proj = _camera()
    tex = torch.full((3, 8, 8), 0.5, requires_grad=True)
    radiance = torch.ones(3, 8, 16, requires_grad=True)
    scene = tr.RenderScene(pos, faces, normals, uvs, materials=[
        tr.Material(base_color_texture=tex, metallic_factor=0.0, roughness_factor=0.6)])
    renderer = tr.Renderer((16, 16), shading="pbr")
    for _ in range(2):
        env = Environment(radiance, specular_size=8, specular_levels=3)
        out = renderer(scene, view, proj, None, env)
        (out.image * out.alpha).sum().backward()
        for g in (tex.grad, radiance.grad):
            assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0
        tex.grad = radiance.grad = None


def test_octahedral_normals_round_trip():
    from torchraster.gbuffer import decode_octahedral, encode_octahedral

    n = torch.nn.functional.normalize(torch.randn(2, 3, 32, 32, dtype=torch.float64), dim=1)
    n[0, :, 0, 0] = torch.tensor([0.0, 0.0, -1.0])  # the folded pole
    n[0, :, 0, 1] = torch.tensor([1.0, 0.0, 0.0])  # the equator
    code = encode_octahedral(n)
    assert code.shape == (2, 2, 32, 32) and code.abs().max() <= 1
    assert (decode_octahedral(code) - n).abs().max() < 1e-12
    # stored as float16 (11-bit mantissa) the angular error stays below 0.1 degree
    back = decode_octahedral(code.half().double())
    angle = torch.rad2deg(torch.acos((back * n).sum(1).clamp(-1, 1)))
    assert angle.max() < 0.1


def test_ssao_feeds_the_lighting_pass():
    """A box corner: SSAO darkens the ambient light in the crease, and the plan says so."""
    from torchraster.post import SSAO

    floor = torch.tensor([[-2, 0, -2], [2, 0, -2], [2, 0, 2], [-2, 0, 2]], dtype=torch.float32)
    wall = torch.tensor([[-2, 0, -2], [2, 0, -2], [2, 4, -2], [-2, 4, -2]], dtype=torch.float32)
    pos = torch.cat([floor, wall])
    faces = torch.tensor([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7]])
    normals = torch.tensor([[0.0, 1.0, 0.0]] * 4 + [[0.0, 0.0, 1.0]] * 4)
    scene = tr.RenderScene(pos, faces, normals, materials=[
        tr.Material(metallic_factor=0.0, roughness_factor=1.0)])
    view = camera.look_at([0.0, 1.5, 3.0], [0.0, 0.5, -2.0])
    proj = camera.perspective(60.0, 1.0, 0.1)
    ambient = lights_from_config([{"type": "ambient", "intensity": 1.0}])
    plain = tr.Renderer((48, 48), shading="pbr")(scene, view, proj, ambient)
    occluded = tr.Renderer((48, 48), shading="pbr", ssao=SSAO(radius=0.5))(
        scene, view, proj, ambient)
    assert "ssao" in occluded.plan and "ssao" not in plain.plan
    ratio = occluded.image.mean(1) / plain.image.mean(1).clamp(min=1e-6)
    assert ratio.max() <= 1.0 + 1e-5 and ratio.min() < 0.8  # only darker, clearly in the crease


def test_plan_lists_exactly_the_computed_channels():
    from torchraster.post import SSAO

    scene = _sphere_scene(2)
    view = camera.look_at([0.0, 0.0, 4.0], [0.0, 0.0, 0.0])
    proj = camera.perspective(40.0, 1.0, 0.1)
    ambient = lights_from_config([{"type": "ambient"}])
    out = tr.Renderer((16, 16), shading="pbr", ssao=SSAO())(scene, view, proj, ambient)
    gbuffer = next(p for p in out.plan if p.startswith("gbuffer "))
    assert "depth" in gbuffer.split(" ")[1].split(",") and "ssao" in out.plan
    out = tr.Renderer((16, 16), shading="headlight")(scene, view, proj)
    gbuffer = next(p for p in out.plan if p.startswith("gbuffer "))
    assert set(gbuffer.split(" ")[1].split(",")) == {"albedo", "mask", "normal", "position"}
