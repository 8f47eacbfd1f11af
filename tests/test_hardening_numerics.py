"""Issue 22 (first list): crashes and wrong numbers found by adversarial probes.

Each test failed on the code before its fix. References: float32 evaluations of the same
(rounded) inputs for half precision, the scale invariance of unit normals (float64), the
compositing formula, the RGBE decoding formula, byte counts of the cache's own tensors.
"""

from __future__ import annotations

import base64
import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import trimesh
from PIL import Image

import torchraster as tr
from torchraster.hdr_io import MAX_RADIANCE, read_hdr
from torchraster.io import MeshFileError, load_scene
from torchraster.mesh import vertex_normals
from torchraster.mip_atlas import MipAtlas
from torchraster.renderer import _check_camera
from torchraster.shading.energy import dfg_terms
from torchraster.shading.ibl import dfg_lut, lookup_dfg
from torchraster.shading.shadows import ShadowMapCache, ShadowSettings
from torchraster.texture import sample_cube, sample_latlong, sample_texture
from torchraster.transparency import composite_over

HALF = (torch.float16, torch.bfloat16)


# ----------------------------------------------------------- 1. half precision lookups
def test_no_grid_sample_runs_in_half_precision(monkeypatch):
    """torch's CPU grid_sample backward segfaults on (large) float16 / bfloat16 inputs:
    no lookup may call it in half precision (forward and backward here)."""
    seen = []
    real = F.grid_sample

    def spy(input, grid, *args, **kwargs):
        seen.append((input.dtype, grid.dtype))
        return real(input, grid, *args, **kwargs)

    monkeypatch.setattr(F, "grid_sample", spy)
    g = torch.Generator().manual_seed(0)
    for dt in HALF:
        tex = torch.rand(1, 3, 16, 16, generator=g).to(dt).requires_grad_()
        uv = torch.rand(1, 2, 4, 4, generator=g).to(dt).requires_grad_()
        d = torch.full((1, 2, 4, 4), 0.1).to(dt)
        outs = [sample_texture(tex, uv, filter=f, duv_dx=d, duv_dy=d)
                for f in ("nearest", "bilinear", "trilinear", "anisotropic")]
        outs.append(MipAtlas([tex[0]]).sample(uv[0].flatten(1), d[0].flatten(1),
                                              d[0].flatten(1)))
        dirs = torch.randn(1, 3, 4, 4, generator=g).to(dt).requires_grad_()
        outs.append(sample_cube(torch.rand(1, 6, 3, 8, 8).to(dt).requires_grad_(), dirs))
        outs.append(sample_latlong(tex, dirs))
        nv = torch.rand(1, 1, 4, 4).to(dt).requires_grad_()
        lut = dfg_lut(8, 8)
        outs += list(lookup_dfg(lut, nv, nv)) + list(dfg_terms(lut, nv, nv))
        for o in outs:
            assert o.dtype == dt  # the policy: evaluated in float32, cast back
        sum(o.float().sum() for o in outs).backward()
        assert torch.isfinite(tex.grad).all() and torch.isfinite(uv.grad).all()
    assert seen and all(a == b == torch.float32 for a, b in seen), set(seen)


@pytest.mark.parametrize("dt", HALF)
def test_half_texture_lookups_equal_float32_lookups(dt):
    """A 300 x 400 texture: texel coordinates need more bits than float16 has. Reference:
    float32 lookups of the same half-rounded texture and UVs (the atlas path was off by
    0.8 before, i.e. the wrong texels)."""
    g = torch.Generator().manual_seed(1)
    tex = torch.rand(3, 300, 400, generator=g).to(dt)
    uv = torch.rand(2, 2000, generator=g).to(dt)
    d = torch.full((2, 2000), 1 / 400).to(dt)
    ref = MipAtlas([tex.float()]).sample(uv.float(), d.float(), d.float() * 0.5)
    got = MipAtlas([tex]).sample(uv, d, d * 0.5).float()
    tol = 2 * torch.finfo(dt).eps  # one rounding of values in [0, 1]
    assert (got - ref).abs().max() <= tol
    ref2 = sample_texture(tex.float()[None], uv.float().view(1, 2, 40, 50), filter="bilinear")
    got2 = sample_texture(tex[None], uv.view(1, 2, 40, 50), filter="bilinear").float()
    assert (got2 - ref2).abs().max() <= tol


