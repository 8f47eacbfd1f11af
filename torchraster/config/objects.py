"""The scene of a config as objects: identity, model-space geometry and motion over time.

Every scene entry is one or more *instances* (ids 1..N in scene order; 0 is the
background): the main mesh and each ``scene.objects`` mesh give one instance per mesh node of
their file (a glTF node graph can hold several), a primitive gives one. An instance keeps its
vertices in its own model frame; its pose at time t is

    object_to_world(t) = entry(t) @ node

with ``node`` the instance's transform inside its file (identity for primitives) and
``entry(t)`` the entry's ``transform``, or its ``animation`` keys interpolated at t (a
component no key sets stays the ``transform``'s). :meth:`SceneObjects.at` poses every vertex
for a time, so the renderer sees world positions, and the per-vertex NOCS coordinates
(``object_coords``) stay those of the model frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from ..animation import Keyframes, compose_transform, quaternion_from_euler, transform_at
from ..io import load_scene, load_texture
from ..material import Material
from ..mesh import Mesh, transform_normals, transform_points, transform_tangents, vertex_normals
from ..mesh import flat as flat_mesh
from ..relative import FAR_COORDINATE
from ..scene import RenderScene, nocs_coords
from .schema import (
    MAX_INSTANCES,
    AnimationConfig,
    ConfigError,
    ObjectConfig,
    ObjectMaterialConfig,
    RenderFile,
    TransformConfig,
)
from .views import object_name


def transform_matrix(t: TransformConfig) -> torch.Tensor:
    """(4, 4) model -> world: scale, then rotations about x, y, z (degrees), then translate."""
    scale = t.scale if isinstance(t.scale, list) else [t.scale] * 3
    rotation = quaternion_from_euler(torch.tensor(t.rotate_deg, dtype=torch.float64), "xyz")
    m = compose_transform(torch.tensor(t.translate, dtype=torch.float64), rotation,
                          torch.tensor(scale, dtype=torch.float64))
    return m if _far(m) else m.float()  # far from the origin: float64 (relative.py)


def _far(matrices: torch.Tensor) -> bool:
    """Whether model -> world matrices ``(..., 4, 4)`` translate beyond
    :data:`~torchraster.relative.FAR_COORDINATE` (the world is then posed in float64, and
    the renderer renders it camera-relative)."""
    return bool((matrices[..., :3, 3].abs() > FAR_COORDINATE).any())


def _far_world(objects: SceneObjects) -> bool:
    """Whether some instance may be posed beyond ``FAR_COORDINATE`` at some time (rest,
    node and keyframe translations added up: one dtype for every frame of a config)."""
    def most(ts: list[torch.Tensor]) -> float:
        return max((float(t.abs().max()) for t in ts if t.numel()), default=0.0)

    keys = [k.translation for k in objects._keys if k is not None and k.translation is not None]
    return (most([m[..., :3, 3] for m in objects._rest]) + most([objects.nodes[..., :3, 3]])
            + most(keys)) > FAR_COORDINATE


def keyframes(anim: AnimationConfig, rest: TransformConfig) -> Keyframes:
    """The :class:`~torchraster.animation.Keyframes` of an entry's animation; components a
    key leaves out are the entry's ``transform`` values."""
    rest_q = quaternion_from_euler(torch.tensor(rest.rotate_deg, dtype=torch.float64), "xyz")
    rest_s = rest.scale if isinstance(rest.scale, list) else [rest.scale] * 3
    times, trans, rots, scales = [], [], [], []
    for k in anim.keys:
        times.append(k.time)
        trans.append(k.translate if k.translate is not None else rest.translate)
        if k.rotation is not None:
            q = torch.tensor(k.rotation, dtype=torch.float64)
            rots.append(q / q.norm())
        elif k.rotate_deg is not None:
            rots.append(quaternion_from_euler(torch.tensor(k.rotate_deg, dtype=torch.float64),
                                              anim.euler_order))
        else:
            rots.append(rest_q)
        s = k.scale if k.scale is not None else rest_s
        scales.append(s if isinstance(s, list) else [s] * 3)
    return Keyframes(times=torch.tensor(times, dtype=torch.float64),
                     translation=torch.tensor(trans, dtype=torch.float64),
                     rotation=torch.stack(rots), scale=torch.tensor(scales, dtype=torch.float64),
                     interpolation=anim.interpolation)


