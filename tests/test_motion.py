"""Optical flow, flow validity and motion vectors (torchraster/motion.py, Renderer channels)
against independent references: float64 numpy reprojection of the rendered depth with the
intrinsics K, analytic displacements of planes parallel to the image, Möller-Trumbore ray
casting (torchraster.testing.raytrace) for visibility, gradcheck in float64."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import torchraster as tr
from torchraster.motion import (
    OtherFrame,
    flow_validity,
    motion_vectors,
    optical_flow,
    reproject,
)
from torchraster.testing.raytrace import occluded

H, W = 48, 64  # non-square: catches swapped axes


def _quad(x0, x1, y0, y1, z, dtype=torch.float32):
    """A quad parallel to the image plane (facing +z), two counter-clockwise triangles."""
    v = torch.tensor([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=dtype)
    return v, torch.tensor([[0, 1, 2], [0, 2, 3]])


def _merge(*parts):
    """Concatenate (positions, faces) parts; returns positions, faces, per-part face ranges."""
    pos, faces, ranges, nv, nf = [], [], [], 0, 0
    for p, f in parts:
        pos.append(p)
        faces.append(f + nv)
        ranges.append((nf, nf + f.shape[0]))
        nv, nf = nv + p.shape[0], nf + f.shape[0]
    return torch.cat(pos), torch.cat(faces), ranges


def _frags(positions, faces, view, proj, res=(H, W)):
    clip = tr.camera.transform_points(positions, proj @ view)
    return tr.rasterize(clip if clip.dim() == 3 else clip[None], faces, res)


# ------------------------------------------------------------------ static scene, camera moves

def test_flow_equals_depth_reprojection_with_K():
    """Static spot, moving camera: flow = the reprojection of the rendered linear depth with
    the relative pose and K, computed in float64 numpy (unproject, transform, project)."""
    mesh = tr.load_spot()
    fx, fy, cx, cy = 70.0, 66.0, 30.3, 25.1  # off-centre principal point
    proj = tr.camera.from_intrinsics(fx, fy, cx, cy, W, H, 0.1)
    view1 = tr.camera.look_at([0.4, 0.5, 2.6], [0.0, 0.05, 0.0])
    view2 = tr.camera.look_at([-0.3, 0.7, 2.3], [0.1, 0.0, 0.1])
    out = tr.Renderer((H, W), shading="unlit")(
        mesh, view1, proj, channels=["depth", "mask", "flow_forward"],
        next_frame=OtherFrame(mesh.positions, view2, proj))
    depth = out.gbuffer["depth"][0, 0].double().numpy()
    covered = out.gbuffer["mask"][0, 0].numpy() > 0
    flow = out.gbuffer["flow_forward"][0].double().numpy()
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    cam = np.stack([(u - cx) / fx * depth, (v - cy) / fy * depth, depth], -1)  # OpenCV
    gl = cam * np.array([1.0, -1.0, -1.0])  # OpenCV -> OpenGL view axes
    rel = view2[0].double().numpy() @ np.linalg.inv(view1[0].double().numpy())
    p2 = gl @ rel[:3, :3].T + rel[:3, 3]
    x, y, z = p2[..., 0], -p2[..., 1], -p2[..., 2]  # back to OpenCV
    ref = np.stack([fx * x / z + cx - u, fy * y / z + cy - v])
    assert covered.sum() > 500
    err = np.abs(flow - ref)[:, covered]
    assert err.max() < 1e-3, err.max()
    assert np.abs(ref[:, covered]).max() > 3  # the camera did move
    assert (flow[:, ~covered] == 0).all()


# ---------------------------------------------------------- translating object, static camera

def _two_planes(dtype=torch.float32):
    back = _quad(-20.0, 20.0, -20.0, 20.0, -10.0, dtype)
    obj = _quad(-1.0, 1.0, -0.8, 0.8, -4.0, dtype)
    return _merge(back, obj)


def test_translation_flow_and_motion_analytic():
    """A plane parallel to the image at depth z translated by t: flow = (f t_x / z,
    -f t_y / z) pixels (y down), zero on the static background; motion vectors = NDC
    (P00 t_x / z, P11 t_y / z)."""
    positions, faces, ((b0, b1), (o0, o1)) = _two_planes()
    view = torch.eye(4)[None]
    proj = tr.camera.perspective(60.0, W / H, 0.1)
    t = torch.tensor([0.3, -0.2, 0.0])
    moving = torch.zeros(positions.shape[0], 1)
    moving[4:] = 1
    frags = _frags(positions, faces, view, proj)
    flow = optical_flow(frags, faces, positions + moving * t, view, proj)
    fid = frags.face_id[0]
    on_obj, on_back = (fid >= o0) & (fid < o1), (fid >= b0) & (fid < b1)
    assert on_obj.sum() > 100 and on_back.sum() > 100
    fx, fy = float(proj[0, 0, 0]) * W / 2, float(proj[0, 1, 1]) * H / 2
    want = torch.tensor([fx * 0.3 / 4, -fy * -0.2 / 4])
    torch.testing.assert_close(flow[0][:, on_obj], want[:, None].expand(2, int(on_obj.sum())),
                               atol=1e-4, rtol=0)
    assert flow[0][:, on_back].abs().max() < 1e-4  # float32 rounding of a 40 m quad
    # motion: the object was at positions - t in the previous frame
    mv = motion_vectors(frags, faces, positions - moving * t, view, proj)
    want_ndc = torch.tensor([float(proj[0, 0, 0]) * 0.3 / 4, float(proj[0, 1, 1]) * -0.2 / 4])
    torch.testing.assert_close(mv[0][:, on_obj],
                               want_ndc[:, None].expand(2, int(on_obj.sum())), atol=1e-6, rtol=0)
    assert mv[0][:, on_back].abs().max() < 3e-6


def test_motion_is_scaled_negative_backward_flow():
    """motion = -flow_backward * (2 / W, -2 / H) (NDC x grows 2/W per column, NDC y falls
    2/H per row), on spot with a moving camera and a moving object."""
    mesh = tr.load_spot()
    proj = tr.camera.perspective(40.0, W / H, 0.1)
    view1 = tr.camera.look_at([0.4, 0.5, 2.6], [0.0, 0.05, 0.0])
    view0 = tr.camera.look_at([0.1, 0.6, 2.5], [0.0, 0.0, 0.0])
    prev = mesh.positions + torch.tensor([0.05, -0.02, 0.1])
    frags = _frags(mesh.positions, mesh.faces, view1, proj)
    flow_b = optical_flow(frags, mesh.faces, prev, view0, proj)
    mv = motion_vectors(frags, mesh.faces, prev, view0, proj)
    scale = torch.tensor([2 / W, -2 / H]).view(1, 2, 1, 1)
    torch.testing.assert_close(mv, -flow_b * scale, atol=2e-6, rtol=0)
    assert mv.abs().max() > 0.05


# --------------------------------------------------------------------- validity, ray traced

def _object_ids(frags, ranges):
    fid = frags.face_id[0]
    ids = torch.zeros_like(fid)
    for k, (a, b) in enumerate(ranges):
        ids[(fid >= a) & (fid < b)] = k + 1
    return ids


def _near_boundary(ids: torch.Tensor, radius: int = 2) -> torch.Tensor:
    """Pixels within ``radius`` of a change of object id (4-neighbours)."""
    edge = torch.zeros_like(ids, dtype=torch.bool)
    edge[1:] |= ids[1:] != ids[:-1]
    edge[:-1] |= ids[1:] != ids[:-1]
    edge[:, 1:] |= ids[:, 1:] != ids[:, :-1]
    edge[:, :-1] |= ids[:, 1:] != ids[:, :-1]
    k = 2 * radius + 1
    return torch.nn.functional.max_pool2d(edge[None, None].float(), k, 1, radius)[0, 0] > 0


def test_flow_validity_against_ray_casting():
    """A slanted floor and a vertical occluder; the camera moves so that the occluder hides
    another part of the floor and some of the floor leaves the image. Reference: inside the
    other frustum (float64 projection) and no triangle hit on the segment from the other
    camera's centre to the point (Möller-Trumbore). Compared on pixels more than 2 px from
    any object boundary in either frame."""
    floor = (torch.tensor([[-3.0, 0, 3], [3, 0, 3], [3, 0, -3], [-3, 0, -3]]),
             torch.tensor([[0, 1, 2], [0, 2, 3]]))
    wall = _quad(-0.2, 0.6, 0.0, 0.8, 1.2)
    positions, faces, ranges = _merge(floor, wall)
    proj = tr.camera.perspective(50.0, W / H, 0.1)
    view1 = tr.camera.look_at([0.0, 2.0, 4.0], [0.0, 0.0, 0.0])
    eye2 = torch.tensor([1.5, 1.0, 3.5])
    view2 = tr.camera.look_at(eye2, [0.5, 0.0, 0.0])
    frags1 = _frags(positions, faces, view1, proj)
    frags2 = _frags(positions, faces, view2, proj)
    valid = flow_validity(frags1, faces, positions, view2, proj)[0, 0] > 0
    rep = reproject(frags1, faces, positions, view2, proj)

    covered = frags1.face_id[0] >= 0
    point = tr.interpolate(positions.double(), frags1, faces)[0].permute(1, 2, 0)[covered]
    homo = torch.cat([point, torch.ones_like(point[:, :1])], 1)
    clip = homo @ (proj[0] @ view2[0]).double().T
    inside = (clip[:, :3].abs() <= clip[:, 3:]).all(1) & (clip[:, 3] > 0)
    hit = occluded(eye2.double().expand_as(point), point - eye2.double(),
                   torch.full((point.shape[0],), 1 - 1e-6, dtype=torch.float64),
                   positions.double(), faces)
    ref = torch.zeros_like(valid)
    ref[covered] = inside & ~hit

    near1 = _near_boundary(_object_ids(frags1, ranges))
    near2 = _near_boundary(_object_ids(frags2, ranges))
    col = torch.floor(rep.pixel[0, 0] + 0.5).long().clamp(0, W - 1)
    row = torch.floor(rep.pixel[0, 1] + 0.5).long().clamp(0, H - 1)
    landing_inside = rep.inside[0, 0]
    near_other = landing_inside & near2[row, col]
    compare = covered & ~near1 & ~near_other
    assert int((compare & ref).sum()) > 300  # visible in both
    assert int((compare & covered & ~ref & landing_inside).sum()) > 30  # occluded
    assert int((compare & ~landing_inside).sum()) > 30  # left the image
    assert torch.equal(valid[compare], ref[compare]), int((valid != ref)[compare].sum())
    assert not bool(valid[~covered].any())


# ------------------------------------------------------------------------- behind the camera

def test_points_behind_other_camera_are_zero_invalid_and_finite():
    floor = (torch.tensor([[-2.0, -1, -0.5], [2, -1, -0.5], [2, -1, -20], [-2, -1, -20]]),
             torch.tensor([[0, 2, 1], [0, 3, 2]]))
    positions, faces, _ = _merge(floor)
    positions.requires_grad_(True)
    proj = tr.camera.perspective(60.0, W / H, 0.1)
    view = torch.eye(4)[None]
    view2 = tr.camera.look_at([0.0, 0.0, -5.0], [0.0, 0.0, -6.0])  # looks along -z from z=-5
    frags = _frags(positions, faces, view, proj)
    moved = positions * 1.0
    flow = optical_flow(frags, faces, moved, view2, proj)
    valid = flow_validity(frags, faces, moved, view2, proj)
    mv = motion_vectors(frags, faces, moved, view2, proj)
    z = tr.interpolate(positions.detach(), frags, faces)[0, 2]
    covered = frags.face_id[0] >= 0
    behind = covered & (z > -5.0 + 1e-3)
    ahead = covered & (z < -5.0 - 1e-3)
    assert behind.sum() > 50 and ahead.sum() > 50
    assert torch.isfinite(flow).all() and torch.isfinite(mv).all()
    assert (flow[0][:, behind] == 0).all() and (mv[0][:, behind] == 0).all()
    assert (valid[0, 0][behind] == 0).all()
    assert (flow[0][:, ahead] != 0).any()
    (flow.square().sum() + mv.sum()).backward()
    assert torch.isfinite(positions.grad).all()


# --------------------------------------------------------------------------------- gradients

def _tiny_scene():
    positions, faces, _ = _merge(_quad(-20.0, 20.0, -20.0, 20.0, -10.0, torch.float64),
                                 _quad(-1.1, 0.9, -0.7, 1.0, -4.0, torch.float64))
    moving = torch.zeros(positions.shape[0], 1, dtype=torch.float64)
    moving[4:] = 1
    view = tr.camera.look_at([0.2, 0.1, 0.3], [0.0, 0.0, -5.0]).double()
    proj = tr.camera.perspective(60.0, 1.0, 0.1).double()
    return positions, faces, moving, view, proj


def test_gradcheck_object_translation_both_frames():
    """d flow / d t, t translating the object in the other frame, and in the current frame
    (through the barycentrics), 8x8, float64."""
    positions, faces, moving, view, proj = _tiny_scene()
    view2 = tr.camera.look_at([0.3, 0.0, 0.2], [0.0, 0.1, -5.0]).double()
    frags = _frags(positions, faces, view, proj, (8, 8))

    def other(t):
        return optical_flow(frags, faces, positions + moving * t, view2, proj)

    def current(t):
        f = _frags(positions + moving * t, faces, view, proj, (8, 8))
        return optical_flow(f, faces, positions + moving * 0.1, view2, proj)

    t = torch.tensor([0.05, -0.03, 0.2], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(other, (t,), eps=1e-6, atol=1e-6)
    assert torch.autograd.gradcheck(current, (t,), eps=1e-6, atol=1e-5)


def test_gradcheck_other_view_matrix():
    """d flow / d (the other camera's view matrix rows 0-2), 8x8, float64."""
    positions, faces, _, view, proj = _tiny_scene()
    frags = _frags(positions, faces, view, proj, (8, 8))
    base = tr.camera.look_at([0.3, 0.0, 0.2], [0.0, 0.1, -5.0]).double()[0]

    def fn(rows):
        v = torch.cat([rows, base[3:]], 0)
        return optical_flow(frags, faces, positions, v, proj)

    rows = base[:3].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(fn, (rows,), eps=1e-6, atol=1e-6)


# ------------------------------------------------------------------------------ the renderer

def _spot_frames():
    mesh = tr.load_spot()
    proj = tr.camera.perspective(40.0, W / H, 0.1)
    view = tr.camera.look_at([0.4, 0.5, 2.6], [0.0, 0.05, 0.0])
    nxt = OtherFrame(mesh.positions + torch.tensor([0.05, 0.0, -0.1]),
                     tr.camera.look_at([0.6, 0.4, 2.5], [0.0, 0.0, 0.0]), proj)
    prev = OtherFrame(mesh.positions - torch.tensor([0.05, 0.0, -0.1]),
                      tr.camera.look_at([0.2, 0.6, 2.7], [0.0, 0.1, 0.0]), proj)
    return mesh, view, proj, nxt, prev


ALL = ["flow_forward", "flow_forward_valid", "flow_backward", "flow_backward_valid", "motion"]


@pytest.mark.parametrize("s", [1, 2, 3])
def test_renderer_channels_match_functions(s):
    """Renderer channels = the functions on the same fragments; with supersampling s, the
    sub-sample (s - 1) // 2 of each block, flow divided by s (output pixels)."""
    mesh, view, proj, nxt, prev = _spot_frames()
    out = tr.Renderer((H, W), shading="unlit", raster=tr.RasterSettings(supersample=s))(
        mesh, view, proj, channels=ALL, next_frame=nxt, previous_frame=prev)
    assert {"flow forward", "flow forward valid", "flow backward", "flow backward valid",
            "motion vectors"} <= set(out.plan.steps)
    frags = _frags(mesh.positions, mesh.faces, view, proj, (H * s, W * s))
    k = (s - 1) // 2
    ref = {
        "flow_forward": optical_flow(frags, mesh.faces, nxt.positions, nxt.view, nxt.proj) / s,
        "flow_backward": optical_flow(frags, mesh.faces, prev.positions, prev.view,
                                      prev.proj) / s,
        "motion": motion_vectors(frags, mesh.faces, prev.positions, prev.view, prev.proj),
        "flow_forward_valid": flow_validity(frags, mesh.faces, nxt.positions, nxt.view,
                                            nxt.proj),
        "flow_backward_valid": flow_validity(frags, mesh.faces, prev.positions, prev.view,
                                             prev.proj),
    }
    for name, want in ref.items():
        got = out.gbuffer[name]
        assert got.shape == (1, want.shape[1], H, W), name
        torch.testing.assert_close(got, want[:, :, k::s, k::s], atol=1e-6, rtol=0, msg=name)
    valid = out.gbuffer["flow_forward_valid"]
    assert 0 < float(valid.mean()) < float((out.alpha > 0).float().mean())  # some occluded


def test_renderer_flow_on_first_opaque_layer():
    """A fully cut-out MASK quad in front of the moving object: the flow is that of the
    surface behind it (the first opaque layer), as if the quad were absent."""
    positions, faces, ((b0, b1), (o0, o1)) = _two_planes()
    glass, gf = _quad(-3.0, 3.0, -3.0, 3.0, -2.0)
    all_pos = torch.cat([positions, glass])
    all_faces = torch.cat([faces, gf + positions.shape[0]])
    face_material = torch.cat([torch.zeros(faces.shape[0], dtype=torch.long),
                               torch.ones(2, dtype=torch.long)])
    cut = tr.Material(base_color_factor=torch.tensor([1.0, 1.0, 1.0, 0.0]), alpha_mode="MASK")
    view, proj = torch.eye(4), tr.camera.perspective(60.0, W / H, 0.1)
    t = torch.tensor([0.3, -0.2, 0.0])
    moving = torch.zeros(all_pos.shape[0], 1)
    moving[4:8] = 1
    scene = tr.RenderScene(all_pos, all_faces, face_material=face_material,
                           materials=[tr.Material(), cut])
    r = tr.Renderer((H, W), shading="unlit")
    out = r(scene, view, proj, channels=["flow_forward", "flow_forward_valid"],
            next_frame=OtherFrame(all_pos + moving * t, view, proj))
    assert out.plan.alpha == "mask"
    alone = r(tr.RenderScene(positions, faces), view, proj,
              channels=["flow_forward", "flow_forward_valid"],
              next_frame=OtherFrame(positions + moving[:8] * t, view, proj))
    torch.testing.assert_close(out.gbuffer["flow_forward"], alone.gbuffer["flow_forward"],
                               atol=1e-5, rtol=0)
    assert float(out.gbuffer["flow_forward"].abs().max()) > 1


def test_renderer_gradients_flow_to_both_frames():
    mesh, view, proj, nxt, _ = _spot_frames()
    pos = mesh.positions.clone().requires_grad_(True)
    nxt_pos = nxt.positions.clone().requires_grad_(True)
    out = tr.Renderer((24, 32), shading="unlit")(
        tr.RenderScene(pos, mesh.faces), view, proj, channels=["flow_forward"],
        next_frame=OtherFrame(nxt_pos, nxt.view, nxt.proj))
    out.gbuffer["flow_forward"].square().sum().backward()
    for g in (pos.grad, nxt_pos.grad):
        assert torch.isfinite(g).all() and g.abs().max() > 0


# ------------------------------------------------------------------------------- bad input

def test_bad_input_errors():
    mesh, view, proj, nxt, prev = _spot_frames()
    r = tr.Renderer((8, 8), shading="unlit")
    with pytest.raises(ValueError, match="'motion'.*previous_frame"):
        r(mesh, view, proj, channels=["motion"], next_frame=nxt)
    with pytest.raises(ValueError, match="'flow_forward_valid'.*next_frame"):
        r(mesh, view, proj, channels=["flow_forward_valid"], previous_frame=prev)
    with pytest.raises(ValueError, match=r"next_frame\.positions: V = 10"):
        r(mesh, view, proj, channels=["flow_forward"],
          next_frame=OtherFrame(torch.zeros(10, 3), view, proj))
    with pytest.raises(ValueError, match=r"previous_frame\.view: batch size 3"):
        r(mesh, view, proj, channels=["motion"],
          previous_frame=OtherFrame(mesh.positions, view.expand(3, 4, 4), proj))
    with pytest.raises(TypeError, match="next_frame: expected a torchraster.motion.OtherFrame"):
        r(mesh, view, proj, channels=["flow_forward"], next_frame=(mesh.positions, view, proj))
    bad = mesh.positions.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"OtherFrame\.positions: contains 1 NaN"):
        OtherFrame(bad, view, proj)
    with pytest.raises(ValueError, match=r"OtherFrame\.view: expected shape"):
        OtherFrame(mesh.positions, torch.eye(3), proj)
    with pytest.raises(TypeError, match=r"OtherFrame\.proj: expected a torch.Tensor"):
        OtherFrame(mesh.positions, view, None)
    frags = _frags(mesh.positions, mesh.faces, view, proj, (8, 8))
    with pytest.raises(ValueError, match="other_positions: V = 5"):
        optical_flow(frags, mesh.faces, torch.zeros(5, 3), view, proj)
    with pytest.raises(ValueError, match="other_view: batch size 2"):
        optical_flow(frags, mesh.faces, mesh.positions, view.expand(2, 4, 4), proj)
    with pytest.raises(TypeError, match="frags: expected Fragments"):
        optical_flow(None, mesh.faces, mesh.positions, view, proj)


