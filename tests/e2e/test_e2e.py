"""End to end over loopback: the SITL autopilot (its own process for the camera) and the
service, on the default scenario (hills, lawnmower; 30 s of flight here, 60 s in `make demo`),
in slow motion (SCALE flight seconds per second: the camera at 15 frames/s).

What is asserted holds at any load (a busy laptop, CI beside another test run; issue 16): every
camera frame is accounted for, what the service sent is what the autopilot decoded, the time
sync is as good as the link's round trip allows, metric ATE in the autopilot's frame and clock
<= 1.5 % of the path, no VO reset unless the machine stalled. The real-time figures (30 Hz
received, latency, the 1 ms time-sync error and 5 ms round trip of a quiet machine) are
benchmarks: `make demo`, docs/BENCHMARKS.md. A service that stalls or drops every other frame
still fails here (received rate >= half what its pipeline could do, up to the camera's rate).

Slow motion (2026-11-27): here the SITL autopilot runs in the service's process (the test reads
its internals), which a real one never does, and on a slow 2-core host that process turned a
frame over in 40-60 ms with stalls of 150 ms: in real time the VO lost its map up to 13 times
in a flight (`vo_resets` 13, `vo_gaps` 0) and the pad's flight published nothing over the pad
again, while `companion demo` (the autopilot in its own process) kept up with 30 Hz on the same
host. At half speed the pipeline has the time a vehicle's companion has.
"""

from __future__ import annotations

import asyncio
import os

import numpy as np
import pytest
from peers import sitl_flight, slow_motion_overrides

from companion.config import load_config
from companion.drivers.status import read_status
from companion.geometry import so3
from companion.service.app import Service
from companion.sitl.stub.autopilot import SimAutopilot

SECONDS = float(os.environ.get("COMPANION_E2E_SECONDS", "30"))
SCALE = 0.5  # flight seconds per wall-clock second (AutopilotOptions.time_scale)


@pytest.mark.slow
@pytest.mark.timeout(2 * SECONDS / SCALE + 240)  # + waiting for the machine (tests/peers/)
def test_service_and_sitl_autopilot_end_to_end(tmp_path) -> None:
    cfg, opts = sitl_flight(tmp_path, SECONDS, time_scale=SCALE)

    async def both() -> tuple[dict, dict]:
        stub = SimAutopilot(cfg, opts)
        stub_task = asyncio.create_task(stub.run(tmp_path / "autopilot"))
        async with Service(cfg) as service:
            stub_task.add_done_callback(lambda _: service.stop())

            async def look() -> None:  # `companion status` while it flies
                while service.stats.published < 300:
                    await asyncio.sleep(0.2)
                seen.update(await asyncio.to_thread(read_status, tmp_path / "status.sock"))

            looker = asyncio.create_task(look())
            await service.run()
            looker.cancel()
        report = await stub_task
        # what the autopilot decoded (pymavlink, MAVLink 2) against what the service sent
        sent = {p.time_us: p for p in service.stats.sent}
        pairs = [(r, sent[r.time_usec]) for r in stub.stats.received if r.time_usec in sent]
        assert len(pairs) >= 100
        for r, pose in pairs:
            np.testing.assert_allclose(r.position, pose.position_ned_m, rtol=1e-6, atol=1e-5)
            rpy = so3.matrix_to_rpy(so3.quat_to_matrix(pose.quat_wxyz_ned_frd))
            np.testing.assert_allclose(r.rpy, rpy, atol=1e-6)
            assert r.reset_counter == pose.reset_counter
        frame_us.extend(p.time_us for p in service.stats.sent)
        return report, service.summary()

    seen: dict = {}
    frame_us: list[int] = []
    report, summary = asyncio.run(both())
    assert seen["vo"]["state"] == "TRACKING"
    rate = cfg.camera.rate_hz * SCALE  # frames per wall-clock second
    assert 0.5 * rate <= seen["camera"]["fps"] <= 1.2 * rate
    assert seen["autopilot"]["timesync_converged"] and seen["autopilot"]["system_id"] == 1
    # ATTITUDE, TIMESYNC (PX4's time sync asked faster) and DISTANCE_SENSOR; SCALED_IMU is
    # refused (FAILED, as PX4 answers for a message it does not stream: the stub has no IMU)
    assert seen["autopilot"]["rates_acknowledged"] == [30, 111, 132]
    assert seen["autopilot"]["rates_refused"] == [26]
    # what the machine let the pipeline do (a slow or shared host turns a frame over in
    # 60-80 ms, 2026-11-27): the service must publish at least half of that, up to the camera
    keep_up = min(rate, summary["pipeline_capacity_hz"])
    assert seen["scale"]["value"] > 0 and seen["output"]["rate_hz"] > 0.5 * keep_up
    rates = seen["scale"]["match_rate"]  # per sensor: 35-50 % of frames match on hills
    assert len(rates) == 4 and min(rates.values()) > 0.1, rates
    print(report, summary)
    assert "error" not in report, report
    assert report["received_rate_hz"] >= 0.5 * keep_up, (report, summary)
    # what the service sent reached the autopilot (a few may follow the autopilot's stop)
    assert report["received"] >= summary["published"] - 2 * rate
    # the time sync is as good as the round trip allows: a sample is off by at most half its
    # round trip, and from the start (the first samples' line) within one (0.16 ms on a slow
    # host, 2026-11-27; 4-6 ms before its skew's gains followed the samples' spacing)
    assert report["timesync_error_ms_p99"] <= 1.0 + 0.5 * report["timesync_rtt_ms_max"]
    assert report["timesync_error_ms_max"] <= 1.0 + report["timesync_rtt_ms_max"]
    assert report["timesync_rtt_ms_p50"] <= 20.0  # requests are answered from the loop
    assert report["ate_pct"] <= 1.5
    assert report["latency_ms_p50"] < 100.0  # stale_frame_ms; wall-clock, not doubled
    # every frame accounted for: rendered and sent or lost by the camera (as a camera loses
    # them when it is behind), received, then processed, skipped for a newer one or refused
    n_frames = int(SECONDS * cfg.camera.rate_hz)
    assert report["camera_frames_sent"] + report["camera_frames_dropped"] >= n_frames - 2
    # slow motion (`companion sitl run --time-scale`): the frames on the service's clock
    # 1 / (30 Hz x SCALE) apart, the sensors' readings per flight second unchanged (4 x 50 Hz)
    gaps_ms = np.diff(np.array(frame_us)) * 1e-3
    assert np.median(gaps_ms) == pytest.approx(1e3 / rate, rel=0.02)
    assert report["received_rate_hz"] <= 1.05 * rate
    assert summary["ranges_in"] >= 0.95 * 4 * 50 * SECONDS
    assert summary["frames_in"] >= report["camera_frames_sent"] - 1
    handled = summary["frames_processed"] + summary["frames_dropped"] + summary["frames_rejected"]
    assert summary["frames_in"] - 8 <= handled <= summary["frames_in"]  # <= 8 left queued
    # no VO re-initialisation unless the service went more than vo.max_gap_ms without a frame
    # (a stall of the whole machine): skipped frames after a slow keyframe used to lose
    # tracking in real time (3-4 frame jumps); the VO now predicts across them
    assert report["resets"] <= summary["vo_gaps"], (report["resets"], summary["vo_gaps"])
    assert summary["link"]["rx_bad"] == 0
    assert summary["pipeline_errors"] == 0
    assert (tmp_path / "autopilot" / "autopilot.png").exists()


