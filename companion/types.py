"""Frozen value types that cross module boundaries (docs/architecture.md, "Types that cross
modules").

Conventions: world frame local NED, body FRD, camera OpenCV (x right, y down, z optical axis).
``T_a_b`` (4, 4) maps points from frame b into frame a. Quaternions are Hamilton ``quat_wxyz``.
Times are ``time_us`` in the companion's monotonic clock unless a name says otherwise.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]


@dataclass(frozen=True, slots=True)
class CameraFrame:
    """One colour image stamped at exposure.

    image_bgr: (H, W, 3) uint8, BGR channel order (OpenCV).
    """

    time_us: int
    seq: int
    image_bgr: U8


class SignalQuality(enum.IntEnum):
    """MAVLink DISTANCE_SENSOR.signal_quality semantics."""

    UNKNOWN = 0
    INVALID = 1
    BEST = 100


@dataclass(frozen=True, slots=True)
class RangeSample:
    """One distance-sensor reading.

    distance_m: measured distance along the beam [m]; min_m / max_m: the sensor's valid range.
    signal_quality: 0 unknown, 1 invalid, 2..100 quality in percent (MAVLink convention).
    """

    time_us: int
    sensor_id: int
    distance_m: float
    min_m: float
    max_m: float
    signal_quality: int

    @property
    def is_valid(self) -> bool:
        """True when the reading is finite, inside [min_m, max_m] and not flagged invalid."""
        d = self.distance_m
        return (
            bool(np.isfinite(d))
            and self.min_m <= d <= self.max_m
            and self.signal_quality != SignalQuality.INVALID
        )


@dataclass(frozen=True, slots=True)
class AttitudeSample:
    """Vehicle attitude from the autopilot (or the simulator).

    quat_wxyz: (4,) Hamilton rotation R_world_body (NED <- FRD).
    rates_rad_s: (3,) body angular rates about FRD axes [rad/s].
    """

    time_us: int
    quat_wxyz: F64
    rates_rad_s: F64


@dataclass(frozen=True, slots=True)
class ImuSample:
    """One inertial sample from the autopilot (SCALED_IMU).

    accel_frd_m_s2: (3,) specific force in the body frame (FRD) [m/s^2]: about (0, 0, -9.81)
    level and at rest. gyro_frd_rad_s: (3,) body rates [rad/s], None when not sent.
    mag_frd_gauss: (3,) magnetic field in the body frame [gauss], None without a magnetometer.
    """

    time_us: int
    accel_frd_m_s2: F64
    gyro_frd_rad_s: F64 | None = None
    mag_frd_gauss: F64 | None = None


class VoState(enum.Enum):
    """Visual odometry state; nothing is published unless TRACKING."""

    INITIALIZING = "initializing"
    TRACKING = "tracking"
    LOST = "lost"


@dataclass(frozen=True, slots=True)
class VoFeatures:
    """Tracked features of one frame.

    pixels: (N, 2) distorted pixel coordinates [px]; point_ids: (N,) int64 map point ids
    (-1 when the feature has no 3D point yet); points_vo: (N, 3) map points in the VO frame
    [VO units] (NaN rows where point_ids == -1); depth_sigma: (N,) depth standard deviation
    [VO units].
    """

    pixels: F64
    point_ids: I64
    points_vo: F64
    depth_sigma: F64


@dataclass(frozen=True, slots=True)
class VoOutput:
    """Monocular VO result of one frame. T_vo_cam: (4, 4) unscaled camera pose in the VO frame."""

    time_us: int
    state: VoState
    is_keyframe: bool
    T_vo_cam: F64
    features: VoFeatures


@dataclass(frozen=True, slots=True)
class ScaleEstimate:
    """Metric scale s such that metres = s * VO units; sigma is its standard deviation."""

    time_us: int
    scale: float
    sigma: float
    method: str
    n_used: int


@dataclass(frozen=True, slots=True)
class TiltEstimate:
    """Roll and pitch of the body (ZYX, FRD in NED) [rad] with their covariance (2, 2) [rad^2].

    reference: "ground" (relative to the plane through the range hit points), "gravity"
    (terrain-compensated) or "fused" (the VO rotation corrected by the ranges).
    """

    time_us: int
    roll_rad: float
    pitch_rad: float
    cov_rad2: F64
    reference: str
    n_sensors: int


@dataclass(frozen=True, slots=True)
class PoseEstimate:
    """Metric pose for the autopilot.

    position_ned_m: (3,); quat_wxyz_ned_frd: (4,) R_world_body; velocity_ned_m_s: (3,);
    covariance_6x6: (6, 6) over (x, y, z, roll, pitch, yaw) [m^2, rad^2] (NaN = unknown);
    quality_pct: 0..100.
    """

    time_us: int
    position_ned_m: F64
    quat_wxyz_ned_frd: F64
    velocity_ned_m_s: F64
    covariance_6x6: F64
    reset_counter: int
    quality_pct: int


@dataclass(frozen=True, slots=True)
class RangeSensorSpec:
    """A distance sensor's calibration.

    T_body_rf: (4, 4) sensor frame -> body; the beam leaves the sensor origin along +z of the
    sensor frame. Noise model: sigma_m = sigma_a_m + sigma_b * range_m.
    """

    sensor_id: int
    T_body_rf: F64
    min_m: float
    max_m: float
    sigma_a_m: float
    sigma_b: float

    def sigma_m(self, range_m: float) -> float:
        """Standard deviation of a reading at ``range_m`` [m]."""
        return self.sigma_a_m + self.sigma_b * range_m


@dataclass(frozen=True, slots=True)
class GroundPlane:
    """The ground under the camera, in metres, for a metric VO initialisation without
    parallax (vehicle on the ground): points X (3,) of the camera frame on the plane satisfy
    ``normal_cam @ X = distance_m``.

    normal_cam: (3,) unit normal pointing away from the camera (towards the ground);
    distance_m: the camera's distance to the plane [m] (> 0); sigma_m: its standard deviation
    [m]; source: "ranges" (a plane fitted to >= 3 distance readings) or "landed" (the
    configured landing-gear height under the autopilot's attitude: sensors below their minimum).
    """

    normal_cam: F64
    distance_m: float
    sigma_m: float
    source: str
