"""``configure`` on either autopilot: plan -> confirm -> write -> read back.

Refuses while the vehicle is armed (asked again just before writing). Shows the changes as a
diff (parameter, type, old -> new, reboot) and asks before writing unless ``--yes``. Writes
each with its own type, reads each back from the autopilot and compares, and says which ones
the autopilot applies only after a reboot. Each autopilot brings its session as a
:class:`ParamLink` and its rules as a function of the parameters.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from companion.autopilot.params import Param, Row, Status, Target, targets_of
from companion.autopilot.report import format_rows
from companion.errors import AutopilotError

GPS_WATCH_S = 2.5  # listen this long for a GNSS receiver (and ArduPilot's origin) before deciding


class ParamLink(Protocol):
    """What the flow needs of an autopilot session (PX4's MAVSDK, ArduPilot's pymavlink)."""

    async def armed(self) -> bool: ...

    async def params(self) -> dict[str, Param]: ...

    async def write(self, target: Target) -> None: ...

    async def read(self, name: str, is_int: bool) -> int | float: ...


@dataclass(frozen=True, slots=True)
class Change:
    """One write: the value before, the one asked for, and the one read back."""

    target: Target
    before: int | float | None
    after: int | float | None
    error: str = ""  # the write or the read-back failed: why

    @property
    def ok(self) -> bool:
        """Read back as written (float32 rounding allowed for a REAL32)."""
        return self.after is not None and not self.error and _same(self.after, self.target)


def _same(value: int | float, target: Target) -> bool:
    if target.is_int:
        return int(value) == int(target.value)
    return math.isclose(float(value), float(target.value), rel_tol=1e-6, abs_tol=1e-9)


@dataclass(frozen=True, slots=True)
class ConfigureReport:
    """What configure planned and did."""

    header: str
    planned: tuple[Change, ...]  # after = None: not written
    written: bool
    changes: tuple[Change, ...]
    rows_after: tuple[Row, ...]

    @property
    def problems(self) -> int:
        """Writes not read back as asked, plus FAIL rows left afterwards."""
        failed = sum(not c.ok for c in self.changes)
        return failed + sum(r.status is Status.FAIL for r in self.rows_after)


def _type(t: Target) -> str:
    return "INT32" if t.is_int else "REAL32"


def _show(v: int | float | None) -> str:
    if v is None:
        return "-"
    return str(v) if isinstance(v, int) else f"{v:g}"


def format_plan(planned: tuple[Change, ...] | list[Change]) -> str:
    """The diff: parameter, type, old -> new, reboot."""
    if not planned:
        return "nothing to change: every parameter is as needed"
    width = max(len(c.target.name) for c in planned)
    lines = ["changes:"]
    for c in planned:
        t = c.target
        lines.append(
            f"  {t.name.ljust(width)}  {_type(t):6}  {_show(c.before)} -> {_show(t.value)}"
            + ("   (reboot)" if t.reboot else "")
        )
    return "\n".join(lines)


def ask(question: str) -> bool:
    """y/N on the terminal; no answer (not a terminal) is no."""
    try:
        return input(f"{question} [y/N] ").strip().lower() in ("y", "yes")
    except EOFError:
        return False


def refuse_if_armed(armed: bool) -> None:
    """AutopilotError while the vehicle is armed: nothing is planned or written."""
    if armed:
        raise AutopilotError(
            "refusing to change parameters while the vehicle is armed: land and disarm first"
        )


async def write_and_read_back(link: ParamLink, planned: tuple[Change, ...]) -> list[Change]:
    """Write each, read each back (every write is tried whatever the others did)."""
    changes = []
    for c in planned:
        error = ""
        try:
            await link.write(c.target)
        except AutopilotError as e:
            error = str(e)
        after: int | float | None = None
        try:
            after = await link.read(c.target.name, c.target.is_int)
        except AutopilotError as e:
            error = error or str(e)
        if after is not None and error and _same(after, c.target):
            error = ""  # the acknowledgement got lost, the value is in
        changes.append(Change(c.target, c.before, after, error))
    return changes


async def plan_and_write(
    link: ParamLink,
    head: str,
    params: dict[str, Param],
    rows_of: Callable[[dict[str, Param]], list[Row]],
    yes: bool,
    confirm: Callable[[str], bool],
    show: Callable[[str], None],
) -> ConfigureReport:
    """The plan from ``rows_of(params)`` (the autopilot's rules), shown after ``head``; then
    confirmed (or ``yes``), written, read back, and the rules again on what the autopilot
    holds afterwards."""
    rows = rows_of(params)
    planned = tuple(
        Change(t, params[t.name].value if t.name in params else None, None)
        for t in targets_of(rows)
    )
    show(head)
    show(format_plan(planned))
    if not planned:
        return ConfigureReport(head, planned, False, (), tuple(rows))
    if not (yes or confirm(f"write these {len(planned)} parameter(s)?")):
        show("nothing written")
        return ConfigureReport(head, planned, False, (), tuple(rows))
    if await link.armed():
        raise AutopilotError("the vehicle was armed meanwhile: nothing written")
    changes = await write_and_read_back(link, planned)
    fresh = await link.params()
    return ConfigureReport(head, planned, True, tuple(changes), tuple(rows_of(fresh)))


def format_result(report: ConfigureReport) -> str:
    """Read-back results, reboot advice, and the table afterwards."""
    if not report.written:
        return ""
    lines = ["", "read back:"]
    for c in report.changes:
        if c.ok:
            status = "OK"
        elif c.after is None:
            status = f"NOT READ BACK ({c.error})"
        else:
            status = f"MISMATCH: wrote {_show(c.target.value)}" + (
                f" ({c.error})" if c.error else " (the autopilot kept another value)"
            )
        lines.append(f"  {c.target.name}: {_show(c.after)} ({_type(c.target)}) {status}")
    reboot = [
        c.target.name
        for c in report.changes
        if c.target.reboot and c.after is not None and c.after != c.before
    ]
    if reboot:
        lines += [
            "",
            "reboot the autopilot to apply: " + ", ".join(reboot),
            "  (QGroundControl: Parameters > Tools > Reboot Vehicle; or `reboot` in the "
            "MAVLink shell)",
        ]
    lines += ["", format_rows(report.rows_after)]
    n = report.problems
    lines += ["", f"result: {'OK' if n == 0 else f'{n} problem(s)'}"]
    return "\n".join(lines)
