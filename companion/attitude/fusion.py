"""Fusion of the drift-free range tilt with the VO rotation: a Kalman filter on the tilt error
of the VO frame (companion/geometry/kalman.py).

The VO frame is gravity-aligned at initialisation and then drifts slowly. We model the true
attitude as R_world_body = Rz(yaw_vo) exp([e_x, e_y, 0]) R_vo_body, with the VO frame's tilt
error e = (e_x, e_y) [rad] a random walk (variance q^2 dt per step, q from the options). A
tilt measurement gives gravity in the body, g_b; seen from the VO frame it is
m = R_vo_body g_b = exp(e)^T e_z, so e is the rotation taking m onto e_z:

    e = (m x e_z) / |m x e_z| * angle(m, e_z),    with m x e_z = (m_y, -m_x, 0).

Its covariance follows from the measurement's (roll, pitch) covariance through the Jacobian
(central differences). A measurement whose normalised innovation exceeds the chi-square gate
(2 dof) is rejected and counted. Successive measurements share the same cloud patch, so their
errors are correlated over about correlation_s; their covariance is inflated by
correlation_s / dt (dt the time since the last update), which keeps the filter from trusting
30 correlated samples a second as if they were independent. The published attitude keeps the
VO's smoothness (the VO rotation every frame) and the ranges' absence of drift (e); yaw is the
VO's.
"""

from __future__ import annotations

import numpy as np

from companion.attitude.ground import normal_from_tilt, tilt_from_normal
from companion.geometry import so3
from companion.geometry.kalman import RandomWalkKalman
from companion.types import F64


def tilt_error_of(roll_rad: float, pitch_rad: float, R_vo_body: F64) -> F64:
    """The VO frame's tilt error e (2,) [rad] that a measured (roll, pitch) implies."""
    m = R_vo_body @ normal_from_tilt(roll_rad, pitch_rad)
    v = np.array([m[1], -m[0]])
    s = float(np.linalg.norm(v))
    if s < 1e-15:
        return np.zeros(2)
    return np.asarray(v / s * np.arctan2(s, m[2]), dtype=np.float64)


def vo_tilt_cov_in_body(cov_rad2: F64, R_vo_body: F64) -> F64:
    """A (2, 2) covariance of a small tilt about the VO frame's x, y axes, expressed over the
    body's (roll, pitch): rotated by the body's yaw in the VO frame."""
    yaw = float(np.arctan2(R_vo_body[1, 0], R_vo_body[0, 0]))
    c, s = np.cos(yaw), np.sin(yaw)
    Rot = np.array([[c, s], [-s, c]])
    return np.asarray(Rot @ cov_rad2 @ Rot.T, dtype=np.float64)


def corrected_rotation(tilt_error: F64, R_vo_body: F64) -> F64:
    """R (3, 3) = exp([e_x, e_y, 0]) R_vo_body: the VO rotation with its tilt error removed."""
    return so3.exp(np.array([tilt_error[0], tilt_error[1], 0.0])) @ R_vo_body


class TiltFilter:
    """Two-state Kalman filter on the VO frame's tilt error."""

    def __init__(
        self,
        drift_rad_per_sqrt_s: float,
        init_sigma_rad: float,
        gate_chi2: float,
        correlation_s: float = 0.0,
    ):
        self.q = drift_rad_per_sqrt_s
        self.correlation_s = correlation_s
        self.init_sigma = init_sigma_rad
        self.gate = gate_chi2
        self.kf = RandomWalkKalman(2)
        self.accepted = 0
        self.rejected = 0
        self.reset(0)

    def reset(self, time_us: int) -> None:
        """Forget everything (a new VO frame): e = 0 with the initial sigma."""
        self.kf.x = np.zeros((2, 1))
        self.kf.P = np.eye(2) * self.init_sigma**2
        self.time_us = time_us
        self.last_update_us: dict[str, int] = {}

    @property
    def tilt_error(self) -> F64:
        return np.asarray(self.kf.x[:, 0], dtype=np.float64)

    @property
    def cov(self) -> F64:
        return np.asarray(self.kf.P, dtype=np.float64)

    def predict(self, time_us: int) -> None:
        """Random-walk prediction to ``time_us``."""
        dt = max(0.0, (time_us - self.time_us) * 1e-6)
        self.kf.predict(np.eye(2) * self.q**2 * dt)
        self.time_us = max(self.time_us, time_us)

    def update(
        self,
        time_us: int,
        roll_rad: float,
        pitch_rad: float,
        cov_rad2: F64,
        R_vo_body: F64,
        source: str = "ranges",
        correlation_s: float | None = None,
    ) -> bool:
        """Predict to ``time_us`` and fuse a measured (roll, pitch) with covariance (2, 2)
        from ``source`` (errors correlated over correlation_s, default the filter's); False
        when gated out or not finite."""
        if not (np.isfinite(roll_rad) and np.isfinite(pitch_rad) and np.all(np.isfinite(cov_rad2))):
            self.rejected += 1
            return False
        last = self.last_update_us.get(source)
        dt_s = 1.0 if last is None else (time_us - last) * 1e-6
        tau = self.correlation_s if correlation_s is None else correlation_s
        self.predict(time_us)
        z = tilt_error_of(roll_rad, pitch_rad, R_vo_body)
        J = np.empty((2, 2))
        h = 1e-6
        for j in range(2):
            d = np.zeros(2)
            d[j] = h
            J[:, j] = (
                tilt_error_of(roll_rad + d[0], pitch_rad + d[1], R_vo_body)
                - tilt_error_of(roll_rad - d[0], pitch_rad - d[1], R_vo_body)
            ) / (2 * h)
        # errors correlated over correlation_s carry less information than independent ones
        inflation = max(1.0, tau / max(dt_s, 1e-3))
        R = J @ cov_rad2 @ J.T * inflation + np.eye(2) * 1e-12
        y = z - self.tilt_error
        S = self.kf.P + R
        if float(y @ np.linalg.solve(S, y)) > self.gate:
            self.rejected += 1
            return False
        self.kf.update(z.reshape(2, 1), R)
        self.last_update_us[source] = time_us
        self.accepted += 1
        return True

    def attitude(self, R_vo_body: F64) -> tuple[float, float, F64]:
        """Corrected (roll, pitch) [rad] of the body and their covariance (2, 2) [rad^2]."""
        R = corrected_rotation(self.tilt_error, R_vo_body)
        roll, pitch = tilt_from_normal(R.T @ np.array([0.0, 0.0, 1.0]))
        # e is a rotation in the VO frame: in body (roll, pitch) axes it turns by the yaw
        return roll, pitch, vo_tilt_cov_in_body(self.cov, R_vo_body)
