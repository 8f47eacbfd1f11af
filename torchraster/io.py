"""Loading OBJ (+MTL), PLY and glTF 2.0 (.gltf / .glb) through trimesh.

Two entry points:

* :func:`load_scene` returns a :class:`Scene`: one model-space :class:`~torchraster.mesh.Mesh`
  per mesh *instance* of the file's scene graph (an instanced geometry appears several times as
  the same Mesh object), the instances' model->world matrices, and per-mesh materials.
  :meth:`Scene.flatten` bakes it into one world-space Mesh plus a per-face material index, so a
  whole scene renders in one rasterize call.
* :func:`load_mesh` returns one world-space Mesh. It refuses files whose meshes use more than
  one material (a Mesh carries one material): the error points at ``load_scene``.

Conventions: positions float32; faces int64 as in the file (``process=False`` keeps
trimesh from merging or reordering vertices, so per-vertex UVs and seams survive); UVs in the
project convention (v up; trimesh already flips glTF's v); normals from the file when present,
else smooth area-weighted ones; tangents computed (:func:`~torchraster.mesh.vertex_tangents`,
a MikkTSpace approximation; trimesh drops glTF TANGENT attributes) for meshes whose material has
a normal map. Not read: vertex colours, glTF samplers (wrap/filter modes), KHR_texture_transform,
TEXCOORD_1, skins, morph targets, animations, cameras and lights.

Every failure (missing file, unsupported extension, unreadable or corrupt file, no triangles,
only points/lines, NaN/Inf positions, face indices out of range) raises one
:class:`MeshFileError` (a ``ValueError``; ``FileNotFoundError`` for a missing file) whose
message starts with the file path; trimesh's own exception is chained as the cause.
"""

from __future__ import annotations

import io
import json
import logging
import struct
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .material import ImageTextureCache, Material, material_from_trimesh
from .mesh import (
    Mesh,
    bake_instances,
    face_normals,
    transform_points,
    vertex_normals,
    vertex_tangents,
)

log = logging.getLogger("torchraster")

#: File extensions :func:`load_scene` / :func:`load_mesh` accept.
SUPPORTED_EXTENSIONS = (".obj", ".ply", ".gltf", ".glb")


class MeshFileError(ValueError):
    """A mesh/scene file could not be loaded; the message starts with the file path."""


