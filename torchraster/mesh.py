"""Triangle meshes: the Mesh record, normals, tangents, transforms and packing.

Shapes: a single mesh stores ``positions (V, 3)`` and ``faces (F, 3)`` int64 (counter-clockwise
= front facing). The geometry functions also take batches of vertex data ``(B, V, C)`` that
share one ``faces`` array (e.g. one mesh under B deformations), and matrices ``(4, 4)`` or
``(B, 4, 4)``. The result keeps the batching of the input: unbatched in, unbatched out
(``(V, 3) -> (V, 3)``); if any input is batched the result is ``(B, ...)``, inputs of batch
size 1 (or unbatched) broadcasting against the others.

Meshes with different topology are batched by packing (:func:`pack_meshes`): all vertices and
faces concatenated, with per-item ``[start, end)`` ranges.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from ._validate import check_tensor
from .material import Material
from .numerics import compute_dtype, finish_low_precision, to_compute

#: Squared length of an (unnormalised) normal below which it counts as zero. Cross products of
#: edges of length L have squared length ~L**4, so this only catches truly degenerate
#: (zero-area, or below ~1e-7.5 units edge length) triangles; at the floor the normalisation
#: gradient is ~1e15, still finite in float32.
NORMAL_EPS = 1e-30


# ------------------------------------------------------------------------------- helpers
def _safe_normalize(v: torch.Tensor, eps: float = NORMAL_EPS) -> tuple[torch.Tensor, torch.Tensor]:
    """``v / |v|`` over the last dim, 0 where ``|v|**2 <= eps``; returns (unit, ok mask).

    "Double where": the square root only sees safe values, so the gradient is finite (zero)
    for degenerate vectors instead of NaN.
    """
    # v / |v| is invariant to scaling v: divide by the largest |component| first (a
    # constant for autograd, the result and gradient are exact), so the rsqrt sees a value
    # in [1, 3] and its derivative cannot overflow for tiny vectors (edges of 1e-7 gave
    # NaN gradients through rsqrt(1e-28)**3)
    with torch.no_grad():
        big = v.abs().amax(-1, keepdim=True)
        vc = v.to(compute_dtype(v))  # half precision: squares of 1e-4 underflow
        ok = (vc * vc).sum(-1, keepdim=True) > eps
        big = torch.where(ok, big, torch.ones_like(big))
    u = v / big
    len2 = (u * u).sum(-1, keepdim=True)
    inv = torch.rsqrt(torch.where(ok, len2, torch.ones_like(len2)))
    return torch.where(ok, u * inv, torch.zeros_like(v)), ok


def _batched(name: str, x: object, channels: int) -> tuple[torch.Tensor, bool]:
    """Check ``(B, V, C)`` or ``(V, C)`` float vertex data; return it as ``(B, V, C)`` and
    whether it was batched."""
    batched = not (isinstance(x, torch.Tensor) and x.dim() == 2)
    if not batched:
        x = x.unsqueeze(0)  # type: ignore[union-attr]
    return check_tensor(name, x, ("B", "V", channels), floating=True), batched


def _unbatch(out: torch.Tensor, *batched: bool) -> torch.Tensor:
    """Drop the batch dim of ``out (1, ...)`` if no input was batched."""
    return out if any(batched) else out[0]


def _check_faces(faces: object, num_vertices: int | None, name: str = "faces") -> torch.Tensor:
    """Check ``(F, 3)`` integer faces, optionally their range, and return them as int64."""
    faces = check_tensor(name, faces, ("F", 3), integer=True)
    if num_vertices is not None and faces.numel():
        lo, hi = int(faces.min()), int(faces.max())
        if lo < 0 or hi >= num_vertices:
            raise ValueError(
                f"{name}: vertex indices must be in [0, {num_vertices}), got range [{lo}, {hi}]"
            )
    return faces.long()


def _broadcast(**named: torch.Tensor) -> list[torch.Tensor]:
    """Broadcast batch dims of size 1 to the common batch size (error if incompatible)."""
    sizes = {k: v.shape[0] for k, v in named.items()}
    b = max(sizes.values())
    if any(s not in (1, b) for s in sizes.values()):
        raise ValueError(f"batch sizes differ: {sizes}")
    devices = {v.device for v in named.values()}
    dtypes = {v.dtype for v in named.values()}
    if len(devices) > 1 or len(dtypes) > 1:
        got = {k: (str(v.dtype), str(v.device)) for k, v in named.items()}
        raise ValueError(f"expected one dtype and device for all inputs, got {got}")
    return [v.expand(b, *v.shape[1:]) for v in named.values()]


# ---------------------------------------------------------------------------------- Mesh
@dataclass
class Mesh:
    """One triangle mesh.

    Attributes:
        positions: ``(V, 3)`` float (float32 by default), model space.
        faces: ``(F, 3)`` int64 vertex indices, counter-clockwise = front.
        normals: ``(V, 3)`` unit vertex normals, or None.
        uvs: ``(V, 2)`` texture coordinates, OBJ/trimesh convention (origin bottom-left of
            the image, v up), or None.
        tangents: ``(V, 4)``: unit tangent xyz (direction of +u) and the handedness sign w
            (glTF: bitangent = w * cross(normal, tangent.xyz), direction of +v), or None.
        material: the mesh's :class:`~torchraster.material.Material`, or None.
        name: a label.

    Float attributes share the positions' dtype and device; integer faces are converted to
    int64. Validation raises one clear ``ValueError``/``TypeError`` naming the field.
    """

    positions: torch.Tensor
    faces: torch.Tensor
    normals: torch.Tensor | None = None
    uvs: torch.Tensor | None = None
    tangents: torch.Tensor | None = None
    material: Material | None = None
    name: str = "mesh"

    def __post_init__(self) -> None:
        pos = check_tensor("positions", self.positions, ("V", 3), floating=True, finite=True)
        self.faces = _check_faces(self.faces, pos.shape[0])
        if self.faces.device != pos.device:
            raise ValueError(f"faces: on {self.faces.device}, positions on {pos.device}")
        for field_name, c in (("normals", 3), ("uvs", 2), ("tangents", 4)):
            v = getattr(self, field_name)
            if v is None:
                continue
            check_tensor(field_name, v, (pos.shape[0], c), floating=True, finite=True)
            if v.dtype != pos.dtype or v.device != pos.device:
                raise ValueError(
                    f"{field_name}: expected dtype {pos.dtype} on {pos.device} like positions, "
                    f"got {v.dtype} on {v.device}"
                )
        if self.material is not None and not isinstance(self.material, Material):
            raise TypeError(
                f"material: expected a Material or None, got {type(self.material).__name__}"
            )
        if not isinstance(self.name, str):
            raise TypeError(f"name: expected a str, got {type(self.name).__name__}")

    @property
    def num_vertices(self) -> int:
        """V."""
        return self.positions.shape[0]

    @property
    def num_faces(self) -> int:
        """F."""
        return self.faces.shape[0]

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> Mesh:
        """Copy with float attributes cast to ``dtype`` and everything moved to ``device``
        (faces stay int64; the material's tensors are moved too)."""
        if dtype is not None and not dtype.is_floating_point:
            raise ValueError(f"dtype: expected a floating dtype, got {dtype}")

        def cast(t: torch.Tensor | None) -> torch.Tensor | None:
            return None if t is None else t.to(device=device, dtype=dtype)

        return replace(
            self,
            positions=cast(self.positions),
            faces=self.faces.to(device),
            normals=cast(self.normals),
            uvs=cast(self.uvs),
            tangents=cast(self.tangents),
            material=None if self.material is None else self.material.to(device),
        )

    def __repr__(self) -> str:
        extras = [k for k in ("normals", "uvs", "tangents") if getattr(self, k) is not None]
        return (
            f"Mesh(name={self.name!r}, V={self.num_vertices}, F={self.num_faces}, "
            f"dtype={self.positions.dtype}, attrs={extras}, material="
            f"{None if self.material is None else self.material.name!r})"
        )


# ------------------------------------------------------------------------ normals
def face_normals(positions: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit face normals.

    Right-handed: counter-clockwise faces (p0, p1, p2) get ``normalize((p1-p0) x (p2-p0))``.
    Degenerate faces (squared cross-product length <= ``NORMAL_EPS``) get a zero normal with
    finite (zero) gradients. Differentiable with respect to ``positions``.

    Args:
        positions: float vertex positions, one mesh or a batch of deformations of it.
        faces: int vertex indices, counter-clockwise = front.

    Returns:
        One unit normal per face, batched like ``positions``.

    Shape:
        - positions: :math:`(V, 3)` or :math:`(B, V, 3)`.
        - faces: :math:`(F, 3)`.
        - Output: :math:`(F, 3)` or :math:`(B, F, 3)`.

    Example:
        >>> pos = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
        >>> face_normals(pos, torch.tensor([[0, 1, 2]]))
        tensor([[0., 0., 1.]])
    """
    pos, batched = _batched("positions", positions, 3)
    faces = _check_faces(faces, pos.shape[1])
    unit = _safe_normalize(_face_cross(to_compute(pos), faces))[0]  # half: in float32
    return _unbatch(finish_low_precision(unit, pos.dtype), batched)


def _face_cross(pos: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """``(B, F, 3)`` unnormalised face normals: ``(p1-p0) x (p2-p0)``, length = 2 * area."""
    p0, p1, p2 = (pos[:, faces[:, k]] for k in range(3))
    return torch.linalg.cross(p1 - p0, p2 - p0, dim=-1)


def vertex_normals(positions: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Smooth area-weighted unit vertex normals.

    Each vertex sums the unnormalised cross products (2 * area * normal) of its faces, then
    normalises. Differentiable; degenerate faces add nothing and vertices without a
    non-degenerate face get a zero normal, both with finite gradients.

    Args:
        positions: float vertex positions, one mesh or a batch of deformations of it.
        faces: int vertex indices, counter-clockwise = front.

    Returns:
        One unit normal per vertex, batched like ``positions``.

    Shape:
        - positions: :math:`(V, 3)` or :math:`(B, V, 3)`.
        - faces: :math:`(F, 3)`.
        - Output: :math:`(V, 3)` or :math:`(B, V, 3)`, like ``positions``.

    Example:
        >>> pos = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
        >>> vertex_normals(pos, torch.tensor([[0, 1, 2]])).shape
        torch.Size([3, 3])
    """
    pos, batched = _batched("positions", positions, 3)
    faces = _check_faces(faces, pos.shape[1])
    # half precision in float32: the cross products' backward overflows float16
    cross = _face_cross(to_compute(pos), faces)
    acc = cross.new_zeros(pos.shape)
    for k in range(3):
        acc = acc.index_add(1, faces[:, k], cross)
    return _unbatch(finish_low_precision(_safe_normalize(acc)[0], pos.dtype), batched)


def flat(mesh: Mesh) -> Mesh:
    """Unwelded copy of ``mesh`` for flat shading.

    Every face gets its own 3 vertices, with the face normal as vertex normal. UVs are
    copied per corner; tangents, if present, are recomputed per face with
    :func:`vertex_tangents`.

    Args:
        mesh: the mesh to unweld.

    Returns:
        A :class:`Mesh` with ``V' = 3F`` vertices and the same faces in the same order
        (face ``f`` uses vertices ``3f, 3f + 1, 3f + 2``).

    Shape:
        - mesh.positions: :math:`(V, 3)`, mesh.faces: :math:`(F, 3)`.
        - Output positions and normals: :math:`(3F, 3)`; faces: :math:`(F, 3)`.

    Example:
        >>> m = Mesh(torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]),
        ...          torch.tensor([[0, 1, 2], [1, 3, 2]]))
        >>> flat(m).positions.shape, flat(m).normals[0]
        (torch.Size([6, 3]), tensor([0., 0., 1.]))
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh: expected a Mesh, got {type(mesh).__name__}")
    f = mesh.faces
    pos = mesh.positions[f].reshape(-1, 3)
    new_faces = torch.arange(pos.shape[0], device=f.device).view(-1, 3)
    normals = face_normals(mesh.positions, f).repeat_interleave(3, dim=0)
    uvs = None if mesh.uvs is None else mesh.uvs[f].reshape(-1, 2)
    tangents = None
    if mesh.tangents is not None and uvs is not None:
        tangents = vertex_tangents(pos, uvs, normals, new_faces)
    return replace(mesh, positions=pos, faces=new_faces, normals=normals, uvs=uvs,
                   tangents=tangents)


def _any_perpendicular(n: torch.Tensor) -> torch.Tensor:
    """A unit vector perpendicular to unit ``n (..., 3)`` ((1, 0, 0) where n is zero)."""
    ex = torch.zeros_like(n)
    ex[..., 0] = 1.0
    ey = torch.zeros_like(n)
    ey[..., 1] = 1.0
    axis = torch.where(n[..., :1].abs() < 0.9, ex, ey)
    t, ok = _safe_normalize(axis - n * (n * axis).sum(-1, keepdim=True))
    return torch.where(ok, t, ex)


def vertex_tangents(
    positions: torch.Tensor, uvs: torch.Tensor, normals: torch.Tensor, faces: torch.Tensor
) -> torch.Tensor:
    """Per-vertex tangent frames: unit tangent xyz and handedness w = +-1.

    Per triangle, the UV gradient of position (Lengyel 2001, "Computing Tangent Space Basis
    Vectors for an Arbitrary Mesh") ``T = dP/du``, ``Bt = dP/dv`` solved from the edges, is
    accumulated to its vertices weighted by the triangle's UV area (i.e. without dividing by
    the UV determinant, so degenerate UVs add nothing instead of blowing up). Per vertex, T is
    Gram-Schmidt orthogonalised against the normal and normalised;
    ``w = sign(dot(cross(N, T), Bt))`` (+1 on ties). UVs follow the project convention (v up),
    so the bitangent points along +v = image up, matching glTF/OpenGL normal maps.

    This approximates MikkTSpace (used by glTF exporters): it agrees on smooth, consistently
    mapped surfaces but differs in weighting and at seams. Vertices with no usable UV
    gradient get an arbitrary tangent perpendicular to the normal. Differentiable (the sign is
    piecewise constant).

    Args:
        positions: float vertex positions.
        uvs: texture coordinates per vertex (v up).
        normals: unit vertex normals.
        faces: int vertex indices.

    Returns:
        ``(tangent xyz, w)`` per vertex; unbatched only if all three inputs are unbatched.

    Shape:
        - positions: :math:`(V, 3)` or :math:`(B, V, 3)`.
        - uvs: :math:`(V, 2)` or :math:`(B, V, 2)`.
        - normals: :math:`(V, 3)` or :math:`(B, V, 3)`.
        - faces: :math:`(F, 3)`.
        - Output: :math:`(V, 4)`, or :math:`(B, V, 4)` if any input is batched.

    Example:
        >>> pos = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
        >>> nrm = torch.tensor([[0.0, 0, 1]]).expand(3, 3)
        >>> vertex_tangents(pos, pos[:, :2], nrm, torch.tensor([[0, 1, 2]]))[0]
        tensor([1., 0., 0., 1.])
    """
    pos, b_pos = _batched("positions", positions, 3)
    uv, b_uv = _batched("uvs", uvs, 2)
    nrm, b_nrm = _batched("normals", normals, 3)
    if not (pos.shape[1] == uv.shape[1] == nrm.shape[1]):
        raise ValueError(
            f"positions, uvs, normals: vertex counts differ "
            f"({pos.shape[1]}, {uv.shape[1]}, {nrm.shape[1]})"
        )
    pos, uv, nrm = _broadcast(positions=pos, uvs=uv, normals=nrm)
    faces = _check_faces(faces, pos.shape[1])
    p0, p1, p2 = (pos[:, faces[:, k]] for k in range(3))
    t0, t1, t2 = (uv[:, faces[:, k]] for k in range(3))
    e1, e2 = p1 - p0, p2 - p0
    d1, d2 = t1 - t0, t2 - t0
    det = d1[..., 0] * d2[..., 1] - d2[..., 0] * d1[..., 1]  # (B, F): 2 * signed UV area
    sgn = torch.where(det < 0, -1.0, 1.0).to(pos.dtype).unsqueeze(-1)
    # T = (e1 dv2 - e2 dv1) / det, Bt = (e2 du1 - e1 du2) / det; weighted by |det| instead.
    tan = (e1 * d2[..., 1:] - e2 * d1[..., 1:]) * sgn
    bit = (e2 * d1[..., :1] - e1 * d2[..., :1]) * sgn
    t_acc = torch.zeros_like(pos)
    b_acc = torch.zeros_like(pos)
    for k in range(3):
        t_acc = t_acc.index_add(1, faces[:, k], tan)
        b_acc = b_acc.index_add(1, faces[:, k], bit)
    t_orth = t_acc - nrm * (nrm * t_acc).sum(-1, keepdim=True)
    t_unit, ok = _safe_normalize(t_orth)
    t_unit = torch.where(ok, t_unit, _any_perpendicular(nrm))
    hand = (torch.linalg.cross(nrm, t_unit, dim=-1) * b_acc).sum(-1, keepdim=True)
    w = torch.where(hand < 0, -1.0, 1.0).to(pos.dtype)
    return _unbatch(torch.cat([t_unit, w], dim=-1), b_pos, b_uv, b_nrm)


# --------------------------------------------------------------------------- transforms
def _batched_matrix(matrix: object) -> tuple[torch.Tensor, bool]:
    batched = not (isinstance(matrix, torch.Tensor) and matrix.dim() == 2)
    if not batched:
        matrix = matrix.unsqueeze(0)  # type: ignore[union-attr]
    return check_tensor("matrix", matrix, ("B", 4, 4), floating=True), batched


def transform_points(points: torch.Tensor, matrix: torch.Tensor) -> torch.Tensor:
    """Homogeneous transform of points (column-vector convention, ``p' = M @ [p, 1]``).

    No perspective divide: the result is e.g. clip space for model-view-projection matrices
    (:func:`torchraster.rasterize` takes ``(B, V, 4)``: index an unbatched result with
    ``[None]``). A batch size of 1 (or an unbatched input) broadcasts against the other.

    Args:
        points: float points.
        matrix: float 4x4 transforms, one or one per batch item.

    Returns:
        Homogeneous points ``(x, y, z, w)``; unbatched only if both inputs are unbatched.

    Shape:
        - points: :math:`(V, 3)` or :math:`(B, V, 3)`.
        - matrix: :math:`(4, 4)` or :math:`(B, 4, 4)`.
        - Output: :math:`(V, 4)`, or :math:`(B, V, 4)` if either input is batched.

    Example:
        >>> shift = torch.eye(4)
        >>> shift[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
        >>> transform_points(torch.zeros(2, 3), shift)
        tensor([[1., 2., 3., 1.],
                [1., 2., 3., 1.]])
    """
    pts, b_pts = _batched("points", points, 3)
    m, b_m = _batched_matrix(matrix)
    pts, m = _broadcast(points=pts, matrix=m)
    homogeneous = torch.cat([pts, torch.ones_like(pts[..., :1])], dim=-1)
    return _unbatch(homogeneous @ m.transpose(-1, -2), b_pts, b_m)


def _cofactor3(m: torch.Tensor) -> torch.Tensor:
    """Cofactor matrix ``det(M) * M^-T`` of ``(B, 3, 3)`` via cross products of rows (exists
    and is differentiable for singular M)."""
    r0, r1, r2 = m[:, 0], m[:, 1], m[:, 2]
    c = torch.linalg.cross
    return torch.stack([c(r1, r2, dim=-1), c(r2, r0, dim=-1), c(r0, r1, dim=-1)], dim=1)


def transform_normals(normals: torch.Tensor, matrix: torch.Tensor) -> torch.Tensor:
    """Transform normals by the inverse transpose of the 3x3 part of ``matrix``, renormalised.

    Uses ``sign(det) * cofactor(M)`` (= ``|det| * M^-T``): no matrix inverse, so singular
    matrices give finite results (normals in the collapsed direction become zero). Note that
    a mirroring matrix (det < 0) also reverses the faces' winding.

    Args:
        normals: float normals (need not be unit).
        matrix: float 4x4 model transforms (the translation is ignored).

    Returns:
        Unit normals (zero where degenerate); unbatched only if both inputs are unbatched.

    Shape:
        - normals: :math:`(V, 3)` or :math:`(B, V, 3)`.
        - matrix: :math:`(4, 4)` or :math:`(B, 4, 4)`.
        - Output: :math:`(V, 3)`, or :math:`(B, V, 3)` if either input is batched.

    Example:
        >>> stretch = torch.diag(torch.tensor([2.0, 1.0, 1.0, 1.0]))
        >>> transform_normals(torch.tensor([[1.0, 1.0, 0.0]]), stretch)
        tensor([[0.4472, 0.8944, 0.0000]])
    """
    nrm, b_nrm = _batched("normals", normals, 3)
    m, b_m = _batched_matrix(matrix)
    nrm, m = _broadcast(normals=nrm, matrix=m)
    m3 = m[:, :3, :3]
    cof = _cofactor3(m3)
    det = (m3[:, 0] * cof[:, 0]).sum(-1)
    cof = cof * torch.where(det < 0, -1.0, 1.0).to(cof.dtype)[:, None, None]
    return _unbatch(_safe_normalize(nrm @ cof.transpose(-1, -2))[0], b_nrm, b_m)


def transform_tangents(tangents: torch.Tensor, matrix: torch.Tensor) -> torch.Tensor:
    """Transform glTF tangents: xyz by the 3x3 part of ``matrix`` (renormalised), w flipped
    when ``det < 0`` (a mirror swaps the handedness).

    Args:
        tangents: float glTF tangents, unit xyz and handedness w = +-1.
        matrix: float 4x4 model transforms (the translation is ignored).

    Returns:
        Transformed tangents; unbatched only if both inputs are unbatched.

    Shape:
        - tangents: :math:`(V, 4)` or :math:`(B, V, 4)`.
        - matrix: :math:`(4, 4)` or :math:`(B, 4, 4)`.
        - Output: :math:`(V, 4)`, or :math:`(B, V, 4)` if either input is batched.

    Example:
        >>> mirror = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))
        >>> transform_tangents(torch.tensor([[1.0, 0.0, 0.0, 1.0]]), mirror)
        tensor([[-1.,  0.,  0., -1.]])
    """
    tan, b_tan = _batched("tangents", tangents, 4)
    m, b_m = _batched_matrix(matrix)
    tan, m = _broadcast(tangents=tan, matrix=m)
    m3 = m[:, :3, :3]
    xyz = _safe_normalize(tan[..., :3] @ m3.transpose(-1, -2))[0]
    det = torch.linalg.det(m3.detach())
    w = tan[..., 3:] * torch.where(det < 0, -1.0, 1.0).to(tan.dtype)[:, None, None]
    return _unbatch(torch.cat([xyz, w], dim=-1), b_tan, b_m)


# ------------------------------------------------------------------------------ packing
@dataclass
class PackedMeshes:
    """Several meshes of different topology concatenated into one vertex/face list.

    Attributes:
        positions: ``(V_total, 3)`` all vertices, mesh after mesh.
        faces: ``(F_total, 3)`` int64 *global* vertex indices.
        face_ranges: ``(N, 2)`` int64 ``[start, end)`` of mesh i's faces in ``faces``.
        vertex_ranges: ``(N, 2)`` int64 ``[start, end)`` of mesh i's vertices.
        face_mesh: ``(F_total,)`` int64 mesh index of every face.
        normals, uvs, tangents: ``(V_total, C)`` if every mesh has them, else None.
        materials: the meshes' materials (entries may be None).

    Rendering convention: ``tr.rasterize(clip_pos (B, V_total, 4), faces, resolution,
    face_ranges=(B, 2))`` rasterizes, for batch item b, only ``faces[start_b:end_b]``. To
    render mesh i in item i, transform ``positions`` with item i's matrices
    (:func:`transform_points` with ``(N, 4, 4)``) and pass ``face_ranges`` as is; vertices
    outside an item's range are simply never referenced.
    """

    positions: torch.Tensor
    faces: torch.Tensor
    face_ranges: torch.Tensor
    vertex_ranges: torch.Tensor
    face_mesh: torch.Tensor
    normals: torch.Tensor | None = None
    uvs: torch.Tensor | None = None
    tangents: torch.Tensor | None = None
    materials: list[Material | None] | None = None

    @property
    def num_meshes(self) -> int:
        """N."""
        return self.face_ranges.shape[0]


def _concat(attrs: list[torch.Tensor | None]) -> torch.Tensor | None:
    return None if any(a is None for a in attrs) else torch.cat(attrs, 0)  # type: ignore[arg-type]


def check_meshes(meshes: object) -> list[Mesh]:
    """``meshes`` as a non-empty list of :class:`Mesh` of one dtype and device; the error
    names the argument (``meshes[i]``) otherwise."""
    if not isinstance(meshes, (list, tuple)) or not meshes:
        raise ValueError("meshes: expected a non-empty list of Mesh")
    for i, m in enumerate(meshes):
        if not isinstance(m, Mesh):
            raise TypeError(f"meshes[{i}]: expected a Mesh, got {type(m).__name__}")
    ref = meshes[0].positions
    for i, m in enumerate(meshes):
        if m.positions.dtype != ref.dtype or m.positions.device != ref.device:
            raise ValueError(
                f"meshes[{i}]: dtype/device {m.positions.dtype}/{m.positions.device} differs "
                f"from meshes[0] ({ref.dtype}/{ref.device})"
            )
    return list(meshes)


def bake_instances(meshes: Sequence[Mesh], matrices: torch.Tensor, fill_normals: bool = True
                   ) -> tuple[Mesh, torch.Tensor, list]:
    """Mesh instances baked into one world-space mesh.

    Positions by the matrices, normals by their inverse transpose (missing ones computed
    first), tangents by the linear part (only if every mesh has them), UVs zero-filled where
    a mesh has none; faces of mirroring instances (det < 0) re-wound to stay
    counter-clockwise (glTF 2.0). Materials are merged by identity (None kept).

    Args:
        meshes: N model-space meshes. matrices: ``(N, 4, 4)`` model -> world.
        fill_normals: compute missing normals even when no mesh has any (else the result
            has none then).

    Returns:
        ``(mesh, face_material (F,) int64, materials)``; ``mesh.material`` is the material
        when there is exactly one.
    """
    index: dict[int, int] = {}
    mats: list = []
    pos, faces, nrm, uvs, tan, fmat = [], [], [], [], [], []
    want_nrm = fill_normals or any(m.normals is not None for m in meshes)
    any_uv = any(m.uvs is not None for m in meshes)
    all_tan = all(m.tangents is not None for m in meshes)
    offset = 0
    for mesh, matrix in zip(meshes, matrices, strict=True):
        key = id(mesh.material)
        if key not in index:
            index[key] = len(mats)
            mats.append(mesh.material)
        f = mesh.faces
        if bool(torch.linalg.det(matrix[:3, :3].detach().double()) < 0):
            f = f[:, [0, 2, 1]]  # a mirror reverses the winding (glTF 2.0, det < 0)
        faces.append(f + offset)
        offset += mesh.num_vertices
        pos.append(transform_points(mesh.positions, matrix)[:, :3])
        if want_nrm:
            normals = mesh.normals if mesh.normals is not None else vertex_normals(
                mesh.positions, mesh.faces)
            nrm.append(transform_normals(normals, matrix))
        if any_uv:
            uvs.append(mesh.uvs if mesh.uvs is not None else mesh.positions.new_zeros(
                mesh.num_vertices, 2))
        if all_tan:
            tan.append(transform_tangents(mesh.tangents, matrix))
        fmat.append(torch.full((mesh.num_faces,), index[key], dtype=torch.int64,
                               device=f.device))
    flat = Mesh(positions=torch.cat(pos), faces=torch.cat(faces),
                normals=torch.cat(nrm) if want_nrm else None,
                uvs=torch.cat(uvs) if any_uv else None,
                tangents=torch.cat(tan) if all_tan else None,
                material=mats[0] if len(mats) == 1 else None)
    return flat, torch.cat(fmat), mats


def pack_meshes(meshes: list[Mesh]) -> PackedMeshes:
    """Pack meshes of different topology into one vertex and face list.

    Args:
        meshes: N :class:`Mesh` of any sizes, one dtype and device.

    Returns:
        :class:`PackedMeshes` (see its docstring for the fields and the rasterize
        convention: batch item i draws mesh i through ``face_ranges``).

    Shape:
        - Output positions: :math:`(\\sum V_i, 3)`; faces: :math:`(\\sum F_i, 3)` with global
          vertex indices; face_ranges, vertex_ranges: :math:`(N, 2)`.

    Example:
        >>> tri = Mesh(torch.eye(3), torch.tensor([[0, 1, 2]]))
        >>> pack_meshes([tri, tri]).face_ranges
        tensor([[0, 1],
                [1, 2]])
    """
    meshes = check_meshes(meshes)
    ref = meshes[0].positions
    nv = torch.tensor([m.num_vertices for m in meshes], dtype=torch.int64)
    nf = torch.tensor([m.num_faces for m in meshes], dtype=torch.int64)
    v_end, f_end = nv.cumsum(0), nf.cumsum(0)
    v_start, f_start = v_end - nv, f_end - nf
    faces = torch.cat([m.faces + int(s) for m, s in zip(meshes, v_start, strict=True)], 0)
    dev = ref.device
    return PackedMeshes(
        positions=torch.cat([m.positions for m in meshes], 0),
        faces=faces,
        face_ranges=torch.stack([f_start, f_end], 1).to(dev),
        vertex_ranges=torch.stack([v_start, v_end], 1).to(dev),
        face_mesh=torch.repeat_interleave(torch.arange(len(meshes)), nf).to(dev),
        normals=_concat([m.normals for m in meshes]),
        uvs=_concat([m.uvs for m in meshes]),
        tangents=_concat([m.tangents for m in meshes]),
        materials=[m.material for m in meshes],
    )


__all__ = [
    "Mesh",
    "PackedMeshes",
    "NORMAL_EPS",
    "face_normals",
    "vertex_normals",
    "flat",
    "vertex_tangents",
    "transform_points",
    "transform_normals",
    "transform_tangents",
    "pack_meshes",
    "check_meshes",
    "bake_instances",
]
