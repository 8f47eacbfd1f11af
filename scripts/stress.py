"""Stress the rasterizer and the renderer with random hostile scenes; count what goes wrong.

Rasterizer scene kinds (cycled):
- soup: hostile triangle soups (slivers, degenerate, near/far crossers, behind the camera) with
  random homogeneous scale 10^[-6, 8], batch 1-4, resolutions from 1x1 to 160x160, float32 or
  float64, culling on/off;
- huge: the same with clip coordinates times 1e8;
- near_far: random triangles through torchraster.camera.perspective with near in
  [1e-6, 1e-1], far in [1e2, 1e9] or inf, standard or reverse-Z;
- closed: convex closed meshes (icospheres, convex hulls of random points) from random views,
  including cameras inside them: any empty pixel whose 4 neighbours are covered is a crack
  (the silhouette of a convex mesh is convex, so such a pixel must be covered);
- grid: shared-edge grids, each face rasterized alone (face_ranges) to count coverage:
  exact grids on pixel centres with power-of-two w (every interior pixel covered exactly
  once), and jittered perspective grids (no pixel covered twice; no crack inside).

For every scene: NaN/Inf in bary, depth of covered pixels, |depth| > 1, interpolated images,
and the gradients of a random loss backpropagated through interpolate to clip_pos and the
attributes; rasterize_depth resolved in bands of random heights against one pass (and its
coverage against rasterize's); the depth keys with occlusion culling of back faces forced on
(however small the scene) against off. Writes section ``stress`` of docs/benchmarks.md with
the counts.

Renderer scene kinds (cycled), each a ground plane with a sphere resting on it (and a
zero-area triangle), rendered forward and backward through ``tr.Renderer``:
- material: hostile material factors and float textures (0, denormal 1e-40, 1e-6, 1e6
  emission, roughness 0, metallic 0 / 1, inward or zero normal-map texels) under a sun and
  ambient light;
- light: hostile lights: intensities and colours 0 / 1e-40 / 1e6, directions grazing the
  plane, from below or of length 1e-15, point and spot lights exactly on a vertex, inside
  the sphere or 1e6 away, ranges 1e-6 to inf, cones of zero width or pi/2; in half of the
  scenes 1-3 area lights (rectangles and discs, one- or two-sided, half-extents 1e-6 to
  1e3 m, at the same hostile places, casting PCSS shadows or not, in fog too, under every
  shading model);
- environment: hostile environment maps (1 to 32 rows; zero, denormal, a single 1e6 texel),
  intensities 0 to 1e6, both diffuse methods, shown as background or not;
- grazing: all of the above at random, cameras edge-on to the plane (elevation 0 or 1e-4
  degrees) and from below it, supersampling, SSAO, every texture filter, every shading
  model, float64. These four kinds draw edge antialiasing (``edge_supersample`` 2 or
  3) in 30 % of the scenes where it is implemented (opaque materials, no SSAO, SSR, fog
  or dissolve). Half of their scenes ask for every channel of the frame, half for some
  label channels only, so the surface channels only the lighting reads stay packed
  (``plan.packed``); half of those are rendered again with every channel and must give
  the same image bit for bit ("packed surface differs"). A third run in small chunks (the
  paths of large frames): lighting in pixel chunks of 16 pixel-lights x 8, each recomputed
  in backward, the other shading models, SSAO and the fog march in bands of one row,
  shadow lookups in chunks of 512 receiver-light-tap corners, image-based lighting in chunks
  of 16 pixels.
- labels: the label channels (instance, semantic, object_coords, distance, amodal, face_id)
  of the same stage as three objects, in float32, float64, float16 or bfloat16, supersampled
  1x to 3x, batch 1-2 (with face_ranges dropping an object), sometimes a MASK cut-out; the
  labels' invariants are checked (ids in range, semantic = category of instance, visible
  inside amodal, amodal = each object rasterized alone when not supersampled, NOCS in
  [0, 1], distance >= depth, all 0 where empty) and counted as "label errors".
- motion: the flow / motion channels (flow_forward, flow_backward, their validity, motion)
  of the stage with the sphere moved by 0 to 1e6 m (1e3 in half precision) and the other
  frames' cameras orbiting (0.5 to 6 m from the target), placed on a vertex, inside the
  sphere or pointing away, in float32, float64, float16 or bfloat16, supersampled 1x to
  3x, batch 1-2, culling and a MASK cut-out at random; checks validity in {0, 1} and only on
  covered pixels, flow and motion 0 where empty, and
  motion = -flow_backward * (2 / W, -2 / H) (counted as "motion errors"). Inf gradients
  of float16 renders are counted apart, not as problems: near the other camera's plane the
  flow's true gradient exceeds float16's range (7e5 in seed 20261128's scene 117); the
  render returns each input's gradient saturated, and the stage's float16 leaf sums two of
  them (this frame's positions and the other frame's, made from them) to Inf in float16.
- half: the stage in float16 / bfloat16 with float textures (up to 300 texels), a sun
  (sometimes straight down), in half of the scenes an area light (a panel or a disc above
  the stage, casting shadows or not) and a spot light casting shadows with every filter (PCF and
  PCSS with a pixel-footprint radius of 0, 0.56 or 8 pixels at random), every texture
  filter, antialiasing on or off, else edge antialiasing (``edge_supersample`` 1 to 3),
  in 40 % of the scenes under a hostile float32 environment (every specular mode).
- far: the stage, its cameras (batch 1-2) and its lights (a sun with 1-3 cascades, a spot
  and two point lights, shadows of a random filter; in 30 % of the scenes a bound on the
  lookups' padded maps that the point lights' maps do not fit together, so they are looked
  up in slices, or that nothing fits; in half of them the lookups recompute their
  receiver chunks in backward, ``RECOMPUTE_TAPS`` 0) moved together by 0 to 1e7 m in a random
  direction (the hard case of camera-relative rendering), float64 world positions (float32
  in a quarter of the scenes: rounded already, checked for NaN/Inf only), fog (its base
  height moved alike) or a dissolve (offset a multiple of the noise period) at random,
  supersampling and antialiasing; the same scene is rendered at the origin, and each
  float64 scene counts as "far-away errors" the face ids that differ beyond 3 pixels + 1 %
  of the covered ones and the world ``position`` channel off by more than float32 rounding.
Any kind may also draw screen-space reflections, fog with light shafts (densities 0 to 50,
height falloffs 0 to 20, light path on or off), a dissolve (threshold 0, 0.3 or 1) and the
multiscatter switch.
For every render: NaN/Inf in the image, alpha and every float G-buffer channel, and in the
gradients of a random loss with respect to vertex positions, material parameters, light
parameters and the environment. A ``ValueError``/``TypeError`` is counted apart (the clear
rejection of an input); any other exception is a problem. Writes section
``stress-renderer``.

    python scripts/stress.py [--part all|raster|renderer] [--n 5000] [--n-renderer 1000]
                             [--seed 0] [--no-picture]

Unless --no-picture, the raster part also renders docs/images/raster_ref_diff.png: engine vs
the independent float64 reference (torchraster/testing/reference_raster.py) face ids for
spot, and their difference.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib
import math
import sys
import time
import warnings
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import torch
import trimesh
from benchmd import markdown_table, update_section

import torchraster as tr
from torchraster.mesh import vertex_normals, vertex_tangents
from torchraster.motion import OtherFrame
from torchraster.numerics import to_compute
from torchraster.raster import rasterize_coverage
from torchraster.renderer import _clip_positions  # the renderer's own clip positions
from torchraster.shading import ibl, lighting, shadows, volumetric
from torchraster.testing.reference_raster import (
    look_at_matrix,
    perspective_matrix,
    random_soup,
    reference_coverage_count,
    to_clip,
)

raster_module = importlib.import_module("torchraster.raster.rasterize")  # knobs: bands, culling
ROOT = Path(__file__).resolve().parent.parent

KINDS = ("soup", "huge", "near_far", "closed", "grid")
DEPTH_SLACK = 1e-5  # |NDC depth| of a covered pixel may exceed 1 by float rounding only


def _rand(gen: torch.Generator, lo: float, hi: float) -> float:
    return lo + (hi - lo) * torch.rand(1, generator=gen).item()


def _randint(gen: torch.Generator, lo: int, hi: int) -> int:
    """Uniform int in [lo, hi]."""
    return int(torch.randint(lo, hi + 1, (1,), generator=gen))


def _resolution(gen: torch.Generator) -> tuple[int, int]:
    if torch.rand(1, generator=gen).item() < 0.2:
        return _randint(gen, 1, 4), _randint(gen, 1, 4)  # tiny
    return _randint(gen, 8, 160), _randint(gen, 8, 160)


def _check_numerics(clip: torch.Tensor, faces: torch.Tensor, res, cull: bool, gen, c: Counter):
    """Rasterize, interpolate, backprop a random loss; count non-finite values."""
    clip = clip.detach().clone().requires_grad_(True)
    attrs = torch.randn(clip.shape[0], clip.shape[1], 3, dtype=clip.dtype, generator=gen)
    attrs.requires_grad_(True)
    frags = tr.rasterize(clip, faces, resolution=res, cull_backfaces=cull)
    img = tr.interpolate(attrs, frags, faces)
    hit = frags.face_id >= 0
    c["pixels"] += frags.face_id.numel()
    c["covered"] += int(hit.sum())
    c["nonfinite_bary"] += int((~torch.isfinite(frags.bary)).any(-1).sum())
    c["nonfinite_depth"] += int((~torch.isfinite(frags.depth[hit])).sum())
    c["depth_out_of_range"] += int((frags.depth[hit].abs() > 1 + DEPTH_SLACK).sum())
    c["bad_empty"] += int((~torch.isposinf(frags.depth[~hit])).sum())
    c["nonfinite_image"] += int((~torch.isfinite(img)).sum())
    weights = torch.randn(img.shape, dtype=img.dtype, generator=gen)
    loss = (img * weights).sum() + frags.depth[hit].sum()
    loss.backward()
    c["nonfinite_grad_clip"] += int((~torch.isfinite(clip.grad)).sum())
    c["nonfinite_grad_attrs"] += int((~torch.isfinite(attrs.grad)).sum())
    # rasterize_depth in bands of rows (forced: random band heights) against one pass
    whole = tr.raster.rasterize_depth(clip.detach(), faces, res, cull)
    band_pixels, raster_module.DEPTH_BAND_PIXELS = raster_module.DEPTH_BAND_PIXELS, max(
        1, res[1] * _randint(gen, 1, 40))
    try:
        banded = tr.raster.rasterize_depth(clip.detach(), faces, res, cull)
    finally:
        raster_module.DEPTH_BAND_PIXELS = band_pixels
    c["bands_vs_whole"] += int((banded != whole).sum() + (torch.isfinite(whole) != hit).sum())
    # occlusion culling of back faces forced on (every scene, however small) against off
    keys = {}
    for name, min_work, on in (("culled", 0, True), ("plain", 0, False)):
        saved = raster_module.OCCLUSION_MIN_WORK, raster_module.OCCLUSION_CULLING
        raster_module.OCCLUSION_MIN_WORK, raster_module.OCCLUSION_CULLING = min_work, on
        try:
            keys[name] = raster_module.resolve_keys(clip.detach(), faces, res, cull, None,
                                                       16, 2**20, 320)[0].clone()
        finally:
            raster_module.OCCLUSION_MIN_WORK, raster_module.OCCLUSION_CULLING = saved
    c["occlusion_vs_plain"] += int((keys["culled"] != keys["plain"]).sum())
    return frags


def scene_soup(gen: torch.Generator, c: Counter, huge: bool) -> None:
    b = _randint(gen, 1, 4)
    weights = tuple(float(w) for w in torch.rand(6, generator=gen) + 0.05)
    clip, faces, _ = random_soup(gen, b, _randint(gen, 1, 150), weights=weights)
    scale = 1e8 if huge else 10 ** _rand(gen, -6, 8)
    dtype = torch.float64 if torch.rand(1, generator=gen).item() < 0.2 else torch.float32
    cull = torch.rand(1, generator=gen).item() < 0.5
    _check_numerics((clip * scale).to(dtype), faces, _resolution(gen), cull, gen, c)


def scene_near_far(gen: torch.Generator, c: Counter) -> None:
    near = 10 ** _rand(gen, -6, -1)
    far = math.inf if torch.rand(1, generator=gen).item() < 0.3 else 10 ** _rand(gen, 2, 9)
    reverse = torch.rand(1, generator=gen).item() < 0.5
    b, n = _randint(gen, 1, 3), _randint(gen, 1, 100)
    lo, hi = math.log10(near) - 1, math.log10(min(far, 1e10)) + 1  # log-uniform distances
    dist = 10 ** (lo + (hi - lo) * torch.rand(b, n, 1, 1, generator=gen, dtype=torch.float64))
    tri = (torch.randn(b, n, 3, 3, generator=gen, dtype=torch.float64) * _rand(gen, 0.01, 1.0)
           + torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)) * dist
    proj = tr.camera.perspective(_rand(gen, 10, 120), _rand(gen, 0.5, 2), near, far,
                                 reverse_z=reverse)
    clip = tr.camera.transform_points(tri.view(b, 3 * n, 3).float(), proj)
    faces = torch.arange(3 * n).view(n, 3)
    _check_numerics(clip, faces, _resolution(gen), torch.rand(1, generator=gen).item() < 0.5,
                    gen, c)


def _holes(face_id: torch.Tensor) -> int:
    cov = face_id >= 0
    nb = cov[:, :-2, 1:-1] & cov[:, 2:, 1:-1] & cov[:, 1:-1, :-2] & cov[:, 1:-1, 2:]
    return int((~cov[:, 1:-1, 1:-1] & nb).sum())


def scene_closed(gen: torch.Generator, c: Counter) -> None:
    if torch.rand(1, generator=gen).item() < 0.5:
        mesh = trimesh.creation.icosphere(subdivisions=_randint(gen, 0, 4))
    else:
        pts = torch.randn(_randint(gen, 8, 400), 3, generator=gen, dtype=torch.float64)
        mesh = trimesh.convex.convex_hull(pts.numpy())
    verts = torch.as_tensor(mesh.vertices, dtype=torch.float64)
    faces = torch.as_tensor(mesh.faces, dtype=torch.int64)
    verts = verts / verts.norm(dim=-1).max()
    b = _randint(gen, 1, 3)
    clips = []
    inside = torch.rand(1, generator=gen).item() < 0.15
    for _ in range(b):
        d = torch.randn(3, generator=gen, dtype=torch.float64)
        eye = d / d.norm() * (_rand(gen, 0.0, 0.2) if inside else 10 ** _rand(gen, 0.1, 2.5))
        target = eye + torch.randn(3, generator=gen, dtype=torch.float64) if inside else 0 * eye
        up = torch.randn(3, generator=gen, dtype=torch.float64)
        near = 1e-3 if inside else 10 ** _rand(gen, -4, -1)
        mat = perspective_matrix(_rand(gen, 5, 100), 1.0, near, 1e4) @ look_at_matrix(
            eye, target, up)
        clips.append(to_clip(verts, mat))
    clip = torch.stack(clips).float()
    cull = (not inside) and torch.rand(1, generator=gen).item() < 0.5
    frags = _check_numerics(clip, faces, _resolution(gen), cull, gen, c)
    c["cracks"] += _holes(frags.face_id)


def _grid_mesh(gen: torch.Generator, res: tuple[int, int], exact: bool):
    """A triangulated lattice: exact (vertices on pixel centres, power-of-two w) or jittered
    with random positive w. Returns clip (1,V,4) float32, faces (F,3), interior mask (H,W)
    or None (exact: pixels strictly inside the lattice box)."""
    h, w = res
    step = _randint(gen, 1, 4)
    rows = torch.arange(_randint(gen, 0, 2), h, step)
    cols = torch.arange(_randint(gen, 0, 2), w, step)
    rows, cols = rows[: _randint(gen, 2, 12)], cols[: _randint(gen, 2, 12)]
    if len(rows) < 2 or len(cols) < 2:
        return None
    ii, jj = torch.meshgrid(rows.double(), cols.double(), indexing="ij")
    if not exact:
        ii = ii + 0.35 * step * (torch.rand(ii.shape, generator=gen, dtype=torch.float64) - 0.5)
        jj = jj + 0.35 * step * (torch.rand(jj.shape, generator=gen, dtype=torch.float64) - 0.5)
    x = (2 * (jj + 0.5) / w - 1).reshape(-1)
    y = (1 - 2 * (ii + 0.5) / h).reshape(-1)
    n = x.numel()
    if exact:
        wv = 2.0 ** torch.randint(-3, 4, (n,), generator=gen).double()
    else:
        wv = 10 ** (2 * torch.rand(n, generator=gen, dtype=torch.float64) - 1)
    z = (torch.rand(n, generator=gen, dtype=torch.float64) - 0.5) * wv
    clip = torch.stack([x * wv, y * wv, z, wv], -1)[None].float()
    nr, nc = len(rows), len(cols)
    faces = []
    for r in range(nr - 1):
        for q in range(nc - 1):
            a, b2, d, e = r * nc + q, r * nc + q + 1, (r + 1) * nc + q, (r + 1) * nc + q + 1
            flip = torch.rand(1, generator=gen).item() < 0.5
            faces += [[a, d, e], [a, e, b2]] if flip else [[a, d, b2], [b2, d, e]]
    faces = torch.tensor(faces)
    if torch.rand(1, generator=gen).item() < 0.5:
        faces = faces[:, [0, 2, 1]]  # back facing
    interior = None
    if exact:
        interior = torch.zeros(h, w, dtype=torch.bool)
        interior[int(rows[0]) + 1 : int(rows[-1]), int(cols[0]) + 1 : int(cols[-1])] = True
    return clip, faces, interior


def scene_grid(gen: torch.Generator, c: Counter) -> None:
    exact = torch.rand(1, generator=gen).item() < 0.5
    if exact:  # power-of-two sizes: pixel centres and vertices are exact dyadic numbers
        res = (2 ** _randint(gen, 2, 6), 2 ** _randint(gen, 2, 6))
    else:
        res = (_randint(gen, 4, 64), _randint(gen, 4, 64))
    mesh = _grid_mesh(gen, res, exact)
    if mesh is None:
        return
    clip, faces, interior = mesh
    nf = faces.shape[0]
    ranges = torch.stack([torch.arange(nf), torch.arange(nf) + 1], -1)
    alone = tr.rasterize(clip.expand(nf, -1, -1), faces, resolution=res, face_ranges=ranges)
    counts = (alone.face_id >= 0).sum(0)
    whole = tr.rasterize(clip, faces, resolution=res).face_id[0]
    c["grid_pixels"] += counts.numel()
    c["double_hits"] += int((counts > 1).sum())
    c["whole_vs_alone"] += int(((whole >= 0) != (counts == 1)).sum())
    if interior is None:  # jittered: inside the float64 union (away from its outline)
        ref = reference_coverage_count(clip.double(), faces, res)[0]
        cov = ref >= 1
        nb = torch.zeros_like(cov)
        nb[1:-1, 1:-1] = cov[:-2, 1:-1] & cov[2:, 1:-1] & cov[1:-1, :-2] & cov[1:-1, 2:]
        interior = cov & nb
    c["cracks"] += int((counts[interior] == 0).sum())


def raster_scene(gen: torch.Generator, kind: str, c: Counter) -> None:
    """One random rasterizer scene of ``kind`` (see the module docstring)."""
    if kind in ("soup", "huge"):
        scene_soup(gen, c, huge=kind == "huge")
    elif kind == "near_far":
        scene_near_far(gen, c)
    elif kind == "closed":
        scene_closed(gen, c)
    else:
        scene_grid(gen, c)


def run_scenes(n: int, seed: int, kinds: tuple[str, ...],
               scene: Callable[[torch.Generator, str, Counter], None],
               rejections: tuple[type[Exception], ...] = (), label: str = "scenes",
               every: int = 100) -> tuple[dict[str, Counter], float]:
    """Run ``n`` random scenes, the kinds in turn; count per kind. An exception of a type in
    ``rejections`` is counted as "rejected", any other as a finding ("exceptions")."""
    gen = torch.Generator().manual_seed(seed)
    counts = {k: Counter() for k in kinds}
    start = time.perf_counter()
    for i in range(n):
        kind = kinds[i % len(kinds)]
        c = counts[kind]
        c["scenes"] += 1
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                scene(gen, kind, c)
        except rejections as exc:
            c["rejected"] += 1
            print(f"{label} {i} ({kind}) rejected: {type(exc).__name__}: {exc}", file=sys.stderr)
        except Exception as exc:  # noqa: BLE001 - every other exception is a finding
            c["exceptions"] += 1
            print(f"{label} {i} ({kind}): {type(exc).__name__}: {exc}", file=sys.stderr)
        if (i + 1) % every == 0:
            print(f"{i + 1}/{n} {label}, {time.perf_counter() - start:.0f} s", file=sys.stderr)
    return counts, time.perf_counter() - start

COLUMNS = [
    ("scenes", "scenes"), ("pixels", "pixels"), ("covered", "covered"),
    ("nonfinite_bary", "NaN/Inf bary"), ("nonfinite_depth", "NaN/Inf depth"),
    ("depth_out_of_range", "abs(depth) > 1"), ("bad_empty", "empty depth != +inf"),
    ("nonfinite_image", "NaN/Inf image"), ("nonfinite_grad_clip", "NaN/Inf grad clip_pos"),
    ("nonfinite_grad_attrs", "NaN/Inf grad attrs"), ("cracks", "cracks (px)"),
    ("grid_pixels", "grid pixels"), ("double_hits", "double hits (px)"),
    ("whole_vs_alone", "whole != alone (px)"), ("bands_vs_whole", "depth in bands != whole (px)"),
    ("occlusion_vs_plain", "culled != plain (px)"), ("exceptions", "exceptions"),
]
PROBLEMS = {"nonfinite_bary", "nonfinite_depth", "depth_out_of_range", "bad_empty",
            "nonfinite_image", "nonfinite_grad_clip", "nonfinite_grad_attrs", "cracks",
            "double_hits", "whole_vs_alone", "bands_vs_whole", "occlusion_vs_plain",
            "exceptions"}


def picture(path: Path) -> None:
    """Engine vs reference face ids for spot (random colours per face) and their difference
    (red: pixels whose face differs; grey: covered in the reference)."""
    import numpy as np
    from PIL import Image, ImageDraw

    from torchraster.testing.reference_raster import (
        compare_fragments,
        load_mesh,
        reference_rasterize,
    )

    data = ROOT / "torchraster" / "assets" / "spot" / "spot_triangulated.obj"
    verts, faces = load_mesh(str(data))
    gen = torch.Generator().manual_seed(3)
    eye = torch.tensor([1.5, 0.7, 2.0], dtype=torch.float64)
    mat = perspective_matrix(40.0, 1.0, 0.1, 100.0) @ look_at_matrix(
        eye, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 1.0, 0.0]))
    clip = to_clip(verts, mat)[None].float()
    res = (240, 240)
    frags = tr.rasterize(clip, faces, resolution=res)
    ref = reference_rasterize(clip.double(), faces, res)
    stats = compare_fragments(frags.face_id, frags.bary, frags.depth, clip, faces, ref)
    palette = torch.rand(faces.shape[0] + 1, 3, generator=gen) * 0.75 + 0.25
    palette[-1] = 0.0  # empty -> black (index -1)

    def colour(fid: torch.Tensor) -> np.ndarray:
        return (palette[fid[0]].numpy() * 255).astype(np.uint8)

    diff = (frags.face_id[0] != ref.face_id[0]).numpy()
    dimg = np.zeros((*res, 3), dtype=np.uint8)
    dimg[(ref.face_id[0] >= 0).numpy()] = 40
    dimg[diff] = (255, 40, 40)
    gap = np.full((res[0], 6, 3), 255, dtype=np.uint8)
    img = Image.fromarray(np.concatenate([colour(frags.face_id), gap, colour(ref.face_id), gap,
                                          dimg], 1))
    draw = ImageDraw.Draw(img)
    step = res[1] + 6
    draw.text((4, 4), "engine face_id (float32)", fill=(255, 255, 255))
    draw.text((step + 4, 4), "reference face_id (float64)", fill=(255, 255, 255))
    draw.text((2 * step + 4, 4), f"differ: {stats['disagree']} of {stats['covered']} px",
              fill=(255, 255, 255))
    img.save(path, optimize=True)
    print(f"{path}: {stats['disagree']} of {stats['pixels']} pixels differ "
          f"({stats['near_edge']} within 1e-4 px of an edge, {stats['depth_tie']} on a depth tie "
          f"(shared edge), {stats['unexplained']} unexplained)")


# ------------------------------------------------------------------------------- renderer
R_KINDS = ("material", "light", "environment", "grazing", "labels", "motion", "half", "far")
#: Hostile magnitudes: zero, a float32 denormal, tiny, one, huge.
HOSTILE = (0.0, 1e-40, 1e-6, 1.0, 1e6)
R_COLUMNS = [
    ("scenes", "scenes"), ("covered", "covered px"), ("nonfinite_image", "NaN/Inf image"),
    ("nonfinite_alpha", "NaN/Inf alpha"), ("nonfinite_gbuffer", "NaN/Inf G-buffer"),
    ("nonfinite_grad_positions", "NaN/Inf grad positions"),
    ("nonfinite_grad_material", "NaN/Inf grad material"),
    ("nonfinite_grad_lights", "NaN/Inf grad lights"),
    ("nonfinite_grad_environment", "NaN/Inf grad environment"),
    ("grad_values", "gradient values checked"), ("label_errors", "label errors"),
    ("motion_errors", "motion errors"), ("far_errors", "far-away errors"),
    ("nograd_differs", "no-grad render differs"),
    ("packed", "packed surface compared"), ("area_lit", "area-lit scenes"),
    ("area_fog", "area-lit fog scenes"),
    ("packed_differs", "packed surface differs from frames"),
    ("motion_f16_overflow", "float16 flow grad overflow (known, not counted)"),
    ("rejected", "rejected (ValueError/TypeError)"), ("exceptions", "exceptions"),
]
R_PROBLEMS = {key for key, _ in R_COLUMNS} - {"scenes", "covered", "grad_values", "rejected",
                                               "motion_f16_overflow", "packed", "area_lit",
                                               "area_fog"}


def _pick(gen: torch.Generator, options: tuple | list):
    return options[_randint(gen, 0, len(options) - 1)]


def _chance(gen: torch.Generator, p: float) -> bool:
    return torch.rand(1, generator=gen).item() < p


def _hostile(gen: torch.Generator, shape: tuple[int, ...], hi: float | None = None,
             dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """A tensor of hostile magnitudes (each entry drawn from HOSTILE, capped at ``hi``)."""
    values = torch.tensor([v for v in HOSTILE if hi is None or v <= hi], dtype=torch.float64)
    idx = torch.randint(0, len(values), shape, generator=gen)
    return values[idx].to(dtype)


def _stage(gen: torch.Generator, dtype: torch.dtype):
    """Ground plane (4x4 quads, y = 0, material 0), a unit-diameter icosphere resting on it
    (material 1) and one zero-area triangle; positions, faces, uvs, face_material."""
    n = 4
    t = torch.linspace(-2.0, 2.0, n + 1, dtype=torch.float64)
    z, x = torch.meshgrid(t, t, indexing="ij")
    plane = torch.stack([x, torch.zeros_like(x), z], -1).view(-1, 3)
    i = torch.arange(n)
    c = (i[:, None] * (n + 1) + i[None, :]).reshape(-1)
    quads = torch.stack([c, c + n + 1, c + n + 2, c + 1], -1)  # counter-clockwise seen from +y
    plane_faces = torch.cat([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    sphere = trimesh.creation.icosphere(subdivisions=_randint(gen, 1, 2), radius=0.5)
    sv = torch.as_tensor(sphere.vertices, dtype=torch.float64) + torch.tensor([0.0, 0.5, 0.0])
    sf = torch.as_tensor(sphere.faces, dtype=torch.int64) + len(plane)
    degenerate = torch.tensor([[0, 1, 1]]) if _chance(gen, 0.5) else torch.zeros(0, 3).long()
    positions = torch.cat([plane, sv]).to(dtype)
    faces = torch.cat([plane_faces, sf, degenerate])
    uvs = (positions[:, [0, 2]] / 4 + 0.5).contiguous()
    face_material = torch.cat([torch.zeros(len(plane_faces), dtype=torch.long),
                               torch.ones(len(sf), dtype=torch.long),
                               torch.zeros(len(degenerate), dtype=torch.long)])
    return positions, faces, uvs, face_material


def _identity(positions: torch.Tensor, faces: torch.Tensor, face_material: torch.Tensor):
    """Object identity of the stage: the plane is object 1, the sphere 2, the zero-area
    triangle (if any) 3; categories 1, 2, 1; NOCS of each object's own vertices."""
    n_plane, n_sphere = 2 * 4 * 4, int((face_material == 1).sum())  # _stage's layout
    face_object = torch.cat([torch.full((n_plane,), 1), torch.full((n_sphere,), 2),
                             torch.full((faces.shape[0] - n_plane - n_sphere,), 3)])
    split = 25  # the plane's (n + 1)**2 vertices come first
    coords = torch.cat([tr.scene.nocs_coords(positions[:split].detach()),
                        tr.scene.nocs_coords(positions[split:].detach())])
    return face_object, torch.tensor([0, 1, 2, 1]), coords


