"""Follow a config through the config layer: which files the code that handles ``cfg`` enters.

Traces ``load_config(path)`` then ``iter_render(cfg)`` (first view rendered, at a small
resolution) and counts, for every direct call made by config-layer code (``config``,
``pipeline``) into another torchraster file (callbacks through pydantic or torch, such as
validators and ``nn.Module.forward``, are not counted): *entries* (calls into another
file), *distinct files* entered, *climbs back* (returns to the calling file) and
*re-entries* (entries into a file already left once), and who entered what. The engine's
own calls below its entry point are not followed.
docs/design.md, "Following a config", quotes the output.

    python scripts/config_walk.py [configs/pbr_spot.yaml]
"""

from __future__ import annotations

import sys
from pathlib import Path

import torchraster as tr
from torchraster.pipeline import iter_render

PACKAGE = Path(tr.__file__).resolve().parent
CONFIG_LAYER = ("config", "pipeline")


def _module(filename: str) -> str | None:
    """``config/build.py`` style name of a torchraster file, None outside the package."""
    try:
        return Path(filename).resolve().relative_to(PACKAGE).as_posix()
    except ValueError:
        return None


def walk(path: str) -> dict:
    """Counts of the walk (see the module docstring) and the entered files in order."""
    stats = {"entries": 0, "climbs back": 0, "re-entries": 0}
    edges: dict[tuple[str, str], int] = {}
    entered: list[str] = []
    left: set[str] = set()
    modules: dict[str, str | None] = {}

    def mod(frame) -> str | None:
        f = frame.f_code.co_filename
        if f not in modules:
            modules[f] = _module(f)
        return modules[f]

    def caller(frame) -> str | None:  # direct calls only: not callbacks from pydantic, torch
        return mod(frame.f_back) if frame.f_back is not None else None

    def profile(frame, event, arg):
        if event not in ("call", "return"):
            return
        here = mod(frame)
        if here is None:
            return
        up = caller(frame)
        if up is None or up == here or not up.startswith(CONFIG_LAYER):
            return
        if event == "call":
            stats["entries"] += 1
            edges[up, here] = edges.get((up, here), 0) + 1
            stats["re-entries"] += here in left
            if here not in entered:
                entered.append(here)
        else:
            stats["climbs back"] += 1
            left.add(here)

    sys.setprofile(profile)
    try:
        cfg = tr.load_config(path)
        cfg = cfg.model_copy(update={"render": cfg.render.model_copy(
            update={"resolution": 32, "supersample": 1})})
        next(iter(iter_render(cfg)))()
    finally:
        sys.setprofile(None)
    return {**stats, "distinct files": len(entered), "files": entered, "edges": edges}


if __name__ == "__main__":
    result = walk(sys.argv[1] if len(sys.argv) > 1 else "configs/pbr_spot.yaml")
    for key in ("distinct files", "entries", "climbs back", "re-entries"):
        print(f"{key}: {result[key]}")
    print("files:", ", ".join(result["files"]))
    for (a, b), n in result["edges"].items():
        print(f"  {a} -> {b}: {n}")
