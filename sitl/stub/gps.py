"""The SITL autopilot's GPS receiver (``AutopilotOptions.gps``): GPS_RAW_INT and
GPS_GLOBAL_ORIGIN from the flight's truth, as PX4 streams them.

The GPS frame is the autopilot's local NED about its EKF origin (``GPS_ORIGIN``: PX4 SITL's
default site): the truth [m] moved by ``gps_offset_ned_m`` (the autopilot's origin is not where
our VO starts, nor where the world's is), plus a receiver's noise: ``gps_noise_m`` per axis,
first-order Gauss-Markov correlated over ``NOISE_TAU_S`` (GPS errors wander, they do not
jitter), seeded by the scenario's seed. The point goes out as latitude / longitude by PX4's own
projection's inverse (azimuthal equidistant, R = 6 371 km: ``companion.frames.gnss`` maps it
back to the same metres to the 1e-7 deg of the message, ~1 cm), altitude AMSL [mm], fix type
3, eph 0.9 m, 12 satellites. A ``gps_loss`` fault (sitl/stub/faults.py) makes it a receiver
without a fix for its duration: fix type 1, eph and satellites unknown-ish (99.99 m, 3), no
position.

Rates: GPS_RAW_INT at 5 Hz, GPS_GLOBAL_ORIGIN at 1 Hz (the companion may set either through
MAV_CMD_SET_MESSAGE_INTERVAL; ``rates_hz`` holds them beside the stub's other streams).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

MSG_GPS_RAW_INT, MSG_GPS_GLOBAL_ORIGIN = 24, 49
DEFAULT_RATES_HZ = {MSG_GPS_RAW_INT: 5.0, MSG_GPS_GLOBAL_ORIGIN: 1.0}
GPS_ORIGIN = (47.397742, 8.545594, 488.0)  # PX4 SITL's home: lat, lon [deg], alt AMSL [m]
EARTH_RADIUS_M = 6_371_000.0  # PX4's CONSTANTS_RADIUS_OF_EARTH
NOISE_TAU_S = 1.0
GOOD_EPH_CM, GOOD_SATELLITES = 90, 12
LOST_EPH_CM, LOST_SATELLITES = 9999, 3


def ned_to_lat_lon(
    north_m: float, east_m: float, lat0_deg: float, lon0_deg: float
) -> tuple[float, float]:
    """The inverse of PX4's azimuthal equidistant projection about (lat0, lon0) [deg]."""
    x, y = north_m / EARTH_RADIUS_M, east_m / EARTH_RADIUS_M
    lat0, lon0 = math.radians(lat0_deg), math.radians(lon0_deg)
    c = math.hypot(x, y)
    if c < 1e-15:
        return lat0_deg, lon0_deg
    sin_c, cos_c = math.sin(c), math.cos(c)
    lat = math.asin(cos_c * math.sin(lat0) + x * sin_c * math.cos(lat0) / c)
    lon = lon0 + math.atan2(y * sin_c, c * math.cos(lat0) * cos_c - x * math.sin(lat0) * sin_c)
    return math.degrees(lat), math.degrees(lon)


class GpsNoise:
    """Per-axis Gauss-Markov noise [m]: stationary sigma ``sigma_m``, correlation ``tau_s``."""

    def __init__(self, sigma_m: float, tau_s: float, seed: int) -> None:
        self.sigma_m, self.tau_s = sigma_m, tau_s
        self.rng = np.random.default_rng([seed, 2443])
        self.value = self.rng.standard_normal(3) * sigma_m
        self.t_s: float | None = None

    def at(self, t_s: float) -> np.ndarray:
        """The noise at flight time ``t_s`` (in increasing order)."""
        if self.t_s is not None and t_s > self.t_s:
            phi = math.exp(-(t_s - self.t_s) / self.tau_s)
            kick = self.rng.standard_normal(3) * self.sigma_m * math.sqrt(1.0 - phi * phi)
            self.value = phi * self.value + kick
        self.t_s = t_s if self.t_s is None else max(self.t_s, t_s)
        return np.asarray(self.value, np.float64)


def gps_raw_int(
    mav: Any, time_usec: int, truth_ned_m: np.ndarray, lost: bool, noise_ned_m: np.ndarray
) -> Any:
    """GPS_RAW_INT for the GPS-frame point ``truth_ned_m`` + ``noise_ned_m`` (or a lost fix)."""
    lat0, lon0, alt0 = GPS_ORIGIN
    if lost:
        return mav.gps_raw_int_encode(
            time_usec, 1, 0, 0, 0, LOST_EPH_CM, 65535, 0, 65535, LOST_SATELLITES
        )
    p = truth_ned_m + noise_ned_m
    lat, lon = ned_to_lat_lon(float(p[0]), float(p[1]), lat0, lon0)
    return mav.gps_raw_int_encode(
        time_usec,
        3,
        int(round(lat * 1e7)),
        int(round(lon * 1e7)),
        int(round((alt0 - float(p[2])) * 1e3)),
        GOOD_EPH_CM,
        150,
        0,
        65535,
        GOOD_SATELLITES,
    )


def gps_global_origin(mav: Any, time_usec: int) -> Any:
    """GPS_GLOBAL_ORIGIN: the autopilot's EKF origin (degE7, mm AMSL)."""
    lat0, lon0, alt0 = GPS_ORIGIN
    return mav.gps_global_origin_encode(
        int(round(lat0 * 1e7)), int(round(lon0 * 1e7)), int(round(alt0 * 1e3)), time_usec
    )
