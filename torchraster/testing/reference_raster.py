"""Independent float64 brute-force reference rasterizer (shares no code with torchraster).

Every pixel centre is tested against every face with 2D homogeneous edge functions
(Olano & Greer 1997, "Triangle scan conversion using 2D homogeneous coordinates"): with the
clip-space vertices ``V_k = (x_k, y_k, w_k)`` as the columns of ``M`` and a pixel's NDC point
``p = (px, py, 1)``, the point of the face's plane seen through ``p`` has the barycentrics
``b = M^-1 p / sum(M^-1 p)`` (perspective-correct: they are the affine weights of the clip-space,
hence world-space, point) and clip ``w = det(M) / sum(e)`` where
``e_0 = (V_1 x V_2) . p``, ``e_1 = (V_2 x V_0) . p``, ``e_2 = (V_0 x V_1) . p``.
The point lies on the face with ``w > 0`` iff every ``det * e_k >= 0`` (and ``det * sum(e) > 0``).
NDC depth is ``z = sum(e_k z_k) / det`` (``sum(e_k w_k) = det``), affine in screen space.

The public contract (docs/design.md) is then applied per point, without any clipping code:
- visible iff ``w > 0`` and ``-w <= z <= w`` (so faces crossing the near or far plane, or
  reaching behind the camera, are clipped exactly where the plane cuts them);
- top-left rule on edges: a pixel centre with ``e_k == 0`` is covered iff the inward normal of
  edge k (``sign(det) * grad e_k`` in NDC, y up) has a positive x component (a left edge), or
  is exactly vertical and points down (-y: a horizontal top edge);
- faces with ``det == 0`` (zero area in 2D homogeneous space) cover nothing;
- ``cull_backfaces`` drops faces with ``det < 0`` (clockwise as seen by the camera);
- nearest NDC depth wins, exact ties go to the lower face index.

Faces are processed in chunks so memory stays bounded (about ``MAX_PAIRS`` face-pixel pairs at a
time), and pixel tiles skip faces whose conservative screen bounds miss them (speed only).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

MAX_PAIRS = 1 << 21  # face-pixel pairs evaluated at once (bounds the float64 temporaries)
TILE = 8  # pixels are visited in TILE x TILE blocks against the faces whose bounds touch them
BBOX_MARGIN = 1e-9  # NDC slack on the conservative face bounds (only ever includes more)


@dataclass
class RefFragments:
    """Reference fragments: face_id (B,H,W) int64 (-1 empty), bary (B,H,W,3) float64 (0 empty),
    depth (B,H,W) float64 NDC z (+inf empty)."""

    face_id: torch.Tensor
    bary: torch.Tensor
    depth: torch.Tensor


def pixel_centres(h: int, w: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """NDC pixel centres (H*W, 2), row-major: x = 2(j+0.5)/W - 1, y = 1 - 2(i+0.5)/H."""
    i = torch.arange(h, dtype=dtype)
    j = torch.arange(w, dtype=dtype)
    y = 1 - 2 * (i + 0.5) / h
    x = 2 * (j + 0.5) / w - 1
    yy, xx = torch.meshgrid(y, x, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], dim=-1)


def edge_coefficients(tri: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Edge-function coefficients of clip-space triangles.

    tri: (..., 3, 4) clip positions (x, y, z, w) of the three vertices.
    Returns ``coef`` (..., 3, 3): row k holds (a, b, c) with e_k(p) = a px + b py + c for edge k
    (the edge opposite vertex k), and ``det`` (...): det of the (x, y, w) vertex matrix.
    """
    v = tri[..., [0, 1, 3]]  # (..., 3, 3): (x, y, w) per vertex
    v0, v1, v2 = v[..., 0, :], v[..., 1, :], v[..., 2, :]
    coef = torch.stack(
        [torch.linalg.cross(v1, v2), torch.linalg.cross(v2, v0), torch.linalg.cross(v0, v1)],
        dim=-2,
    )
    det = (v0 * coef[..., 0, :]).sum(-1)
    return coef, det


def _top_left(coef: torch.Tensor, det: torch.Tensor) -> torch.Tensor:
    """(..., 3) bool: edge k owns pixel centres lying exactly on it (top-left rule)."""
    s = torch.sign(det)[..., None]
    nx, ny = s * coef[..., 0], s * coef[..., 1]  # inward normal in NDC (y up)
    return (nx > 0) | ((nx == 0) & (ny < 0))


