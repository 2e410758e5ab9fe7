"""The published pose: the metric VO pose turned into NED, anchored, with velocity and noise.

Frames: the VO frame is turned about the vertical by the map's heading ``yaw_vo_rad`` onto
NED; the body is FRD. Positions are metres, times microseconds.
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple

import numpy as np

from companion.attitude.estimator import TiltStep
from companion.attitude.fusion import corrected_rotation
from companion.geometry import so3
from companion.types import F64, PoseEstimate, ScaleEstimate

VELOCITY_WINDOW_US = 150_000  # velocity = position difference over this long [us]
POSITION_SIGMA_FLOOR_M = 0.02  # added to the scale-derived position sigma [m]
SAMPLE_NOISE_ARM_M = 1.0  # one sample's position sigma: the scale's relative sigma times this [m]
VO_TILT_SIGMA_RAD = float(np.radians(0.5))  # roll/pitch sigma without the range fusion
VO_YAW_SIGMA_RAD = float(np.radians(2.0))  # yaw sigma of the VO (no absolute heading)


class Anchor(NamedTuple):
    """Where a reset_counter's published positions start."""

    reset_counter: int
    offset_ned_m: F64  # (3,) added to the rotated metric position [m]


class RecentPosition(NamedTuple):
    """A published position, kept for the velocity."""

    time_us: int
    reset_counter: int
    position_ned_m: F64  # (3,) [m]


class PoseOutput:
    """Shapes the published pose; keeps the anchor and the recent positions it needs."""

    def __init__(self) -> None:
        # the published position's anchor for the current reset_counter, so that a new map
        # continues from the last published position whatever its heading (see anchored)
        self._anchor: Anchor | None = None
        self._last_position_ned_m: F64 | None = None
        self._recent: deque[RecentPosition] = deque(maxlen=16)

    def pose(
        self,
        time_us: int,
        est: ScaleEstimate,
        position_vo_m: F64,
        R_vo_body: F64,
        yaw_vo_rad: float,
        reset_counter: int,
        tilt: TiltStep | None,
        tilt_error: F64 | None,
    ) -> PoseEstimate:
        """The pose to publish from the scale ``est``, the metric body position (3,) and
        orientation (3, 3) in the VO frame, the map's heading [rad] and the trajectory's
        reset counter; ``tilt`` the frame's fused roll/pitch and ``tilt_error`` the fusion's
        correction of the VO rotation (None: roll/pitch off)."""
        R_world_vo = so3.rot_z(yaw_vo_rad)
        position = self.anchored(R_world_vo @ position_vo_m, reset_counter)
        velocity = self.velocity(time_us, reset_counter, position)
        # covariance over (x, y, z, roll, pitch, yaw), for an autopilot's filter that takes
        # it as one sample's white measurement noise (EKF2: R = max(ours, EKF2_EVP_NOISE^2)).
        # Position: a 2 cm floor plus the scale's relative sigma over one metre (the part of
        # our error that changes from sample to sample: a scale update moves the local map by
        # that much per metre). Not the drift since the map's origin (that sigma times the
        # distance travelled, until 2026-11-28): drift is correlated over minutes, no filter
        # averages it away, and as noise it only weighed our later samples less than the
        # earlier ones (docs/decisions.md, "What EKF2 adds to our height"). Roll/pitch from
        # the fused tilt (else a VO default); yaw from the VO default
        rel = est.sigma / est.scale if est.scale > 0 else 1.0
        cov = np.zeros((6, 6))
        sigma_p = rel * SAMPLE_NOISE_ARM_M + POSITION_SIGMA_FLOOR_M
        cov[:3, :3] = np.eye(3) * sigma_p**2
        cov[3:5, 3:5] = np.eye(2) * VO_TILT_SIGMA_RAD**2
        cov[5, 5] = VO_YAW_SIGMA_RAD**2
        fused = tilt.fused if tilt is not None else None
        if fused is not None and tilt_error is not None:
            R_vo_body = corrected_rotation(tilt_error, R_vo_body)
            cov[3:5, 3:5] = fused.cov_rad2
        quality = int(np.clip(100.0 * (1.0 - 10.0 * rel), 0, 100)) if np.isfinite(rel) else 0
        return PoseEstimate(
            time_us,
            position,
            so3.matrix_to_quat(R_world_vo @ R_vo_body),
            velocity,
            cov,
            reset_counter,
            quality,
        )

    def anchored(self, position_ned_m: F64, reset_counter: int) -> F64:
        """(3,) [m] the published NED position: the metric position turned by the map's
        heading plus the anchor of its reset_counter. A new map (a new reset_counter) is
        anchored at the last published position: the metric trajectory continues from there
        in its own axes (MetricTrajectory), but a map that starts on another heading than the
        last one would otherwise turn the whole track about the first map's origin and jump
        by up to twice the distance flown."""
        a = self._anchor
        if a is None or a.reset_counter != reset_counter:
            last = self._last_position_ned_m
            offset = np.zeros(3) if last is None else last - position_ned_m
            self._anchor = a = Anchor(reset_counter, offset)
        anchored: F64 = position_ned_m + a.offset_ned_m
        self._last_position_ned_m = anchored
        return anchored

    def velocity(self, time_us: int, reset_counter: int, position: F64) -> F64:
        """NED velocity [m/s] as the difference over the last VELOCITY_WINDOW_US of poses of
        the same VO map (a longer base than one frame: frame-to-frame noise divided by 33 ms
        would dominate); NaN until such a pose exists (after a reset or a gap)."""
        recent = self._recent
        while recent and (
            recent[0].reset_counter != reset_counter
            or time_us - recent[0].time_us > VELOCITY_WINDOW_US
        ):
            recent.popleft()
        velocity = np.full(3, np.nan)
        if recent and time_us - recent[0].time_us >= VELOCITY_WINDOW_US // 2:
            velocity = (position - recent[0].position_ned_m) / (
                (time_us - recent[0].time_us) * 1e-6
            )
        recent.append(RecentPosition(time_us, reset_counter, position))
        return velocity
