"""Ground plane and body tilt from three or more distance readings (pure).

A sensor k with pose T_body_rf[k] measures range d_k along its beam u_k (+z of its frame), so
its ground point in the body frame (FRD, metres) is p_k = o_k + d_k u_k. The ground plane
through the points, written z = a + b x + c y in the body frame (the readings' errors are along
the beams, which are close to body z), has the downward unit normal
n = (-b, -c, 1) / |(-b, -c, 1)|. Over a level plane n is gravity in the body frame,
g_b = R_world_body^T e_z = (-sin(theta), sin(phi) cos(theta), cos(phi) cos(theta)) for ZYX
roll phi and pitch theta (docs/methods.md), hence

    phi = atan2(n_y, n_z),    theta = atan2(-n_x, sqrt(n_y^2 + n_z^2)).

The covariance of (phi, theta) is J diag(sigma_k^2) J^T with J = d(phi, theta)/d(d_k): the fit
is linear in the heights, and a reading moves its point along the beam (height change
u_z dd; the horizontal change, sin of the beam tilt, is neglected). For two sensors L apart over a
level plane the single-sample sigma of the angle about the axis between them is
sigma * sqrt(2) / L (the thesis's bound).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.errors import GeometryError
from companion.types import F64


def beams_body(T_body_rf: F64) -> tuple[F64, F64]:
    """Origins (K, 3) and unit beam directions (K, 3) in the body frame from (K, 4, 4) mounts."""
    return T_body_rf[:, :3, 3].copy(), T_body_rf[:, :3, 2].copy()


def ground_points_body(origins: F64, beams: F64, range_m: F64) -> F64:
    """Ground points (K, 3) [m] in the body frame of readings range_m (K,)."""
    return origins + range_m[:, None] * beams


def plane_fit(points: F64, weights: F64 | None = None) -> tuple[F64, F64]:
    """Weighted least-squares plane z = a + b x + c y through points (K >= 3, 3).

    Returns (a, b, c) and the (3, K) matrix M with (a, b, c) = M z (the fit is linear in the
    heights, so M is also the Jacobian of the coefficients with respect to them)."""
    A = np.column_stack([np.ones(len(points)), points[:, 0], points[:, 1]])
    w = np.ones(len(points)) if weights is None else weights
    AtW = A.T * w
    M = np.asarray(np.linalg.solve(AtW @ A, AtW), dtype=np.float64)
    return M @ points[:, 2], M


def normal_of(b: float, c: float) -> F64:
    """Downward unit normal (3,) of the plane z = a + b x + c y."""
    n = np.array([-b, -c, 1.0])
    return np.asarray(n / np.sqrt(1.0 + b * b + c * c), dtype=np.float64)


def plane_normal(points: F64, weights: F64 | None = None) -> F64:
    """Downward unit normal (3,) of the weighted least-squares plane through points (K, 3)."""
    coef, _ = plane_fit(points, weights)
    return normal_of(float(coef[1]), float(coef[2]))


def tilt_jacobian(b: float, c: float) -> F64:
    """d(roll, pitch)/d(b, c) (2, 2) for the plane z = a + b x + c y, where
    roll = -atan(c) and pitch = atan2(b, sqrt(1 + c^2)) (from :func:`tilt_from_normal`)."""
    q = 1.0 + c * c
    r = q + b * b
    return np.array([[0.0, -1.0 / q], [np.sqrt(q) / r, -b * c / (r * np.sqrt(q))]])


def tilt_from_normal(normal: F64) -> tuple[float, float]:
    """(roll, pitch) [rad] of a body whose gravity (or ground normal) direction is ``normal``."""
    nx, ny, nz = (float(v) for v in normal)
    return float(np.arctan2(ny, nz)), float(np.arctan2(-nx, np.hypot(ny, nz)))


def normal_from_tilt(roll_rad: float, pitch_rad: float) -> F64:
    """The inverse of :func:`tilt_from_normal`: R_world_body^T e_z for ZYX roll and pitch."""
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    return np.array([-sp, sr * cp, cr * cp])


def spread_m(points: F64) -> float:
    """How far (K, 3) points are from being collinear [m]: the second singular value of their
    centred horizontal (x, y) coordinates, divided by sqrt(K)."""
    xy = points[:, :2] - points[:, :2].mean(axis=0)
    s = np.linalg.svd(xy, compute_uv=False)
    return float(s[1] / np.sqrt(len(points))) if len(s) > 1 else 0.0


@dataclass(frozen=True, slots=True)
class RangeTilt:
    """Roll/pitch of the body relative to the plane through the hit points.

    normal_body: (3,) downward unit normal; points_body: (K, 3) [m]; cov_rad2: (2, 2) over
    (roll, pitch); sensor_ids: (K,) in the order of the points.
    """

    roll_rad: float
    pitch_rad: float
    cov_rad2: F64
    normal_body: F64
    points_body: F64
    sensor_ids: tuple[int, ...]


def tilt_from_ranges(
    origins: F64,
    beams: F64,
    range_m: F64,
    sigma_m: F64,
    sensor_ids: tuple[int, ...],
    min_spread_m: float,
) -> RangeTilt:
    """Tilt of the body relative to the ground plane through K >= 3 hit points.

    origins, beams: (K, 3) body frame; range_m, sigma_m: (K,) [m]. Raises GeometryError when
    fewer than three readings are given or the hit points are (nearly) collinear."""
    if len(range_m) < 3:
        raise GeometryError(f"{len(range_m)} valid readings, 3 needed")
    points = ground_points_body(origins, beams, range_m)
    spread = spread_m(points)
    if spread < min_spread_m:
        raise GeometryError(f"hit points are collinear (spread {spread:.3f} m)")
    coef, M = plane_fit(points, 1.0 / sigma_m**2)
    normal = normal_of(float(coef[1]), float(coef[2]))
    roll, pitch = tilt_from_normal(normal)
    # a reading moves its point along the beam; the fit sees the change of its height
    J = tilt_jacobian(float(coef[1]), float(coef[2])) @ M[1:3] * beams[:, 2]
    cov = (J * sigma_m**2) @ J.T
    return RangeTilt(roll, pitch, cov, normal, points, sensor_ids)
