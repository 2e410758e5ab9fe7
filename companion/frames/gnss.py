"""GPS fixes as the autopilot reports them: the quality verdict with hysteresis, and a fix in
the autopilot's local NED (pure).

Input: GPS_RAW_INT's fields (fix_type 0..8, eph [cm] with 65535 = unknown, satellites_visible
with 255 = unknown, lat / lon [degE7], alt [mm] above mean sea level), stamped on our clock
(``time_us``), and GPS_GLOBAL_ORIGIN (the EKF's origin: latitude / longitude [degE7], altitude
[mm] AMSL).

Verdict: a sample is good when fix_type >= ``min_fix_type`` (3: 3-D), eph <= ``max_eph_m``
(PX4's EKF2_REQ_EPH: 3 m) and satellites >= ``min_satellites`` (EKF2_REQ_NSATS: 6); the GPS is
also bad when no sample came for ``max_age_s``. The verdict turns bad once the samples have
been bad for ``bad_after_s`` (fast: the service hands over at once), and good again once they
have been good for ``good_after_s`` (slow: a receiver's first fixes after an outage can be far
off). ``bad_since_us`` is the first bad sample of the current bad run, so that the handover can
take its alignment from before the GPS started to degrade.

Local NED: the autopilot's own projection about its origin, so that the fix lands where the
autopilot's local position would: PX4 (``map_projection``) the azimuthal equidistant projection
on a sphere of 6 371 000 m; ArduPilot (``Location::get_distance_NE``) an equirectangular one,
1e-7 deg = 0.011131884502145034 m, the longitude scaled by cos of the mean latitude. They
differ by 0.11 % (the radii: 6 371 km against 6 378.1 km): 0.001 deg of latitude is 111.19 m
on PX4, 111.32 m on ArduPilot.
Down = origin altitude - fix altitude.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from companion.types import F64

PX4_EARTH_RADIUS_M = 6_371_000.0  # CONSTANTS_RADIUS_OF_EARTH
ARDUPILOT_M_PER_DEG_E7 = 0.011131884502145034  # LOCATION_SCALING_FACTOR
EPH_UNKNOWN_CM, SATELLITES_UNKNOWN = 65535, 255
Projection = Literal["px4", "ardupilot"]


@dataclass(frozen=True, slots=True)
class GpsFix:
    """One GPS_RAW_INT: time_us on our clock; lat_deg, lon_deg [deg]; alt_m AMSL [m];
    eph_m [m] (inf: unknown); satellites (-1: unknown)."""

    time_us: int
    fix_type: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    eph_m: float
    satellites: int

    @staticmethod
    def from_gps_raw_int(
        time_us: int, fix_type: int, lat: int, lon: int, alt: int, eph: int, satellites: int
    ) -> GpsFix:
        """From GPS_RAW_INT's integer fields (degE7, mm, cm)."""
        return GpsFix(
            time_us,
            fix_type,
            lat * 1e-7,
            lon * 1e-7,
            alt * 1e-3,
            math.inf if eph == EPH_UNKNOWN_CM else eph * 1e-2,
            -1 if satellites == SATELLITES_UNKNOWN else satellites,
        )


@dataclass(frozen=True, slots=True)
class GlobalOrigin:
    """GPS_GLOBAL_ORIGIN: lat_deg, lon_deg [deg], alt_m AMSL [m]."""

    lat_deg: float
    lon_deg: float
    alt_m: float

    @staticmethod
    def from_message(latitude: int, longitude: int, altitude: int) -> GlobalOrigin:
        """From GPS_GLOBAL_ORIGIN's fields (degE7, degE7, mm)."""
        return GlobalOrigin(latitude * 1e-7, longitude * 1e-7, altitude * 1e-3)


def to_local_ned(
    origin: GlobalOrigin, lat_deg: float, lon_deg: float, alt_m: float, projection: Projection
) -> F64:
    """The point (3,) [m] in the autopilot's local NED about ``origin``, by its projection."""
    down = origin.alt_m - alt_m
    if projection == "ardupilot":
        scale = max(math.cos(math.radians(0.5 * (origin.lat_deg + lat_deg))), 0.01)
        north = (lat_deg - origin.lat_deg) * 1e7 * ARDUPILOT_M_PER_DEG_E7
        east = _wrap_deg(lon_deg - origin.lon_deg) * 1e7 * ARDUPILOT_M_PER_DEG_E7 * scale
        return np.array([north, east, down])
    lat0, lon0 = math.radians(origin.lat_deg), math.radians(origin.lon_deg)
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    cos_d_lon = math.cos(lon - lon0)
    arg = math.sin(lat0) * math.sin(lat) + math.cos(lat0) * math.cos(lat) * cos_d_lon
    c = math.acos(min(1.0, max(-1.0, arg)))
    k = c / math.sin(c) if abs(c) > 1e-12 else 1.0
    north = k * (math.cos(lat0) * math.sin(lat) - math.sin(lat0) * math.cos(lat) * cos_d_lon)
    east = k * math.cos(lat) * math.sin(lon - lon0)
    return np.array([north * PX4_EARTH_RADIUS_M, east * PX4_EARTH_RADIUS_M, down])


