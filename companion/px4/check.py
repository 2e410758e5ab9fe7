"""``companion px4 check``: the parameters that govern external vision, then a few seconds of
watching whether EKF2 fuses our estimate (and if not, the most likely reason).

The autopilot is reached through MAVSDK on ``--url``, or on the service's own link
(``service.mavlink_url``) when the service is not running: a running service holds that port,
and then check asks for another link instead of fighting over it.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from companion.config import Config
from companion.drivers.mavlink import LinkUrl
from companion.drivers.px4_shell_text import parse_listener, parse_uorb_top
from companion.drivers.status import StatusError, find_status_socket, printable, read_status
from companion.errors import ConfigError
from companion.px4.fusion import Observations, ShellView, Verdict, diagnose
from companion.px4.link import Px4Link, mavsdk_url
from companion.px4.options import Px4Options
from companion.px4.rules import LinkContext, Param, Row, Status, evaluate

SHELL_TOPICS = (
    "vehicle_visual_odometry",
    "vehicle_mocap_odometry",
    "estimator_status_flags",
    "estimator_aid_src_ev_pos",
    "timesync_status",
    "estimator_aid_src_gnss_pos",
)


@dataclass(frozen=True, slots=True)
class Target:
    """Where check and configure talk to, and what they know of our side."""

    url: str  # MAVSDK URL of the autopilot
    ctx: LinkContext  # our output and link, for the rules
    socket: Path  # the service's status socket


@dataclass(frozen=True, slots=True)
class CheckReport:
    """What check found."""

    url: str
    system_id: int
    autopilot: str
    armed: bool
    n_params: int
    ctx: LinkContext
    rows: tuple[Row, ...]
    verdict: Verdict | None  # None: not watched
    watch_s: float  # how long the autopilot was watched [s]

    @property
    def problems(self) -> int:
        """FAIL rows, plus one when the estimate is not (known to be) fused, or is fused but
        PX4 will not fly on it."""
        fails = sum(r.status is Status.FAIL for r in self.rows)
        return fails + (1 if self.verdict is not None and not self.verdict.ok else 0)


def service_status(path: Path) -> dict[str, Any] | None:
    """The running service's status, or None (not running, or not answering sensibly)."""
    try:
        return read_status(path)
    except (OSError, ValueError, json.JSONDecodeError, StatusError):
        return None


def service_answers(path: Path) -> bool:
    """Something answers on the service's status socket (a status we may not trust counts:
    whatever it is, it is running and may hold the service's link)."""
    try:
        return read_status(path) is not None
    except StatusError:
        return True
    except (OSError, ValueError):
        return False


def resolve(cfg: Config, opts: Px4Options) -> Target:
    """The autopilot URL and our side's context; ConfigError when the only link is the one
    the running service holds."""
    service_url = cfg.service.mavlink_url
    link = LinkUrl.parse(service_url)
    fc_port = opts.fc_port
    if fc_port == "auto":
        fc_port = "TELEM2" if link.kind == "serial" else "ETHERNET"
    socket = find_status_socket(opts.socket or cfg.service.status_socket)
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
    )
    own = mavsdk_url(service_url, "service.mavlink_url")
    url = mavsdk_url(opts.url) if opts.url else own
    if url == own and service_answers(socket):
        raise ConfigError(
            f"--url: the running service holds {service_url} (its status is on {socket}); "
            "give check its own link to the autopilot: PX4 SITL's (and the stub's) ground-"
            "station port --url udpin://127.0.0.1:14550, a USB or telemetry port "
            "(--url serial:///dev/ttyACM0:115200), or stop the service to use its link"
        )
    return Target(url, ctx, socket)


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


def finite_params(params: dict[str, Param]) -> tuple[dict[str, Param], tuple[Row, ...]]:
    """The parameters whose value is a finite number, and a FAIL row for each other one: a
    NaN or an infinity as read (a damaged parameter store, a hostile peer) is no value any
    rule can judge, and must not reach one (``int(nan)`` raised a traceback)."""
    finite = {k: p for k, p in params.items() if math.isfinite(p.value)}
    bad = tuple(
        Row(
            printable(name, 16),
            str(p.value),
            "a finite number",
            "not a number as read: set it (companion autopilot configure, or the GCS)",
            Status.FAIL,
        )
        for name, p in sorted(params.items())
        if name not in finite
    )
    return finite, bad


async def run_check(cfg: Config, opts: Px4Options) -> CheckReport:
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


def format_rows(rows: tuple[Row, ...] | list[Row]) -> str:
    """The parameter table: name, value, need, status, why."""
    head = ("parameter", "value", "need", "status", "why")
    table = [head] + [(r.name, r.value, r.need, r.status.value, r.why) for r in rows]
    widths = [max(len(t[i]) for t in table) for i in range(4)]
    lines = []
    for t in table:
        lines.append("  ".join(t[i].ljust(widths[i]) for i in range(4)) + "  " + t[4])
    return "\n".join(lines)


def autopilot_line(url: str, system_id: int, autopilot: str, armed: bool, n: int) -> str:
    """The header's first line (check and configure, PX4 and ArduPilot): the autopilot as
    reached."""
    return (
        f"autopilot: {autopilot} system {system_id} on {url}, "
        f"{'ARMED' if armed else 'disarmed'}, {n} parameters"
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


class CheckedReport(Protocol):
    """What :func:`format_report` prints of a check's report (PX4's or ArduPilot's)."""

    @property
    def rows(self) -> tuple[Row, ...]: ...

    @property
    def verdict(self) -> Verdict | None: ...

    @property
    def watch_s(self) -> float: ...

    @property
    def problems(self) -> int: ...


def format_report(head: str, r: CheckedReport, configure_command: str, undecided_label: str) -> str:
    """Everything a check prints: ``head``, the parameter table, the fusion verdict and the
    result line, which points to ``configure_command`` when it would write something. The
    first reason is "most likely:" when not fused, "but:" when fused, ``undecided_label``
    (12 characters) when the verdict cannot tell."""
    out = [head, ""]
    out.append(format_rows(r.rows))
    warns = sum(x.status is Status.WARN for x in r.rows)
    v = r.verdict
    if v is not None:
        out += ["", f"fusion (watched {r.watch_s:.1f} s): {v.headline}"]
        if v.reasons:
            first = (
                "most likely:"
                if v.fused is False
                else ("but:        " if v.fused else undecided_label)
            )
            out.append(f"  {first} {v.reasons[0]}")
            out += [f"  also:        {x}" for x in v.reasons[1:]]
        out += [f"  warning:     {x}" for x in v.warnings]
        out += [f"  seen:        {x}" for x in v.evidence]
    else:
        out += ["", "fusion: not watched (--watch-s 0)"]
    n = r.problems
    out += [
        "",
        f"result: {'OK' if n == 0 else f'{n} problem(s)'}"
        + (f", {warns} warning(s)" if warns else "")
        + (
            f" -- `{configure_command}` writes the needed values"
            if any(x.targets and x.status is not Status.OK for x in r.rows)
            else ""
        ),
    ]
    return "\n".join(out)


def format_check(report: CheckReport) -> str:
    """Everything check prints."""
    r = report
    head = header(r.url, r.system_id, r.autopilot, r.armed, r.n_params, r.ctx)
    return format_report(head, r, "companion px4 configure", "because:    ")
