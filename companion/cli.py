"""Command line: ``companion sitl record|sheet``, ``companion config``, ``companion bench``.

Exit codes: 0 success, 1 a runtime error (message on stderr), 2 a bad configuration or bad
arguments (the message names the key), 130 interrupted.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from companion import __version__
from companion.config import Config, describe, load_config
from companion.errors import CompanionError, ConfigError

EXIT_OK, EXIT_ERROR, EXIT_CONFIG, EXIT_INTERRUPTED = 0, 1, 2, 130


def _sitl_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """CLI flags -> nested config overrides (only the flags the user gave)."""
    sitl: dict[str, Any] = {}
    for flag, key in (
        ("terrain", "terrain"),
        ("trajectory", "trajectory"),
        ("seed", "seed"),
        ("seconds", "seconds"),
        ("altitude", "altitude_m"),
        ("speed", "speed_m_s"),
    ):
        value = getattr(args, flag, None)
        if value is not None:
            sitl[key] = value
    if getattr(args, "takeoff_landing", False):
        sitl["takeoff_landing"] = True
    if getattr(args, "laser_marks", None) is not None:
        sitl["render"] = {"laser_marks": args.laser_marks}
    return {"sitl": sitl} if sitl else {}


def _load(args: argparse.Namespace) -> Config:
    return load_config(getattr(args, "config", None), _sitl_overrides(args))


def cmd_config(args: argparse.Namespace) -> int:
    """Print every option with its value and help."""
    cfg = _load(args)
    print("\n".join(describe(cfg)))
    return EXIT_OK


def cmd_sitl_record(args: argparse.Namespace) -> int:
    """Record a SITL dataset."""
    from sitl.dataset import record

    cfg = _load(args)
    out = record(
        cfg,
        args.out,
        image_format=args.image_format,
        overwrite=args.overwrite,
        progress=not args.no_progress,
    )
    print(out)
    return EXIT_OK


def cmd_sitl_sheet(args: argparse.Namespace) -> int:
    """Write a PNG contact sheet of a dataset and print its path."""
    from sitl.dataset import contact_sheet, open_dataset

    path = contact_sheet(open_dataset(args.dataset), args.out)
    print(path)
    return EXIT_OK


def cmd_bench_render(args: argparse.Namespace) -> int:
    """Benchmark SITL rendering (frames/s on one core)."""
    from companion.bench import bench_render, format_render_report

    cfg = _load(args)
    report = bench_render(cfg, args.terrains, args.frames)
    print(format_render_report(report))
    return EXIT_OK


def _add_sitl_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, help="TOML config file (default: built-in SITL)")
    p.add_argument("--terrain", choices=["flat", "hills", "urban", "slope"])
    p.add_argument("--trajectory", choices=["hover", "circle", "lawnmower", "figure8", "climb"])
    p.add_argument("--seconds", type=float, help="flight duration [s]")
    p.add_argument("--seed", type=int)
    p.add_argument("--altitude", type=float, help="height above ground [m] (0 = terrain default)")
    p.add_argument("--speed", type=float, help="cruise speed [m/s]")
    p.add_argument("--takeoff-landing", action="store_true", help="take off and land")
    p.add_argument("--laser-marks", choices=["off", "live", "painted"])


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``companion``."""
    parser = argparse.ArgumentParser(prog="companion", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"companion {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p_cfg = sub.add_parser("config", help="print the effective configuration")
    p_cfg.add_argument("--config", type=Path)
    p_cfg.set_defaults(func=cmd_config)

    p_sitl = sub.add_parser("sitl", help="the simulator")
    sitl_sub = p_sitl.add_subparsers(dest="sitl_command", required=True)
    p_rec = sitl_sub.add_parser("record", help="record a dataset")
    _add_sitl_flags(p_rec)
    p_rec.add_argument("--out", type=Path, required=True, help="output folder")
    p_rec.add_argument("--image-format", choices=["jpg", "png"], default="jpg")
    p_rec.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    p_rec.add_argument("--no-progress", action="store_true", help="no progress bar")
    p_rec.set_defaults(func=cmd_sitl_record)
    p_sheet = sitl_sub.add_parser("sheet", help="write a PNG contact sheet of a dataset")
    p_sheet.add_argument("dataset", type=Path)
    p_sheet.add_argument("--out", type=Path)
    p_sheet.set_defaults(func=cmd_sitl_sheet)

    p_bench = sub.add_parser("bench", help="benchmarks")
    bench_sub = p_bench.add_subparsers(dest="bench_command", required=True)
    p_br = bench_sub.add_parser("render", help="SITL rendering speed on one core")
    p_br.add_argument("--config", type=Path)
    p_br.add_argument("--terrains", nargs="+", default=["flat", "hills", "urban", "slope"])
    p_br.add_argument("--frames", type=int, default=300, help="frames per terrain")
    p_br.set_defaults(func=cmd_bench_render)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``companion`` console script; returns the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # argparse exits 2 on bad usage, 0 for --help
        return int(e.code) if isinstance(e.code, int) else EXIT_CONFIG
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except ConfigError as e:
        print(f"companion: config error: {e}", file=sys.stderr)
        return EXIT_CONFIG
    except CompanionError as e:
        print(f"companion: error: {e}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("companion: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
