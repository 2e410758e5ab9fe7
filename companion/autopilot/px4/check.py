"""``companion autopilot check`` on PX4 (``companion px4 check``): the parameters that govern
external vision, then a few seconds of watching whether EKF2 fuses our estimate (and if not,
the most likely reason).

The autopilot is reached through MAVSDK (:mod:`companion.autopilot.reach` says on which link).
"""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.autopilot.options import CheckOptions
from companion.autopilot.params import finite_params
from companion.autopilot.px4.ekf2_diagnosis import diagnose
from companion.autopilot.px4.ekf2_observations import Observations, ShellView
from companion.autopilot.px4.link import Px4Link
from companion.autopilot.px4.link_context import LinkContext
from companion.autopilot.px4.rules import evaluate
from companion.autopilot.reach import resolve_link
from companion.autopilot.report import (
    CheckReport,
    autopilot_line,
    format_report,
    service_status,
)
from companion.config import Config
from companion.drivers.px4_shell_text import parse_listener, parse_uorb_top

SHELL_TOPICS = (
    "vehicle_visual_odometry",
    "vehicle_mocap_odometry",
    "estimator_status_flags",
    "estimator_aid_src_ev_pos",
    "timesync_status",
    "estimator_aid_src_gnss_pos",
)


@dataclass(frozen=True, slots=True)
class Px4Target:
    """Where check and configure talk to, and what they know of our side."""

    url: str  # MAVSDK URL of the autopilot
    ctx: LinkContext  # our output and link, for the rules
    socket: Path  # the service's status socket


def resolve(cfg: Config, opts: CheckOptions) -> Px4Target:
    """The autopilot URL and our side's context; ConfigError when the only link is the one
    the running service holds."""
    target = resolve_link(cfg, opts)
    link = target.service_link
    fc_port = opts.fc_port
    if fc_port == "auto":
        fc_port = "TELEM2" if link.kind == "serial" else "ETHERNET"
    ctx = LinkContext(
        cfg.service.output,
        fc_port,
        link.kind,
        link.port,
        link_host=link.host,
        no_gnss=opts.no_gnss,
        odometry_frame=cfg.service.odometry_frame,
        oldest_stamp_ms=cfg.oldest_stamp_ms(),
        velocity_sigma_m_s=cfg.service.odometry_velocity_sigma_m_s,
        with_gps=opts.with_gps,
    )
    return Px4Target(target.url, ctx, target.socket)


def shell_view(outputs: list[str] | None) -> ShellView | None:
    """Parse the outputs of ``listener`` for SHELL_TOPICS then ``uorb top -1``."""
    if outputs is None or len(outputs) != len(SHELL_TOPICS) + 1:
        return None
    f = {t: parse_listener(o) for t, o in zip(SHELL_TOPICS, outputs, strict=False)}
    return ShellView(
        visual=f["vehicle_visual_odometry"],
        mocap=f["vehicle_mocap_odometry"],
        flags=f["estimator_status_flags"],
        aid_pos=f["estimator_aid_src_ev_pos"],
        timesync=f["timesync_status"],
        aid_gnss=f["estimator_aid_src_gnss_pos"],
        rates_hz=parse_uorb_top(outputs[-1]),
    )


def shell_commands() -> list[str]:
    """The shell commands whose outputs ``shell_view`` parses, in its order."""
    return [f"listener {t}" for t in SHELL_TOPICS] + ["uorb top -1 " + " ".join(SHELL_TOPICS[:2])]


async def run_check(cfg: Config, opts: CheckOptions) -> CheckReport[LinkContext]:
    """Connect, read every parameter, watch for ``opts.watch_s`` seconds, diagnose."""
    target = await asyncio.to_thread(resolve, cfg, opts)  # a blocking socket read
    async with Px4Link(target.url, opts.timeout_s) as px4:
        params = await px4.params()
        armed = await px4.armed()
        seen: Mapping[str, Any] | None = None
        view: ShellView | None = None
        if opts.watch_s > 0:
            seen = await px4.watch(opts.watch_s)
            if opts.shell:
                view = shell_view(await px4.shell(shell_commands()))
        system_id, autopilot = px4.system_id, px4.autopilot
    ctx = dataclasses.replace(target.ctx, gps_seen=bool(seen["gps_seen"]) if seen else None)
    params, not_finite = finite_params(params)
    rows = not_finite + tuple(evaluate(params, ctx))
    verdict = None
    if seen is not None:
        obs = Observations(
            watch_s=opts.watch_s,
            estimator_flags=seen["estimator_flags"],
            local_positions=int(seen["local_positions"]),
            lpos_first_s=seen["lpos_first_s"],
            lpos_last_s=seen["lpos_last_s"],
            lpos_max_gap_s=seen["lpos_max_gap_s"],
            gps_seen=bool(seen["gps_seen"]),
            statustexts=tuple(seen["statustexts"]),
            shell=view,
            service=await asyncio.to_thread(service_status, target.socket),
        )
        verdict = diagnose(obs, params, ctx)
    n_params = len(params) + len(not_finite)
    return CheckReport(
        target.url, system_id, autopilot, armed, n_params, ctx, rows, verdict, opts.watch_s
    )


def header(url: str, system_id: int, autopilot: str, armed: bool, n: int, ctx: LinkContext) -> str:
    """Two lines: the autopilot as reached, and our side."""
    link = (
        f"{ctx.link_kind} {ctx.link_host}:{ctx.link_port}"
        if ctx.link_kind != "serial"
        else f"{ctx.link_host} at {ctx.link_port} baud"
    )
    return (
        autopilot_line(url, system_id, autopilot, armed, n)
        + f"\ncompanion: sends {ctx.output} on {link}, wired to the autopilot's {ctx.fc_port}"
    )


def format_check(report: CheckReport[LinkContext]) -> str:
    """Everything check prints."""
    r = report
    head = header(r.url, r.system_id, r.autopilot, r.armed, r.n_params, r.ctx)
    return format_report(head, r, "companion px4 configure", "because:    ")