def test_neighbour_raster_is_reused_and_changes_nothing(monkeypatch):
    """Frame t's flow validity rasterizes frame t + 1; rendering t + 1 next (same positions,
    camera and options, no gradients) reuses that raster instead of rasterizing again, and
    gives exactly what a fresh renderer gives for t + 1 alone."""
    import torchraster.renderer as renderer_module

    mesh, view, proj, nxt, _ = _spot_frames()
    after = OtherFrame(nxt.positions + torch.tensor([0.05, 0.0, -0.1]),
                       tr.camera.look_at([0.8, 0.3, 2.4], [0.0, 0.0, 0.0]), proj)
    here = OtherFrame(mesh.positions, view, proj)
    calls = []
    real = renderer_module.rasterize
    monkeypatch.setattr(renderer_module, "rasterize",
                        lambda *a, **k: calls.append(1) or real(*a, **k))
    r = tr.Renderer((H, W), shading="unlit")
    want = ["flow_forward", "flow_forward_valid", "flow_backward_valid", "depth", "normal"]
    scene = tr.RenderScene.from_mesh(mesh)
    with torch.no_grad():
        r(scene, view, proj, channels=["flow_forward_valid"], next_frame=nxt)
        assert len(calls) == 2  # its own raster and frame t + 1's
        second = dataclasses.replace(scene, positions=nxt.positions)
        got = r(second, nxt.view, nxt.proj, channels=want, next_frame=after,
                previous_frame=here)
        assert len(calls) == 4  # frames t + 2 and t: its own raster was kept
        fresh = tr.Renderer((H, W), shading="unlit")(
            second, nxt.view, nxt.proj, channels=want,
            next_frame=OtherFrame(after.positions, after.view, after.proj),
            previous_frame=OtherFrame(mesh.positions, view, proj))
    assert torch.equal(got.image, fresh.image) and torch.equal(got.alpha, fresh.alpha)
    for name in want:
        assert torch.equal(got.gbuffer[name], fresh.gbuffer[name]), name
    # with gradients the main pass never takes a kept raster (it has no graph)
    pos = nxt.positions.clone().requires_grad_(True)
    r(dataclasses.replace(scene, positions=pos), nxt.view, nxt.proj).image.sum().backward()
    assert len(calls) == 8 and pos.grad.abs().sum() > 0  # 3 fresh, 1 here


