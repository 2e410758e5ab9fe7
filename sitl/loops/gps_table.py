"""The GPS missions' table for docs/RESULTS.md, from their ``summary.json`` files.

``python -m companion.sitl.loops.gps_table OUT...``: one row per flight (``companion sitl
px4|ardupilot --mission gps-denied-zone|gps-appears|gps-hover --out OUT``), sorted by
autopilot, mission and seed; the columns say whether it landed without a failsafe, the GPS
change times, ``max_jump_m`` and the event it was at, the horizontal p95 while denied (and
before), how far EKF2's own estimate lay from our output when the service carried that lag into
it at the loss (PX4: ``[gps] px4_loss_carry``), and how much of the denial the autopilot used
our estimate. A folder without a
summary is a row that says so. The last column is the alignment the service applied at its end:
how far our own frame (our compass's north, the take-off point) lay from the GPS frame.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from companion.sitl.loops import flight_tables
from companion.sitl.loops.flight_tables import Row, fmt, render

HEADER = (
    "| autopilot | mission | seed | landed, no failsafe | GPS lost / back [s after arming] "
    "| max_jump_m (at) | EKF2's lag carried at the loss [m] | horizontal p95 denied (before) "
    "| ours used while denied "
    "| autopilot's resets while denied | our frame to the GPS's (yaw, shift) |"
)


def _frame(frame: Any) -> str:
    """The service's applied alignment at its exit: how far our own frame lay from the GPS's."""
    if not isinstance(frame, dict) or frame.get("yaw_deg") is None:
        return "-"
    t = frame.get("translation_ned_m") or [0.0, 0.0, 0.0]
    return f"{float(frame['yaw_deg']):.2f} deg, {math.hypot(t[0], t[1]):.2f} m"


def row(out: Path) -> Row:
    """The sort key and the markdown row of one flight's folder."""
    path = out / "summary.json"
    if not path.is_file():
        return ("~", out.name, 0), f"| {out.name} | no summary.json | | | | | | | | | |"
    s = json.loads(path.read_text())
    ap = "ArduPilot" if s.get("autopilot") == "ArduPilot" else "PX4"
    mission, seed = str(s.get("mission")), int(s.get("seed") or 0)
    ok = bool(s.get("landed")) and not s.get("failsafes")
    events = [e for e in s.get("gps_events") or [] if e.get("jump_m") is not None]
    worst = max(events, key=lambda e: e["jump_m"], default=None)
    at = f" ({worst['event']})" if worst else ""
    used = s.get("ev_used_fraction_denied")
    before = s.get("horizontal_error_m_p95_before_denial")
    resets = s.get("px4_xy_resets_denied")
    reset_text = (
        "-" if resets is None else f"{resets} ({fmt(s.get('px4_xy_reset_max_m_denied'), 2)} m)"
    )
    cells = [
        ap,
        mission,
        str(seed),
        "yes" if ok else f"NO ({'; '.join(s.get('failsafes') or []) or 'not landed'})",
        f"{fmt(s.get('gps_lost_s'), 1)} / {fmt(s.get('gps_back_s'), 1)}",
        f"{fmt(s.get('max_jump_m'))}{at}",
        fmt((s.get("service_frame") or {}).get("carried_m")),
        f"{fmt(s.get('horizontal_error_m_p95_denied'))} ({fmt(before)})",
        "-" if used is None else f"{100.0 * used:.1f} %",
        reset_text,
        _frame(s.get("service_frame")),
    ]
    return (ap, mission, seed), "| " + " | ".join(cells) + " |"


def table(outs: list[Path]) -> str:
    return render(HEADER, row, outs)


def main(argv: list[str] | None = None) -> int:
    return flight_tables.main("companion.sitl.loops.gps_table", table, argv)


if __name__ == "__main__":
    raise SystemExit(main())