def _material(gen: torch.Generator, hostile: bool, params: list[torch.Tensor]) -> tr.Material:
    """A material; hostile: factors and float textures from HOSTILE (within their ranges)."""
    if not hostile:
        return tr.Material(base_color_factor=torch.tensor([0.8, 0.6, 0.4, 1.0]),
                           metallic_factor=0.0, roughness_factor=0.5)
    base = torch.cat([_hostile(gen, (3,), 1.0), torch.ones(1)]).requires_grad_(True)
    metallic = torch.tensor(_pick(gen, (0.0, 1e-40, 0.5, 1.0))).requires_grad_(True)
    rough = torch.tensor(_pick(gen, (0.0, 0.0, 1e-40, 1e-6, 0.5, 1.0))).requires_grad_(True)
    emissive = _hostile(gen, (3,)).requires_grad_(True)
    params += [base, metallic, rough, emissive]
    tex: dict[str, torch.Tensor] = {}
    for slot in ("base_color_texture", "metallic_roughness_texture", "occlusion_texture",
                 "emissive_texture"):
        if _chance(gen, 0.3):
            size = _pick(gen, (1, 2, 4, 8))
            tex[slot] = _hostile(gen, (3, size, size), 1.0).requires_grad_(True)
    if _chance(gen, 0.3):  # tangent-space normals: inward, zero-length (0.5 texels), random
        size = _pick(gen, (1, 2, 4))
        nt = _pick(gen, (torch.tensor([0.5, 0.5, 0.0]), torch.tensor([0.5, 0.5, 0.5]),
                         torch.rand(3, generator=gen)))
        tex["normal_texture"] = nt.view(3, 1, 1).expand(3, size, size).clone().requires_grad_()
    params += list(tex.values())
    return tr.Material(base_color_factor=base, metallic_factor=metallic, roughness_factor=rough,
                       emissive_factor=emissive, double_sided=_chance(gen, 0.5), **tex)


