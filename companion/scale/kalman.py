"""MSCwK: the scale as a Gaussian random walk, updated by scale measurements.

State x = s [m per VO unit]; prediction over dt adds variance (q * s)^2 * dt (a relative
random walk, to follow the VO's scale drift); a measurement z with sigma r updates it unless
its normalised innovation y^2 / S exceeds the chi-square gate (1 degree of freedom; 6.63 is
the 99 % quantile), which rejects outliers such as a 10x wrong match.
"""

from __future__ import annotations

import numpy as np

from companion.geometry.kalman import RandomWalkKalman


class ScaleKalman:
    """Scalar Kalman filter on the metric scale."""

    def __init__(self, random_walk_per_s: float, gate_chi2: float) -> None:
        self.q = random_walk_per_s
        self.gate = gate_chi2
        self.kf = RandomWalkKalman(1)
        self.initialized = False
        self.time_us = 0
        self.accepted = 0
        self.rejected = 0

    @property
    def scale(self) -> float:
        return float(self.kf.x[0, 0])

    @property
    def sigma(self) -> float:
        return float(np.sqrt(self.kf.P[0, 0]))

    def initialize(self, time_us: int, scale: float, sigma: float) -> None:
        """Start at ``scale`` with standard deviation ``sigma``."""
        self.kf.x = np.array([[scale]])
        self.kf.P = np.array([[sigma**2]])
        self.time_us = time_us
        self.initialized = True

    def predict(self, time_us: int) -> None:
        """Random-walk prediction to ``time_us``."""
        dt = max(0.0, (time_us - self.time_us) * 1e-6)
        self.kf.predict(np.array([[(self.q * self.scale) ** 2 * dt]]))
        self.time_us = max(self.time_us, time_us)

    def update(self, time_us: int, z: float, sigma: float) -> bool:
        """Predict to ``time_us`` and fuse a measurement; False when gated out (or invalid)."""
        if not (np.isfinite(z) and np.isfinite(sigma) and sigma > 0 and z > 0):
            self.rejected += 1
            return False
        if not self.initialized:
            self.initialize(time_us, z, sigma)
            self.accepted += 1
            return True
        self.predict(time_us)
        S = self.kf.P[0, 0] + sigma**2
        y = z - self.scale
        if y * y / S > self.gate:
            self.rejected += 1
            return False
        self.kf.update(np.array([[z]]), np.array([[sigma**2]]))
        self.accepted += 1
        return True
