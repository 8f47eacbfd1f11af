"""The manifest of a rendered dataset: one JSON record per view, what training code reads.

An output folder ``DIR`` rendered by ``torchraster render CONFIG... --out DIR`` holds::

    DIR/manifest.jsonl                one record per view of every config rendered to DIR
    DIR/<config>/<folder>/<channel>.<format>       the images (folder: see ViewSpec)
    DIR/.torchraster/shards/*.jsonl   records of views finished by a run still going (or
                                      killed); merged into manifest.jsonl at the end

Each process appends the record of a view to its own shard file (one file per process and
run, one ``write`` per line) only after every image of the view is in place, so a record
names complete files only; a line torn by a kill is ignored. At the end of a run rank 0
merges the shards into ``manifest.jsonl`` (written atomically) and deletes them.

A record (one JSON object per line)::

    key            "<config>/<folder>": the view's folder relative to DIR (unique)
    config, config_file, config_hash, version    what rendered it (hash: see config_hash)
    object, mesh, camera, camera_config, seed    which view (camera_config: the concrete
                                                 camera, random orbits drawn)
    resolution     [H, W]
    opencv         K (3, 3) (null for orthographic), world_to_camera and camera_to_world
                   (4, 4): x right, y down, z forward; pixel (row v, col u) centred at (u, v)
    opengl         world_to_view, view_to_world, projection (4, 4): the renderer's matrices
    lights, environment                          the light set-up as in the config
    frame, time    the frame index and its time in seconds (``frames:``)
    categories     category names: id i + 1 is categories[i], 0 the background
    randomized     the draws of a randomised scene (``randomize:``), else null
    objects        one entry per instance (torchraster.labels.object_records): instance_id,
                   name, category, category_id, object_to_world (4, 4) at this frame,
                   bbox_visible / bbox_amodal [x0, y0, x1, y1] (pixel edges, COCO's), pixels,
                   pixels_amodal, visible_fraction, box3d {center_model, size_model,
                   corners_world, corners_camera (OpenCV), corners_pixels}, keypoints
    files          {"color.png": "<config>/<folder>/color.png", ...} relative to DIR
    timings        render_s, write_s; finished_at (Unix time), rank, host

A view is *done* (skipped on resume) when its record's config hash, camera, seed and
package version match the view about to be rendered and every file it names exists.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import time
from collections.abc import Iterable
from pathlib import Path

import torch

from .camera import intrinsics_from_projection
from .config import RenderFile, safe_name
from .pipeline import TEMP_MARKER, ViewResult, ViewSpec, atomic_write, sweep_temp_files

#: The merged manifest in an output folder.
MANIFEST = "manifest.jsonl"
#: Per-process record shards of runs in progress (or killed).
SHARDS = Path(".torchraster") / "shards"
#: OpenGL view space (y up, z backwards) to OpenCV camera space (y down, z forwards).
_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


def package_version() -> str:
    """The torchraster version recorded with every view."""
    from . import __version__

    return __version__


def view_key(config: str, spec: ViewSpec) -> str:
    """A view's key: its folder relative to the output folder (``<config>/<folder>``)."""
    return f"{config}/{spec.folder}" if spec.folder else config


