"""GPS in, GPS out on the SITL stub: a short flight with [gps] align on through a GPS-denied
zone and back (issue 43).

The stub's GPS (sitl/stub/gps.py) reports the truth moved by GPS_OFFSET_M (its EKF origin is
not where our VO starts: the alignment has that, and our VO's own start, to find) with 0.3 m
of noise per axis correlated over 1 s; its heading (ATTITUDE) is the truth's, so our VO frame,
whose heading is the autopilot's at its start, differs from the GPS frame by a translation and
the VO's heading error. The GPS has no fix from LOSS_S for LOSS_LEN_S. The thresholds of the
GPS frame are shortened so that the flight stays short: 1 s of good fixes to trust a return,
4 s of pairs to fit, a 10 s window.

Asserted: the status's frame goes aligned -> held -> slewing -> aligned and STATUSTEXT says
so, and so does the status a fleet reads from the MQTT broker (Mosquitto); the autopilot is
told (EKF2_GPS_CTRL 0 at the loss, back to 7 after the slew, both echoed); between two poses
the autopilot received (same reset counter) the output never moves more than 0.1 m/s x dt plus
the vehicle's own motion plus VO_NOISE_M; while held, it stays within 0.5 m of the truth in
the GPS frame horizontally. The height is not aligned ([gps]
align_height off, the default: z stays ours, the autopilot's height reference), so the
alignment's z is 0 and the GPS frame's 1.5 m of height offset is not in the output.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import time

import aiomqtt
import numpy as np
import pytest
from peers import MOSQUITTO, Broker, sitl_flight

from companion.service.app import Service
from companion.sitl.stub.autopilot import SimAutopilot
from companion.sitl.stub.faults import Fault

SECONDS = 40.0
LOSS_S, LOSS_LEN_S = 13.0, 9.0
GPS_OFFSET_M = (40.0, -25.0, 1.5)
VO_NOISE_M = 0.05  # two poses' VO errors apart (320x240 camera)
GPS = {
    "align": True,
    "handover": "px4",
    "good_after_s": 1.0,
    "min_window_s": 4.0,
    "window_s": 10.0,
}


def runs(states: list[str]) -> list[str]:
    return [s for i, s in enumerate(states) if i == 0 or states[i - 1] != s]


def is_subsequence(wanted: list[str], seen: list[str]) -> bool:
    it = iter(seen)
    return all(any(s == w for s in it) for w in wanted)


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_gps_denied_zone_is_flown_through_without_a_jump(tmp_path) -> None:
    if not os.path.exists(MOSQUITTO):
        pytest.fail("mosquitto is not installed (make test installs it with apt-get)")
    broker = Broker(tmp_path)
    broker.start()
    cfg, opts = sitl_flight(
        tmp_path,
        SECONDS,
        small=True,
        service={"mqtt": {"enabled": True, "port": broker.port, "status_hz": 2.0}},
        overrides={"gps": GPS},
        gps=True,
        gps_offset_ned_m=GPS_OFFSET_M,
        faults=(Fault("gps_loss", LOSS_S, LOSS_LEN_S),),
    )

    mqtt_states: list[str] = []  # the frame's state in each status the broker passed on

    async def from_the_broker() -> None:
        async with aiomqtt.Client("127.0.0.1", broker.port) as sub:
            await sub.subscribe(f"companion/{cfg.service.system_id}/status")
            async for msg in sub.messages:
                frame = json.loads(msg.payload).get("frame")
                if isinstance(frame, dict):
                    mqtt_states.append(str(frame.get("state")))

    async def fly() -> tuple[SimAutopilot, dict, list[tuple[float, str]], dict]:
        stub = SimAutopilot(cfg, opts)
        stub_task = asyncio.create_task(stub.run(tmp_path / "autopilot"))
        timeline: list[tuple[float, str]] = []
        async with Service(cfg) as service:
            stub_task.add_done_callback(lambda _: service.stop())
            subscriber = asyncio.create_task(from_the_broker())

            async def watch() -> None:
                while not service.stopped:
                    frame = service.status()["frame"]
                    t_now = stub.t_sim_of_mono(time.monotonic_ns())
                    timeline.append((t_now, frame["state"]))
                    if len(timeline) % 10 == 0 and t_now > -1.0:  # its course, each second
                        print(
                            f"[{t_now:5.1f} s] {frame['state']} to target "
                            f"{frame['to_target_m']} agree {frame['agreement_m']}",
                            flush=True,
                        )
                    await asyncio.sleep(0.1)

            watcher = asyncio.create_task(watch())
            await service.run()
            await watcher
            status = service.status()
            subscriber.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await subscriber
        report = await stub_task
        return stub, report, timeline, status

    try:
        stub, report, timeline, status = asyncio.run(fly())
    finally:
        broker.stop()
    frame = status["frame"]
    print(runs([s for _, s in timeline]), frame, report.get("position_error_m_rms"))
    assert "error" not in report, report
    states = runs([s for _, s in timeline])
    assert is_subsequence(["aligned", "held", "slewing", "aligned"], states), states
    assert states[-1] == "aligned", states
    assert frame["gps"]["good"] and frame["gps"]["dropped"] == 0
    # told at the loss and after the slew, each echoed by the stub's parameter server
    assert [(a["what"], a["result"]) for a in frame["handover"]] == [
        ("EKF2_GPS_CTRL 0", "acknowledged"),
        ("EKF2_GPS_CTRL 7", "acknowledged"),
    ]
    texts = " | ".join(t for _, _, t, _, _ in stub.stats.statustexts)
    for said in ("frame aligned to GPS, agree", "GPS lost, frame held", "GPS back, slewing"):
        assert said in texts, texts
    # a fleet sees it too: the status over MQTT carries the frame section through the denial
    assert is_subsequence(["aligned", "held", "aligned"], runs(mqtt_states)), runs(mqtt_states)
    # the output, as the autopilot received it, in flight-time order
    rec = sorted(
        (r for r in stub.stats.received if r.kind == report["message"]), key=lambda r: r.t_sim_s
    )
    t = np.array([r.t_sim_s for r in rec])
    out = np.array([r.position for r in rec])
    truth = np.array([r.true_position for r in rec]) + np.array(GPS_OFFSET_M)
    resets = np.array([r.reset_counter for r in rec])
    same = np.diff(resets) == 0
    step = np.linalg.norm(np.diff(out, axis=0), axis=1)
    moved = np.linalg.norm(np.diff(truth, axis=0), axis=1)
    bound = 0.1 * np.diff(t) + moved + VO_NOISE_M
    print("largest step beyond the vehicle's motion [m]:", float(np.max((step - moved)[same])))
    assert np.all(step[same] <= bound[same]), float(np.max((step - bound)[same]))
    assert len(np.unique(resets)) <= 3, np.unique(resets)  # the first alignment's jump, a VO reset
    # while held (from the first second of the loss to the return's slew): near the truth
    held_t = [ts for ts, s in timeline if s == "held"]
    held = (t >= min(held_t)) & (t <= max(held_t))
    err = np.linalg.norm(out[held, :2] - truth[held, :2], axis=1)
    print(
        f"held: {held.sum()} poses, horizontal error max {err.max():.3f}, mean {err.mean():.3f} m"
    )
    assert held.sum() > 100 and err.max() <= 0.5, err.max()
    assert frame["translation_ned_m"][2] == 0.0
