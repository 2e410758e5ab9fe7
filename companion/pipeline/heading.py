"""``vo.heading_source = magnetometer``: the VO frame's heading from our own compass.

From a VO map's first tracking frame the IMU samples (SCALED_IMU's accelerometer, gyroscope
and raw field) are averaged while the body stands still (companion/attitude/heading.py); once
they span ``vo.mag_heading_min_s`` the frame's heading becomes the compass's body heading
minus the body's yaw in the VO frame (its mean over the window), and it is refined with every
frame until the body moves (the IMU, or the VO seeing it move MAG_STILL_MAX_MOVE_M or turn
MAG_STILL_MAX_TURN_RAD). Then it stays for the map's life (a later change would turn the
published trajectory about the map's origin), and no later map takes the compass's: the first
motion is the take-off, and in the air the accelerometer is no level and the motors disturb
the field (a map after a VO reset takes the autopilot's heading, which fused ours). On the
ground the position is at that origin, so the turn moves it by millimetres; the published yaw
steps by the compass's correction (< 2 deg on PX4 SIH), which EKF2 fuses as a yaw measurement.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from companion.attitude.heading import HeadingFix, MagHeading
from companion.geometry import so3
from companion.pipeline.inputs import ImuHistory
from companion.types import F64
from companion.vo.odometry import VisualOdometry
from companion.vo.options import VoOptions

# the compass window ends when the VO sees the body move this far or turn this much from
# where the window started
MAG_STILL_MAX_MOVE_M = 0.1
MAG_STILL_MAX_TURN_RAD = float(np.radians(1.0))


class CompassWindow(NamedTuple):
    """Where a VO map's compass window started."""

    vo_map: int  # the VO map it belongs to
    position_vo_m: F64  # (3,) the body's metric position in the VO frame then [m]
    yaw_body_vo_rad: float  # the body's yaw in the VO frame then [rad]


class CompassHeading:
    """The compass's heading for the VO frame (``fix`` the fix it took, ``ended`` once the
    body moved and the compass no longer refines it)."""

    def __init__(self, options: VoOptions) -> None:
        self.options = options
        self.mag: MagHeading | None = None
        self._window: CompassWindow | None = None
        self._turn = (0.0, 0)  # (sum of the turns since the window's start [rad], frames)
        self.fix: HeadingFix | None = None
        self.ended = False

    def step(
        self,
        time_us: int,
        position_vo_m: F64 | None,
        R_vo_body: F64 | None,
        vo: VisualOdometry,
        imu: ImuHistory,
    ) -> None:
        """One tracked frame: feed the IMU samples since the last one, end the window if the
        body moved, else set ``vo.yaw_vo_rad`` from the compass once its fix is long enough."""
        o = self.options
        if o.heading_source != "magnetometer" or self.ended:
            return
        p, R = position_vo_m, R_vo_body
        if p is None or R is None:
            return
        yaw_body_vo = so3.matrix_to_rpy(R)[2]
        w = self._window
        h = self.mag
        if h is None or w is None or w.vo_map != vo.resets:
            h = self.mag = MagHeading(float(np.radians(o.mag_declination_deg)))
            h.last_us = time_us  # the window starts at the map's first pose
            w = self._window = CompassWindow(vo.resets, np.array(p, dtype=np.float64), yaw_body_vo)
            self._turn = (0.0, 0)
        start = h.last_us if h.last_us is not None else time_us
        for sample in imu.between(start, time_us, include_from=False):
            h.add(sample)
        turn = math.remainder(yaw_body_vo - w.yaw_body_vo_rad, math.tau)  # wrapped to [-pi, pi]
        if (
            float(np.linalg.norm(p - w.position_vo_m)) > MAG_STILL_MAX_MOVE_M
            or abs(turn) > MAG_STILL_MAX_TURN_RAD
        ):
            h.moved = True
        if h.moved:
            self.ended = True
            return
        total, n = self._turn
        self._turn = (total + turn, n + 1)
        fix = h.fix()
        if fix is None or fix.span_us < o.mag_heading_min_s * 1e6:
            return
        mean_yaw_body_vo = w.yaw_body_vo_rad + self._turn[0] / self._turn[1]
        vo.yaw_vo_rad = math.remainder(fix.yaw_rad - mean_yaw_body_vo, math.tau)
        vo.yaw_vo_known = True
        self.fix = fix
