"""Analytic antialiasing (torchraster.antialias): gradients of coverage against central
differences of an independent float64 supersampled reference, translation moments, float64
gradcheck, the silhouette rule (internal edges never blend) and hostile geometry."""

from __future__ import annotations

import math

import pytest
import torch
import trimesh

import torchraster as tr
from torchraster.raster import antialias_topology

# ---------------------------------------------------------------------------------------------
# Independent reference: box-filtered coverage from s x s point samples per pixel (float64,
# point-in-triangle with NDC depth test; no torchraster code). Scenes keep w > 0.
# ---------------------------------------------------------------------------------------------


def supersample(clip: torch.Tensor, faces: torch.Tensor, vertex_color: torch.Tensor,
                resolution: tuple[int, int], s: int = 64) -> torch.Tensor:
    """(C, H, W) mean over s x s samples per pixel of the perspective-correct interpolated
    ``vertex_color`` (V, C) of the nearest face, 0 where no face covers a sample.
    ``clip`` (V, 4) with w > 0."""
    h, w = resolution
    hs, ws = h * s, w * s
    clip = clip.detach().to(torch.float64)
    vertex_color = vertex_color.detach().to(torch.float64)
    px = (((clip[:, 0] / clip[:, 3]) + 1) * 0.5 * ws - 0.5).tolist()  # sample units
    py = ((1 - clip[:, 1] / clip[:, 3]) * 0.5 * hs - 0.5).tolist()  # centres at integers
    pz = (clip[:, 2] / clip[:, 3]).tolist()
    inv_w = (1 / clip[:, 3]).tolist()
    zbuf = torch.full((hs, ws), math.inf, dtype=torch.float64)
    img = torch.zeros(vertex_color.shape[1], hs, ws, dtype=torch.float64)
    cols = torch.arange(ws, dtype=torch.float64)
    rows = torch.arange(hs, dtype=torch.float64)[:, None]
    for tri in faces.tolist():
        xs, ys = [px[i] for i in tri], [py[i] for i in tri]
        c0, c1 = max(0, math.floor(min(xs))), min(ws - 1, math.ceil(max(xs)))
        r0, r1 = max(0, math.floor(min(ys))), min(hs - 1, math.ceil(max(ys)))
        area = (xs[1] - xs[0]) * (ys[2] - ys[0]) - (xs[2] - xs[0]) * (ys[1] - ys[0])
        if c0 > c1 or r0 > r1 or area == 0:
            continue
        xx, yy = cols[c0:c1 + 1], rows[r0:r1 + 1]
        # screen-space barycentrics (affine), then perspective-correct ones (divide by w)
        lam = [((xs[k] - xs[j]) / area) * (yy - ys[j]) - ((ys[k] - ys[j]) / area) * (xx - xs[j])
               for j, k in ((1, 2), (2, 0), (0, 1))]
        inside = (lam[0] >= 0) & (lam[1] >= 0) & (lam[2] >= 0)
        z = lam[0] * pz[tri[0]] + lam[1] * pz[tri[1]] + lam[2] * pz[tri[2]]  # affine in screen
        zb = zbuf[r0:r1 + 1, c0:c1 + 1]
        win = inside & (z < zb)
        if not bool(win.any()):
            continue
        zb[win] = z[win]
        persp = torch.stack([lam[i][win] * inv_w[tri[i]] for i in range(3)])  # (3, n)
        col = vertex_color[tri].T @ (persp / persp.sum(0))  # (C, n)
        img[:, r0:r1 + 1, c0:c1 + 1][:, win] = col
    return img.reshape(-1, h, s, w, s).mean((2, 4))


