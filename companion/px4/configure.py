"""``companion px4 configure``: write the values check asks for, with the right types.

Refuses while the vehicle is armed (asked again just before writing). Shows the changes as a
diff (parameter, type, old -> new, reboot) and asks before writing unless ``--yes``. Writes
each with its own type through MAVSDK (``set_param_int`` for an INT32: its bits, never a
float), reads each back from the autopilot and compares, and says which ones PX4 applies only
after a reboot.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

from companion.config import Config
from companion.errors import Px4Error
from companion.px4.check import format_rows, header, resolve
from companion.px4.link import Px4Link
from companion.px4.options import Px4Options
from companion.px4.rules import Row, Status, Target, evaluate, targets_of

GPS_WATCH_S = 2.5  # listen this long for a GNSS receiver (GPS_RAW_INT) before deciding


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


async def run_configure(
    cfg: Config,
    opts: Px4Options,
    confirm: Callable[[str], bool] = ask,
    show: Callable[[str], None] = print,
) -> ConfigureReport:
    """Plan, confirm, write, read back."""
    target = await asyncio.to_thread(resolve, cfg, opts)  # a blocking socket read
    async with Px4Link(target.url, opts.timeout_s) as px4:
        armed = await px4.armed()
        params = await px4.params()
        head = header(px4.url, px4.system_id, px4.autopilot, armed, len(params), target.ctx)
        if armed:
            raise Px4Error(
                "refusing to change parameters while the vehicle is armed: land and disarm first"
            )
        seen = await px4.watch(GPS_WATCH_S)
        ctx = dataclasses.replace(target.ctx, gps_seen=bool(seen["gps_seen"]))
        planned = tuple(
            Change(t, params[t.name].value if t.name in params else None, None)
            for t in targets_of(evaluate(params, ctx))
        )
        show(head)
        show(format_plan(planned))
        if not planned:
            return ConfigureReport(head, planned, False, (), tuple(evaluate(params, ctx)))
        if not (opts.yes or confirm(f"write these {len(planned)} parameter(s)?")):
            show("nothing written")
            return ConfigureReport(head, planned, False, (), tuple(evaluate(params, ctx)))
        if await px4.armed():
            raise Px4Error("the vehicle was armed meanwhile: nothing written")
        changes = []
        for c in planned:  # every write is tried and read back, whatever the others did
            error = ""
            try:
                await px4.write(c.target)
            except Px4Error as e:
                error = str(e)
            after: int | float | None = None
            try:
                after = await px4.read(c.target.name, c.target.is_int)
            except Px4Error as e:
                error = error or str(e)
            if after is not None and error and _same(after, c.target):
                error = ""  # the acknowledgement got lost, the value is in
            changes.append(Change(c.target, c.before, after, error))
        fresh = await px4.params()
    rows_after = tuple(evaluate(fresh, ctx))
    return ConfigureReport(head, planned, True, tuple(changes), rows_after)


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
