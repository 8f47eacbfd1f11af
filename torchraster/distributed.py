"""Rendering a dataset across processes and machines with PyTorch's own launcher.

``torchrun --nproc-per-node N -m torchraster render CONFIG... --out DIR`` starts N copies
of the command; each joins the process group (gloo, from torchrun's environment:
``RANK``, ``WORLD_SIZE``, ``MASTER_ADDR``, ...), and :func:`render_dataset` then

1. lists every view of every config (config, object, camera) in one fixed order, the same
   in every process (checked: a rank that sees other files stops the run);
2. scans for views already done (``manifest.jsonl`` and the record shards: see
   :mod:`torchraster.manifest`), each rank a strided slice, and gathers the result;
3. splits the views still to render into N contiguous blocks (neighbouring views share an
   object, so each rank loads few scenes): rank r renders block r, writing each view's files
   atomically and appending its record to the rank's own shard file (one writer thread
   per rank writes view i, files then record, while view i + 1 renders);
4. shows, on rank 0 only, the global progress (views done / total, views per second, ETA),
   from an asynchronous ``all_reduce`` of the ranks' counts after each view;
5. waits for every rank (barrier); rank 0 merges the shards into ``manifest.jsonl``.

A world of one process (plain ``torchraster render``) needs no process group. Two ranks
never write the same file: views are disjoint, shards are per process, only rank 0 writes
the manifest.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import itertools
import math
import os
import sys
import time
import traceback
import warnings
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import torch

from . import manifest, pipeline
from .config import RenderFile


class RankMismatchError(RuntimeError):
    """The ranks of a run do not see the same views (not a shared filesystem?)."""


@dataclass
class World:
    """This process's place among the processes of a run.

    Attributes:
        rank: this process, in ``[0, size)``.
        size: the number of processes.
        owned: the process group was created by :func:`init_world` (and is destroyed by
            :meth:`close`).
    """

    rank: int = 0
    size: int = 1
    owned: bool = False

    @property
    def distributed(self) -> bool:
        return self.size > 1

    def all_gather(self, obj: object) -> list:
        """``obj`` of every rank, in rank order (picklable objects)."""
        if not self.distributed:
            return [obj]
        out: list = [None] * self.size
        torch.distributed.all_gather_object(out, obj)
        return out

    def all_sum(self, values: list[int]) -> list[int]:
        """Element-wise sums over the ranks of a list of ints."""
        if not self.distributed:
            return list(values)
        t = torch.tensor(values, dtype=torch.int64)
        torch.distributed.all_reduce(t)
        return [int(v) for v in t]

    def barrier(self) -> None:
        if self.distributed:
            torch.distributed.barrier()

    def close(self) -> None:
        """Leave the process group if this object created it."""
        if self.owned and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()
        self.owned = False


def init_world(backend: str = "gloo") -> World:
    """Join the process group of a ``torchrun`` launch, or describe the one that is already
    initialised, or a world of one process (``WORLD_SIZE`` unset or 1: nothing is
    initialised).

    Args:
        backend: the ``torch.distributed`` backend (gloo runs on CPU everywhere).

    Raises:
        RuntimeError: ``WORLD_SIZE`` > 1 but this torch has no ``torch.distributed``.
    """
    dist = torch.distributed
    if dist.is_available() and dist.is_initialized():
        return World(dist.get_rank(), dist.get_world_size())
    size = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if size <= 1:
        return World()
    if not dist.is_available():
        raise RuntimeError(f"WORLD_SIZE={size} but this torch build has no torch.distributed")
    dist.init_process_group(backend)
    return World(dist.get_rank(), dist.get_world_size(), owned=True)


def current_rank_and_size() -> tuple[int, int]:
    """``(rank, world size)`` of the initialised process group, else ``(0, 1)``."""
    dist = torch.distributed
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def block(n: int, rank: int, size: int) -> range:
    """Rank ``rank``'s contiguous share of ``n`` items split over ``size`` ranks (sizes
    differ by at most one)."""
    return range(n * rank // size, n * (rank + 1) // size)


class GlobalProgress:
    """Progress of the whole run, shown by rank 0 only.

    Each rank calls :meth:`step` after each of its views; in a distributed run that posts an
    asynchronous ``all_reduce`` of the rank's count (ranks keep rendering; the sums arrive
    in order), and rank 0 moves its bar to the latest global sum that has arrived. Every
    rank posts the same number of reductions (:meth:`finish` pads), as collectives require.

    Args:
        world: the processes.
        total: views of the run; ``done``: of which already done before it started.
        steps: reductions each rank posts (the largest block of views).
        enabled: show a bar at all (on rank 0).
    """

    def __init__(self, world: World, total: int, done: int, steps: int, enabled: bool = True):
        from tqdm import tqdm

        self.world, self.done, self.steps = world, done, steps
        self.local = self.posted = 0
        self._pending: deque = deque()
        self.bar = tqdm(total=total, initial=done, unit="view", file=sys.stderr,
                        disable=world.rank != 0 or not enabled or total - done < 2,
                        smoothing=0.1)

    def write(self, text: str) -> None:
        """Print a line without breaking the bar (any rank)."""
        self.bar.write(text, file=sys.stderr)

    @contextlib.contextmanager
    def redirect_output(self) -> Iterator[None]:
        """Within the block, log records of the root logger's console handlers and Python
        warnings are printed through :meth:`write` (tqdm's ``write``: the bar is cleared,
        the line printed, the bar redrawn), never onto the bar's line."""
        from tqdm.contrib.logging import logging_redirect_tqdm

        def show(message, category, filename, lineno, file=None, line=None):  # noqa: ANN001
            self.write(warnings.formatwarning(message, category, filename, lineno,
                                              line).rstrip("\n"))

        with logging_redirect_tqdm(), warnings.catch_warnings():
            warnings.showwarning = show
            yield

    def step(self) -> None:
        """One more view of this rank is finished (written or failed)."""
        self.local += 1
        self._post()

    def _post(self) -> None:
        if not self.world.distributed:
            self.bar.update(1)
            return
        if self.posted >= self.steps:
            return
        t = torch.tensor([self.local], dtype=torch.int64)
        self._pending.append((torch.distributed.all_reduce(t, async_op=True), t))
        self.posted += 1
        self._poll(wait=False)

    def _poll(self, wait: bool) -> None:
        while self._pending and (wait or self._pending[0][0].is_completed()):
            work, t = self._pending.popleft()
            work.wait()
            target = self.done + int(t[0])
            if target > self.bar.n:
                self.bar.update(target - self.bar.n)

    def finish(self) -> None:
        """Post the remaining reductions, wait for all of them and close the bar."""
        while self.world.distributed and self.posted < self.steps:
            self._post()
        self._poll(wait=True)
        self.bar.close()