def plausible_position(lat_deg: float, lon_deg: float, alt_m: float) -> bool:
    """A fix or origin on the Earth: finite, |latitude| <= 90 deg, |longitude| <= 180 deg,
    altitude -1 km .. 100 km AMSL."""
    return (
        math.isfinite(lat_deg + lon_deg + alt_m)
        and abs(lat_deg) <= 90.0
        and abs(lon_deg) <= 180.0
        and -1000.0 <= alt_m <= 100_000.0
    )


def _wrap_deg(d: float) -> float:
    return (d + 180.0) % 360.0 - 180.0


@dataclass(frozen=True, slots=True)
class GnssOptions:
    """The verdict's thresholds (module docstring); times in seconds."""

    min_fix_type: int = 3
    max_eph_m: float = 3.0
    min_satellites: int = 6
    max_age_s: float = 1.0
    bad_after_s: float = 0.0
    good_after_s: float = 3.0


@dataclass(frozen=True, slots=True)
class GnssVerdict:
    """good: the hysteresis verdict; sample_good: the newest sample alone (and fresh);
    reasons: why the newest sample is bad (empty when good); bad_since_us: the first bad
    sample of the current bad run (None while the samples are good)."""

    good: bool
    sample_good: bool
    reasons: tuple[str, ...]
    bad_since_us: int | None


def sample_reasons(fix: GpsFix, opts: GnssOptions) -> tuple[str, ...]:
    """Why one fix is not good enough (empty: good)."""
    out = []
    if fix.fix_type < opts.min_fix_type:
        out.append(f"fix type {fix.fix_type} < {opts.min_fix_type}")
    if not fix.eph_m <= opts.max_eph_m:
        out.append(f"eph {fix.eph_m:g} m > {opts.max_eph_m:g} m")
    if fix.satellites < opts.min_satellites:
        out.append(f"{fix.satellites} satellites < {opts.min_satellites}")
    return tuple(out)


class GnssMonitor:
    """The verdict over a stream of fixes: :meth:`update` with each, :meth:`at` any time."""

    def __init__(self, opts: GnssOptions | None = None) -> None:
        self.opts = opts or GnssOptions()
        self.good = False
        self.last_us: int | None = None
        self.reasons: tuple[str, ...] = ("no GPS sample yet",)
        self.bad_since_us: int | None = None  # first bad sample (or silence) of this bad run
        self.good_since_us: int | None = None  # first good sample of this good run

    def update(self, fix: GpsFix) -> GnssVerdict:
        """Take one fix and return the verdict at its stamp."""
        self.reasons = sample_reasons(fix, self.opts)
        if self.last_us is not None and fix.time_us - self.last_us > self.opts.max_age_s * 1e6:
            self._bad(self.last_us + int(self.opts.max_age_s * 1e6))  # silence was bad
            self.good = False  # a loss, whether or not :meth:`at` was asked meanwhile
        self.last_us = fix.time_us
        if self.reasons:
            self._bad(fix.time_us)
        else:
            self.bad_since_us = None
            if self.good_since_us is None:
                self.good_since_us = fix.time_us
        return self.at(fix.time_us)

    def _bad(self, time_us: int) -> None:
        self.good_since_us = None
        if self.bad_since_us is None:
            self.bad_since_us = time_us

    def at(self, time_us: int) -> GnssVerdict:
        """The verdict at ``time_us`` (a GPS silent for ``max_age_s`` is bad)."""
        o = self.opts
        reasons = self.reasons
        if self.last_us is not None and time_us - self.last_us > o.max_age_s * 1e6:
            reasons = (f"no GPS sample for {(time_us - self.last_us) * 1e-6:.1f} s",)
            self._bad(self.last_us + int(o.max_age_s * 1e6))
        sample_good = not reasons
        if self.good and self.bad_since_us is not None:
            self.good = time_us - self.bad_since_us < o.bad_after_s * 1e6
        elif not self.good and self.good_since_us is not None and sample_good:
            self.good = time_us - self.good_since_us >= o.good_after_s * 1e6
        return GnssVerdict(self.good, sample_good, reasons, self.bad_since_us)