def _stage(dtype, tex_size=32):
    """A 4 x 4 m floor and a sphere on it, a textured material, a sun casting shadows."""
    t = torch.linspace(-2.0, 2.0, 5, dtype=torch.float64)
    z, x = torch.meshgrid(t, t, indexing="ij")
    plane = torch.stack([x, torch.zeros_like(x), z], -1).view(-1, 3)
    c = (torch.arange(4)[:, None] * 5 + torch.arange(4)[None, :]).reshape(-1)
    quads = torch.stack([c, c + 5, c + 6, c + 1], -1)
    pf = torch.cat([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    sv = torch.as_tensor(sphere.vertices) + torch.tensor([0.0, 0.5, 0.0])
    sf = torch.as_tensor(sphere.faces, dtype=torch.int64) + len(plane)
    pos = torch.cat([plane, sv]).to(dtype).requires_grad_(True)
    faces = torch.cat([pf, sf])
    uvs = (pos.detach()[:, [0, 2]] / 4 + 0.5).contiguous()
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(3, tex_size, tex_size, generator=g).to(dtype).requires_grad_(True)
    mat = tr.Material(base_color_factor=torch.tensor([0.8, 0.6, 0.4, 1.0]),
                      metallic_factor=0.0, roughness_factor=0.5, base_color_texture=tex)
    scene = tr.RenderScene.from_mesh(tr.Mesh(pos, faces, uvs=uvs, material=mat))
    return scene, pos, tex


def _sun(dtype, direction=(-0.3, -1.0, -0.2)):
    d = torch.tensor([[direction]], dtype=dtype, requires_grad=True)
    lights = tr.Lights(
        ambient=tr.sh_from_color(torch.full((1, 3), 0.1, dtype=dtype)),
        directional=tr.DirectionalLights(d, torch.ones(1, 1, 3, dtype=dtype),
                                         torch.full((1, 1), 3.0, dtype=dtype),
                                         cast_shadows=torch.tensor([[True]])))
    return lights, d


def _render(dtype, filt, res=32, eye=(3.0, 3.0, 3.0), direction=(-0.3, -1.0, -0.2)):
    scene, pos, tex = _stage(dtype)
    lights, d = _sun(dtype, direction)
    view = tr.camera.look_at(torch.tensor(eye), torch.zeros(3)).to(dtype)
    proj = tr.camera.perspective(45.0, 1.0, 0.1, 100.0).to(dtype)
    r = tr.Renderer((res, res),
                    shadows=ShadowSettings(map_size=64, filter=filt),
                    raster=tr.RasterSettings(antialias=True))
    img = r(scene, view, proj, lights).image
    weights = torch.linspace(0, 1, img.numel()).view_as(img)
    (img.float() * weights).sum().backward()
    return img.detach().float(), pos.grad.float(), tex.grad.float(), d.grad.float()


@pytest.mark.parametrize("dt", HALF)
@pytest.mark.parametrize("filt", ["pcf", "vsm"])
def test_low_precision_renderer_textures_shadows(dt, filt):
    """float16 / bfloat16 mesh, texture, sun with shadow maps, antialiasing: forward and
    backward finite, two runs identical, and the light's gradient close to float32's
    (VSM gradients were NaN and runs differed)."""
    torch.manual_seed(0)
    a, b = _render(dt, filt), _render(dt, filt)
    ref = _render(torch.float32, filt)
    for x, y in zip(a, b, strict=True):
        assert torch.isfinite(x).all()
        assert torch.equal(x, y)
    tol = 0.05 if dt == torch.float16 else 0.1
    assert (a[3] - ref[3]).norm() <= tol * ref[3].norm()
    assert (a[0] - ref[0]).abs().mean() <= tol * ref[0].abs().mean()


# ------------------------------------------------------------------ 3. VSM slope bias
def test_vsm_sun_straight_down_has_finite_gradients():
    """cos = 1 between the floor's normal and the sun: d tan / d cos is infinite there."""
    img, gpos, gtex, gdir = _render(torch.float32, "vsm", direction=(0.0, -1.0, 0.0))
    assert torch.isfinite(gdir).all() and torch.isfinite(gpos).all()
    assert gdir.abs().sum() > 0


# ------------------------------------------------------------- 4. tiny vertex normals
@pytest.mark.parametrize("scale", [1e-3, 1e-6, 1e-7])
def test_vertex_normals_gradients_at_tiny_scales(scale):
    """n(s p) = n(p), so d n / d p at scale s = (1 / s) (d n / d p at scale 1): float32 at
    scale s against float64 at scale 1 (NaN before for edges <~ 1e-7). Slivers (1e-3 thin)
    at 1e-3 only: smaller, their cross products fall below NORMAL_EPS (degenerate)."""
    m = trimesh.creation.icosphere(subdivisions=1)
    faces = torch.tensor(m.faces)
    sliver = torch.tensor(m.vertices) * torch.tensor([1.0, 1.0, 1e-3])  # flat slivers too
    w = torch.randn(len(m.vertices), 3, generator=torch.Generator().manual_seed(0),
                    dtype=torch.float64)
    for verts in (torch.tensor(m.vertices), sliver) if scale >= 1e-3 else (
            torch.tensor(m.vertices),):
        p64 = verts.clone().requires_grad_(True)
        (vertex_normals(p64, faces) * w).sum().backward()
        p = (verts * scale).float().requires_grad_(True)
        n = vertex_normals(p, faces)
        (n * w.float()).sum().backward()
        assert torch.isfinite(p.grad).all()
        ref = p64.grad / scale
        assert (p.grad.double() - ref).abs().max() <= 1e-4 * ref.abs().max()


# ---------------------------------------------------------------- 5. distant cameras
@pytest.mark.parametrize("distance", [1e3, 1e4, 1e6])
def test_cameras_far_from_the_origin_are_not_singular(distance):
    eye = torch.tensor([distance, 0.3 * distance, -distance])
    view = tr.camera.look_at(eye, eye + torch.tensor([1.0, -0.2, 0.5]))
    assert _check_camera("view", view).shape == (1, 4, 4)
    assert _check_camera("proj", tr.camera.perspective(60.0, 1.5, 1e-6)).shape == (1, 4, 4)


def test_singular_cameras_are_still_rejected():
    rank3 = torch.eye(4)[[0, 0, 2, 3]] * 1e4
    rank3[:3, 3] = torch.tensor([5e3, 5e3, -2e3])
    for bad in (torch.zeros(4, 4), rank3, torch.ones(4, 4)):
        with pytest.raises(ValueError, match="view: .*singular"):
            _check_camera("view", bad)


# -------------------------------------------------------------- 6. BLEND, nothing opaque
def test_composite_over_with_no_layer():
    like = (torch.rand(2, 3, 4, 5), torch.rand(2, 1, 4, 5))
    total, trans = composite_over([], [], like=like)
    assert torch.equal(total, torch.zeros(2, 3, 4, 5))
    assert torch.equal(trans, torch.ones(2, 1, 4, 5))
    with pytest.raises(ValueError, match="colors"):
        composite_over([], [])


@pytest.mark.parametrize("empty_view", [True, False])
def test_blend_with_nothing_opaque_renders_the_background(empty_view):
    pos = torch.tensor([[-1.0, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    mat = tr.Material(base_color_factor=torch.tensor([1.0, 0.0, 0.0, 0.0]),
                      alpha_mode="BLEND", double_sided=True)
    scene = tr.RenderScene(pos, faces, materials=[mat])
    target = [0.0, 0.0, 0.0] if not empty_view else [0.0, 0.0, 10.0]  # look away
    view = tr.camera.look_at([0.0, 0.0, 3.0], target)
    bg = (0.2, 0.3, 0.4)
    out = tr.Renderer(8, shading="unlit", background=bg)(scene, view,
                                                          tr.camera.perspective(40.0, 1.0, 0.1))
    assert torch.allclose(out.image, torch.tensor(bg).view(1, 3, 1, 1).expand(1, 3, 8, 8))
    assert torch.equal(out.alpha, torch.zeros(1, 1, 8, 8))


# ---------------------------------------------------------------- 7. shadow-map cache
def _held_bytes(obj, seen=None) -> int:
    """Bytes of every tensor reachable from ``obj``'s attributes (storages counted once)."""
    seen = set() if seen is None else seen
    if isinstance(obj, torch.Tensor):
        key = obj.untyped_storage().data_ptr()
        if key in seen:
            return 0
        seen.add(key)
        return obj.untyped_storage().nbytes()
    if isinstance(obj, (list, tuple)):
        return sum(_held_bytes(o, seen) for o in obj)
    if isinstance(obj, dict):
        return sum(_held_bytes(o, seen) for o in obj.values())
    if hasattr(obj, "__dict__"):
        return _held_bytes(vars(obj), seen)
    return 0


def test_shadow_map_cache_stays_bounded_with_moving_geometry():
    m = trimesh.creation.icosphere(subdivisions=4)  # 2562 vertices, 5120 faces
    faces = torch.tensor(m.faces)
    base = torch.tensor(m.vertices, dtype=torch.float32)
    cache = ShadowMapCache(max_bytes=2**20)
    mats = torch.eye(4)[None] * torch.tensor([0.5, 0.5, 0.5, 1.0]).view(1, 4, 1)
    for step in range(60):  # a deforming mesh: new positions every call
        pos = (base * (1 + 0.01 * step))[None]
        cache.render(pos, faces, None, torch.zeros(1, dtype=torch.int64), mats, 32, 8)
    per_call = 32 * 32 * 4 + 16 * 4  # one map and its matrix
    assert _held_bytes(cache) <= cache.max_bytes
    assert _held_bytes(cache) <= 60 * per_call + 4096  # no copies of the casters
    assert cache.nbytes == _held_bytes(cache)
    # still a cache: the same casters again are not re-rendered
    renders = cache.renders
    cache.render(pos, faces, None, torch.zeros(1, dtype=torch.int64), mats, 32, 8)
    assert cache.renders == renders


# -------------------------------------------------------------------- 8. huge HDR texels
def _write_rgbe(path: Path, pixels: np.ndarray) -> None:
    h, w, _ = pixels.shape
    path.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n"
                     + f"-Y {h} +X {w}\n".encode() + pixels.astype(np.uint8).tobytes())


def test_hdr_with_maximum_texels_is_clamped_not_nan(tmp_path, caplog):
    px = np.zeros((4, 8, 4), np.uint8)
    px[..., :] = (128, 128, 128, 128)  # 0.5 + 1/512 by the RGBE formula
    px[1, 2] = (255, 255, 255, 255)  # (255.5) 2^119 ~ 1.7e38: legal, finite in float32
    _write_rgbe(tmp_path / "sky.hdr", px)
    with caplog.at_level(logging.WARNING, logger="torchraster"):
        img = read_hdr(tmp_path / "sky.hdr")
    assert "sky.hdr" in caplog.text and "MAX_RADIANCE" in caplog.text
    assert torch.equal(img[:, 1, 2], torch.full((3,), MAX_RADIANCE))
    assert torch.allclose(img[:, 0, 0], torch.full((3,), 128.5 / 256))
    env = tr.Environment(img, specular_size=4, specular_levels=2, specular_samples=2)
    scene, _, _ = _stage(torch.float32)
    lights, _ = _sun(torch.float32)
    view = tr.camera.look_at(torch.tensor([3.0, 3.0, 3.0]), torch.zeros(3))
    out = tr.Renderer(16, background=tr.BackgroundSettings(environment=True))(
        scene, view, tr.camera.perspective(45.0, 1.0, 0.1), lights, env)
    assert torch.isfinite(out.image).all()


# ------------------------------------------------------------ 9. unusable glTF textures
def _gltf(path: Path, uri: str) -> None:
    """A one-triangle glTF whose base colour texture is the file ``uri``."""
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32).tobytes()
    uv = np.array([[0, 0], [1, 0], [0, 1]], np.float32).tobytes()
    idx = np.array([0, 1, 2, 0], np.uint16).tobytes()
    blob = pos + uv + idx
    gltf = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(blob), "uri": "data:application/octet-stream;base64,"
                     + base64.b64encode(blob).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36},
                        {"buffer": 0, "byteOffset": 36, "byteLength": 24},
                        {"buffer": 0, "byteOffset": 60, "byteLength": 6}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
             "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC2"},
            {"bufferView": 2, "componentType": 5123, "count": 3, "type": "SCALAR"}],
        "images": [{"uri": uri}],
        "textures": [{"source": 0}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1},
                                    "indices": 2, "material": 0}]}],
        "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}], "scene": 0,
    }
    path.write_text(json.dumps(gltf))


