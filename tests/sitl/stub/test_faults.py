"""Fault injection against the running service and the SITL autopilot, in real time.

One signed flight (MAVLink 2 signing on both ends, as a hardened vehicle would fly) carries a
schedule of faults, each in its own window, while the MQTT broker is down for 45 s:

- camera: 1 s frozen, 1 s black, 1 s saturated, 2 s unplugged. Nothing from those frames may
  reach the autopilot, publishing stops within 100 ms of the last good frame, and resumes
  with a new reset_counter;
- autopilot link: 10 s of silence, a new UDP port, a reboot (its clock restarts at zero). The
  service asks for its message rates again and the time sync is back within 1 ms + half the
  link's p99 round trip;
- MQTT broker down from 5 s to 50 s: the output rate away from the faults stays >= half the
  camera rate with the broker down and after it is back (28 Hz on a quiet machine: a
  benchmark, docs/BENCHMARKS.md), and the retained status is fresh again.

Thresholds hold at any load (issue 16): the time sync is judged against the link's own round
trip, and the new port is taken once the old one has been silent for PEER_SILENCE_S (a
spoofer's address is never taken while the autopilot talks).
"""

from __future__ import annotations

import asyncio
import json
import os
import time

import aiomqtt
import numpy as np
import pytest
from peers import MOSQUITTO, Broker, sitl_flight

from companion.drivers.mavlink import PEER_SILENCE_S
from companion.service.app import Service
from companion.sitl.stub.autopilot import SimAutopilot
from companion.sitl.stub.faults import Fault

