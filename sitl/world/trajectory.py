"""Smooth multirotor trajectories with a consistent attitude.

A pattern is first laid out as a piecewise-linear path flown at constant speed (with hover
dwells), its height following the terrain at ``altitude_m``; it is then convolved in time with a
Gaussian (sigma 1 s), which makes it C-infinity with |v| <= cruise speed, and represented by
quintic splines sampled at 100 Hz so that position, velocity and acceleration are continuous.

Attitude follows the multirotor model (Mellinger & Kumar, ICRA 2011): the thrust axis (body -z,
FRD) is parallel to the specific force a - g, and yaw follows the direction of travel. Roll and
pitch therefore follow the horizontal acceleration. World: NED; body: FRD.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage
from scipy.interpolate import make_interp_spline

from companion.errors import SitlError
from companion.geometry import se3, so3
from companion.sitl.world.terrain import World
from companion.types import F64

TRAJECTORIES = (
    "hover",
    "circle",
    "lawnmower",
    "figure8",
    "climb",
    "spiral",
    "pad",
    "bob",
    "handheld",
)
GRAVITY_M_S2 = 9.80665
LANDED_HEIGHT_M = 0.25  # body origin above ground when landed (landing gear)
_SAMPLE_HZ = 100.0
_SMOOTH_SIGMA_S = 1.0
_GROUND_REST_S = 3.5  # on the ground before take-off and after landing (> 3 sigma)
_CLIMB_RATE_M_S = 1.5  # take-off and landing
# "bob": a small multirotor flown by hand indoors, low over its floor (the real downward flight
# of docs/RESULTS.md, "Real sequences": 0.13-1.31 m, within a 0.3 x 0.7 m patch, 22 m of path
# in about 45 s of flight): a hover at BOB_MID_M plus sines in north, east and down, each
# (axis, amplitude [m], period [s]), faded in and out over BOB_FADE_S at the pattern's ends; added
# after the 1 s smoothing, which would flatten them. 0.28-1.22 m, ~0.5 m/s.
BOB_MID_M = 0.75
BOB_SINES = ((0, 0.16, 3.1), (1, 0.35, 4.3), (2, 0.35, 7.0), (2, 0.12, 2.3))  # (axis, m, s)
BOB_FADE_S = 2.0
# "handheld": a camera turned by hand (the real hand-held sequence of docs/RESULTS.md, "Real
# sequences": 64 deg/s median, 119 deg/s p95, within a 0.15 x 0.19 x 0.19 m box): roll, pitch
# and yaw each a sine of its own amplitude [rad] and period [s], faded in and out over
# HAND_FADE_S at the pattern's ends; not a multirotor's attitude (no thrust axis to follow)
HAND_SINES = ((0.6, 4.1), (0.45, 5.3), (1.0, 6.7))  # roll, pitch, yaw: (rad, s)
# and the hand's drift: north, east and down sines (amplitude [m], period [s]) about a hover,
# added after the smoothing like bob's: ~0.1 m/s in a 0.16 x 0.18 m box (the real: 1.6-2.2 m
# of path in 24 s within 0.15 x 0.18 x 0.19 m)
HAND_SHIFTS = ((0, 0.07, 6.1), (1, 0.08, 7.3), (2, 0.09, 5.5))  # (axis, m, s)
HAND_FADE_S = 2.0
PAD_HOVER_S = 6.0  # "pad": the hover over the start before and after the square [s]


@dataclass(frozen=True, slots=True)
class TrajectorySample:
    """Vehicle state at N times. position/velocity/accel: (N, 3) NED [m, m/s, m/s^2];
    R_world_body: (N, 3, 3); omega_body_rad_s: (N, 3) body rates (FRD)."""

    time_s: F64
    position_m: F64
    velocity_m_s: F64
    accel_m_s2: F64
    R_world_body: F64
    omega_body_rad_s: F64

    def T_world_body(self, i: int) -> F64:
        """(4, 4) pose at sample i."""
        return se3.make(self.R_world_body[i], self.position_m[i])


def _polyline_xy(name: str, speed: float) -> F64:
    """Horizontal waypoints (K, 2) [m] of one repetition of the pattern, starting at (0, 0)."""
    if name == "hover":
        return np.zeros((1, 2))
    if name == "circle":
        r = 10.0
        a = np.linspace(0.0, 2 * np.pi, 181)
        return np.stack([r * np.sin(a), r * (1 - np.cos(a))], axis=1)
    if name == "lawnmower":
        leg, step, n_legs = 30.0, 6.0, 4
        pts = [(0.0, 0.0)]
        for i in range(n_legs):
            x_end = leg if i % 2 == 0 else 0.0
            y = i * step
            pts.append((x_end, y))
            if i < n_legs - 1:
                pts.append((x_end, y + step))
        fwd = np.asarray(pts)
        return np.concatenate([fwd, fwd[::-1][1:]], axis=0)  # and back again
    if name == "figure8":
        a = np.linspace(0.0, 2 * np.pi, 241)
        return np.stack([14.0 * np.sin(a), 7.0 * np.sin(2 * a)], axis=1)
    if name == "climb":
        return np.array([[0.0, 0.0], [12.0, 0.0], [0.0, 0.0]])
    if name == "pad":  # out of the start's view and back, once, then over it (d-Pose return)
        return np.array([[0.0, 0.0], [12.0, 0.0], [12.0, 12.0], [0.0, 12.0], [0.0, 0.0]])
    if name == "spiral":  # a slow 0.4 m circle over the start point (d-Pose evaluation)
        a = np.linspace(0.0, 2 * np.pi, 73)
        return np.stack([0.4 * np.sin(a), 0.4 * (1 - np.cos(a))], axis=1)
    if name in _DRIFTS:  # a hover; the motion is added after the smoothing (_drift)
        return np.zeros((1, 2))
    raise SitlError(f"unknown trajectory {name!r}; choose one of {', '.join(TRAJECTORIES)}")


def pattern_length_m(name: str, speed_m_s: float = 3.0) -> float:
    """Length [m] of one repetition of a trajectory's horizontal pattern (a lap)."""
    poly = _polyline_xy(name, speed_m_s)
    return float(np.sum(np.linalg.norm(np.diff(poly, axis=0), axis=1)))


