"""Deform an icosphere into a target shape from its silhouettes (and shading) in 16 views.

The target (the Stanford bunny of $TORCHRASTER_DATA, Spot when that is absent, or
``--target``) is rendered from ``--views`` cameras around it: its silhouettes at 4x
supersampling without antialiasing (the pixels' true area coverage) and, for the optional
shading term, the same views lit by a headlight. An icosphere is then deformed by Adam on

    loss = w_sil * sum_l mean((pool_l(alpha) - pool_l(target_alpha)) ** 2)
         + w_shade * mean((image - target_image) ** 2)
         + w_lap * mean(|L x| ** 2) + w_edge * mean((|e| / mean|e| - 1) ** 2)

``alpha`` and ``image`` come from ``tr.Renderer(..., raster=tr.RasterSettings(antialias=True))``
(headlight shading,
normals recomputed from the deformed positions ``x``); ``L`` is the uniform Laplacian
``I - D^-1 A`` (a sparse torch matrix from trimesh's unique edges), ``e`` the edges. The
positions are parametrised as ``x = (I + lambda (D - A))^-1 u`` ("large steps", Nicolet et
al. 2021; ``--smooth 0``: plain per-vertex offsets), which keeps the surface from crumpling
where only the outline's vertices get gradients. The quality measure is the Chamfer
distance (mean distance of points sampled on the target surface to points sampled on the
current mesh, plus the reverse, both from ``trimesh.sample``; the target fits in the unit
sphere; two samples of the target itself score the "floor"). The same optimisation is then
run with ``antialias=False`` (everything else equal): there the silhouette term has no
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
                                   (num_vertices, num_vertices),
                                   check_invariants=True).coalesce()


def laplacian_loss(laplacian: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """Mean squared norm of the uniform Laplacian of the positions (smoothness)."""
    return (torch.sparse.mm(laplacian, positions) ** 2).sum(1).mean()


def edge_loss(edges: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """Mean squared relative deviation of the edge lengths from their mean (even
    triangles)."""
    length = (positions[edges[:, 0]] - positions[edges[:, 1]]).norm(dim=1)
    return ((length / length.mean().detach() - 1) ** 2).mean()


class OffsetParam(torch.nn.Module):
    """Positions = the starting vertices + free per-vertex offsets."""

    def __init__(self, base: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("base", base)
        self.offset = torch.nn.Parameter(torch.zeros_like(base))

    def positions(self) -> torch.Tensor:
        """``(V, 3)`` current positions."""
        return self.base + self.offset


class SmoothParam(torch.nn.Module):
    """Positions ``x = (I + lambda L)^-1 u``, with ``u`` optimised: the "large steps"
    reparametrisation of Nicolet et al. 2021 ("Large Steps in Inverse Rendering of
    Geometry"), with ``L = D - A`` the combinatorial Laplacian of the mesh graph. A gradient
    step on ``u`` moves ``x`` by a smoothed step, so silhouette gradients that reach only the
    vertices on the outline spread to their neighbourhood instead of crumpling the surface.
    The system is small (V < ~10k): one dense float64 Cholesky factorisation, then a
    ``torch.cholesky_solve`` (differentiable) per step.
    """

    def __init__(self, base: torch.Tensor, edges: torch.Tensor, smooth: float) -> None:
        super().__init__()
        n = base.shape[0]
        if n > 12000:
            raise ValueError(f"SmoothParam: {n} vertices: the dense system would not fit; use "
                             "fewer subdivisions or --smooth 0")
        adjacency = torch.zeros(n, n, dtype=torch.float64)
        adjacency[edges[:, 0], edges[:, 1]] = 1.0
        adjacency[edges[:, 1], edges[:, 0]] = 1.0
        system = torch.eye(n, dtype=torch.float64) + smooth * (
            torch.diag(adjacency.sum(1)) - adjacency)
        self.register_buffer("factor", torch.linalg.cholesky(system).to(base.dtype))
        self.u = torch.nn.Parameter((system @ base.double()).to(base.dtype))

    def positions(self) -> torch.Tensor:
        """``(V, 3)`` current positions."""
        return torch.cholesky_solve(self.u, self.factor)


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


def optimise(args: argparse.Namespace, antialias: bool, targets: dict, label: str
             ) -> dict:
    """One run of the deformation from the icosphere; returns its history and mesh."""
    torch.manual_seed(args.seed)
    sphere = trimesh.creation.icosphere(subdivisions=args.subdivisions, radius=args.radius)
    faces = torch.tensor(sphere.faces, dtype=torch.int64)
    base = torch.tensor(sphere.vertices, dtype=torch.float32)
    edges = torch.tensor(sphere.edges_unique, dtype=torch.int64)
    lap = uniform_laplacian(edges, base.shape[0])
    param = SmoothParam(base, edges, args.smooth) if args.smooth > 0 else OffsetParam(base)
    opt = torch.optim.Adam(param.parameters(), lr=args.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.iterations, args.lr * 0.05)
    renderer = tr.Renderer(args.resolution,
                           shading="headlight",
                           raster=tr.RasterSettings(antialias=antialias))
    views, proj = targets["views"], targets["proj"]
    target_points = targets["points"]

    def measure() -> float:
        with torch.no_grad():
            points = surface_points(param.positions().numpy(), sphere.faces, args.points,
                                    args.seed + 1)
            return chamfer(points, target_points)

    initial = measure()
    table = common.Table([f"chamfer {label}", "silhouette", "loss"], args.log_every,
                         args.quiet)
    for it in range(args.iterations):
        table.tick()
        positions = param.positions()
        out = renderer(tr.Mesh(positions, faces), views, proj)
        sil = common.pyramid_loss(out.alpha, targets["alpha"], args.levels)
        loss = (args.w_silhouette * sil + args.w_lap * laplacian_loss(lap, positions)
                + args.w_edge * edge_loss(edges, positions))
        if args.w_shading > 0:
            loss = loss + args.w_shading * ((out.image - targets["image"]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        table.tock()
        table.record(it, [measure(), sil.item(), loss.item()], last=it == args.iterations - 1)
    with torch.no_grad():
        positions = param.positions()
        final = chamfer(surface_points(positions.numpy(), sphere.faces, args.final_points,
                                       args.seed + 4), targets["fine"])
    return {"history": table.history, "initial": initial, "final": final,
            "positions": positions, "faces": faces, "start": base}


def prepare(args: argparse.Namespace) -> dict:
    """Target mesh, cameras, target silhouettes / images and target surface points."""
    target_mesh, name = common.load_target(args.target)
    mesh = common.as_mesh(target_mesh)
    views = common.ring_views(args.views, DISTANCE, ELEVATIONS)
    proj = tr.camera.perspective(FOV_DEG, 1.0, 0.1)
    with torch.no_grad():
        out = tr.Renderer(args.resolution,
                          shading="headlight",
                          raster=tr.RasterSettings(supersample=4))(mesh, views, proj)
    points = surface_points(target_mesh.vertices, target_mesh.faces, args.points, args.seed)
    # the Chamfer distance between two samples of the target itself: what a perfect shape
    # would score with this many points
    floor = chamfer(points, surface_points(target_mesh.vertices, target_mesh.faces,
                                           args.points, args.seed + 1))
    fine = surface_points(target_mesh.vertices, target_mesh.faces, args.final_points,
                          args.seed + 2)
    fine_floor = chamfer(fine, surface_points(target_mesh.vertices, target_mesh.faces,
                                              args.final_points, args.seed + 3))
    return {"name": name, "mesh": mesh, "views": views, "proj": proj, "alpha": out.alpha,
            "image": out.image, "points": points, "floor": floor, "fine": fine,
            "fine_floor": fine_floor}


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
    result = {"target": targets["name"], "runs": runs, "floor": targets["floor"],
              "fine_floor": targets["fine_floor"], "final_points": args.final_points}
    if args.out is not None or args.picture is not None:
        result["panels"] = pictures(targets, runs, args.picture_resolution)
    return result


def parser() -> argparse.ArgumentParser:
    """The command line."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    common.add_common_args(p, iterations=200, resolution=96, views=16,
                           out="out/inverse_shape")
    p.add_argument("--target", default="bunny",
                   help="bunny (default; Spot when $TORCHRASTER_DATA is absent), spot, "
                        "ellipsoid or a mesh file")
    p.add_argument("--subdivisions", type=int, default=4,
                   help="icosphere subdivisions (default 4: 2,562 vertices)")
    p.add_argument("--radius", type=float, default=0.7, help="icosphere radius (default 0.7)")
    p.add_argument("--lr", type=float, default=0.03, help="Adam learning rate (default 0.03)")
    p.add_argument("--levels", type=int, default=3,
                   help="silhouette pyramid levels of the loss (default 3)")
    p.add_argument("--smooth", type=float, default=10.0,
                   help="lambda of the large-steps parametrisation x = (I + lambda L)^-1 u "
                        "(default 10; 0: plain per-vertex offsets)")
    p.add_argument("--w-silhouette", type=float, default=1.0)
    p.add_argument("--w-shading", type=float, default=0.5,
                   help="weight of the headlight shading term (0: silhouettes only)")
    p.add_argument("--w-lap", type=float, default=5.0, help="Laplacian weight (default 5)")
    p.add_argument("--w-edge", type=float, default=0.01, help="edge-length weight")
    p.add_argument("--points", type=int, default=5000,
                   help="surface points per Chamfer evaluation (default 5000)")
    p.add_argument("--final-points", type=int, default=30000,
                   help="surface points of the final Chamfer evaluation (default 30000)")
    p.add_argument("--skip-no-antialias", action="store_true",
                   help="skip the comparison run with antialias=False")
    p.add_argument("--picture-resolution", type=int, default=160,
                   help="panel size of the pictures (default 160)")
    return p


