"""``companion autopilot check | configure`` on ArduPilot: the parameters that govern external
navigation (:mod:`.ardupilot_rules`), a few seconds of watching whether EKF3 fuses our estimate
(:mod:`.ardupilot_fusion`), and configure: write what check asks for with the parameter's own
type, read every one back, say which need a reboot. The same table, verdict and exit codes as
``companion px4 check | configure`` (whose resolution of the link, status reading, plan and
read-back formatting are reused).
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from companion.autopilot.ardupilot_fusion import ArduPilotObservations, diagnose
from companion.autopilot.ardupilot_link import ArduPilotLink, Watched
from companion.autopilot.ardupilot_rules import ArduPilotContext, evaluate
from companion.config import Config
from companion.errors import Px4Error
from companion.px4.check import (
    autopilot_line,
    finite_params,
    format_report,
    resolve,
    service_status,
)
from companion.px4.configure import Change, ConfigureReport, ask, format_plan
from companion.px4.fusion import Verdict
from companion.px4.options import Px4Options
from companion.px4.rules import Param, Row, Status, targets_of

GPS_WATCH_S = 2.5  # configure: listen this long (GPS, origin) before deciding


@dataclass(frozen=True, slots=True)
class ArduPilotReport:
    """What check found."""

    url: str
    system_id: int
    autopilot: str
    armed: bool
    n_params: int
    ctx: ArduPilotContext
    rows: tuple[Row, ...]
    verdict: Verdict | None
    watch_s: float

    @property
    def problems(self) -> int:
        """FAIL rows, plus one when the estimate is not fused (or fused with a problem)."""
        fails = sum(r.status is Status.FAIL for r in self.rows)
        return fails + (1 if self.verdict is not None and not self.verdict.ok else 0)


def context(
    cfg: Config, opts: Px4Options, status: dict[str, Any] | None, seen: Watched | None
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
    )


def _session(
    cfg: Config, opts: Px4Options, url: str, socket: Any
) -> tuple[ArduPilotLink, dict[str, Param], bool, Watched | None, dict[str, Any] | None]:
    link = ArduPilotLink(url, opts.timeout_s).__enter__()
    try:
        params = link.params()  # NaN and infinities included: finite_params() sorts them out
        armed = link.armed()
        seen = link.watch(opts.watch_s) if opts.watch_s > 0 else None
    finally:
        link.close()
    return link, params, armed, seen, service_status(socket)


async def run_check(cfg: Config, opts: Px4Options) -> ArduPilotReport:
    """Connect, read every parameter, watch for ``opts.watch_s`` seconds, diagnose."""
    target = await asyncio.to_thread(resolve, cfg, opts)
    link, params, armed, seen, status = await asyncio.to_thread(
        _session, cfg, opts, target.url, target.socket
    )
    ctx = context(cfg, opts, status, seen)
    finite, not_finite = finite_params(params)
    rows = not_finite + tuple(evaluate(finite, ctx))
    verdict = None
    if seen is not None:
        verdict = diagnose(ArduPilotObservations(opts.watch_s, seen, status), finite, ctx)
    return ArduPilotReport(
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


def format_check(r: ArduPilotReport) -> str:
    """Everything check prints (the layout of ``companion px4 check``)."""
    head = header(r.url, r.system_id, r.autopilot, r.armed, r.n_params, r.ctx)
    return format_report(head, r, "companion autopilot configure", "but:        ")


def _write_all(link: ArduPilotLink, planned: tuple[Change, ...]) -> list[Change]:
    """Write each, read each back (every write is tried whatever the others did)."""
    changes = []
    for c in planned:
        error = ""
        try:
            link.write(c.target)
        except Px4Error as e:
            error = str(e)
        after: int | float | None = None
        try:
            value = link.read(c.target.name)
            after = int(round(value)) if c.target.is_int and math.isfinite(value) else value
        except Px4Error as e:
            error = error or str(e)
        changes.append(Change(c.target, c.before, after, error))
    return changes


async def run_configure(
    cfg: Config,
    opts: Px4Options,
    confirm: Callable[[str], bool] = ask,
    show: Callable[[str], None] = print,
) -> ConfigureReport:
    """Plan, confirm, write, read back (refused while armed)."""
    target = await asyncio.to_thread(resolve, cfg, opts)
    link = ArduPilotLink(target.url, opts.timeout_s)
    await asyncio.to_thread(link.__enter__)
    try:
        armed = await asyncio.to_thread(link.armed)
        params = await asyncio.to_thread(link.params)
        status = await asyncio.to_thread(service_status, target.socket)
        if armed:
            raise Px4Error(
                "refusing to change parameters while the vehicle is armed: land and disarm first"
            )
        seen = await asyncio.to_thread(link.watch, GPS_WATCH_S)
        ctx = context(cfg, opts, status, seen)
        head = header(link.url, link.system_id, link.autopilot, armed, len(params), ctx)
        finite, not_finite = finite_params(params)
        rows = [*not_finite, *evaluate(finite, ctx)]
        planned = tuple(
            Change(t, params[t.name].value if t.name in params else None, None)
            for t in targets_of(rows)
        )
        show(head)
        show(format_plan(planned))
        if not planned:
            return ConfigureReport(head, planned, False, (), tuple(rows))
        if not (opts.yes or confirm(f"write these {len(planned)} parameter(s)?")):
            show("nothing written")
            return ConfigureReport(head, planned, False, (), tuple(rows))
        if await asyncio.to_thread(link.armed):
            raise Px4Error("the vehicle was armed meanwhile: nothing written")
        changes = await asyncio.to_thread(_write_all, link, planned)
        fresh = await asyncio.to_thread(link.params)
    finally:
        link.close()
    ctx = dataclasses.replace(ctx)
    fresh_finite, fresh_not_finite = finite_params(fresh)
    rows_after = fresh_not_finite + tuple(evaluate(fresh_finite, ctx))
    return ConfigureReport(head, planned, True, tuple(changes), rows_after)