def flat_image(frags: tr.Fragments, face_color: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) colour of the visible face (``face_color`` (F, C)), 0 on the background."""
    table = torch.cat([torch.zeros_like(face_color[:1]), face_color])
    return table[frags.face_id + 1].permute(0, 3, 1, 2)


def weights(c: int, h: int, w: int) -> torch.Tensor:
    """A smooth, non-constant loss weighting (C, H, W)."""
    i = torch.arange(h, dtype=torch.float64)[:, None]
    j = torch.arange(w, dtype=torch.float64)[None]
    return torch.stack([1 + 0.5 * torch.sin(0.37 * i + 1.3 * k) * torch.cos(0.29 * j - 0.4 * k)
                        for k in range(c)])


def aa_loss(clip, faces, vertex_color, res, wgt):
    frags = tr.rasterize(clip, faces, res)
    out = tr.antialias(tr.interpolate(vertex_color, frags, faces), frags, clip, faces)
    return (out[0] * wgt).sum()


def ref_loss(clip, faces, vertex_color, res, wgt, s):
    return float((supersample(clip[0], faces, vertex_color, res, s) * wgt).sum())


def directional_pairs(clip, faces, vertex_color, res, directions, step, s=64):
    """(g . v, central difference of the reference along v) per direction v ((1, V, 4)
    clip-space displacements; ``step`` in the units of v)."""
    wgt = weights(vertex_color.shape[1], *res)
    x = clip.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(aa_loss(x, faces, vertex_color, res, wgt), x)
    out = []
    for v in directions:
        fd = (ref_loss(clip + step * v, faces, vertex_color, res, wgt, s)
              - ref_loss(clip - step * v, faces, vertex_color, res, wgt, s)) / (2 * step)
        out.append((float((grad * v).sum()), fd))
    return out


def relative_error(pairs) -> float:
    """|g - g_ref| / |g_ref| over the stacked directional derivatives."""
    got = torch.tensor([p[0] for p in pairs])
    ref = torch.tensor([p[1] for p in pairs])
    return float((got - ref).norm() / ref.norm())


def smooth_directions(clip: torch.Tensor, n: int, gen: torch.Generator) -> list:
    """Screen-space deformations of the whole scene, one NDC pixel-scale-free field each:
    x and y translations, a rotation about the centre, and ``n`` random smooth fields
    (affine + quadratic in the vertices' NDC position), as (1, V, 4) clip displacements."""
    w = clip[0, :, 3:]
    p = clip[0, :, :2] / w
    fields = [torch.tensor([1.0, 0.0]).expand_as(p), torch.tensor([0.0, 1.0]).expand_as(p),
              torch.stack([-p[:, 1], p[:, 0]], 1)]
    for _ in range(n):
        a = torch.randn(2, 2, generator=gen, dtype=torch.float64)
        b = torch.randn(2, generator=gen, dtype=torch.float64)
        q = torch.randn(2, 3, generator=gen, dtype=torch.float64)
        quad = torch.stack([p[:, 0] ** 2, p[:, 0] * p[:, 1], p[:, 1] ** 2], 1)
        fields.append(p @ a.T + b + quad @ q.T)
    out = []
    for f in fields:
        v = torch.zeros_like(clip)
        v[0, :, :2] = f.to(torch.float64) * w  # move the projection by f (NDC)
        out.append(v)
    return out


def ndc_clip(xy: torch.Tensor, z: torch.Tensor | float = 0.0) -> torch.Tensor:
    """(1, V, 4) float64 clip positions with w = 1 from NDC (V, 2)."""
    xy = xy.to(torch.float64)
    z = torch.as_tensor(z, dtype=torch.float64).expand(xy.shape[0])
    return torch.cat([xy, z[:, None], torch.ones_like(xy[:, :1])], 1)[None]


def disc(n: int, cx: float, cy: float, r: float, z: float = 0.0, phase: float = 0.1):
    """Polygon fan: clip (1, n + 1, 4), faces (n, 3) counter-clockwise, centre vertex 0."""
    a = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n) + phase
    xy = torch.cat([torch.tensor([[cx, cy]], dtype=torch.float64),
                    torch.stack([cx + r * a.cos(), cy + r * a.sin()], 1)])
    k = torch.arange(n)
    faces = torch.stack([torch.zeros_like(k), 1 + k, 1 + (k + 1) % n], 1)
    return ndc_clip(xy, z), faces


def sphere(subdivisions: int = 2, distance: float = 3.2):
    """An icosphere seen by a perspective camera: clip (1, V, 4) float64, faces (F, 3)."""
    ico = trimesh.creation.icosphere(subdivisions=subdivisions)
    verts = torch.tensor(ico.vertices, dtype=torch.float64)
    faces = torch.tensor(ico.faces, dtype=torch.int64)
    view = tr.camera.look_at([0.3, 0.2, distance], [0.05, -0.03, 0.0]).to(torch.float64)
    proj = tr.camera.perspective(40.0, 1.0, 0.1).to(torch.float64)
    clip = tr.camera.transform_points(verts, proj @ view)
    return clip.reshape(1, -1, 4), faces


