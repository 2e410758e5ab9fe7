"""``companion autopilot check | configure``, and ``companion px4 check | configure``, its
alias for PX4: argparse wiring (flags built from :class:`CheckOptions`' fields).

The autopilot on the link says who it is (HEARTBEAT.autopilot) and the matching checker runs:
PX4 (:mod:`companion.autopilot.px4`, through MAVSDK) or ArduPilot
(:mod:`companion.autopilot.ardupilot`, through pymavlink); ``--autopilot`` skips the detection,
and ``companion px4`` is ``companion autopilot --autopilot px4``.

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
import time
import typing
from pathlib import Path
from typing import Any

from companion.autopilot.options import CheckOptions
from companion.errors import AutopilotUnreachableError, ConfigError

EXIT_OK, EXIT_PROBLEMS = 0, 1  # and 3 through companion.cli: AutopilotUnreachableError
CHECK_ONLY = {"watch_s", "shell"}
CONFIGURE_ONLY = {"yes", "no_gnss"}
HELP = "check / configure PX4 or ArduPilot (by its HEARTBEAT)"
PX4_HELP = "check / configure PX4 so that EKF2 fuses our estimate"


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _add_option_flags(p: argparse.ArgumentParser, skip: set[str]) -> None:
    """One flag per CheckOptions field (help, default and choices from the field)."""
    hints = typing.get_type_hints(CheckOptions)
    for f in dataclasses.fields(CheckOptions):
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


def _options(args: argparse.Namespace) -> CheckOptions:
    values: dict[str, Any] = {
        f.name: getattr(args, f.name)
        for f in dataclasses.fields(CheckOptions)
        if hasattr(args, f.name)
    }
    if getattr(args, "watch_s", 0) < 0:
        raise ConfigError(f"--watch-s: must be >= 0, got {args.watch_s}")
    if getattr(args, "timeout_s", 1) <= 0:
        raise ConfigError(f"--timeout-s: must be > 0, got {args.timeout_s}")
    if getattr(args, "with_gps", False) and getattr(args, "no_gnss", False):
        raise ConfigError("--with-gps and --no-gnss: one or the other (GPS fitted, or none)")
    return CheckOptions(**values)


def detect(url: str, timeout_s: float) -> str:
    """``PX4`` or ``ArduPilot`` (or ``MAV_AUTOPILOT n``) from the first autopilot HEARTBEAT on
    ``url``; AutopilotUnreachableError when none comes within ``timeout_s``."""
    from pymavlink import mavutil

    from companion.autopilot.reach import pymavlink_url
    from companion.drivers.ardupilot import autopilot_name

    u = pymavlink_url(url)
    try:
        conn = mavutil.mavlink_connection(u, source_system=255, source_component=190)
    except Exception as e:
        raise AutopilotUnreachableError(f"cannot open {u}: {e}") from None
    try:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            conn.mav.heartbeat_send(6, 8, 0, 0, 0)
            m = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
            if m is not None and m.get_srcComponent() == 1 and m.autopilot != 8:
                return autopilot_name(m.autopilot)
    finally:
        conn.close()
    raise AutopilotUnreachableError(f"no autopilot heartbeat on {u} within {timeout_s:g} s")


def _which(args: argparse.Namespace) -> str:
    """``PX4`` or ``ArduPilot`` as ``--autopilot`` says, else as its HEARTBEAT says."""
    if args.autopilot != "auto":
        return {"px4": "PX4", "ardupilot": "ArduPilot"}[args.autopilot]
    from companion.autopilot.reach import resolve_link
    from companion.config import load_config

    target = resolve_link(load_config(args.config), _options(args))
    return detect(target.url, args.timeout_s)


def cmd_check(args: argparse.Namespace) -> int:
    """Check the parameters and watch whether the EKF fuses our estimate (PX4's check, or
    ArduPilot's)."""
    from companion.config import load_config

    if _which(args) == "ArduPilot":
        from companion.autopilot.ardupilot import check as ardupilot

        ap = asyncio.run(ardupilot.run_check(load_config(args.config), _options(args)))
        text, problems = ardupilot.format_check(ap), ap.problems
    else:
        from companion.autopilot.px4 import check as px4

        report = asyncio.run(px4.run_check(load_config(args.config), _options(args)))
        text, problems = px4.format_check(report), report.problems
    print(text)
    return EXIT_OK if problems == 0 else EXIT_PROBLEMS


def cmd_configure(args: argparse.Namespace) -> int:
    """Write the needed values (typed), read them back, say which need a reboot (PX4's
    configure, or ArduPilot's)."""
    from companion.autopilot.configure import format_result
    from companion.config import load_config

    ardupilot = _which(args) == "ArduPilot"
    if ardupilot:
        from companion.autopilot.ardupilot.configure import run_configure as run_ardupilot

        report = asyncio.run(run_ardupilot(load_config(args.config), _options(args)))
    else:
        from companion.autopilot.px4.configure import run_configure as run_px4

        report = asyncio.run(run_px4(load_config(args.config), _options(args)))
    text = format_result(report)
    if text:
        print(text)
    elif ardupilot and report.problems:  # nothing it can write, and yet problems: show them
        from companion.autopilot.report import format_rows

        rows = format_rows(report.rows_after)
        print("\n" + rows + f"\n\nresult: {report.problems} problem(s)")
    if report.planned and not report.written:
        return EXIT_PROBLEMS
    return EXIT_OK if report.problems == 0 else EXIT_PROBLEMS


CONFIGURE_TEXT = "write the values check asks for (typed, read back; not while armed)"


def _add_commands(
    sub: Any, command: str, help_text: str, check_text: str, autopilot_flag: bool
) -> None:
    """The subcommand ``command`` with ``check`` and ``configure`` under it (``--autopilot``
    only where asked); the chosen one in ``args.<command>_command``."""
    p = sub.add_parser(command, help=help_text)
    a_sub = p.add_subparsers(dest=f"{command}_command", required=True)
    for name, func, skip, text in (
        ("check", cmd_check, CONFIGURE_ONLY, check_text),
        ("configure", cmd_configure, CHECK_ONLY, CONFIGURE_TEXT),
    ):
        q = a_sub.add_parser(name, help=text)
        q.add_argument("--config", type=Path, help="TOML config (the service's)")
        if autopilot_flag:
            q.add_argument(
                "--autopilot",
                choices=["auto", "px4", "ardupilot"],
                default="auto",
                help="which autopilot (default: auto, from its HEARTBEAT)",
            )
        else:
            q.set_defaults(autopilot="px4")
        _add_option_flags(q, skip)
        q.set_defaults(func=func)


def add_parser(sub: Any) -> None:
    """Add ``autopilot check`` and ``autopilot configure`` to the ``companion`` subcommands."""
    check = "the parameters for external navigation, and whether the EKF fuses us"
    _add_commands(sub, "autopilot", HELP, check, autopilot_flag=True)


def add_px4_parser(sub: Any) -> None:
    """Add ``px4 check`` and ``px4 configure`` (``autopilot ... --autopilot px4``)."""
    check = "the EKF2 / MAVLink parameters for external vision, and whether EKF2 fuses us"
    _add_commands(sub, "px4", PX4_HELP, check, autopilot_flag=False)