@dataclass
class _Instance:
    """One instance in its model frame."""

    name: str
    mesh: Mesh  # model space, normals always set
    face_material: torch.Tensor
    materials: list
    cast: torch.Tensor
    receive: torch.Tensor
    node: torch.Tensor  # (4, 4) inside its file
    entry: int
    category: str | None
    keypoints: torch.Tensor | None = None


#: Times whose poses :class:`SceneObjects` keeps (a frame and its two neighbours, + 1).
_POSES_KEPT = 4


@dataclass
class SceneObjects:
    """The instances of a config's scene (see the module docstring).

    Attributes:
        scene: the :class:`~torchraster.scene.RenderScene` posed at time 0, with
            ``face_object``, ``object_category`` and ``object_coords``.
        names: instance names (the entry's name; ``<entry>/<node>`` for a file of several
            mesh nodes). categories: each instance's category name or None.
        category_names: the id table: category id i + 1 is ``category_names[i]``.
        model_positions, model_normals: ``(V, 3)`` every vertex in its instance's model frame;
            model_tangents ``(V, 4)`` or None.
        vertex_ranges: ``(N, 2)`` ``[start, end)`` of each instance's vertices.
        nodes: ``(N, 4, 4)`` each instance's transform inside its file.
        entry_of: the scene entry of each instance (0 = ``scene.mesh`` when given).
        box_center, box_size: ``(N, 3)`` model-space axis-aligned boxes.
        keypoints: per instance a ``(K, 3)`` model-space tensor or None.
    """

    scene: RenderScene
    names: list[str]
    categories: list[str | None]
    category_names: list[str]
    model_positions: torch.Tensor
    model_normals: torch.Tensor
    model_tangents: torch.Tensor | None
    vertex_ranges: torch.Tensor
    nodes: torch.Tensor
    entry_of: list[int]
    box_center: torch.Tensor
    box_size: torch.Tensor
    keypoints: list[torch.Tensor | None]
    _rest: list[torch.Tensor] = field(repr=False, default_factory=list)
    _keys: list[Keyframes | None] = field(repr=False, default_factory=list)
    #: time -> posed tensors of the last few times (consecutive frames share their
    #: neighbours: frame t's next frame is frame t + 1); not copied by ``replace``.
    _poses: dict[float, dict] = field(repr=False, init=False, default_factory=dict)
    #: time -> ``(N, 4, 4)`` matrices evaluated ahead by :meth:`prepare`.
    _prepared: dict[float, torch.Tensor] = field(repr=False, init=False, default_factory=dict)
    _vertex_of: torch.Tensor | None = field(repr=False, init=False, default=None)

    @property
    def num_objects(self) -> int:
        return len(self.names)

    @property
    def animated(self) -> bool:
        """Whether any instance moves over time."""
        return any(k is not None for k in self._keys)

    @property
    def category_ids(self) -> list[int]:
        """Each instance's category id (0 without a category)."""
        table = {c: i + 1 for i, c in enumerate(self.category_names)}
        return [table.get(c, 0) if c is not None else 0 for c in self.categories]

    def object_to_world(self, t: float) -> torch.Tensor:
        """``(N, 4, 4)`` float64 model -> world of every instance at time ``t`` seconds."""
        return self._pose(t)["matrices"].clone()

    def prepare(self, times: Sequence[float]) -> None:
        """Evaluate the keyframes of many times at once (one call per animated entry for all
        of them, not one per frame): :meth:`at`, :meth:`positions_at` and
        :meth:`object_to_world` at those times then only look their matrices up. The poses
        are the same as without it."""
        ts = [float(t) for t in dict.fromkeys(times)]
        if not ts or not self.animated:
            return
        entries = [rest.double().expand(len(ts), 4, 4) if keys is None else transform_at(keys, ts)
                   for rest, keys in zip(self._rest, self._keys, strict=True)]
        mats = torch.stack([entries[e] for e in self.entry_of], 1) @ self.nodes.double()
        self._prepared = dict(zip(ts, mats.unbind(0), strict=True))

    def _pose(self, t: float) -> dict:
        """The cache entry of time ``t`` (its matrices computed), the last few times kept."""
        t = float(t)
        entry = self._poses.pop(t, None)
        if entry is None:
            mats = self._prepared.get(t)
            if mats is None:
                entries = [rest.double() if keys is None else transform_at(keys, [t])[0]
                           for rest, keys in zip(self._rest, self._keys, strict=True)]
                mats = torch.stack([entries[e] for e in self.entry_of]) @ self.nodes.double()
            entry = {"matrices": mats}
            while len(self._poses) >= _POSES_KEPT:
                self._poses.pop(next(iter(self._poses)))  # the least recently used
        self._poses[t] = entry  # (re)inserted last: most recently used
        return entry

    def at(self, t: float) -> RenderScene:
        """The scene posed at time ``t``: world positions, normals and tangents of every
        vertex (the scene at time 0 itself when nothing moves)."""
        if not self.animated and t == 0.0 and self.scene is not None:
            return self.scene
        return replace(self.scene, **self._posed(t))

    def positions_at(self, t: float) -> torch.Tensor:
        """``(V, 3)`` world positions at time ``t`` (the other frames of flow)."""
        if not self.animated:
            return self.scene.positions
        return self._posed(t, positions_only=True)["positions"]

    def _posed(self, t: float, positions_only: bool = False) -> dict:
        """World positions (and normals, tangents) at ``t``, cached per time (the returned
        tensors are shared by calls at the same time: read-only)."""
        entry = self._pose(t)
        if "positions" in entry and (positions_only or "normals" in entry):
            return {k: entry[k] for k in (("positions",) if positions_only else
                                          ("positions", "normals", "tangents"))}
        # one batched transform for all instances: every vertex is a batch item of one point
        # with its instance's matrix
        mats = entry["matrices"].to(self.model_positions)[self._vertex_instance()]
        device = self.scene.positions.device if self.scene is not None else "cpu"
        if "positions" not in entry:
            pos = transform_points(self.model_positions[:, None], mats)[:, 0, :3]
            if _far_world(self):  # far from the origin: float64 world positions
                pos = transform_points(self.model_positions.double()[:, None], entry[
                    "matrices"][self._vertex_instance()])[:, 0, :3]
            entry["positions"] = pos.to(device)
        if not positions_only:
            entry["normals"] = transform_normals(self.model_normals[:, None], mats)[:, 0].to(device)
            entry["tangents"] = None if self.model_tangents is None else transform_tangents(
                self.model_tangents[:, None], mats)[:, 0].to(device)
        return self._posed(t, positions_only)

    def _vertex_instance(self) -> torch.Tensor:
        """``(V,)`` int64 the instance of each vertex."""
        if self._vertex_of is None:
            counts = self.vertex_ranges[:, 1] - self.vertex_ranges[:, 0]
            self._vertex_of = torch.repeat_interleave(torch.arange(counts.shape[0]), counts)
        return self._vertex_of

    def to(self, device: torch.device | str) -> SceneObjects:
        """The same objects with the scene on ``device`` (model data stays on the CPU)."""
        return replace(self, scene=self.scene.to(device))


