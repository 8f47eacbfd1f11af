"""The layering of docs/design.md, checked: every module imports only from its own layer or
the layers below, and only the config layer imports pydantic / yaml."""

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "torchraster"

#: Layers bottom-up (docs/design.md, "Layers"); a module may import its own layer and below.
LAYERS: list[set[str]] = [
    {"numerics", "_validate", "frame_pool"},
    {"camera", "mesh", "material", "mip", "texture", "anisotropic", "mip_atlas", "hdr_io",
     "animation", "randomize"},
    {"raster", "io"},
    {"gbuffer", "scene", "labels", "motion", "testing"},
    {"shading"},
    {"post"},
    {"renderer", "settings", "transparency", "background", "dissolve", "relative", "low_precision",
     "edge_aa"},
    {"config", "pipeline", "manifest", "distributed", "data", "cli", "__main__", "__init__",
     "export"},
]
CONFIG_ONLY = {"pydantic", "yaml"}


def _layer_of(name: str) -> int:
    for i, layer in enumerate(LAYERS):
        if name in layer:
            return i
    raise AssertionError(f"torchraster.{name}: module not placed in a layer of "
                         "tests/test_layers.py / docs/design.md")


def _imports(path: Path) -> list[tuple[str, int]]:
    """(top-level torchraster module or third-party package, line) of every import."""
    rel = path.relative_to(PACKAGE).with_suffix("")
    parts = list(rel.parts)
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the module's package
                base = parts[:-node.level] if node.level <= len(parts) else []
                target = base + (node.module.split(".") if node.module else [])
                if not target:  # "from . import camera"
                    out += [(a.name, node.lineno) for a in node.names
                            if not a.name.startswith("__")]
                else:
                    out.append((target[0], node.lineno))
            elif node.module and node.module.split(".")[0] == "torchraster":
                sub = node.module.split(".")[1:] or [a.name for a in node.names]
                out.append((sub[0], node.lineno))
            elif node.module:
                out.append(("ext:" + node.module.split(".")[0], node.lineno))
        elif isinstance(node, ast.Import):
            for a in node.names:
                head = a.name.split(".")
                if head[0] == "torchraster" and len(head) > 1:
                    out.append((head[1], node.lineno))
                else:
                    out.append(("ext:" + head[0], node.lineno))
    return out


def test_modules_import_only_their_layer_and_below():
    problems = []
    for path in sorted(PACKAGE.rglob("*.py")):
        top = path.relative_to(PACKAGE).parts[0].removesuffix(".py")
        own = _layer_of(top)
        for name, line in _imports(path):
            where = f"{path.relative_to(PACKAGE.parent)}:{line}"
            if name.startswith("ext:"):
                if name[4:] in CONFIG_ONLY and own < _layer_of("config"):
                    problems.append(f"{where}: a core module imports {name[4:]}")
                continue
            if name != top and _layer_of(name) > own:
                problems.append(f"{where}: {top} (layer {own}) imports {name} "
                                f"(layer {_layer_of(name)})")
    assert not problems, "\n".join(problems)


def test_no_private_names_cross_modules():
    problems = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.level or (
                    node.module or "").startswith("torchraster")):
                for a in node.names:
                    if a.name.startswith("_") and not a.name.startswith("__"):
                        problems.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: "
                                        f"imports private {a.name}")
    assert not problems, "\n".join(problems)


def test_testing_references_share_no_code_with_the_engine():
    """torchraster/testing holds independent references: it imports no other torchraster
    module (docs/design.md, layer 3), so a test against it compares two implementations."""
    problems = []
    for path in sorted((PACKAGE / "testing").rglob("*.py")):
        for name, line in _imports(path):
            if not name.startswith("ext:") and name != "testing":
                problems.append(f"{path.relative_to(PACKAGE.parent)}:{line}: imports "
                                f"torchraster.{name}")
    assert not problems, "\n".join(problems)


def test_import_torchraster_does_not_import_kornia():
    """kornia costs ~0.2 s on top of torch at import; only the functions that use it import
    it (post-processing's sRGB encode, OpenCV extrinsics, Gaussian mip pyramids)."""
    code = ("import sys, torchraster; assert 'kornia' not in sys.modules, "
            "sorted(m for m in sys.modules if m.startswith('kornia'))[:3]; "
            "torchraster.post.encode_srgb(torchraster.post.tone_curve(__import__('torch')"
            ".ones(1, 3, 1, 1), 'aces')); assert 'kornia' in sys.modules")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
