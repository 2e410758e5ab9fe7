"""What our dataset format is made of (docs/dataset.md): its name and version, the
columns of its CSV files, the bounds a stored value must keep, a published pose as read and
the count of rows a reader left out."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.types import (
    F64,
    AttitudeSample,
    CameraFrame,
    ImuSample,
    RangeSample,
)

I64 = NDArray[np.int64]

FORMAT_NAME = "companion-dataset"
FORMAT_VERSION = 1
Event = CameraFrame | RangeSample | AttitudeSample | ImuSample
# the algorithm options a recording was processed with (config.toml of a recording)
ALGORITHM_SECTIONS = ("vo", "scale", "attitude", "dpose")
RANGE_COLUMNS = ["time_us", "sensor_id", "distance_m", "min_m", "max_m", "signal_quality"]
ATTITUDE_COLUMNS = ["time_us", "qw", "qx", "qy", "qz", "wx_rad_s", "wy_rad_s", "wz_rad_s"]
IMU_COLUMNS = ["time_us", "ax_m_s2", "ay_m_s2", "az_m_s2"]  # specific force, body FRD
# optional (recordings made before 2026-11-27 lack them; empty when the autopilot sent none):
# body rates and the raw magnetic field, body FRD
IMU_GYRO_COLUMNS = ["wx_rad_s", "wy_rad_s", "wz_rad_s"]
IMU_MAG_COLUMNS = ["mx_gauss", "my_gauss", "mz_gauss"]
PUBLISHED_COLUMNS = [
    "time_us",
    "x_m",
    "y_m",
    "z_m",
    "qw",
    "qx",
    "qy",
    "qz",
    "vx_m_s",
    "vy_m_s",
    "vz_m_s",
    "reset_counter",
    "quality_pct",
]
FED = "fed_before_frame"  # column: the index of the frame this sample was fed before


@dataclass(frozen=True, slots=True)
class PublishedPose:
    """A pose the service sent to the autopilot (published.csv of a recording): time_us of
    its frame, position (3,) NED [m], quat_wxyz (4,) NED <- FRD, velocity (3,) NED [m/s], the
    reset_counter as sent (the wire's, which continues across restarts) and quality [%]."""

    time_us: int
    position_ned_m: F64
    quat_wxyz: F64
    velocity_ned_m_s: F64
    reset_counter: int
    quality_pct: int


MAX_TIME_US = 2**62  # a time stamp of ours: [0, 2**62] us (146,000 years)
MAX_SEQ = 2**62
QUAT_NORM_TOLERANCE = 0.01  # |norm - 1| of a stored unit quaternion (float32 sources: 1e-7)
MAX_RATE_RAD_S = 50.0  # as the live service refuses ATTITUDE (drivers/messages.py)
MAX_SPECIFIC_FORCE_M_S2 = 16 * 9.80665  # as it refuses SCALED_IMU
MAX_DISTANCE_M = 1000.0
MAX_POSITION_M = 1e7
MAX_VELOCITY_M_S = 1e4
MAX_MAGNETIC_GAUSS = 100.0


@dataclass
class RowCount:
    """The rows of one file left out by the reader: how many, and the first one's reason."""

    skipped: int = 0
    first: str = ""

    def add(self, reason: str) -> None:
        """Count a left-out row (its reason kept if it is the first)."""
        self.skipped += 1
        self.first = self.first or reason
