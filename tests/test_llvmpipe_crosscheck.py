"""Mesa llvmpipe baseline (torchraster/testing/llvmpipe.py): checked against a brute-force
numpy reference, then cross-checked against torchraster.rasterize / interpolate on a real mesh.

Skipped cleanly when moderngl or an EGL llvmpipe context is not available.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from torchraster.testing import llvmpipe

pytestmark = pytest.mark.skipif(
    not llvmpipe.available(), reason=f"llvmpipe unavailable: {llvmpipe.unavailable_reason()}"
)

# Brute-force reference margins: pixels this close to a coverage/clip boundary, or where the
# two nearest surfaces are this close in NDC depth, are legitimately ambiguous between two
# rasterizers (GL snaps vertices to 1/256 px; llvmpipe interpolates in float32), so they are
# excluded from the exact comparison. Perspective-correct barycentric units.
EDGE_TOL = 5e-3
DEPTH_TOL = 1e-4
ATTR_TOL = 1e-4  # llvmpipe's float32 interpolation vs float64 reference, attributes in [0, 1]


def reference(
    clip: np.ndarray, faces: np.ndarray, attrs: np.ndarray, height: int, width: int,
    cull_backfaces: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Brute-force float64 rasterizer in 2D homogeneous coordinates (no clipping needed).

    For pixel centre p = (x, y, 1) and clip vertices q_k = (x_k, y_k, w_k), Cramer's rule
    gives weights d_k = det(p, q_{k+1}, q_{k+2}) with sum_k d_k q_k = det(q0, q1, q2) p, so
    b_k = d_k / sum(d) are the perspective-correct barycentrics and t = det / sum(d) is w at
    the point. Covered iff all b_k >= 0, t > 0 and -t <= z <= t (OpenGL clip volume).
    Front facing iff det(q0, q1, q2) > 0 (counter-clockwise in NDC).

    Returns face_id (B, H, W) int64 (-1 empty), values (B, H, W, C), ambiguous (B, H, W) bool.
    """
    x = 2 * (np.arange(width) + 0.5) / width - 1
    y = 1 - 2 * (np.arange(height) + 0.5) / height
    px, py = (a.ravel() for a in np.meshgrid(x, y))  # (N,), row-major: row 0 = top
    p = np.stack([px, py, np.ones_like(px)], 1)  # (N, 3)
    batch = clip.shape[0]
    face_id = np.full((batch, height * width), -1, np.int64)
    values = np.zeros((batch, height * width, attrs.shape[2]))
    ambiguous = np.zeros((batch, height * width), bool)
    for b in range(batch):
        v = clip[b].astype(np.float64)[faces]  # (F, 3, 4)
        q = v[..., [0, 1, 3]]  # (F, 3, 3) homogeneous 2D points
        det = np.linalg.det(q)  # (F,)
        d = np.stack(
            [np.einsum("nc,fc->fn", p, np.cross(q[:, (k + 1) % 3], q[:, (k + 2) % 3]))
             for k in range(3)],
            -1,
        )  # (F, N, 3): det(p, q1, q2) = p . (q1 x q2)
        s = d.sum(-1)
        s = np.where(np.abs(s) < 1e-300, 1e-300, s)
        bary = d / s[..., None]
        t = det[:, None] / s
        z = np.einsum("fnk,fk->fn", bary, v[..., 2])
        zn = z / np.where(np.abs(t) < 1e-300, 1e-300, t)  # NDC depth
        margins = np.concatenate(
            [bary, (1 - np.abs(zn))[..., None] * np.sign(t)[..., None]], -1
        )  # every margin >= 0 <=> inside (with t > 0)
        inside = (margins >= 0).all(-1) & (t > 0)
        near = (margins >= -EDGE_TOL).all(-1) & (np.abs(margins) < EDGE_TOL).any(-1) & (t > 0)
        if cull_backfaces:
            inside &= det[:, None] > 0
            near &= det[:, None] > 0
        depth = np.where(inside, zn, np.inf)  # (F, N)
        order = np.argsort(depth, axis=0, kind="stable")  # ties -> lower face index
        best, second = order[0], order[1] if len(faces) > 1 else order[0]
        n = np.arange(p.shape[0])
        d_best, d_second = depth[best, n], depth[second, n]
        hit = np.isfinite(d_best)
        face_id[b] = np.where(hit, best, -1)
        values[b] = np.where(
            hit[:, None], np.einsum("nk,nkc->nc", bary[best, n], attrs[b][faces[best]]), 0
        )
        # ambiguous: a boundary within tolerance on a face that could be in front, or two
        # surfaces within DEPTH_TOL of each other
        near_front = near & (zn < d_best[None] + DEPTH_TOL)
        gap = np.where(np.isfinite(d_second), d_second - np.where(hit, d_best, 0), np.inf)
        ambiguous[b] = near_front.any(0) | (gap < DEPTH_TOL)
    shape = (batch, height, width)
    return face_id.reshape(shape), values.reshape(*shape, -1), ambiguous.reshape(shape)


