"""The real PX4 (SIH) with GPS and our estimate together: a hover in which the GPS is lost for
15 s and comes back (`companion sitl px4 --mission gps-hover`, sitl/loops/gps_missions.py).

PX4 boots with its simulated GPS on, EKF2 fusing GNSS beside our position and velocity (no EV
yaw, our height the reference: what `companion px4 configure --with-gps` writes); the service
runs with ``[gps] align`` and the PX4 handover. It aligns its output to PX4's GPS frame on the
ground, holds that alignment while SIM_GPS_USED = 0 (at the first bad fix EKF2's lag behind
our output carried into it, EKF2_GPS_CTRL 0 sent 0.3 s later), slews back onto the returned
GPS and restores EKF2_GPS_CTRL. Nothing is mocked. PX4 instance 2 (a `make demo-px4` on
instance 0 and the vision-only hover on 1 can run beside it); the ground hold is cut to 20 s
(the vision-only hover keeps 45 s: the GNSS anchors the position here). About 130 s of wall
time.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest

from companion.sitl.loops.px4_flight import SHARED_PX4, Flight, FlightOptions

# PX4 SIH's lockstep clock against ours, as test_px4_loop.py bounds it: beyond 1 % PX4 could not
# keep real time on the host, our real-time samples reach EKF2 bunched and late, and the steps
# and the denied error are PX4's pace as much as ours (looser bounds then, with a warning)
PX4_REAL_TIME_PPM = 10_000

pytestmark = [
    pytest.mark.skipif(
        not SHARED_PX4.is_file(),
        reason=(
            f"PX4 SITL not found at {SHARED_PX4} (the shared folder beside the repository): "
            "this closed-loop test needs a real PX4 with its SIH simulator and its simulated "
            "GPS (docs/install.md, 'PX4 SITL')"
        ),
    ),
    pytest.mark.timeout(360),
]


def test_px4_hovers_through_a_gps_loss_and_return(tmp_path: Path) -> None:
    out = tmp_path / "px4-gps-hover"
    opts = FlightOptions(
        out=out,
        px4=str(SHARED_PX4),
        mission="gps-hover",
        instance=2,
        configure=False,  # the boot parameters are the --with-gps set (test_gps_missions.py)
        ground_hold_s=20.0,
    )
    s = Flight(opts).run()
    detail = {k: v for k, v in s.items() if not isinstance(v, (dict, list))}
    detail["gps_events"] = s.get("gps_events")
    assert s["completed"], detail
    assert s["failsafes"] == [], detail
    assert s["landed"], detail
    # the GPS was lost for the hover's 15 s of our clock and came back, as PX4's own log says;
    # PX4's log counts its own lockstep time, which a loaded host slows (15 s of ours were
    # 13.0 s of PX4's in a CI run with PX4 ~13 % slow), so its span goes back onto our clock
    assert s["gps_denied_s"] is not None, detail
    denied_our_clock_s = s["gps_denied_s"] * (1.0 + s["px4_clock_rate_vs_ours_ppm"] * 1e-6)
    assert 13.0 <= denied_our_clock_s <= 20.0, detail
    events = [e["event"] for e in s["gps_events"]]
    assert events[:2] == ["fix lost", "EKF2 stopped GNSS"], detail
    assert "fix back" in events and "EKF2 started GNSS" in events, detail
    # EKF2 stopped GNSS at once (our EKF2_GPS_CTRL 0), not at its own 7 s time-out
    stopped = s["gps_events"][1]["t_after_arming_s"] - s["gps_events"][0]["t_after_arming_s"]
    assert stopped <= 2.0, detail
    # issue "GPS in, GPS out": no step over 0.3 m at the loss or at the return (0.09 and
    # 0.16 m in the first hover), and the denied p95 within 0.5 m (0.37 m); our estimate
    # carried PX4 through the denial
    assert s["max_jump_m"] is not None and s["horizontal_error_m_p95_denied"] is not None
    if abs(s["px4_clock_rate_vs_ours_ppm"]) <= PX4_REAL_TIME_PPM:
        assert s["max_jump_m"] <= 0.3, detail
        assert s["horizontal_error_m_p95_denied"] <= 0.5, detail
        assert s["ev_used_fraction_denied"] >= 0.95, detail
    else:
        warnings.warn(
            f"PX4 SIH's clock ran {s['px4_clock_rate_vs_ours_ppm'] / 1e4:.1f} % off real time "
            f"on this host: largest step {s['max_jump_m']:.2f} m, denied p95 "
            f"{s['horizontal_error_m_p95_denied']:.2f} m, ours used "
            f"{100 * s['ev_used_fraction_denied']:.0f} % of the denial; the 0.3 / 0.5 m bounds "
            "need a host where PX4's lockstep keeps real time",
            stacklevel=1,
        )
        assert s["max_jump_m"] <= 0.6, detail
        assert s["horizontal_error_m_p95_denied"] <= 1.0, detail
        assert s["ev_used_fraction_denied"] >= 0.8, detail
    # the service said so: held at the loss, slewed back, EKF2_GPS_CTRL 0 then 7 acknowledged
    log = (out / "service.log").read_text()
    for line in ("aligned -> held", "held -> slewing", "slewing -> aligned"):
        assert f"GPS frame: {line}" in log, line
    assert "EKF2_GPS_CTRL 0 acknowledged" in log and "EKF2_GPS_CTRL 7 acknowledged" in log
    # EKF2's lag behind us carried into our output before EKF2_GPS_CTRL 0 ([gps]
    # px4_loss_carry): PX4 streamed its LOCAL_POSITION_NED at our request
    assert "carried into our output" in log and "EKF2_GPS_CTRL 0 in 0.30 s" in log