def main(argv: list[str] | None = None) -> dict:
    """Parse ``argv``, run, write the pictures (and the benchmark section)."""
    args = parser().parse_args(argv)
    result = run(args)
    section = "inverse-shape" if args.w_shading > 0 else "inverse-shape-silhouettes"
    return common.finish(args, result, "shape.png", summary(result), section,
                         lambda: benchmark_body(args, result))


def catch_up(history: common.History, value: float) -> int | None:
    """First iteration whose Chamfer is at most ``value`` (None: never)."""
    for i, row in enumerate(history.rows):
        if row[0] <= value:
            return i
    return None


def summary(result: dict) -> str:
    """Start and final Chamfer of each run, and how much antialiasing wins."""
    n, floor = result["final_points"], result["fine_floor"]
    lines = []
    for label, r in result["runs"].items():
        h = r["history"]
        lines.append(f"{label}: Chamfer {r['initial']:.4f} -> {h.rows[-1][0]:.4f}; final "
                     f"{r['final']:.4f} with {n} points (floor {floor:.4f}); "
                     f"{h.ms_per_iteration:.0f} ms/iteration")
    runs = result["runs"]
    if "no antialias" in runs:
        aa, no = runs["antialias"], runs["no antialias"]
        excess_a, excess_n = aa["final"] - floor, no["final"] - floor
        reach = catch_up(aa["history"], no["history"].rows[-1][0])
        if reach is None:
            reached = "never reaches the no-antialias final Chamfer"
        else:
            seconds = sum(aa["history"].seconds[:reach + 1])
            reached = (f"reaches the no-antialias final Chamfer after {reach + 1} of "
                       f"{len(aa['history'].rows)} iterations ({seconds:.1f} s against "
                       f"{sum(no['history'].seconds):.1f} s)")
        lines.append(
            f"antialiasing wins: final Chamfer {no['final'] / aa['final']:.2f}x lower "
            f"({(1 - aa['final'] / no['final']) * 100:.0f} % less), "
            f"{excess_n / excess_a:.2f}x lower above the floor; antialias {reached}")
    return "\n".join(lines)


