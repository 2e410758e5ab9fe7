"""Laser points and range samples aligned to frame times.

A distance sensor's beam leaves its origin along +z of its frame, so the laser point of a
reading d [m] is P_rf = (0, 0, d); in the camera frame P_cam = T_cam_body @ T_body_rf @ P_rf
(docs/methods.md, MSC). Ranges arrive at their own rates; a frame at time t uses the
linear interpolation of the two samples around t (refused when they are further apart than
max_gap_us), or the nearest sample when it is at most max_age_us away (stale otherwise).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from companion.geometry import se3
from companion.types import F64, RangeSample, RangeSensorSpec


def laser_point_cam(spec: RangeSensorSpec, T_cam_body: F64, range_m: float) -> F64:
    """The laser point (3,) [m] of a reading in the camera frame."""
    p_body = se3.transform(spec.T_body_rf, np.array([0.0, 0.0, range_m]))
    return se3.transform(T_cam_body, p_body)


class RangeHistory:
    """Recent valid readings per sensor, for time-aligned lookups."""

    def __init__(self, maxlen: int = 256) -> None:
        self._buf: dict[int, deque[tuple[int, float]]] = {}
        self._maxlen = maxlen
        self.rejected = 0
        # per sensor: the last time it read below its minimum (on the ground, too close)
        self.too_close_us: dict[int, int] = {}

    def add(self, sample: RangeSample) -> bool:
        """Keep a reading if valid (finite, inside its range, not flagged invalid) and newer
        than the sensor's last one; returns whether it was kept."""
        if not sample.is_valid:
            self.rejected += 1
            d = sample.distance_m
            # below the minimum: reported under it, or at it and flagged invalid (a TFmini
            # in its blind zone, PX4's and our simulator's DISTANCE_SENSOR)
            if np.isfinite(d) and 0.0 <= d <= sample.min_m:
                self.too_close_us[sample.sensor_id] = sample.time_us
            return False
        buf = self._buf.setdefault(sample.sensor_id, deque(maxlen=self._maxlen))
        if buf and sample.time_us <= buf[-1][0]:
            self.rejected += 1
            return False
        buf.append((sample.time_us, float(sample.distance_m)))
        return True

    def window(self, sensor_id: int, t0_us: int, t1_us: int) -> F64:
        """(K,) the sensor's valid readings [m] stamped in [t0_us, t1_us]."""
        out: list[float] = []
        for t, d in reversed(self._buf.get(sensor_id, ())):  # newest first (times increase)
            if t < t0_us:
                break
            if t <= t1_us:
                out.append(d)
        out.reverse()
        return np.array(out, dtype=np.float64)

    def sensors(self) -> list[int]:
        """Ids of the sensors seen so far."""
        return sorted(self._buf)

    def at(self, sensor_id: int, time_us: int, max_gap_us: int, max_age_us: int) -> float | None:
        """Distance [m] of ``sensor_id`` at ``time_us``, or None (no data, stale, or gap)."""
        buf = self._buf.get(sensor_id)
        if not buf:
            return None
        before = None
        after = None
        for t, d in reversed(buf):
            if t <= time_us:
                before = (t, d)
                break
            after = (t, d)
        if before is not None and after is not None:
            gap = after[0] - before[0]
            if gap <= max_gap_us:
                a = (time_us - before[0]) / gap
                return before[1] + a * (after[1] - before[1])
        near = [p for p in (before, after) if p is not None]
        if not near:
            return None
        t, d = min(near, key=lambda p: abs(p[0] - time_us))
        return d if abs(t - time_us) <= max_age_us else None