@dataclass
class DatasetConfig:
    """One config of a run: its file (for messages), its output folder name, the config."""

    path: Path
    name: str
    cfg: RenderFile


@dataclass
class RunSummary:
    """Global counts of a run (the same on every rank).

    Attributes:
        total: views of all configs; ``skipped``: already done; ``written``: rendered now;
        ``failed``: reported and left out of the manifest; ``seconds``: wall time of the
        whole call (listing, scan, rendering, manifest); ``render_seconds``: of the
        rendering alone (from the end of the scan until every rank is done);
        ``render_cpu_seconds``: CPU time of the rendering, summed over the ranks.
    """

    total: int = 0
    skipped: int = 0
    written: int = 0
    failed: int = 0
    seconds: float = 0.0
    render_seconds: float = 0.0
    render_cpu_seconds: float = 0.0

    @property
    def views_per_second(self) -> float:
        """Views written per second of rendering (all ranks together)."""
        return self.written / self.render_seconds if self.render_seconds > 0 else 0.0


@dataclass
class _Job:
    """One view to render: where it comes from, its key and what its record must say."""

    config: int
    obj: int
    spec: pipeline.ViewSpec
    key: str
    expected: dict = field(repr=False)


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split()) or type(e).__name__
    return text if isinstance(e, (ValueError, OSError, MemoryError)) else (
        f"{type(e).__name__}: {text}")


