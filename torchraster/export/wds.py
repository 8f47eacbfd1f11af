"""WebDataset shards of a rendered dataset (``exports/webdataset/shard-%06d.tar``).

One sample per view, in manifest order: its files as ``<key>.<file name>`` (e.g.
``view_0.color.png``, ``view_0.instance.npy``) and its record as ``<key>.json``. The key is
the view key with every run of characters other than letters, digits, ``_`` and ``-``
replaced by ``_`` (WebDataset splits a member name at its first dot), made unique with a
``_<n>`` suffix. Shards hold at most ``shard_size`` samples; each is written to a temporary
name and renamed. A re-run keeps a shard whose members (names, sizes) and records are
unchanged and rewrites the others, so an interrupted export resumes; shards past the new
count are deleted. Members carry mtime 0 and no owner, so equal inputs give equal bytes.
"""

from __future__ import annotations

import io
import json
import re
import tarfile
from pathlib import Path

from ..pipeline import atomic_write, sweep_temp_files
from .common import EXPORTS, ExportError, field, file_path, load

SHARD_PATTERN = "shard-%06d.tar"
#: A member of a shard: its name and its source file or bytes.
Member = tuple[str, Path | bytes]


def sample_key(view_key: str) -> str:
    """A WebDataset sample key from a view key (no dots or slashes)."""
    return re.sub(r"[^A-Za-z0-9_-]+", "_", view_key).strip("_") or "view"


def _samples(out_dir: Path, records: list[dict]) -> list[tuple[str, list[Member]]]:
    """(key, [(member name, source file or bytes)]) of every view."""
    used: dict[str, int] = {}
    samples = []
    for r in records:
        base = sample_key(str(field(r, "key")))
        key = base
        while key in used:
            used[base] += 1
            key = f"{base}_{used[base]}"
        used.setdefault(key, 0)
        members: list[Member] = []
        for name in sorted(field(r, "files")):
            if "/" in name:
                raise ExportError(f"view {r['key']!r}: file name {name!r} has a '/'")
            members.append((f"{key}.{name}", file_path(out_dir, r, name)))
        text = json.dumps(r, sort_keys=True, separators=(",", ":")).encode()
        members.append((f"{key}.json", text))
        samples.append((key, members))
    return samples


def _size(src: Path | bytes) -> int:
    return len(src) if isinstance(src, bytes) else src.stat().st_size


def _is_current(path: Path, members: list[Member]) -> bool:
    """Whether the shard at ``path`` holds exactly ``members`` (names and sizes; the JSON
    records byte for byte)."""
    try:
        with tarfile.open(path, "r") as tar:
            got = tar.getmembers()
            if [(m.name, m.size) for m in got] != [(n, _size(s)) for n, s in members]:
                return False
            for m, (_, src) in zip(got, members, strict=True):
                if isinstance(src, bytes) and tar.extractfile(m).read() != src:
                    return False
    except (OSError, tarfile.TarError):
        return False
    return True


def _write_shard(tmp: str, members: list[Member]) -> None:
    with tarfile.open(tmp, "w", format=tarfile.PAX_FORMAT) as tar:
        for name, src in members:
            info = tarfile.TarInfo(name)
            info.size, info.mtime, info.mode = _size(src), 0, 0o644
            if isinstance(src, bytes):
                tar.addfile(info, io.BytesIO(src))
            else:
                with open(src, "rb") as f:
                    tar.addfile(info, f)


def write_webdataset(out_dir: str | Path, records: list[dict] | None = None,
                     shard_size: int = 1000) -> list[Path]:
    """Write the dataset as WebDataset tar shards under ``<out_dir>/exports/webdataset``
    (see the module docstring); returns every shard's path (kept or written).

    Args:
        out_dir: the rendered dataset folder.
        records: its manifest records (default: ``read_manifest(out_dir)``).
        shard_size: the most samples (views) per shard.

    Raises:
        ExportError: a missing record field or file, named.
    """
    if isinstance(shard_size, bool) or not isinstance(shard_size, int) or shard_size < 1:
        raise ValueError(f"shard_size: expected an int >= 1, got {shard_size!r}")
    out_dir, records = load(out_dir, records)
    folder = out_dir / EXPORTS / "webdataset"
    sweep_temp_files(folder)
    samples = _samples(out_dir, records)
    paths = []
    for index, start in enumerate(range(0, len(samples), shard_size)):
        members = [m for _, ms in samples[start:start + shard_size] for m in ms]
        path = folder / (SHARD_PATTERN % index)
        if not (path.is_file() and _is_current(path, members)):
            atomic_write(path, lambda tmp, ms=members: _write_shard(tmp, ms))
        paths.append(path)
    if folder.is_dir():
        for stale in folder.glob("shard-*.tar"):
            if stale not in paths and re.fullmatch(r"shard-\d{6}\.tar", stale.name):
                stale.unlink()
    return paths
