"""The terrain under the hit points, from the scaled VO point cloud (pure).

Over irregular ground the plane through the hit points is itself tilted, and the ranges then
give the body's tilt relative to that plane, not to gravity (the thesis's bias, its figure
6.2). The VO map points live in the gravity-aligned VO frame (z down); scaled by the metric
scale s they are a metric sample of the terrain. Around each hit point we fit a local surface
to the map points, weighted by a Gaussian of their horizontal distance (local regression:
quadratic z = a + b dx + c dy + d dx^2 + e dx dy + f dy^2 when there are enough points, a plane
otherwise) and read the terrain height a under the hit. The K points (x_k, y_k, a_k) give the
terrain's own downward normal n_vo; the compensated gravity direction in the body is

    g_b = R_vo_body^T  R(n_vo -> e_z)  R_vo_body  n_b

where n_b is the range plane's normal in the body and R(n_vo -> e_z) the smallest rotation
taking the terrain normal to the vertical (R_vo_body enters only through the small terrain
rotation, so its error matters to second order).

A hit whose height disagrees with the surface fitted around it (a wall edge, a box corner,
a beam through foliage) or a patch too rough to trust is refused, with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.attitude.ground import normal_of, plane_fit, tilt_jacobian
from companion.geometry import so3
from companion.types import F64

E_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True, slots=True)
class Patch:
    """The surface fitted around one hit point: height (VO frame z, metres) under the hit,
    its standard deviation, the RMS of the fit residuals [m] and the number of points."""

    height_m: float
    sigma_m: float
    rms_m: float
    n_points: int


def surfaces_under(
    points_m: F64, xy_m: F64, radius_m: float, min_points: int
) -> list[Patch | None]:
    """Local weighted regressions of the terrain height at each of xy_m (K, 2) from points_m
    (N, 3) (metric, gravity-aligned, z down), using the points within 2 radius_m of each;
    None for a hit with fewer than min_points there or a singular fit. Batched over the K
    hits (one set of array operations for all)."""
    K = len(xy_m)
    reach = 2.0 * radius_m  # only the points near some hit matter: drop the rest first
    lo, hi = xy_m.min(axis=0) - reach, xy_m.max(axis=0) + reach
    keep = np.all((points_m[:, :2] >= lo) & (points_m[:, :2] <= hi), axis=1)
    points_m = points_m[keep]
    dxy = points_m[None, :, :2] - xy_m[:, None, :]  # (K, N, 2)
    d2 = np.einsum("knj,knj->kn", dxy, dxy)
    near = d2 < (2.0 * radius_m) ** 2
    counts = near.sum(axis=1)
    w = np.where(near, np.exp(-0.5 * d2 / radius_m**2), 0.0)  # (K, N)
    dx, dy = dxy[..., 0], dxy[..., 1]
    quad = (counts >= 12)[:, None]  # a quadratic needs the points; else a plane
    zero = np.zeros_like(dx)
    A = np.stack(
        [
            np.ones_like(dx),
            dx,
            dy,
            np.where(quad, dx * dx, zero),
            np.where(quad, dx * dy, zero),
            np.where(quad, dy * dy, zero),
        ],
        axis=-1,
    )  # (K, N, 6)
    AtW = np.swapaxes(A, 1, 2) * w[:, None, :]  # (K, 6, N)
    normal = AtW @ A
    normal[~quad[:, 0], 3:, 3:] += np.eye(3)  # plane fits: the quadratic terms stay zero
    out: list[Patch | None] = [None] * K
    ok = counts >= min_points
    if not ok.any():
        return out
    try:
        N_inv = np.linalg.inv(normal[ok])
    except np.linalg.LinAlgError:
        return out
    z = points_m[:, 2]
    for j, k in enumerate(np.flatnonzero(ok)):
        coef = N_inv[j] @ (AtW[k] @ z)
        resid = (z - A[k] @ coef)[near[k]]
        wk = w[k, near[k]]
        n_par = 6 if quad[k, 0] else 3
        n = int(counts[k])
        var = float(np.sum(wk * resid**2) / np.sum(wk) * n / max(n - n_par, 1))
        # sigma of the intercept for weights that are not inverse variances (sandwich form)
        var_a = float(N_inv[j, 0] @ ((AtW[k] * w[k]) @ A[k]) @ N_inv[j, :, 0]) * var
        if np.all(np.isfinite(coef)) and np.isfinite(var_a):
            out[k] = Patch(float(coef[0]), float(np.sqrt(max(var_a, 0.0))), np.sqrt(var), n)
    return out


def rotation_to_vertical(normal: F64) -> F64:
    """The smallest rotation (3, 3) that maps the unit vector ``normal`` onto e_z."""
    axis = np.array([normal[1], -normal[0], 0.0])  # normal x e_z
    s = float(np.hypot(normal[0], normal[1]))
    angle = float(np.arctan2(s, float(normal @ E_Z)))
    if s < 1e-12:
        return np.eye(3)
    return so3.exp(axis / s * angle)


def compensate(normal_body: F64, terrain_normal_vo: F64, R_vo_body: F64) -> F64:
    """Gravity in the body frame (3,) from the range plane's normal and the terrain's own
    normal in the VO frame (module docstring)."""
    R_d = rotation_to_vertical(terrain_normal_vo)
    g = R_vo_body.T @ (R_d @ (R_vo_body @ normal_body))
    return np.asarray(g / np.linalg.norm(g), dtype=np.float64)


def terrain_tilt_cov(xy_m: F64, heights_m: F64, sigma_m: F64) -> tuple[F64, F64]:
    """Downward normal (3,) of the terrain through the points (xy_m (K, 2), heights_m (K,))
    and the covariance (2, 2) [rad^2] of its (roll, pitch) from the height sigmas (K,)."""
    pts = np.column_stack([xy_m, heights_m])
    var = np.maximum(sigma_m, 1e-4) ** 2
    coef, M = plane_fit(pts, 1.0 / var)
    b, c = float(coef[1]), float(coef[2])
    J = tilt_jacobian(b, c) @ M[1:3]
    return normal_of(b, c), (J * var) @ J.T