def build_objects(cfg: RenderFile) -> SceneObjects:
    """Load the config's scene entries as instances with identity and motion.

    Raises:
        ConfigError: more instances than 16-bit ids hold (naming ``scene``).
    """
    sc = cfg.scene
    instances: list[_Instance] = []

    def texture_key(i: int) -> str:
        return cfg.where("scene", "objects", i, "material", "base_color_texture")

    rests: list[torch.Tensor] = []
    keys: list[Keyframes | None] = []

    def add_entry(transform: TransformConfig, anim: AnimationConfig | None) -> int:
        rests.append(transform_matrix(transform))
        keys.append(keyframes(anim, transform) if anim is not None else None)
        return len(rests) - 1

    if sc.mesh is not None:
        entry = add_entry(sc.transform, sc.animation)
        instances += _file_instances(cfg, sc.mesh, object_name(cfg), sc.normals, sc.cast_shadows,
                                     sc.receive_shadows, entry, sc.category, None)
    for i, obj in enumerate(sc.objects):
        entry = add_entry(obj.transform, obj.animation)
        name = obj.name or (Path(obj.mesh).stem if obj.mesh is not None
                            else f"{obj.primitive}{i}")
        kp = (torch.tensor(obj.keypoints, dtype=torch.float32) if obj.keypoints is not None
              else None)
        if obj.mesh is not None:
            found = _file_instances(cfg, obj.mesh, name, "auto", obj.cast_shadows,
                                    obj.receive_shadows, entry, obj.category, kp)
            if obj.material is not None:
                for inst in found:
                    inst.materials = [_object_material(m, obj.material, sc.max_texture_size,
                                                       texture_key(i))
                                      for m in inst.materials]
            instances += found
        else:
            instances.append(_primitive_instance(obj, name, sc.max_texture_size, entry, kp,
                                                 texture_key(i)))
    if len(instances) > MAX_INSTANCES:
        raise ConfigError(f"{cfg.where('scene')}: {len(instances)} instances; instance ids are "
                          f"16-bit (at most {MAX_INSTANCES})")
    for inst in instances:
        inst.materials = [_override(mat, cfg) for mat in inst.materials]
    return _assemble(cfg, instances, rests, keys)


