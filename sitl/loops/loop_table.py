"""The vision-only missions' table for docs/RESULTS.md, from their ``summary.json`` files.

``python -m companion.sitl.loops.loop_table OUT...``: one row per flight (``companion sitl
px4|ardupilot --mission square|lawnmower --seed N --out OUT``), sorted by autopilot, mission and
seed. The columns are the figures of issues 19 and 21 as the loops summarise them
(sitl/loops/px4_results.py, ardupilot_results.py, loop_results.py): the path flown, the share of
the airborne time the autopilot fused our position, its horizontal and vertical error p95
against the simulator's truth (and as a share of the path), where it landed from home, the
failsafes, the frames dropped between the renderer and the service, and the capture-to-send
latency. A folder without a summary is a row that says so.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from companion.sitl.loops import flight_tables
from companion.sitl.loops.flight_tables import Row, fmt, render

HEADER = (
    "| autopilot | mission | seed | path [m] | ours fused [% of airborne] "
    "| horizontal p95 [m] (% of path) | vertical p95 [m] | landing from home [m] "
    "| failsafes | landed | frames dropped | latency p50 / p99 [ms] |"
)


def row(out: Path) -> Row:
    """The sort key and the markdown row of one flight's folder."""
    path = out / "summary.json"
    if not path.is_file():
        return ("~", out.name, 0), f"| {out.name} | no summary.json |" + " |" * 10
    s: dict[str, Any] = json.loads(path.read_text())
    ap = "ArduPilot" if s.get("autopilot") == "ArduPilot" else "PX4"
    mission, seed = str(s.get("mission")), int(s.get("seed") or 0)
    fused = s.get("ev_pos_fused_pct")
    pct = s.get("horizontal_error_pct_of_path")
    cells = [
        ap,
        mission,
        str(seed),
        fmt(s.get("path_m"), 1),
        "-" if fused is None else f"{float(fused):.1f}",
        f"{fmt(s.get('horizontal_error_m_p95'))} ({fmt(pct, 2)})",
        fmt(s.get("vertical_error_m_p95")),
        fmt(s.get("landing_error_m"), 2),
        "; ".join(s.get("failsafes") or []) or "none",
        "yes" if s.get("landed") else "NO",
        "-" if s.get("camera_frames_dropped") is None else str(s["camera_frames_dropped"]),
        f"{fmt(s.get('latency_ms_p50'), 1)} / {fmt(s.get('latency_ms_p99'), 1)}",
    ]
    return (ap, mission, seed), "| " + " | ".join(cells) + " |"


def table(outs: list[Path]) -> str:
    return render(HEADER, row, outs)


def main(argv: list[str] | None = None) -> int:
    return flight_tables.main("companion.sitl.loops.loop_table", table, argv)


if __name__ == "__main__":
    raise SystemExit(main())