def benchmark_body(args: argparse.Namespace, result: dict) -> str:
    """The docs/benchmarks.md section of this run."""
    runs = result["runs"]
    aa = runs["antialias"]["history"]
    noaa = runs["no antialias"]["history"] if "no antialias" in runs else None
    header = ["iteration", "Chamfer, antialias", "ms / iteration, antialias"]
    start = ["start", runs["antialias"]["initial"], ""]
    if noaa is not None:
        header += ["Chamfer, no antialias", "ms / iteration, no antialias"]
        start += [runs["no antialias"]["initial"], ""]
    rows = [start]
    for i in common.checkpoints(len(aa.rows)):
        row = [i + 1, aa.rows[i][0], aa.seconds[i] * 1e3]
        if noaa is not None:
            row += [noaa.rows[i][0], noaa.seconds[i] * 1e3]
        rows.append(row)
    param = (f"the large-steps parametrisation (lambda {args.smooth:g})" if args.smooth > 0
             else "plain per-vertex offsets")
    return (
        f"### Shape from silhouettes{' and shading' if args.w_shading > 0 else ' only'} "
        f"({result['target']}, {args.views} views, "
        f"{args.resolution}², {args.iterations} iterations)\n\n"
        f"An icosphere ({args.subdivisions} subdivisions, radius {args.radius:g}) deformed "
        f"by Adam (learning rate {args.lr:g}, cosine decay) through {param}: silhouette "
        f"pyramid loss ({args.levels} levels, weight {args.w_silhouette:g}) against "
        f"4x-supersampled target coverage, headlight shading (weight {args.w_shading:g}), "
        f"uniform Laplacian ({args.w_lap:g}) and edge-length ({args.w_edge:g}) "
        "regularisers. Chamfer = mean nearest distance target -> mesh + mesh -> target "
        f"over {args.points} points sampled on each surface (`trimesh.sample`), target in "
        f"the unit sphere; two samples of the target itself score {result['floor']:.4f} "
        f"(the floor; {result['fine_floor']:.4f} with the {args.final_points} points of the "
        "final evaluation). The `antialias=False` run is the same optimisation with only that "
        "flag changed: its silhouette term has no gradient. Iteration = after that many "
        "steps; times exclude the Chamfer evaluation.\n\n"
        + common.markdown_table(header, rows)
        + "\n\n" + summary(result).replace("\n", "  \n")
        + (f"\n\n![start / target / results](images/{args.picture.name})"
           if args.picture is not None else "")
    )


if __name__ == "__main__":
    main()
