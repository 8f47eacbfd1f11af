"""Reading a render config: YAML text to a validated :class:`RenderFile`.

Every error names the file, the line and the key path, e.g.
``quickstart.yaml:7: cameras.0.fov_deg: Input should be less than 180``; unknown keys get a
"did you mean" suggestion. Relative paths are resolved here, once, against the config
file's folder (see :mod:`torchraster.config.schema`).
"""

from __future__ import annotations

import difflib
import math
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from .check import dataset_problems
from .lines import UNION_TAGS, key_lines, line_of
from .schema import (
    AmbientLightConfig,
    AreaLightConfig,
    ConfigError,
    DirectionalLightConfig,
    PointLightConfig,
    RenderFile,
    SpotLightConfig,
)
from .views import duplicate_cameras

#: YAML nodes a config may expand to (aliases expanded): far above any real config, far
#: below what a "billion laughs" document would make us allocate.
MAX_YAML_NODES: int = 100_000


def _expanded_size(node: yaml.Node, source: str) -> int:
    """Number of nodes of the document with aliases expanded (memoised, so a "billion
    laughs" document is measured in linear time); raises ConfigError past MAX_YAML_NODES
    or on a recursive alias."""
    sizes: dict[int, int] = {}
    active: set[int] = set()

    def size(n: yaml.Node) -> int:
        key = id(n)
        if key in sizes:
            return sizes[key]
        if key in active:
            line = n.start_mark.line + 1
            raise ConfigError(f"{source}:{line}: recursive YAML alias (a node that contains "
                              "itself); configs cannot be recursive")
        active.add(key)
        total = 1
        if isinstance(n, yaml.MappingNode):
            total += sum(size(k) + size(v) for k, v in n.value)
        elif isinstance(n, yaml.SequenceNode):
            total += sum(size(v) for v in n.value)
        active.discard(key)
        sizes[key] = min(total, MAX_YAML_NODES + 1)
        return sizes[key]

    total = size(node)
    if total > MAX_YAML_NODES:
        raise ConfigError(f"{source}: YAML aliases expand to more than {MAX_YAML_NODES:,} "
                          "values; refusing to load it (an alias bomb?)")
    return total


def _model_at(loc: Sequence) -> type[BaseModel] | None:
    """The config model that holds the key at ``loc`` (for "did you mean" suggestions)."""
    model: Any = RenderFile
    for part in loc[:-1]:
        if isinstance(part, int) or (isinstance(part, str) and part.isdigit()):
            continue
        if part in UNION_TAGS:
            model = {"ambient": AmbientLightConfig, "directional": DirectionalLightConfig,
                     "point": PointLightConfig, "spot": SpotLightConfig,
                     "area": AreaLightConfig}[part]
            continue
        field = model.model_fields.get(part) if isinstance(model, type) else None
        if field is None:
            return None
        model = _inner_model(field.annotation)
        if model is None:
            return None
    return model if isinstance(model, type) and issubclass(model, BaseModel) else None


def _inner_model(annotation: Any) -> type[BaseModel] | None:
    """The (single) pydantic model inside an annotation like ``list[X] | None``."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        found = _inner_model(arg)
        if found is not None:
            return found
    return None


def _message(err: dict) -> str:
    """A pydantic error message, with a suggestion for a misspelt key (a NaN named as such,
    not as a failed bound; our own checks without pydantic's "Value error, " prefix)."""
    value = err.get("input")
    if isinstance(value, float) and math.isnan(value):
        return "expected a number, got NaN"
    if err["type"] == "value_error" and "error" in err.get("ctx", {}):
        return str(err["ctx"]["error"])
    if err["type"] != "extra_forbidden":
        return err["msg"]
    key = str(err["loc"][-1])
    model = _model_at(err["loc"])
    names = list(model.model_fields) if model is not None else []
    close = difflib.get_close_matches(key, names, n=1)
    hint = f"; did you mean {close[0]!r}?" if close else (
        f"; expected one of {names}" if names else "")
    return f"unknown key{hint}"


def parse_config(text: str | bytes, source: str = "<string>",
                 base_dir: Path | None = None) -> RenderFile:
    """Validate YAML text into a :class:`RenderFile`.

    Args:
        text: the YAML document (bytes must be UTF-8).
        source: the file name used in error messages.
        base_dir: the folder relative paths resolve against (default: the working folder).

    Returns:
        The validated config, every path field absolute (:class:`ConfigPath`).

    Raises:
        ConfigError: naming ``source``, the line and the key path of every problem.
    """
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8-sig")
        except UnicodeDecodeError as e:
            raise ConfigError(f"{source}: not UTF-8 text (invalid byte at offset {e.start}); "
                              "save the config as UTF-8") from None
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        if node is not None:
            _expanded_size(node, source)
        data = yaml.safe_load(text)
    except yaml.MarkedYAMLError as e:
        mark = e.context_mark or e.problem_mark  # where the broken construct starts
        line = mark.line + 1 if mark else "?"
        detail = f"{e.context}; {e.problem}" if e.context else str(e.problem)
        if e.problem_mark and mark is not e.problem_mark:
            detail += f" (line {e.problem_mark.line + 1})"
        raise ConfigError(f"{source}:{line}: malformed YAML: {detail}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"{source}: malformed YAML: {e}") from None
    except RecursionError:
        raise ConfigError(f"{source}: YAML nested too deeply") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level (scene:, cameras:, ...)")
    lines = key_lines(node) if node is not None else {}
    base = Path(base_dir if base_dir is not None else ".").resolve()
    try:
        cfg = RenderFile.model_validate(data, context={"base_dir": base})
    except ValidationError as e:
        msgs = []
        for err in e.errors():
            loc = tuple(err["loc"])
            key = ".".join(str(p) for p in loc) or "(top level)"
            line = line_of(lines, loc)
            where = f"{source}:{line}" if line else source
            msgs.append(f"{where}: {key}: {_message(err)}")
        raise ConfigError("invalid render config\n  " + "\n  ".join(msgs)) from None
    cfg._base_dir, cfg._source, cfg._lines = base, source, lines
    problems = duplicate_cameras(cfg) + dataset_problems(cfg)
    if problems:
        raise ConfigError("invalid render config\n  " + "\n  ".join(problems))
    return cfg


def load_config(path: str | Path) -> RenderFile:
    """Read and validate a YAML render config; relative paths resolve against its folder.

    Raises:
        ConfigError: naming the file (and line and key path) of every problem.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except IsADirectoryError:
        raise ConfigError(f"{p}: is a folder, not a config file") from None
    except OSError as e:
        raise ConfigError(f"{p}: cannot read the config file ({e.strerror})") from None
    return parse_config(data, source=str(p), base_dir=p.resolve().parent)
