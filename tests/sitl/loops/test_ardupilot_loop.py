"""The real ArduCopter (SITL) flies on our estimate: EKF3 on our external navigation, arm in
GUIDED, take off to 5 m, hover 20 s, land.

ArduCopter SITL, the bridge (sitl/loops/ardupilot_bridge.py: SIM_STATE truth -> our camera stream
and TFmini ptys) and the service (`companion run`, a subprocess, sending ODOMETRY and the EKF
origin) run for real; nothing is mocked. ArduPilot instance 2 (TCP 5780-5783, camera on TCP
15702) so that a `companion sitl ardupilot` on instance 0 can run beside it. About 100 s of
wall time.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from peers.ardupilot import SKIP_REASON

from companion.sitl.loops import ardupilot_sitl
from companion.sitl.loops.ardupilot_flight import Flight, FlightOptions

pytestmark = [
    pytest.mark.skipif(not ardupilot_sitl.available(), reason=SKIP_REASON),
    pytest.mark.timeout(300),
]


def test_ardupilot_hovers_on_our_estimate(tmp_path: Path) -> None:
    opts = FlightOptions(
        out=tmp_path / "ardupilot-hover",
        mission="hover",
        instance=2,
        hover_s=20.0,
        configure=False,  # `companion autopilot configure` has its own test
    )
    s = Flight(opts).run()
    detail = {k: v for k, v in s.items() if not isinstance(v, dict)}
    assert s["completed"], detail
    assert s["failsafes"] == [], detail
    assert s["landed"], detail
    assert s["ev_pos_fused_pct"] >= 99.0, detail
    assert s["compared_s"] >= 20.0, detail
    # issue 21: EKF3 minus the truth, horizontal p95 <= 0.25 m, in north-aligned axes too
    # (EKF3's heading from the compass with the site's declination; our frame's from the
    # autopilot's attitude at the VO's start). Measured 0.051 and 0.053 m on a loaded machine;
    # with our own yaw as EKF3's heading it was 0.19-0.37 m, turned 7 deg from north
    assert s["heading"] == "compass", detail
    assert s["horizontal_error_m_p95"] <= 0.25, detail
    assert s["horizontal_error_m_p95_north"] <= 0.25, detail
    assert abs(s["heading_offset_deg"]) <= 1.0, detail  # EKF3's north is true north
    log = (opts.out / "service.log").read_text()
    assert "its frame's heading" in log and "without an autopilot attitude" not in log, log
