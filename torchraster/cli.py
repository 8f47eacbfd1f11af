"""``torchraster render CONFIG... [--out DIR]``: batch rendering of YAML render configs.

Views already rendered (their files present, their ``DIR/manifest.jsonl`` record made by
the same config, camera, seed and version) are skipped, so a killed run is finished by
running it again; ``--force`` renders everything. Under ``torchrun`` the views are split
across the processes (``torchrun --nproc-per-node N -m torchraster render ...``; see
:mod:`torchraster.distributed`).

Exit codes: 0 all views written (or already done); 1 some views failed (each reported on
one line, the others still rendered); 2 a config, output folder or device error found before
rendering; 130 interrupted (Ctrl-C).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

EXAMPLE = """\
example:
  torchraster render configs/quickstart.yaml --out out
  torchraster render configs/*.yaml --out renders -v
  torchrun --nproc-per-node 4 -m torchraster render dataset.yaml --out renders

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
                   help="output folder; each config writes to OUT/<config name>/[<object>/]"
                   "[<camera>/], and OUT/manifest.jsonl lists every view")
    r.add_argument("--force", action="store_true",
                   help="render every view again, even those already done")
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
    raise one ConfigError listing every problem found. Returns ``DatasetConfig``s."""
    from .config import ConfigError, check_config, load_config, safe_name
    from .distributed import DatasetConfig
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
        stem = safe_name(path.stem)
        if stem in stems:
            problems.append(f"{path}: writes to {args.out / stem}, like {stems[stem]}; "
                            "rename one of the configs (or render them separately)")
            continue
        stems[stem] = path
        configs.append(DatasetConfig(path, stem, cfg))
    try:
        check_output_dir(args.out)
    except OutputError as e:
        problems.append(str(e))
    if problems:
        raise ConfigError("\n".join(problems))
    return configs


def _render(args: argparse.Namespace, configs: list, world) -> int:
    from .distributed import RankMismatchError, render_dataset
    from .pipeline import OutputError

    try:
        summary = render_dataset(configs, args.out, device=args.device, force=args.force,
                                 world=world, verbose=args.verbose,
                                 show_traceback=args.traceback)
    except (RankMismatchError, OutputError) as e:
        _error(str(e))
        return 2 if isinstance(e, RankMismatchError) else 1
    if world.rank == 0:
        done = f", {summary.skipped} already done" if summary.skipped else ""
        rate = (f" ({summary.seconds:.1f} s; rendering {summary.render_seconds:.1f} s, "
                f"{summary.views_per_second:.2f} views/s, {summary.render_cpu_seconds:.1f} "
                "CPU s)" if summary.written else "")
        print(f"torchraster: {summary.written} view(s) written to {args.out}{done}, "
              f"{summary.failed} failed{rate}", file=sys.stderr)
    return 1 if summary.failed else 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``torchraster`` console command. Returns the exit code."""
    args = _parser().parse_args(argv)
    if args.command == "schema":
        from .config import config_reference

        print(config_reference())
        return 0
    logging.basicConfig(level=logging.WARNING, format="torchraster: %(message)s")
    from .distributed import init_world

    world = init_world()
    try:
        from .config import ConfigError

        problem = None
        try:
            configs = _prepare(args)
        except ConfigError as e:
            problem = str(e)
        problems = world.all_gather(problem)  # every rank stops if any rank found a problem
        if any(problems):
            if world.rank == 0:
                _error(problem or next(f"(rank {r}) {p}" for r, p in enumerate(problems) if p))
            return 2
        return _render(args, configs, world)
    except KeyboardInterrupt:
        print("torchraster: interrupted", file=sys.stderr)
        return 130
    finally:
        world.close()


if __name__ == "__main__":
    sys.exit(main())