def config_hash(cfg: RenderFile) -> str:
    """A hash (16 hex digits) of everything in a one-object config that decides its pixels,
    cameras excepted (compared one by one): every section as written, and the mesh as its
    file name, size and modification time (an edited mesh re-renders; moving the project,
    or a config file, does not)."""
    data = cfg.model_dump(mode="json", exclude={"cameras"})
    if cfg.scene.mesh is not None:
        mesh = cfg.resolve(cfg.scene.mesh)
        data["scene"]["mesh"] = mesh.name
        try:
            st = mesh.stat()
            data["scene"]["mesh_stat"] = [st.st_size, st.st_mtime_ns]
        except OSError:
            data["scene"]["mesh_stat"] = None
    text = json.dumps(data, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def expected_fields(cfg_hash: str, spec: ViewSpec) -> dict:
    """What a record must hold for ``spec`` to count as done (see :func:`is_done`)."""
    return {"config_hash": cfg_hash, "camera_config": spec.camera_config.model_dump(mode="json"),
            "seed": spec.seed, "frame": spec.frame, "version": package_version()}


def _rows(m: torch.Tensor) -> list[list[float]]:
    return [[float(x) for x in row] for row in m.tolist()]


def camera_matrices(view: torch.Tensor, proj: torch.Tensor, resolution: tuple[int, int]
                    ) -> dict:
    """A camera as OpenCV and OpenGL matrices (nested lists of float).

    Args:
        view: ``(4, 4)`` world -> view (OpenGL: x right, y up, looking down -z).
        proj: ``(4, 4)`` projection (view -> clip) of :mod:`torchraster.camera`.
        resolution: ``(H, W)`` of the image.

    Returns:
        ``{"opencv": {"K", "world_to_camera", "camera_to_world"}, "opengl":
        {"world_to_view", "view_to_world", "projection"}}``. ``K`` (3, 3) follows OpenCV
        (pixel (row v, col u) centred at (u, v); ``u = fx X/Z + cx``), the inverse of
        :func:`torchraster.camera.from_intrinsics`
        (:func:`torchraster.camera.intrinsics_from_projection`); None for an orthographic
        projection.
    """
    h, w = resolution
    view64, proj64 = view.detach().double().cpu(), proj.detach().double().cpu()
    cv = _GL_TO_CV @ view64
    k = None
    if float(proj64[3, 3]) == 0.0:  # perspective: w_clip = -z_view
        k = _rows(intrinsics_from_projection(proj64, (h, w)))
    return {"opencv": {"K": k, "world_to_camera": _rows(cv),
                       "camera_to_world": _rows(torch.linalg.inv(cv))},
            "opengl": {"world_to_view": _rows(view64),
                       "view_to_world": _rows(torch.linalg.inv(view64)),
                       "projection": _rows(proj64)}}


def view_record(*, key: str, config: str, config_file: str | Path, cfg: RenderFile,
                cfg_hash: str, spec: ViewSpec, mesh: Path | None, result: ViewResult,
                files: Iterable[Path], out_dir: Path, timings: dict, rank: int = 0,
                drawn: dict | None = None) -> dict:
    """The manifest record of one rendered view (see the module docstring).

    Args:
        key: :func:`view_key`.
        config: the config's output name; ``config_file`` its file.
        cfg: the object's config (lights, environment, resolution).
        cfg_hash: :func:`config_hash` of ``cfg``.
        spec: the view; ``mesh`` its object's file.
        result: the rendered view (its ``view`` and ``proj`` matrices).
        files: the written files; recorded relative to ``out_dir``.
        timings: e.g. ``{"render_s": ..., "write_s": ...}``.
        rank: the process that rendered it.
        drawn: a randomised scene's draws (recorded as ``randomized``).
    """
    res = cfg.render.size
    record = {"key": key, "config": config, "config_file": str(config_file),
              **expected_fields(cfg_hash, spec), "object": spec.object,
              "mesh": None if mesh is None else str(mesh), "camera": spec.camera,
              "resolution": list(res)}
    record.update(camera_matrices(result.view, result.proj, res))
    record["lights"] = [light.model_dump(mode="json") for light in cfg.lights]
    record["environment"] = (cfg.environment.model_dump(mode="json")
                             if cfg.environment is not None else None)
    record.update(frame=result.frame, time=result.time, categories=result.categories,
                  objects=result.objects, randomized=drawn)
    record["files"] = {p.name: p.relative_to(out_dir).as_posix() for p in files}
    record["timings"] = {k: round(v, 6) for k, v in timings.items()}
    record.update(finished_at=time.time(), rank=rank, host=socket.gethostname())
    return record


class ShardWriter:
    """Appends records to this process's own shard file (created on the first record).

    Args:
        out_dir: the output folder.
    """

    def __init__(self, out_dir: Path) -> None:
        name = f"{safe_name(socket.gethostname())}-{os.getpid()}-{time.time_ns()}.jsonl"
        self.path = Path(out_dir) / SHARDS / name
        self._fd: int | None = None

    def append(self, record: dict) -> None:
        """Append one record as one line, in one ``write`` (a kill tears at most this line,
        which readers skip)."""
        if self._fd is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o666)
        data = (json.dumps(record, separators=(",", ":")) + "\n").encode()
        written = os.write(self._fd, data)
        if written != len(data):  # a short write (disk full): finish it or fail loudly
            os.write(self._fd, data[written:])

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def _read_jsonl(path: Path) -> Iterable[dict]:
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return
    for line in text.splitlines():
        try:
            record = json.loads(line)
        except ValueError:
            continue  # a line torn by a kill
        if isinstance(record, dict) and isinstance(record.get("key"), str):
            yield record