def _eval(
    tri: torch.Tensor, pix: torch.Tensor, cull_backfaces: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Coverage, depth and edge values for faces ``tri`` (F,3,4) at pixels ``pix`` (P,2).

    Returns covered (F,P) bool, depth (F,P) NDC z (inf where not covered), e (F,P,3).
    """
    coef, det = edge_coefficients(tri)  # (F,3,3), (F,)
    e = (
        coef[:, None, :, 0] * pix[None, :, None, 0]
        + coef[:, None, :, 1] * pix[None, :, None, 1]
        + coef[:, None, :, 2]
    )  # (F,P,3)
    s = torch.sign(det)[:, None, None]
    tl = _top_left(coef, det)[:, None, :]
    inside = ((s * e > 0) | ((e == 0) & tl)).all(-1)
    esum = e.sum(-1)
    inside &= (det[:, None] * esum) > 0  # w > 0 (excludes det == 0)
    if cull_backfaces:
        inside &= (det > 0)[:, None]
    safe_det = torch.where(det == 0, torch.ones_like(det), det)
    z = (e * tri[:, None, :, 2]).sum(-1) / safe_det[:, None]  # NDC z, affine in screen space
    inside &= (z >= -1) & (z <= 1)
    depth = torch.where(inside, z, torch.full_like(z, float("inf")))
    return inside, depth, e


def face_bary_depth(
    clip_pos: torch.Tensor, faces: torch.Tensor, face_idx: torch.Tensor, pix: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Perspective-correct barycentrics (N,3) and NDC depth (N,) of face ``face_idx`` (N,)
    at NDC points ``pix`` (N,2), for one batch item's ``clip_pos`` (V,4). No coverage test."""
    tri = clip_pos[faces[face_idx]].to(torch.float64)  # (N,3,4)
    coef, det = edge_coefficients(tri)
    e = coef[..., 0] * pix[:, None, 0] + coef[..., 1] * pix[:, None, 1] + coef[..., 2]
    bary = e / e.sum(-1, keepdim=True)
    depth = (e * tri[..., 2]).sum(-1) / det
    return bary, depth


def rounding_condition(
    clip_pos: torch.Tensor, faces: torch.Tensor, face_idx: torch.Tensor, pix: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Componentwise condition numbers of the barycentrics (N,) and NDC depth (N,) of face
    ``face_idx`` (N,) at ``pix`` (N,2) with respect to the face's clip coordinates:
    ``cond = sum_j |d out / d x_j| |x_j|`` (max over the three barycentrics), from float64
    autograd. Perturbing every input by a relative u (float rounding of the inputs, or of an
    algorithm that is backward stable in them) changes the output by at most ~u * cond to
    first order (Higham, "Accuracy and Stability of Numerical Algorithms", 2nd ed., sec. 7.2).
    Well-shaped faces have cond ~ 1..10; slivers and huge near-plane crossers far more."""
    with torch.enable_grad():
        tri = clip_pos[faces[face_idx]].detach().to(torch.float64).requires_grad_(True)
        # The pixel centre's NDC coordinates are inputs too: a float32 engine rounds them.
        p = pix.detach().to(torch.float64).requires_grad_(True)
        coef, det = edge_coefficients(tri)
        e = coef[..., 0] * p[:, None, 0] + coef[..., 1] * p[:, None, 1] + coef[..., 2]
        bary = e / e.sum(-1, keepdim=True)
        z = (e * tri[..., 2]).sum(-1) / det
        conds = []
        for out in (bary[:, 0], bary[:, 1], bary[:, 2], z):
            g, gp = torch.autograd.grad(out.sum(), (tri, p), retain_graph=True)
            conds.append((g.abs() * tri.detach().abs()).sum((-1, -2))
                         + (gp.abs() * p.detach().abs()).sum(-1))
    cond_bary = torch.stack(conds[:3], -1).amax(-1)
    # Depth computed *through* the barycentrics (as the engine does: z = sum b_i z_i /
    # sum b_i w_i) inherits their rounding: on slivers the barycentrics are ill-conditioned
    # while the depth itself is not, so add the first-order propagation of the barycentric
    # errors, cond_bary * spread of the vertices' NDC depths.
    w = tri.detach()[..., 3]
    z_ndc = tri.detach()[..., 2] / torch.where(w > 0, w, torch.ones_like(w))
    spread = torch.where((w > 0).all(-1), z_ndc.amax(-1) - z_ndc.amin(-1), torch.ones_like(w[:, 0]))
    return cond_bary, conds[3] + cond_bary * spread


def boundary_distance_px(
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    face_idx: torch.Tensor,
    pix: torch.Tensor,
    resolution: tuple[int, int],
) -> torch.Tensor:
    """Distance in pixels (N,) from NDC points ``pix`` (N,2) to the nearest boundary line of the
    visible region of face ``face_idx`` (N,): its three edge lines, the near/far plane lines
    (NDC z = -1 / +1) and the horizon (w = 0). 0 for degenerate faces. One batch item."""
    h, w = resolution
    tri = clip_pos[faces[face_idx]].to(torch.float64)
    coef, det = edge_coefficients(tri)
    px_scale = torch.tensor([2.0 / w, 2.0 / h], dtype=torch.float64)  # NDC units per pixel
    # Linear functions of p (NDC): the three edges, sum(e) (w = 0 line), z*det -/+ det.
    zc = (coef * tri[..., 2:3]).sum(-2)  # sum_k z_k * coef_k -> (N,3): z*det as linear fn
    wc = coef.sum(-2)  # sum(e) as a linear function
    near = zc + torch.stack([0 * det, 0 * det, det], -1)  # z*det + det = 0  <=> z = -1
    far = zc - torch.stack([0 * det, 0 * det, det], -1)
    lines = torch.cat([coef, wc[:, None], near[:, None], far[:, None]], dim=1)  # (N,6,3)
    val = lines[..., 0] * pix[:, None, 0] + lines[..., 1] * pix[:, None, 1] + lines[..., 2]
    grad = torch.linalg.vector_norm(lines[..., :2] * px_scale, dim=-1)
    dist = torch.where(grad > 0, val.abs() / grad.clamp_min(1e-300), torch.full_like(val, 1e30))
    dist = dist.min(-1).values
    return torch.where(det == 0, torch.zeros_like(dist), dist)


def _candidates(tris: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Conservative per-face screen bounds, used only to skip pixels that cannot be covered.

    tris: (F,3,4). Returns keep (F,) bool (False when all three vertices lie outside one clip
    plane: by convexity no point of the face is visible) and bbox (F,4) = (xmin, xmax, ymin,
    ymax) in NDC (the whole plane for faces with a vertex at w <= 0, whose projection is
    unbounded).
    """
    x, y, z, w = tris.unbind(-1)  # (F,3) each
    keep = torch.ones(tris.shape[0], dtype=torch.bool)
    for c in (x, y, z):
        keep &= ~((c > w).all(-1) | (c < -w).all(-1))
    front = (w > 0).all(-1)
    sw = torch.where(w > 0, w, torch.ones_like(w))
    sx, sy = x / sw, y / sw
    big = torch.full_like(sx[:, 0], float("inf"))
    bbox = torch.stack(
        [
            torch.where(front, sx.min(-1).values - BBOX_MARGIN, -big),
            torch.where(front, sx.max(-1).values + BBOX_MARGIN, big),
            torch.where(front, sy.min(-1).values - BBOX_MARGIN, -big),
            torch.where(front, sy.max(-1).values + BBOX_MARGIN, big),
        ],
        dim=-1,
    )
    return keep, bbox


def reference_rasterize(
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    resolution: tuple[int, int],
    cull_backfaces: bool = False,
    face_ranges: torch.Tensor | None = None,
) -> RefFragments:
    """Brute-force float64 rasterization following the torchraster contract.

    clip_pos: (B,V,4) clip-space positions; faces: (F,3) int64; resolution: (H, W);
    face_ranges: optional (B,2) [start, end) face range per batch item.
    Returns RefFragments with face_id (B,H,W), bary (B,H,W,3) float64, depth (B,H,W) float64.
    Pixels are visited in TILE x TILE blocks, each against the faces whose conservative screen
    bounds touch it (a pure speed-up: every face-pixel pair that can cover is still tested).
    """
    h, w = resolution
    clip_pos = clip_pos.detach().to(torch.float64).cpu()
    faces = faces.detach().to(torch.int64).cpu()
    bsz, nf = clip_pos.shape[0], faces.shape[0]
    pix = pixel_centres(h, w)
    face_id = torch.full((bsz, h * w), -1, dtype=torch.int64)
    depth = torch.full((bsz, h * w), float("inf"), dtype=torch.float64)
    bary = torch.zeros((bsz, h * w, 3), dtype=torch.float64)
    rows = torch.arange(h * w) // w
    cols = torch.arange(h * w) % w
    tiles = [
        ((rows // TILE == ti) & (cols // TILE == tj)).nonzero().squeeze(1)
        for ti in range((h + TILE - 1) // TILE)
        for tj in range((w + TILE - 1) // TILE)
    ]
    for b in range(bsz):
        lo, hi = 0, nf
        if face_ranges is not None:
            lo, hi = (int(v) for v in face_ranges[b])
            lo, hi = max(lo, 0), min(hi, nf)
        idx = torch.arange(lo, max(hi, lo))
        tris = clip_pos[b][faces[idx]]
        keep, bbox = _candidates(tris)
        idx, tris, bbox = idx[keep], tris[keep], bbox[keep]
        for tile in tiles:
            tp = pix[tile]
            x0, x1 = tp[:, 0].min(), tp[:, 0].max()
            y0, y1 = tp[:, 1].min(), tp[:, 1].max()
            sel = (bbox[:, 0] <= x1) & (bbox[:, 1] >= x0) & (bbox[:, 2] <= y1) & (bbox[:, 3] >= y0)
            t_idx, t_tris = idx[sel], tris[sel]  # ascending face index
            best_z = torch.full((tile.numel(),), float("inf"), dtype=torch.float64)
            best_f = torch.full((tile.numel(),), -1, dtype=torch.int64)
            chunk = max(1, MAX_PAIRS // tile.numel())
            for s in range(0, t_idx.numel(), chunk):
                _, z, _ = _eval(t_tris[s : s + chunk], tp, cull_backfaces)
                zmin, arg = z.min(0)  # first minimum = lowest face index within the chunk
                better = zmin < best_z  # strict: earlier chunks (lower indices) win ties
                best_z = torch.where(better, zmin, best_z)
                best_f = torch.where(better, t_idx[s : s + chunk][arg], best_f)
            depth[b, tile], face_id[b, tile] = best_z, best_f
        hit = face_id[b] >= 0
        if hit.any():
            bb, _ = face_bary_depth(clip_pos[b], faces, face_id[b][hit], pix[hit])
            bary[b, hit] = bb
    return RefFragments(
        face_id=face_id.view(bsz, h, w),
        bary=bary.view(bsz, h, w, 3),
        depth=depth.view(bsz, h, w),
    )


def reference_pixels(
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    pixels: torch.Tensor,
    resolution: tuple[int, int],
    cull_backfaces: bool = False,
) -> torch.Tensor:
    """Reference face ids (N,) at selected pixels ``pixels`` (N,2) (row, col) of one batch
    item (``clip_pos`` (V,4)); -1 where empty. Cheap for a few pixels of a big mesh."""
    h, w = resolution
    clip_pos = clip_pos.detach().to(torch.float64).cpu()
    faces = faces.detach().cpu()
    pix = pixel_centres(h, w)[pixels[:, 0] * w + pixels[:, 1]]
    best_z = torch.full((pix.shape[0],), float("inf"), dtype=torch.float64)
    best_f = torch.full((pix.shape[0],), -1, dtype=torch.int64)
    chunk = max(1, MAX_PAIRS // max(pix.shape[0], 1))
    for s in range(0, faces.shape[0], chunk):
        _, z, _ = _eval(clip_pos[faces[s : s + chunk]], pix, cull_backfaces)
        zmin, arg = z.min(0)
        better = zmin < best_z
        best_z = torch.where(better, zmin, best_z)
        best_f = torch.where(better, arg + s, best_f)
    return best_f


def reference_coverage_count(
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    resolution: tuple[int, int],
    cull_backfaces: bool = False,
) -> torch.Tensor:
    """How many faces cover each pixel centre, ignoring depth: (B,H,W) int64."""
    h, w = resolution
    clip_pos = clip_pos.detach().to(torch.float64).cpu()
    pix = pixel_centres(h, w)
    chunk = max(1, MAX_PAIRS // max(h * w, 1))
    out = torch.zeros((clip_pos.shape[0], h * w), dtype=torch.int64)
    for b in range(clip_pos.shape[0]):
        tris = clip_pos[b][faces.cpu()]
        for s in range(0, tris.shape[0], chunk):
            cov, _, _ = _eval(tris[s : s + chunk], pix, cull_backfaces)
            out[b] += cov.sum(0)
    return out.view(-1, h, w)


def reference_interpolate(
    vertex_attrs: torch.Tensor, frags: RefFragments, faces: torch.Tensor
) -> torch.Tensor:
    """Interpolate (B,V,C) or (V,C) attributes with the reference fragments -> (B,C,H,W)."""
    bsz, h, w = frags.face_id.shape
    attrs = vertex_attrs.detach().to(torch.float64).cpu()
    if attrs.dim() == 2:
        attrs = attrs.expand(bsz, -1, -1)
    fid = frags.face_id.reshape(bsz, -1)
    hit = fid >= 0
    tri_idx = faces.cpu()[fid.clamp_min(0)]  # (B,P,3)
    vals = torch.gather(
        attrs[:, None].expand(-1, fid.shape[1], -1, -1),
        2,
        tri_idx[..., None].expand(-1, -1, -1, attrs.shape[-1]),
    )  # (B,P,3,C)
    out = (vals * frags.bary.reshape(bsz, -1, 3, 1)).sum(2)
    out = torch.where(hit[..., None], out, torch.zeros_like(out))
    return out.permute(0, 2, 1).reshape(bsz, -1, h, w)


# ---------------------------------------------------------------------------------------------
# Scene helpers shared by the rasterizer tests and scripts/stress.py (own float64 camera maths,
# independent of torchraster.camera).
# ---------------------------------------------------------------------------------------------

EDGE_TOL_PX = 1e-4  # a disagreement is "float32 rounding" only this close (px) to a boundary
DEPTH_TIE_TOL = 1e-6  # ... or where the two faces' NDC depths differ by less than this
ROUNDOFF_FACTOR = 8.0  # allowed error = max(abs tol, ROUNDOFF_FACTOR * u * rounding_condition)
UNIT_ROUNDOFF = {torch.float32: 2.0**-24, torch.float64: 2.0**-53}


def perspective_matrix(fov_y_deg: float, aspect: float, near: float, far: float) -> torch.Tensor:
    """OpenGL perspective projection (4,4) float64 (camera looks down -z, NDC z in [-1, 1])."""
    f = 1.0 / torch.tan(torch.tensor(fov_y_deg, dtype=torch.float64) * torch.pi / 360)
    m = torch.zeros(4, 4, dtype=torch.float64)
    m[0, 0], m[1, 1] = f / aspect, f
    m[2, 2], m[2, 3] = (far + near) / (near - far), 2 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


def look_at_matrix(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """World -> view (4,4) float64, OpenGL convention (camera at eye looking down -z)."""
    eye, target, up = (t.to(torch.float64) for t in (eye, target, up))
    fwd = target - eye
    fwd = fwd / fwd.norm()
    right = torch.linalg.cross(fwd, up)
    right = right / right.norm()
    true_up = torch.linalg.cross(right, fwd)
    m = torch.eye(4, dtype=torch.float64)
    m[0, :3], m[1, :3], m[2, :3] = right, true_up, -fwd
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def to_clip(points: torch.Tensor, matrix: torch.Tensor) -> torch.Tensor:
    """(..., N, 3) points times a (4,4) matrix -> (..., N, 4) homogeneous positions."""
    ones = torch.ones_like(points[..., :1])
    return torch.cat([points, ones], -1) @ matrix.transpose(-1, -2)


def load_mesh(path: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Load a mesh with trimesh, centred and scaled into the unit ball: verts (V,3) float64,
    faces (F,3) int64."""
    import trimesh

    mesh = trimesh.load(path, force="mesh", process=False)
    v = torch.as_tensor(mesh.vertices, dtype=torch.float64)
    f = torch.as_tensor(mesh.faces, dtype=torch.int64)
    v = v - (v.max(0).values + v.min(0).values) / 2
    return v / v.norm(dim=-1).max(), f


def random_view_clip(
    verts: torch.Tensor,
    gen: torch.Generator,
    distance: tuple[float, float] = (2.2, 3.5),
    fov: float = 45.0,
    near: float = 0.1,
    far: float = 100.0,
) -> torch.Tensor:
    """Clip positions (V,4) float64 of ``verts`` seen from a random viewpoint on a sphere
    (radius drawn from ``distance``) looking at a jittered origin with a random up vector."""
    d = torch.randn(3, generator=gen, dtype=torch.float64)
    r = distance[0] + (distance[1] - distance[0]) * torch.rand(1, generator=gen).item()
    eye = d / d.norm() * r
    target = 0.1 * torch.randn(3, generator=gen, dtype=torch.float64)
    up = torch.randn(3, generator=gen, dtype=torch.float64)
    view = look_at_matrix(eye, target, up)
    return to_clip(verts, perspective_matrix(fov, 1.0, near, far) @ view)


SOUP_KINDS = ("normal", "sliver", "degenerate", "near", "behind", "far")


def random_soup(
    gen: torch.Generator,
    batch: int,
    n_faces: int,
    weights: tuple[float, ...] = (4, 2, 1, 0.5, 1, 1),
    near: float = 0.5,
    far: float = 10.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A hostile triangle soup in clip space.

    Faces of every kind in SOUP_KINDS: ordinary triangles, slivers (third vertex 1e-6 .. 1e-1 of
    the size off the opposite edge), degenerate ones (exactly collinear in clip space, or a
    repeated vertex index), triangles crossing the near plane and reaching behind the camera,
    triangles wholly behind the camera, and triangles crossing the far plane.
    ``weights`` are the relative frequencies of the kinds.
    Returns clip_pos (B, 3F, 4) float64, faces (F,3) int64, kind (F,) int64 (index into
    SOUP_KINDS); faces are shared by the batch, positions differ per batch item.
    """
    fov = 50.0
    proj = perspective_matrix(fov, 1.0, near, far)
    tan = float(torch.tan(torch.tensor(fov * torch.pi / 360)))
    kind = torch.multinomial(
        torch.tensor(weights, dtype=torch.float64), n_faces, replacement=True, generator=gen
    )
    out = []
    for _ in range(batch):
        u = torch.rand(n_faces, generator=gen, dtype=torch.float64)
        depth = near + (far - near) * u
        size = depth * (0.03 + 0.5 * torch.rand(n_faces, generator=gen, dtype=torch.float64))
        depth = torch.where(kind == 3, near * (0.5 + u), depth)
        size = torch.where(kind == 3, near * (1 + 3 * u), size)
        depth = torch.where(kind == 4, -near * (0.5 + 3 * u), depth)  # behind the camera
        depth = torch.where(kind == 5, far * (0.9 + 0.2 * u), depth)
        size = torch.where(kind == 5, far * 0.3, size)
        xy = (2.4 * torch.rand(n_faces, 2, generator=gen, dtype=torch.float64) - 1.2)
        xy = xy * depth.abs()[:, None] * tan * torch.where(kind == 3, 3.0, 1.0)[:, None]
        centre = torch.cat([xy, -depth[:, None]], -1)
        tri = centre[:, None] + size[:, None, None] * torch.randn(
            n_faces, 3, 3, generator=gen, dtype=torch.float64
        )
        t = torch.rand(n_faces, 1, generator=gen, dtype=torch.float64)
        sliver = tri[:, 0] + t * (tri[:, 1] - tri[:, 0])
        thin = 10 ** (-1 - 5 * torch.rand(n_faces, 1, generator=gen, dtype=torch.float64))
        sliver = sliver + thin * size[:, None] * torch.randn(
            n_faces, 3, generator=gen, dtype=torch.float64
        )
        tri[:, 2] = torch.where((kind == 1)[:, None], sliver, tri[:, 2])
        out.append(to_clip(tri.reshape(-1, 3), proj))
    clip = torch.stack(out)
    # degenerate: every other one exactly collinear in clip space, the rest a repeated index
    deg = (kind == 2).nonzero().squeeze(1)
    col, rep = deg[0::2], deg[1::2]
    clip[:, 3 * col + 2] = 0.5 * (clip[:, 3 * col] + clip[:, 3 * col + 1])
    faces = torch.arange(3 * n_faces).view(n_faces, 3)
    faces[rep, 2] = faces[rep, 0]
    return clip, faces, kind


def compare_fragments(
    face_id: torch.Tensor,
    bary: torch.Tensor,
    depth: torch.Tensor,
    clip_pos: torch.Tensor,
    faces: torch.Tensor,
    ref: RefFragments,
) -> dict:
    """Compare engine fragments (face_id (B,H,W), bary (B,H,W,3), depth (B,H,W)) with the
    reference computed from the SAME clip positions (B,V,4).

    Each disagreeing pixel is checked for an explanation: its centre is within EDGE_TOL_PX of a
    boundary of either face, or both faces are there (within the tolerance) and their depths
    differ by < DEPTH_TIE_TOL. Returns counts, the agreeing fraction, worst depth / barycentric
    errors where the face agrees, and up to 20 unexplained pixels as
    (b, row, col, ref_face, engine_face, distance_px).
    """
    bsz, h, w = ref.face_id.shape
    face_id, bary, depth = (t.detach().cpu() for t in (face_id, bary, depth))
    clip64 = clip_pos.detach().to(torch.float64).cpu()
    faces = faces.cpu()
    pix = pixel_centres(h, w)
    agree = face_id == ref.face_id
    hit = agree & (ref.face_id >= 0)
    depth_err = (depth.double() - ref.depth)[hit].abs()
    bary_err = (bary.double() - ref.bary)[hit].abs().amax(-1)
    b_idx, i_idx, j_idx = hit.nonzero().unbind(-1)
    cond_b = torch.zeros_like(depth_err)
    cond_z = torch.zeros_like(depth_err)
    for b in range(bsz):
        m = b_idx == b
        if m.any():
            cond_b[m], cond_z[m] = rounding_condition(
                clip64[b], faces, ref.face_id[b, i_idx[m], j_idx[m]], pix[i_idx[m] * w + j_idx[m]]
            )
    unexplained = []
    n_edge = n_tie = 0
    for b, i, j in (~agree).nonzero().tolist():
        p = pix[i * w + j][None]
        fa, fb = int(ref.face_id[b, i, j]), int(face_id[b, i, j])
        dist, zs = [], []
        for f in (fa, fb):
            if f >= 0:
                ft = torch.tensor([f])
                dist.append(float(boundary_distance_px(clip64[b], faces, ft, p, (h, w))[0]))
                zs.append(float(face_bary_depth(clip64[b], faces, ft, p)[1][0]))
        if min(dist) < EDGE_TOL_PX:
            n_edge += 1
        elif len(zs) == 2 and abs(zs[0] - zs[1]) < DEPTH_TIE_TOL:
            n_tie += 1
        elif len(unexplained) < 20:
            unexplained.append((b, i, j, fa, fb, min(dist)))
        else:
            unexplained.append(None)
    n = face_id.numel()
    return {
        "pixels": n,
        "covered": int((ref.face_id >= 0).sum()),
        "disagree": int((~agree).sum()),
        "near_edge": n_edge,
        "depth_tie": n_tie,
        "unexplained": len(unexplained),
        "unexplained_list": [u for u in unexplained if u is not None],
        "agree_frac": float(agree.double().mean()),
        "max_depth_err": float(depth_err.max()) if depth_err.numel() else 0.0,
        "max_bary_err": float(bary_err.max()) if bary_err.numel() else 0.0,
        "depth_err": depth_err,
        "bary_err": bary_err,
        "cond_depth": cond_z,
        "cond_bary": cond_b,
    }


def error_ratios(stats: dict, dtype: torch.dtype, depth_tol: float, bary_tol: float) -> dict:
    """Worst error / allowed error over the agreeing pixels of ``compare_fragments`` stats, with
    allowed = max(tol, ROUNDOFF_FACTOR * u * cond): the fixed tolerance for well-conditioned
    pixels, the float rounding bound for slivers and other ill-conditioned ones. Also counts
    the pixels whose error exceeds the fixed tolerance (all of them ill-conditioned if the
    ratios are <= 1)."""
    u = UNIT_ROUNDOFF[dtype]
    allow_z = (ROUNDOFF_FACTOR * u * stats["cond_depth"]).clamp_min(depth_tol)
    allow_b = (ROUNDOFF_FACTOR * u * stats["cond_bary"]).clamp_min(bary_tol)
    nz = stats["depth_err"].numel()
    return {
        "depth_ratio": float((stats["depth_err"] / allow_z).max()) if nz else 0.0,
        "bary_ratio": float((stats["bary_err"] / allow_b).max()) if nz else 0.0,
        "depth_over_tol": int((stats["depth_err"] > depth_tol).sum()),
        "bary_over_tol": int((stats["bary_err"] > bary_tol).sum()),
    }
