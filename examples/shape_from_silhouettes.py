"""Deform an icosphere into a target shape from its silhouettes (and shading) in 16 views.

The target (the Stanford bunny of ../shared/data, Spot when that is absent, or
``--target``) is rendered from ``--views`` cameras around it: its silhouettes at 4x
supersampling without antialiasing (the pixels' true area coverage) and, for the optional
shading term, the same views lit by a headlight. An icosphere's vertex offsets are then
optimised with Adam on

    loss = w_sil * sum_l mean((pool_l(alpha) - pool_l(target_alpha)) ** 2)
         + w_shade * mean((image - target_image) ** 2)
         + w_lap * mean(|L v| ** 2) + w_edge * mean((|e| / mean|e| - 1) ** 2)

``alpha`` and ``image`` come from ``tr.Renderer(..., antialias=True)`` (headlight shading,
normals recomputed from the deformed positions); ``L`` is the uniform Laplacian
``I - D^-1 A`` (a sparse torch matrix from trimesh's unique edges), ``e`` the edges. The
quality measure is the Chamfer distance (mean distance of points sampled on the target
surface to points sampled on the current mesh, plus the reverse, both from
``trimesh.sample``; the target fits in the unit sphere). The same optimisation is then run
with ``antialias=False`` (everything else equal): there the silhouette term has no
gradient and only the shading term moves the vertices.

    python examples/shape_from_silhouettes.py                 # 16 views, 96 px, bunny
    python examples/shape_from_silhouettes.py --iterations 40 --resolution 48 --target ellipsoid
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

import torchraster as tr  # noqa: E402

FOV_DEG = 40.0
DISTANCE = 3.2
ELEVATIONS = (35.0, 5.0, -25.0)


def uniform_laplacian(edges: torch.Tensor, num_vertices: int) -> torch.Tensor:
    """The uniform graph Laplacian ``I - D^-1 A`` as a sparse ``(V, V)`` tensor.

    Args:
        edges: ``(E, 2)`` int64 unique undirected edges.
        num_vertices: V.
    """
    i = torch.cat([edges[:, 0], edges[:, 1]])
    j = torch.cat([edges[:, 1], edges[:, 0]])
    degree = torch.zeros(num_vertices).index_add_(0, i, torch.ones(i.shape[0]))
    rows = torch.cat([i, torch.arange(num_vertices)])
    cols = torch.cat([j, torch.arange(num_vertices)])
    vals = torch.cat([-1.0 / degree[i], torch.ones(num_vertices)])
    return torch.sparse_coo_tensor(torch.stack([rows, cols]), vals,
                                   (num_vertices, num_vertices)).coalesce()


def laplacian_loss(laplacian: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """Mean squared norm of the uniform Laplacian of the positions (smoothness)."""
    return (torch.sparse.mm(laplacian, positions) ** 2).sum(1).mean()


def edge_loss(edges: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """Mean squared relative deviation of the edge lengths from their mean (even
    triangles)."""
    length = (positions[edges[:, 0]] - positions[edges[:, 1]]).norm(dim=1)
    return ((length / length.mean().detach() - 1) ** 2).mean()


def chamfer(a: torch.Tensor, b: torch.Tensor, chunk: int = 2048) -> float:
    """Symmetric Chamfer distance: mean over ``a`` of the distance to the nearest point of
    ``b`` plus the reverse (``(N, 3)`` and ``(M, 3)`` point sets)."""

    def one_way(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        return torch.cat([torch.cdist(p[k:k + chunk], q).min(1).values
                          for k in range(0, p.shape[0], chunk)]).mean()

    return float(one_way(a, b) + one_way(b, a))


def surface_points(vertices: np.ndarray, faces: np.ndarray, count: int, seed: int
                   ) -> torch.Tensor:
    """``count`` points sampled uniformly on a triangle mesh's surface (``trimesh.sample``)."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return torch.tensor(points, dtype=torch.float32)


def silhouette_loss(alpha: torch.Tensor, target: torch.Tensor, levels: int) -> torch.Tensor:
    """Sum over ``levels`` box-filtered levels of the mean squared difference."""
    loss = alpha.new_zeros(())
    for level in range(levels):
        k = 2 ** level
        a, b = (F.avg_pool2d(alpha, k), F.avg_pool2d(target, k)) if k > 1 else (alpha, target)
        loss = loss + ((a - b) ** 2).mean()
    return loss