# ---------------------------------------------------------------------------------------------
# 1. Gradients against central differences of the supersampled reference
# ---------------------------------------------------------------------------------------------
#
# The analytic gradient samples each silhouette edge once per pixel row (or column) it
# crosses, so the gradient of one vertex of a 2-px edge is only sampled once or twice: it is
# compared here on smooth deformations of whole shapes (translations, rotation, random
# affine + quadratic fields) and per vertex only on a large triangle.

FD_STEP_PX = 0.25  # screen-space step of the central differences (64 samples per pixel)


def _px(res: tuple[int, int]) -> float:
    return 2.0 / res[0]  # NDC per pixel (square images)


def _check(name, pairs, bound):
    err = relative_error(pairs)
    print(f"{name}: relative error {err:.2%}; (analytic, reference) = "
          + ", ".join(f"({g:.4g}, {r:.4g})" for g, r in pairs))
    assert err < bound


@pytest.mark.parametrize("channels", ["alpha", "color"])
def test_single_triangle_per_vertex_gradient_matches_supersampled_fd(channels: str) -> None:
    res = (32, 32)
    clip = ndc_clip(torch.tensor([[-0.62, -0.49], [0.71, -0.27], [0.08, 0.77]]))
    clip = clip * torch.tensor([1.0, 1.3, 0.8], dtype=torch.float64)[None, :, None]
    faces = torch.tensor([[0, 1, 2]])
    if channels == "alpha":
        color = torch.ones(3, 1, dtype=torch.float64)
    else:
        color = torch.tensor([[1.0, 0.2, 0.1], [0.1, 1.0, 0.3], [0.2, 0.3, 1.0]],
                             dtype=torch.float64)
    dirs = []
    for v in range(3):
        for c in range(2):
            d = torch.zeros_like(clip)
            d[0, v, c] = clip[0, v, 3]
            dirs.append(d)
    pairs = directional_pairs(clip, faces, color, res, dirs, 2 * FD_STEP_PX * _px(res), s=32)
    _check(f"triangle per vertex ({channels})", pairs, 0.10)


def test_disc_gradient_matches_supersampled_fd() -> None:
    res = (24, 24)
    clip, faces = disc(24, 0.04, -0.03, 0.63)
    color = torch.tensor([[1.0, 0.3, 0.6]], dtype=torch.float64).expand(clip.shape[1], 3)
    dirs = smooth_directions(clip, 3, torch.Generator().manual_seed(1))
    pairs = directional_pairs(clip, faces, color, res, dirs, FD_STEP_PX * _px(res))
    _check("disc", pairs, 0.10)


@pytest.mark.parametrize("channels", ["alpha", "color"])
def test_sphere_silhouette_gradient_matches_supersampled_fd(channels: str) -> None:
    res = (24, 24)
    clip, faces = sphere()
    if channels == "alpha":
        color = torch.ones(clip.shape[1], 1, dtype=torch.float64)
    else:  # a colour per vertex, interpolated: gradients also flow through the barycentrics
        gen = torch.Generator().manual_seed(3)
        color = torch.rand(clip.shape[1], 3, generator=gen, dtype=torch.float64)
    dirs = smooth_directions(clip, 3, torch.Generator().manual_seed(2))
    pairs = directional_pairs(clip, faces, color, res, dirs, FD_STEP_PX * _px(res), s=32)
    _check(f"sphere ({channels})", pairs, 0.10)


def test_occlusion_boundary_gradient_matches_supersampled_fd() -> None:
    """A disc in front of a larger triangle, different colours: gradients at the
    disc/triangle occlusion boundary and at both silhouettes against the background."""
    res = (48, 48)
    front, f_faces = disc(20, 0.18, 0.1, 0.45, z=0.2)
    back = ndc_clip(torch.tensor([[-0.8, -0.7], [0.75, -0.45], [-0.2, 0.8]]), z=0.5)
    clip = torch.cat([front, back], 1)
    faces = torch.cat([f_faces, torch.tensor([[0, 1, 2]]) + front.shape[1]])
    color = torch.cat([torch.tensor([[0.9, 0.2, 0.1]]).expand(front.shape[1], 3),
                       torch.tensor([[0.1, 0.5, 1.0], [0.2, 0.9, 0.4], [0.0, 0.3, 0.8]])])
    color = color.to(torch.float64)
    dirs = smooth_directions(clip, 3, torch.Generator().manual_seed(4))
    for c in range(2):  # move the occluder only: the occlusion boundary moves over the back
        only_front = torch.zeros_like(clip)
        only_front[0, :front.shape[1], c] = 1.0
        dirs.append(only_front)
    pairs = directional_pairs(clip, faces, color, res, dirs, FD_STEP_PX * _px(res), s=32)
    _check("occlusion", pairs, 0.10)


