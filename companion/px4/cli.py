"""``companion px4 check | configure``: argparse wiring (flags built from Px4Options' fields).

Exit codes (docs/service.md, "Exit codes"), as a checker's: 0 everything as needed (check: and
our estimate is fused), 1 problems found (or a write that did not read back, or the vehicle
armed), 2 bad arguments or configuration (``companion.cli`` maps ConfigError to 2), 3 no
autopilot answers on the link (AutopilotUnreachableError: no heartbeat, the link cannot be
opened), so that a script can tell "PX4 would not fuse us" from "nothing is there".
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import typing
from pathlib import Path
from typing import Any

from companion.errors import ConfigError
from companion.px4.options import Px4Options

EXIT_OK, EXIT_PROBLEMS = 0, 1  # and 3 through companion.cli: AutopilotUnreachableError
CHECK_ONLY = {"watch_s", "shell"}
CONFIGURE_ONLY = {"yes", "no_gnss"}


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _add_option_flags(p: argparse.ArgumentParser, skip: set[str]) -> None:
    """One flag per Px4Options field (help, default and choices from the field)."""
    hints = typing.get_type_hints(Px4Options)
    for f in dataclasses.fields(Px4Options):
        if f.name in skip:
            continue
        help_text = f.metadata.get("help", "")
        if isinstance(f.default, bool):
            if f.default:
                p.add_argument(
                    _flag("no_" + f.name),
                    dest=f.name,
                    action="store_false",
                    help="do not: " + help_text,
                )
            else:
                p.add_argument(_flag(f.name), dest=f.name, action="store_true", help=help_text)
            continue
        choices = (
            typing.get_args(hints[f.name])
            if typing.get_origin(hints[f.name]) is typing.Literal
            else None
        )
        p.add_argument(
            _flag(f.name),
            dest=f.name,
            type=type(f.default),
            default=f.default,
            choices=choices,
            help=f"{help_text} (default: {f.default!r})",
        )


def _options(args: argparse.Namespace) -> Px4Options:
    values: dict[str, Any] = {
        f.name: getattr(args, f.name)
        for f in dataclasses.fields(Px4Options)
        if hasattr(args, f.name)
    }
    if getattr(args, "watch_s", 0) < 0:
        raise ConfigError(f"--watch-s: must be >= 0, got {args.watch_s}")
    if getattr(args, "timeout_s", 1) <= 0:
        raise ConfigError(f"--timeout-s: must be > 0, got {args.timeout_s}")
    return Px4Options(**values)


def cmd_check(args: argparse.Namespace) -> int:
    """Check the parameters and watch whether EKF2 fuses our estimate."""
    from companion.config import load_config
    from companion.px4.check import format_check, run_check

    cfg = load_config(args.config)
    report = asyncio.run(run_check(cfg, _options(args)))
    print(format_check(report))
    return EXIT_OK if report.problems == 0 else EXIT_PROBLEMS


def cmd_configure(args: argparse.Namespace) -> int:
    """Write the needed values (typed), read them back, say which need a reboot."""
    from companion.config import load_config
    from companion.px4.configure import format_result, run_configure

    cfg = load_config(args.config)
    report = asyncio.run(run_configure(cfg, _options(args)))
    text = format_result(report)
    if text:
        print(text)
    if report.planned and not report.written:
        return EXIT_PROBLEMS
    return EXIT_OK if report.problems == 0 else EXIT_PROBLEMS


def add_parser(sub: Any) -> None:
    """Add ``px4 check`` and ``px4 configure`` to the ``companion`` subcommands."""
    p = sub.add_parser("px4", help="check / configure PX4 so that EKF2 fuses our estimate")
    px4_sub = p.add_subparsers(dest="px4_command", required=True)
    p_check = px4_sub.add_parser(
        "check",
        help="the EKF2 / MAVLink parameters for external vision, and whether EKF2 fuses us",
    )
    p_check.add_argument("--config", type=Path, help="TOML config (the service's)")
    _add_option_flags(p_check, CONFIGURE_ONLY)
    p_check.set_defaults(func=cmd_check)
    p_conf = px4_sub.add_parser(
        "configure", help="write the values check asks for (typed, read back; not while armed)"
    )
    p_conf.add_argument("--config", type=Path, help="TOML config (the service's)")
    _add_option_flags(p_conf, CHECK_ONLY)
    p_conf.set_defaults(func=cmd_configure)
