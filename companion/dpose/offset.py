"""The offset that moves the VO's published position onto d-Pose's (pure; issue 18).

The published position is p_pub = p_vo + offset (3,) [m], both in the published (NED) frame.
Each d-Pose position p_dp with its sigma s_dp [m] measures the offset as p_dp - p_vo. The
offset's own sigma s grows between d-Pose poses with the VO's drift,

    s <- s + drift_per_m * path + drift_m_per_s * dt        (linear: a bias)

(path: the VO's path length since the last d-Pose pose, summed frame by frame: a square flown
back to the pad has its whole length, not its end-to-end distance)

and each measurement is taken with the scalar Kalman gain K = s^2 / (s^2 + s_dp^2) on every
axis (s^2 <- (1 - K) s^2). Back over the pad after a flight, s is tens of centimetres and
K ~ 1: the published position is d-Pose's at once. Hovering over the pad, K falls to a few
percent and the offset averages d-Pose's frame-to-frame noise (~1 cm at 3 m). A gap larger
than ``reset_m`` is taken whole and counted as a reset: the caller publishes it with a new
reset_counter, so that EKF2 re-anchors its vision frame instead of fusing a jump.
"""

from __future__ import annotations

import numpy as np

from companion.types import F64


class DposeOffset:
    """d-Pose minus VO [m], its sigma [m], and the resets it made.

    At arming the offset is zero by definition (the pattern is placed at the published pose)
    with sigma 0; ``update`` is refused before ``arm``."""

    def __init__(self, drift_per_m: float, drift_m_per_s: float, reset_m: float) -> None:
        self.drift_per_m = drift_per_m
        self.drift_m_per_s = drift_m_per_s
        self.reset_m = reset_m
        self.offset_m = np.zeros(3)
        self.sigma_m = 0.0
        self.resets = 0
        self.updates = 0
        self._last_vo_m: F64 | None = None  # the VO position last seen [m] (None: not armed)
        self._since_us: int | None = None  # time of sigma_m (the last update or arming)
        self._path_m = 0.0  # the VO's path since then [m]

    def arm(self, time_us: int, vo_m: F64) -> None:
        """Start at the arming pose: offset 0, sigma 0, at the VO position ``vo_m`` (3,)."""
        self.offset_m = np.zeros(3)
        self.sigma_m = 0.0
        self._last_vo_m = np.asarray(vo_m, dtype=np.float64).copy()
        self._since_us = time_us
        self._path_m = 0.0

    def move(self, vo_m: F64) -> None:
        """The VO's position ``vo_m`` (3,) [m] at a frame: adds to the path (every published
        pose; a no-op before arming)."""
        if self._last_vo_m is None:
            return
        vo = np.asarray(vo_m, dtype=np.float64)
        self._path_m += float(np.linalg.norm(vo - self._last_vo_m))
        self._last_vo_m = vo.copy()

    def predicted_sigma_m(self, time_us: int, vo_m: F64) -> float:
        """The offset's sigma [m] at ``time_us`` with the VO at ``vo_m`` (3,): grown by the
        VO's drift over its path and the time since the last update."""
        if self._last_vo_m is None or self._since_us is None:
            raise ValueError("the offset is not armed")
        path_m = self._path_m + float(np.linalg.norm(np.asarray(vo_m) - self._last_vo_m))
        dt_s = max(time_us - self._since_us, 0) * 1e-6
        return self.sigma_m + self.drift_per_m * path_m + self.drift_m_per_s * dt_s

    def update(self, time_us: int, vo_m: F64, dpose_m: F64, dpose_sigma_m: float) -> bool:
        """Take one d-Pose position ``dpose_m`` (3,) [m] with sigma ``dpose_sigma_m`` against
        the VO's ``vo_m`` (3,) at the same frame; True when it was a reset (gap > reset_m)."""
        sigma = self.predicted_sigma_m(time_us, vo_m)
        vo = np.asarray(vo_m, dtype=np.float64)
        gap = np.asarray(dpose_m, dtype=np.float64) - vo - self.offset_m
        reset = float(np.linalg.norm(gap)) > self.reset_m
        if reset:
            self.offset_m = self.offset_m + gap
            self.sigma_m = dpose_sigma_m
            self.resets += 1
        else:
            gain = sigma**2 / (sigma**2 + dpose_sigma_m**2) if sigma > 0 else 0.0
            self.offset_m = self.offset_m + gain * gap
            self.sigma_m = float(np.sqrt(1.0 - gain) * sigma)
        self._last_vo_m = vo.copy()
        self._since_us = time_us
        self._path_m = 0.0
        self.updates += 1
        return reset