def build_scene(cfg: RenderFile) -> RenderScene:
    """The config's scene (main mesh and ``scene.objects``) as one
    :class:`~torchraster.scene.RenderScene` at time 0, with per-face materials, shadow flags
    and object identity (names the file on error)."""
    return build_objects(cfg).scene


def _file_instances(cfg: RenderFile, path: str, name: str, normals_mode: str, cast: bool,
                    receive: bool, entry: int, category: str | None,
                    keypoints: torch.Tensor | None) -> list[_Instance]:
    scene = load_scene(Path(path), max_texture_size=cfg.scene.max_texture_size,
                       allow_missing_textures=cfg.scene.allow_missing_textures)
    several = len(scene.meshes) > 1
    out = []
    for k, (mesh, node) in enumerate(zip(scene.meshes, scene.transforms, strict=True)):
        if normals_mode == "flat":
            mesh = flat_mesh(mesh)
        elif normals_mode == "smooth" or mesh.normals is None:
            mesh = replace(mesh, normals=vertex_normals(mesh.positions, mesh.faces))
        node = node.float()
        if float(torch.linalg.det(node[:3, :3])) < 0:  # a mirror: keep faces counter-clockwise
            mesh = replace(mesh, faces=mesh.faces[:, [0, 2, 1]])
        n_faces = mesh.faces.shape[0]
        material = mesh.material if mesh.material is not None else Material(name="default")
        label = f"{name}/{scene.node_names[k] or k}" if several else name
        out.append(_Instance(label, mesh, torch.zeros(n_faces, dtype=torch.int64), [material],
                             torch.full((n_faces,), scene.cast_shadows[k] and cast),
                             torch.full((n_faces,), scene.receive_shadows[k] and receive),
                             node, entry, category, keypoints))
    return out


