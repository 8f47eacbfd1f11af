"""What the renderer draws: :class:`RenderScene`, the checked tensors of a batch of scenes.

A ``RenderScene`` is built from a :class:`~torchraster.mesh.Mesh`, a loaded
:class:`~torchraster.io.Scene` (its instances baked into world space), a list of meshes
(one per batch item, packed with :func:`~torchraster.mesh.pack_meshes`) or by hand from
tensors; :func:`as_render_scene` does whichever applies, so ``Renderer`` accepts all of them.

Object identity (the dataset labels, docs/design.md "Labels"): a scene of N objects
(:meth:`RenderScene.from_objects`, or an ``io.Scene``: one object per mesh instance) numbers
them 1..N in order (0 = background). ``face_object`` maps each face to its object (each
object's faces one contiguous range), ``object_category`` each object to a category id, and
``object_coords`` holds each vertex's NOCS coordinates (:func:`nocs_coords`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import torch

from ._validate import check_tensor
from .material import Material
from .mesh import (
    Mesh,
    bake_instances,
    check_meshes,
    pack_meshes,
)


def nocs_coords(positions_model: torch.Tensor) -> torch.Tensor:
    """NOCS coordinates of an object's model-space vertices (Wang et al. 2019, "Normalized
    Object Coordinate Space for Category-Level 6D Object Pose and Size Estimation"):
    ``(p - c) / d + 0.5`` with ``c`` the centre and ``d`` the diagonal length of the
    vertices' axis-aligned box, so every coordinate lies in [0, 1] and the box's longest
    extent keeps its proportion. A single point (``d = 0``) maps to 0.5.

    Args:
        positions_model: ``(V, 3)`` float vertex positions in the object's own model frame.

    Returns:
        ``(V, 3)`` NOCS coordinates, differentiable with respect to ``positions_model``.

    Example:
        >>> nocs_coords(torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]))
        tensor([[0.0000, 0.5000, 0.5000],
                [1.0000, 0.5000, 0.5000]])
    """
    check_tensor("positions_model", positions_model, ("V", 3), floating=True, finite=True)
    if positions_model.shape[0] == 0:
        return positions_model.clone()
    lo, hi = positions_model.amin(0), positions_model.amax(0)
    diag = (hi - lo).norm()
    scale = torch.where(diag > 0, diag, torch.ones_like(diag))
    return (positions_model - (lo + hi) / 2) / scale + 0.5


@dataclass
class RenderScene:
    """Scene tensors of a batch of B scenes.

    Attributes:
        positions: ``(B, V, 3)`` or ``(V, 3)`` (shared) world-space vertex positions.
        faces: ``(F, 3)`` int64 vertex indices, counter-clockwise = front.
        normals: like ``positions``; None: smooth normals are computed when needed.
        uvs: ``(V, 2)`` or ``(B, V, 2)``; tangents: ``(V, 4)`` or ``(B, V, 4)``.
        face_material: ``(F,)`` int64 index into ``materials`` (None: material 0 for all).
        materials: the materials (None entries = the glTF default material).
        face_ranges: ``(B, 2)`` int64 ``[start, end)``: batch item b draws only
            ``faces[start:end]`` (a batch of different meshes, see :meth:`from_meshes`);
            None: every item draws every face.
        cast_shadows: ``(F,)`` bool: faces drawn into shadow maps (None: all).
        receive_shadows: ``(F,)`` bool: faces darkened by shadows (None: all). A ground
            plane that receives without casting has ``cast_shadows`` False on its faces.
        face_object: ``(F,)`` int64 object (instance) id 1..N of each face, each object's
            faces one contiguous range (None: no identity; the ``instance``, ``semantic``
            and ``amodal`` channels need it).
        object_category: ``(N + 1,)`` int64 category id of each object id, entry 0 (the
            background) 0 (None: categories unknown; the ``semantic`` channel needs it).
        object_coords: ``(V, 3)`` or ``(B, V, 3)`` NOCS coordinates of each vertex in its
            object's model frame (:func:`nocs_coords`; the ``object_coords`` channel).

    Every field is checked on construction; an error names the field and what was expected.
    """

    positions: torch.Tensor
    faces: torch.Tensor
    normals: torch.Tensor | None = None
    uvs: torch.Tensor | None = None
    tangents: torch.Tensor | None = None
    face_material: torch.Tensor | None = None
    materials: list[Material | None] = field(default_factory=list)
    face_ranges: torch.Tensor | None = None
    cast_shadows: torch.Tensor | None = None
    receive_shadows: torch.Tensor | None = None
    face_object: torch.Tensor | None = None
    object_category: torch.Tensor | None = None
    object_coords: torch.Tensor | None = None

    def __post_init__(self) -> None:
        pos = self.positions
        if isinstance(pos, torch.Tensor) and pos.dim() == 2:
            check_tensor("RenderScene.positions", pos, ("V", 3), floating=True, finite=True)
        else:
            check_tensor("RenderScene.positions", pos, ("B", "V", 3), floating=True,
                         finite=True)
        n_vert = pos.shape[-2]
        check_tensor("RenderScene.faces", self.faces, ("F", 3), integer=True)
        if self.faces.numel() and (int(self.faces.min()) < 0
                                   or int(self.faces.max()) >= n_vert):
            raise ValueError(f"RenderScene.faces: vertex indices must be in [0, {n_vert}), got "
                             f"[{int(self.faces.min())}, {int(self.faces.max())}]")
        for name, size in (("normals", 3), ("uvs", 2), ("tangents", 4)):
            value = getattr(self, name)
            if value is None:
                continue
            shape = ("V", size) if isinstance(value, torch.Tensor) and value.dim() == 2 else (
                "B", "V", size)
            check_tensor(f"RenderScene.{name}", value, shape, floating=True, finite=True)
            if value.shape[-2] != n_vert:
                raise ValueError(f"RenderScene.{name}: expected V = {n_vert} rows like "
                                 f"positions, got {value.shape[-2]}")
        if not isinstance(self.materials, (list, tuple)):
            raise TypeError("RenderScene.materials: expected a list of Material (or None)")
        self.materials = list(self.materials)
        for i, m in enumerate(self.materials):
            if m is not None and not isinstance(m, Material):
                raise TypeError(f"RenderScene.materials[{i}]: expected a Material or None, got "
                                f"{type(m).__name__}")
        if self.face_material is not None:
            n_faces = self.faces.shape[0]
            check_tensor("RenderScene.face_material", self.face_material, (n_faces,),
                         integer=True)
            n_mat = max(1, len(self.materials))
            if self.face_material.numel() and (int(self.face_material.min()) < 0
                                               or int(self.face_material.max()) >= n_mat):
                raise ValueError(
                    f"RenderScene.face_material: indices must be in [0, {n_mat}) for "
                    f"{len(self.materials)} material(s), got [{int(self.face_material.min())}, "
                    f"{int(self.face_material.max())}]")
        if self.face_ranges is not None:
            check_tensor("RenderScene.face_ranges", self.face_ranges, ("B", 2), integer=True)
        for name in ("cast_shadows", "receive_shadows"):
            flags = getattr(self, name)
            if flags is not None:
                check_tensor(f"RenderScene.{name}", flags, (self.faces.shape[0],))
                if flags.dtype != torch.bool:
                    raise TypeError(f"RenderScene.{name}: expected an (F,) bool tensor, got "
                                    f"{flags.dtype}")
        self._check_identity(n_vert)

    def _check_identity(self, n_vert: int) -> None:
        """Check ``face_object``, ``object_category`` and ``object_coords``."""
        n_faces = self.faces.shape[0]
        obj, cat = self.face_object, self.object_category
        if cat is not None:
            check_tensor("RenderScene.object_category", cat, ("N + 1",), integer=True)
            if cat.numel() == 0 or int(cat[0]) != 0 or int(cat.min()) < 0:
                raise ValueError("RenderScene.object_category: expected (N + 1,) non-negative "
                                 "category ids with entry 0 (the background) 0, got "
                                 f"{cat.tolist() if cat.numel() <= 16 else cat.shape}")
            if obj is None:
                raise ValueError("RenderScene.object_category: needs face_object (the object "
                                 "id of each face) to say which faces are which object")
        if obj is not None:
            check_tensor("RenderScene.face_object", obj, (n_faces,), integer=True)
            if obj.numel():
                lo, hi = int(obj.min()), int(obj.max())
                n_obj = cat.shape[0] - 1 if cat is not None else hi
                if lo < 1 or hi > n_obj:
                    raise ValueError(f"RenderScene.face_object: object ids must be in [1, "
                                     f"{n_obj}] (0 is the background), got [{lo}, {hi}]")
                runs = 1 + int((obj[1:] != obj[:-1]).sum())
                if runs != int(torch.unique(obj).numel()):
                    raise ValueError("RenderScene.face_object: each object's faces must be "
                                     "one contiguous range of faces (reorder the faces)")
        coords = self.object_coords
        if coords is not None:
            shape = ("V", 3) if isinstance(coords, torch.Tensor) and coords.dim() == 2 else (
                "B", "V", 3)
            check_tensor("RenderScene.object_coords", coords, shape, floating=True,
                         finite=True)
            if coords.shape[-2] != n_vert:
                raise ValueError(f"RenderScene.object_coords: expected V = {n_vert} rows like "
                                 f"positions, got {coords.shape[-2]}")

    @property
    def num_objects(self) -> int:
        """N: ``len(object_category) - 1``, else the largest id in ``face_object`` (0 without
        identity)."""
        if self.object_category is not None:
            return self.object_category.shape[0] - 1
        if self.face_object is None or self.face_object.numel() == 0:
            return 0
        return int(self.face_object.max())

    def object_face_ranges(self) -> torch.Tensor:
        """``(N, 2)`` int64 ``[start, end)`` of object k + 1's faces (``[0, 0)`` for an object
        without faces), on the faces' device.

        Raises:
            ValueError: when the scene has no ``face_object``.
        """
        if self.face_object is None:
            raise ValueError("RenderScene.face_object: required for per-object face ranges")
        n = self.num_objects
        obj = self.face_object.to(self.faces.device)
        index = torch.arange(obj.shape[0], device=obj.device)
        start = torch.full((n + 1,), obj.shape[0], dtype=torch.int64, device=obj.device)
        end = torch.zeros(n + 1, dtype=torch.int64, device=obj.device)
        start = start.scatter_reduce(0, obj, index, "amin")
        end = end.scatter_reduce(0, obj, index + 1, "amax")
        start = torch.where(end > 0, start, torch.zeros_like(start))
        return torch.stack([start, end], 1)[1:]

    def to(self, device: torch.device | str) -> RenderScene:
        """The same scene with every tensor (and material texture) on ``device``."""
        moved = {f: (v.to(device) if isinstance(v, torch.Tensor) else v)
                 for f, v in vars(self).items() if f != "materials"}
        return RenderScene(**moved, materials=[m.to(device) if m is not None else None
                                               for m in self.materials])

    @property
    def batch_size(self) -> int:
        """B of the per-item tensors (1 when every tensor is shared)."""
        sizes = [t.shape[0] for t in (self.positions, self.normals, self.uvs, self.tangents,
                                      self.object_coords)
                 if t is not None and t.dim() == 3]
        if self.face_ranges is not None:
            sizes.append(self.face_ranges.shape[0])
        return max(sizes, default=1)

    @classmethod
    def from_mesh(cls, mesh: Mesh, face_material: torch.Tensor | None = None,
                  materials: Sequence[Material | None] | None = None) -> RenderScene:
        """From a :class:`~torchraster.mesh.Mesh` (e.g. ``io.load_mesh``)."""
        mats = list(materials) if materials is not None else [mesh.material]
        return cls(mesh.positions, mesh.faces, mesh.normals, mesh.uvs, mesh.tangents,
                   face_material, mats)

    @classmethod
    def from_meshes(cls, meshes: Sequence[Mesh]) -> RenderScene:
        """A batch of different meshes: batch item i draws ``meshes[i]`` with its material.

        Attributes shared by every mesh are kept (UVs, tangents, normals only when every mesh
        has them; missing normals are computed).
        """
        packed = pack_meshes(list(meshes))
        return cls(packed.positions, packed.faces, packed.normals, packed.uvs,
                   packed.tangents, packed.face_mesh, list(packed.materials or []),
                   packed.face_ranges)

    @classmethod
    def from_objects(cls, meshes: Sequence[Mesh], object_to_world: torch.Tensor | None = None,
                     categories: Sequence[int] | None = None) -> RenderScene:
        """One scene of N objects with identity: mesh i (model space) is object i + 1.

        Vertices are placed in the world by ``object_to_world`` (normals by its inverse
        transpose, tangents by its 3x3 part; faces of a mirroring transform, det < 0, are
        re-wound to stay counter-clockwise); object i's faces are the contiguous range
        ``object_face_ranges()[i]``. Materials are the meshes' (one entry per distinct
        material, None = glTF default). ``object_coords`` are each mesh's NOCS coordinates
        (:func:`nocs_coords` of its model-space vertices), constant whatever the transform.

        Args:
            meshes: N :class:`~torchraster.mesh.Mesh` in model space (one dtype and device).
            object_to_world: ``(N, 4, 4)`` model -> world matrices (None: identity).
            categories: N non-negative category ids (object i has ``categories[i]``; 0 is
                the background's id); None: ``object_category`` stays None.

        Returns:
            The :class:`RenderScene` (unbatched ``(V, 3)`` positions) with ``face_object``
            ``(F,)``, ``object_category`` ``(N + 1,)`` (or None) and ``object_coords``
            ``(V, 3)``.

        Example:
            >>> tri = Mesh(torch.eye(3), torch.tensor([[0, 1, 2]]))
            >>> scene = RenderScene.from_objects([tri, tri], torch.eye(4).expand(2, 4, 4),
            ...                                  [7, 7])
            >>> scene.face_object, scene.object_category
            (tensor([1, 2]), tensor([0, 7, 7]))
        """
        meshes = check_meshes(meshes)
        ref = meshes[0].positions
        n = len(meshes)
        if object_to_world is None:
            object_to_world = torch.eye(4, dtype=ref.dtype, device=ref.device).expand(n, 4, 4)
        check_tensor("object_to_world", object_to_world, (n, 4, 4), floating=True,
                     finite=True)
        matrices = object_to_world.to(dtype=ref.dtype, device=ref.device)
        category = None
        if categories is not None:
            cats = [int(c) for c in categories]
            if len(cats) != n or any(c < 0 for c in cats):
                raise ValueError(f"categories: expected {n} non-negative category ids (one per "
                                 f"mesh), got {list(categories)}")
            category = torch.tensor([0, *cats], dtype=torch.int64, device=ref.device)
        baked, face_material, materials = bake_instances(meshes, matrices,
                                                         fill_normals=False)
        coords = [nocs_coords(mesh.positions) for mesh in meshes]
        counts = torch.tensor([m.num_faces for m in meshes], device=ref.device)
        face_object = torch.repeat_interleave(
            torch.arange(1, n + 1, device=ref.device), counts)
        return cls(baked.positions, baked.faces, baked.normals, baked.uvs, baked.tangents,
                   face_material if len(materials) > 1 else None, materials,
                   face_object=face_object, object_category=category,
                   object_coords=torch.cat(coords))


def as_render_scene(scene: object) -> RenderScene:
    """A :class:`RenderScene` from a RenderScene, a Mesh, an ``io.Scene`` or a list of Mesh.

    Raises:
        TypeError: naming what was passed, for anything else.
    """
    from .io import Scene  # io imports trimesh: only when needed

    if isinstance(scene, RenderScene):
        return scene
    if isinstance(scene, Mesh):
        return RenderScene.from_mesh(scene)
    if isinstance(scene, Scene):
        mesh, face_material, materials = scene.flatten()
        cast, receive = scene.face_shadow_flags()
        out = RenderScene.from_mesh(mesh, face_material, materials)
        out.cast_shadows = None if bool(cast.all()) else cast
        out.receive_shadows = None if bool(receive.all()) else receive
        # one object per mesh instance, in the face / vertex order of flatten()
        counts = torch.tensor([m.num_faces for m in scene.meshes], device=mesh.faces.device)
        out.face_object = torch.repeat_interleave(
            torch.arange(1, len(scene.meshes) + 1, device=counts.device), counts)
        out.object_coords = torch.cat([nocs_coords(m.positions) for m in scene.meshes])
        return out
    if isinstance(scene, (list, tuple)) and scene and all(isinstance(m, Mesh) for m in scene):
        return RenderScene.from_meshes(scene)
    raise TypeError(f"scene: expected a RenderScene, Mesh, io.Scene or list of Mesh, got "
                    f"{type(scene).__name__}")


__all__ = ["RenderScene", "as_render_scene", "nocs_coords"]
