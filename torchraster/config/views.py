"""The views of a config: camera and view names, mesh sets (a glob or a list file of
meshes, one object each) and the seeded cameras of every object."""

from __future__ import annotations

import glob
import hashlib
import os
import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .schema import CameraConfig, ConfigError, ConfigPath, RenderFile, written

_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


def safe_name(name: str) -> str:
    """A file-system-safe name: letters, digits, ``.``, ``_`` and ``-`` kept, any other run
    of characters replaced by ``_``, no leading dots (so never ``..``); never empty."""
    cleaned = _UNSAFE.sub("_", name).lstrip(".")
    return cleaned or "_"


def camera_names(cfg: RenderFile) -> list[str]:
    """The output folder name of every camera (sanitised ``name``, or ``view<index>``)."""
    return [safe_name(c.name) if c.name is not None else f"view{i}"
            for i, c in enumerate(cfg.cameras)]


def view_names(cfg: RenderFile) -> list[list[str]]:
    """The output name of every view of every camera entry: ``[name]`` for a single camera,
    ``[name_000, name_001, ...]`` for ``random_orbits`` (``name`` as in :func:`camera_names`)."""
    out = []
    for base, cam in zip(camera_names(cfg), cfg.cameras, strict=True):
        if cam.random_orbits is None:
            out.append([base])
        else:
            count = cam.random_orbits.count
            width = max(3, len(str(count - 1)))
            out.append([f"{base}_{j:0{width}d}" for j in range(count)])
    return out


def duplicate_cameras(cfg: RenderFile) -> list[str]:
    """A problem (``file:line: key: message``) per camera whose view names clash with an
    earlier camera's."""
    seen: dict[str, int] = {}
    problems = []
    for i, names in enumerate(view_names(cfg)):
        for name in names:
            if name in seen and seen[name] != i:
                problems.append(f"{cfg.where('cameras', i, 'name')}: camera name {name!r} is "
                                f"used by cameras.{seen[name]} too; names must be unique "
                                "(after sanitising to letters, digits, '.', '_', '-')")
                break
            seen.setdefault(name, i)
    return problems


