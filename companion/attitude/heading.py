"""The heading of the VO frame from the magnetometer, averaged while the vehicle stands still.

Without GNSS the only absolute heading on a small vehicle is its compass. The VO frame's x
axis takes the autopilot's heading when the VO initialises (companion/vo/odometry.py), and
that heading is only as good as the autopilot's estimate at that instant. PX4's EKF2 on the
ground, with GPS off, let its heading wander by 1-2 deg within a minute while the
magnetometer's own mean stayed put: EKF2 learns magnetometer biases that the ground cannot
observe (PX4 SIH, 2026-03: EKF2's heading error at rest +0.2 -> +1.2, +2.0 -> +2.9,
+1.0 -> +1.9 deg over 50 s in three boots; the raw field's 10 s means within +-0.3 deg of one
direction; docs/decisions.md, "The frame's heading from the magnetometer"). So the service
can average the raw field itself over the time the vehicle stands still before take-off.

Method (a tilt-compensated compass, the accelerometer giving the tilt). Over the still
window, the mean specific force f (body FRD [m/s^2], about (0, 0, -g) level) and the mean
field m (body FRD [gauss]). The world's down in the body frame is d = -f / |f|. The field's
horizontal part h = m - (m . d) d points at magnetic north, the body's x axis projected on the
horizontal plane, x_h = e_x - (e_x . d) d, at the body's heading; the angle from h to x_h
about d is the magnetic heading, and with the declination D (east positive) the true one:

    yaw = atan2(d . (h x x_h), h . x_h) + D                                   (1)

This is the ZYX yaw of R_world_body = Rz(yaw) Ry(pitch) Rx(roll) exactly (the body's x axis
projects on the horizontal plane at azimuth yaw). Its uncertainty: the scatter of the field
across the horizontal direction of h, over |h| and the square root of the sample count (the
white-noise bound; a real magnetometer's slow noise and a wrong declination are not in it).
Averaging the vectors first, not per-sample headings, keeps (1) unbiased at any noise.

A reading equal to the previous one is the same sample sent again (PX4's SCALED_IMU carries
its latest field with every accelerometer sample: 50 Hz of field in a 200 Hz stream) and is
not counted twice.

Stillness: a sample with the gyroscope's rate above ``max_rate_rad_s`` or its specific
force's norm further than ``max_force_error_m_s2`` from the standard gravity ends the window
for good (:attr:`MagHeading.moved`): once the vehicle has moved the body's heading in the
window is no longer one angle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.types import F64, ImuSample

STANDARD_GRAVITY_M_S2 = 9.80665


def magnetic_yaw_rad(force_frd_m_s2: F64, field_frd: F64, declination_rad: float) -> float:
    """Equation (1): the body's true heading [rad] in [-pi, pi] from the specific force (3,)
    [m/s^2] and the magnetic field (3,) [any unit] in the body frame (FRD), at rest, with the
    site's declination [rad, east positive]. NaN when the field has no horizontal part."""
    f = np.asarray(force_frd_m_s2, dtype=np.float64)
    m = np.asarray(field_frd, dtype=np.float64)
    d = -f / np.linalg.norm(f)
    h = m - float(m @ d) * d
    x_h = np.array([1.0, 0.0, 0.0]) - d[0] * d
    if np.linalg.norm(h) < 1e-9 or np.linalg.norm(x_h) < 1e-9:
        return math.nan
    yaw = math.atan2(float(d @ np.cross(h, x_h)), float(h @ x_h)) + declination_rad
    return math.remainder(yaw, math.tau)


@dataclass(frozen=True, slots=True)
class HeadingFix:
    """The still window's heading: ``yaw_rad`` the body's true heading (ZYX yaw of
    R_world_body) [rad], ``sigma_rad`` its white-noise standard error, ``samples`` the
    magnetometer samples averaged, ``span_us`` the window's length."""

    yaw_rad: float
    sigma_rad: float
    samples: int
    span_us: int


@dataclass(eq=False)
class MagHeading:
    """Accumulates accelerometer and magnetometer samples (ImuSample with ``mag_frd_gauss``)
    while the body stands still; :meth:`fix` is equation (1) over them."""

    declination_rad: float
    max_rate_rad_s: float = 0.05
    max_force_error_m_s2: float = 0.5
    moved: bool = field(init=False, default=False)  # a sample that was not still ended it
    last_us: int | None = field(init=False, default=None)  # the newest sample seen
    # the first and last magnetometer samples averaged
    _first_us: int | None = field(init=False, default=None)
    _last_field_us: int | None = field(init=False, default=None)
    _last_field: F64 | None = field(init=False, default=None)
    _n: int = field(init=False, default=0)
    _force_sum: F64 = field(init=False, default_factory=lambda: np.zeros(3))
    _field_sum: F64 = field(init=False, default_factory=lambda: np.zeros(3))
    # sum of m m^T, for the scatter
    _field_outer: F64 = field(init=False, default_factory=lambda: np.zeros((3, 3)))

    def add(self, sample: ImuSample) -> None:
        """Take one sample (older than the last one seen: ignored). Samples without a
        magnetometer reading still end the window when the body moves."""
        if self.moved or (self.last_us is not None and sample.time_us <= self.last_us):
            return
        self.last_us = sample.time_us
        f = sample.accel_frd_m_s2
        still = abs(float(np.linalg.norm(f)) - STANDARD_GRAVITY_M_S2) <= self.max_force_error_m_s2
        w = sample.gyro_frd_rad_s
        if w is not None and np.all(np.isfinite(w)):
            still = still and float(np.linalg.norm(w)) <= self.max_rate_rad_s
        if not still:
            self.moved = True
            return
        m = sample.mag_frd_gauss
        if m is None or not np.all(np.isfinite(m)) or not np.any(m):
            return
        if self._last_field is not None and np.array_equal(m, self._last_field):
            return  # the same reading again (PX4 repeats its 50 Hz field in a 200 Hz stream)
        self._last_field = m
        if self._first_us is None:
            self._first_us = sample.time_us
        self._last_field_us = sample.time_us
        self._n += 1
        self._force_sum += f
        self._field_sum += m
        self._field_outer += np.outer(m, m)

    @property
    def samples(self) -> int:
        """Magnetometer samples averaged so far."""
        return self._n

    def fix(self) -> HeadingFix | None:
        """The heading over the window so far; None before 2 samples or without a horizontal
        field."""
        if self._n < 2 or self._first_us is None or self._last_field_us is None:
            return None
        f = self._force_sum / self._n
        m = self._field_sum / self._n
        yaw = magnetic_yaw_rad(f, m, self.declination_rad)
        if not math.isfinite(yaw):
            return None
        d = -f / np.linalg.norm(f)
        h = m - float(m @ d) * d
        across = np.cross(d, h / np.linalg.norm(h))  # horizontal, perpendicular to h
        cov = self._field_outer / self._n - np.outer(m, m)
        var = max(float(across @ cov @ across), 0.0)
        sigma = math.sqrt(var / (self._n - 1)) / float(np.linalg.norm(h))
        return HeadingFix(yaw, sigma, self._n, self._last_field_us - self._first_us)