SECONDS = 60.0
CAMERA_FAULTS = (
    Fault("camera_freeze", 8.0, 1.0),
    Fault("camera_black", 11.0, 1.0),
    Fault("camera_saturated", 14.0, 1.0),
    Fault("camera_unplug", 17.0, 2.0),
)
LINK_FAULTS = (
    Fault("link_silence", 21.0, 10.0),
    Fault("link_port_change", 35.0),
    Fault("autopilot_reboot", 39.0, 2.0),
)
BROKER_DOWN_S = (5.0, 50.0)
CLEAN_WINDOWS_S = ((5.0, 7.5), (46.0, 50.0), (52.0, 59.0))  # no fault; broker down, down, up


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_the_service_survives_camera_link_and_broker_faults(tmp_path) -> None:
    if not os.path.exists(MOSQUITTO):
        pytest.fail("mosquitto is not installed (make test installs it with apt-get)")
    broker = Broker(tmp_path)
    broker.start()
    key = bytes(range(32))
    key_file = tmp_path / "mavlink.key"
    key_file.write_bytes(key)
    key_file.chmod(0o600)
    cfg, opts = sitl_flight(
        tmp_path,
        SECONDS,
        service={
            "signing": {"key_file": str(key_file)},
            "mqtt": {"enabled": True, "port": broker.port, "keepalive_s": 2},
        },
        small=True,  # the 320x240 camera: the faults are the service's, not the image's
        faults=CAMERA_FAULTS + LINK_FAULTS,
        signing_key=key,
    )

    async def fly() -> tuple[SimAutopilot, dict, dict, dict]:
        stub = SimAutopilot(cfg, opts)
        stub_task = asyncio.create_task(stub.run(tmp_path / "autopilot"))
        async with Service(cfg) as service:
            stub_task.add_done_callback(lambda _: service.stop())

            async def broker_outage() -> dict:
                def t_flight() -> float:
                    return stub.t_sim_of_mono(time.monotonic_ns())

                while t_flight() < BROKER_DOWN_S[0]:
                    await asyncio.sleep(0.05)
                broker.stop()
                published_down = service.mqtt.stats.published if service.mqtt else 0
                while t_flight() < BROKER_DOWN_S[1]:
                    await asyncio.sleep(0.05)
                broker.start()
                back, uptime_back = time.monotonic(), service.status()["uptime_s"]
                async with aiomqtt.Client("127.0.0.1", broker.port) as sub:
                    await sub.subscribe("companion/1/status")
                    async with asyncio.timeout(20):  # reconnection backoff <= 10 s x 1.5
                        async for msg in sub.messages:
                            status = json.loads(msg.payload)
                            if status.get("uptime_s", 0.0) >= uptime_back:  # a fresh one
                                break
                return {
                    "published_down": published_down,
                    "status": status,
                    "resumed_after_s": time.monotonic() - back,
                }

            async def ranges_after_reboot() -> int:
                """DISTANCE_SENSOR readings taken in from 4 s to 14 s after the reboot."""
                t_reboot_end = LINK_FAULTS[2].end_s
                while stub.t_sim_of_mono(time.monotonic_ns()) < t_reboot_end + 4.0:
                    await asyncio.sleep(0.05)
                n0 = service.stats.ranges_in
                while stub.t_sim_of_mono(time.monotonic_ns()) < t_reboot_end + 14.0:
                    await asyncio.sleep(0.05)
                return service.stats.ranges_in - n0

            outage = asyncio.create_task(broker_outage())
            ranges_task = asyncio.create_task(ranges_after_reboot())
            await service.run()
            mqtt_seen = await outage
            ranges_back = await ranges_task
            summary = service.summary()
            status = service.status()
            mqtt_stats = vars(service.mqtt.stats) if service.mqtt else {}
        report = await stub_task
        extra = {"mqtt": mqtt_seen, "status": status, "stats": mqtt_stats, "ranges": ranges_back}
        return stub, report, summary, extra

    try:
        stub, report, summary, extra = asyncio.run(fly())
    finally:
        broker.stop()
    print(json.dumps(report["faults"], indent=1), summary, extra["stats"], extra["mqtt"])
    assert "error" not in report, report
    faults = {f["kind"]: f for f in report["faults"]}
    for f in CAMERA_FAULTS:
        m = faults[f.kind]
        assert m["poses_from_fault_time"] == 0, m  # nothing from a bad frame
        assert m["stop_after_last_good_frame_ms"] <= 100.0, m
        assert m["resume_s"] is not None and m["resume_s"] <= 5.0, m
        assert m["reset_counter_after"] > m["reset_counter_before"], m
    silence, port, reboot = (faults[f.kind] for f in LINK_FAULTS)
    assert silence["rate_requests_after"] >= 1 and reboot["rate_requests_after"] >= 1
    # from 2 s after the fault the time sync is as good as the round trip allows: a sample is
    # off by at most half its round trip, and the filter averages them (0.12-0.19 ms on a
    # loaded slow host, 2026-11-27; its skew, swinging by +-7000 ppm before, made it 2-13 ms)
    sync_bound_ms = 1.0 + 0.5 * report["timesync_rtt_ms_p99"]
    for m in (silence, port, reboot):
        assert m["resume_s"] is not None and m["resume_s"] <= 5.0, m
        assert m["sync_error_ms_after"] is not None, m
        assert m["sync_error_ms_after"] <= sync_bound_ms, (m, sync_bound_ms)
    # the new port is answered once the old one fell silent, on the autopilot's next heartbeat
    assert port["resume_s"] <= PEER_SILENCE_S + 1.5
    assert report["reboots"] == 1
    # 4 sensors at 50 Hz: the readings are taken in again once the clocks agree
    assert extra["ranges"] >= 0.8 * 4 * 50 * 10, extra["ranges"]
    # the output rate away from the faults, with the broker down and after it is back: at
    # least half of what the machine let the pipeline do, up to the camera's rate (a slow host,
    # 2026-11-27: 14.8 poses/s in the first window)
    keep_up = min(cfg.camera.rate_hz, summary["pipeline_capacity_hz"])
    rec = [r for r in stub.stats.received if r.kind == report["message"]]
    t_pose = np.array([r.t_sim_s for r in rec])
    for lo, hi in CLEAN_WINDOWS_S:
        n = int(((t_pose >= lo) & (t_pose < hi)).sum())
        assert n / (hi - lo) >= 0.5 * keep_up, (lo, hi, n, keep_up)
    # telemetry resumed: a fresh retained status after the broker came back
    assert extra["mqtt"]["resumed_after_s"] <= 20.0
    assert extra["stats"]["published"] > extra["mqtt"]["published_down"]
    # signed both ways, nothing refused, no handler error, no pipeline error
    assert report["signing"]["good_signatures"] > 1000 and report["signing"]["refused"] == 0
    assert summary["signing"]["good_signatures"] > 1000 and summary["signing"]["refused"] == 0
    assert summary["link"]["handler_errors"] == 0 and summary["pipeline_errors"] == 0
    rejected = extra["status"]["camera"]["rejected"]
    assert rejected["frozen"] >= 25 and rejected["dark"] >= 25 and rejected["saturated"] >= 25
    warnings = " | ".join(summary["warnings"])
    assert "frozen" in warnings and "heartbeat back" in warnings