def stable_seed(*parts: object) -> int:
    """A seed in [0, 2**63) from ``parts`` (their ``str``), the same in every process and on
    every machine (unlike ``hash``)."""
    digest = hashlib.sha256("\x1f".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


@dataclass(frozen=True)
class MeshSetEntry:
    """One object of a mesh set: its output name, its file and where it was named (for
    errors: ``list.txt:7`` or ``config.yaml:2: scene.mesh``)."""

    name: str
    path: Path
    source: str


_GLOB_MAGIC = re.compile(r"[*?[]")


def is_mesh_set(cfg: RenderFile) -> bool:
    """Whether the config names a set of objects (``scene.meshes_from``, or ``scene.mesh``
    as a glob pattern that is not itself an existing file)."""
    sc = cfg.scene
    if sc.meshes_from is not None:
        return True
    return (sc.mesh is not None and _GLOB_MAGIC.search(written(sc.mesh)) is not None
            and not Path(sc.mesh).is_file())


def _listed_meshes(cfg: RenderFile) -> tuple[Path, list[tuple[int, Path]]]:
    """The list file of ``scene.meshes_from`` and its entries ``(line, resolved path)``."""
    listing = Path(cfg.scene.meshes_from)
    try:
        text = listing.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        reason = "is a folder" if listing.is_dir() else (
            "file not found" if not listing.exists() else getattr(e, "strerror", None) or e)
        raise ConfigError(f"{cfg.where('scene', 'meshes_from')}: {listing}: {reason}") from None
    entries = []
    for number, line in enumerate(text.splitlines(), 1):
        entry = line.strip()
        if entry and not entry.startswith("#"):
            path = Path(entry).expanduser()
            entries.append((number, path if path.is_absolute() else
                            (listing.parent / path).resolve()))
    return listing, entries


def _unique_object_names(paths: list[Path], base: Path) -> list[str]:
    """Sanitised file stems; where stems clash, the path relative to ``base`` (suffix
    kept); any clash left gets ``-2``, ``-3``, ..."""
    stems = [safe_name(p.stem) for p in paths]
    counts = Counter(stems)
    names = [safe_name(os.path.relpath(p, base).replace(os.sep, "_")) if counts[s] > 1 else s
             for p, s in zip(paths, stems, strict=True)]
    seen: Counter = Counter()
    out = []
    for n in names:
        seen[n] += 1
        out.append(n if seen[n] == 1 else f"{n}-{seen[n]}")
    return out


def mesh_set(cfg: RenderFile) -> list[MeshSetEntry]:
    """The objects of a mesh set config in order (glob matches sorted; list entries in file
    order, duplicates dropped), each with a unique sanitised name. Empty when nothing
    matches (:func:`check_config` reports it).

    Raises:
        ConfigError: the list file of ``scene.meshes_from`` cannot be read.
    """
    sc = cfg.scene
    if sc.meshes_from is not None:
        listing, entries = _listed_meshes(cfg)
        first: dict[Path, int] = {}
        for number, path in entries:
            first.setdefault(path, number)
        paths = list(first)
        sources = [f"{listing}:{first[p]}" for p in paths]
        base = listing.parent
    else:
        pattern = Path(sc.mesh)
        paths = sorted(Path(m) for m in glob.glob(str(pattern), recursive=True)
                       if os.path.isfile(m))
        sources = [cfg.where("scene", "mesh")] * len(paths)
        parts = pattern.parts  # names are made relative to the folder the pattern starts in
        first = next((i for i, part in enumerate(parts) if _GLOB_MAGIC.search(part)),
                     len(parts) - 1)
        base = Path(*parts[:max(first, 1)])
    names = _unique_object_names(paths, base)
    return [MeshSetEntry(n, p, src) for n, p, src in zip(names, paths, sources, strict=True)]


def mesh_set_problems(cfg: RenderFile) -> list[str]:
    """Every problem of a mesh set config's list (``list.txt:7: ...``) or glob (nothing
    matches), for :func:`~torchraster.config.check.check_config`."""
    sc = cfg.scene
    if sc.meshes_from is None:
        return [] if mesh_set(cfg) else [
            f"{cfg.where('scene', 'mesh')}: no file matches {written(sc.mesh)!r} (in "
            f"{cfg.base_dir})"]
    try:
        listing, entries = _listed_meshes(cfg)
    except ConfigError as e:
        return [str(e)]
    problems, seen = [], {}
    for number, path in entries:
        if path in seen:
            problems.append(f"{listing}:{number}: {path.name} is listed twice (first at "
                            f"line {seen[path]})")
        elif path.is_dir():
            problems.append(f"{listing}:{number}: {path} is a folder, expected a mesh file")
        elif not path.is_file():
            problems.append(f"{listing}:{number}: file not found: {path}")
        seen.setdefault(path, number)
    if not entries:
        problems.append(f"{cfg.where('scene', 'meshes_from')}: {listing} lists no mesh")
    return problems


def object_name(cfg: RenderFile) -> str:
    """The object name of a config that is not a mesh set: its mesh's sanitised stem, or
    ``scene`` for a scene built from ``objects`` only."""
    return safe_name(Path(cfg.scene.mesh).stem) if cfg.scene.mesh is not None else "scene"


@dataclass(frozen=True)
class PlannedCamera:
    """One view of one object: its name, its camera (``random_orbits`` drawn into an
    ``orbit``; ``name`` set) and its seed (:func:`stable_seed`)."""

    name: str
    camera: CameraConfig
    seed: int


def expand_cameras(cfg: RenderFile, obj: str, seed: int = 0) -> list[PlannedCamera]:
    """The views of object ``obj``: one per camera entry, ``count`` per ``random_orbits``
    entry (drawn from ``stable_seed(seed, random_orbits.seed, obj, view name)``).

    Args:
        cfg: the config.
        obj: the object's name (the same object gets the same views in every process).
        seed: a seed mixed into every view's (``RenderDataset(seed=...)``; 0 on the
            command line).
    """
    out = []
    for cam, names in zip(cfg.cameras, view_names(cfg), strict=True):
        ro = cam.random_orbits
        for name in names:
            view_seed = stable_seed(seed, ro.seed if ro is not None else 0, obj, name)
            update: dict[str, Any] = {"name": name}
            if ro is not None:
                update.update(random_orbits=None, orbit=ro.draw(view_seed))
            out.append(PlannedCamera(name, cam.model_copy(update=update), view_seed))
    return out


def object_config(cfg: RenderFile, mesh: Path | str | None,
                  cameras: Sequence[CameraConfig]) -> RenderFile:
    """A copy of ``cfg`` that renders one object (``mesh``, an absolute path or None for a
    scene of ``objects`` only) with the given concrete cameras (names set, no
    ``random_orbits``)."""
    if mesh is not None and not isinstance(mesh, ConfigPath):
        mesh = ConfigPath(mesh, str(mesh))
    scene = cfg.scene.model_copy(update={"mesh": mesh,
                                         "meshes_from": None})
    return cfg.model_copy(update={"scene": scene, "cameras": list(cameras)})
