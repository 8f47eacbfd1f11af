"""Write one section of docs/benchmarks.md, leaving the other scripts' sections alone.

Each benchmark script owns a section between ``<!-- begin NAME -->`` and ``<!-- end NAME -->``
markers. The section is stamped with the command that produced it and the machine it ran on.
"""

from __future__ import annotations

import os
import platform
import re
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch

DOC = Path(__file__).resolve().parent.parent / "docs" / "benchmarks.md"
HEADER = (
    "# Benchmarks\n\n"
    "Every table below was printed and written by the script named in its section, on the "
    "machine stated there. Times are medians of repeated runs; compare ratios within one "
    "section (one run), not absolute times across sections.\n"
)


def machine() -> str:
    """One line describing the machine: CPU model, cores, torch version and threads."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (
        f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"torch {torch.__version__} ({torch.get_num_threads()} threads)"
    )


def update_section(name: str, body: str, command: str | None = None) -> None:
    """Replace (or append) section ``name`` of docs/benchmarks.md with ``body`` (Markdown)."""
    command = command or "python " + " ".join([os.path.relpath(sys.argv[0])] + sys.argv[1:])
    block = (
        f"<!-- begin {name} -->\n{body.rstrip()}\n\n"
        f"Command: `{command}`  \nMachine: {machine()}\n<!-- end {name} -->"
    )
    text = DOC.read_text() if DOC.exists() else HEADER
    tag = re.escape(name)
    pattern = re.compile(rf"<!-- begin {tag} -->.*?<!-- end {tag} -->", re.S)
    if pattern.search(text):
        text = pattern.sub(lambda _: block, text)
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    DOC.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=DOC.parent, suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, DOC)


def markdown_table(header: list[str], rows: list[list[object]]) -> str:
    """Format rows as a Markdown table (floats with 4 significant digits)."""

    def fmt(v: object) -> str:
        return f"{v:.4g}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def median_time(fn: Callable[[], object], repeats: int, warmup: bool = True) -> float:
    """Median wall time (s) of ``repeats`` calls of ``fn``, after one warm-up call."""
    if warmup:
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)