def _lights(gen: torch.Generator, hostile: bool, positions: torch.Tensor,
            params: list[torch.Tensor]) -> tr.Lights:
    """Sun + ambient (benign) or hostile directional, point, spot and ambient lights."""
    dtype = positions.dtype
    if not hostile:
        d = torch.tensor([[[-0.3, -1.0, -0.2]]], dtype=dtype)
        return tr.Lights(ambient=tr.sh_from_color(torch.full((1, 3), 0.1, dtype=dtype)),
                         directional=tr.DirectionalLights(d, torch.ones(1, 1, 3, dtype=dtype),
                                                          torch.full((1, 1), 3.0, dtype=dtype)))

    def leaf(t: torch.Tensor) -> torch.Tensor:
        t = t.to(dtype).requires_grad_(True)
        params.append(t)
        return t

    def directions(n: int) -> torch.Tensor:
        options = [torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, -1.0, 0.0]),
                   torch.tensor([0.0, 1.0, 0.0]), torch.tensor([0.3, -1e-7, 0.9])]
        out = []
        for _ in range(n):
            d = _pick(gen, options) if _chance(gen, 0.7) else torch.randn(3, generator=gen)
            out.append(d * _pick(gen, (1.0, 1e-15, 1e6)))  # any non-zero length
        return torch.stack(out)[None]

    def places(n: int) -> torch.Tensor:
        out = []
        for _ in range(n):
            kind = _randint(gen, 0, 3)
            if kind == 0:  # exactly on a vertex
                out.append(positions[_randint(gen, 0, len(positions) - 1)].detach().double())
            elif kind == 1:  # inside the sphere
                out.append(torch.tensor([0.0, 0.5, 0.0], dtype=torch.float64))
            elif kind == 2:  # 1e-20 off a vertex
                out.append(positions[0].detach().double() + 1e-20)
            else:
                out.append(torch.randn(3, generator=gen, dtype=torch.float64)
                           * _pick(gen, (1.0, 1e6)))
        return torch.stack(out)[None]

    ambient = directional = point = spot = None
    if _chance(gen, 0.6):
        ambient = tr.sh_from_color(leaf(_hostile(gen, (1, 3))))
    if _chance(gen, 0.7):
        n = _randint(gen, 1, 3)
        directional = tr.DirectionalLights(leaf(directions(n)), leaf(_hostile(gen, (1, n, 3))),
                                           leaf(_hostile(gen, (1, n))))
    if _chance(gen, 0.7):
        n = _randint(gen, 1, 3)
        point = tr.PointLights(leaf(places(n)), leaf(_hostile(gen, (1, n, 3))),
                               leaf(_hostile(gen, (1, n))),
                               range=torch.tensor([[_pick(gen, (math.inf, 1e-6, 1.0, 1e6))
                                                    for _ in range(n)]], dtype=dtype))
    if _chance(gen, 0.7):
        n = _randint(gen, 1, 3)
        cones = [_pick(gen, ((0.0, 0.0), (0.0, 1e-7), (math.pi / 2, math.pi / 2),
                             (0.0, math.pi / 2), (0.3, 0.3))) for _ in range(n)]
        spot = tr.SpotLights(leaf(places(n)), leaf(directions(n)), leaf(_hostile(gen, (1, n, 3))),
                             leaf(_hostile(gen, (1, n))),
                             range=torch.tensor([[_pick(gen, (math.inf, 1e-6, 1.0))
                                                  for _ in range(n)]], dtype=dtype),
                             inner_cone_angle=torch.tensor([[c[0] for c in cones]], dtype=dtype),
                             outer_cone_angle=torch.tensor([[c[1] for c in cones]], dtype=dtype))
    area = _area_lights(gen, places, leaf, dtype) if _chance(gen, 0.5) else None
    return tr.Lights(ambient=ambient, directional=directional, point=point, spot=spot,
                     area=area)


