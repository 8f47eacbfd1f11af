"""Key paths of a YAML document and the lines they are on (for error messages)."""

from __future__ import annotations

from collections.abc import Sequence

import yaml

#: Tags pydantic adds to the key paths of a discriminated union (the light types).
UNION_TAGS = ("ambient", "directional", "point", "spot", "area")


def key_lines(node: yaml.Node) -> dict:
    """Map every key path of a composed YAML tree to its 1-based line number (each node
    visited once: aliased content keeps the line of its anchor)."""
    out: dict = {}
    seen: set[int] = set()
    stack: list[tuple[yaml.Node, tuple]] = [(node, ())]
    while stack:
        n, path = stack.pop()
        out.setdefault(path, n.start_mark.line + 1)
        if id(n) in seen:
            continue
        seen.add(id(n))
        if isinstance(n, yaml.MappingNode):
            for key, value in n.value:
                kp = path + (getattr(key, "value", str(key)),)
                out.setdefault(kp, key.start_mark.line + 1)
                stack.append((value, kp))
        elif isinstance(n, yaml.SequenceNode):
            stack.extend((item, path + (i,)) for i, item in enumerate(n.value))
    return out


def line_of(lines: dict, loc: Sequence) -> int | None:
    """Line of the longest prefix of ``loc`` found in the YAML (pydantic adds union tags)."""
    loc = tuple(int(p) if isinstance(p, str) and p.isdigit() else p for p in loc)
    for n in range(len(loc), -1, -1):
        cand = tuple(loc[:n])
        if cand in lines:
            return lines[cand]
        stripped = tuple(p for p in cand if p not in UNION_TAGS)
        if stripped in lines:
            return lines[stripped]
    return None