def _walk(poly: F64, speed: float, times: F64, repeat: bool = True) -> F64:
    """Position along a polyline flown at constant speed, repeated (or once, then held at its
    end); (N, 2) at times (N,)."""
    if len(poly) == 1:
        return np.repeat(poly, len(times), axis=0)
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s_knots = np.concatenate([[0.0], np.cumsum(seg)])
    total = s_knots[-1]
    s = np.mod(speed * times, total) if repeat else np.minimum(speed * times, total)
    return np.stack([np.interp(s, s_knots, poly[:, 0]), np.interp(s, s_knots, poly[:, 1])], axis=1)


@dataclass(frozen=True, slots=True)
class _Phases:
    """Sample times and the flight's phases: [rest, take-off] dwell, pattern, dwell, [landing,
    rest]."""

    t: F64  # sample times [s], padded by the smoothing kernel's reach on both sides
    tc: F64  # the times clipped to the flight [0, seconds]
    tp: F64  # time into the pattern [s], held before and after it
    start: float  # pattern start and end [s]
    end: float

    @property
    def duration(self) -> float:
        """The pattern's duration [s] (> 0)."""
        return max(self.end - self.start, 1e-6)


def _phases(seconds: float, alt: float, takeoff_landing: bool, dwell_s: float = 2.0) -> _Phases:
    dt = 1.0 / _SAMPLE_HZ
    pad = 4.0 * _SMOOTH_SIGMA_S
    t = np.arange(-pad, seconds + pad + dt / 2, dt)
    tc = np.clip(t, 0.0, seconds)
    dwell = min(dwell_s, 0.1 * seconds if dwell_s <= 2.0 else dwell_s)
    t_up = (_GROUND_REST_S + alt / _CLIMB_RATE_M_S) if takeoff_landing else 0.0
    t_pattern0 = t_up + dwell
    t_pattern1 = max(t_pattern0, seconds - dwell - t_up)
    tp = np.clip(tc, t_pattern0, t_pattern1) - t_pattern0
    return _Phases(t, tc, tp, t_pattern0, t_pattern1)