def _primitive_instance(obj: ObjectConfig, name: str, max_texture: int | None, entry: int,
                        keypoints: torch.Tensor | None, key: str) -> _Instance:
    """A plane, box or sphere of ``obj.size`` with its material, in its model frame."""
    import trimesh

    s = float(obj.size)
    if obj.primitive == "plane":
        h = s / 2
        positions = torch.tensor([[-h, 0, -h], [h, 0, -h], [h, 0, h], [-h, 0, h]])
        faces = torch.tensor([[0, 2, 1], [0, 3, 2]])  # counter-clockwise seen from +Y
        normals = torch.tensor([[0.0, 1.0, 0.0]]).expand(4, 3)
        uvs = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    else:
        tm = (trimesh.creation.box(extents=[s, s, s]) if obj.primitive == "box"
              else trimesh.creation.icosphere(subdivisions=3, radius=s / 2))
        mesh = Mesh(torch.tensor(tm.vertices, dtype=torch.float32),
                    torch.tensor(tm.faces, dtype=torch.int64))
        if obj.primitive == "box":
            mesh = flat_mesh(mesh)  # sharp edges: one normal per face
            positions, faces, normals = mesh.positions, mesh.faces, mesh.normals
            # each face projected along its axis: [0, 1]^2 over the face
            axis = normals.abs().argmax(-1, keepdim=True)
            keep = torch.tensor([[1, 2], [0, 2], [0, 1]]).index_select(0, axis.flatten())
            uvs = torch.gather(positions, 1, keep) / s + 0.5
        else:
            positions, faces = mesh.positions, mesh.faces
            normals = torch.nn.functional.normalize(positions, dim=-1)
            # latitude-longitude
            uvs = torch.stack([0.5 + torch.atan2(normals[:, 0], normals[:, 2]) / (2 * math.pi),
                               0.5 + torch.asin(normals[:, 1].clamp(-1, 1)) / math.pi], -1)
    mc = obj.material or ObjectMaterialConfig()
    rgba = list(mc.base_color) + ([1.0] if len(mc.base_color) == 3 else [])
    texture = None
    if mc.base_color_texture is not None:
        texture = _texture(mc.base_color_texture, max_texture, key)
    material = Material(name=mc.name or f"object:{name}", base_color_factor=torch.tensor(rgba),
                        base_color_texture=texture, metallic_factor=mc.metallic,
                        roughness_factor=mc.roughness, emissive_factor=torch.tensor(mc.emissive),
                        alpha_mode=mc.alpha_mode, alpha_cutoff=mc.alpha_cutoff,
                        double_sided=obj.primitive == "plane" or mc.alpha_mode != "OPAQUE")
    n_faces = faces.shape[0]
    mesh = Mesh(positions.float(), faces, normals=normals.float().contiguous(), uvs=uvs.float())
    return _Instance(name, mesh, torch.zeros(n_faces, dtype=torch.int64), [material],
                     torch.full((n_faces,), obj.cast_shadows),
                     torch.full((n_faces,), obj.receive_shadows), torch.eye(4), entry,
                     obj.category, keypoints)


