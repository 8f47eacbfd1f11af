"""What the renderer draws: :class:`RenderScene`, the checked tensors of a batch of scenes.

A ``RenderScene`` is built from a :class:`~torchraster.mesh.Mesh`, a loaded
:class:`~torchraster.io.Scene` (its instances baked into world space), a list of meshes
(one per batch item, packed with :func:`~torchraster.mesh.pack_meshes`) or by hand from
tensors; :func:`as_render_scene` does whichever applies, so ``Renderer`` accepts all of them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import torch

from ._validate import check_tensor
from .material import Material
from .mesh import Mesh, pack_meshes


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

    def to(self, device: torch.device | str) -> RenderScene:
        """The same scene with every tensor (and material texture) on ``device``."""
        moved = {f: (v.to(device) if isinstance(v, torch.Tensor) else v)
                 for f, v in vars(self).items() if f != "materials"}
        return RenderScene(**moved, materials=[m.to(device) if m is not None else None
                                               for m in self.materials])

    @property
    def batch_size(self) -> int:
        """B of the per-item tensors (1 when every tensor is shared)."""
        sizes = [t.shape[0] for t in (self.positions, self.normals, self.uvs, self.tangents)
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
        return out
    if isinstance(scene, (list, tuple)) and scene and all(isinstance(m, Mesh) for m in scene):
        return RenderScene.from_meshes(scene)
    raise TypeError(f"scene: expected a RenderScene, Mesh, io.Scene or list of Mesh, got "
                    f"{type(scene).__name__}")


__all__ = ["RenderScene", "as_render_scene"]
