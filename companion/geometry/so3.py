"""Rotations: SO(3) exponential/logarithm, Hamilton quaternions (wxyz), roll-pitch-yaw.

All rotations are (3, 3) float64 matrices R_a_b (maps vectors from frame b to frame a).
Quaternions are Hamilton, scalar first: ``quat_wxyz`` (PX4 / MAVLink order).
Roll-pitch-yaw are aerospace ZYX angles: R = Rz(yaw) @ Ry(pitch) @ Rx(roll) [rad].
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from companion.errors import GeometryError
from companion.types import F64

_SMALL = 1e-10
_I3 = np.eye(3)  # read only: arithmetic on it makes new arrays
_I3.flags.writeable = False


def hat(omega: ArrayLike) -> F64:
    """Skew-symmetric matrix [w]_x (3, 3) with hat(w) @ v == cross(w, v)."""
    w = np.asarray(omega, dtype=np.float64)
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def exp(omega: ArrayLike) -> F64:
    """Rodrigues' formula: rotation vector (3,) [rad] -> R (3, 3)."""
    w = np.asarray(omega, dtype=np.float64)
    theta = float(np.linalg.norm(w))
    K = hat(w)
    if theta < _SMALL:
        R: F64 = _I3 + K + 0.5 * K @ K
    else:
        R = _I3 + (np.sin(theta) / theta) * K + ((1 - np.cos(theta)) / theta**2) * K @ K
    return R


def log(R: ArrayLike) -> F64:
    """Inverse of :func:`exp`: R (3, 3) -> rotation vector (3,) [rad], angle in [0, pi]."""
    return quat_to_rotvec(matrix_to_quat(R))


def quat_to_rotvec(quat_wxyz: ArrayLike) -> F64:
    """Unit quaternion (4,) -> rotation vector (3,) with angle in [0, pi]."""
    q = normalize_quat(quat_wxyz)
    if q[0] < 0:
        q = -q
    v = q[1:]
    s = float(np.linalg.norm(v))
    if s < _SMALL:
        return 2.0 * v
    angle = 2.0 * np.arctan2(s, q[0])
    return np.asarray(v * (angle / s), dtype=np.float64)


def normalize_quat(quat_wxyz: ArrayLike) -> F64:
    """Return the unit quaternion (4,); raises GeometryError for zero or non-finite input."""
    q = np.asarray(quat_wxyz, dtype=np.float64).reshape(4)
    n = float(np.linalg.norm(q))
    if not np.isfinite(n) or n < _SMALL:
        raise GeometryError(f"quaternion must be finite and non-zero, got {q}")
    return q / n


