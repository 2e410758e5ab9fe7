"""Frame intake (companion.service.frame_intake): the wait rule that picks the next frame."""

from __future__ import annotations

import numpy as np

from companion.types import CameraFrame


def test_frames_wait_for_a_slow_step_but_not_for_a_slow_board(tmp_path) -> None:
    """The pipeline takes the oldest frame <= frame_wait_ms (60) old, and young enough to
    be sent after the recent processing time: a keyframe that ran long costs latency, not
    a pose; older frames are skipped for newer ones (counted as dropped), so a board slower
    than the camera keeps a bounded latency."""
    from peers import service_config

    from companion.service.app import Service
    from companion.service.runtime import now_ns

    service = Service(service_config(tmp_path))
    image = np.zeros((4, 4, 3), np.uint8)

    def queue(*ages_ms: float) -> None:
        now_us = now_ns() // 1000
        for k, age in enumerate(ages_ms):
            service.intake.frames.append(CameraFrame(now_us - int(age * 1e3), k, image))

    def taken() -> list[int]:
        seqs = []
        while (frame := service.intake.next_frame()) is not None:
            seqs.append(frame.seq)
        return seqs

    queue(55.0, 22.0, 0.0)  # after a 60-ms keyframe: all three are still worth a pose
    assert taken() == [0, 1, 2] and service.stats.frames_dropped == 0
    queue(130.0, 97.0, 64.0, 31.0, 0.0)  # a stall: the ones too old to help are skipped
    assert taken() == [3, 4] and service.stats.frames_dropped == 3
    queue(500.0)  # the only frame is always taken (the publisher's stale rule decides)
    assert taken() == [0] and service.stats.frames_dropped == 3
    # a loaded machine: with 50 ms of processing a frame over 50 ms old would be stale
    # (stale_frame_ms 100) once processed: skipped before the work while a newer one waits
    service.stats.process_ms.extend([50.0] * 20)
    queue(55.0, 22.0, 0.0)
    assert taken() == [1, 2] and service.stats.frames_dropped == 4
    service.stats.process_ms.extend([90.0] * 20)  # the newest alone can still make it
    queue(55.0, 22.0, 0.0)
    assert taken() == [2] and service.stats.frames_dropped == 6
    queue(70.0)  # still: the only frame is always taken
    assert taken() == [0] and service.stats.frames_dropped == 6
