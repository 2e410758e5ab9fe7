"""The GPS missions (sitl/loops/gps_missions.py) and their figures (gps_results.py).

The parameters the missions boot the real autopilots with are the ones `check --with-gps`
passes (so the missions fly what a user is told to set); the jump and the denied error are
measured as their docstrings say on tracks with a known reset, pull and offset.
"""

from __future__ import annotations

import numpy as np
import pytest

from companion.autopilot.ardupilot.check import evaluate_rows
from companion.autopilot.ardupilot.rules import ArduPilotContext
from companion.autopilot.params import Param, Status
from companion.autopilot.px4.link_context import LinkContext
from companion.autopilot.px4.rules import evaluate
from companion.sitl.loops import gps_missions, gps_results


def _judged(rows: list, names: set[str]) -> dict[str, Status]:
    return {r.name: r.status for r in rows if r.name in names}


@pytest.mark.parametrize("mission", gps_missions.GPS_MISSIONS)
def test_the_missions_boot_px4_as_check_with_gps_wants(mission: str) -> None:
    boot = {
        k: float(v) if "." in v else int(v)
        for k, v in gps_missions.px4_boot_params(mission).items()
    }
    params = {k: Param(k, v, isinstance(v, int)) for k, v in boot.items()}
    rows = evaluate(params, LinkContext("odometry", gps_seen=True, with_gps=True))
    judged = _judged(rows, set(gps_missions.PX4_GPS_BOOT_PARAMS))
    assert set(judged) == set(gps_missions.PX4_GPS_BOOT_PARAMS) - {"SENS_EN_GPSSIM"}
    assert all(s in (Status.OK, Status.INFO) for s in judged.values()), judged
    assert boot["SIM_GPS_USED"] == (0 if mission == "gps-appears" else 10)


@pytest.mark.parametrize("mission", gps_missions.GPS_MISSIONS)
def test_the_missions_boot_ardupilot_as_check_with_gps_wants(mission: str) -> None:
    boot = gps_missions.ardupilot_boot_params(mission)
    params = {k: Param(k, float(v), isinstance(v, int)) for k, v in boot.items()}
    ctx = ArduPilotContext(output="odometry", gps_seen=True, origin_seen=True, with_gps=True)
    names = set(boot) - {"SIM_GPS1_ENABLE"}  # the simulator's; ARMING_CHECK is judged
    judged = _judged(evaluate_rows(params, ctx), names)
    assert set(judged) == names
    assert all(s in (Status.OK, Status.INFO) for s in judged.values()), judged
    assert boot["SIM_GPS1_ENABLE"] == (0 if mission == "gps-appears" else 1)
    # indoors every pre-arm check stays on but the GPS lock
    assert boot.get("ARMING_CHECK") == (0xFFFFE & ~8 if mission == "gps-appears" else None)
    assert gps_missions.ardupilot_boot_params("square") == {}


def _flight(step_at_s: float, step_m: float, pull_m_s: float = 0.0):
    """A 60 s track at 100 Hz moving 2 m/s north; the estimate = truth + 0.3 m offset +
    1 cm noise, stepping by ``step_m`` east at ``step_at_s`` and pulling ``pull_m_s`` north
    after it."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 60.0, 0.01)
    truth = np.column_stack([2.0 * t, np.zeros_like(t), np.full_like(t, -5.0)])
    est = truth + np.array([0.3, 0.0, 0.0]) + rng.normal(0.0, 0.01, truth.shape)
    after = t >= step_at_s
    est[after, 1] += step_m
    est[after, 0] += pull_m_s * (t[after] - step_at_s)
    return t, est, truth


def test_a_reset_is_the_jump_and_the_motion_and_offset_are_not() -> None:
    t, est, truth = _flight(30.0, 0.25)
    j = gps_results.jump_at(t, est - truth, 29.5)  # the step 0.5 s after the change
    assert j is not None and 0.22 < j["jump_m"] < 0.29 and j["vertical_m"] < 0.05
    quiet = gps_results.jump_at(t, est - truth, 10.0)  # 2 m/s of motion, 0.3 m offset: none
    assert quiet is not None and quiet["jump_m"] < 0.05
    assert gps_results.jump_at(t, est - truth, 59.5) is not None
    assert gps_results.jump_at(t, est - truth, 61.0) is None  # outside the track


def test_the_summary_of_a_denial() -> None:
    t, est, truth = _flight(40.0, 0.0, pull_m_s=0.05)  # drifts 5 cm/s north from 40 s
    s: dict = {}
    events = [("fix lost", 20.0), ("fix back", 40.0), ("EKF2 started GNSS", 50.0)]
    gps_results.summarise_gps(s, t, est, t, truth, events, 5.0, (20.0, 40.0))
    assert s["gps_lost_s"] == 15.0 and s["gps_back_s"] == 35.0 and s["gps_denied_s"] == 20.0
    assert [e["event"] for e in s["gps_events"]] == [n for n, _ in events]
    # raw: the 0.3 m offset stays in (the frame is the GPS's)
    assert 0.3 < s["horizontal_error_m_p95_denied"] < 0.34
    assert s["max_jump_m"] == pytest.approx(0.05, abs=0.03)  # the pull's first second
    s2: dict = {}
    gps_results.summarise_gps(s2, t, est, t, truth, [("fix back", 30.0)], 0.0, (None, 30.0))
    assert s2["gps_lost_s"] is None and s2["horizontal_error_m_p95_denied"] is None
    assert s2["gps_back_s"] == 30.0


def test_transitions_of_a_flag() -> None:
    t = np.arange(6.0)
    assert gps_results.transitions(t, np.array([1, 1, 0, 0, 1, 1])) == [(2.0, False), (4.0, True)]


def test_the_table_of_the_missions(tmp_path) -> None:
    from companion.sitl.loops import gps_table

    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    s = {"mission": "gps-denied-zone", "seed": 2, "landed": True, "failsafes": []}
    s |= {"gps_lost_s": 18.9, "gps_back_s": 78.6, "max_jump_m": 0.214}
    s |= {"gps_events": [{"event": "fix lost", "jump_m": 0.1}, {"event": "x", "jump_m": 0.214}]}
    s |= {"horizontal_error_m_p95_denied": 0.21, "ev_used_fraction_denied": 1.0}
    s |= {"service_frame": {"yaw_deg": 1.0249, "translation_ned_m": [0.3, -0.4, 0.0]}}
    s["service_frame"] |= {"carried_m": 0.2408}
    (a / "summary.json").write_text(__import__("json").dumps(s))
    text = gps_table.table([b, a])
    lines = text.splitlines()
    assert lines[2].startswith(
        "| PX4 | gps-denied-zone | 2 | yes | 18.9 / 78.6 | 0.214 (x) | 0.241 | 0.210 (-) |"
    )
    assert "100.0 %" in lines[2] and "no summary.json" in lines[3]
    assert lines[2].endswith("| 1.02 deg, 0.50 m |")
    assert lines[1].count("---") == lines[0].count(" | ") + 1
    assert gps_table.main([]) == 2
