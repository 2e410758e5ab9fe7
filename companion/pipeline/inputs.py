"""The pipeline's buffered inputs: the autopilot's attitude and the accelerometer samples.

Both arrive in time order per stream (an out-of-order or non-finite sample is dropped) and
are looked up at a frame's capture time. Times are microseconds on the companion's clock.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from companion.geometry import so3
from companion.types import F64, AttitudeSample, CameraFrame, ImuSample, RangeSample

# what a pipeline takes between frames, and everything it takes
Sample = AttitudeSample | RangeSample | ImuSample
Event = CameraFrame | Sample

ATTITUDE_MAX_GAP_US = 100_000  # an attitude older than this is not used for a frame
# the longest gap between two attitude samples that a frame's attitude is interpolated over
# (an autopilot's slowest default stream, ArduPilot's 4 Hz, is; a stall of seconds is not)
ATTITUDE_MAX_SPAN_US = 500_000
ATTITUDE_BUFFER = 512  # attitude samples kept
IMU_BUFFER = 4096  # accelerometer samples kept (80 s at 50 Hz, 16 s at 250 Hz)


def _usable(kept: deque[AttitudeSample] | deque[ImuSample], time_us: int, values: F64) -> bool:
    """Whether a sample with these values may join ``kept``: finite, and newer than the last."""
    if not np.all(np.isfinite(values)):
        return False
    return not (kept and time_us <= kept[-1].time_us)


class AttitudeHistory:
    """The autopilot's attitude samples (R_world_body, NED <- FRD) of the last few seconds.

    The last look-up is remembered until the next sample arrives, so the attitude of one
    frame is resolved once however many stages ask for it."""

    def __init__(self) -> None:
        self.samples: deque[AttitudeSample] = deque(maxlen=ATTITUDE_BUFFER)
        self._last: tuple[int, F64 | None] | None = None  # (time_us, R_world_body) asked last

    def add(self, sample: AttitudeSample) -> bool:
        """Keep a sample; False (dropped) unless finite and newer than the last."""
        if not _usable(self.samples, sample.time_us, sample.quat_wxyz):
            return False
        self.samples.append(sample)
        self._last = None
        return True

    def at(self, time_us: int) -> F64 | None:
        """(3, 3) R_world_body at ``time_us`` by slerp between the bracketing samples when
        they are at most ATTITUDE_MAX_SPAN_US apart, else the nearest one within
        ATTITUDE_MAX_GAP_US; None when there is none close enough."""
        last = self._last
        if last is not None and last[0] == time_us:
            return last[1]
        R = self._lookup(time_us)
        self._last = (time_us, R)
        return R

    def _lookup(self, time_us: int) -> F64 | None:
        if not self.samples:
            return None
        # from the newest end: the times asked for are the last few frames' (a scan of the
        # whole buffer from its oldest end cost ~0.3 ms a call on a slow board)
        before = after = None
        for a in reversed(self.samples):
            if a.time_us <= time_us:
                before = a
                break
            after = a
        if before is not None and after is not None:
            span_us = after.time_us - before.time_us
            if 0 < span_us <= ATTITUDE_MAX_SPAN_US:
                alpha = (time_us - before.time_us) / span_us
                R0 = so3.quat_to_matrix(before.quat_wxyz)
                R1 = so3.quat_to_matrix(after.quat_wxyz)
                R: F64 = R0 @ so3.exp(alpha * so3.log(R0.T @ R1))
                return R
            # a gap in the stream (a stall): no slerp across it, the nearer if close enough
            if time_us - before.time_us <= after.time_us - time_us:
                after = None
            else:
                before = None
        near = before or after
        assert near is not None
        if abs(near.time_us - time_us) > ATTITUDE_MAX_GAP_US:
            return None
        return so3.quat_to_matrix(near.quat_wxyz)


class ImuHistory:
    """The accelerometer (and gyroscope, magnetometer) samples of the last seconds."""

    def __init__(self) -> None:
        self.samples: deque[ImuSample] = deque(maxlen=IMU_BUFFER)

    def __bool__(self) -> bool:
        return bool(self.samples)

    def add(self, sample: ImuSample) -> bool:
        """Keep a sample; False (dropped) unless finite and newer than the last."""
        if not _usable(self.samples, sample.time_us, sample.accel_frd_m_s2):
            return False
        self.samples.append(sample)
        return True

    def between(self, from_us: int, to_us: int, *, include_from: bool) -> list[ImuSample]:
        """The samples from ``from_us`` (itself included or not) to ``to_us`` (included), in
        time order; scanned from the newest end (the windows asked for are recent)."""
        out: list[ImuSample] = []
        for s in reversed(self.samples):
            if s.time_us < from_us or (s.time_us == from_us and not include_from):
                break
            if s.time_us <= to_us:
                out.append(s)
        out.reverse()
        return out