def optimise(args: argparse.Namespace, antialias: bool, targets: dict, label: str
             ) -> dict:
    """One run of the deformation from the icosphere; returns its history and mesh."""
    torch.manual_seed(args.seed)
    sphere = trimesh.creation.icosphere(subdivisions=args.subdivisions, radius=args.radius)
    faces = torch.tensor(sphere.faces, dtype=torch.int64)
    base = torch.tensor(sphere.vertices, dtype=torch.float32)
    edges = torch.tensor(sphere.edges_unique, dtype=torch.int64)
    lap = uniform_laplacian(edges, base.shape[0])
    if args.smooth > 0:
        dense = torch.eye(base.shape[0], dtype=torch.float64) + args.smooth * (
            torch.diag(torch.bincount(edges.flatten(), minlength=base.shape[0]).double())
            - torch.sparse_coo_tensor(torch.cat([edges, edges.flip(1)]).T,
                                      torch.ones(2 * edges.shape[0], dtype=torch.float64),
                                      (base.shape[0],) * 2).to_dense())
        chol = torch.linalg.cholesky(dense).float()
        u = (dense.float() @ base).requires_grad_(True)
        params = [u]
    else:
        offset = torch.zeros_like(base, requires_grad=True)
        params = [offset]
    opt = torch.optim.Adam(params, lr=args.lr)

    def current():
        if args.smooth > 0:
            return torch.cholesky_solve(u, chol)
        return base + offset

    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.iterations, args.lr * 0.05)
    renderer = tr.Renderer(args.resolution, shading="headlight", antialias=antialias)
    views, proj = targets["views"], targets["proj"]
    target_points = targets["points"]
    table = common.Table([f"chamfer {label}", "silhouette", "loss"], args.log_every,
                         args.quiet)
    for it in range(args.iterations):
        table.tick()
        positions = current()
        out = renderer(tr.Mesh(positions, faces), views, proj)
        sil = silhouette_loss(out.alpha, targets["alpha"], args.levels)
        loss = (args.w_silhouette * sil + args.w_lap * laplacian_loss(lap, positions)
                + args.w_edge * edge_loss(edges, positions))
        if args.w_shading > 0:
            loss = loss + args.w_shading * ((out.image - targets["image"]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        table.tock()
        with torch.no_grad():
            points = surface_points(current().numpy(), sphere.faces, args.points,
                                    args.seed + 1)
            dist = chamfer(points, target_points)
        table.record(it, [dist, sil.item(), loss.item()], last=it == args.iterations - 1)
    return {"history": table.history, "positions": current().detach(), "faces": faces,
            "start": base}


def prepare(args: argparse.Namespace) -> dict:
    """Target mesh, cameras, target silhouettes / images and target surface points."""
    target_mesh, name = common.load_target(args.target)
    mesh = common.as_mesh(target_mesh)
    count = args.views
    az = torch.arange(count, dtype=torch.float32) * (360.0 / count)
    el = torch.tensor([ELEVATIONS[i % len(ELEVATIONS)] for i in range(count)])
    views = tr.camera.orbit(az, el, torch.full((count,), DISTANCE))
    proj = tr.camera.perspective(FOV_DEG, 1.0, 0.1)
    with torch.no_grad():
        out = tr.Renderer(args.resolution, shading="headlight", supersample=4)(mesh, views, proj)
    points = surface_points(target_mesh.vertices, target_mesh.faces, args.points, args.seed)
    return {"name": name, "mesh": mesh, "views": views, "proj": proj, "alpha": out.alpha,
            "image": out.image, "points": points}


def pictures(targets: dict, runs: dict, size: int, rows: int = 2
             ) -> list[tuple[str, np.ndarray]]:
    """Start / target / result panels (headlight renders from ``rows`` of the views)."""
    renderer = tr.Renderer(size, shading="headlight")
    step = max(1, targets["views"].shape[0] // rows)
    views = targets["views"][::step][:rows]
    proj = targets["proj"]
    first = next(iter(runs.values()))
    meshes = [("start", tr.Mesh(first["start"], first["faces"])),
              ("target", targets["mesh"])]
    meshes += [(f"result, {label}", tr.Mesh(r["positions"], r["faces"]))
               for label, r in runs.items()]
    panels = []
    with torch.no_grad():
        for label, mesh in meshes:
            image = renderer(mesh, views, proj).image.clamp(0, 1)
            panels.append((label, common.stack_rows([common.to_uint8(i) for i in image])))
    return panels


def run(args: argparse.Namespace) -> dict:
    """Prepare the targets, run the optimisation with antialiasing and, unless
    ``--skip-no-antialias``, without; returns both histories and the pictures."""
    common.setup(args)
    targets = prepare(args)
    runs = {}
    for antialias in (True, False) if not args.skip_no_antialias else (True,):
        label = "antialias" if antialias else "no antialias"
        if not args.quiet:
            print(f"--- {targets['name']}, {label}")
        runs[label] = optimise(args, antialias, targets, "AA" if antialias else "no AA")
    result = {"target": targets["name"], "runs": runs}
    if args.out is not None or args.picture is not None:
        result["panels"] = pictures(targets, runs, args.picture_resolution)
    return result


def parser() -> argparse.ArgumentParser:
    """The command line."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    common.add_common_args(p, iterations=200, resolution=96, views=16,
                           out="out/inverse_shape")
    p.add_argument("--target", default="bunny",
                   help="bunny (default; Spot when ../shared/data is absent), spot, "
                        "ellipsoid or a mesh file")
    p.add_argument("--subdivisions", type=int, default=4,
                   help="icosphere subdivisions (default 4: 2,562 vertices)")
    p.add_argument("--radius", type=float, default=0.7, help="icosphere radius (default 0.7)")
    p.add_argument("--lr", type=float, default=0.01, help="Adam learning rate (default 0.01)")
    p.add_argument("--levels", type=int, default=3,
                   help="silhouette pyramid levels of the loss (default 3)")
    p.add_argument("--smooth", type=float, default=0.0)
    p.add_argument("--w-silhouette", type=float, default=1.0)
    p.add_argument("--w-shading", type=float, default=0.5,
                   help="weight of the headlight shading term (0: silhouettes only)")
    p.add_argument("--w-lap", type=float, default=0.5, help="Laplacian weight (default 0.5)")
    p.add_argument("--w-edge", type=float, default=0.01, help="edge-length weight")
    p.add_argument("--points", type=int, default=5000,
                   help="surface points per Chamfer evaluation (default 5000)")
    p.add_argument("--skip-no-antialias", action="store_true",
                   help="skip the comparison run with antialias=False")
    p.add_argument("--picture-resolution", type=int, default=160,
                   help="panel size of the pictures (default 160)")
    return p


def main(argv: list[str] | None = None) -> dict:
    """Parse ``argv``, run, write the pictures (and the benchmark section)."""
    args = parser().parse_args(argv)
    result = run(args)
    if "panels" in result:
        if args.out is not None:
            common.save_strip(args.out / "shape.png", result["panels"])
        if args.picture is not None:
            common.save_strip(args.picture, result["panels"])
    if not args.quiet:
        for label, r in result["runs"].items():
            ch = r["history"].column(r["history"].columns[0])
            print(f"{label}: Chamfer {ch[0]:.4f} -> {ch[-1]:.4f} "
                  f"({r['history'].ms_per_iteration:.0f} ms/iteration)")
    if args.benchmark:
        common.write_benchmark("inverse-shape", benchmark_body(args, result))
    return result


def benchmark_body(args: argparse.Namespace, result: dict) -> str:
    """The docs/benchmarks.md section of this run."""
    runs = result["runs"]
    aa = runs["antialias"]["history"]
    noaa = runs.get("no antialias", {}).get("history")
    header = ["iteration", "Chamfer, antialias", "ms / iteration"]
    if noaa is not None:
        header[2:2] = ["Chamfer, no antialias"]
    rows = []
    for i in common.checkpoints(len(aa.rows)):
        row = [i, aa.rows[i][0]] + ([noaa.rows[i][0]] if noaa is not None else [])
        rows.append(row + [aa.seconds[i] * 1e3])
    body = (
        f"### Shape from silhouettes ({result['target']}, {args.views} views, "
        f"{args.resolution}², {args.iterations} iterations)\n\n"
        f"An icosphere ({args.subdivisions} subdivisions, radius {args.radius:g}) deformed "
        f"by Adam on its vertex offsets: silhouette pyramid loss (weight "
        f"{args.w_silhouette:g}) against 4x-supersampled target coverage, headlight shading "
        f"(weight {args.w_shading:g}), uniform Laplacian ({args.w_lap:g}) and edge-length "
        f"({args.w_edge:g}) regularisers. Chamfer = mean nearest distance target -> mesh + "
        f"mesh -> target over {args.points} points sampled on each surface "
        "(`trimesh.sample`), target in the unit sphere. The `antialias=False` run is the "
        "same optimisation with only that flag changed.\n\n"
        + common.markdown_table(header, rows)
    )
    first, last = aa.rows[0][0], aa.rows[-1][0]
    body += (f"\n\nChamfer with antialiasing: {first:.4f} -> {last:.4f} "
             f"({aa.ms_per_iteration:.0f} ms per iteration")
    if noaa is not None:
        nl = noaa.rows[-1][0]
        body += (f"; without: {noaa.rows[0][0]:.4f} -> {nl:.4f} "
                 f"({noaa.ms_per_iteration:.0f} ms per iteration). Antialiasing ends "
                 f"{nl / last:.2f}x lower ({(1 - last / nl) * 100:.0f} % less)")
    body += ").\n\n![start / target / results](images/inverse_shape.png)"
    return body


if __name__ == "__main__":
    main()
