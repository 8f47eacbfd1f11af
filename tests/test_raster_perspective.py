"""Perspective-correct interpolation: UVs of a plane seen at a grazing angle match the analytic
ray-plane intersection through every pixel centre.

The camera maths for the analytic side is written here from the definitions (OpenGL camera
looking down -z, vertical field of view, aspect = W / H), independently of torchraster.camera,
whose matrices feed the engine. So this also checks look_at / perspective / transform_points.
"""

from __future__ import annotations

import math

import pytest
import torch

import torchraster as tr
from torchraster.testing.reference_raster import pixel_centres

UV_TOL = 1e-5


def _plane_scene(dtype: torch.dtype, crossing: bool):
    """A 2-triangle quad on a tilted plane, seen at a grazing angle; with ``crossing`` the quad
    also extends behind the camera (clipped at the near plane). Returns the analytic setup."""
    eye = torch.tensor([0.3, 0.25, 1.0], dtype=torch.float64)
    target = torch.tensor([0.0, 0.0, -4.0], dtype=torch.float64)
    up = torch.tensor([0.1, 1.0, 0.0], dtype=torch.float64)
    # plane through c spanned by unit t1, t2 (tilted a little off the ground plane y = 0)
    c = torch.tensor([0.0, 0.0, -6.0], dtype=torch.float64)
    t1 = torch.tensor([1.0, 0.05, 0.0], dtype=torch.float64)
    t1 = t1 / t1.norm()
    t2 = torch.tensor([0.0, 0.02, -1.0], dtype=torch.float64)
    t2 = t2 - (t2 @ t1) * t1
    t2 = t2 / t2.norm()
    a, b_lo, b_hi = 3.0, (-8.0 if crossing else -6.5), 20.0  # extents along t1, t2
    corners = [(-a, b_lo), (a, b_lo), (a, b_hi), (-a, b_hi)]
    verts = torch.stack([c + s * t1 + r * t2 for s, r in corners])
    # uv: affine in the plane parameters, u over [-a, a], v over [b_lo, b_hi]
    uv = torch.tensor([[(s + a) / (2 * a), (r - b_lo) / (b_hi - b_lo)] for s, r in corners],
                      dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    return dict(eye=eye, target=target, up=up, c=c, t1=t1, t2=t2, a=a, b_lo=b_lo, b_hi=b_hi,
                verts=verts.to(dtype), uv=uv.to(dtype), faces=faces)


def _analytic_uv(s: dict, h: int, w: int, fov: float, near: float, far: float):
    """Per pixel (H,W): hit mask and uv (H,W,2) of the ray through the pixel centre."""
    fwd = s["target"] - s["eye"]
    fwd = fwd / fwd.norm()
    right = torch.linalg.cross(fwd, s["up"])
    right = right / right.norm()
    up = torch.linalg.cross(right, fwd)
    tan = math.tan(math.radians(fov) / 2)
    pix = pixel_centres(h, w)
    # view-space direction through the pixel: x = px tan * aspect, y = py tan, z = -1
    d = (pix[:, :1] * tan * (w / h)) * right + (pix[:, 1:] * tan) * up + fwd  # (P,3)
    normal = torch.linalg.cross(s["t1"], s["t2"])
    t = ((s["c"] - s["eye"]) @ normal) / (d @ normal)  # ray parameter = view depth
    p = s["eye"] + t[:, None] * d
    ps, pr = (p - s["c"]) @ s["t1"], (p - s["c"]) @ s["t2"]
    inside = (ps.abs() <= s["a"]) & (pr >= s["b_lo"]) & (pr <= s["b_hi"])
    hit = inside & (t >= near) & (t <= far)
    uv = torch.stack([(ps + s["a"]) / (2 * s["a"]), (pr - s["b_lo"]) / (s["b_hi"] - s["b_lo"])],
                     -1)
    # distance of the pixel centre to the quad's outline, to skip the silhouette pixels
    margin = torch.minimum(s["a"] - ps.abs(), torch.minimum(pr - s["b_lo"], s["b_hi"] - pr))
    return hit.view(h, w), uv.view(h, w, 2), margin.view(h, w), t.view(h, w)


@pytest.mark.parametrize("crossing", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_grazing_plane_uv_matches_ray_intersection(dtype: torch.dtype, crossing: bool) -> None:
    h, w, fov, near, far = 48, 64, 60.0, 0.1, 100.0
    s = _plane_scene(dtype, crossing)
    view = tr.camera.look_at(s["eye"].to(dtype), s["target"].to(dtype), s["up"].to(dtype))
    proj = tr.camera.perspective(*(torch.tensor(v, dtype=dtype) for v in (fov, w / h, near, far)))
    clip = tr.camera.transform_points(s["verts"][None], proj @ view)
    assert clip.shape == (1, 4, 4) and clip.dtype == dtype
    frags = tr.rasterize(clip, s["faces"], resolution=(h, w))
    uv = tr.interpolate(s["uv"], frags, s["faces"])  # (1,2,H,W)
    assert uv.shape == (1, 2, h, w) and uv.dtype == dtype
    hit, uv_ref, margin, _ = _analytic_uv(s, h, w, fov, near, far)
    cov = frags.face_id[0] >= 0
    safe = margin.abs() > 1e-3  # pixels whose coverage is not decided by rounding
    assert torch.equal(cov[safe], hit[safe])
    assert hit.float().mean() > 0.3
    err = (uv[0].permute(1, 2, 0).double() - uv_ref)[hit & safe].abs().max()
    assert err <= UV_TOL, f"max uv error {err:.3g}"
    # the scene really is perspective: affine screen-space interpolation would be far off
    tri = s["faces"][frags.face_id[0].clamp_min(0)]  # (H,W,3) vertex ids
    bary_affine = frags.bary[0].double() * clip[0, :, 3].double()[tri]  # screen-space weights
    bary_affine = bary_affine / bary_affine.sum(-1, keepdim=True)
    uv_aff = (bary_affine[..., None] * s["uv"].double()[tri]).sum(-2)
    assert (uv_aff - uv_ref)[hit & safe].abs().max() > 1e-2


def test_depth_is_ndc_z_of_the_analytic_hit() -> None:
    """frags.depth equals the NDC z of the ray-plane hit: (f+n)/(f-n) - 2fn/((f-n) d)."""
    h, w, fov, near, far = 48, 64, 60.0, 0.1, 100.0
    s = _plane_scene(torch.float64, False)
    view = tr.camera.look_at(s["eye"], s["target"], s["up"])
    proj = tr.camera.perspective(
        *(torch.tensor(v, dtype=torch.float64) for v in (fov, w / h, near, far))
    )
    assert proj.dtype == torch.float64
    clip = tr.camera.transform_points(s["verts"][None], proj @ view)
    frags = tr.rasterize(clip, s["faces"], resolution=(h, w))
    hit, _, margin, dist = _analytic_uv(s, h, w, fov, near, far)
    ok = hit & (margin.abs() > 1e-3)
    # the ray parameter t is the view depth, since d has unit component along the view axis
    z_ref = (far + near) / (far - near) - 2 * far * near / ((far - near) * dist)
    assert (frags.depth[0][ok] - z_ref[ok]).abs().max() < 1e-10