def _area_lights(gen: torch.Generator, places, leaf, dtype: torch.dtype) -> tr.AreaLights:
    """1-3 hostile area lights: rectangles and discs at the hostile places, half-extents of
    1e-6 to 1e3 m (a sliver sometimes), one- or two-sided, casting shadows or not."""
    n = _randint(gen, 1, 3)
    u, v = [], []
    for _ in range(n):
        a = torch.randn(3, generator=gen, dtype=torch.float64)
        b = torch.linalg.cross(a, torch.randn(3, generator=gen, dtype=torch.float64))
        u.append(a / a.norm() * _pick(gen, (1e-6, 0.3, 1.0, 1e3)))
        v.append(b / b.norm() * _pick(gen, (1e-6, 0.3, 1.0)))
    flags = [[_chance(gen, 0.5) for _ in range(n)] for _ in range(3)]
    return tr.AreaLights(leaf(places(n)), leaf(torch.stack(u)[None]), leaf(torch.stack(v)[None]),
                         leaf(_hostile(gen, (1, n, 3))), leaf(_hostile(gen, (1, n))),
                         disc=torch.tensor([flags[0]]), two_sided=torch.tensor([flags[1]]),
                         cast_shadows=torch.tensor([flags[2]]))


def _environment(gen: torch.Generator, dtype: torch.dtype, params: list[torch.Tensor]):
    """A hostile lat-long map: 1-32 rows of zeros, denormals, one 1e6 texel or a mix."""
    he = _pick(gen, (1, 2, 8, 32))
    fill = _randint(gen, 0, 3)
    if fill == 0:
        rad = torch.zeros(3, he, 2 * he)
    elif fill == 1:
        rad = torch.full((3, he, 2 * he), 1e-40)
    elif fill == 2:
        rad = torch.zeros(3, he, 2 * he)
        rad[:, _randint(gen, 0, he - 1), _randint(gen, 0, 2 * he - 1)] = 1e6
    else:
        rad = _hostile(gen, (3, he, 2 * he))
    rad = rad.to(dtype).requires_grad_(True)
    params.append(rad)
    return tr.Environment(rad, intensity=_pick(gen, (0.0, 1e-40, 1.0, 1e6)),
                          yaw=_rand(gen, -4.0, 4.0), diffuse=_pick(gen, ("map", "sh")),
                          specular_size=_pick(gen, (4, 16)), specular_levels=_randint(gen, 2, 5),
                          specular_samples=_pick(gen, (1, 8)),
                          specular=_pick(gen, ("split_sum", "fitted", "table", "importance")),
                          importance_samples=_pick(gen, (1, 4)),
                          table_levels=_pick(gen, (2, 3)), table_views=_pick(gen, (2, 3)),
                          table_azimuths=_pick(gen, (2, 4)),
                          sun_threshold=_pick(gen, (None, None, 0.5, 10.0)))


