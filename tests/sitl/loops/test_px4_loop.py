"""The real PX4 (SIH) flies on our estimate: vision only, arm, take off, hover 20 s, land.

PX4 SITL, the bridge (sitl/loops/px4_bridge.py: SIH truth -> our camera stream and TFmini ptys) and
the service (`companion run`, a subprocess) run for real; nothing is mocked. PX4 instance 1
(ports 18571, 14581/14541, 19451/19411; camera stream on TCP 15601) so that a `make demo-px4`
on instance 0 can run beside it. About 105 s of wall time: PX4's time sync converges ~11 s
after the service starts (it asks PX4 for TIMESYNC at 50 Hz), but the flight keeps EKF2 fusing
our position on the ground for 45 s before arming (FlightOptions.ground_hold_s: armed 5 s after
the fusion began, this hover drifted 0.8 m in the climb; docs/decisions.md).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest

from companion.sitl.loops.px4_flight import SHARED_PX4, Flight, FlightOptions

# PX4 SIH's lockstep clock against ours: ~0.1 % on the host of 2026-11-25, 0.9-2.3 % over the
# hovers of 2026-11-27 on a slower one (docs/RESULTS.md, "2026-11-27 (bfdc1dc)"), 0.6-0.8 % in
# every hover here from e751c17 to d7a0c08. Up to 1 % the 99 % is asserted: since EKF2's longer
# horizon (5451f47: EKF2_DELAY_MAX 300, poses up to 200 ms old) the late, bunched samples of a
# slow clock are fused (hovers at 0.64 / 0.77 % off: 100.0 % fused; the six missions 100.0 %)
PX4_REAL_TIME_PPM = 10_000

pytestmark = [
    pytest.mark.skipif(
        not SHARED_PX4.is_file(),
        reason=(
            f"PX4 SITL not found at {SHARED_PX4} (the shared folder beside the repository): "
            "this closed-loop test needs a real PX4 with its SIH simulator. Put the px4-sitl "
            "launcher there, or build PX4 SITL yourself (docs/install.md, 'PX4 SITL': "
            "PX4-Autopilot + `make px4_sitl_default`) and run `companion sitl px4 --px4 PATH`"
        ),
    ),
    pytest.mark.timeout(300),
]


def test_px4_hovers_on_our_estimate(tmp_path: Path) -> None:
    opts = FlightOptions(
        out=tmp_path / "px4-hover",
        px4=str(SHARED_PX4),
        mission="hover",
        instance=1,
        hover_s=20.0,
        configure=False,  # `companion px4 configure` is not under test here (boot parameters)
    )
    s = Flight(opts).run()
    detail = {k: v for k, v in s.items() if not isinstance(v, dict)}
    assert s["completed"], detail
    assert s["failsafes"] == [], detail
    assert s["landed"], detail
    # armed only once PX4 converted our stamps through its time sync (its shell said so:
    # `listener vehicle_visual_odometry`, a stamp some latency before arrival)
    assert s["timesync_converged_at_arming"] is True, detail
    # PX4 took the TIMESYNC rate the service asks for (service.px4_timesync_rate_hz): its time
    # sync converges ~10 s after the service starts, not ~50 s
    assert 111 in (s["rates_acknowledged"] or []), detail
    # the ground start: PX4 armed in Position mode on our estimate, so it is fused over the
    # whole airborne time and the vehicle comes down where it took off (0.18-0.42 m measured
    # on a quiet machine, 0.97 m at load average 10 with 1,099 frames dropped; the take-off in
    # Altitude mode before it drifted 2-4 m)
    assert s["armed_mode"] == "POSCTL", detail
    assert s["landing_error_m"] <= 1.0, detail
    if abs(s["px4_clock_rate_vs_ours_ppm"]) <= PX4_REAL_TIME_PPM:
        assert s["ev_pos_fused_pct"] >= 99.0, detail
        assert s["ev_pos_fused_pct_whole_airborne"] >= 99.0, detail
    else:
        # PX4's own simulation could not keep real time on this host: its lockstep clock ran
        # slow and unsteadily (PX4 alone, nothing else running: 2.2-3.3 % slow on 2026-11-27),
        # so our real-time samples reach EKF2 bunched and late and it drops some of them; the
        # 99 % is not a property of the companion there. What must still hold: EKF2 never goes
        # long without our position (0.7-3.0 s at most, 48-92 % fused, in the hovers of bfdc1dc
        # there) and the loop stays safe (the assertions above and below).
        warnings.warn(
            f"PX4 SIH's clock ran {s['px4_clock_rate_vs_ours_ppm'] / 1e4:.1f} % off real time "
            f"on this host (more than {PX4_REAL_TIME_PPM / 1e4:.1f} %): EV fusion "
            f"{s['ev_pos_fused_pct']:.1f} % of the airborne time, at most "
            f"{s.get('ev_pos_unfused_max_s', float('inf')):.2f} s without it; the >= 99 % "
            "bound of issue 19 needs a host where PX4's lockstep keeps real time",
            stacklevel=1,
        )
        assert s.get("ev_pos_unfused_max_s", float("inf")) <= 5.0, detail
        assert s["ev_pos_fused_pct"] >= 40.0, detail
    # issue 19's p95 <= 0.25 m. Every hover at 20 Hz since 06612af met it: 0.136-0.209 m
    # by hand and in CI, 0.153 / 0.156 m in two CI runs side by side on 2026-11-27 (load average
    # 4-7). Before (30 Hz, the fusion gaps of a slow host) it was 0.141-0.376 m (2026-11-25
    # to 2026-11-27). PX4's own rangefinder mixed into our sensor 0 gave 0.44-1.09 m
    assert s["horizontal_error_m_p95"] is not None, detail  # a stretch of >= 10 finite samples
    assert s["horizontal_error_m_p95"] <= 0.25, detail
    # our frame's heading comes from our compass at rest (vo.heading_source = magnetometer):
    # within 0.6 deg of SIH's yaw (the six missions of d7a0c08: -0.08 to +0.24 deg, sigma 0.10;
    # PX4's heading at our start, which the frame took before, was up to 1.15 deg off)
    assert abs(s["frame_heading_error_deg"]) <= 0.6, detail
    # ... from PX4's SCALED_IMU through the service: >= 10 s of field samples at 50 Hz (the
    # ground hold gives ~50 s)
    assert (s["mag_heading_samples"] or 0) >= 500, detail
