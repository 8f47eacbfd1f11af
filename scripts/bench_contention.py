"""Contention benchmark: how much rasterize + interpolate slows down when other processes
share the cores, for ours (torch on 2 threads and on 1) and for Mesa's llvmpipe.

ML pipelines run the renderer beside data-loader workers and other jobs. Each row is timed
(``bench_raster.py``'s worker, in a fresh process: ours and llvmpipe in turns) while one
of these runs beside it:

* *quiet*: nothing;
* *busy loop*: one Python process spinning (``while True: pass``), like a CPU-bound
  data-loader worker;
* *torch process*: another PyTorch process on as many threads as cores, multiplying
  matrices in a loop (like a training step of another job, or a test run).

Rows: the 82k-face frame (512², batch 8: big ops) and a 5k-face sphere at 256², batch 1 (a
training loop with one small view per step: many small ops). Renderer settings: torch on 2
threads with OpenMP's default wait policy (a thread that finishes its share of an op spins
before it sleeps), the same with ``OMP_WAIT_POLICY=PASSIVE`` (it sleeps at once), and 1
thread; llvmpipe on as many threads. The slowdown of a condition is its median time over
the quiet one of the same setting, measured in the same run.

    python scripts/bench_contention.py [--repeats 7] [--no-write]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_raster import SUBDIV, run  # noqa: E402
from benchmd import markdown_table, update_section  # noqa: E402

LOADS = {
    "quiet": None,
    "busy loop": [sys.executable, "-c", "while True: pass"],
    "torch process": [sys.executable, "-c",
                      "import torch\n"
                      f"torch.set_num_threads({os.cpu_count() or 2})\n"
                      "a = torch.randn(768, 768)\n"
                      "while True: a = (a @ a).tanh()\n"],
}
ROWS = [("82k frame", "frame", SUBDIV["80k"], 512, 8), ("5k sphere", "sphere", SUBDIV["5k"],
                                                         256, 1)]


#: (label, torch threads, extra environment) of the renderer process.
SETTINGS = [("2, default", 2, {}), ("2, OMP_WAIT_POLICY=PASSIVE", 2,
                                     {"OMP_WAIT_POLICY": "PASSIVE"}), ("1", 1, {})]


def measure(row: tuple, threads: int, env: dict, load: list[str] | None,
            repeats: int) -> dict:
    """The row timed in a fresh process (environment ``env`` added) with ``load`` running
    beside it."""
    _, kind, subdiv, res, batch = row
    spec = {"kind": kind, "subdiv": subdiv, "res": res, "batch": batch, "threads": threads,
            "repeats": repeats, "gl": True}
    proc = subprocess.Popen(load, stdout=subprocess.DEVNULL) if load else None
    try:
        if proc is not None:
            time.sleep(1.0)  # let it start (imports) before timing
        return run(spec, extra_env=env)
    finally:
        if proc is not None:
            proc.kill()
            proc.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    table = []
    for row in ROWS:
        base: dict[str, dict] = {}
        for load_name, load in LOADS.items():
            for label, threads, env in SETTINGS:
                r = measure(row, threads, env, load, args.repeats)
                if load is None:
                    base[label] = r
                q = base[label]
                table.append([row[0], load_name, label, f"{r['ours_s'] * 1e3:.1f}",
                              f"{r['ours_s'] / q['ours_s']:.2f}x",
                              f"{r.get('gl_s', float('nan')) * 1e3:.1f}",
                              f"{r.get('gl_s', float('nan')) / q.get('gl_s', float('nan')):.2f}x"])
                print(" | ".join(table[-1]), flush=True)
    head = ["row", "beside", "threads (torch = llvmpipe)", "ours ms", "ours slowdown",
            "llvmpipe ms", "llvmpipe slowdown"]
    text = markdown_table(head, table)
    print(text)
    body = ("## Contention: speed beside other processes\n\n" + __doc__.split("\n\n", 1)[1]
            .rsplit("\n\n", 1)[0] + f"\n\n{args.repeats} calls per cell after a warm-up (median); "
            "slowdown = over the quiet cell of the same threads, same run.\n\n" + text + "\n")
    if not args.no_write:
        update_section("contention", body)


if __name__ == "__main__":
    main()
