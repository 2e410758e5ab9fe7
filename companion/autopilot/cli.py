"""``companion autopilot check | configure``: the autopilot on the link says who it is
(HEARTBEAT.autopilot) and the matching checker runs: PX4 (``companion px4 ...``, through MAVSDK)
or ArduPilot (:mod:`companion.autopilot.ardupilot_check`, through pymavlink). The flags are
``companion px4``'s, plus ``--autopilot`` to skip the detection. Exit codes as ``px4``'s: 0 as
needed (and fused), 1 problems found, 2 bad arguments or configuration, 3 no autopilot.
"""

from __future__ import annotations

import argparse
import asyncio
import time
from pathlib import Path
from typing import Any

from companion.errors import AutopilotUnreachableError
from companion.px4 import cli as px4_cli

EXIT_OK, EXIT_PROBLEMS = px4_cli.EXIT_OK, px4_cli.EXIT_PROBLEMS
HELP = "check / configure PX4 or ArduPilot (by its HEARTBEAT)"


def detect(url: str, timeout_s: float) -> str:
    """``PX4`` or ``ArduPilot`` (or ``MAV_AUTOPILOT n``) from the first autopilot HEARTBEAT on
    ``url``; AutopilotUnreachableError when none comes within ``timeout_s``."""
    from pymavlink import mavutil

    from companion.autopilot.ardupilot_link import pymavlink_url
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
    if args.autopilot != "auto":
        return {"px4": "PX4", "ardupilot": "ArduPilot"}[args.autopilot]
    from companion.config import load_config
    from companion.px4.check import resolve

    target = resolve(load_config(args.config), px4_cli._options(args))
    return detect(target.url, args.timeout_s)


def cmd_check(args: argparse.Namespace) -> int:
    """PX4's check, or ArduPilot's."""
    if _which(args) != "ArduPilot":
        return px4_cli.cmd_check(args)
    from companion.autopilot.ardupilot_check import format_check, run_check
    from companion.config import load_config

    report = asyncio.run(run_check(load_config(args.config), px4_cli._options(args)))
    print(format_check(report))
    return EXIT_OK if report.problems == 0 else EXIT_PROBLEMS


def cmd_configure(args: argparse.Namespace) -> int:
    """PX4's configure, or ArduPilot's."""
    if _which(args) != "ArduPilot":
        return px4_cli.cmd_configure(args)
    from companion.autopilot.ardupilot_check import run_configure
    from companion.config import load_config
    from companion.px4.configure import format_result

    report = asyncio.run(run_configure(load_config(args.config), px4_cli._options(args)))
    text = format_result(report)
    if text:
        print(text)
    elif report.problems:  # nothing configure can write, and yet problems: show them
        from companion.px4.check import format_rows

        print("\n" + format_rows(report.rows_after) + f"\n\nresult: {report.problems} problem(s)")
    if report.planned and not report.written:
        return EXIT_PROBLEMS
    return EXIT_OK if report.problems == 0 else EXIT_PROBLEMS


def add_parser(sub: Any) -> None:
    """Add ``autopilot check`` and ``autopilot configure`` to the ``companion`` subcommands."""
    p = sub.add_parser("autopilot", help=HELP)
    a_sub = p.add_subparsers(dest="autopilot_command", required=True)
    for name, func, skip, text in (
        (
            "check",
            cmd_check,
            px4_cli.CONFIGURE_ONLY,
            "the parameters for external navigation, and whether the EKF fuses us",
        ),
        (
            "configure",
            cmd_configure,
            px4_cli.CHECK_ONLY,
            "write the values check asks for (typed, read back; not while armed)",
        ),
    ):
        q = a_sub.add_parser(name, help=text)
        q.add_argument("--config", type=Path, help="TOML config (the service's)")
        q.add_argument(
            "--autopilot",
            choices=["auto", "px4", "ardupilot"],
            default="auto",
            help="which autopilot (default: auto, from its HEARTBEAT)",
        )
        px4_cli._add_option_flags(q, skip)
        q.set_defaults(func=func)