def _horizontal(name: str, speed_m_s: float, ph: _Phases) -> F64:
    """Horizontal position (N, 2) along the pattern: at the cruise speed, or paced by the
    pattern's duration (climb: out and back once) or slowly (spiral)."""
    poly = _polyline_xy(name, speed_m_s)
    if name == "climb":
        return _walk(poly, 2.0 * float(np.linalg.norm(poly[1] - poly[0])) / ph.duration, ph.tp)
    if name == "spiral":
        return _walk(poly, 0.3, ph.tp)
    return _walk(poly, speed_m_s, ph.tp, repeat=name != "pad")


def _height_agl(name: str, alt: float, ph: _Phases) -> F64:
    """Height above ground (N,) [m] before take-off and landing: the cruise altitude, or the
    climb's and the spiral's profiles."""
    if name == "climb":
        lo, hi = 2.0, 15.0
        phase = np.clip(ph.tp / ph.duration, 0.0, 1.0)
        agl = lo + (hi - lo) * (1.0 - np.abs(2.0 * phase - 1.0))
        agl = np.where(ph.tc < ph.start, lo, agl)
        return np.where(ph.tc > ph.end, lo, agl)
    if name == "spiral":  # 3 m at the start (arming), then 2 -> 8 -> 2 m, yaw turning
        phase = np.clip(ph.tp / ph.duration, 0.0, 1.0)
        agl = 5.0 - 3.0 * np.cos(2 * np.pi * phase)
        agl = np.where(ph.tc < ph.start, 3.0, np.clip(agl, 2.0, 8.0))
        return np.where(ph.tc > ph.end, 2.0, agl)
    return np.full(ph.t.shape, alt)


def _fade(t: F64, start: float, end: float, fade_s: float) -> F64:
    """(N,) 0 before ``start``, 1 from ``fade_s`` after it to ``fade_s`` before ``end``, 0 after
    it: a C3 smoothstep between (its jerk does not jump, so the splines do not ring)."""
    x = np.clip(np.minimum(t - start, end - t) / fade_s, 0.0, 1.0)
    return np.asarray(x**4 * (35.0 - 84.0 * x + 70.0 * x**2 - 20.0 * x**3), dtype=np.float64)


def _sines(t: F64, start: float, fade: F64, sines: tuple[tuple[float, float], ...]) -> F64:
    """(N, len(sines)) each (amplitude, period [s]) sine from ``start``, times ``fade``."""
    cols = [fade * amp * np.sin(2 * np.pi * (t - start) / period) for amp, period in sines]
    return np.stack(cols, axis=1)


def _drift(ph: _Phases, terms: tuple[tuple[int, float, float], ...], fade_s: float) -> F64:
    """(N, 3) a motion about a hover [m] (NED): each (axis, amplitude [m], period [s]) sine
    added on its axis, faded in and out over ``fade_s`` at the pattern's ends."""
    out = np.zeros((len(ph.tc), 3))
    sines = tuple((amp, period) for _, amp, period in terms)
    columns = _sines(ph.tc, ph.start, _fade(ph.tc, ph.start, ph.end, fade_s), sines)
    for k, (axis, _, _) in enumerate(terms):
        out[:, axis] += columns[:, k]
    return out


# the trajectories whose motion is sines about a hover, added after the 1 s smoothing
_DRIFTS = {"bob": (BOB_SINES, BOB_FADE_S), "handheld": (HAND_SHIFTS, HAND_FADE_S)}


