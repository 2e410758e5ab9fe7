"""The closed loops' missions: waypoints from the take-off point and the setpoints along a leg.

Positions NED [m] in the autopilot's local frame, velocities [m/s], times [s] since the leg's
start.
"""

from __future__ import annotations

import math

import numpy as np


def mission_path(name: str, start: np.ndarray, side_m: float) -> list[np.ndarray]:
    """Waypoints (NED) of a mission from ``start`` at its altitude: a square of side side_m
    (north, east, south, west, back), or a lawnmower of four 30 m legs 6 m apart and back."""
    if name == "square":
        offs = [(0, 0), (side_m, 0), (side_m, side_m), (0, side_m), (0, 0)]
    elif name == "lawnmower":
        offs = [(0, 0)]
        for k in range(4):
            e = 6.0 * k
            offs += [(30.0, e), (30.0, e + 6.0)] if k % 2 == 0 else [(0.0, e), (0.0, e + 6.0)]
        offs[-1] = (offs[-1][0], 18.0)
        offs += [(0.0, 18.0), (0.0, 0.0)]
    else:
        offs = [(0, 0)]
    return [start + np.array([n, e, 0.0]) for n, e in offs]


def leg_setpoints(
    a: np.ndarray, b: np.ndarray, speed: float, accel: float = 1.0
) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """(t, position, velocity) along a straight leg with a trapezoidal speed profile."""
    d = float(np.linalg.norm(b - a))
    if d < 1e-6:
        return []
    u = (b - a) / d
    v = min(speed, math.sqrt(accel * d))
    t_acc = v / accel
    d_acc = 0.5 * accel * t_acc**2
    t_cruise = (d - 2 * d_acc) / v
    total = 2 * t_acc + t_cruise
    out = []
    for t in np.arange(0.0, total + 1e-9, 0.05):
        if t < t_acc:
            s, sp = 0.5 * accel * t**2, accel * t
        elif t < t_acc + t_cruise:
            s, sp = d_acc + v * (t - t_acc), v
        else:
            tr = total - t
            s, sp = d - 0.5 * accel * tr**2, accel * tr
        out.append((float(t), a + u * s, u * sp))
    out.append((total, b.copy(), np.zeros(3)))
    return out