def test_gltf_texture_that_is_not_an_image_is_an_error(tmp_path, caplog):
    (tmp_path / "tex.png").write_bytes(b"this is not a PNG")
    _gltf(tmp_path / "m.gltf", "tex.png")
    with pytest.raises(MeshFileError, match=r"m\.gltf.*tex\.png.*not an image"):
        load_scene(tmp_path / "m.gltf")
    with caplog.at_level(logging.WARNING, logger="torchraster"):
        scene = load_scene(tmp_path / "m.gltf", allow_missing_textures=True)
    assert "tex.png" in caplog.text and len(scene) == 1


def test_gltf_texture_outside_its_folder_is_an_error(tmp_path):
    Image.fromarray(np.full((2, 2, 3), 200, np.uint8)).save(tmp_path / "secret.png")
    (tmp_path / "model").mkdir()
    _gltf(tmp_path / "model" / "m.gltf", "../secret.png")
    with pytest.raises(MeshFileError, match=r"m\.gltf.*\.\./secret\.png.*outside"):
        load_scene(tmp_path / "model" / "m.gltf")
    # a texture beside the file still loads
    Image.fromarray(np.full((2, 2, 3), 200, np.uint8)).save(tmp_path / "model" / "ok.png")
    _gltf(tmp_path / "model" / "ok.gltf", "ok.png")
    mesh = load_scene(tmp_path / "model" / "ok.gltf").meshes[0]
    assert mesh.material.base_color_texture is not None
    assert math.isfinite(float(mesh.positions.sum()))
