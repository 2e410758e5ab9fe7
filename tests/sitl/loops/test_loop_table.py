"""The vision-only missions' table (companion.sitl.loops.loop_table) from summary.json files."""

from __future__ import annotations

import json
from pathlib import Path

from companion.sitl.loops import loop_table


def test_the_table_of_the_vision_only_missions(tmp_path: Path) -> None:
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    for d in (a, b, c):
        d.mkdir()
    s = {"mission": "square", "seed": 2, "landed": True, "failsafes": [], "path_m": 100.61}
    s |= {"ev_pos_fused_pct": 100.0, "horizontal_error_m_p95": 0.1234}
    s |= {"horizontal_error_pct_of_path": 0.1227, "vertical_error_m_p95": 0.067}
    s |= {"landing_error_m": 0.121, "camera_frames_dropped": 1}
    s |= {"latency_ms_p50": 44.04, "latency_ms_p99": 67.66}
    (a / "summary.json").write_text(json.dumps(s))
    s2 = s | {"autopilot": "ArduPilot", "mission": "lawnmower", "seed": 1, "landed": False}
    s2 |= {"failsafes": ["land"], "ev_pos_fused_pct": None}
    (b / "summary.json").write_text(json.dumps(s2))
    lines = loop_table.table([c, b, a]).splitlines()
    assert lines[1].count("---") == lines[0].count(" | ") + 1
    assert lines[2].startswith("| ArduPilot | lawnmower | 1 | 100.6 | - |")
    assert "| land | NO |" in lines[2]
    assert lines[3] == (
        "| PX4 | square | 2 | 100.6 | 100.0 | 0.123 (0.12) | 0.067 | 0.12 | none | yes | 1 "
        "| 44.0 / 67.7 |"
    )
    assert "no summary.json" in lines[4]
    assert all(line.count("|") == lines[0].count("|") for line in lines)
    assert loop_table.main([]) == 2