def _with_takeoff_landing(agl: F64, tc: F64, seconds: float) -> F64:
    """The height capped by the take-off and landing ramps (rest on the ground, climb or
    descend at the climb rate)."""
    up = np.clip((tc - _GROUND_REST_S) * _CLIMB_RATE_M_S, 0.0, None) + LANDED_HEIGHT_M
    down = np.clip((seconds - _GROUND_REST_S - tc) * _CLIMB_RATE_M_S, 0.0, None) + LANDED_HEIGHT_M
    return np.minimum(np.minimum(agl, up), down)


def _clearance_surface(world: World, xy: F64, sig: float) -> F64:
    """Surface height (N,) under the path, raised to clear buildings after smoothing."""
    surface = world.surface_height(xy[:, 0], xy[:, 1])
    if len(world.boxes):
        # over buildings the height steps by metres at a wall: take the highest surface
        # the smoothing kernel reaches (+-3 sigma), so the smoothed path clears the roof
        # edges by the altitude instead of cutting through them
        surface = ndimage.maximum_filter1d(surface, size=int(6 * sig) + 1, mode="nearest")
    return np.asarray(surface, dtype=np.float64)


def _heading(name: str, vel: F64, ph: _Phases) -> F64:
    """Yaw (N,) [rad], unsmoothed: along the horizontal velocity when moving, held otherwise;
    north for the climb; one full turn over the pattern for the spiral."""
    speed_xy = np.hypot(vel[:, 0], vel[:, 1])
    yaw = np.arctan2(vel[:, 1], vel[:, 0])
    moving = speed_xy > 0.3
    if not moving.any():
        yaw[:] = 0.0
    else:
        idx = np.where(moving, np.arange(len(ph.t)), 0)
        idx = np.maximum.accumulate(idx)
        first = int(np.argmax(moving))
        idx[:first] = first
        yaw = yaw[idx]
    yaw = np.unwrap(yaw)
    if name in ("climb", "handheld", "bob"):
        yaw = np.zeros_like(yaw)
    if name == "spiral":  # one full turn of the heading over the pattern phase
        yaw = 2 * np.pi * np.clip((ph.tc - ph.start) / ph.duration, 0.0, 1.0)
    return np.asarray(yaw, dtype=np.float64)