def random_scene(
    rng: np.random.Generator, batch: int, nfaces: int, aspect: float, crossing: int = 3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random overlapping triangles seen through a perspective camera.

    ``crossing`` triangles per item have one vertex behind the near plane (some behind the
    camera), so near-plane clipping is exercised. Returns clip (B, 3F, 4) float32,
    faces (F, 3) int64, attrs (B, 3F, 3) float32 in [0, 1].
    """
    proj = llvmpipe.perspective(60.0, aspect, 0.1, 10.0)
    nv = 3 * nfaces
    zv = -rng.uniform(0.6, 6.0, (batch, nv))
    zv[:, 0 : 3 * crossing : 3] = rng.uniform(-0.3, 1.0, (batch, crossing))
    reach = 0.7 * np.maximum(np.abs(zv), 1.0)
    xv = rng.uniform(-1, 1, (batch, nv)) * reach * aspect
    yv = rng.uniform(-1, 1, (batch, nv)) * reach
    view = np.stack([xv, yv, zv, np.ones_like(zv)], -1)
    clip = (view @ proj.T).astype(np.float32)
    faces = np.arange(nv, dtype=np.int64).reshape(nfaces, 3)
    attrs = rng.uniform(0, 1, (batch, nv, 3)).astype(np.float32)
    return clip, faces, attrs


@pytest.mark.parametrize("cull", [False, True])
def test_matches_bruteforce_reference(cull: bool) -> None:
    rng = np.random.default_rng(1)
    h, w = 40, 56  # non-square: catches swapped axes
    clip, faces, attrs = random_scene(rng, batch=3, nfaces=24, aspect=w / h)
    gl_id, gl_val = llvmpipe.GLRasterizer(h, w).render(clip, faces, attrs, cull_backfaces=cull)
    ref_id, ref_val, ambiguous = reference(clip, faces, attrs, h, w, cull_backfaces=cull)
    assert gl_id.shape == (3, h, w) and gl_id.dtype == np.int64
    assert gl_val.shape == (3, h, w, 3) and gl_val.dtype == np.float32
    clear = ~ambiguous
    assert clear.mean() > 0.85  # the comparison below covers most pixels
    assert (ref_id[clear] >= 0).mean() > 0.5  # ... and most of those are covered
    np.testing.assert_array_equal(gl_id[clear], ref_id[clear])
    np.testing.assert_allclose(gl_val[clear], ref_val[clear], atol=ATTR_TOL, rtol=0)
    assert (gl_val[gl_id < 0] == 0).all()
    # near-plane crossing triangles really are drawn (clipped, not dropped)
    assert np.isin(ref_id[clear], np.arange(3)).any()


def test_orientation_and_pixel_centres() -> None:
    """A quad on the upper-left NDC quadrant lands at the top-left of the image, and the
    interpolated NDC (x, y) equals the contract's pixel-centre grid."""
    h, w = 8, 10
    # x in [-1, 0], y in [0, 1]: the edges lie between pixel centres, no ties.
    corners = np.array([[-1, 0], [0, 0], [0, 1], [-1, 1]], np.float32)
    clip = np.concatenate([corners, np.zeros((4, 1)), np.ones((4, 1))], 1)[None]
    faces = np.array([[0, 1, 2], [0, 2, 3]])  # counter-clockwise
    face_id, val = llvmpipe.GLRasterizer(h, w).render(clip, faces, corners[None])
    expected = np.zeros((h, w), bool)
    expected[: h // 2, : w // 2] = True
    np.testing.assert_array_equal(face_id[0] >= 0, expected)
    cx = 2 * (np.arange(w) + 0.5) / w - 1
    cy = 1 - 2 * (np.arange(h) + 0.5) / h
    grid = np.stack(np.meshgrid(cx, cy), -1)
    np.testing.assert_allclose(val[0][expected], grid[expected], atol=1e-6)
    assert (val[0][~expected] == 0).all()
    culled, _ = llvmpipe.GLRasterizer(h, w).render(
        clip, faces[:, ::-1], corners[None], cull_backfaces=True
    )
    assert (culled == -1).all()  # clockwise = back facing


def test_batch_items_match_single_renders() -> None:
    """Every image of a batch is rendered exactly as it would be alone."""
    rng = np.random.default_rng(2)
    clip, faces, attrs = random_scene(rng, batch=4, nfaces=10, aspect=1.0)
    raster = llvmpipe.GLRasterizer(16, 16)
    whole = raster.render(clip, faces, attrs)
    singles = [raster.render(clip[b : b + 1], faces, attrs[b : b + 1]) for b in range(4)]
    for k in range(2):
        np.testing.assert_array_equal(whole[k], np.concatenate([s[k] for s in singles]))
    assert len(np.unique(whole[0])) > 3


def test_shared_edge_ties_are_watertight() -> None:
    """Pixel centres exactly on the edges of a quad split in two: covered exactly once, and
    on the outline llvmpipe's bottom-left rule (in image rows) applies."""
    h = w = 8
    x0, x1 = 2 * 1.5 / w - 1, 2 * 4.5 / w - 1  # through the centres of columns 1 and 4
    y0, y1 = 1 - 2 * 1.5 / h, 1 - 2 * 5.5 / h  # through the centres of rows 1 and 5
    corners = np.array([[x0, y1], [x1, y1], [x1, y0], [x0, y0]], np.float32)
    clip = np.concatenate([corners, np.zeros((4, 1)), np.ones((4, 1))], 1)[None]
    face_id, _ = llvmpipe.GLRasterizer(h, w).render(clip, np.array([[0, 1, 2], [0, 2, 3]]),
                                                    corners[None])
    expected = np.zeros((h, w), bool)
    expected[2:6, 1:4] = True  # left column 1 and bottom row 5 in; right and top out
    np.testing.assert_array_equal(face_id[0] >= 0, expected)
    # the diagonal (0 -> 2) passes through centres too: each goes to exactly one triangle
    assert set(np.unique(face_id[0][expected])) == {0, 1}


def test_bad_input_raises_clear_errors() -> None:
    raster = llvmpipe.GLRasterizer(4, 4)
    clip = np.zeros((1, 3, 4), np.float32)
    faces = np.array([[0, 1, 2]])
    attrs = np.zeros((1, 3, 3), np.float32)
    with pytest.raises(ValueError, match="clip_pos"):
        raster.render(clip[..., :3], faces, attrs)
    with pytest.raises(ValueError, match="faces"):
        raster.render(clip, faces + 1, attrs)
    with pytest.raises(TypeError, match="faces"):
        raster.render(clip, faces.astype(np.float32), attrs)
    with pytest.raises(ValueError, match="attrs"):
        raster.render(clip, faces, attrs[:, :2])
    with pytest.raises(ValueError, match="height"):
        llvmpipe.GLRasterizer(0, 4)
    face_id, val = raster.render(clip, np.zeros((0, 3), np.int64), attrs)  # no faces: empty
    assert (face_id == -1).all() and (val == 0).all()


# -- cross-check against torchraster ---------------------------------------------------------

SPOT = Path(__file__).resolve().parents[1] / "torchraster" / "assets" / "spot"


def test_crosscheck_torchraster_on_spot() -> None:
    """Face ids agree on >= 99.9 % of pixels, normals within 1e-3 where they agree."""
    import torch

    tr = pytest.importorskip("torchraster")
    if not (hasattr(tr, "rasterize") and hasattr(tr, "interpolate")):
        pytest.skip("torchraster.rasterize / interpolate not implemented yet")
    trimesh = pytest.importorskip("trimesh")
    path = SPOT / "spot_triangulated.obj"
    if not path.is_file():
        pytest.skip(f"{path} not present")
    mesh = trimesh.load(path, force="mesh", process=False)
    faces = np.asarray(mesh.faces, np.int64)
    h = w = 128
    clip = llvmpipe.orbit_clip_positions(mesh.vertices, [0.0, 75.0, 160.0, 250.0], distance=2.6)
    normals = np.broadcast_to(
        np.asarray(mesh.vertex_normals, np.float32), (len(clip), len(mesh.vertices), 3)
    ).copy()
    gl_id, gl_n = llvmpipe.GLRasterizer(h, w).render(clip, faces, normals)

    clip_t, faces_t = torch.from_numpy(clip), torch.from_numpy(faces)
    frags = tr.rasterize(clip_t, faces_t, resolution=(h, w))
    our_id = frags.face_id.numpy()
    our_n = tr.interpolate(torch.from_numpy(normals), frags, faces_t).permute(0, 2, 3, 1)
    our_n = our_n.detach().numpy()

    assert our_id.shape == gl_id.shape
    assert (gl_id >= 0).mean() > 0.2  # the cow fills a good part of the frame
    agree = our_id == gl_id
    assert agree.mean() >= 0.999, f"face ids agree on only {agree.mean():.5%} of pixels"
    both = agree & (gl_id >= 0)
    np.testing.assert_allclose(our_n[both], gl_n[both], atol=1e-3, rtol=0)