def _nonfinite(t: torch.Tensor | None) -> int:
    if t is None or not t.is_floating_point():
        return 0
    return int((~torch.isfinite(t)).sum())

def _random_views(gen: torch.Generator, b: int, dtype: torch.dtype
                  ) -> tuple[torch.Tensor, torch.Tensor, tuple[int, int]]:
    """b orbit views of the stage and one random perspective of a random small frame."""
    view = tr.camera.orbit(torch.tensor([_rand(gen, 0.0, 360.0) for _ in range(b)]),
                           torch.tensor([_rand(gen, -20.0, 70.0) for _ in range(b)]),
                           torch.tensor([_rand(gen, 1.5, 6.0) for _ in range(b)]),
                           torch.tensor([0.0, 0.3, 0.0])).to(dtype)
    res = (_randint(gen, 4, 32), _randint(gen, 4, 32))
    proj = tr.camera.perspective(_rand(gen, 20.0, 90.0), res[1] / res[0], 0.01).to(dtype)
    return view, proj, res


#: Channels that need no other frame.
SURFACE_CHANNELS = ("position", "normal", "albedo", "metallic", "roughness")
ONE_FRAME_CHANNELS = tuple(ch for ch in tr.CHANNELS if not ch.startswith("flow")
                           and ch != "motion")

#: Knobs of the chunked paths and their values in the "small chunks" scenes (a few pixels,
#: receivers or rows each).
SMALL_CHUNKS = ((lighting, "PIXEL_LIGHT_CHUNK", 16), (lighting, "MODEL_BAND_ELEMENTS", 16),
                (shadows, "TAP_CHUNK_ELEMENTS", 512), (ibl, "IBL_PIXEL_CHUNK", 16),
                (importlib.import_module("torchraster.post.ssao"), "SSAO_BAND_ELEMENTS", 16),
                (volumetric, "FOG_BAND_PIXELS", 16))


@contextlib.contextmanager
def _small_chunks(on: bool):
    """Within the block, the chunked paths run in :data:`SMALL_CHUNKS` when ``on``."""
    saved = [getattr(mod, name) for mod, name, _ in SMALL_CHUNKS]
    if on:
        for mod, name, value in SMALL_CHUNKS:
            setattr(mod, name, value)
    try:
        yield
    finally:
        for (mod, name, _), value in zip(SMALL_CHUNKS, saved, strict=True):
            setattr(mod, name, value)


def scene_renderer(gen: torch.Generator, kind: str, c: Counter) -> None:
    """One hostile render forward and backward (see the module docstring for the kinds)."""
    if kind == "half":
        return scene_half(gen, c)
    if kind == "far":
        return scene_far(gen, c)
    wild = kind == "grazing"
    dtype = torch.float64 if wild and _chance(gen, 0.25) else torch.float32
    positions, faces, uvs, face_material = _stage(gen, dtype)
    positions = positions.requires_grad_(True)
    groups: dict[str, list[torch.Tensor]] = {"material": [], "lights": [], "environment": []}
    hostile_mat = kind == "material" or (wild and _chance(gen, 0.7))
    materials = [_material(gen, hostile_mat, groups["material"]) for _ in range(2)]
    hostile_light = kind == "light" or (wild and _chance(gen, 0.7))
    lights = _lights(gen, hostile_light, positions, groups["lights"])
    env = None
    if kind == "environment" or (wild and _chance(gen, 0.5)):
        env = _environment(gen, dtype, groups["environment"])
    tangents = None
    if any(m.normal_texture is not None for m in materials):
        tangents = vertex_tangents(positions, uvs, vertex_normals(positions, faces), faces)
    face_object, category, coords = _identity(positions, faces, face_material)
    scene = tr.RenderScene(positions, faces, uvs=uvs, tangents=tangents,
                           face_material=face_material, materials=materials,
                           face_object=face_object, object_category=category,
                           object_coords=coords)
    if kind == "labels":
        return scene_labels(gen, scene, c)
    if kind == "motion":
        return scene_motion(gen, scene, c)
    b = _randint(gen, 1, 2)
    if wild:
        elevation = torch.tensor([_pick(gen, (0.0, 1e-4, -20.0, 30.0)) for _ in range(b)])
    else:
        elevation = torch.tensor([_rand(gen, -10.0, 60.0) for _ in range(b)])
    view = tr.camera.orbit(torch.tensor([_rand(gen, 0.0, 360.0) for _ in range(b)]), elevation,
                           torch.tensor([_rand(gen, 1.5, 6.0) for _ in range(b)]),
                           torch.tensor([0.0, 0.3, 0.0])).to(dtype)
    res = (_randint(gen, 8, 40), _randint(gen, 8, 40))
    proj = tr.camera.perspective(_rand(gen, 20.0, 90.0), res[1] / res[0], 0.01).to(dtype)
    ssao = tr.post.SSAO() if wild and _chance(gen, 0.2) else None
    shading = "pbr" if not wild or _chance(gen, 0.6) else _pick(gen, (
        "blinn_phong", "half_lambert", "toon", "headlight", "unlit"))
    # the optional passes: screen-space reflections, fog with light shafts, dissolve
    ssr = tr.post.SSR(max_steps=_randint(gen, 4, 32)) if _chance(gen, 0.15) and (
        env is None or env.sun_threshold is None) else None  # SSR refuses an extracted sun
    fog = tr.Fog(density=_pick(gen, (0.0, 1e-3, 0.3, 50.0)), height_falloff=_pick(
        gen, (0.0, 1e-6, 0.5, 20.0)), steps=_randint(gen, 1, 8),
        light_transmittance=_chance(gen, 0.8)) if _chance(
        gen, 0.15 if lights.area is None else 0.4) else None  # area lights in fog more often
    dissolve = tr.Dissolve(threshold=_pick(gen, (0.0, 0.3, 1.0))) if _chance(gen, 0.1) else None
    supersample = _pick(gen, (1, 2)) if wild else 1
    # edge antialiasing where it is implemented (opaque materials, none of the passes below)
    edge = _pick(gen, (2, 3)) if _chance(gen, 0.3) and supersample == 1 and all(
        x is None for x in (ssao, ssr, fog, dissolve)) and all(
        m.alpha_mode == "OPAQUE" for m in materials) else 1
    raster = tr.RasterSettings(supersample=supersample, edge_supersample=edge,
                               cull_backfaces=_chance(gen, 0.3))
    textures = tr.TextureSettings(
        filter=_pick(gen, ("trilinear", "bilinear", "nearest", "anisotropic")))
    multiscatter = _chance(gen, 0.8)
    renderer = tr.Renderer(
        res, shading=tr.ShadingSettings(shading, multiscatter=multiscatter or shading != "pbr"),
        raster=raster, textures=textures, ssao=ssao, ssr=ssr, fog=fog, dissolve=dissolve,
        background=tr.BackgroundSettings(environment=_chance(gen, 0.5)))
    # every channel of one frame (the flow channels need another: the motion kind draws
    # them), or half of the time only label channels, so that the surface channels only the
    # lighting reads stay packed (plan.packed) where the plan allows
    channels = ONE_FRAME_CHANNELS if _chance(gen, 0.5) else tuple(
        ch for ch in ONE_FRAME_CHANNELS if ch not in SURFACE_CHANNELS and _chance(gen, 0.5))
    # a third of the scenes light in small chunks (pixel chunks recomputed in backward, row
    # bands of the other models, shadow-lookup and IBL chunks: what a large frame does;
    # these frames are too small to be chunked otherwise)
    small = _chance(gen, 0.33)
    with _small_chunks(small):
        out = renderer(scene, view, proj, lights, env, channels=channels)
    c["covered"] += int((out.alpha > 0).sum())
    c["area_lit"] += int(any(kind == "area" for kind, _ in out.plan.lights))
    c["area_fog"] += int(any(s.startswith("fog march") and "area" in s for s in out.plan.steps))
    c["nonfinite_image"] += _nonfinite(out.image)
    c["nonfinite_alpha"] += _nonfinite(out.alpha)
    c["nonfinite_gbuffer"] += sum(_nonfinite(v) for v in out.gbuffer.values())
    if _chance(gen, 0.25):  # the no-grad path: frames finished in place, fragments released
        with torch.no_grad():
            again = renderer(scene, view, proj, lights, env, channels=channels)
        c["nonfinite_image"] += _nonfinite(again.image)
        c["nograd_differs"] += int(not torch.allclose(again.image, out.image.detach(),
                                                      rtol=1e-3, atol=1e-5, equal_nan=True))
    if out.plan.packed and _chance(gen, 0.5):  # packed surface = the frames' (requested),
        with _small_chunks(small):  # bit for bit, in the same chunks (area lights' atan2
            # rounds 1 ulp apart in vectorised loops and their remainders)
            framed = renderer(scene, view, proj, lights, env,
                              channels=ONE_FRAME_CHANNELS).image.detach()
        c["packed_differs"] += int(not torch.allclose(framed, out.image.detach(), rtol=0,
                                                      atol=0, equal_nan=True))
        c["packed"] += 1
    loss = (out.image * torch.randn(out.image.shape, generator=gen, dtype=dtype)).sum()
    for v in out.gbuffer.values():
        if v.is_floating_point() and v.requires_grad:
            loss = loss + (v * torch.randn(v.shape, generator=gen, dtype=v.dtype)).sum()
    leaves = [positions] + [t for ts in groups.values() for t in ts]
    grads = torch.autograd.grad(loss, leaves, allow_unused=True) if loss.requires_grad else (
        [None] * len(leaves))
    c["grad_values"] += sum(g.numel() for g in grads if g is not None)
    c["nonfinite_grad_positions"] += _nonfinite(grads[0])
    k = 1
    for name, ts in groups.items():
        c[f"nonfinite_grad_{name}"] += sum(_nonfinite(g) for g in grads[k:k + len(ts)])
        k += len(ts)