# ---------------------------------------------------------------------------------------------
# 2. Translation: d/dx sum(alpha * x) = area
# ---------------------------------------------------------------------------------------------


def _translated_moment(clip, faces, res, axis):
    """d/dshift of sum(alpha * coordinate) for a screen-space shift along ``axis`` (0: x
    right, 1: y down), the coordinate (column or row) measured from the image centre."""
    h, w = res
    shift = torch.zeros(2, dtype=torch.float64, requires_grad=True)
    moved = torch.cat([clip[..., :1] + shift[0] * (2.0 / w) * clip[..., 3:],
                       clip[..., 1:2] - shift[1] * (2.0 / h) * clip[..., 3:], clip[..., 2:]], -1)
    frags = tr.rasterize(moved, faces, res)
    alpha = tr.antialias(frags.mask.to(torch.float64), frags, moved, faces)[0, 0]
    coord = torch.arange(res[1 - axis], dtype=torch.float64) - (res[1 - axis] - 1) / 2
    coord = coord[None] if axis == 0 else coord[:, None]
    (g,) = torch.autograd.grad((alpha * coord).sum(), shift)
    return float(g[axis])


def _polygon_area_px(clip, faces, res):
    h, w = res
    p = clip[0, :, :2] / clip[0, :, 3:]
    x, y = (p[:, 0] + 1) * w / 2, (1 - p[:, 1]) * h / 2
    a = faces[:, 0], faces[:, 1], faces[:, 2]
    cross = (x[a[1]] - x[a[0]]) * (y[a[2]] - y[a[0]]) - (x[a[2]] - x[a[0]]) * (y[a[1]] - y[a[0]])
    return float(cross.abs().sum() / 2)


def _tilted_disc():
    """A 3-D disc tilted 55 degrees away from a perspective camera: w varies over it."""
    clip, faces = disc(48, 0.0, 0.0, 1.0)
    a = math.radians(55)
    x, y = clip[0, :, 0], clip[0, :, 1]
    pts = torch.stack([x + 0.1, y * math.cos(a) - 0.2, y * math.sin(a)], 1)
    view = tr.camera.look_at([0.0, 0.0, 2.6], [0.0, 0.0, 0.0]).to(torch.float64)
    proj = tr.camera.perspective(50.0, 1.0, 0.1).to(torch.float64)
    return tr.camera.transform_points(pts, proj @ view).reshape(1, -1, 4), faces


@pytest.mark.parametrize("shape", ["disc", "triangle", "square45", "tilted_disc"])
@pytest.mark.parametrize("axis", [0, 1])
def test_translation_moment_equals_area(shape: str, axis: int) -> None:
    """For a shape moved by d pixels, d/dd sum(alpha * x) = its area in pixels. The
    analytic gradient samples every straight edge once per row or column (the orientation
    rule), so this holds up to the sampling at the vertices (a fraction of a pixel each)."""
    res = (256, 256)
    if shape == "disc":
        clip, faces = disc(48, 0.03, -0.05, 0.61)
    elif shape == "triangle":
        clip = ndc_clip(torch.tensor([[-0.72, -0.6], [0.8, -0.31], [0.05, 0.74]]))
        faces = torch.tensor([[0, 1, 2]])
    elif shape == "square45":  # edges at exactly 45 degrees (the orientation tie)
        clip, faces = disc(4, 0.01, 0.02, 0.7, phase=0.0)
    else:
        clip, faces = _tilted_disc()
    area = _polygon_area_px(clip, faces, res)
    got = _translated_moment(clip, faces, res, axis)
    print(f"{shape} axis {axis}: d/dx sum(alpha x) = {got:.2f}, area {area:.2f}, "
          f"error {got / area - 1:+.3%}")
    assert got == pytest.approx(area, rel=0.01)


