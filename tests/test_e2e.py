"""End to end, in real time over loopback: the SITL autopilot (its own process for the camera)
and the service, on the default scenario (hills, lawnmower, 60 s).

Thresholds are the issue's: >= 29 Hz received for a 30 Hz camera once tracking; time-sync
conversion error <= 1 ms; metric ATE in the autopilot's frame and clock <= 1.5 % of the path;
TIMESYNC round trip p99 <= 5 ms while the pipeline runs. Latency figures are benchmarks
(docs/BENCHMARKS.md), so here they only have to be sane (p50 < 100 ms).
"""

from __future__ import annotations

import asyncio
import os

import numpy as np
import pytest
from peers import sitl_flight

from companion.geometry import so3
from companion.service.app import Service
from companion.service.status import read_status
from sitl.autopilot import SimAutopilot

SECONDS = float(os.environ.get("COMPANION_E2E_SECONDS", "60"))


@pytest.mark.slow
@pytest.mark.timeout(2 * SECONDS + 120)
def test_service_and_sitl_autopilot_end_to_end(tmp_path) -> None:
    cfg, opts = sitl_flight(tmp_path, SECONDS)

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
        return report, service.summary()

    seen: dict = {}
    report, summary = asyncio.run(both())
    assert seen["vo"]["state"] == "TRACKING"
    assert 25.0 <= seen["camera"]["fps"] <= 35.0
    assert seen["autopilot"]["timesync_converged"] and seen["autopilot"]["system_id"] == 1
    assert sorted(seen["autopilot"]["rates_acknowledged"]) == [30, 132]
    assert seen["scale"]["value"] > 0 and seen["output"]["rate_hz"] > 25.0
    rates = seen["scale"]["match_rate"]  # per sensor: 35-50 % of frames match on hills
    assert len(rates) == 4 and min(rates.values()) > 0.1, rates
    print(report, summary)
    assert "error" not in report, report
    assert report["received_rate_hz"] >= 29.0
    assert report["timesync_error_ms_max"] <= 1.0
    assert report["ate_pct"] <= 1.5
    assert report["timesync_rtt_ms_p99"] <= 5.0
    assert report["latency_ms_p50"] < 100.0
    assert summary["frames_in"] >= 0.97 * SECONDS * cfg.camera.rate_hz
    # no VO re-initialisation unless the service went more than vo.max_gap_ms without a frame
    # (a stall of the whole machine): skipped frames after a slow keyframe used to lose
    # tracking in real time (3-4 frame jumps); the VO now predicts across them
    assert report["resets"] <= summary["vo_gaps"], (report["resets"], summary["vo_gaps"])
    assert summary["link"]["rx_bad"] == 0
    assert summary["pipeline_errors"] == 0
    assert (tmp_path / "autopilot" / "autopilot.png").exists()
