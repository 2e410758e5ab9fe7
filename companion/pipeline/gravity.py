"""Gravity in the VO frame from the accelerometer and our own motion: the tilt correction.

Each tracked frame leaves a :class:`MotionSample`; over the last ``vo.imu_gravity_window_s``
of one VO map, the accelerometer samples less the acceleration of our metric track give
gravity in the VO frame (companion/attitude/gravity.py), and the autopilot's mean tilt error
against it is the correction the VO takes for its keyframes.
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple

import numpy as np

from companion.attitude.gravity import (
    AttitudeCorrection,
    GravityEstimate,
    attitude_correction,
    gravity_from_motion,
)
from companion.pipeline.inputs import ImuHistory
from companion.types import F64

MOTION_BUFFER = 1024  # motion samples of the last frames kept
# the tilt correction of a 4 s window changes slowly: recomputed at most this often (~1 ms
# of Python per computation on the 2-core machine, docs/BENCHMARKS.md)
GRAVITY_REFRESH_US = 250_000


class Segment(NamedTuple):
    """Which stretch of track a frame belongs to: positions of two segments are never
    differenced."""

    vo_map: int  # the VO's map (its resets so far)
    reset_counter: int  # the published trajectory's reset counter (a jump makes a new one)


class MotionSample(NamedTuple):
    """The body's motion at one tracked frame."""

    time_us: int
    segment: Segment
    R_vo_body: F64  # (3, 3) body orientation in the VO frame
    position_vo_m: F64  # (3,) metric body position in the VO frame's axes [m]
    R_world_body: F64 | None  # (3, 3) the autopilot's attitude at the frame, if any


class MotionGravity:
    """The accelerometer samples and our motion, and the tilt correction they give.

    ``gravity`` the last window's gravity, ``correction`` the last correction, ``frames``
    how many frames had one."""

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s  # vo.imu_gravity_window_s (0: off)
        self.imu = ImuHistory()
        self.motion: deque[MotionSample] = deque(maxlen=MOTION_BUFFER)
        self.gravity: GravityEstimate | None = None
        self.correction: AttitudeCorrection | None = None
        self.frames = 0
        self._at: tuple[int, int] | None = None  # (time, VO map) of the last computation

    def remember(self, sample: MotionSample) -> None:
        """Keep a tracked frame's motion (nothing when the correction is off)."""
        if self.window_s > 0:
            self.motion.append(sample)

    def at_frame(self, time_us: int, tracking: bool, vo_map: int) -> AttitudeCorrection | None:
        """The correction for a frame at ``time_us``: recomputed every GRAVITY_REFRESH_US of
        one VO map (the last one kept in between); counted in ``frames`` when there is one."""
        last = self._at
        fresh = (
            last is not None and last[1] == vo_map and 0 <= time_us - last[0] < GRAVITY_REFRESH_US
        )
        if not fresh:
            self.correction = self._compute(time_us, tracking, vo_map)
            self._at = (time_us, vo_map)
        self.frames += self.correction is not None
        return self.correction

    def _compute(self, time_us: int, tracking: bool, vo_map: int) -> AttitudeCorrection | None:
        """The correction of the autopilot's gravity over the last window: gravity in the
        current VO map's frame, then the autopilot's mean tilt error against it in the
        window; None without accelerometer samples or attitudes, before the window is
        covered, or off (window 0). The window's gravity stays in ``gravity``."""
        window_s = self.window_s
        if window_s <= 0 or not self.imu or not self.motion:
            return None
        if not tracking:
            return None
        seg = self.motion[-1].segment
        if seg.vo_map != vo_map:
            return None
        t_from = self.motion[-1].time_us - int((window_s + 0.5) * 1e6)
        rows: list[MotionSample] = []
        for m in reversed(self.motion):
            if m.segment != seg or m.time_us < t_from:
                break
            rows.append(m)
        if len(rows) < 3:
            return None
        rows.reverse()
        t_pose = np.array([r.time_us for r in rows], dtype=np.int64)
        imu = self.imu.between(int(t_pose[0]), time_us, include_from=True)
        if not imu:
            return None
        self.gravity = est = gravity_from_motion(
            np.array([s.time_us for s in imu], dtype=np.int64),
            np.array([s.accel_frd_m_s2 for s in imu], dtype=np.float64),
            t_pose,
            np.stack([r.R_vo_body for r in rows]),
            np.stack([r.position_vo_m for r in rows]),
            window_s,
        )
        if est is None:
            return None
        # (our rotation, the autopilot's attitude) of the window's frames that had one
        pairs = [
            (r.R_vo_body, r.R_world_body)
            for r in rows
            if est.t0_us <= r.time_us <= est.t1_us and r.R_world_body is not None
        ]
        if len(pairs) < 3:
            return None
        R_vo_body, R_world_body = (np.stack(x) for x in zip(*pairs, strict=True))
        return attitude_correction(est.down_vo, est.sigma_rad, R_vo_body, R_world_body)