def shard_files(out_dir: Path) -> list[Path]:
    """The shard files in ``out_dir`` (sorted by name)."""
    folder = Path(out_dir) / SHARDS
    return sorted(folder.glob("*.jsonl")) if folder.is_dir() else []


def _overlay(records: dict[str, dict], paths: Iterable[Path]) -> dict[str, dict]:
    """Add the records of ``paths`` to ``records`` (the most recently finished wins)."""
    for path in paths:
        for r in _read_jsonl(path):
            old = records.get(r["key"])
            if old is None or r.get("finished_at", 0) >= old.get("finished_at", 0):
                records[r["key"]] = r
    return records


def load_records(out_dir: Path) -> dict[str, dict]:
    """Every record of ``out_dir``: ``manifest.jsonl`` then the shards; for a key recorded
    more than once, the most recently finished record wins."""
    return _overlay({}, [Path(out_dir) / MANIFEST, *shard_files(out_dir)])


def matches(record: dict | None, expected: dict) -> bool:
    """Whether a record was made for the view described by ``expected``
    (:func:`expected_fields`)."""
    return record is not None and all(record.get(k) == v for k, v in expected.items())


def is_done(record: dict | None, expected: dict, out_dir: Path) -> bool:
    """Whether a view needs no rendering: its record matches and every file it names
    exists. Temporary files a killed run left in the view's folder are deleted."""
    if not matches(record, expected) or not isinstance(record.get("files"), dict):
        return False
    by_folder: dict[Path, list[str]] = {}
    for rel in record["files"].values():
        path = Path(out_dir) / rel
        by_folder.setdefault(path.parent, []).append(path.name)
    for folder, names in by_folder.items():
        try:
            present = set(os.listdir(folder))
        except OSError:
            return False
        if any(TEMP_MARKER in n for n in present):
            sweep_temp_files(folder)
        if not present.issuperset(names):
            return False
    return True


def write_manifest(out_dir: Path, expected: dict[str, dict], configs: set[str],
                   records: dict[str, dict] | None = None) -> int:
    """Merge ``manifest.jsonl`` and the shards into a new ``manifest.jsonl`` (atomically)
    and delete the merged shards. Records of configs not in ``configs`` are kept as they
    are; for the configs of this run, the manifest holds exactly the views of ``expected``
    (key -> :func:`expected_fields`, in order) whose record matches.

    Args:
        out_dir: the output folder.
        expected: the views of this run.
        configs: the config names of this run.
        records: :func:`load_records` of ``out_dir`` read earlier in the run (the shards are
            read again; saves parsing a large manifest twice). When there are no shards
            and nothing changes, the manifest is not rewritten.

    Returns:
        The number of records of this run's views written.
    """
    out_dir = Path(out_dir)
    shards = shard_files(out_dir)
    if records is None:
        records = load_records(out_dir)
        before = None
    else:
        before = list(records) if not shards else None
        records = _overlay(dict(records), shards)
    lines = [r for r in records.values() if r.get("config") not in configs]
    ours = [records[k] for k, exp in expected.items() if matches(records.get(k), exp)]
    sweep_temp_files(out_dir)
    if not shards and before is not None and before == [r["key"] for r in lines + ours] and (
            out_dir / MANIFEST).is_file():
        return len(ours)  # nothing rendered, nothing dropped: the manifest is current
    text = "".join(json.dumps(r, separators=(",", ":")) + "\n" for r in lines + ours)

    def write(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)

    atomic_write(out_dir / MANIFEST, write)
    for path in shards:
        path.unlink(missing_ok=True)
    return len(ours)


def read_manifest(path: str | Path) -> list[dict]:
    """The records of a ``manifest.jsonl`` (a file or the output folder holding it)."""
    path = Path(path)
    return list(_read_jsonl(path / MANIFEST if path.is_dir() else path))


__all__ = ["MANIFEST", "SHARDS", "ShardWriter", "camera_matrices", "config_hash",
           "expected_fields", "is_done", "load_records", "matches", "read_manifest",
           "shard_files", "view_key", "view_record", "write_manifest"]