def scene_half(gen: torch.Generator, c: Counter) -> None:
    """The stage in float16 or bfloat16 (positions, UVs, float textures up to 300 texels,
    lights, cameras), a sun and a spot light casting shadows (random filter), random
    texture filter and antialiasing; forward and backward, NaN/Inf counted."""
    dtype = _pick(gen, (torch.float16, torch.bfloat16))
    positions, faces, uvs, face_material = _stage(gen, dtype)
    positions = positions.requires_grad_(True)
    size = _pick(gen, (4, 64, 300))
    textures = [torch.rand(3, size, size, generator=gen).to(dtype).requires_grad_(True)
                for _ in range(2)]
    materials = [tr.Material(base_color_texture=t, roughness_factor=_rand(gen, 0.0, 1.0),
                             metallic_factor=_pick(gen, (0.0, 1.0))) for t in textures]
    sun = torch.tensor([[[_rand(gen, -0.5, 0.5), -1.0, _rand(gen, -0.5, 0.5)]]])
    if _chance(gen, 0.3):
        sun = torch.tensor([[[0.0, -1.0, 0.0]]])  # straight down onto the floor
    sun = sun.to(dtype).requires_grad_(True)
    spot_pos = torch.tensor([[[_rand(gen, -1.0, 1.0), 2.5, _rand(gen, -1.0, 1.0)]]], dtype=dtype)
    lights = tr.Lights(
        ambient=tr.sh_from_color(torch.full((1, 3), 0.1, dtype=dtype)),
        directional=tr.DirectionalLights(sun, torch.ones(1, 1, 3, dtype=dtype),
                                         torch.full((1, 1), 3.0, dtype=dtype),
                                         cast_shadows=torch.tensor([[True]])),
        spot=tr.SpotLights(spot_pos, torch.tensor([[[0.0, -1.0, 0.0]]], dtype=dtype),
                           torch.ones(1, 1, 3, dtype=dtype), torch.full((1, 1), 20.0,
                                                                        dtype=dtype),
                           cast_shadows=torch.tensor([[_chance(gen, 0.5)]])))
    if _chance(gen, 0.5):  # a panel or disc above the stage, maybe shadowed (PCSS)
        panel = torch.tensor([[[_rand(gen, -1.0, 1.0), 2.0, _rand(gen, -1.0, 1.0)]]])
        lights.area = tr.AreaLights(panel.to(dtype).requires_grad_(True),
                                    torch.tensor([[[0.6, 0.0, 0.0]]], dtype=dtype),
                                    torch.tensor([[[0.0, 0.0, 0.4]]], dtype=dtype),
                                    torch.ones(1, 1, 3, dtype=dtype),
                                    torch.full((1, 1), 8.0, dtype=dtype),
                                    disc=torch.tensor([[_chance(gen, 0.5)]]),
                                    cast_shadows=torch.tensor([[_chance(gen, 0.5)]]))
    scene = tr.RenderScene(positions, faces, uvs=uvs.to(dtype), face_material=face_material,
                           materials=materials)
    view = tr.camera.orbit(torch.tensor([_rand(gen, 0.0, 360.0)]),
                           torch.tensor([_rand(gen, 10.0, 60.0)]),
                           torch.tensor([_rand(gen, 2.0, 6.0)]),
                           torch.tensor([0.0, 0.3, 0.0])).to(dtype)
    res = (_randint(gen, 8, 40), _randint(gen, 8, 40))
    proj = tr.camera.perspective(_rand(gen, 20.0, 90.0), res[1] / res[0], 0.01).to(dtype)
    filt = _pick(gen, tr.shading.shadows.FILTERS)
    settings = tr.shading.shadows.ShadowSettings(  # pixel_radius: pcf / pcss only
        map_size=_pick(gen, (32, 128)), filter=filt,
        pixel_radius=_pick(gen, (0.0, 0.56, 8.0)) if filt in ("pcf", "pcss") else 0.0)
    antialias = _chance(gen, 0.5)
    raster = tr.RasterSettings(antialias=antialias,
                               edge_supersample=1 if antialias else _pick(gen, (1, 2, 3)))
    filtering = tr.TextureSettings(
        filter=_pick(gen, ("trilinear", "bilinear", "nearest", "anisotropic")))
    raster = dataclasses.replace(raster, max_batch=_pick(gen, (None, 1)))  # chunked batches too
    renderer = tr.Renderer(res, shadows=settings, raster=raster, textures=filtering)
    if renderer.raster_settings.max_batch is not None:  # two views, rendered one at a time
        view = torch.cat([view, view])
    env_params: list[torch.Tensor] = []  # half-precision surfaces under a float32 map (IBL
    env = _environment(gen, torch.float32, env_params) if _chance(gen, 0.4) else None
    out = renderer(scene, view, proj, lights, env)  # in float32 for them, every mode)
    c["covered"] += int((out.alpha > 0).sum())
    c["area_lit"] += int(lights.area is not None)
    c["nonfinite_image"] += _nonfinite(out.image)
    c["nonfinite_alpha"] += _nonfinite(out.alpha)
    loss = (out.image.float() * torch.randn(out.image.shape, generator=gen)).sum()
    panel = [lights.area.position] if lights.area is not None else []
    leaves = [positions, *textures, sun, *panel, *env_params]
    grads = torch.autograd.grad(loss, leaves, allow_unused=True)
    c["grad_values"] += sum(g.numel() for g in grads if g is not None)
    c["nonfinite_grad_positions"] += _nonfinite(grads[0])
    c["nonfinite_grad_material"] += sum(_nonfinite(g) for g in grads[1:3])
    c["nonfinite_grad_lights"] += sum(_nonfinite(g) for g in grads[3:4 + len(panel)])
    c["nonfinite_grad_environment"] += sum(_nonfinite(g) for g in grads[4 + len(panel):])


LABELS = ["instance", "semantic", "object_coords", "distance", "amodal", "face_id", "depth"]


