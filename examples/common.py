"""Shared pieces of the inverse-rendering examples: meshes, the per-iteration table, timing,
pictures and the benchmark section.

The examples import this module by path (``examples/`` is not a package); nothing here
is specific to one optimisation.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import trimesh

import torchraster as tr
from torchraster.post import encode_srgb
from torchraster.testing.assets import data_dir

ROOT = Path(__file__).resolve().parents[1]
BUNNY = data_dir() / "meshes" / "stanford-bunny.obj"  # optional ($TORCHRASTER_DATA)


def add_common_args(parser: argparse.ArgumentParser, *, iterations: int, resolution: int,
                    views: int, out: str) -> None:
    """The options every example takes: sizes, threads, seed, output folder, benchmark."""
    parser.add_argument("--iterations", type=int, default=iterations,
                        help=f"optimisation steps (default {iterations})")
    parser.add_argument("--resolution", type=int, default=resolution,
                        help=f"image side in pixels (default {resolution})")
    parser.add_argument("--views", type=int, default=views, help=f"views (default {views})")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch intra-op threads (default 1: fastest for small renders "
                             "on a 2-core machine, see README 'Threads')")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--log-every", type=int, default=10,
                        help="print a table row every N iterations (default 10)")
    parser.add_argument("--out", type=Path, default=Path(out),
                        help=f"folder for the start / target / result pictures (default {out})")
    parser.add_argument("--picture", type=Path, default=None,
                        help="also write the start / target / result strip to this PNG "
                             "(e.g. docs/images/inverse_pose.png)")
    parser.add_argument("--benchmark", action="store_true",
                        help="write this run's figures into docs/benchmarks.md")
    parser.add_argument("--quiet", action="store_true", help="print nothing")


def setup(args: argparse.Namespace) -> None:
    """Apply ``--threads`` and ``--seed``."""
    torch.set_num_threads(max(1, args.threads))
    torch.manual_seed(args.seed)


def normalized(vertices: np.ndarray) -> np.ndarray:
    """Vertices centred on their bounding box and scaled into the unit sphere."""
    v = np.asarray(vertices, dtype=np.float64)
    v = v - (v.min(0) + v.max(0)) / 2
    return v / np.linalg.norm(v, axis=1).max()


def load_target(name: str) -> tuple[trimesh.Trimesh, str]:
    """A target mesh, normalised into the unit sphere: ``"bunny"`` (the Stanford bunny of
    $TORCHRASTER_DATA; Spot when that file is absent), ``"spot"`` (shipped), ``"ellipsoid"``
    (an analytic stretched icosphere, for tests) or a mesh file path.

    Returns:
        The mesh and the name of what was actually loaded.
    """
    if name == "bunny" and not BUNNY.is_file():
        name = "spot"
    if name == "ellipsoid":
        mesh = trimesh.creation.icosphere(subdivisions=3)
        mesh.vertices = mesh.vertices * np.array([1.0, 0.55, 0.75])
        # a bump, so that the shape is not convex
        bump = np.exp(-((mesh.vertices - [0.6, 0.3, 0.3]) ** 2).sum(1) / 0.08)
        mesh.vertices = mesh.vertices + 0.35 * bump[:, None] * mesh.vertex_normals
    elif name == "spot":
        spot = tr.load_spot(max_texture_size=8)
        mesh = trimesh.Trimesh(spot.positions.numpy(), spot.faces.numpy(), process=False)
    else:
        loaded = tr.load_mesh(BUNNY if name == "bunny" else name)
        mesh = trimesh.Trimesh(loaded.positions.numpy(), loaded.faces.numpy(), process=False)
        mesh.remove_unreferenced_vertices()
    return trimesh.Trimesh(normalized(mesh.vertices), mesh.faces, process=False), name


def as_mesh(mesh: trimesh.Trimesh) -> tr.Mesh:
    """A trimesh as an untextured :class:`torchraster.Mesh` (float32)."""
    return tr.Mesh(torch.tensor(mesh.vertices, dtype=torch.float32),
                   torch.tensor(mesh.faces, dtype=torch.int64))


def ring_views(count: int, distance: float, elevations: Sequence[float],
               target: torch.Tensor | None = None, offset_deg: float = 0.0) -> torch.Tensor:
    """``count`` world -> view matrices ``(count, 4, 4)`` orbiting ``target`` (default the
    origin), evenly spread in azimuth from ``offset_deg``, cycling through ``elevations``
    (degrees)."""
    az = torch.arange(count, dtype=torch.float32) * (360.0 / max(1, count)) + offset_deg
    el = torch.tensor([elevations[i % len(elevations)] for i in range(count)],
                      dtype=torch.float32)
    return tr.camera.orbit(az, el, torch.full((count,), distance), target=target)


def pyramid_loss(image: torch.Tensor, target: torch.Tensor, levels: int) -> torch.Tensor:
    """Sum over ``levels`` box-filtered levels (1, 2, 4, ... px) of the mean squared
    difference of two ``(B, C, H, W)`` images: the coarse levels see a misplaced
    silhouette from further away."""
    loss = image.new_zeros(())
    for level in range(levels):
        k = 2 ** level
        a, b = (F.avg_pool2d(image, k), F.avg_pool2d(target, k)) if k > 1 else (image, target)
        loss = loss + ((a - b) ** 2).mean()
    return loss


@dataclass
class History:
    """Per-iteration records of an optimisation: the metric columns and the step time."""

    columns: list[str]
    rows: list[list[float]] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)

    def column(self, name: str) -> list[float]:
        """All values of one metric column."""
        k = self.columns.index(name)
        return [r[k] for r in self.rows]

    @property
    def ms_per_iteration(self) -> float:
        """Median step time (ms) over the run (the first step, which warms up, excluded)."""
        times = self.seconds[1:] or self.seconds
        return float(np.median(times)) * 1e3 if times else float("nan")


class Table:
    """Prints a per-iteration table (metric columns and ms per iteration) as it goes."""

    def __init__(self, columns: list[str], every: int, quiet: bool = False) -> None:
        self.history = History(list(columns))
        self.every = max(1, every)
        self.quiet = quiet
        self._last = time.perf_counter()
        self._step: float | None = None
        if not quiet:
            print(" ".join(f"{c:>14}" for c in ["iteration", *columns, "ms/iter"]))

    def tick(self) -> None:
        """Start timing an iteration (call before the step's work)."""
        self._last = time.perf_counter()

    def tock(self) -> float:
        """Stop timing the iteration (call after the step, before computing metrics that
        are not part of it); returns its seconds."""
        self._step = time.perf_counter() - self._last
        return self._step

    def record(self, iteration: int, values: Sequence[float], last: bool = False) -> None:
        """Record the metrics after ``iteration`` and the step time (from :meth:`tick` to
        :meth:`tock`, or to now); print a row every ``every`` iterations and on the last."""
        dt = self._step
        if dt is None:
            dt = time.perf_counter() - self._last
        self._step = None
        self.history.rows.append([float(v) for v in values])
        self.history.seconds.append(dt)
        if not self.quiet and (iteration % self.every == 0 or last):
            cells = [f"{iteration:>14d}"] + [f"{v:>14.5g}" for v in values]
            print(" ".join(cells + [f"{dt * 1e3:>14.1f}"]), flush=True)


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """Linear ``(3, H, W)`` or ``(1, H, W)`` image in [0, 1] -> sRGB ``(H, W, 3)`` uint8."""
    image = image.detach().float().cpu()
    if image.shape[0] == 1:
        image = image.expand(3, -1, -1)
    srgb = encode_srgb(image[None])[0]
    return (srgb.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)


def save_strip(path: Path, panels: Sequence[tuple[str, np.ndarray]]) -> None:
    """Write labelled ``(H, W, 3)`` uint8 panels side by side (or one row per list item
    when the panels are rows of equal width) as a PNG."""
    from PIL import Image, ImageDraw

    label_h = 16
    h = max(p.shape[0] for _, p in panels)
    w = sum(p.shape[1] for _, p in panels)
    canvas = Image.new("RGB", (w, h + label_h), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    x = 0
    for label, pixels in panels:
        canvas.paste(Image.fromarray(pixels), (x, label_h))
        draw.text((x + 4, 2), label, fill=(0, 0, 0))
        x += pixels.shape[1]
    path.parent.mkdir(parents=True, exist_ok=True)
    canvas.save(path, optimize=True)


def stack_rows(rows: Sequence[np.ndarray]) -> np.ndarray:
    """Stack ``(H, W, 3)`` images of one width vertically."""
    return np.concatenate(list(rows), axis=0)


def finish(args: argparse.Namespace, result: dict, picture: str, summary: str,
           section: str, body: Callable[[], str]) -> dict:
    """The end of every example: write the pictures (``result["panels"]``) to
    ``--out``/``picture`` and ``--picture``, print ``summary`` (unless ``--quiet``) and,
    with ``--benchmark``, write ``body()`` as section ``section`` of docs/benchmarks.md."""
    if "panels" in result:
        if args.out is not None:
            save_strip(args.out / picture, result["panels"])
        if args.picture is not None:
            save_strip(args.picture, result["panels"])
    if not args.quiet:
        print(summary)
    if args.benchmark:
        write_benchmark(section, body())
    return result


def write_benchmark(name: str, body: str) -> None:
    """Replace (or append) section ``name`` of docs/benchmarks.md, stamped with the command
    and the machine (``scripts/benchmd.py``: re-reads the file and rewrites it atomically)."""
    sys.path.insert(0, str(ROOT / "scripts"))
    import benchmd

    benchmd.update_section(name, body)


def markdown_table(header: list[str], rows: list[list[object]]) -> str:
    """A Markdown table (floats with 4 significant digits), as in ``scripts/benchmd.py``."""
    sys.path.insert(0, str(ROOT / "scripts"))
    import benchmd

    return benchmd.markdown_table(header, rows)


def checkpoints(iterations: int) -> list[int]:
    """The iterations a summary table shows: 0, a few along the way and the last."""
    marks = {0, iterations - 1}
    for frac in (0.05, 0.1, 0.25, 0.5, 0.75):
        marks.add(int(round(frac * (iterations - 1))))
    return sorted(m for m in marks if 0 <= m < iterations)
