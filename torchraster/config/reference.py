"""The config reference (``docs/config.md``, ``torchraster schema``), generated from the
models of :mod:`torchraster.config.schema`."""

from __future__ import annotations

import inspect
import math
import types
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel

from . import schema
from .schema import RenderFile


def _type_name(annotation: Any) -> str:
    """A short readable type of a field annotation (``float >= 0``, ``[float] x 3``, ...)."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is Annotated:
        base, *meta = args
        return _type_name(base) + _bounds_text(meta)
    if origin is Literal:
        return " \\| ".join(repr(a) for a in args)
    if origin in (list, Sequence):
        return f"list of {_type_name(args[0])}" if args else "list"
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in args if a is not type(None)) + (
            " or null" if type(None) in args else "")
    if isinstance(annotation, type):
        if issubclass(annotation, BaseModel):
            return f"[{annotation.__name__}](#{annotation.__name__.lower()})"
        return annotation.__name__
    return str(annotation).replace("typing.", "")


def _bounds_text(meta: Sequence[Any]) -> str:
    """`` >= 0 <= 1``, `` (exactly 3)``, ... of pydantic constraints (annotated types or
    ``FieldInfo.metadata``)."""
    found: dict[str, Any] = {}
    for m in meta:
        for c in [m, *getattr(m, "metadata", [])]:
            for attr in ("ge", "gt", "le", "lt", "min_length", "max_length"):
                if getattr(c, attr, None) is not None:
                    found[attr] = getattr(c, attr)
    text = "".join(f" {sym} {found[attr]:g}" for attr, sym in (
        ("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<")) if attr in found)
    lo, hi = found.get("min_length"), found.get("max_length")
    if lo is not None and lo == hi:
        text += f" (exactly {lo})"
    elif lo and hi is not None:
        text += f" ({lo} to {hi} items)"
    elif lo:
        text += f" (at least {lo})"
    elif hi is not None:
        text += f" (at most {hi})"
    return text


def _default_text(field: Any) -> str:
    if field.is_required():
        return "**required**"
    value = field.default_factory() if field.default_factory is not None else field.default
    if isinstance(value, BaseModel):
        return "(section defaults)"
    if isinstance(value, float) and math.isfinite(value):
        return f"`{value:g}`"
    return f"`{value!r}`" if not isinstance(value, Path) else f"`{value}`"


def config_reference() -> str:
    """The config reference as Markdown, generated from the pydantic models (every key with
    its type, bounds, default and description). ``torchraster schema`` prints it;
    ``scripts/make_config_docs.py`` writes it to ``docs/config.md``."""
    order: list[type[BaseModel]] = []

    def visit(model: type[BaseModel]) -> None:
        if model in order:
            return
        order.append(model)
        for field in model.model_fields.values():
            for sub in _models_in(field.annotation):
                visit(sub)

    visit(RenderFile)
    out = ["# Render config reference", "",
           "Generated from the pydantic models in `torchraster/config/schema.py` by "
           "`python scripts/make_config_docs.py` (also `torchraster schema`). Unknown keys "
           "are errors; paths are relative to the config file; `resolution` is `[H, W]` "
           "(or one int for a square image). Lights are a list of entries with a `type`.", ""]
    for model in order:
        out += [f"## {model.__name__}", ""]
        doc = inspect.getdoc(model) or ""
        if doc and model.__module__ == schema.__name__:
            out += [doc, ""]
        out += ["| key | type | default | description |", "|---|---|---|---|"]
        for name, field in model.model_fields.items():
            if field.exclude:
                continue
            desc = (field.description or "").replace("|", "\\|").replace("\n", " ")
            kind = _type_name(field.annotation) + _bounds_text(field.metadata)
            out.append(f"| `{name}` | {kind} | "
                       f"{_default_text(field)} | {desc} |")
        out.append("")
    return "\n".join(out)


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    found = []
    for arg in typing.get_args(annotation):
        found += _models_in(arg)
    return found
