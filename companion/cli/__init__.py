"""Command line of ``companion``: the service, evaluation, benchmarks, the simulator, tools.

Exit codes: 0 success, 1 a runtime error (message on stderr), 2 a bad configuration or bad
arguments (the message names the key), 130 interrupted; ``status``: 3 when the service is not
running; ``calibrate lasers``: 1 when a sensor is flagged.

One module per group of commands; each parses its arguments and calls functions elsewhere:

- :mod:`.service`: ``run``, ``status``, ``config``
- :mod:`.evaluate`: ``eval``, ``report``; :mod:`.evaluate_dpose` (``eval --dpose``) and
  :mod:`.flight` (``eval --phases``: the published poses by flight phase) beside it
- :mod:`.bench`: ``bench render | vo | attitude | dpose | soak``
- :mod:`.sim`: ``sitl record | sheet | run | px4``, ``demo``; and the one place where the
  product reaches the simulator (``sitl``): the other modules get simulated flights from it
- :mod:`.calibrate`: ``calibrate board | intrinsics | lasers | sim-board | sim-lasers``
- :mod:`companion.px4.cli`: ``px4 check | configure``
- :mod:`.common`: the config with the SITL flags, run names, progress bars, exit codes

The Pipeline, the reports, the service and the simulator are imported inside the commands
that use them, so that ``companion status`` or ``--help`` start without them.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

from companion import __version__
from companion.cli import bench, calibrate, evaluate, service, sim
from companion.cli.common import (
    EXIT_CONFIG,
    EXIT_ERROR,
    EXIT_INTERRUPTED,
    EXIT_NOT_RUNNING,
    EXIT_OK,
)
from companion.cli.service import format_status
from companion.errors import CompanionError, ConfigError
from companion.px4 import cli as px4_cli

__all__ = [
    "EXIT_CONFIG",
    "EXIT_ERROR",
    "EXIT_INTERRUPTED",
    "EXIT_NOT_RUNNING",
    "EXIT_OK",
    "build_parser",
    "format_status",
    "main",
]

# the subcommands in the order `companion --help` lists them
_COMMANDS: tuple[Callable[[argparse._SubParsersAction[argparse.ArgumentParser]], None], ...] = (
    service.add_config,
    sim.add_sitl,
    bench.add_bench,
    evaluate.add_report,
    service.add_run,
    service.add_status,
    sim.add_demo,
    evaluate.add_eval,
    calibrate.add_parser,  # companion calibrate board | intrinsics | lasers | sim-*
    px4_cli.add_parser,  # companion px4 check | configure
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``companion``."""
    assert __doc__ is not None
    parser = argparse.ArgumentParser(prog="companion", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"companion {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in _COMMANDS:
        add(sub)
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