def _assemble(cfg: RenderFile, instances: list[_Instance], rests: list[torch.Tensor],
              keys: list[Keyframes | None]) -> SceneObjects:
    """Concatenate the instances (missing UVs / tangents zero-filled where another instance
    has them) and pose them at time 0."""
    any_uv = any(p.mesh.uvs is not None for p in instances)
    any_tan = any(p.mesh.tangents is not None for p in instances)
    pos, nrm, uvs, tan, faces, fmat, mats, nocs, ranges = [], [], [], [], [], [], [], [], []
    lo, hi = [], []
    seen: dict[int, int] = {}
    offset = 0
    for p in instances:
        m = p.mesh
        n_vert = m.positions.shape[0]
        pos.append(m.positions)
        nrm.append(m.normals)
        if any_uv:
            uvs.append(m.uvs if m.uvs is not None else m.positions.new_zeros(n_vert, 2))
        if any_tan:
            tan.append(m.tangents if m.tangents is not None else m.positions.new_zeros(n_vert, 4))
        faces.append(m.faces + offset)
        index = []
        for mat in p.materials:  # instances of one file share their materials
            if id(mat) not in seen:
                seen[id(mat)] = len(mats)
                mats.append(mat)
            index.append(seen[id(mat)])
        fmat.append(torch.tensor(index, dtype=torch.int64)[p.face_material])
        nocs.append(nocs_coords(m.positions))
        ranges.append([offset, offset + n_vert])
        lo.append(m.positions.amin(0) if n_vert else m.positions.new_zeros(3))
        hi.append(m.positions.amax(0) if n_vert else m.positions.new_zeros(3))
        offset += n_vert
    names = [p.category for p in instances if p.category is not None]
    table = list(cfg.categories) if cfg.categories is not None else list(dict.fromkeys(names))
    ids = {c: i + 1 for i, c in enumerate(table)}
    category = torch.tensor([0] + [ids.get(p.category, 0) if p.category is not None else 0
                                   for p in instances])
    face_object = torch.cat([torch.full((p.mesh.faces.shape[0],), i + 1, dtype=torch.int64)
                             for i, p in enumerate(instances)])
    cast = torch.cat([p.cast for p in instances])
    receive = torch.cat([p.receive for p in instances])
    lo_t, hi_t = torch.stack(lo), torch.stack(hi)
    objects = SceneObjects(
        scene=None, names=[p.name for p in instances],  # type: ignore[arg-type]
        categories=[p.category for p in instances], category_names=table,
        model_positions=torch.cat(pos), model_normals=torch.cat(nrm),
        model_tangents=torch.cat(tan) if any_tan else None,
        vertex_ranges=torch.tensor(ranges, dtype=torch.int64).reshape(-1, 2),
        nodes=torch.stack([p.node for p in instances]), entry_of=[p.entry for p in instances],
        box_center=(lo_t + hi_t) / 2, box_size=hi_t - lo_t,
        keypoints=[p.keypoints for p in instances], _rest=rests, _keys=keys)
    posed = objects._posed(0.0)
    objects.scene = RenderScene(
        posed["positions"], torch.cat(faces), posed["normals"],
        torch.cat(uvs) if any_uv else None, posed["tangents"], torch.cat(fmat), mats,
        cast_shadows=None if bool(cast.all()) else cast,
        receive_shadows=None if bool(receive.all()) else receive, face_object=face_object,
        object_category=category, object_coords=torch.cat(nocs))
    return objects


def _object_material(mat: Material, mc: ObjectMaterialConfig,
                     max_texture: int | None, key: str) -> Material:
    """A mesh's material with the fields an object's ``material:`` sets replaced (a new
    Material: other instances of the file keep theirs)."""
    given = mc.model_fields_set
    changes: dict = {}
    if "base_color" in given:
        rgba = list(mc.base_color) + ([1.0] if len(mc.base_color) == 3 else [])
        changes["base_color_factor"] = torch.tensor(rgba)
    if "metallic" in given:
        changes["metallic_factor"] = mc.metallic
    if "roughness" in given:
        changes["roughness_factor"] = mc.roughness
    if "emissive" in given:
        changes["emissive_factor"] = torch.tensor(mc.emissive)
    if "base_color_texture" in given and mc.base_color_texture is not None:
        changes["base_color_texture"] = _texture(mc.base_color_texture, max_texture, key)
    return replace(mat, **changes)


def _texture(path: str | Path, max_texture: int | None, key: str) -> torch.Tensor:
    """``load_texture`` of a config's texture; errors name the config key (``key``:
    ``file:line: key.path``) and the image file."""
    try:
        return load_texture(Path(path), max_size=max_texture)
    except (OSError, ValueError) as e:
        raise ConfigError(f"{key}: {e}") from None


def _override(mat: Material | None, cfg: RenderFile) -> Material | None:
    """Apply the config's material overrides (in order) to one material."""
    for j, o in enumerate(cfg.materials):
        if o.match != "*" and (mat is None or mat.name != o.match):
            continue
        mat = mat if mat is not None else Material()
        changes = {}
        if o.base_color is not None:
            rgba = list(o.base_color) + ([1.0] if len(o.base_color) == 3 else [])
            changes["base_color_factor"] = torch.tensor(rgba)
        if o.metallic is not None:
            changes["metallic_factor"] = o.metallic
        if o.roughness is not None:
            changes["roughness_factor"] = o.roughness
        if o.emissive is not None:
            changes["emissive_factor"] = torch.tensor(o.emissive)
        if o.base_color_texture is not None:
            changes["base_color_texture"] = _texture(
                o.base_color_texture, cfg.scene.max_texture_size,
                cfg.where("materials", j, "base_color_texture"))
        mat = replace(mat, **changes)
    return mat
