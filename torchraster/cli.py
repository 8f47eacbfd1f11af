"""``torchraster render CONFIG... [--out DIR]``: batch rendering of YAML render configs."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from tqdm import tqdm

from .config import ConfigError, load_config
from .io import MeshFileError
from .pipeline import check_formats, iter_render, write_outputs


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="torchraster", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("render", help="render YAML configs to image files")
    r.add_argument("configs", nargs="+", type=Path, help="render config files (YAML)")
    r.add_argument("--out", type=Path, default=Path("out"),
                   help="output folder; each config writes to OUT/<config name>/[<camera>/]")
    r.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    r.add_argument("--verbose", "-v", action="store_true", help="log the render plans")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``torchraster`` console command. Returns the exit code."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(message)s")
    # Validate every config (and its output formats) before rendering anything.
    try:
        configs = [(path, load_config(path)) for path in args.configs]
        for path, cfg in configs:
            check_formats(cfg, str(path))
    except ConfigError as e:
        print(f"torchraster: error: {e}", file=sys.stderr)
        return 2
    total = sum(len(cfg.cameras) for _, cfg in configs)
    status = 0
    with tqdm(total=total, unit="view", disable=total < 2, file=sys.stderr) as bar:
        for path, cfg in configs:
            done = 0
            try:
                for result in iter_render(cfg, args.device):
                    folder = args.out / path.stem
                    if len(cfg.cameras) > 1:
                        folder = folder / result.name
                    for written in write_outputs(result, folder, cfg.outputs.formats):
                        tqdm.write(str(written), file=sys.stdout)
                    if args.verbose:
                        tqdm.write(f"plan: {'; '.join(result.plan)}", file=sys.stderr)
                    bar.update(1)
                    done += 1
            except (ConfigError, MeshFileError, FileNotFoundError, ValueError) as e:
                print(f"torchraster: error: {path}: {e}", file=sys.stderr)
                status = 1
                bar.update(len(cfg.cameras) - done)
    return status


if __name__ == "__main__":
    sys.exit(main())
