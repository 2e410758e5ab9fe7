"""Gravity from the distance sensors over the take-off pad (pure).

Why: in a vertical climb over the ground the images cannot tell a tilt from a sideways move
(companion/vo/ba.py), so the local BA takes its tilt from the gravity prior, and an
autopilot without GNSS may be a degree off in the air (PX4 on SIH: 0.5-1.2 deg in the climb,
docs/RESULTS.md) while it is good at rest (0.07 deg on the ground, same flights). The
distance sensors see the ground's plane in the body frame with no such error; over a level
plane that plane's normal is gravity (docs/methods.md, companion/attitude/ground.py), and
over any planar pad it is gravity once the pad's own tilt is known. So:

1. At rest on the pad, the pad's normal in the world (NED, down) is measured with the
   autopilot's attitude where it is good: n_pad = mean_i R_world_body(t_i) n_body(t_i),
   normalised (n_body: the downward normal of the readings' plane, ground.py).
2. In the air over the pad, each plane n_body(t) seen through the autopilot's attitude is
   off n_pad by the autopilot's tilt error: for R_world_body = R_err R_true (R_err a small
   world-frame rotation), R_world_body n_body = R_err n_pad, so the sample
   e(t) = R_world_body(t) n_body(t) - n_pad  (3,)
   is that error acting on n_pad (first order: theta x n_pad).
3. A keyframe's gravity (down, body frame) is the autopilot's corrected by the samples of
   the last ``window_us``: with m = normalise(n_pad + mean(e)) (the pad as the autopilot sees
   it) and Q the smallest rotation taking n_pad onto m (Q estimates R_err but for a turn about
   n_pad, which the plane cannot show and which leaves gravity near alone for a pad near level),
   the true gravity R_true^T e_z = R_world_body^T R_err e_z is estimated as
   down_body = R_world_body^T Q e_z.

Its sigma: the samples' scatter over their count (each sample is one plane fit of the
readings, sigma sqrt(2) * sigma_range / L per axis for sensors L apart), floored at
``sigma_floor_rad`` (the pad's own flatness, the autopilot's attitude at rest).

What it assumes: the pad is one plane under every hit point from rest up to the climb's top
(a floor, a landing mat, a flat clearing), which it cannot check from three or four hits alone.
Over a pad that is not one plane the correction is wrong: on our clipped hills, whose take-off
point sits on the edge of a 6 deg slope, the hits' plane moved 2-6 deg as they crossed it in the
climb (docs/RESULTS.md, "2026-11-25 (f7f4e68)"). Samples that disagree with the autopilot by
more than ``max_error_rad`` are refused (a hit on a box, a person's foot). Only keyframes within
a radius of where the vehicle rested use it (the caller's check, :meth:`PadLevel.near`).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from companion.geometry import so3
from companion.types import F64

E_Z = np.array([0.0, 0.0, 1.0])


@dataclass(eq=False)
class PadLevel:
    """The pad measured at rest, then the autopilot's tilt error over it from the ranges.

    Times [us]; vectors in the world frame (NED) unless named ``_body``; ``position_m``: the
    body's metric position (3,) in the caller's gravity-aligned frame, with ``segment`` naming
    that frame (a new VO map moves the origin: the pad's position is then unknown)."""

    window_us: int
    sigma_floor_rad: float
    max_error_rad: float
    min_samples: int = 10
    rest_window_us: int = 10_000_000
    rest_guard_us: int = 1_000_000
    # (time, n_world) of the current rest: the last rest_guard_us, and the settled ones
    # before (their sum kept as they come and go: a rest is ~30 planes a second)
    _rest: deque[tuple[int, F64]] = field(init=False, default_factory=deque)
    _settled: deque[tuple[int, F64]] = field(init=False, default_factory=deque)
    _settled_sum: F64 = field(init=False, default_factory=lambda: np.zeros(3))
    # (time, e) of the flight over the pad
    _air: deque[tuple[int, F64]] = field(init=False, default_factory=deque)
    n_pad: F64 | None = field(init=False, default=None)  # the pad's downward normal (world)
    centre_m: F64 | None = field(init=False, default=None)  # where the body rested
    segment: object = field(init=False, default=None)
    refused: int = field(init=False, default=0)  # air samples off the autopilot by > max_error

    def at_rest(
        self, time_us: int, n_body: F64, R_world_body: F64, position_m: F64 | None, segment: object
    ) -> None:
        """A plane seen at rest on the pad. The pad's normal is the mean of the rest's
        R_world_body n_body over its last ``rest_window_us`` but the last ``rest_guard_us``
        (a rest is called over a window of readings, so it is still called in the lift-off's
        first moments, when the autopilot's attitude is already the air's)."""
        last = self._rest[-1][0] if self._rest else self._settled[-1][0] if self._settled else None
        if last is not None and time_us - last > self.rest_guard_us:
            # a new rest (landed elsewhere, or moved by hand)
            self._rest.clear()
            self._settled.clear()
            self._settled_sum = np.zeros(3)
        self._rest.append((time_us, R_world_body @ n_body))
        while self._rest and time_us - self._rest[0][0] >= self.rest_guard_us:
            t, v = self._rest.popleft()
            self._settled.append((t, v))
            self._settled_sum += v
        while self._settled and time_us - self._settled[0][0] > self.rest_window_us:
            self._settled_sum -= self._settled.popleft()[1]
        if self._settled:
            n = self._settled_sum / len(self._settled)
            self.n_pad = np.asarray(n / np.linalg.norm(n), dtype=np.float64)
        if position_m is not None:
            self.centre_m = np.array(position_m, dtype=np.float64)
            self.segment = segment

    def near(self, position_m: F64 | None, segment: object, radius_m: float) -> bool:
        """Whether the body is within ``radius_m`` (horizontally) of where it rested, in the
        same frame."""
        if self.n_pad is None or self.centre_m is None or position_m is None:
            return False
        if segment != self.segment:
            return False
        return bool(np.hypot(*(position_m[:2] - self.centre_m[:2])) <= radius_m)

    def sample(self, time_us: int, n_body: F64, R_world_body: F64) -> bool:
        """A plane seen over the pad (at rest or in the air): one sample of the autopilot's
        tilt error (refused when larger than ``max_error_rad``); returns whether it was
        kept."""
        if self.n_pad is None:
            return False
        e = R_world_body @ n_body - self.n_pad
        if float(np.linalg.norm(e)) > self.max_error_rad:
            self.refused += 1
            return False
        self._air.append((time_us, e))
        return True

    def down_body(self, time_us: int, R_world_body: F64) -> tuple[F64, float] | None:
        """Gravity (down, (3,) unit, body frame) at ``time_us`` for the autopilot's attitude
        ``R_world_body`` corrected by the samples of the last ``window_us``, and its sigma
        [rad]; None with fewer than ``min_samples`` of them."""
        while self._air and time_us - self._air[0][0] > self.window_us:
            self._air.popleft()
        if len(self._air) < self.min_samples:
            return None
        e = np.array([v for _, v in self._air])
        assert self.n_pad is not None  # samples are taken only once the pad is known
        m = self.n_pad + e.mean(axis=0)
        m /= np.linalg.norm(m)
        axis = np.cross(self.n_pad, m)
        angle = float(np.arctan2(np.linalg.norm(axis), float(self.n_pad @ m)))
        s = float(np.linalg.norm(axis))
        Q = so3.exp(axis / s * angle) if s > 1e-12 else np.eye(3)
        down: F64 = R_world_body.T @ (Q @ E_Z)
        scatter = float(np.sqrt(np.sum(e[:, :2].var(axis=0, ddof=1)) / 2.0 / len(e)))
        return down, max(scatter, self.sigma_floor_rad)
