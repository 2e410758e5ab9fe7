"""``companion autopilot check`` on ArduPilot: the parameters that govern external navigation
(:mod:`.rules`) and a few seconds of watching whether EKF3 fuses our estimate
(:mod:`.ekf3_diagnosis`). The same table, verdict and exit codes as on PX4
(:mod:`companion.autopilot.report`).
"""

from __future__ import annotations

import asyncio
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from companion.autopilot.ardupilot.ekf3_diagnosis import ArduPilotObservations, diagnose
from companion.autopilot.ardupilot.gps_rules import with_gps
from companion.autopilot.ardupilot.link import ArduPilotLink, Watched
from companion.autopilot.ardupilot.rules import ArduPilotContext, evaluate
from companion.autopilot.options import CheckOptions
from companion.autopilot.params import Param, Row, finite_params
from companion.autopilot.reach import resolve_link
from companion.autopilot.report import (
    CheckReport,
    autopilot_line,
    format_report,
    service_status,
)
from companion.config import Config


def context(
    cfg: Config, opts: CheckOptions, status: dict[str, Any] | None, seen: Watched | None
) -> ArduPilotContext:
    """Our side (the config, the running service's latency) and what the watch saw."""
    latency = None
    if status is not None:
        out = status.get("output")
        value = out.get("latency_ms_p50") if isinstance(out, dict) else None
        latency = float(value) if isinstance(value, (int, float)) else None
    origin = None
    if seen is not None:
        origin = seen.origin is not None or (seen.position is not None and seen.position != (0, 0))
    return ArduPilotContext(
        output=cfg.service.output,
        system_id=cfg.service.system_id,
        set_origin=cfg.service.ardupilot.set_origin,
        autopilot_sensor_ids=tuple(rf.sensor_id for rf in cfg.rangefinders if not rf.serial),
        latency_ms=latency,
        gps_seen=seen.gps_seen if seen is not None else None,
        origin_seen=origin,
        no_gnss=opts.no_gnss,
        declination_deg=(
            cfg.service.ardupilot.declination_deg if cfg.service.ardupilot.set_declination else None
        ),
        with_gps=opts.with_gps,
    )


def evaluate_rows(params: Mapping[str, Param], ctx: ArduPilotContext) -> list[Row]:
    """Every row (:func:`.rules.evaluate`); with ``ctx.with_gps`` judged for GPS (set 1) and
    our vision (set 2) together (:mod:`.gps_rules`)."""
    rows = evaluate(params, ctx)
    return with_gps(rows, params, ctx) if ctx.with_gps else rows


def _session(
    cfg: Config, opts: CheckOptions, url: str, socket: Path
) -> tuple[ArduPilotLink, dict[str, Param], bool, Watched | None, dict[str, Any] | None]:
    link = ArduPilotLink(url, opts.timeout_s).__enter__()
    try:
        params = link.params()  # NaN and infinities included: finite_params() sorts them out
        armed = link.armed()
        seen = link.watch(opts.watch_s) if opts.watch_s > 0 else None
    finally:
        link.close()
    return link, params, armed, seen, service_status(socket)


async def run_check(cfg: Config, opts: CheckOptions) -> CheckReport[ArduPilotContext]:
    """Connect, read every parameter, watch for ``opts.watch_s`` seconds, diagnose."""
    target = await asyncio.to_thread(resolve_link, cfg, opts)
    link, params, armed, seen, status = await asyncio.to_thread(
        _session, cfg, opts, target.url, target.socket
    )
    ctx = context(cfg, opts, status, seen)
    finite, not_finite = finite_params(params)
    rows = not_finite + tuple(evaluate_rows(finite, ctx))
    verdict = None
    if seen is not None:
        verdict = diagnose(ArduPilotObservations(opts.watch_s, seen, status), finite, ctx)
    return CheckReport(
        link.url,
        link.system_id,
        link.autopilot,
        armed,
        len(params),
        ctx,
        rows,
        verdict,
        opts.watch_s,
    )


def header(
    url: str, system_id: int, autopilot: str, armed: bool, n: int, ctx: ArduPilotContext
) -> str:
    origin = "sends the EKF origin" if ctx.set_origin else "sends no EKF origin"
    return (
        autopilot_line(url, system_id, autopilot, armed, n)
        + f"\ncompanion: sends {ctx.output} as system {ctx.system_id}, {origin}"
        + (f", latency {ctx.latency_ms:.0f} ms (p50)" if ctx.latency_ms is not None else "")
    )


def format_check(r: CheckReport[ArduPilotContext]) -> str:
    """Everything check prints (the layout of PX4's)."""
    head = header(r.url, r.system_id, r.autopilot, r.armed, r.n_params, r.ctx)
    return format_report(head, r, "companion autopilot configure", "but:        ")