def scene_labels(gen: torch.Generator, scene: tr.RenderScene, c: Counter) -> None:
    """The label channels of ``scene`` (the stage as three objects) forward and backward in
    a random dtype (half precision included), supersampling and batch; counts NaN/Inf and
    violated label invariants."""
    dtype = _pick(gen, (torch.float32, torch.float64, torch.float16, torch.bfloat16))
    positions = scene.positions.detach().to(dtype).requires_grad_(True)
    scene.positions = positions
    scene.object_coords = scene.object_coords.to(dtype)
    scene.uvs = scene.tangents = None
    if _chance(gen, 0.3):  # the sphere is a cut-out: labels of what is behind it
        scene.materials = [None, tr.Material(base_color_factor=torch.tensor(
            [1.0, 1.0, 1.0, _pick(gen, (0.0, 0.3, 1.0))]), alpha_mode="MASK")]
    else:
        scene.materials = [None, None]
    b = _randint(gen, 1, 2)
    if b == 2 and _chance(gen, 0.5):  # item 1 draws the sphere (and triangle) only
        n_plane = int((scene.face_object == 1).sum())
        scene.face_ranges = torch.tensor([[0, scene.faces.shape[0]],
                                          [n_plane, scene.faces.shape[0]]])
    view, proj, res = _random_views(gen, b, dtype)
    renderer = tr.Renderer(res, shading="unlit", raster=tr.RasterSettings(
        supersample=_randint(gen, 1, 3), cull_backfaces=_chance(gen, 0.3)))
    out = renderer(scene, view, proj, channels=LABELS)
    gb = out.gbuffer
    c["covered"] += int((gb["instance"] > 0).sum())
    c["nonfinite_image"] += _nonfinite(out.image)
    c["nonfinite_gbuffer"] += sum(_nonfinite(v) for v in gb.values())
    inst, empty = gb["instance"], gb["face_id"] < 0
    amodal = gb["amodal"]
    tol = 1e-2 if dtype in (torch.float16, torch.bfloat16) else 1e-5
    errors = int((inst < 0).sum() + (inst > 3).sum() + (empty != (inst == 0)).sum())
    errors += int((gb["semantic"] != scene.object_category[inst]).sum())
    visible = torch.nn.functional.one_hot(inst[:, 0], 4)[..., 1:].permute(0, 3, 1, 2).bool()
    errors += int((visible & ~amodal).sum())
    if renderer.raster_settings.supersample == 1:  # amodal = each object rasterized alone
        clip = _clip_positions(to_compute(positions.detach()), to_compute(view),
                               to_compute(proj), b)  # half precision renders in float32
        items = scene.face_ranges if scene.face_ranges is not None else torch.tensor(
            [[0, scene.faces.shape[0]]]).expand(b, 2)
        for k, (lo, hi) in enumerate(scene.object_face_ranges().tolist()):
            for i in range(b):
                fr = torch.tensor([[max(lo, int(items[i, 0])), min(hi, int(items[i, 1]))]])
                fr[:, 1] = fr[:, 1].clamp_min(fr[0, 0])
                alone = rasterize_coverage(clip[i:i + 1], scene.faces, res,
                                           renderer.raster_settings.cull_backfaces, fr)[0]
                errors += int((amodal[i, k] != alone).sum())
    nocs = gb["object_coords"].float()
    errors += int(((nocs < -tol) | (nocs > 1 + tol)).any(1, keepdim=True)[~empty].sum())
    errors += int(((nocs != 0).any(1, keepdim=True) & empty).sum())
    dist, depth = gb["distance"].float(), gb["depth"].float()
    errors += int(((dist != 0) & empty).sum())
    if renderer.raster_settings.supersample == 1:  # (depth is box-filtered when supersampled)
        errors += int((dist < depth * (1 - tol) - tol)[~empty].sum())
    c["label_errors"] += errors
    loss = sum((v.float() * torch.randn(v.shape, generator=gen)).sum()
               for k, v in gb.items() if v.is_floating_point() and v.requires_grad)
    grad = torch.autograd.grad(loss, positions, allow_unused=True)[0] if isinstance(
        loss, torch.Tensor) and loss.requires_grad else None
    c["grad_values"] += 0 if grad is None else grad.numel()
    c["nonfinite_grad_positions"] += _nonfinite(grad)


MOTION = ["flow_forward", "flow_forward_valid", "flow_backward", "flow_backward_valid",
          "motion", "mask"]


def _other_frame(gen: torch.Generator, positions: torch.Tensor, split: int, b: int,
                 proj: torch.Tensor) -> OtherFrame:
    """The stage at another frame: the sphere (vertices from ``split``) moved by a hostile
    offset, the camera orbiting, on a vertex, inside the sphere or looking away."""
    dtype = positions.dtype
    low = dtype in (torch.float16, torch.bfloat16)
    offset = (torch.randn(3, generator=gen) * _pick(gen, (0.0, 1e-6, 0.1, 1.0, 1e3 if low
                                                          else 1e6))).to(dtype)
    moved = torch.cat([positions[:split], positions[split:] + offset])
    kind = _randint(gen, 1, 3) if _chance(gen, 0.5) else 0
    if kind == 0:
        view = tr.camera.orbit(torch.tensor([_rand(gen, 0.0, 360.0) for _ in range(b)]),
                               torch.tensor([_rand(gen, -20.0, 70.0) for _ in range(b)]),
                               torch.tensor([_rand(gen, 0.5, 6.0) for _ in range(b)]),
                               torch.tensor([0.0, 0.3, 0.0]))
    else:
        eye = (positions[_randint(gen, 0, len(positions) - 1)].detach().float() if kind == 1
               else torch.tensor([0.0, 0.5, 0.0]) if kind == 2 else torch.tensor([0.0, 1.0, 3.0]))
        target = torch.tensor([0.0, 0.3, 0.0]) if kind != 3 else torch.tensor([0.0, 1.0, 9.0])
        view = tr.camera.look_at(eye, target + 1e-3)
    return OtherFrame(moved, view.to(dtype), proj)


def scene_motion(gen: torch.Generator, scene: tr.RenderScene, c: Counter) -> None:
    """The flow / motion channels of ``scene`` (the stage) forward and backward in a random
    dtype (half precision included), supersampling and batch, with hostile motions and
    other-frame cameras; counts NaN/Inf and violated invariants."""
    dtype = _pick(gen, (torch.float32, torch.float64, torch.float16, torch.bfloat16))
    positions = scene.positions.detach().to(dtype).requires_grad_(True)
    scene.positions = positions
    scene.uvs = scene.tangents = None
    scene.materials = [None, tr.Material(base_color_factor=torch.tensor(
        [1.0, 1.0, 1.0, 0.0]), alpha_mode="MASK") if _chance(gen, 0.3) else None]
    b = _randint(gen, 1, 2)
    view, proj, res = _random_views(gen, b, dtype)
    split = 25  # _stage's plane vertices come first
    nxt = _other_frame(gen, positions, split, b, proj)
    prev = _other_frame(gen, positions, split, b, proj)
    renderer = tr.Renderer(res, shading="unlit", raster=tr.RasterSettings(
        supersample=_randint(gen, 1, 3), cull_backfaces=_chance(gen, 0.3)))
    out = renderer(scene, view, proj, channels=MOTION, next_frame=nxt, previous_frame=prev)
    gb = out.gbuffer
    c["covered"] += int((gb["mask"] > 0).sum())
    c["nonfinite_gbuffer"] += sum(_nonfinite(v) for v in gb.values())
    empty = gb["mask"] == 0
    errors = 0
    for name in ("flow_forward_valid", "flow_backward_valid"):
        v = gb[name]
        errors += int(((v != 0) & (v != 1)).sum() + ((v != 0) & empty).sum())
    for name in ("flow_forward", "flow_backward", "motion"):
        errors += int(((gb[name] != 0) & empty).sum())
    if renderer.raster_settings.supersample == 1 and dtype in (torch.float32, torch.float64):
        scale = torch.tensor([2 / res[1], -2 / res[0]], dtype=dtype).view(1, 2, 1, 1)
        want = -gb["flow_backward"] * scale
        errors += int(((gb["motion"] - want).abs() > 1e-4 * (1 + want.abs())).sum())
    c["motion_errors"] += errors
    loss = sum((v.float() * torch.randn(v.shape, generator=gen)).sum()
               for k, v in gb.items() if v.is_floating_point() and v.requires_grad)
    grad = torch.autograd.grad(loss, positions, allow_unused=True)[0] if isinstance(
        loss, torch.Tensor) and loss.requires_grad else None
    c["grad_values"] += 0 if grad is None else grad.numel()
    # float16: the flow's gradient near the other camera's plane (flows of hundreds of
    # pixels) exceeds float16's range; the leaf sums two saturated gradients (docstring)
    key = "motion_f16_overflow" if dtype == torch.float16 else "nonfinite_grad_positions"
    c[key] += _nonfinite(grad)


def _far_lights(gen: torch.Generator, offset: torch.Tensor, leaves: list[torch.Tensor]
                ) -> tr.Lights:
    """A sun (1-3 cascades), a spot and two point lights (one group: looked up in slices
    under a small padding bound), all casting shadows of one random filter, float64; the
    local lights placed relative to ``offset`` (leaves: gradients)."""
    d = torch.float64
    filt = _pick(gen, tr.shading.shadows.FILTERS)
    size = _pick(gen, (32, 128))
    footprint = _pick(gen, (0.0, 0.56)) if filt in ("pcf", "pcss") else 0.0
    sun_s = tr.shading.shadows.ShadowSettings(map_size=size, filter=filt,
                                              cascades=_randint(gen, 1, 3),
                                              pixel_radius=footprint)
    local_s = tr.shading.shadows.ShadowSettings(map_size=size, filter=filt,
                                                pixel_radius=footprint)
    sun = torch.tensor([[[_rand(gen, -0.6, 0.6), -1.0, _rand(gen, -0.6, 0.6)]]], dtype=d)
    spot = torch.tensor([_rand(gen, -1.5, 1.5), 2.5, _rand(gen, -1.5, 1.5)], dtype=d)
    point = torch.tensor([_rand(gen, -1.5, 1.5), _rand(gen, 0.3, 2.0), _rand(gen, -1.5, 1.5)],
                         dtype=d)
    sun, spot, point = (t.requires_grad_(True) for t in (sun, spot, point))
    leaves += [sun, spot, point]
    yes = torch.tensor([[True]])
    one = torch.ones(1, 1, 3, dtype=d)
    return tr.Lights(
        ambient=tr.sh_from_color(torch.full((1, 3), 0.05, dtype=d)),
        directional=tr.DirectionalLights(sun, one, torch.full((1, 1), 3.0, dtype=d),
                                         cast_shadows=yes, shadow=sun_s),
        spot=tr.SpotLights((spot + offset)[None, None], torch.tensor([[[0.0, -1.0, 0.0]]],
                                                                     dtype=d),
                           one, torch.full((1, 1), 20.0, dtype=d), cast_shadows=yes,
                           shadow=local_s),
        point=tr.PointLights(torch.stack([point, point * torch.tensor(
            [-1.0, 1.0, -1.0], dtype=d)])[None] + offset, one.expand(1, 2, 3),
                             torch.full((1, 2), 5.0, dtype=d),
                             cast_shadows=torch.tensor([[True, True]]), shadow=local_s))


