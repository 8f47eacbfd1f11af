"""Dataset-scale rendering: views per second with 1 and 2 processes, and the cost of resuming.

* A 200-view job (20 generated objects x 10 random orbits, 64², color + depth + normal
  PNG) rendered by ``python -m torchraster render`` (1 process) and by ``torchrun
  --nproc-per-node 2 -m torchraster render`` (2 processes), one thread each
  (``OMP_NUM_THREADS=1``), the two alternated, each run into a fresh folder: wall time of
  the command, the rendering time it reports (from the end of the done-scan until every
  rank is done: without interpreter start-up, imports and rendezvous) and the CPU time of
  all its processes per view.
* Resuming a 10k-view job (100 objects x 100 random orbits) whose views are all done (a
  10k-record manifest, every file present): the plan (views, config hashes), reading the
  records, the done-scan (one folder listing per view), and the whole command, which
  renders nothing, against the command on a 1-view job (start-up alone).

    python scripts/bench_scale.py            # full run, updates docs/benchmarks.md
    python scripts/bench_scale.py --quick    # 1 repeat, 40 + 1k views, no doc update
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import trimesh
from benchmd import markdown_table, median_time, update_section

import torchraster as tr
from torchraster import manifest
from torchraster.pipeline import ViewResult, plan_objects

JOB = """\
scene:
  mesh: objects/*.obj
cameras:
  - random_orbits: {{count: {views}, seed: 0, elevation_deg: [-10, 50]}}
render:
  resolution: {resolution}
outputs:
  channels: [color, depth, normal]
  formats: [png]
"""


def make_objects(folder: Path, count: int, seed: int = 0) -> None:
    """``count`` small meshes (0.3k-5k faces): bumpy spheres, boxes, capsules, cylinders."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for i in range(count):
        kind = i % 4
        if kind == 0:
            m = trimesh.creation.icosphere(subdivisions=int(rng.integers(2, 5)))
            m.vertices *= 1 + 0.15 * np.sin(5 * m.vertices[:, :1] + rng.uniform(0, 6))
        elif kind == 1:
            m = trimesh.creation.box(extents=rng.uniform(0.5, 1.5, 3))
        elif kind == 2:
            m = trimesh.creation.capsule(height=rng.uniform(0.5, 2), count=[24, 24])
        else:
            m = trimesh.creation.cylinder(radius=0.5, height=rng.uniform(0.5, 2), sections=48)
        m.export(folder / f"object{i:04d}.obj")


def env() -> dict:
    e = {**os.environ, "OMP_NUM_THREADS": "1"}
    if sys.platform.startswith("linux"):
        e["GLOO_SOCKET_IFNAME"] = "lo"
    return e


def command(nproc: int, config: Path, out: Path) -> list[str]:
    if nproc == 1:
        head = [sys.executable, "-m", "torchraster"]
    else:
        head = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", str(nproc),
                "--rdzv-backend", "c10d", "--rdzv-endpoint", "127.0.0.1:0", "-m",
                "torchraster"]
    return [*head, "render", str(config), "--out", str(out)]


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run(cmd: list[str]) -> tuple[float, str, float]:
    """Wall time (s), stderr and CPU time (s, all its processes) of a command (which must
    succeed)."""
    cpu = _children_cpu()
    t = time.perf_counter()
    res = subprocess.run(cmd, env=env(), capture_output=True, text=True)
    wall = time.perf_counter() - t
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stderr[-3000:]}")
    return wall, res.stderr, _children_cpu() - cpu


def reported(stderr: str) -> tuple[int, float, float]:
    """(views written, seconds of rendering, CPU seconds of rendering) from the command's
    summary line."""
    m = re.search(r"(\d+) view\(s\) written.*rendering (\d+\.\d+) s, .* (\d+\.\d+) CPU s",
                  stderr)
    if m is None:
        raise RuntimeError(f"no summary line in:\n{stderr[-2000:]}")
    return int(m.group(1)), float(m.group(2)), float(m.group(3))


def bench_processes(root: Path, objects: int, views: int, repeats: int) -> tuple[list, float]:
    """Rows of the 1 vs 2 process table; returns (rows, seconds per view of 1 process)."""
    make_objects(root / "objects", objects)
    cfg = root / "job.yaml"
    cfg.write_text(JOB.format(views=views, resolution=64))
    total = objects * views
    walls: dict[int, list[float]] = {1: [], 2: []}
    inner: dict[int, list[float]] = {1: [], 2: []}
    cpus: dict[int, list[float]] = {1: [], 2: []}
    render_cpus: dict[int, list[float]] = {1: [], 2: []}
    for rep in range(repeats):
        for nproc in (1, 2) if rep % 2 == 0 else (2, 1):
            out = root / f"out{nproc}_{rep}"
            wall, err, cpu = run(command(nproc, cfg, out))
            written, seconds, render_cpu = reported(err)
            assert written == total, err[-2000:]
            walls[nproc].append(wall)
            inner[nproc].append(seconds)
            cpus[nproc].append(cpu)
            render_cpus[nproc].append(render_cpu)
            shutil.rmtree(out)
            print(f"  {nproc} process(es), run {rep + 1}: {wall:.1f} s wall, "
                  f"{seconds:.1f} s rendering, {cpu:.1f} s CPU", flush=True)
    rows = []
    for nproc in (1, 2):
        wall, seconds = statistics.median(walls[nproc]), statistics.median(inner[nproc])
        rows.append([nproc, total, wall, total / wall, seconds, total / seconds,
                     statistics.median(inner[1]) / seconds,
                     statistics.median(cpus[nproc]) / total * 1e3,
                     statistics.median(render_cpus[nproc]) / total * 1e3])
    return rows, statistics.median(inner[1]) / total


def fake_done(root: Path, objects: int, views: int) -> Path:
    """A job of objects x views whose views are all done: files present and a manifest
    of matching records (written the way a run writes them). Returns the config."""
    src = root / "objects"
    src.mkdir(parents=True)
    trimesh.creation.icosphere(subdivisions=1).export(src / "object0000.obj")
    for i in range(1, objects):
        shutil.copy(src / "object0000.obj", src / f"object{i:04d}.obj")
    cfg_path = root / "job.yaml"
    cfg_path.write_text(JOB.format(views=views, resolution=64))
    cfg = tr.load_config(cfg_path)
    out = root / "out"
    shard = manifest.ShardWriter(out)
    expected = {}
    eye = torch.eye(4)
    proj = tr.camera.perspective(45.0, 1.0, 0.1)[0]
    for obj in plan_objects(cfg):
        h = manifest.config_hash(obj.config)
        for spec in obj.views:
            key = manifest.view_key("job", spec)
            folder = out / key
            folder.mkdir(parents=True)
            files = []
            for name in ("color.png", "depth.png", "normal.png"):
                (folder / name).write_bytes(b"")
                files.append(folder / name)
            result = ViewResult(spec.camera, {}, None, view=eye, proj=proj)  # type: ignore
            shard.append(manifest.view_record(
                key=key, config="job", config_file=cfg_path, cfg=obj.config, cfg_hash=h,
                spec=spec, mesh=obj.mesh, result=result, files=files, out_dir=out,
                timings={"render_s": 0.0, "write_s": 0.0}))
            expected[key] = manifest.expected_fields(h, spec)
    shard.close()
    manifest.write_manifest(out, expected, {"job"})
    return cfg_path


def bench_resume(root: Path, objects: int, views: int, repeats: int) -> list:
    """Rows of the resume table."""
    cfg_path = fake_done(root, objects, views)
    out = root / "out"
    cfg = tr.load_config(cfg_path)
    total = objects * views
    records: dict = {}

    def plan() -> list:
        return [(manifest.view_key("job", s), manifest.expected_fields(
            manifest.config_hash(o.config), s)) for o in plan_objects(cfg) for s in o.views]

    views_expected = plan()
    t_plan = median_time(plan, repeats, warmup=False)
    t_load = median_time(lambda: records.update(manifest.load_records(out)), repeats,
                         warmup=False)
    assert len(records) == total

    def scan() -> None:
        done = sum(manifest.is_done(records.get(k), e, out) for k, e in views_expected)
        assert done == total, done

    t_scan = median_time(scan, repeats, warmup=False)
    # the whole command with everything done, against a 1-view job (start-up alone)
    one = root / "one"
    one.mkdir()
    (one / "job.yaml").write_text(JOB.format(views=1, resolution=16).replace(
        "objects/*.obj", str((root / "objects" / "object0000.obj").as_posix())))
    run(command(1, one / "job.yaml", one / "out"))
    walls, base = [], []
    for _ in range(repeats):
        wall, err, _ = run(command(1, cfg_path, out))
        assert f"{total} already done" in err, err[-2000:]
        walls.append(wall)
        base.append(run(command(1, one / "job.yaml", one / "out"))[0])
    mb = (out / manifest.MANIFEST).stat().st_size / 1e6
    cli = statistics.median(walls) - statistics.median(base)
    return [[f"plan ({total} views: cameras, names, config hashes)", t_plan, t_plan / total],
            [f"read the records ({mb:.1f} MB manifest)", t_load, t_load / total],
            ["done-scan (one folder listing per view)", t_scan, t_scan / total],
            ["whole command, nothing to render, minus start-up "
             f"({statistics.median(base):.1f} s)", cli, cli / total]]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small jobs, 1 repeat, no doc update")
    args = p.parse_args()
    torch.set_num_threads(1)
    objects, views, big, repeats = (4, 10, (10, 100), 1) if args.quick else (
        20, 10, (100, 100), 5)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        print(f"{objects * views}-view job, 1 and 2 processes ...", flush=True)
        rows, per_view = bench_processes(tmp / "scale", objects, views, repeats)
        table1 = markdown_table(["processes", "views", "command s", "views/s (command)",
                                 "rendering s", "views/s (rendering)",
                                 "speed-up (rendering)", "CPU ms per view (command)",
                                 "CPU ms per view (rendering)"], rows)
        print(table1)
        load1 = os.getloadavg()
        print(f"resume scan, {big[0] * big[1]}-view job ...", flush=True)
        resume = bench_resume(tmp / "resume", *big, repeats)
        rows2 = [[name, s, us * 1e6, 100 * us / per_view] for name, s, us in resume]
        table2 = markdown_table(["step", "s", "µs per view", "% of rendering a view"], rows2)
        print(table2)
    load = os.getloadavg()
    if args.quick:
        return
    body = f"""## Dataset-scale rendering

`torchraster render` on a {objects * views}-view job ({objects} generated objects, 0.3k-5k
faces, x {views} random orbits; 64², color + depth + normal PNG) with 1 process and with
`torchrun --nproc-per-node 2` (gloo, rendezvous on 127.0.0.1), one thread per process
(`OMP_NUM_THREADS=1`), the two alternated, median of {repeats} runs each into a fresh folder.
"Command" is the whole command (interpreter start-up, imports, rendezvous, listing the
views, the done-scan, rendering, the manifest); "rendering" is the time the command reports
from the end of the done-scan until every rank is done (each rank pays its own warm-up:
lazy imports, first calls). CPU times change much less with the load of other
jobs than wall times: "CPU (command)" is the user + system time of all the command's
processes (torchrun's agent and each rank's start-up included) per view, "CPU (rendering)"
the CPU time of the rendering phase summed over the ranks, per view: equal for 1 and 2
processes when splitting the work costs nothing, so that on free cores the rendering
speed-up is the number of processes.

{table1}

Load average at the end of these runs (1/5/15 min): {load1[0]:.1f} / {load1[1]:.1f} /
{load1[2]:.1f} on {os.cpu_count()} cores. Where other jobs leave less than two free cores,
a second process only shares the same CPU time, and its wall-time speed-up stays near 1:
read the CPU columns for the cost of the split.

Resuming a {big[0] * big[1]:,}-view job ({big[0]} objects x {big[1]} random orbits) whose
views are all done: what a re-run does before it knows there is nothing to render, per view
and against the time one view takes to render in the job above
({per_view * 1e3:.0f} ms, 1 process). Median of {repeats}.

{table2}

Load average at the end (1/5/15 min): {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}; the
machine was shared with other jobs, so compare within a table.

**Across machines.** Run the same command on every node, e.g. 4 nodes of 8 processes:
`torchrun --nnodes 4 --nproc-per-node 8 --rdzv-backend c10d --rdzv-endpoint
node0.example:29400 --rdzv-id renders-1 -m torchraster render dataset.yaml --out
/shared/renders` (`GLOO_SOCKET_IFNAME` picks the network interface if the default one is
wrong). The configs, meshes, textures and `--out` must be on a shared filesystem (NFS,
Lustre, ...) that every node sees: each rank lists the views itself (globs, list files,
random orbits are deterministic) and the run stops before rendering if the ranks do not see
the same views (counts and hashes of keys and config hashes are compared; a mesh's size and
modification time are part of its hash). Each image is written to a temporary file and
renamed in its own folder (atomic on POSIX filesystems, NFS included); each process appends
its records to its own shard file (named by host, process id and start time); only rank 0
writes `manifest.jsonl`, after a barrier. If a node dies, its workers' views in flight leave
at most temporary files; torchrun's agents stop the job (with the default `--max-restarts
0`; ranks blocked in a collective are stopped by their agents or time out) and every view
finished before has its files and its record. Re-running the command, on any number of
nodes, renders exactly the views that are missing (temporary files are swept, finished views
are skipped) and rank 0 merges every shard into `manifest.jsonl`; with `--max-restarts N`
torchrun does that re-run itself."""
    update_section("scale", body)
    print("updated docs/benchmarks.md")


if __name__ == "__main__":
    main()
