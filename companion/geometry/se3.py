"""Rigid transforms T_a_b (4, 4) float64: p_a = T_a_b @ p_b (homogeneous).

exp/log follow the usual SE(3) parameterisation xi = (rho, omega) (6,), translation part first
(Barfoot, "State Estimation for Robotics", section 7.1.3).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from companion.errors import GeometryError
from companion.geometry import so3
from companion.types import F64

_I3 = np.eye(3)  # read only (below): arithmetic on them makes new arrays
_I4 = np.eye(4)
_E4 = np.array([0.0, 0.0, 0.0, 1.0])
for _constant in (_I3, _I4, _E4):
    _constant.flags.writeable = False


def make(R: ArrayLike, t: ArrayLike) -> F64:
    """Build T (4, 4) from R (3, 3) and t (3,)."""
    T = _I4.copy()
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def from_xyz_rpy(xyz_m: ArrayLike, rpy_rad: ArrayLike) -> F64:
    """T from a translation (3,) [m] and ZYX roll-pitch-yaw (3,) [rad]."""
    r = np.asarray(rpy_rad, dtype=np.float64)
    return make(so3.rpy_to_matrix(r[0], r[1], r[2]), xyz_m)


def from_quat(quat_wxyz: ArrayLike, t: ArrayLike) -> F64:
    """T from a Hamilton quaternion (w, x, y, z) and a translation (3,)."""
    return make(so3.quat_to_matrix(quat_wxyz), t)


def inverse(T: ArrayLike) -> F64:
    """Closed-form inverse of a rigid transform."""
    M = np.asarray(T, dtype=np.float64)
    R = M[:3, :3]
    return make(R.T, -R.T @ M[:3, 3])


def transform(T: ArrayLike, points: ArrayLike) -> F64:
    """Apply T (4, 4) to points (N, 3) or (3,); returns the same shape."""
    M = np.asarray(T, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    out = p @ M[:3, :3].T + M[:3, 3]
    return np.asarray(out, dtype=np.float64)


def is_rigid(T: ArrayLike, tol: float = 1e-9) -> bool:
    """True when T is a finite proper rigid transform."""
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        return False
    R = M[:3, :3]
    # np.allclose's test (|a - b| <= atol + 1e-5 |b|) written out: a tenth of its time
    return bool(
        np.all(np.abs(R.T @ R - _I3) <= tol + 1e-5 * _I3)
        and abs(np.linalg.det(R) - 1.0) < tol
        and np.all(np.abs(M[3] - _E4) <= tol + 1e-5 * _E4)
    )


def _left_jacobian(omega: F64) -> F64:
    theta = float(np.linalg.norm(omega))
    K = so3.hat(omega)
    if theta < 1e-8:
        J: F64 = _I3 + 0.5 * K + K @ K / 6.0
    else:
        a = (1 - np.cos(theta)) / theta**2
        b = (theta - np.sin(theta)) / theta**3
        J = _I3 + a * K + b * K @ K
    return J


def exp(xi: ArrayLike) -> F64:
    """Twist (6,) = (rho, omega) -> T (4, 4)."""
    v = np.asarray(xi, dtype=np.float64).reshape(6)
    rho, omega = v[:3], v[3:]
    return make(so3.exp(omega), _left_jacobian(omega) @ rho)


def log(T: ArrayLike) -> F64:
    """Inverse of :func:`exp`: T (4, 4) -> twist (6,)."""
    M = np.asarray(T, dtype=np.float64)
    if not is_rigid(M, tol=1e-6):
        raise GeometryError("log of a matrix that is not a rigid transform")
    omega = so3.log(M[:3, :3])
    rho = np.linalg.solve(_left_jacobian(omega), M[:3, 3])
    return np.concatenate([rho, omega])


def interpolate(T_a: ArrayLike, T_b: ArrayLike, alpha: float) -> F64:
    """Pose at fraction alpha in [0, 1] between T_a and T_b (rotation slerp, linear translation)."""
    A = np.asarray(T_a, dtype=np.float64)
    B = np.asarray(T_b, dtype=np.float64)
    dR = so3.exp(alpha * so3.log(A[:3, :3].T @ B[:3, :3]))
    return make(A[:3, :3] @ dR, (1 - alpha) * A[:3, 3] + alpha * B[:3, 3])
