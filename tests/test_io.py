"""Loading the shared real assets, scenes with node transforms, and every kind of bad file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from torchraster.io import (
    ASSETS_DIR,
    MeshFileError,
    Scene,
    load_mesh,
    load_scene,
    load_spot,
    load_texture,
)
from torchraster.material import Material
from torchraster.mesh import Mesh, face_normals

# (relative path, faces, vertices) as stated in SOURCES.md; vertices None where trimesh drops
# unreferenced ones (stanford-bunny.obj: 35,947 in the file, 34,834 referenced).
# DamagedHelmet (15,452) and MaterialsVariantsShoe (22,700) are checked in their own tests.
MESHES = [
    ("meshes/suzanne.obj", 968, 507),
    ("meshes/stanford-bunny-res2.ply", 16301, 8171),
    ("meshes/teapot.obj", 6320, 3644),
    ("meshes/fandisk.obj", 12946, 6475),
    ("meshes/spot/spot_triangulated.obj", 5856, 3225),
    ("meshes/fuze/fuze.obj", 1000, 664),
    ("meshes/armadillo-50k.obj", 50000, 25002),
    ("meshes/stanford-bunny.obj", 69451, 34834),
    ("gltf/BoxTextured.glb", 12, None),
]


def pil_array(path: Path) -> np.ndarray:
    return np.array(Image.open(path).convert("RGB"))


@pytest.fixture(scope="module")
def helmet(shared_data: Path) -> Mesh:
    return load_mesh(shared_data / "gltf/DamagedHelmet/DamagedHelmet.gltf")


# ------------------------------------------------------------------------ every shared file
@pytest.mark.parametrize(("rel", "faces", "verts"), MESHES)
def test_face_counts_match_sources(shared_data: Path, rel: str, faces: int,
                                   verts: int | None) -> None:
    mesh = load_mesh(shared_data / rel, max_texture_size=64)
    assert mesh.num_faces == faces
    if verts is not None:
        assert mesh.num_vertices == verts
    assert mesh.positions.dtype == torch.float32 and mesh.faces.dtype == torch.int64
    used = torch.unique(mesh.faces)  # (bunny-res2 has 30 unreferenced vertices: normal 0)
    torch.testing.assert_close(mesh.normals[used].norm(dim=-1), torch.ones(len(used)))
    # file order and geometry preserved: same triangles as trimesh reports
    ref = trimesh.load(shared_data / rel, force="mesh", process=False)
    np.testing.assert_allclose(mesh.positions[mesh.faces].sum().item(),
                               ref.vertices[ref.faces].sum(), rtol=1e-5)


def test_damaged_helmet(shared_data: Path, helmet: Mesh) -> None:
    d = shared_data / "gltf/DamagedHelmet"
    assert helmet.num_faces == 15452 and helmet.uvs is not None
    m = helmet.material
    assert m.name == "Material_MR"
    for slot in ("base_color_texture", "metallic_roughness_texture", "normal_texture",
                 "emissive_texture", "occlusion_texture"):
        tex = getattr(m, slot)
        assert tex is not None and tex.dtype == torch.uint8 and tex.shape[1:] == (2048, 2048)
    # factors: the JSON gives emissiveFactor 1 and omits the others (glTF defaults)
    assert m.base_color_factor.tolist() == [1, 1, 1, 1]
    assert m.metallic_factor == 1.0 and m.roughness_factor == 1.0
    assert m.emissive_factor.tolist() == [1, 1, 1]
    assert m.alpha_mode == "OPAQUE" and not m.double_sided
    # texture content equals the JPEGs decoded independently by PIL, slot by slot
    albedo = pil_array(d / "Default_albedo.jpg")
    assert torch.equal(m.base_color_texture[:3].permute(1, 2, 0), torch.from_numpy(albedo))
    mr = pil_array(d / "Default_metalRoughness.jpg")
    assert torch.equal(m.metallic_roughness_texture.permute(1, 2, 0), torch.from_numpy(mr))
    ao = pil_array(d / "Default_AO.jpg")[:, :, 0]
    assert torch.equal(m.occlusion_texture[0], torch.from_numpy(ao))
    em = pil_array(d / "Default_emissive.jpg")
    assert torch.equal(m.emissive_texture.permute(1, 2, 0), torch.from_numpy(em))
    # compact storage: uint8, occlusion only one channel: 4 * 3 + 1 planes of 2048^2
    assert m.texture_nbytes == 13 * 2048 * 2048
    assert helmet.tangents is not None  # has a normal map -> tangents computed
    # the node rotation is applied: world bounds equal trimesh's scene bounds
    ref = trimesh.load(d / "DamagedHelmet.gltf").bounds
    b = torch.stack([helmet.positions.amin(0), helmet.positions.amax(0)])
    np.testing.assert_allclose(b.numpy(), ref, atol=1e-5)


def test_max_texture_size(shared_data: Path) -> None:
    m = load_mesh(shared_data / "gltf/BoxTextured.glb", max_texture_size=64).material
    assert m.base_color_texture.shape[1:] == (64, 64)
    with pytest.raises(ValueError, match="max_texture_size"):
        load_scene(shared_data / "gltf/BoxTextured.glb", max_texture_size=0)
    # JPEGs are decoded at a reduced DCT scale first: still close to a 4x4 area average
    small = load_mesh(shared_data / "meshes/fuze/fuze.obj", max_texture_size=256)
    tex = small.material.base_color_texture.permute(1, 2, 0).numpy().astype(np.float64)
    full = pil_array(shared_data / "meshes/fuze/fuze uv.jpg").astype(np.float64)
    ref = full.reshape(256, 4, 256, 4, 3).mean(axis=(1, 3))
    assert tex.shape == (256, 256, 3) and np.abs(tex - ref).mean() < 2.0


def test_materials_variants_shoe_default_material(shared_data: Path) -> None:
    d = shared_data / "gltf/MaterialsVariantsShoe"
    shoe = load_mesh(d / "MaterialsVariantsShoe.gltf")
    assert shoe.num_faces == 22700
    m = shoe.material
    header = json.loads((d / "MaterialsVariantsShoe.gltf").read_text())
    mat_index = header["meshes"][0]["primitives"][0]["material"]  # the default (no variant)
    tex_index = header["materials"][mat_index]["pbrMetallicRoughness"]["baseColorTexture"]
    uri = header["images"][header["textures"][tex_index["index"]]["source"]]["uri"]
    assert uri == "diffuseMidnight.jpg"
    assert torch.equal(m.base_color_texture.permute(1, 2, 0),
                       torch.from_numpy(pil_array(d / uri)))
    orm = pil_array(d / "occlusionRougnessMetalness.jpg")
    assert torch.equal(m.metallic_roughness_texture.permute(1, 2, 0), torch.from_numpy(orm))
    assert torch.equal(m.occlusion_texture[0], torch.from_numpy(orm[:, :, 0]))
    assert (m.occlusion_texture.untyped_storage().data_ptr()
            == m.metallic_roughness_texture.untyped_storage().data_ptr())  # packed, shared
    assert m.normal_texture.shape == (3, 1024, 1024) and m.emissive_texture is None
    assert m.metallic_factor == 1.0 and m.roughness_factor == 1.0
    assert m.normal_scale == 1.0 and m.occlusion_strength == 1.0
    assert shoe.tangents is not None and shoe.tangents[:, 3].abs().eq(1).all()


def test_cesium_milk_truck_scene(shared_data: Path) -> None:
    path = shared_data / "gltf/CesiumMilkTruck.glb"
    scene = load_scene(path, max_texture_size=256)
    assert len(scene) == 5  # 4 meshes, the wheels instanced twice
    unique = {id(m): m for m in scene.meshes}
    assert len(unique) == 4 and sum(m.num_faces for m in unique.values()) == 2856
    flat, face_mat, mats = scene.flatten()
    names = {m.name for m in mats}
    assert {"truck", "glass", "window_trim", "wheels"} == names
    assert flat.num_faces == 2856 + 768 and face_mat.shape == (flat.num_faces,)
    assert flat.material is None and face_mat.min() == 0 and face_mat.max() == len(mats) - 1
    glass = next(m for m in mats if m.name == "glass")
    # exact float factors from the glTF JSON (trimesh rounds them to 8 bits)
    np.testing.assert_allclose(glass.base_color_factor.numpy(),
                               [0.0, 0.04050629958510399, 0.021240700036287308, 1.0], rtol=1e-6)
    assert glass.base_color_texture is None
    wheels = next(m for m in mats if m.name == "wheels")
    assert wheels.base_color_texture is not None
    assert int((face_mat == mats.index(wheels)).sum()) == 2 * 768
    # node transforms: world bounds against trimesh's independent scene bounds
    ref = trimesh.load(path).bounds
    np.testing.assert_allclose(scene.bounds().numpy(), ref, atol=1e-5)
    b = torch.stack([flat.positions.amin(0), flat.positions.amax(0)])
    np.testing.assert_allclose(b.numpy(), ref, atol=1e-5)
    # the two wheel instances sit at different places
    wheel_idx = [i for i, m in enumerate(scene.meshes) if m.material is wheels]
    assert len(wheel_idx) == 2
    assert not torch.allclose(scene.transforms[wheel_idx[0]], scene.transforms[wheel_idx[1]])
    # a mesh carries one material: load_mesh refuses and points at load_scene
    with pytest.raises(MeshFileError, match="load_scene") as err:
        load_mesh(path)
    assert str(path) in str(err.value)


def test_fuze_obj_mtl_with_space_in_texture_name(shared_data: Path) -> None:
    d = shared_data / "meshes/fuze"
    mesh = load_mesh(d / "fuze.obj")
    m = mesh.material
    assert m.name == "a-super-duper-material"
    assert torch.equal(m.base_color_texture.permute(1, 2, 0),
                       torch.from_numpy(pil_array(d / "fuze uv.jpg")))
    assert m.base_color_factor.tolist() == [1, 1, 1, 1] and m.metallic_factor == 0.0
    assert m.roughness_factor == 1.0  # Ns 0
    assert mesh.uvs is not None and mesh.uvs.shape == (664, 2)


def test_box_textured_glb(shared_data: Path) -> None:
    path = shared_data / "gltf/BoxTextured.glb"
    mesh = load_mesh(path)
    ref = trimesh.load(path, force="mesh", process=False)
    tex = mesh.material.base_color_texture
    img = np.array(ref.visual.material.baseColorTexture)
    assert tuple(tex.shape[1:]) == (256, 256)
    assert torch.equal(tex.permute(1, 2, 0), torch.from_numpy(img[:, :, : tex.shape[0]]))
    # UV convention: the raw glTF TEXCOORD_0 (origin top-left, v down), read straight from
    # the GLB's binary chunk, maps to (u, 1 - v)
    raw = path.read_bytes()
    json_len = int.from_bytes(raw[12:16], "little")
    header = json.loads(raw[20:20 + json_len])
    binary = raw[20 + json_len + 8:]
    acc = header["accessors"][header["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]]
    view = header["bufferViews"][acc["bufferView"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    uv_gltf = np.frombuffer(binary, np.float32, acc["count"] * 2, start).reshape(-1, 2)
    np.testing.assert_allclose(mesh.uvs[:, 0].numpy(), uv_gltf[:, 0])
    np.testing.assert_allclose(mesh.uvs[:, 1].numpy(), 1.0 - uv_gltf[:, 1], atol=1e-6)
    assert mesh.material.metallic_factor == 0.0


def test_ply_with_extra_vertex_properties(shared_data: Path) -> None:
    path = shared_data / "meshes/stanford-bunny-res2.ply"
    mesh = load_mesh(path)
    lines = path.read_text().splitlines()
    start = lines.index("end_header") + 1
    xyz = np.array([[float(v) for v in ln.split()[:3]] for ln in lines[start:start + 8171]])
    faces = np.array([[int(v) for v in ln.split()[1:4]]
                      for ln in lines[start + 8171:start + 8171 + 16301]])
    np.testing.assert_allclose(mesh.positions.numpy(), xyz, rtol=1e-6)
    assert np.array_equal(mesh.faces.numpy(), faces)
    assert mesh.material is None and mesh.uvs is None


def test_file_normals_are_used(shared_data: Path) -> None:
    path = shared_data / "meshes/suzanne.obj"
    mesh = load_mesh(path)
    vn = np.array([[float(v) for v in ln.split()[1:4]]
                   for ln in path.read_text().splitlines() if ln.startswith("vn ")])
    vn /= np.linalg.norm(vn, axis=1, keepdims=True)
    np.testing.assert_allclose(mesh.normals.numpy(), vn, atol=1e-6)


def test_shipped_spot_asset() -> None:
    assert (ASSETS_DIR / "spot" / "README.txt").is_file()
    png = ASSETS_DIR / "spot" / "spot_texture.png"
    assert png.stat().st_size < 1_000_000
    spot = load_spot()
    assert spot.num_faces == 5856 and spot.uvs is not None and spot.normals is not None
    tex = spot.material.base_color_texture
    assert torch.equal(tex.permute(1, 2, 0), torch.from_numpy(pil_array(png)))
    assert spot.material.metallic_factor == 0.0
    # the OBJ itself has no MTL: no trimesh placeholder material leaks through
    assert load_mesh(ASSETS_DIR / "spot" / "spot_triangulated.obj").material is None
    assert load_spot(max_texture_size=128).material.base_color_texture.shape == (3, 128, 128)


# ------------------------------------------------------------------------------ Scene
def test_scene_flatten_rewinds_mirrored_instances() -> None:
    pos = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    mesh = Mesh(pos, torch.tensor([[0, 1, 2]]), normals=torch.tensor([[0.0, 0, 1]] * 3))
    mirror = torch.diag(torch.tensor([-1.0, 1, 1, 1]))
    shift = torch.eye(4)
    shift[:3, 3] = torch.tensor([5.0, 0, 0])
    scene = Scene([mesh, mesh], torch.stack([mirror, shift]), ["a", "b"])
    flat, face_mat, mats = scene.flatten()
    assert len(mats) == 1 and isinstance(mats[0], Material)  # default material for None
    assert face_mat.tolist() == [0, 0] and flat.material is mats[0]
    # front faces stay counter-clockwise: geometric normals agree with shading normals
    fn = face_normals(flat.positions, flat.faces)
    torch.testing.assert_close(fn, flat.normals[flat.faces[:, 0]])
    torch.testing.assert_close(scene.bounds(), torch.tensor([[-1.0, 0, 0], [6, 1, 0]]))
    with pytest.raises(ValueError, match="transforms"):
        Scene([mesh], torch.eye(4), ["a"])


# ------------------------------------------------------------------------------ errors
BAD_FILES = {
    "oor.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 5\n",
    "negative.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -9\n",
    "nan.obj": b"v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n",
    "inf.obj": b"v 0 0 0\nv inf 0 0\nv 0 1 0\nf 1 2 3\n",
    "points.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\n",
    "lines.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2 3\n",
    "junk.obj": b"garbage here\n\x00\x01\x02",
    "empty.obj": b"",
    "points.ply": b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
    b"property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n",
    "corrupt.ply": b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n0 0\n",
    "oor.ply": b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
    b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
    b"0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n",
    "truncated.gltf": b'{"asset": {"version": "2.0"}, "meshes": [',
    "nobuffer.gltf": b'{"asset": {"version": "2.0"}, "buffers": [{"uri": "missing.bin", '
    b'"byteLength": 36}], "bufferViews": [{"buffer": 0, "byteLength": 36}], "accessors": '
    b'[{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}], "meshes": '
    b'[{"primitives": [{"attributes": {"POSITION": 0}}]}], "nodes": [{"mesh": 0}], '
    b'"scenes": [{"nodes": [0]}]}',
    "corrupt.glb": b"glTF\x02\x00\x00\x00",
    "random.glb": bytes(range(256)) * 4,
}


@pytest.mark.parametrize("name", sorted(BAD_FILES))
def test_bad_files_raise_one_clear_error_naming_the_file(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    path.write_bytes(BAD_FILES[name])
    with pytest.raises(MeshFileError) as err:
        load_mesh(path)
    assert str(path) in str(err.value)
    assert isinstance(err.value, ValueError)


def test_error_messages_say_what_is_wrong(tmp_path: Path) -> None:
    cases = {
        "oor.obj": "out of bounds|indices",
        "nan.obj": "NaN/Inf",
        "points.ply": "no triangles.*PointCloud",
        "lines.obj": "no triangles",
        "oor.ply": r"face indices must be in \[0, 3\)",
        "corrupt.glb": "cannot read",
    }
    for name, pattern in cases.items():
        path = tmp_path / name
        path.write_bytes(BAD_FILES[name])
        with pytest.raises(MeshFileError, match=pattern):
            load_scene(path)


def test_missing_unsupported_and_directory(tmp_path: Path) -> None:
    missing = tmp_path / "nope.obj"
    with pytest.raises(FileNotFoundError, match="nope.obj"):
        load_mesh(missing)
    stl = tmp_path / "x.stl"
    stl.write_bytes(b"solid x\nendsolid x\n")
    with pytest.raises(MeshFileError, match=r"x.stl.*unsupported extension"):
        load_mesh(stl)
    folder = tmp_path / "folder.obj"
    folder.mkdir()
    with pytest.raises(MeshFileError, match="not a regular file"):
        load_mesh(folder)
    with pytest.raises(TypeError, match="path"):
        load_mesh(42)


def test_load_texture_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="none.png"):
        load_texture(tmp_path / "none.png")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not an image")
    with pytest.raises(MeshFileError, match="bad.png"):
        load_texture(bad)
    good = tmp_path / "good.png"
    Image.fromarray(np.full((4, 6, 4), 9, dtype=np.uint8)).save(good)
    assert load_texture(good).shape == (4, 4, 6)
    assert load_texture(good, alpha=False).shape == (3, 4, 6)


def _write_gltf(path: Path, material: dict, node: dict) -> None:
    """A one-triangle glTF with embedded buffer and a 2x2 PNG texture."""
    import base64
    import io as _io

    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32).tobytes()
    uv = np.array([[0, 0], [1, 0], [0, 1]], np.float32).tobytes()
    idx = np.array([0, 1, 2, 0], np.uint16).tobytes()  # padded to 8 bytes
    blob = pos + uv + idx
    png = _io.BytesIO()
    Image.fromarray(np.full((2, 2, 3), 128, np.uint8)).save(png, format="PNG")
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
        "images": [{"uri": "data:image/png;base64," + base64.b64encode(png.getvalue()).decode()}],
        "textures": [{"source": 0}],
        "materials": [material],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1},
                                    "indices": 2, "material": 0}]}],
        "nodes": [{"mesh": 0, **node}],
        "scenes": [{"nodes": [0]}],
        "scene": 0,
    }
    path.write_text(json.dumps(gltf))


def test_gltf_exact_factors_scale_strength_and_mirror_node(tmp_path: Path) -> None:
    path = tmp_path / "tri.gltf"
    material = {
        "name": "m",
        "pbrMetallicRoughness": {"baseColorFactor": [0.3, 0.6, 0.9, 1], "metallicFactor": 0,
                                 "roughnessFactor": 0.25},
        "normalTexture": {"index": 0, "scale": 0.5},
        "occlusionTexture": {"index": 0, "strength": 0.25},
        "emissiveFactor": [0, 0, 1],
        "alphaMode": "MASK", "alphaCutoff": 0.4, "doubleSided": True,
    }
    _write_gltf(path, material, {"scale": [-1, 1, 1]})
    scene = load_scene(path)
    m = scene.meshes[0].material
    np.testing.assert_allclose(m.base_color_factor.numpy(), [0.3, 0.6, 0.9, 1], rtol=1e-7)
    assert m.normal_scale == 0.5 and m.occlusion_strength == 0.25  # trimesh drops these
    assert m.emissive_factor.tolist() == [0, 0, 1] and m.emissive_factor.dtype == torch.float32
    assert m.metallic_factor == 0 and m.roughness_factor == 0.25
    assert m.alpha_mode == "MASK" and m.alpha_cutoff == pytest.approx(0.4) and m.double_sided
    assert m.normal_texture.shape == (3, 2, 2) and m.occlusion_texture.shape == (1, 2, 2)
    assert scene.meshes[0].tangents is not None  # normal map -> tangents
    # the mirror node: world x negated, faces re-wound so the front stays counter-clockwise
    mesh = load_mesh(path)
    torch.testing.assert_close(mesh.positions[:, 0], -scene.meshes[0].positions[:, 0])
    fn = face_normals(mesh.positions, mesh.faces)
    torch.testing.assert_close(fn, mesh.normals[mesh.faces[:, 0]])
    assert mesh.tangents[:, 3].tolist() == (-scene.meshes[0].tangents[:, 3]).tolist()


def test_truncated_texture_image(tmp_path: Path) -> None:
    png = tmp_path / "full.png"
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (64, 64, 3), np.uint8)).save(png)
    data = png.read_bytes()
    (tmp_path / "trunc.png").write_bytes(data[: len(data) // 2])
    (tmp_path / "t.mtl").write_text("newmtl m\nKd 1 1 1\nmap_Kd trunc.png\n")
    obj = tmp_path / "t.obj"
    obj.write_text("mtllib t.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\n"
                   "usemtl m\nf 1/1 2/2 3/3\n")
    with pytest.raises(MeshFileError, match="truncated") as err:
        load_mesh(obj)
    assert str(obj) in str(err.value)


def test_obj_with_two_materials(tmp_path: Path) -> None:
    (tmp_path / "two.mtl").write_text(
        "newmtl red\nKd 0.9 0.1 0.1\nNs 200\nd 1\n\nnewmtl blue\nKd 0.1 0.1 0.9\nNs 0\n")
    obj = tmp_path / "two.obj"
    obj.write_text("mtllib two.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n"
                   "usemtl red\nf 1 2 3\nusemtl blue\nf 2 4 3\n")
    scene = load_scene(obj)
    assert len(scene) == 2
    flat, face_mat, mats = scene.flatten()
    kd = {m.name: m.base_color_factor[:3].tolist() for m in mats}
    np.testing.assert_allclose(kd["red"], [0.9, 0.1, 0.1], rtol=1e-6)
    np.testing.assert_allclose(kd["blue"], [0.1, 0.1, 0.9], rtol=1e-6)
    red = next(m for m in mats if m.name == "red")
    assert red.roughness_factor == pytest.approx((2 / 202) ** 0.25)
    assert flat.num_faces == 2 and sorted(face_mat.tolist()) == [0, 1]
    # each face keeps its own material
    for f, k in zip(flat.faces, face_mat, strict=True):
        centroid_x = float(flat.positions[f, 0].mean())
        assert mats[int(k)].name == ("red" if centroid_x < 0.5 else "blue")
    with pytest.raises(MeshFileError, match="2 materials"):
        load_mesh(obj)