def test_translation_moment_of_a_finely_tessellated_sphere() -> None:
    """Triangles much smaller than a pixel (icosphere of 20k faces at 64^2): a pixel
    segment crosses several faces before it reaches the silhouette (the walk), and the
    moment still gives the silhouette's area (front faces tile it exactly once)."""
    ico = trimesh.creation.icosphere(subdivisions=5)
    verts = torch.tensor(ico.vertices, dtype=torch.float64)
    faces = torch.tensor(ico.faces, dtype=torch.int64)
    view = tr.camera.look_at([0.2, 0.1, 3.0], [0.0, 0.0, 0.0]).to(torch.float64)
    clip = tr.camera.transform_points(
        verts, tr.camera.perspective(45.0, 1.0, 0.1).to(torch.float64) @ view).reshape(1, -1, 4)
    res = (64, 64)
    p = clip[0, :, :2] / clip[0, :, 3:]
    x, y = (p[:, 0] + 1) * res[1] / 2, (1 - p[:, 1]) * res[0] / 2
    f0, f1, f2 = faces.unbind(1)
    cross = (x[f1] - x[f0]) * (y[f2] - y[f0]) - (x[f2] - x[f0]) * (y[f1] - y[f0])
    area = float(-cross.clamp_max(0).sum() / 2)  # y down: front faces have cross < 0
    for axis in (0, 1):
        got = _translated_moment(clip, faces, res, axis)
        print(f"fine sphere axis {axis}: {got:.2f} vs area {area:.2f} ({got / area - 1:+.3%})")
        assert got == pytest.approx(area, rel=0.01)


@pytest.mark.slow
def test_spot_gradient_matches_supersampled_fd() -> None:
    """Spot (5,856 faces, concave, self-occluding: legs, ears, horns) at 96^2 against the
    supersampled reference, smooth deformations of the whole mesh (about a minute). Where
    two silhouettes fall between two pixel centres (horn tips, a fold in front of a farther
    part of the body), only the faces visible at the centres are known and the analytic
    gradient misses the rest: 16 % error at 48^2, 7 % at 96^2."""
    mesh = tr.load_spot()
    verts, faces = mesh.positions.to(torch.float64), mesh.faces
    view = tr.camera.look_at([2.0, 0.6, 1.6], [0.0, 0.05, 0.0]).to(torch.float64)
    clip = tr.camera.transform_points(
        verts, tr.camera.perspective(40.0, 1.0, 0.1).to(torch.float64) @ view).reshape(1, -1, 4)
    res = (96, 96)
    dirs = smooth_directions(clip, 2, torch.Generator().manual_seed(6))
    smooth = 0.5 + 0.4 * torch.sin(3.0 * verts + torch.tensor([0.0, 1.0, 2.0]))  # no aliasing
    for name, col in (("alpha", torch.ones(verts.shape[0], 1, dtype=torch.float64)),
                      ("colour", smooth)):
        pairs = directional_pairs(clip, faces, col, res, dirs, FD_STEP_PX * _px(res), s=24)
        _check(f"spot ({name})", pairs, 0.10)


# ---------------------------------------------------------------------------------------------
# 3. gradcheck (float64, configurations away from discontinuities)
# ---------------------------------------------------------------------------------------------