def test_face_depth_slope_matches_finite_differences():
    """``face_depth_slope`` (the gradient of the point's own face's linear depth per pixel
    of the other frame) against central differences of the other frame's rasterized linear
    depth, on a tilted plane, float64; 0 outside ``where``."""
    from torchraster.motion import face_depth_slope, linear_depth

    dt = torch.float64
    plane = torch.tensor([[-1.0, -1, 0], [1, -1, -1.5], [1, 1, -1.5], [-1, 1, 0]], dtype=dt)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    proj = tr.camera.perspective(50.0, W / H, 0.1).to(dt)
    view = tr.camera.look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0]).to(dt)
    other_view = tr.camera.look_at([0.5, 0.3, 2.8], [0.0, 0.0, -0.5]).to(dt)
    frags = _frags(plane, faces, view, proj)
    rep = reproject(frags, faces, plane, other_view, proj)
    where = torch.ones(1, 1, H, W, dtype=torch.bool)
    where[..., : W // 4] = False
    slope = face_depth_slope(frags, faces, plane, other_view, proj, where)
    assert slope.shape == (1, 2, H, W) and (slope[..., : W // 4] == 0).all()
    other = _frags(plane, faces, other_view, proj)
    d = linear_depth(other.depth, proj)[0]  # (H, W) float64
    fd_x = (d[:, 2:] - d[:, :-2]) / 2  # at columns 1 .. W-2
    fd_y = (d[2:] - d[:-2]) / 2
    col = torch.floor(rep.pixel[0, 0] + 0.5).long()
    row = torch.floor(rep.pixel[0, 1] + 0.5).long()
    inner = (rep.inside[0, 0] & where[0, 0] & (col > 1) & (col < W - 2) & (row > 1)
             & (row < H - 2))
    assert int(inner.sum()) > 100
    r, c = row[inner], col[inner]
    finite = torch.isfinite(fd_x[r, c - 1]) & torch.isfinite(fd_y[r - 1, c])
    got_x, got_y = slope[0, 0][inner][finite], slope[0, 1][inner][finite]
    # the slope at the point vs the difference across the nearest centre (half a pixel away
    # at most): equal to the curvature of depth over one pixel
    torch.testing.assert_close(got_x, fd_x[r, c - 1][finite], rtol=0.02, atol=1e-4)
    torch.testing.assert_close(got_y, fd_y[r - 1, c][finite], rtol=0.02, atol=1e-4)
    assert float(got_x.abs().mean()) > 1e-3  # a tilted plane: the test can fail


def test_kept_raster_only_for_the_same_inputs():
    """The renderer's kept neighbour raster is returned only for the same clip positions,
    culling, face ranges and (unchanged) faces: anything else rasterizes anew and equals
    ``rasterize`` of those inputs."""
    from torchraster.renderer import _RasterMemo

    mesh, view, proj, _, _ = _spot_frames()
    plan = tr.Renderer((H, W), shading="unlit").plan(tr.RenderScene.from_mesh(mesh), None,
                                                    None, [])
    clip = tr.camera.transform_points(mesh.positions, proj @ view).reshape(1, -1, 4)
    faces = mesh.faces.clone()
    memo = _RasterMemo()
    kept = memo.rasterize(clip, faces, plan, False, None, keep=True)
    assert memo.rasterize(clip.clone(), faces, plan, False, None) is kept
    ranges = torch.tensor([[0, faces.shape[0] // 2]])
    for cull, fr in ((True, None), (False, ranges)):
        got = memo.rasterize(clip, faces, plan, cull, fr)
        want = tr.rasterize(clip, faces, (H, W), cull_backfaces=cull, face_ranges=fr)
        assert got is not kept and torch.equal(got.face_id, want.face_id), (cull, fr)
    faces[:, [1, 2]] = faces[:, [2, 1]].clone()  # changed in place: not the kept raster
    assert memo.rasterize(clip, faces, plan, True, None) is not kept
    assert memo.rasterize(clip, faces, plan, False, None) is not kept


def test_linear_depth_unprojects_every_pixel_centre():
    """``linear_depth`` against a per-pixel solve of ``proj @ (x, y, z, 1) ~ (ndc, 1)`` for
    perspective, reverse-Z and orthographic projections, one per batch item or shared."""
    from torchraster.motion import linear_depth

    h, w = 5, 7
    g = torch.Generator().manual_seed(1)
    projs = [tr.camera.perspective(50.0, 1.3, 0.1, 40.0),
             tr.camera.perspective(70.0, 0.8, 0.05, reverse_z=True),
             tr.camera.orthographic(-2.0, 1.5, -1.0, 1.2, 0.1, 9.0)]
    for shared in (True, False):
        proj = torch.cat([p.reshape(-1, 4, 4) for p in (projs[:1] if shared else projs)]
                         ).to(torch.float64)
        b = 3
        ndc = torch.rand(b, h, w, generator=g, dtype=torch.float64) * 1.8 - 0.9
        ndc[:, 0, :2] = float("inf")
        got = linear_depth(ndc, proj)
        for i in range(b):
            p = proj[0 if shared else i]
            for r in range(h):
                for c in range(w):
                    if not torch.isfinite(ndc[i, r, c]):
                        assert got[i, r, c] == float("inf")
                        continue
                    q = torch.linalg.solve(p, torch.tensor(
                        [(2 * c + 1) / w - 1, 1 - (2 * r + 1) / h, float(ndc[i, r, c]), 1.0],
                        dtype=torch.float64))
                    assert abs(float(got[i, r, c]) + float(q[2] / q[3])) < 1e-9 * (
                        1 + abs(float(q[2] / q[3])))