class Trajectory:
    """A smooth flight; query any time with :meth:`sample` (times in seconds from start)."""

    def __init__(
        self,
        name: str,
        world: World,
        seconds: float,
        altitude_m: float = 0.0,
        speed_m_s: float = 3.0,
        takeoff_landing: bool = False,
    ) -> None:
        if name not in TRAJECTORIES:
            raise SitlError(f"unknown trajectory {name!r}; choose one of {', '.join(TRAJECTORIES)}")
        if seconds <= 0 or not math.isfinite(seconds):
            raise SitlError("trajectory duration must be positive")
        self.name = name
        self.seconds = float(seconds)
        alt = altitude_m if altitude_m > 0 else world.default_altitude_m
        if name == "bob":  # its own heights; the take-off climbs to its middle
            alt = BOB_MID_M
        self.altitude_m = alt
        # over the pad the vehicle hovers 6 s before it leaves (the marks are left then)
        ph = _phases(self.seconds, alt, takeoff_landing, PAD_HOVER_S if name == "pad" else 2.0)
        t = ph.t
        xy = _horizontal(name, speed_m_s, ph)
        agl = _height_agl(name, alt, ph)
        if takeoff_landing:
            agl = _with_takeoff_landing(agl, ph.tc, self.seconds)
        sig = _SMOOTH_SIGMA_S * _SAMPLE_HZ
        z = -(_clearance_surface(world, xy, sig) + agl)

        pos = np.stack([xy[:, 0], xy[:, 1], z], axis=1)
        pos = ndimage.gaussian_filter1d(pos, sig, axis=0, mode="nearest")
        if name in _DRIFTS:
            pos = pos + _drift(ph, *_DRIFTS[name])
        self._pos = make_interp_spline(t, pos, k=5)
        yaw = _heading(name, self._pos.derivative(1)(t), ph)
        yaw = ndimage.gaussian_filter1d(yaw, sig, mode="nearest")
        self._yaw = make_interp_spline(t, yaw, k=5)
        self._pos_d1 = self._pos.derivative(1)
        self._pos_d2 = self._pos.derivative(2)
        self._hand = (ph.start, ph.end) if name == "handheld" else None

    def _hand_rotation(self, t: F64) -> F64:
        """(N, 3, 3) the hand-held camera's body attitude at times (N,): ZYX Euler angles of
        HAND_SINES, faded in and out (a C3 smoothstep) over HAND_FADE_S at the pattern's ends."""
        assert self._hand is not None
        start, end = self._hand
        roll, pitch, yaw = _sines(t, start, _fade(t, start, end, HAND_FADE_S), HAND_SINES).T
        return so3.rpy_to_matrices(roll, pitch, yaw)

    def _rotation(self, accel: F64, yaw: F64, t: F64) -> F64:
        """(N, 3, 3) R_world_body: the thrust axis along the specific force, the nose at
        ``yaw`` (a multirotor), or the hand's attitude at times ``t`` (handheld)."""
        if self._hand is not None:
            return self._hand_rotation(t)
        f = accel - np.array([0.0, 0.0, GRAVITY_M_S2])
        z_b = -f / np.linalg.norm(f, axis=1, keepdims=True)
        x_c = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=1)
        y_b = np.cross(z_b, x_c)
        y_b /= np.linalg.norm(y_b, axis=1, keepdims=True)
        x_b = np.cross(y_b, z_b)
        return np.stack([x_b, y_b, z_b], axis=2)

    def _position_rotation(self, times_s: ArrayLike) -> tuple[F64, F64, F64, F64]:
        """Clamped times (N,) [s], position (N, 3), acceleration (N, 3), R_world_body (N, 3, 3)."""
        t = np.clip(np.atleast_1d(np.asarray(times_s, dtype=np.float64)), 0.0, self.seconds)
        p = np.asarray(self._pos(t), dtype=np.float64)
        a = np.asarray(self._pos_d2(t), dtype=np.float64)
        return t, p, a, self._rotation(a, np.asarray(self._yaw(t)), t)

    def sample(self, times_s: ArrayLike) -> TrajectorySample:
        """State at times (N,) [s] (clamped to [0, seconds])."""
        t, p, a, R = self._position_rotation(times_s)
        v = np.asarray(self._pos_d1(t), dtype=np.float64)
        # body rates from the rotation's time derivative: [w]x = R^T dR/dt (central difference)
        h = 1e-4
        Rp = self._rotation(np.asarray(self._pos_d2(t + h)), np.asarray(self._yaw(t + h)), t + h)
        Rm = self._rotation(np.asarray(self._pos_d2(t - h)), np.asarray(self._yaw(t - h)), t - h)
        W = np.einsum("nji,njk->nik", R, (Rp - Rm) / (2 * h))
        omega = (
            np.stack(
                [W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0], W[:, 1, 0] - W[:, 0, 1]], axis=1
            )
            / 2.0
        )
        return TrajectorySample(t, p, v, a, R, omega)

    def poses(self, times_s: ArrayLike) -> F64:
        """(N, 4, 4) body poses T_world_body at times (N,) [s] (clamped to [0, seconds]):
        sample()'s position and rotation, equal to the bit, without its body rates (a third
        of the spline evaluations: the SITL autopilot asks for one per range reading)."""
        t, p, _, R = self._position_rotation(times_s)
        T = np.zeros((len(t), 4, 4))
        T[:, :3, :3] = R
        T[:, :3, 3] = p
        T[:, 3, 3] = 1.0
        return T

    def T_world_body(self, time_s: float) -> F64:
        """(4, 4) body pose at one time [s]."""
        T: F64 = self.poses([time_s])[0]
        return T

    def path_length_m(self, step_s: float = 0.01) -> float:
        """Length of the flown 3D path [m]."""
        p = self.sample(np.arange(0.0, self.seconds + step_s / 2, step_s)).position_m
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
