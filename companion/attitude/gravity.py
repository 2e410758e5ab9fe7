"""Gravity in the VO frame from the accelerometer and our own metric motion.

The VO frame is gravity-aligned at initialisation and its local bundle adjustment keeps it so
with a prior on each keyframe's gravity direction. Taking that direction from the autopilot's
attitude makes our frame inherit the autopilot's tilt error, and an autopilot without GNSS
estimates its tilt only as well as its velocity aiding allows: PX4's EKF2 on SIH, aided by our
position alone, was 1.1-1.7 deg RMS off in tilt (docs/RESULTS.md). The accelerometer measures the
specific force f = R_body_world (a - g) in the body frame (FRD) [m/s^2]; over a window
[t0, t1] of T seconds, with the body rotation R_vo_body from the VO and the metric velocity
v(t) from our published positions,

    g_vo = (v(t1) - v(t0)) / T - mean_i(R_vo_body(t_i) f_i)          (1)

is gravity in the VO frame (a loosely coupled visual-inertial gravity estimate: the mean
acceleration over the window is the velocity change, so no double differentiation). Its
direction is what the BA's prior needs; any tilt of the VO frame is in R_vo_body and v alike,
so (1) measures the frame's tilt against true gravity. Measured in PX4 SIH squares (SCALED_IMU
at 50 Hz, our own rotations and positions): 0.55 deg RMS airborne with T = 4 s, against PX4's
own attitude's 1.1-1.7 deg (docs/decisions.md, "Gravity from the accelerometer").

How it is used (:func:`attitude_correction`): not as each keyframe's gravity on its own. The
window's estimate says where the VO frame's down is on average over seconds; a keyframe's own
gravity still needs the attitude at its instant (a prior tying the keyframe to its tracked
rotation instead let the lift-off's rotation errors stand: 7 deg of frame tilt in a PX4
square). What the window measures is the autopilot's slow tilt error: over the window, its
attitude seen through our VO rotation, d_i = R_vo_body(t_i) R_world_body(t_i)^T e_z, should
average to g_vo's direction; the rotation taking their mean onto it corrects the autopilot's
gravity at every keyframe (its fast part stays the autopilot's, its slow part is the
accelerometer's).

Uncertainty: the accelerometer's white noise (from its first differences) over the samples'
count, the two velocities' standard errors over T, both over |g|; plus a floor for what
neither shows (accelerometer bias and misalignment). Estimates whose |g_vo| is more than
``max_norm_error_m_s2`` from the standard gravity are refused (a wrong scale, a bad window).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.geometry import so3
from companion.types import F64

I64 = NDArray[np.int64]

STANDARD_GRAVITY_M_S2 = 9.80665


@dataclass(frozen=True, slots=True)
class GravityEstimate:
    """Gravity (down) in the VO frame over a window.

    down_vo: (3,) unit vector; sigma_rad: its direction's standard deviation [rad];
    norm_m_s2: |g_vo| [m/s^2]; n_imu: accelerometer samples used; t0_us, t1_us: the window.
    """

    down_vo: F64
    sigma_rad: float
    norm_m_s2: float
    n_imu: int
    t0_us: int
    t1_us: int


@dataclass(frozen=True, slots=True)
class AttitudeCorrection:
    """The autopilot's tilt error over a window, as a rotation of the VO frame.

    R_vo: (3, 3) rotation (VO frame) taking the attitude's mean down onto the measured one;
    angle_rad: its angle; sigma_rad: the corrected gravity's direction sigma (the measured
    one's and the attitude's scatter about its mean in the window, combined).
    """

    R_vo: F64
    angle_rad: float
    sigma_rad: float


def attitude_correction(
    down_vo: F64, sigma_rad: float, R_vo_body: F64, R_world_body: F64
) -> AttitudeCorrection | None:
    """The correction of the autopilot's gravity that the measured ``down_vo`` (3,) implies.

    R_vo_body (M, 3, 3): our rotations of the window's frames; R_world_body (M, 3, 3): the
    autopilot's attitudes at the same instants. d_i = R_vo_body_i R_world_body_i^T e_z is
    the autopilot's down in the VO frame; R_vo rotates their (normalised) mean onto down_vo
    about their common perpendicular. None for an empty window."""
    if len(R_vo_body) == 0:
        return None
    d = np.einsum("nij,nkj,k->ni", R_vo_body, R_world_body, np.array([0.0, 0.0, 1.0]))
    d_mean = d.mean(axis=0)
    d_mean = d_mean / np.linalg.norm(d_mean)
    scatter = float(np.sqrt(np.mean(np.sum(np.cross(d, d_mean) ** 2, axis=1))))
    axis = np.cross(d_mean, down_vo)
    s = float(np.linalg.norm(axis))
    angle = float(np.arctan2(s, float(d_mean @ down_vo)))
    R = np.eye(3) if s < 1e-12 else so3.exp(axis / s * angle)
    return AttitudeCorrection(R, angle, float(np.hypot(sigma_rad, scatter)))


def velocity_at(t_us: float, pose_time_us: I64, p_m: F64, half_span_us: float) -> tuple[F64, float]:
    """Velocity (3,) [m/s] at t_us: the slope of a straight-line fit of the positions
    ``p_m`` (M, 3) [m] at ``pose_time_us`` (M,) within +-half_span_us; and the slope's
    standard error [m/s] (from the fit's residuals, the mean over the axes). Raises
    ValueError with fewer than three positions in the span."""
    sel = np.abs(pose_time_us - t_us) <= half_span_us
    if int(sel.sum()) < 3:
        raise ValueError("fewer than three positions around the time")
    t = (pose_time_us[sel] - t_us) * 1e-6
    p = p_m[sel]
    tc = t - t.mean()
    stt = float(tc @ tc)
    if stt <= 0.0:
        raise ValueError("positions at one instant")
    slope = (tc @ (p - p.mean(axis=0))) / stt
    resid = p - p.mean(axis=0) - np.outer(tc, slope)
    dof = max(len(t) - 2, 1)
    sigma_p = float(np.sqrt(np.sum(resid**2) / (3 * dof)))
    return np.asarray(slope, dtype=np.float64), sigma_p / np.sqrt(stt)


def rotations_at(t_us: NDArray[Any], pose_time_us: I64, R_vo_body: F64) -> F64:
    """R_vo_body (N, 3, 3) at the times t_us (N,) within the poses' span: the element-wise
    linear interpolation of the neighbouring poses' rotations (between frames 33 ms apart the
    rotation is small; the average this feeds is insensitive to the second-order error)."""
    i = np.clip(np.searchsorted(pose_time_us, t_us), 1, len(pose_time_us) - 1)
    t0 = pose_time_us[i - 1].astype(np.float64)
    t1 = pose_time_us[i].astype(np.float64)
    a = np.clip((np.asarray(t_us, np.float64) - t0) / np.maximum(t1 - t0, 1.0), 0.0, 1.0)
    out: F64 = (1.0 - a)[:, None, None] * R_vo_body[i - 1] + a[:, None, None] * R_vo_body[i]
    return out


def gravity_from_motion(
    imu_time_us: I64,
    accel_frd_m_s2: F64,
    pose_time_us: I64,
    R_vo_body: F64,
    p_vo_m: F64,
    window_s: float,
    velocity_half_span_s: float = 0.1,
    sigma_floor_rad: float = np.radians(0.2),
    min_imu_hz: float = 20.0,
    max_norm_error_m_s2: float = 1.0,
) -> GravityEstimate | None:
    """Equation (1) over the last ``window_s`` seconds that the poses cover on both ends.

    imu_time_us (N,) and accel_frd_m_s2 (N, 3): accelerometer samples (specific force, body
    FRD [m/s^2]) in the poses' clock; pose_time_us (M,) increasing, R_vo_body (M, 3, 3) and
    p_vo_m (M, 3): the body's rotation and metric position [m] in the VO frame, all of one VO
    map. The window ends ``velocity_half_span_s`` before the last pose (its velocity needs
    poses on both sides). None when the poses do not cover the window, fewer than
    ``min_imu_hz`` accelerometer samples per second fall in it, or |g| is implausible.
    """
    if len(pose_time_us) < 3 or window_s <= 0:
        return None
    half_us = velocity_half_span_s * 1e6
    t1 = float(pose_time_us[-1]) - half_us
    t0 = t1 - window_s * 1e6
    if t0 - half_us < float(pose_time_us[0]):
        return None
    sel = (imu_time_us >= t0) & (imu_time_us < t1)
    n = int(sel.sum())
    if n < min_imu_hz * window_s or n < 3:
        return None
    try:
        v0, sv0 = velocity_at(t0, pose_time_us, p_vo_m, half_us)
        v1, sv1 = velocity_at(t1, pose_time_us, p_vo_m, half_us)
    except ValueError:
        return None
    f_body = accel_frd_m_s2[sel]
    R = rotations_at(imu_time_us[sel], pose_time_us, R_vo_body)
    f_vo = np.einsum("nij,nj->ni", R, f_body)
    T = (t1 - t0) * 1e-6
    g = (v1 - v0) / T - f_vo.mean(axis=0)
    norm = float(np.linalg.norm(g))
    if not np.isfinite(norm) or abs(norm - STANDARD_GRAVITY_M_S2) > max_norm_error_m_s2:
        return None
    # white noise per sample and axis from first differences (the motion between 20 ms
    # samples is far smaller than the noise); the mean's error is that over sqrt(n)
    d = np.diff(f_body, axis=0)
    sigma_f = float(np.sqrt(np.mean(d**2) / 2.0)) if len(d) else 0.0
    sigma_acc = np.hypot(sigma_f / np.sqrt(n), np.hypot(sv0, sv1) / T)
    sigma = float(np.hypot(sigma_acc / norm, sigma_floor_rad))
    return GravityEstimate(g / norm, sigma, norm, n, int(t0), int(t1))
