"""The pipeline worker (companion.service.worker): frames held for the autopilot's attitude."""

from __future__ import annotations

import numpy as np

from companion.types import CameraFrame


def test_the_vo_waits_for_the_autopilots_attitude_then_goes_without(tmp_path) -> None:
    """ArduPilot streams ATTITUDE on a companion port only once asked: the frames before it
    are held from the VO (whose frame takes the autopilot's heading at its start), up to
    service.attitude_wait_s after the first one; then the VO starts without (logged)."""
    from peers import service_config

    from companion.service.app import Service
    from companion.types import AttitudeSample

    service = Service(service_config(tmp_path, attitude_wait_s=2.0))
    image = np.zeros((4, 4, 3), np.uint8)
    t0 = 5_000_000_000
    frames = [CameraFrame(t0 + k * 100_000, k, image) for k in range(40)]  # 10 Hz, 4 s
    assert service.worker.wait_for_attitude(frames[0]) is False  # no autopilot heard: nothing held
    service.stats.autopilot_heartbeat_ns = 1  # an autopilot's HEARTBEAT came, no ATTITUDE yet
    held = [service.worker.wait_for_attitude(f) for f in frames]
    # no attitude: 2 s held (frames 0-20, the 20th exactly at the limit), then none
    assert held == [True] * 21 + [False] * 19
    assert service.stats.waited_for_attitude == 21

    late = Service(service_config(tmp_path, attitude_wait_s=2.0))
    late.stats.autopilot_heartbeat_ns = 1
    assert late.worker.wait_for_attitude(frames[0]) is True
    q = np.array([1.0, 0.0, 0.0, 0.0])
    late.pipeline.feed_attitude(AttitudeSample(frames[1].time_us - 5_000, q, np.zeros(3)))
    assert late.worker.wait_for_attitude(frames[1]) is False  # at hand: the VO may start
    # an attitude far from the frame's time is not at hand (the VO would take no heading)
    assert late.worker.wait_for_attitude(frames[15]) is True

    off = Service(service_config(tmp_path, attitude_wait_s=0.0))
    off.stats.autopilot_heartbeat_ns = 1
    assert off.worker.wait_for_attitude(frames[0]) is False
