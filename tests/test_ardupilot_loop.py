"""The real ArduCopter (SITL) flies on our estimate: EKF3 on our external navigation, arm in
GUIDED, take off to 5 m, hover 20 s, land.

ArduCopter SITL, the bridge (sitl/ardupilot_bridge.py: SIM_STATE truth -> our camera stream and
TFmini ptys) and the service (`companion run`, a subprocess, sending ODOMETRY and the EKF origin)
run for real; nothing is mocked. ArduPilot instance 2 (TCP 5780-5783, camera on TCP 15702) so
that a `companion sitl ardupilot` on instance 0 can run beside it. About 100 s of wall time.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from ardupilot_peer import SKIP_REASON

from sitl import ardupilot_sitl
from sitl.ardupilot_flight import Flight, FlightOptions

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
    # issue 21 asks EKF3 minus the truth, horizontal p95 <= 0.25 m (in EKF3's own axes, which
    # are turned by the first heading: docs/RESULTS.md). Measured 0.19 m and 0.37 m (the
    # latter in a full-suite run, 0 frames dropped, 0 VO resets): not met reliably yet, the
    # issue stays open; this bound holds on a loaded machine, and a loop that does not fuse
    # our estimate fails the fusion and landing checks above
    assert s["horizontal_error_m_p95"] <= 0.5, detail