def quat_to_matrix(quat_wxyz: ArrayLike) -> F64:
    """Hamilton quaternion (w, x, y, z) -> R (3, 3)."""
    w, x, y, z = normalize_quat(quat_wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(R: ArrayLike) -> F64:
    """R (3, 3) -> unit Hamilton quaternion (w, x, y, z) with w >= 0 (Shepperd's method)."""
    M = np.asarray(R, dtype=np.float64)
    if M.shape != (3, 3) or not np.all(np.isfinite(M)):
        raise GeometryError("rotation matrix must be a finite (3, 3) array")
    tr = M[0, 0] + M[1, 1] + M[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array(
            [0.25 * s, (M[2, 1] - M[1, 2]) / s, (M[0, 2] - M[2, 0]) / s, (M[1, 0] - M[0, 1]) / s]
        )
    elif M[0, 0] > M[1, 1] and M[0, 0] > M[2, 2]:
        s = 2.0 * np.sqrt(1.0 + M[0, 0] - M[1, 1] - M[2, 2])
        q = np.array(
            [(M[2, 1] - M[1, 2]) / s, 0.25 * s, (M[0, 1] + M[1, 0]) / s, (M[0, 2] + M[2, 0]) / s]
        )
    elif M[1, 1] > M[2, 2]:
        s = 2.0 * np.sqrt(1.0 + M[1, 1] - M[0, 0] - M[2, 2])
        q = np.array(
            [(M[0, 2] - M[2, 0]) / s, (M[0, 1] + M[1, 0]) / s, 0.25 * s, (M[1, 2] + M[2, 1]) / s]
        )
    else:
        s = 2.0 * np.sqrt(1.0 + M[2, 2] - M[0, 0] - M[1, 1])
        q = np.array(
            [(M[1, 0] - M[0, 1]) / s, (M[0, 2] + M[2, 0]) / s, (M[1, 2] + M[2, 1]) / s, 0.25 * s]
        )
    q_unit: F64 = q / np.linalg.norm(q)
    return q_unit if q_unit[0] >= 0 else -q_unit


def quat_wxyz_to_xyzw(quat_wxyz: ArrayLike) -> F64:
    """Reorder (w, x, y, z) -> (x, y, z, w), as scipy's Rotation and the TUM format want."""
    q = np.asarray(quat_wxyz, dtype=np.float64)
    return np.asarray(q[..., [1, 2, 3, 0]], dtype=np.float64)


def quat_xyzw_to_wxyz(quat_xyzw: ArrayLike) -> F64:
    """Reorder (x, y, z, w) -> (w, x, y, z)."""
    q = np.asarray(quat_xyzw, dtype=np.float64)
    return np.asarray(q[..., [3, 0, 1, 2]], dtype=np.float64)


def rot_x(angle_rad: float) -> F64:
    """Rotation about +x by angle_rad."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> F64:
    """Rotation about +y by angle_rad."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> F64:
    """Rotation about +z by angle_rad."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rpy_to_matrix(roll_rad: float, pitch_rad: float, yaw_rad: float) -> F64:
    """Aerospace ZYX Euler angles -> R = Rz(yaw) Ry(pitch) Rx(roll)."""
    return rot_z(yaw_rad) @ rot_y(pitch_rad) @ rot_x(roll_rad)


def rpy_to_matrices(roll_rad: ArrayLike, pitch_rad: ArrayLike, yaw_rad: ArrayLike) -> F64:
    """(N, 3, 3) :func:`rpy_to_matrix` of N angle triples (each (N,)), in closed form."""
    r, p, y = (np.asarray(a, dtype=np.float64) for a in (roll_rad, pitch_rad, yaw_rad))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], axis=-1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], axis=-1),
            np.stack([-sp, cp * sr, cp * cr], axis=-1),
        ],
        axis=-2,
    )


def matrix_to_rpy(R: ArrayLike) -> tuple[float, float, float]:
    """Inverse of :func:`rpy_to_matrix`: (roll_rad, pitch_rad, yaw_rad), pitch in [-pi/2, pi/2]."""
    M = np.asarray(R, dtype=np.float64)
    pitch = float(np.arcsin(np.clip(-M[2, 0], -1.0, 1.0)))
    roll = float(np.arctan2(M[2, 1], M[2, 2]))
    yaw = float(np.arctan2(M[1, 0], M[0, 0]))
    return roll, pitch, yaw


def angle_between(R_a: ArrayLike, R_b: ArrayLike) -> float:
    """Geodesic angle [rad] between two rotations."""
    R = np.asarray(R_a, dtype=np.float64).T @ np.asarray(R_b, dtype=np.float64)
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def mean(Rs: Sequence[F64]) -> F64:
    """(3, 3) the mean of rotations (each (3, 3), the same frames): the first times exp of the
    mean of their rotation vectors from it. For rotations within a degree of each other (a
    hover's attitudes) this is the chordal L2 mean to ~1e-5 rad (Hartley et al., "Rotation
    Averaging", IJCV 2013, section 5)."""
    R0 = np.asarray(Rs[0], dtype=np.float64)
    omega = np.mean([log(R0.T @ R) for R in Rs], axis=0)
    return np.asarray(R0 @ exp(omega), dtype=np.float64)
