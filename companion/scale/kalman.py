"""MSCwK: the scale as a Gaussian random walk, updated by scale measurements.

State x = s [m per VO unit]; prediction over dt adds variance (q * s)^2 * dt (a relative
random walk, to follow the VO's scale drift); a measurement z with sigma r updates it unless
its normalised innovation y^2 / S exceeds the chi-square gate (1 degree of freedom; 6.63 is
the 99 % quantile), which rejects outliers such as a 10x wrong match.

The gate has a blind spot: when the VO's unit changes faster than the random walk allows (its
map rebuilt through a ground that moves under the camera, a local BA that rescales it), every
later measurement is gated out, and the filter's variance grows back by the random walk alone:
a 40 % step takes ~4 minutes of (1 %/sqrt(s))^2 to come within the gate, all that time at the
old scale. With ``recover_s`` > 0 the filter restarts at the median of the gated-out
measurements once nothing has passed the gate for that long and those of the last
``recover_s`` (at least RECOVER_MIN) agree: 90 % of them within ``recover_spread`` of their
median (relative): then they are usually what is right, not outliers (not always: on a real
camera they also agreed on a wrong scale, hence off by default). Measured on 2026-12-01: in ideal
60 s flights (hills lawnmower, urban figure8, urban lawnmower, seed 1) the longest run of
gated-out measurements was 0.23 s; the ground-up table's urban lawnmower at 12 m/s, 4 m over
the roofs, held M-MSCwK outside its gate for 37 s (docs/methods.md, "MSCwK").
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

from companion.geometry.kalman import RandomWalkKalman

log = logging.getLogger(__name__)
RECOVER_MIN = 10  # gated-out measurements in the last recover_s needed for a restart


class ScaleKalman:
    """Scalar Kalman filter on the metric scale."""

    def __init__(
        self,
        random_walk_per_s: float,
        gate_chi2: float,
        recover_s: float = 0.0,
        recover_spread: float = 0.1,
    ) -> None:
        self.q = random_walk_per_s
        self.gate = gate_chi2
        self.recover_us = int(recover_s * 1e6)
        self.recover_spread = recover_spread
        self.kf = RandomWalkKalman(1)
        self.initialized = False
        self.time_us = 0
        self.accepted = 0
        self.rejected = 0
        self.recoveries = 0  # restarts at the gated-out measurements (recover_s)
        self._gated_since_us: int | None = None  # the first gated-out since the last accepted
        self._gated: deque[tuple[int, float, float]] = deque()  # the last recover_s: t, z, sigma
        self._last_gated_us = 0

    @property
    def scale(self) -> float:
        return float(self.kf.x[0, 0])

    @property
    def sigma(self) -> float:
        return float(np.sqrt(self.kf.P[0, 0]))

    @property
    def outside_gate_s(self) -> float:
        """How long every measurement has been gated out [s]: from the first of the current
        run to its last; 0 when the last measurement passed (a status shows it: a filter held
        at an old scale)."""
        if self._gated_since_us is None:
            return 0.0
        return (self._last_gated_us - self._gated_since_us) * 1e-6

    def initialize(self, time_us: int, scale: float, sigma: float) -> None:
        """Start at ``scale`` with standard deviation ``sigma``."""
        self.kf.x = np.array([[scale]])
        self.kf.P = np.array([[sigma**2]])
        self.time_us = time_us
        self.initialized = True
        self._gated_since_us = None
        self._gated.clear()

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
            if self._gated_since_us is None:
                self._gated_since_us = time_us
            self._last_gated_us = time_us
            return self._recover(time_us, z, sigma)
        self.kf.update(np.array([[z]]), np.array([[sigma**2]]))
        self.accepted += 1
        self._gated_since_us = None
        self._gated.clear()
        return True

    def _recover(self, time_us: int, z: float, sigma: float) -> bool:
        """A gated-out measurement: True when it completes ``recover_s`` of nothing but
        gated-out measurements and those of the last ``recover_s`` agree (the filter then
        restarts at their median, sigma their spread or their median sigma over sqrt(n),
        whichever is larger); else False."""
        if self.recover_us <= 0 or self._gated_since_us is None:
            return False
        gated = self._gated
        gated.append((time_us, z, sigma))
        while time_us - gated[0][0] > self.recover_us:
            gated.popleft()
        if time_us - self._gated_since_us < self.recover_us or len(gated) < RECOVER_MIN:
            return False
        zs = np.array([g[1] for g in gated])
        median = float(np.median(zs))
        spread = float(np.quantile(np.abs(zs - median), 0.9))
        if spread > self.recover_spread * median:
            return False  # they disagree: outliers, not a new scale
        n = len(zs)
        sigma0 = max(spread, float(np.median([g[2] for g in gated])) / np.sqrt(n))
        was = self.scale
        held_s = (time_us - self._gated_since_us) * 1e-6
        self.initialize(time_us, median, sigma0)
        self.recoveries += 1
        log.warning(
            "scale filter: %.1f s of measurements outside its gate agree on %.4f (it held %.4f); "
            "restarted there",
            held_s,
            median,
            was,
        )
        return True
