"""``torchraster render CONFIG... [--out DIR]``: batch rendering of YAML render configs.

Exit codes: 0 all views written; 1 some views failed (each reported on one line, the
others still rendered); 2 a config, output folder or device error found before rendering;
130 interrupted (Ctrl-C).
"""

from __future__ import annotations

import argparse
import logging
import sys
import traceback
from pathlib import Path

EXAMPLE = """\
example:
  torchraster render configs/quickstart.yaml --out out
  torchraster render configs/*.yaml --out renders -v

Config reference: docs/config.md (or `torchraster schema`).
"""


def _parser() -> argparse.ArgumentParser:
    from . import __version__

    raw = argparse.RawDescriptionHelpFormatter
    p = argparse.ArgumentParser(prog="torchraster", description=__doc__.splitlines()[0],
                                epilog=EXAMPLE, formatter_class=raw)
    p.add_argument("--version", action="version", version=f"torchraster {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("render", help="render YAML configs to image files", epilog=EXAMPLE,
                       formatter_class=raw)
    r.add_argument("configs", nargs="+", type=Path, help="render config files (YAML)")
    r.add_argument("--out", type=Path, default=Path("out"),
                   help="output folder; each config writes to OUT/<config name>/[<camera>/]")
    r.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda:0 "
                   "(default: cpu)")
    r.add_argument("--allow-missing-textures", action="store_true",
                   help="render meshes whose texture files are missing without them")
    r.add_argument("--verbose", "-v", action="store_true",
                   help="print the render plan of each view and the files written")
    r.add_argument("--traceback", action="store_true",
                   help="print the full traceback of a failing view")
    sub.add_parser("schema", help="print the render config reference (Markdown)")
    return p


def _error(message: str) -> None:
    print(f"torchraster: error: {message}", file=sys.stderr)


def _check_device(name: str):
    """A usable torch device from ``--device`` (one clear line when it is not)."""
    import torch

    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        raise ValueError(f"--device: {name!r} is not a torch device (e.g. cpu, cuda, "
                         "cuda:1)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device: {name!r} requested but this torch has no CUDA device "
                         f"(torch {torch.__version__}); use --device cpu")
    if device.type == "cuda" and device.index is not None and (
            device.index >= torch.cuda.device_count()):
        raise ValueError(f"--device: {name!r}: only {torch.cuda.device_count()} CUDA "
                         "device(s)")
    if device.type not in ("cpu", "cuda"):
        try:
            torch.zeros(1, device=device)
        except (RuntimeError, AssertionError) as e:
            raise ValueError(f"--device: {name!r} is not usable here ({e})") from None
    return device


def _prepare(args: argparse.Namespace) -> list:
    """Load and check every config, the output folders and the device before rendering;
    raise one ConfigError listing every problem found."""
    from .config import ConfigError, check_config, load_config
    from .pipeline import OutputError, check_formats, check_output_dir

    problems, configs, stems = [], [], {}
    try:
        _check_device(args.device)
    except ValueError as e:
        problems.append(str(e))
    for path in args.configs:
        try:
            cfg = load_config(path)
            if args.allow_missing_textures:
                cfg.scene.allow_missing_textures = True
            check_config(cfg)
            check_formats(cfg, str(path))
        except ConfigError as e:
            problems.append(str(e))
            continue
        stem = path.stem
        if stem in stems:
            problems.append(f"{path}: writes to {args.out / stem}, like {stems[stem]}; "
                            "rename one of the configs (or render them separately)")
            continue
        stems[stem] = path
        configs.append((path, cfg))
    try:
        check_output_dir(args.out)
    except OutputError as e:
        problems.append(str(e))
    if problems:
        raise ConfigError("\n".join(problems))
    return configs


def _render(args: argparse.Namespace, configs: list) -> int:
    from tqdm import tqdm

    from .pipeline import iter_render, view_folder, write_outputs

    total = sum(len(cfg.cameras) for _, cfg in configs)
    written = failed = 0
    with tqdm(total=total, unit="view", disable=total < 2, file=sys.stderr) as bar:
        for path, cfg in configs:
            folder = args.out / path.stem
            try:
                views = list(iter_render(cfg, args.device))
            except Exception as e:  # noqa: BLE001 (one bad config never stops the others)
                tqdm.write(f"torchraster: error: {path}: {_one_line(e)}", file=sys.stderr)
                if args.traceback:
                    tqdm.write(traceback.format_exc(), file=sys.stderr)
                failed += len(cfg.cameras)
                bar.update(len(cfg.cameras))
                continue
            for i, render in enumerate(views):
                name = cfg.cameras[i].name or f"view{i}"
                try:
                    result = render()
                    files = write_outputs(result, view_folder(folder, cfg, result.name),
                                          cfg.outputs.formats)
                    written += 1
                    if args.verbose:
                        tqdm.write(f"{path} [{result.name}]: {result.plan}", file=sys.stderr)
                        for f in files:
                            tqdm.write(str(f), file=sys.stderr)
                except Exception as e:  # noqa: BLE001 (one bad view never stops the others)
                    failed += 1
                    tqdm.write(f"torchraster: error: {path} [camera {name}]: {_one_line(e)}",
                               file=sys.stderr)
                    if args.traceback:
                        tqdm.write(traceback.format_exc(), file=sys.stderr)
                bar.update(1)
    print(f"torchraster: {written} view(s) written to {args.out}, {failed} failed",
          file=sys.stderr)
    return 1 if failed else 0


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split()) or type(e).__name__
    return text if isinstance(e, (ValueError, OSError, MemoryError)) else (
        f"{type(e).__name__}: {text}")


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``torchraster`` console command. Returns the exit code."""
    args = _parser().parse_args(argv)
    if args.command == "schema":
        from .config import config_reference

        print(config_reference())
        return 0
    logging.basicConfig(level=logging.WARNING, format="torchraster: %(message)s")
    try:
        from .config import ConfigError

        try:
            configs = _prepare(args)
        except ConfigError as e:
            _error(str(e))
            return 2
        return _render(args, configs)
    except KeyboardInterrupt:
        print("torchraster: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