# --------------------------------------------------------------------------------- Scene
@dataclass
class Scene:
    """Mesh instances of a file with their model->world transforms.

    Attributes:
        meshes: N model-space meshes (one per instance; instances of one geometry share the
            same Mesh object).
        transforms: ``(N, 4, 4)`` model->world matrices (column-vector convention), same
            dtype as the meshes.
        node_names: N scene-graph node names.
        name: the file name.
        cast_shadows: N bools: the instance is drawn into shadow maps (default all True;
            a glTF node's ``extras: {"cast_shadows": false}`` sets it).
        receive_shadows: N bools: the instance is darkened by shadows (likewise).
    """

    meshes: list[Mesh]
    transforms: torch.Tensor
    node_names: list[str]
    name: str = "scene"
    cast_shadows: list[bool] | None = None
    receive_shadows: list[bool] | None = None

    def __post_init__(self) -> None:
        if not self.meshes or not all(isinstance(m, Mesh) for m in self.meshes):
            raise ValueError("meshes: expected a non-empty list of Mesh")
        n = len(self.meshes)
        if not isinstance(self.transforms, torch.Tensor) or tuple(self.transforms.shape) != (
            n, 4, 4,
        ):
            got = getattr(self.transforms, "shape", type(self.transforms).__name__)
            raise ValueError(f"transforms: expected shape ({n}, 4, 4), got {got}")
        if len(self.node_names) != n:
            raise ValueError(f"node_names: expected {n} names, got {len(self.node_names)}")
        for flag in ("cast_shadows", "receive_shadows"):
            value = getattr(self, flag)
            if value is None:
                setattr(self, flag, [True] * n)
            elif len(value) != n or not all(isinstance(v, bool) for v in value):
                raise ValueError(f"{flag}: expected {n} bools (one per instance), got {value!r}")

    def face_shadow_flags(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-face ``(cast_shadows, receive_shadows)``, each ``(F,)`` bool, in the face order
        of :meth:`flatten`."""
        counts = torch.tensor([m.num_faces for m in self.meshes])
        cast = torch.tensor(self.cast_shadows).repeat_interleave(counts)
        receive = torch.tensor(self.receive_shadows).repeat_interleave(counts)
        device = self.meshes[0].faces.device
        return cast.to(device), receive.to(device)

    def __len__(self) -> int:
        return len(self.meshes)

    @property
    def materials(self) -> list[Material | None]:
        """Distinct materials (by identity) in order of first use; may contain None."""
        seen: dict[int, Material | None] = {}
        for m in self.meshes:
            seen.setdefault(id(m.material), m.material)
        return list(seen.values())

    def flatten(self) -> tuple[Mesh, torch.Tensor, list[Material]]:
        """Bake all instances into one world-space mesh.

        Returns ``(mesh, face_material, materials)``: ``mesh`` has world positions ``(V, 3)``,
        normals (inverse-transpose transformed), UVs (zeros for instances without UVs, whose
        materials then have no textures to sample) and tangents (only if every instance has
        them); faces of mirroring instances (det < 0) are re-wound to stay counter-clockwise.
        ``face_material (F,)`` int64 indexes ``materials``: the distinct materials, with
        meshes without a material mapped to one default (glTF default) Material.
        ``mesh.material`` is the material when there is exactly one, else None.
        """
        mesh, face_mat, mats = _flatten(self)
        default = Material(name="default")
        mats_out = [default if m is None else m for m in mats]
        single = mats_out[0] if len(mats_out) == 1 else None
        return replace(mesh, material=single), face_mat, mats_out

    def bounds(self) -> torch.Tensor:
        """World-space axis-aligned bounds ``(2, 3)``: row 0 = min, row 1 = max."""
        lo, hi = [], []
        for mesh, m in zip(self.meshes, self.transforms, strict=True):
            world = transform_points(mesh.positions, m)[:, :3]
            lo.append(world.amin(0))
            hi.append(world.amax(0))
        return torch.stack([torch.stack(lo).amin(0), torch.stack(hi).amax(0)])


def _flatten(scene: Scene) -> tuple[Mesh, torch.Tensor, list[Material | None]]:
    """Flatten keeping None materials (see :meth:`Scene.flatten`)."""
    flat, face_material, mats = bake_instances(scene.meshes, scene.transforms)
    return replace(flat, name=scene.name), face_material, mats


# ------------------------------------------------------------------------------ loading
def _check_path(path: str | Path) -> Path:
    if not isinstance(path, (str, Path)):
        raise TypeError(f"path: expected a str or Path, got {type(path).__name__}")
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: file not found")
    if not p.is_file():
        raise MeshFileError(f"{p}: not a regular file")
    if p.suffix.lower() not in SUPPORTED_EXTENSIONS:
        raise MeshFileError(
            f"{p}: unsupported extension {p.suffix!r}; expected one of {SUPPORTED_EXTENSIONS}"
        )
    return p


def _gltf_header(path: Path) -> dict | None:
    """The glTF JSON of a .gltf/.glb file, or None (then trimesh's values are used)."""
    try:
        if path.suffix.lower() == ".gltf":
            return json.loads(path.read_text(encoding="utf-8"))
        with path.open("rb") as fh:
            head = fh.read(20)
            magic, _, _, length, kind = struct.unpack("<4sIIII", head)
            if magic != b"glTF" or kind != 0x4E4F534A:  # 'JSON' chunk
                return None
            return json.loads(fh.read(length))
    except (OSError, ValueError, struct.error):
        return None


def _gltf_exact(header: dict | None, mat: Material) -> Material:
    """Restore exact glTF factors and normal/occlusion scale that trimesh drops or rounds.

    Header materials are matched by name; applied only when every header material of that
    name agrees and its base colour matches trimesh's 8-bit rounding (so a wrong match can
    only leave trimesh's values in place).
    """
    if not header:
        return mat
    cands = [m for m in header.get("materials", []) if m.get("name") == mat.name]
    if not cands:
        return mat
    values = []
    for m in cands:
        pbr = m.get("pbrMetallicRoughness", {})
        values.append(
            (
                tuple(pbr.get("baseColorFactor", (1.0, 1.0, 1.0, 1.0))),
                tuple(m.get("emissiveFactor", (0.0, 0.0, 0.0))),
                float(m.get("normalTexture", {}).get("scale", 1.0)),
                float(m.get("occlusionTexture", {}).get("strength", 1.0)),
            )
        )
    if any(v != values[0] for v in values):
        return mat
    base, emissive, scale, strength = values[0]
    try:
        base_t = torch.tensor(base, dtype=torch.float32)
        if base_t.shape != (4,) or float((base_t - mat.base_color_factor).abs().max()) > 1.01 / 255:
            return mat
        emissive_t = torch.tensor(emissive, dtype=torch.float32)
        return replace(mat, base_color_factor=base_t, emissive_factor=emissive_t,
                       normal_scale=scale, occlusion_strength=min(max(strength, 0.0), 1.0))
    except (TypeError, ValueError):
        return mat


def _convert_geometry(
    geom: Any, name: str, path: Path, material: Material | None
) -> Mesh:
    """trimesh.Trimesh -> Mesh (float32), validating with errors that name the file."""
    vertices = np.asarray(geom.vertices, dtype=np.float64)
    faces = np.asarray(geom.faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshFileError(f"{path}: mesh {name!r}: vertices of shape {vertices.shape}")
    bad = int((~np.isfinite(vertices)).any(axis=1).sum())
    if bad:
        raise MeshFileError(f"{path}: mesh {name!r}: {bad} vertex position(s) are NaN/Inf")
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise MeshFileError(
            f"{path}: mesh {name!r}: face indices must be in [0, {len(vertices)}), got "
            f"[{faces.min()}, {faces.max()}]"
        )
    positions = torch.from_numpy(vertices.astype(np.float32))
    faces_t = torch.from_numpy(faces.astype(np.int64)).reshape(-1, 3)
    smooth = vertex_normals(positions, faces_t)
    # Where incident face normals cancel (e.g. a triangle stored with both windings, as in
    # bunny-res2.ply), use the normal of one incident face so every used vertex has a normal.
    cancelled = smooth.norm(dim=-1) < 0.5
    if bool(cancelled.any()) and faces_t.numel():
        fn = face_normals(positions, faces_t)
        fallback = torch.zeros_like(smooth)
        for k in range(3):
            fallback[faces_t[:, k]] = fn
        smooth = torch.where(cancelled[:, None], fallback, smooth)
    normals = smooth
    # File normals: trimesh keeps them in its cache (its OBJ exporter tests the same way).
    if "vertex_normals" in geom._cache:
        fn = np.asarray(geom.vertex_normals, dtype=np.float64)
        if fn.shape == vertices.shape:
            fn_t = torch.from_numpy(fn.astype(np.float32))
            length = fn_t.norm(dim=-1, keepdim=True)
            ok = torch.isfinite(fn_t).all(-1, keepdim=True) & (length > 1e-6)
            normals = torch.where(ok, fn_t / torch.where(ok, length, 1.0), smooth)
    uvs = None
    uv = getattr(geom.visual, "uv", None)
    if uv is not None and len(uv) == len(vertices):
        uv = np.asarray(uv, dtype=np.float64)
        if not np.isfinite(uv).all():
            raise MeshFileError(f"{path}: mesh {name!r}: texture coordinates contain NaN/Inf")
        uvs = torch.from_numpy(uv.astype(np.float32))
    tangents = None
    if uvs is not None and material is not None and material.normal_texture is not None:
        tangents = vertex_tangents(positions, uvs, normals, faces_t)
    try:
        return Mesh(positions, faces_t, normals, uvs, tangents, material, name)
    except (ValueError, TypeError) as e:  # pragma: no cover - checks above come first
        raise MeshFileError(f"{path}: mesh {name!r}: {e}") from e


def missing_textures(path: Path) -> list[str]:
    """Texture files a mesh file refers to that do not exist (OBJ via its MTL files, .gltf
    via its image URIs; .glb and .ply embed theirs). Paths as written in the file."""
    missing = []
    suffix = path.suffix.lower()
    if suffix == ".obj":
        for line in _read_text(path).splitlines():
            if line.strip().startswith("mtllib"):
                mtl = path.parent / line.split(None, 1)[1].strip()
                if not mtl.is_file():
                    missing.append(mtl.name)
                    continue
                for mline in _read_text(mtl).splitlines():
                    words = mline.split()
                    if words and words[0].lower().startswith(("map_", "bump", "disp", "norm")):
                        # the file name is the tail after any options; it may hold spaces
                        tails = [" ".join(words[k:]) for k in range(1, len(words))]
                        if tails and not any((mtl.parent / t).is_file() for t in tails):
                            missing.append(tails[-1] if len(words) > 2 and words[-2][:1] == "-"
                                           else " ".join(words[1:]))
    elif suffix == ".gltf":
        header = _gltf_header(path) or {}
        for image in header.get("images", []):
            uri = image.get("uri")
            if uri and not uri.startswith("data:"):
                from urllib.parse import unquote

                if not (path.parent / unquote(uri)).is_file():
                    missing.append(uri)
    return missing


def unusable_textures(path: Path) -> list[str]:
    """Texture files a ``.gltf`` refers to that exist but cannot be used, each as ``"<uri>
    (<reason>)"``: the URI leaves the glTF's folder (trimesh's resolver refuses it) or
    the file is not a readable image (PIL cannot identify or decode it). Both were dropped
    silently by the loader. Missing files: :func:`missing_textures`."""
    if path.suffix.lower() != ".gltf":
        return []
    from urllib.parse import unquote

    from PIL import Image

    header = _gltf_header(path) or {}
    root = path.parent.resolve()
    bad = []
    for image in header.get("images", []):
        uri = image.get("uri")
        if not isinstance(uri, str) or not uri or uri.startswith("data:"):
            continue
        file = path.parent / unquote(uri)
        if not file.is_file():
            continue  # missing: reported by missing_textures
        if not file.resolve().is_relative_to(root):
            bad.append(f"{uri} (outside the glTF's folder {root})")
            continue
        try:
            with Image.open(file) as im:
                im.verify()
        except Exception as e:  # PIL raises UnidentifiedImageError, OSError, SyntaxError...
            bad.append(f"{uri} (not an image: {type(e).__name__})")
    return bad


def _read_text(path: Path) -> str:
    """A text file as str: UTF-8, else Latin-1 (every byte decodes; OBJ/MTL keywords are
    ASCII, so names with other encodings survive as text)."""
    data = path.read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def load_scene(
    path: str | Path,
    *,
    process: bool = False,
    max_texture_size: int | None = None,
    allow_missing_textures: bool = False,
) -> Scene:
    """Load every triangle-mesh instance of an OBJ / PLY / glTF / GLB file.

    Walks the scene graph (``trimesh.Scene.graph.nodes_geometry``) so each instance keeps its
    own model->world transform and material (no ``Scene.to_mesh()``, which would merge
    materials). glTF materials keep exact float factors and ``normalTexture.scale`` /
    ``occlusionTexture.strength`` (read from the glTF JSON, which trimesh rounds / drops).

    Args:
        path: the file. OBJ files find their MTL and textures relative to it.
        process: passed to trimesh; False keeps vertices exactly as in the file.
        max_texture_size: if given, textures are downscaled so the longer side is at most
            this (saves memory: DamagedHelmet's five 2048^2 maps).
        allow_missing_textures: render materials whose texture files are missing (or, for
            glTF, are not images or lie outside the file's folder) without those textures
            (logged as a warning) instead of raising.

    Returns:
        A :class:`Scene`.

    Raises:
        MeshFileError: naming the file (unreadable, no triangles, missing textures; glTF
            textures that are not images or whose URI leaves the file's folder, naming the
            URI).
        FileNotFoundError: the file does not exist.
    """
    import trimesh

    p = _check_path(path)
    if max_texture_size is not None and (
        not isinstance(max_texture_size, int) or max_texture_size < 1
    ):
        raise ValueError(f"max_texture_size: expected a positive int, got {max_texture_size!r}")
    for problem, names in (("not found", missing_textures(p)),
                           ("cannot be used", unusable_textures(p))):
        if names and not allow_missing_textures:
            raise MeshFileError(f"{p}: texture file(s) {problem}: {', '.join(names)} (pass "
                                "allow_missing_textures=True / --allow-missing-textures to "
                                "render without them)")
        if names:
            log.warning("%s: texture file(s) %s, rendering without them: %s", p, problem,
                        ", ".join(names))
    try:
        if p.suffix.lower() == ".obj":  # decode ourselves: any encoding, no charset detector
            with open(p, "rb") as fh:
                head = fh.read()
            try:
                head.decode("utf-8")
                loaded = trimesh.load(str(p), force="scene", process=bool(process))
            except UnicodeDecodeError:
                loaded = trimesh.load(
                    io.BytesIO(head.decode("latin-1").encode("utf-8")), file_type="obj",
                    force="scene", process=bool(process),
                    resolver=trimesh.resolvers.FilePathResolver(str(p)))
        else:
            loaded = trimesh.load(str(p), force="scene", process=bool(process))
    except Exception as e:  # trimesh raises anything from KeyError to struct.error
        raise MeshFileError(
            f"{p}: cannot read as {p.suffix.lower()} ({type(e).__name__}: {e})"
        ) from e
    header = _gltf_header(p) if p.suffix.lower() in (".gltf", ".glb") else None

    textures = ImageTextureCache(max_texture_size)
    materials: dict[int, Material | None] = {}
    converted: dict[str, Mesh] = {}
    meshes, transforms, names, skipped = [], [], [], []
    for node in loaded.graph.nodes_geometry:
        transform, geom_name = loaded.graph[node]
        geom = loaded.geometry[geom_name]
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            skipped.append(type(geom).__name__)
            continue
        if geom_name not in converted:
            vis_mat = getattr(geom.visual, "material", None)
            key = id(vis_mat)
            if key not in materials:
                try:
                    mat = material_from_trimesh(vis_mat, _cache=textures)
                except (ValueError, TypeError, OSError) as e:  # OSError: broken image data
                    raise MeshFileError(
                        f"{p}: material of mesh {geom_name!r}: {type(e).__name__}: {e}"
                    ) from e
                materials[key] = None if mat is None else _gltf_exact(header, mat)
            converted[geom_name] = _convert_geometry(geom, geom_name, p, materials[key])
        meshes.append(converted[geom_name])
        transforms.append(np.asarray(transform, dtype=np.float64))
        names.append(str(node))
    if not meshes:
        found = ", ".join(sorted(set(skipped))) or "nothing"
        raise MeshFileError(f"{p}: contains no triangles (found: {found})")
    if not all(np.isfinite(t).all() for t in transforms):
        raise MeshFileError(f"{p}: a node transform contains NaN/Inf")
    cast, receive = _node_shadow_flags(header, names)
    return Scene(
        meshes=meshes,
        transforms=torch.from_numpy(np.stack(transforms).astype(np.float32)),
        node_names=names,
        name=p.name,
        cast_shadows=cast,
        receive_shadows=receive,
    )


def _node_shadow_flags(header: dict | None, names: list[str]
                       ) -> tuple[list[bool], list[bool]]:
    """Per-instance shadow flags from glTF node ``extras`` (``cast_shadows`` /
    ``receive_shadows`` booleans); True where absent."""
    extras: dict[str, dict] = {}
    for node in (header or {}).get("nodes", []):
        if isinstance(node, dict) and isinstance(node.get("extras"), dict) and "name" in node:
            extras[str(node["name"])] = node["extras"]

    def flag(name: str, key: str) -> bool:
        value = extras.get(name, {}).get(key, True)
        return value if isinstance(value, bool) else True

    return ([flag(n, "cast_shadows") for n in names],
            [flag(n, "receive_shadows") for n in names])


def load_mesh(
    path: str | Path,
    *,
    process: bool = False,
    max_texture_size: int | None = None,
    allow_missing_textures: bool = False,
) -> Mesh:
    """Load a file as one world-space :class:`~torchraster.mesh.Mesh` (node transforms
    applied) with its single material (None for files without one).

    Files whose mesh instances use more than one material raise :class:`MeshFileError`
    pointing at :func:`load_scene` / :meth:`Scene.flatten`. Several instances sharing one
    material are merged. Arguments as in :func:`load_scene`.
    """
    scene = load_scene(path, process=process, max_texture_size=max_texture_size,
                       allow_missing_textures=allow_missing_textures)
    mats = scene.materials
    if len(mats) > 1:
        raise MeshFileError(
            f"{Path(path)}: holds {len(scene)} mesh instances with {len(mats)} materials, but a "
            "Mesh carries one material; use torchraster.io.load_scene(path) and "
            "Scene.flatten() (per-face material index) instead"
        )
    if len(scene) == 1 and torch.equal(scene.transforms[0], torch.eye(4)):
        return scene.meshes[0]
    return _flatten(scene)[0]


#: Directory of the assets shipped with the package.
ASSETS_DIR = Path(__file__).resolve().parent / "assets"


def load_texture(
    path: str | Path, *, max_size: int | None = None, alpha: bool = True
) -> torch.Tensor:
    """Read an image file as a ``uint8`` texture ``(C, Ht, Wt)`` (row 0 = top), C = 3, or 4
    if the image has alpha and ``alpha`` is True. Stored values are as in the file (sRGB
    colour textures stay encoded; :meth:`Material.texture` decodes). Downscaled (area
    average) so the longer side is at most ``max_size`` if given."""
    from PIL import Image, UnidentifiedImageError

    from .material import pil_to_tensor

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: file not found")
    if max_size is not None and (not isinstance(max_size, int) or max_size < 1):
        raise ValueError(f"max_size: expected a positive int, got {max_size!r}")
    try:
        with Image.open(p) as img:
            return pil_to_tensor(img, "RGBA" if alpha else "RGB", max_size)
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as e:
        raise MeshFileError(f"{p}: cannot read as an image ({type(e).__name__}: {e})") from e


def load_spot(*, max_texture_size: int | None = None) -> Mesh:
    """The shipped "spot" cow (Keenan Crane, public domain; ``assets/spot/README.txt``):
    5,856 triangles with UVs and its 1024^2 base-colour texture, as a Mesh with a
    dielectric material (metallic 0, roughness 0.5). Its OBJ has no MTL, so the texture is
    attached here.

    Example:
        >>> spot = load_spot()
        >>> spot.positions.shape, spot.faces.shape, spot.uvs.shape
        (torch.Size([3225, 3]), torch.Size([5856, 3]), torch.Size([3225, 2]))
    """
    mesh = load_mesh(ASSETS_DIR / "spot" / "spot_triangulated.obj")
    texture = load_texture(ASSETS_DIR / "spot" / "spot_texture.png", max_size=max_texture_size)
    material = Material(
        name="spot", base_color_texture=texture, metallic_factor=0.0, roughness_factor=0.5
    )
    return replace(mesh, material=material, name="spot")


__all__ = [
    "ASSETS_DIR",
    "MeshFileError",
    "Scene",
    "SUPPORTED_EXTENSIONS",
    "load_mesh",
    "load_scene",
    "load_spot",
    "load_texture",
]
