"""Stress the rasterizer with thousands of random hostile scenes and count what goes wrong.

Scene kinds (cycled):
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
attributes. Writes section ``stress`` of docs/benchmarks.md with the counts.

    python scripts/stress.py [--n 1000] [--seed 0] [--no-picture]

Unless --no-picture, also renders docs/images/raster_ref_diff.png: engine vs the independent
float64 reference (tests/reference_raster.py) face ids for spot, and their difference.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import Counter
from pathlib import Path

import torch
import trimesh

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

from benchmd import markdown_table, update_section  # noqa: E402
from reference_raster import (  # noqa: E402
    look_at_matrix,
    perspective_matrix,
    random_soup,
    reference_coverage_count,
    to_clip,
)

import torchraster as tr  # noqa: E402

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


def run(n: int, seed: int) -> tuple[dict[str, Counter], float]:
    gen = torch.Generator().manual_seed(seed)
    counts = {k: Counter() for k in KINDS}
    start = time.perf_counter()
    for i in range(n):
        kind = KINDS[i % len(KINDS)]
        c = counts[kind]
        c["scenes"] += 1
        try:
            if kind in ("soup", "huge"):
                scene_soup(gen, c, huge=kind == "huge")
            elif kind == "near_far":
                scene_near_far(gen, c)
            elif kind == "closed":
                scene_closed(gen, c)
            else:
                scene_grid(gen, c)
        except Exception as exc:  # noqa: BLE001 - every exception is a finding to count
            c["exceptions"] += 1
            print(f"scene {i} ({kind}): {type(exc).__name__}: {exc}", file=sys.stderr)
        if (i + 1) % 100 == 0:
            print(f"{i + 1}/{n} scenes, {time.perf_counter() - start:.0f} s", file=sys.stderr)
    return counts, time.perf_counter() - start


COLUMNS = [
    ("scenes", "scenes"), ("pixels", "pixels"), ("covered", "covered"),
    ("nonfinite_bary", "NaN/Inf bary"), ("nonfinite_depth", "NaN/Inf depth"),
    ("depth_out_of_range", "abs(depth) > 1"), ("bad_empty", "empty depth != +inf"),
    ("nonfinite_image", "NaN/Inf image"), ("nonfinite_grad_clip", "NaN/Inf grad clip_pos"),
    ("nonfinite_grad_attrs", "NaN/Inf grad attrs"), ("cracks", "cracks (px)"),
    ("grid_pixels", "grid pixels"), ("double_hits", "double hits (px)"),
    ("whole_vs_alone", "whole != alone (px)"), ("exceptions", "exceptions"),
]
PROBLEMS = {"nonfinite_bary", "nonfinite_depth", "depth_out_of_range", "bad_empty",
            "nonfinite_image", "nonfinite_grad_clip", "nonfinite_grad_attrs", "cracks",
            "double_hits", "whole_vs_alone", "exceptions"}


def picture(path: Path) -> None:
    """Engine vs reference face ids for spot (random colours per face) and their difference
    (red: pixels whose face differs; grey: covered in the reference)."""
    import numpy as np
    from PIL import Image, ImageDraw
    from reference_raster import compare_fragments, load_mesh, reference_rasterize

    data = ROOT.parent / "shared" / "data" / "meshes" / "spot" / "spot_triangulated.obj"
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=5000, help="number of random scenes")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-picture", action="store_true")
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    counts, seconds = run(args.n, args.seed)
    rows = [[k] + [counts[k][key] for key, _ in COLUMNS] for k in KINDS]
    rows.append(["total"] + [sum(counts[k][key] for k in KINDS) for key, _ in COLUMNS])
    table = markdown_table(["kind"] + [label for _, label in COLUMNS], rows)
    bad = sum(rows[-1][1 + i] for i, (key, _) in enumerate(COLUMNS) if key in PROBLEMS)
    body = (f"### Stress: {args.n} random hostile scenes (seed {args.seed}, "
            f"{seconds:.0f} s)\n\nCounts of problems found (all should be 0); "
            f"kinds are described in `scripts/stress.py`.\n\n{table}\n\n"
            f"Total problems: **{bad}**.")
    print(body)
    update_section("stress", body)
    if not args.no_picture:
        picture(ROOT / "docs" / "images" / "raster_ref_diff.png")
    return 1 if bad else 0


def picture_only() -> None:
    """Only (re)draw the picture: ``python -c 'import stress; stress.picture_only()'``."""
    picture(ROOT / "docs" / "images" / "raster_ref_diff.png")


if __name__ == "__main__":
    sys.exit(main())
