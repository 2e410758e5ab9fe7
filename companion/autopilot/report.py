"""What ``check`` prints on either autopilot: the parameter table, the fusion verdict and the
result line; and the running service's status it weighs."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

from companion.autopilot.params import Row, Status
from companion.autopilot.verdict import Verdict
from companion.drivers.status import StatusError, read_status

ContextT = TypeVar("ContextT")


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


@dataclass(frozen=True, slots=True)
class CheckReport(Generic[ContextT]):
    """What check found, on PX4 (``ctx``: its LinkContext) or ArduPilot (its
    ArduPilotContext)."""

    url: str
    system_id: int
    autopilot: str
    armed: bool
    n_params: int
    ctx: ContextT  # our side, as the autopilot's rules saw it
    rows: tuple[Row, ...]
    verdict: Verdict | None  # None: not watched
    watch_s: float  # how long the autopilot was watched [s]

    @property
    def problems(self) -> int:
        """FAIL rows, plus one when the estimate is not (known to be) fused, or is fused but
        the autopilot will not fly on it."""
        fails = sum(r.status is Status.FAIL for r in self.rows)
        return fails + (1 if self.verdict is not None and not self.verdict.ok else 0)


def format_report(
    head: str, r: CheckReport[Any], configure_command: str, undecided_label: str
) -> str:
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