def _gradcheck_scene():
    """8x8, a coloured triangle partly in front of another one, on the background."""
    clip = torch.tensor([[
        [-0.71, -0.63, 0.1, 1.0], [0.62, -0.41, 0.1, 1.1], [-0.13, 0.74, 0.2, 0.9],
        [-0.27, -0.88, 0.6, 1.3], [0.93, 0.14, 0.5, 1.2], [0.34, 0.93, 0.4, 1.0],
    ]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    colors = torch.tensor([[1.0, 0.2], [0.3, 0.9], [0.6, 0.5], [0.1, 0.4], [0.8, 0.7],
                           [0.2, 0.1]], dtype=torch.float64)
    return clip, faces, colors


def test_gradcheck_clip_pos_and_color() -> None:
    clip, faces, colors = _gradcheck_scene()
    res = (8, 8)
    frags = tr.rasterize(clip, faces, res)
    assert set(frags.face_id.unique().tolist()) == {-1, 0, 1}

    def f(c, col):
        fr = tr.rasterize(c, faces, res)
        img = tr.interpolate(col, fr, faces)
        img = torch.cat([img, fr.mask], 1)
        return tr.antialias(img, fr, c, faces)

    out = f(clip, colors)
    changed = (out - torch.cat([tr.interpolate(colors, frags, faces), frags.mask], 1)).abs()
    assert int((changed > 0).sum()) > 10  # some pixels blend
    assert torch.autograd.gradcheck(f, (clip.clone().requires_grad_(True),
                                        colors.clone().requires_grad_(True)),
                                    eps=1e-7, atol=1e-6)


def test_gradcheck_near_plane_crosser() -> None:
    """A triangle with a vertex behind the camera (w < 0): its projected edges pass
    through infinity; the crossing is still a smooth function of the clip positions."""
    clip = torch.tensor([[[-0.7, -0.6, 0.1, 1.0], [0.5, -0.45, 0.2, 1.0],
                          [0.13, 0.41, 0.7, -0.4]]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2]])
    res = (8, 8)

    def f(c):
        fr = tr.rasterize(c, faces, res)
        return tr.antialias(fr.mask, fr, c, faces)

    assert int((tr.rasterize(clip, faces, res).face_id >= 0).sum()) > 4
    assert torch.autograd.gradcheck(f, (clip.clone().requires_grad_(True),), eps=1e-7,
                                    atol=1e-6)


# ---------------------------------------------------------------------------------------------
# Silhouette rule, contract, batching
# ---------------------------------------------------------------------------------------------


def test_topology_pairs_shared_edges() -> None:
    faces = torch.tensor([[0, 1, 2], [2, 1, 3], [3, 1, 4], [5, 6, 7]])
    opp = antialias_topology(faces)
    assert opp.tolist() == [[-1, 3, -1], [1, 6, -1], [4, -1, -1], [-1, -1, -1]]
    # non-manifold: three faces on edge 0-1
    opp = antialias_topology(torch.tensor([[0, 1, 2], [1, 0, 3], [0, 1, 4]]))
    assert bool((opp[:, 0] == -1).all())


def test_internal_edges_do_not_blend() -> None:
    """A closed sphere with a random colour per face: every pixel whose four neighbours
    all show the sphere keeps its colour exactly; silhouette pixels change."""
    clip, faces = sphere()
    res = (48, 48)
    frags = tr.rasterize(clip, faces, res)
    color = flat_image(frags, torch.rand(faces.shape[0], 3, dtype=torch.float64))
    out = tr.antialias(color, frags, clip, faces)
    cov = frags.face_id[0] >= 0
    interior = cov.clone()
    interior[1:] &= cov[:-1]
    interior[:-1] &= cov[1:]
    interior[:, 1:] &= cov[:, :-1]
    interior[:, :-1] &= cov[:, 1:]
    interior[0], interior[-1], interior[:, 0], interior[:, -1] = False, False, False, False
    steps = (frags.face_id[0, 1:] != frags.face_id[0, :-1]) & cov[1:] & cov[:-1]
    assert int(steps.sum()) > 50  # plenty of internal colour steps
    assert torch.equal(out[0][:, interior], color[0][:, interior])
    assert int(((out - color).abs().sum(1)[0] > 0).sum()) > 40  # the silhouette blends


def test_quad_diagonal_blends_only_when_folded() -> None:
    """Two triangles sharing the diagonal 0-2 of a quad: flat (either winding of the second
    triangle: silhouettes are geometric, not read from the winding) the diagonal never
    blends; folded (the second triangle turned over onto the first's side, behind it) the
    diagonal is a silhouette with background beyond, and blends."""
    res = (16, 16)
    corners = torch.tensor([[-0.7, -0.65], [0.68, -0.7], [0.72, 0.66], [-0.69, 0.7]])
    folded = corners.clone()
    folded[3] = torch.tensor([0.4, -0.3])  # same side of the diagonal as vertex 1
    z = torch.tensor([0.0, 0.0, 0.0, 0.5])  # ... and behind the first triangle
    ys, xs = torch.meshgrid(1 - 2 * (torch.arange(16) + 0.5) / 16,
                            2 * (torch.arange(16) + 0.5) / 16 - 1, indexing="ij")
    inner = (xs.abs() < 0.45) & (ys.abs() < 0.45)  # pixel centres well inside the quad
    two = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    cases = (("flat", corners, [[0, 1, 2], [0, 2, 3]], False),
             ("flat, inconsistent winding", corners, [[0, 1, 2], [2, 0, 3]], False),
             ("folded", folded, [[0, 1, 2], [2, 0, 3]], True))
    for name, xy, faces, blends in cases:
        clip = ndc_clip(xy, z)
        faces = torch.tensor(faces)
        frags = tr.rasterize(clip, faces, res)
        img = flat_image(frags, two)
        out = tr.antialias(img, frags, clip, faces)
        changed = (out - img).abs().sum(1)[0] > 0
        assert bool((changed & inner).any()) == blends, name


def test_output_contract_on_a_vertical_edge() -> None:
    """A half-plane x < e: every horizontal pair across e blends by exactly |t - 1/2|
    (a vertical edge belongs to the horizontal pairs alone: share 1)."""
    res = (4, 8)
    # pixel centres at j + 0.5: an edge at 4.3 px leaves pixel 3 at t = 0.8, so pixel 4
    # takes 0.3 of it; one at 3.8 px leaves pixel 3 at t = 0.3, which keeps 1 - 0.2
    for e_px, target, value in ((4.3, 4, 0.3), (3.8, 3, 0.8)):
        e = 2 * e_px / res[1] - 1
        clip = ndc_clip(torch.tensor([[-3.0, -3.0], [e, -3.0], [e, 3.0], [-3.0, 3.0]]))
        faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
        frags = tr.rasterize(clip, faces, res)
        out = tr.antialias(frags.mask.double(), frags, clip, faces)[0, 0]
        expect = (torch.arange(res[1]) + 0.5 < e_px).double()
        expect[target] = value
        assert torch.allclose(out, expect.expand(res[0], -1), atol=1e-12), out


def test_batch_broadcast_and_memory_budget_invariance() -> None:
    c1, faces = sphere()
    c2, _ = sphere(distance=2.7)
    clip = torch.cat([c1, c2]).float()
    res = (64, 64)
    frags = tr.rasterize(clip, faces, res)
    color = torch.rand(2, 3, *res)
    out = tr.antialias(color, frags, clip, faces)
    pairs = int((frags.face_id[:, :, 1:] != frags.face_id[:, :, :-1]).sum())
    assert pairs > 2 * 256  # memory_budget=1 walks chunks of the smallest size, 256 pairs
    small = tr.antialias(color, frags, clip, faces, memory_budget=1)
    assert torch.equal(out, small)
    for i in range(2):
        fi = tr.rasterize(clip[i:i + 1], faces, res)
        assert torch.equal(tr.antialias(color[i:i + 1], fi, clip[i:i + 1], faces), out[i:i + 1])
    # a shared batch of 1 positions
    frags2 = tr.rasterize(c1.float().expand(2, -1, -1), faces, res)
    shared = tr.antialias(color, frags2, c1.float(), faces)
    assert torch.equal(shared[1], tr.antialias(color, frags2, c1.float().expand(2, -1, -1),
                                               faces)[1])
    topo = antialias_topology(faces)
    assert torch.equal(tr.antialias(color, frags, clip, faces, topology=topo), out)


def test_alpha_stays_in_unit_interval_and_approximates_coverage(device, dtype) -> None:
    gen = torch.Generator().manual_seed(5)
    n = 30
    xy = torch.rand(n, 3, 2, generator=gen, dtype=torch.float64) * 1.6 - 0.8
    xy = xy * torch.rand(n, 1, 1, generator=gen, dtype=torch.float64) * 0.6 \
        + torch.rand(n, 1, 2, generator=gen, dtype=torch.float64) * 1.4 - 0.7
    clip = ndc_clip(xy.reshape(-1, 2), torch.rand(3 * n, generator=gen) * 1.8 - 0.9)
    faces = torch.arange(3 * n).view(n, 3)
    res = (32, 32)
    ref = supersample(clip[0], faces, torch.ones(3 * n, 1, dtype=torch.float64), res, s=16)
    clip_d = clip.to(device=device, dtype=dtype)
    frags = tr.rasterize(clip_d, faces.to(device), res)
    alpha = tr.antialias(frags.mask, frags, clip_d, faces.to(device))
    assert alpha.dtype == dtype and alpha.device.type == torch.device(device).type
    assert float(alpha.min()) >= 0 and float(alpha.max()) <= 1
    err_aa = float((alpha[0].cpu().double() - ref).abs().mean())
    err_mask = float((frags.mask[0].cpu().double() - ref).abs().mean())
    assert err_aa < 0.6 * err_mask, (err_aa, err_mask)


# ---------------------------------------------------------------------------------------------
# 4. Stress: finite values and gradients on hostile geometry
# ---------------------------------------------------------------------------------------------


def _stress_scenes():
    res = 8
    c = lambda i: 2 * (i + 0.5) / res - 1  # noqa: E731 - NDC of pixel centre i
    scenes = {
        # edges through pixel centres, along rows, columns and a diagonal
        "through_centres": ndc_clip(torch.tensor([[c(1), c(6)], [c(6), c(6)], [c(1), c(1)]])),
        # edges on pixel boundaries (x, y = k * 2 / res - 1)
        "on_boundaries": ndc_clip(torch.tensor([[-0.5, -0.5], [0.75, -0.5], [-0.5, 0.75]])),
        # a sliver: 1e-7 px wide and a long thin one
        "sliver": ndc_clip(torch.tensor([[c(0), c(0)], [c(7), c(7)], [c(7) + 1e-7, c(7)]])),
        "thin": ndc_clip(torch.tensor([[-0.95, -0.3], [0.95, -0.28], [0.95, -0.05]])),
        # vertex exactly at w = 0, vertex behind the camera, vertex beyond the near plane
        "w_zero": torch.tensor([[[-0.6, -0.5, 0.0, 1.0], [0.6, -0.4, 0.0, 1.0],
                                 [0.1, 0.3, 0.2, 0.0]]], dtype=torch.float64),
        "behind": torch.tensor([[[-0.6, -0.5, 0.0, 1.0], [0.6, -0.4, 0.0, 1.0],
                                 [0.1, 0.3, 0.9, -1e-9]]], dtype=torch.float64),
        "near_cut": torch.tensor([[[-0.6, -0.5, 0.5, 1.0], [0.6, -0.4, 0.5, 1.0],
                                   [0.1, 0.5, -3.0, 0.5]]], dtype=torch.float64),
        "huge": ndc_clip(torch.tensor([[-1e6, -1e6], [1e6, -2e6], [0.2, 3e6]])),
        "degenerate_point": ndc_clip(torch.tensor([[0.1, 0.1], [0.1, 0.1], [0.1, 0.1]])),
    }
    return scenes, (res, res)


@pytest.mark.parametrize("name", list(_stress_scenes()[0]))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_stress_finite_values_and_gradients(name: str, dtype: torch.dtype) -> None:
    scenes, res = _stress_scenes()
    clip = scenes[name].to(dtype).requires_grad_(True)
    faces = torch.tensor([[0, 1, 2]])
    frags = tr.rasterize(clip, faces, res)
    color = torch.rand(1, 3, *res, dtype=dtype, requires_grad=True)
    img = torch.cat([color * frags.mask, frags.mask], 1)
    out = tr.antialias(img, frags, clip, faces)
    assert bool(torch.isfinite(out).all())
    print(name, dtype, "covered", int((frags.face_id >= 0).sum()), "changed",
          int(((out - img).abs().sum(1) > 0).sum()))
    assert float(out[:, 3].detach().min()) >= 0 and float(out[:, 3].detach().max()) <= 1
    (out * torch.rand_like(out)).sum().backward()
    assert bool(torch.isfinite(color.grad).all())
    if clip.grad is not None:  # None: nothing covered, the output does not depend on clip
        assert bool(torch.isfinite(clip.grad).all())


def test_stress_mesh_with_degenerate_and_duplicate_faces() -> None:
    clip, faces = disc(12, 0.0, 0.0, 0.7)
    faces = torch.cat([faces, torch.tensor([[0, 0, 1], [1, 2, 3], [1, 2, 3]])])
    clip = clip.float().requires_grad_(True)
    frags = tr.rasterize(clip, faces, (16, 16))
    out = tr.antialias(frags.mask, frags, clip, faces)
    out.sum().backward()
    assert bool(torch.isfinite(out).all()) and bool(torch.isfinite(clip.grad).all())


def test_empty_frame_and_errors() -> None:
    clip = ndc_clip(torch.tensor([[5.0, 5.0], [6.0, 5.0], [5.0, 6.0]])).float()
    faces = torch.tensor([[0, 1, 2]])
    frags = tr.rasterize(clip, faces, (4, 4))
    color = torch.rand(1, 2, 4, 4)
    assert torch.equal(tr.antialias(color, frags, clip, faces), color)
    with pytest.raises(ValueError, match="color"):
        tr.antialias(color[:, :, :3], frags, clip, faces)
    with pytest.raises(ValueError, match="clip_pos"):
        tr.antialias(color, frags, clip.expand(3, -1, -1), faces)
    with pytest.raises(TypeError, match="frags"):
        tr.antialias(color, None, clip, faces)


def test_half_precision_color() -> None:
    clip, faces = disc(12, 0.0, 0.0, 0.7)
    frags = tr.rasterize(clip.float(), faces, (16, 16))
    out = tr.antialias(frags.mask.half(), frags, clip.float(), faces)
    assert out.dtype == torch.float16 and bool(torch.isfinite(out).all())
