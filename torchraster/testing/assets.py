"""Where tests and benchmark scripts find the optional large assets (glTF models, HDR
environment maps, scanned meshes) that the repository does not ship.

The folder is named by the environment variable ``TORCHRASTER_DATA`` (subfolders ``gltf/``,
``envmaps/``, ``meshes/``); when it is unset, a ``shared/data`` folder beside the checkout
is used if one exists (the development machine's layout). Tests that need an asset skip
when neither is there; the scripts say what they skipped.
"""

from __future__ import annotations

import os
from pathlib import Path

#: The environment variable naming the asset folder.
ENV_VAR = "TORCHRASTER_DATA"


def data_dir() -> Path:
    """The asset folder (it may not exist: check ``.is_dir()``)."""
    named = os.environ.get(ENV_VAR)
    if named:
        return Path(named).expanduser().resolve()
    return Path(__file__).resolve().parents[3] / "shared" / "data"


__all__ = ["ENV_VAR", "data_dir"]
