"""The pipeline worker (companion.service.worker): the pipeline's wait rule on the service's
frames, and what the service reports of it."""

from __future__ import annotations

import numpy as np

from companion.types import CameraFrame, VoState


def test_the_worker_holds_frames_by_the_pipelines_rule_and_reports_them(tmp_path) -> None:
    """Once an autopilot's HEARTBEAT came but no ATTITUDE, the worker holds each frame from
    the VO (Pipeline.hold_for_attitude, tested itself in test_pipeline.py) and publishes
    nothing; the exit report and the status count the held frames from the pipeline's own
    snapshot. Without a HEARTBEAT (a replay, a bench test) the first frame goes on."""
    from peers import service_config

    from companion.service.app import Service

    service = Service(service_config(tmp_path, attitude_wait_s=2.0))
    image = np.zeros((4, 4, 3), np.uint8)
    t0 = 5_000_000_000
    frames = [CameraFrame(t0 + k * 100_000, k, image) for k in range(21)]  # 10 Hz, 2 s
    service.stats.autopilot_heartbeat_ns = 1  # an autopilot's HEARTBEAT came, no ATTITUDE yet
    poses = [service.worker.process(f, [], [], []) for f in frames]
    assert poses == [None] * 21
    assert service.worker.status.waited_for_attitude == 21
    assert service.summary()["waited_for_attitude"] == 21
    assert service.pipeline.vo.state == VoState.INITIALIZING
    assert service.pipeline.vo_output is None  # no held frame reached the VO

    replay = Service(service_config(tmp_path, attitude_wait_s=2.0))
    replay.worker.process(frames[0], [], [], [])  # no HEARTBEAT: not held, fed to the VO
    assert replay.worker.status.waited_for_attitude == 0
