"""Synthetic flights for the frame alignment and the GPS handover tests (seeded).

A path is our pose in our own frame (NED [m], yaw [rad]) at 30 Hz; the reference is the same
path in the autopilot's frame through a known :class:`FrameAlignment`, with GPS-like noise:
a first-order Gauss-Markov process (sigma, time constant) per axis, as a receiver's errors are
correlated over seconds, plus a little white noise. The autopilot's heading is ours turned by the
alignment's yaw, each with its own white noise (and an optional bias: a declination error).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from companion.frames.alignment import FrameAlignment, PairWindow, wrap_rad

RATE_HZ = 30.0
GPS_EVERY = 6  # one GPS fix every 6 samples: 5 Hz
TRUE_ALIGNMENT = FrameAlignment(math.radians(37.0), np.array([5.0, -3.0, 0.4]))


@dataclass(frozen=True, slots=True)
class Path:
    """time_us (N,); position_ned_m (N, 3); yaw_rad (N,) the heading of travel."""

    time_us: np.ndarray
    position_ned_m: np.ndarray
    yaw_rad: np.ndarray


def _path(points: np.ndarray, yaw: np.ndarray) -> Path:
    t = (np.arange(len(points)) * 1e6 / RATE_HZ).astype(np.int64)
    return Path(t, points, yaw)


def lawnmower(
    legs: int = 5, leg_m: float = 20.0, spacing_m: float = 5.0, speed_m_s: float = 2.0
) -> Path:
    """Legs north and south, stepping east between them, at 5 m altitude (z = -5)."""
    corners = [np.array([0.0, 0.0])]
    for i in range(legs):
        north = leg_m if i % 2 == 0 else 0.0
        corners.append(np.array([north, corners[-1][1]]))
        if i < legs - 1:
            corners.append(np.array([north, corners[-1][1] + spacing_m]))
    step = speed_m_s / RATE_HZ
    pts, yaws = [], []
    for a, b in itertools.pairwise(corners):
        n = max(1, int(round(np.linalg.norm(b - a) / step)))
        heading = math.atan2(b[1] - a[1], b[0] - a[0])
        for k in range(n):
            pts.append(a + (b - a) * k / n)
            yaws.append(heading)
    xy = np.array(pts)
    return _path(np.column_stack([xy, np.full(len(xy), -5.0)]), np.array(yaws))


def hover(seconds: float, at_ned_m: tuple[float, float, float] = (3.0, 4.0, -5.0)) -> Path:
    """Standing still at ``at_ned_m`` heading 20 deg."""
    n = int(seconds * RATE_HZ)
    return _path(np.tile(np.array(at_ned_m), (n, 1)), np.full(n, math.radians(20.0)))


def markov(n: int, sigma: float, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) first-order Gauss-Markov noise at RATE_HZ: stationary sigma, time constant tau_s."""
    phi = math.exp(-1.0 / (RATE_HZ * tau_s))
    e = rng.normal(0.0, sigma * math.sqrt(1.0 - phi * phi), (n, 3))
    out = np.empty((n, 3))
    out[0] = rng.normal(0.0, sigma, 3)
    for k in range(1, n):
        out[k] = phi * out[k - 1] + e[k]
    return out


@dataclass(frozen=True, slots=True)
class Flight:
    """Ours and the reference at every sample (the reference is used every GPS_EVERY-th)."""

    path: Path
    ours_ned_m: np.ndarray
    our_yaw_rad: np.ndarray
    ref_ned_m: np.ndarray
    ref_yaw_rad: np.ndarray

    def gps_pairs(self) -> PairWindow:
        """The pairs at the GPS fixes (ours already at the fix's instant)."""
        k = np.arange(0, len(self.path.time_us), GPS_EVERY)
        return PairWindow(
            self.path.time_us[k],
            self.ours_ned_m[k],
            self.ref_ned_m[k],
            self.our_yaw_rad[k],
            self.ref_yaw_rad[k],
            np.zeros(len(k), dtype=np.int64),
        )


def fly(
    path: Path,
    seed: int,
    truth: FrameAlignment = TRUE_ALIGNMENT,
    gps_sigma_m: float = 0.3,
    tau_s: float = 1.0,
    heading_sigma_deg: float = 1.0,
    heading_bias_deg: float = 0.0,
) -> Flight:
    """Our track (the path, with 1 cm of our own noise) and the GPS-like reference."""
    rng = np.random.default_rng(seed)
    n = len(path.time_us)
    ours = path.position_ned_m + rng.normal(0.0, 0.01, (n, 3))
    ref = truth.apply_points(path.position_ned_m) + markov(n, gps_sigma_m, tau_s, rng)
    ref += rng.normal(0.0, 0.05, (n, 3))
    sd = math.radians(heading_sigma_deg)
    our_yaw = path.yaw_rad + rng.normal(0.0, sd, n)
    ref_yaw = path.yaw_rad + truth.yaw_rad + math.radians(heading_bias_deg)
    ref_yaw = np.array([wrap_rad(y) for y in ref_yaw + rng.normal(0.0, sd, n)])
    return Flight(path, ours, our_yaw, ref, ref_yaw)