@pytest.mark.slow
@pytest.mark.timeout(480)  # 34 s of flight in 68 s + prerendering + waiting for the machine
def test_dpose_corrects_what_the_autopilot_receives_over_the_pad(tmp_path) -> None:
    """d-Pose through the running service (config/pad.toml's 40 s flight, in slow motion, up
    to the end of its hover over the pad again): armed on the hover over the pad, the marks
    left there; after a 12 m square out of their view, over the pad again the position the
    autopilot decodes is within 2 cm (RMS) of the truth relative to the arming pose (the VO
    alone drifts 5-10 cm there). The landing after that hover (34.7-40 s) is not flown: nothing
    is asserted of it, and it was 12 s of the test's wall time with the machine alone."""
    pad = "config/pad.toml"
    arm_after_s = load_config(pad).dpose.arm_after_s  # in flight time
    cfg, opts = sitl_flight(
        tmp_path,
        40.0,  # the trajectory: the square ends at 27.5 s, the landing starts at 34.7 s
        config=pad,
        overrides=slow_motion_overrides(pad, SCALE),
        time_scale=SCALE,
        end_s=34.0,
    )

    async def both() -> tuple[dict, SimAutopilot, dict]:
        stub = SimAutopilot(cfg, opts)
        stub_task = asyncio.create_task(stub.run(tmp_path / "autopilot"))
        async with Service(cfg) as service:
            stub_task.add_done_callback(lambda _: service.stop())
            await service.run()
            s = service.pipeline.status()
            dpose = {"armed": s.dpose_armed, "used": s.dpose_used, "resets": s.dpose_resets}
        return await stub_task, stub, dpose

    report, stub, dpose = asyncio.run(both())
    assert "error" not in report, report
    assert dpose["armed"] and dpose["used"] >= 30, dpose
    rec = [r for r in stub.stats.received if r.kind == report["message"]]
    t = np.array([r.t_sim_s for r in rec])
    est = np.array([r.position for r in rec])
    gt = np.array([r.true_position for r in rec])
    k0 = int(np.searchsorted(t, arm_after_s))  # the arming window's start
    back = (t >= 29.0) & (t <= 33.0)  # hovering over the pad again (the square ends at 27.5 s)
    assert back.sum() >= 30, back.sum()
    err = np.linalg.norm((est[back] - est[k0]) - (gt[back] - gt[k0]), axis=1)
    assert float(np.sqrt(np.mean(err**2))) <= 0.02, err
    # a correction beyond dpose.reset_m arrives with a new reset_counter (EKF2 re-anchors):
    # the counter the autopilot decoded moved by the pipeline's d-Pose and VO resets
    resets = [r.reset_counter for r in rec]
    assert resets[-1] - resets[0] >= dpose["resets"], (resets[-1], dpose)