def scene_far(gen: torch.Generator, c: Counter) -> None:
    """The stage, cameras and lights moved together far from the origin (module
    docstring), rendered there and at the origin; forward and backward."""
    dtype = torch.float32 if _chance(gen, 0.25) else torch.float64
    base, faces, uvs, face_material = _stage(gen, torch.float64)
    direction = torch.randn(3, generator=gen, dtype=torch.float64)
    offset = direction / direction.norm() * _pick(gen, (0.0, 1e3, 1e5, 1e6, 1e7))
    fog = dissolve = None
    if _chance(gen, 0.3):
        fog = tr.Fog(density=_pick(gen, (1e-3, 0.3)), height_falloff=_pick(gen, (0.0, 0.5)),
                     steps=_randint(gen, 1, 4), light_transmittance=_chance(gen, 0.7))
    elif _chance(gen, 0.3):
        dissolve = tr.Dissolve(threshold=0.3)
        period = tr.dissolve.PERIOD / dissolve.scale  # the same pattern at the origin
        offset = torch.round(offset / period) * period
    b = _randint(gen, 1, 2)
    view0 = tr.camera.orbit(torch.tensor([_rand(gen, 0.0, 360.0) for _ in range(b)]),
                            torch.tensor([_rand(gen, 10.0, 60.0) for _ in range(b)]),
                            torch.tensor([_rand(gen, 1.5, 6.0) for _ in range(b)]),
                            torch.tensor([0.0, 0.3, 0.0])).double()
    move = torch.eye(4, dtype=torch.float64)
    move[:3, 3] = -offset
    res = (_randint(gen, 8, 40), _randint(gen, 8, 40))
    proj = tr.camera.perspective(_rand(gen, 20.0, 90.0), res[1] / res[0], 0.01)
    kw = dict(shading="pbr", raster=tr.RasterSettings(supersample=_pick(gen, (1, 2)),
                                                      antialias=_chance(gen, 0.3)),
              dissolve=dissolve)
    outs = []
    seed = int(torch.randint(0, 2**31, (1,), generator=gen))  # the same lights twice
    # sometimes a bound on the lookups' padded maps that the two point lights' maps do not
    # fit together (looked up in slices, shadows._light_slices) or that nothing fits
    bound = _pick(gen, (0, 20000, 200000)) if _chance(gen, 0.3) else None
    recompute = _chance(gen, 0.5)  # lookups checkpointed (recomputed in backward)
    for shift in (offset, torch.zeros(3, dtype=torch.float64)):
        positions = (base + shift).to(dtype).requires_grad_(True)
        leaves = [positions]
        lights = _far_lights(torch.Generator().manual_seed(seed), shift, leaves)
        f = fog if fog is None else dataclasses.replace(
            fog, base_height=float(fog.base_height) + float(shift[1]))
        view = view0 @ (move if shift is offset else torch.eye(4, dtype=torch.float64))
        if dtype == torch.float32 and shift is not offset:
            view = view.float()  # the plain float32 render at the origin
        scene = tr.RenderScene(positions, faces, uvs=uvs.float(), face_material=face_material,
                               materials=[tr.Material(), tr.Material(roughness_factor=0.3)])
        default_bound, default_taps = shadows.PAD_MAP_ELEMENTS, shadows.RECOMPUTE_TAPS
        shadows.PAD_MAP_ELEMENTS = default_bound if bound is None else bound
        shadows.RECOMPUTE_TAPS = 0 if recompute else default_taps
        try:
            out = tr.Renderer(res, fog=f, **kw)(scene, view, proj, lights,
                                                channels=("face_id", "position"))
        finally:
            shadows.PAD_MAP_ELEMENTS, shadows.RECOMPUTE_TAPS = default_bound, default_taps
        c["covered"] += int((out.alpha > 0).sum())
        c["nonfinite_image"] += _nonfinite(out.image)
        c["nonfinite_alpha"] += _nonfinite(out.alpha)
        c["nonfinite_gbuffer"] += sum(_nonfinite(v) for v in out.gbuffer.values())
        loss = (out.image * torch.randn(out.image.shape, generator=gen)).sum()
        grads = torch.autograd.grad(loss, leaves, allow_unused=True)
        c["grad_values"] += sum(g.numel() for g in grads if g is not None)
        c["nonfinite_grad_positions"] += _nonfinite(grads[0])
        c["nonfinite_grad_lights"] += sum(_nonfinite(g) for g in grads[1:])
        outs.append(out)
    if dtype != torch.float64:
        return  # float32 positions far away are rounded already: finiteness only
    far, near = outs
    fid, fid0 = far.gbuffer["face_id"], near.gbuffer["face_id"]
    covered = int((fid0 >= 0).sum())
    c["far_errors"] += max(0, int((fid != fid0).sum()) - 3 - covered // 100)
    if kw["raster"].supersample > 1:
        return  # box-filtered positions: the covered fraction is not known per pixel
    same = (fid == fid0) & (fid >= 0)
    mask = (fid >= 0).to(torch.float64)
    world = near.gbuffer["position"].double() + offset.view(1, 3, 1, 1) * mask
    err = (far.gbuffer["position"].double() - world).abs()
    tol = 1e-3 + 4 * torch.finfo(torch.float32).eps * float(offset.abs().max())
    c["far_errors"] += int((err > tol)[same.expand_as(err)].sum())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("all", "raster", "renderer"), default="all")
    parser.add_argument("--n", type=int, default=5000, help="number of random raster scenes")
    parser.add_argument("--n-renderer", type=int, default=1000,
                        help="number of random renderer scenes")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-picture", action="store_true")
    args = parser.parse_args()
    bad = 0
    if args.part in ("all", "raster"):
        bad += raster_part(args)
    if args.part in ("all", "renderer"):
        bad += renderer_part(args)
    return 1 if bad else 0


def counts_table(counts: dict[str, Counter], columns: list[tuple[str, str]],
                 problems: set[str]) -> tuple[str, int]:
    """Markdown table of the counts (a row per kind and a total) and the total problems."""
    rows = [[k] + [c[key] for key, _ in columns] for k, c in counts.items()]
    rows.append(["total"] + [sum(c[key] for c in counts.values()) for key, _ in columns])
    table = markdown_table(["kind"] + [label for _, label in columns], rows)
    return table, sum(rows[-1][1 + i] for i, (key, _) in enumerate(columns) if key in problems)


def raster_part(args: argparse.Namespace) -> int:
    torch.manual_seed(args.seed)
    counts, seconds = run_scenes(args.n, args.seed, KINDS, raster_scene)
    table, bad = counts_table(counts, COLUMNS, PROBLEMS)
    body = (f"### Stress: {args.n} random hostile scenes (seed {args.seed}, "
            f"{seconds:.0f} s)\n\nCounts of problems found (all should be 0); "
            f"kinds are described in `scripts/stress.py`.\n\n{table}\n\n"
            f"Total problems: **{bad}**.")
    print(body)
    update_section("stress", body)
    if not args.no_picture:
        picture(ROOT / "docs" / "images" / "raster_ref_diff.png")
    return bad


def renderer_part(args: argparse.Namespace) -> int:
    counts, seconds = run_scenes(args.n_renderer, args.seed, R_KINDS, scene_renderer,
                                 (ValueError, TypeError), "renderer scenes", 50)
    table, bad = counts_table(counts, R_COLUMNS, R_PROBLEMS)
    body = (f"### Stress: {args.n_renderer} random hostile renderer scenes (seed {args.seed}, "
            f"{seconds:.0f} s)\n\nMaterials, lights and environments with hostile values "
            "(0, denormals, 1e6, grazing angles, roughness 0), rendered forward and backward "
            "through `tr.Renderer`; kinds are described in `scripts/stress.py`. Problem counts "
            "(all should be 0) are NaN/Inf values in the outputs and gradients and exceptions "
            "other than a `ValueError`/`TypeError` rejecting an input (counted apart under "
            f"\"rejected\").\n\n{table}\n\nTotal problems: **{bad}**.")
    print(body)
    update_section("stress-renderer", body)
    return bad


def picture_only() -> None:
    """Only (re)draw the picture: ``python -c 'import stress; stress.picture_only()'``."""
    picture(ROOT / "docs" / "images" / "raster_ref_diff.png")


if __name__ == "__main__":
    sys.exit(main())