def seeded_call(seed: int, fn: Callable[[], object]) -> object:
    """``fn()`` with torch's CPU generator seeded with ``seed`` (its state restored after):
    the same view renders the same whichever process renders it, and in whatever order."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return fn()


def render_dataset(configs: list[DatasetConfig], out_dir: str | Path, *,
                   device: str | torch.device = "cpu", force: bool = False,
                   world: World | None = None, verbose: bool = False,
                   show_traceback: bool = False, progress: bool = True,
                   log: Callable[[str], None] | None = None) -> RunSummary:
    """Render the views of ``configs`` not done yet into ``out_dir``, this rank's share of
    them, and (rank 0) write ``out_dir/manifest.jsonl``. Every rank must call it with the
    same arguments. One failing view (or object) is reported and the others render.

    Args:
        configs: the configs, validated and checked (``check_config``), names unique.
        out_dir: the output folder; config ``c`` writes to ``out_dir/<c.name>/``.
        device: where to render.
        force: render every view, done or not.
        world: the processes (default: :func:`init_world`).
        verbose: print each view's render plan and files.
        show_traceback: print the traceback of a failing view.
        progress: show the global progress bar (rank 0).
        log: where lines go (default: stderr, above the bar).

    Returns:
        The global :class:`RunSummary`.

    Raises:
        RankMismatchError: the ranks do not see the same views (different files, not a
            shared filesystem?).
        OutputError: the manifest cannot be written.
    """
    if world is not None:
        return _render_dataset(configs, out_dir, device, force, world, verbose,
                               show_traceback, progress, log)
    # a process group made here is left here: a process exiting with gloo's threads still
    # running may abort ("terminate called without an active exception") after its work
    world = init_world()
    try:
        return _render_dataset(configs, out_dir, device, force, world, verbose,
                               show_traceback, progress, log)
    finally:
        world.close()


def _render_dataset(configs: list[DatasetConfig], out_dir: str | Path,
                    device: str | torch.device, force: bool, world: World, verbose: bool,
                    show_traceback: bool, progress: bool,
                    log: Callable[[str], None] | None) -> RunSummary:
    """:func:`render_dataset` in the given ``world``."""
    start = time.perf_counter()
    out_dir = Path(out_dir)
    jobs, plans = [], []
    for ci, dc in enumerate(configs):
        objects = pipeline.plan_objects(dc.cfg)
        plans.append(objects)
        for oi, obj in enumerate(objects):
            h = manifest.config_hash(obj.config)
            for spec in obj.views:
                jobs.append(_Job(ci, oi, spec, manifest.view_key(dc.name, spec),
                                 manifest.expected_fields(h, spec)))
    digest = (len(jobs), hashlib.sha256("\n".join(
        f"{j.key} {j.expected['config_hash']}" for j in jobs).encode()).hexdigest()[:16])
    seen = world.all_gather(digest)
    if any(d != seen[0] for d in seen):
        raise RankMismatchError(f"the ranks see different views (count and hash per rank: "
                                f"{seen}); every rank needs the same configs and mesh files "
                                "(a shared filesystem)")
    # scan: each rank checks a strided slice, then all agree on what is left
    done_here, records = [], {}
    if not force:
        records = manifest.load_records(out_dir)
        done_here = [i for i in range(world.rank, len(jobs), world.size)
                     if manifest.is_done(records.get(jobs[i].key), jobs[i].expected, out_dir)]
    done = {i for part in world.all_gather(done_here) for i in part}
    pending = [i for i in range(len(jobs)) if i not in done]
    render_start, cpu_start = time.perf_counter(), time.process_time()
    mine = [pending[k] for k in block(len(pending), world.rank, world.size)]
    steps = math.ceil(len(pending) / world.size)
    bar = GlobalProgress(world, len(jobs), len(done), steps, enabled=progress)
    say = log or bar.write
    prefix = f"[rank {world.rank}] " if world.distributed else ""
    written = failed = 0
    reported: set = set()
    shard = manifest.ShardWriter(out_dir)
    try:  # one object at a time: its scene loads once for its consecutive views
        with bar.redirect_output(), writer_core():  # warnings above the bar, not onto its line
            for (ci, oi), grouped in itertools.groupby((jobs[i] for i in mine),
                                                       key=lambda j: (j.config, j.obj)):
                w, f = _render_group(list(grouped), configs[ci], plans[ci][oi], out_dir,
                                     device, world, shard, bar, say, prefix, verbose,
                                     show_traceback, reported)
                written, failed = written + w, failed + f
    finally:
        shard.close()
    bar.finish()
    cpu_us = round((time.process_time() - cpu_start) * 1e6)
    written, failed, cpu_us = world.all_sum([written, failed, cpu_us])  # all ranks done
    render_seconds = time.perf_counter() - render_start
    if world.rank == 0:
        expected = {j.key: j.expected for j in jobs}
        manifest.write_manifest(out_dir, expected, {dc.name for dc in configs},
                                records=None if force else records)
        write_exports(out_dir, configs, say)
    return RunSummary(len(jobs), len(done), written, failed, time.perf_counter() - start,
                      render_seconds, cpu_us / 1e6)


def write_exports(out_dir: Path, configs: list[DatasetConfig],
                  say: Callable[[str], None] = print) -> list[Path]:
    """Write the ``outputs.exports`` of ``configs`` from the manifest of ``out_dir`` (each
    format once, over the records of every config that asks for it; a failing export is
    reported and the others are written). Returns the written paths."""
    from . import export

    points = next((dc.cfg.outputs.track_points for dc in configs
                   if "tracks" in dc.cfg.outputs.exports), 256)
    writers = {"coco": export.write_coco, "bop": export.write_bop, "nerf": export.write_nerf,
               "webdataset": export.write_webdataset,
               "tracks": lambda out, recs: export.write_tracks(out, recs, n_points=points)}
    wanted: dict[str, set[str]] = {}
    for dc in configs:
        for fmt in dc.cfg.outputs.exports:
            wanted.setdefault(fmt, set()).add(dc.name)
    if not wanted:
        return []
    records = manifest.read_manifest(out_dir)
    written = []
    for fmt, names in wanted.items():
        mine = [r for r in records if r.get("config") in names]
        if not mine:
            continue
        try:
            written += writers[fmt](out_dir, mine)
        except (ValueError, OSError, ImportError) as e:
            say(f"torchraster: error: export {fmt}: {_one_line(e)}")
    return written


@contextlib.contextmanager
def writer_core() -> Iterator[int]:
    """Leave one core to the writer thread while the views render: torch's intra-op threads
    are set to one fewer than this process's cores when they would use them all (and
    ``OMP_NUM_THREADS`` does not fix them), then restored. Yields the threads in use.

    A view's files are encoded in a writer thread while the next view renders; with every
    core in torch's thread pool the two contend (each parallel op waits at a barrier for a
    descheduled thread). On 2 cores (configs/dataset_movi.yaml, docs/benchmarks.md, dataset)
    a steady frame took 184 ms with 2 torch threads and 135 ms with 1 beside the writer.
    Every view of a run renders with the same thread count (reductions split by thread
    could otherwise round differently in a view re-rendered alone).
    """
    threads = torch.get_num_threads()
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
        os.cpu_count() or 1)
    if threads < 2 or threads < cores or "OMP_NUM_THREADS" in os.environ:
        yield threads
        return
    torch.set_num_threads(threads - 1)
    try:
        yield threads - 1
    finally:
        torch.set_num_threads(threads)


def _render_group(group: list[_Job], dc: DatasetConfig, obj: pipeline.ObjectPlan,
                  out_dir: Path, device, world: World, shard: manifest.ShardWriter,
                  bar: GlobalProgress, say: Callable[[str], None], prefix: str, verbose: bool,
                  show_traceback: bool, reported: set) -> tuple[int, int]:
    """Render the views of one object; returns (written, failed)."""
    cfg = obj.config.model_copy(update={"cameras": [j.spec.camera_config for j in group]})
    where = f"{dc.path} [object {obj.name}]" if "/" in obj.views[0].folder else str(dc.path)
    try:
        render = pipeline.view_renderer(cfg, device)
        renders = [functools.partial(render, j.spec.camera_config, j.spec.folder or j.spec.camera,
                                     j.spec.frame) for j in group]
    except Exception as e:  # noqa: BLE001 (one bad object never stops the others)
        message = _one_line(e)
        if (dc.name, message) not in reported:  # e.g. a bad environment: once per config
            reported.add((dc.name, message))
            say(f"{prefix}torchraster: error: {where}: {message}")
            if show_traceback:
                say(traceback.format_exc())
        for _ in group:
            bar.step()
        return 0, len(group)
    written = failed = 0
    cfg_hash = group[0].expected["config_hash"]

    def report(spec: pipeline.ViewSpec, e: Exception) -> None:
        nonlocal failed
        failed += 1
        name = f"object {spec.object}, camera {spec.camera}" if "/" in spec.folder else (
            f"camera {spec.camera}")
        say(f"{prefix}torchraster: error: {dc.path} [{name}]: {_one_line(e)}")
        if show_traceback:
            say("".join(traceback.format_exception(e)))

    def store(job: _Job, result: pipeline.ViewResult, render_s: float) -> list[Path]:
        """Write a view's files, then its record (in the writer thread)."""
        t1 = time.perf_counter()
        files = pipeline.write_outputs(result, out_dir / job.key, cfg.outputs.formats,
                                       cfg.outputs.previews, cfg.outputs.png_compression)
        shard.append(manifest.view_record(
            key=job.key, config=dc.name, config_file=dc.path, cfg=obj.config,
            cfg_hash=cfg_hash, spec=job.spec, mesh=obj.mesh, result=result, files=files,
            out_dir=out_dir, timings={"render_s": render_s, "write_s": time.perf_counter() - t1},
            rank=world.rank, drawn=obj.drawn))
        return files

    def finish(job: _Job, result: pipeline.ViewResult, future: Future) -> None:
        nonlocal written
        try:
            files = future.result()
            written += 1
            if verbose:
                say(f"{prefix}{dc.path} [{job.spec.folder or job.spec.camera}]: {result.plan}")
                for p in files:
                    say(str(p))
        except Exception as e:  # noqa: BLE001 (one bad view never stops the others)
            report(job.spec, e)
        bar.step()

    # one writer thread: view i's files are written while view i + 1 renders (files, then
    # the record, in view order, as before; at most one view waits to be written)
    pending: tuple | None = None
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="torchraster-write") as writer:
        for job, render in zip(group, renders, strict=True):
            try:
                t0 = time.perf_counter()
                result = seeded_call(job.spec.seed, render)
                render_s = time.perf_counter() - t0
            except Exception as e:  # noqa: BLE001 (one bad view never stops the others)
                if pending is not None:
                    finish(*pending)
                    pending = None
                report(job.spec, e)
                bar.step()
                continue
            future = writer.submit(store, job, result, render_s)
            if pending is not None:
                finish(*pending)
            pending = (job, result, future)
        if pending is not None:
            finish(*pending)
    return written, failed


__all__ = ["DatasetConfig", "GlobalProgress", "RankMismatchError", "RunSummary", "World",
           "block", "write_exports",
           "current_rank_and_size", "init_world", "render_dataset", "seeded_call"]
