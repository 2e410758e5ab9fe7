"""A Kalman filter for a state that only drifts and is measured directly.

The model of the scale filter (companion/scale/kalman.py, one state) and of the tilt-error
filter (companion/attitude/fusion.py, two states): the state x (n, 1) is a random walk,
x_k = x_(k-1) + w with w ~ N(0, Q), and each measurement sees it whole, z = x + v with
v ~ N(0, R). With the identity for both the transition and the measurement matrix the
general equations reduce to (Simon, "Optimal State Estimation", 2006, eqs. 5.17-5.19):

    predict:  P <- P + Q
    update:   S = P + R,  K = P S^-1,  x <- x + K (z - x),
              P <- (I - K) P (I - K)^T + K R K^T   (Joseph's form: P stays symmetric and
              positive even when K is computed with round-off)

Written here because the general filter of filterpy costs the service far more than its
arithmetic: importing ``filterpy.kalman`` imports ``scipy.stats`` (45 MB of resident memory
and 0.45 s at every start on a laptop core), and each update copies its inputs. The products
are the same NumPy calls in the same order as that general filter's with identity matrices,
so the estimates are the same to the last bit (tests/companion/geometry/test_kalman.py).
"""

from __future__ import annotations

import numpy as np

from companion.types import F64


class RandomWalkKalman:
    """x (n, 1) and its covariance P (n, n); predict with the drift's covariance Q (n, n),
    update with a measurement z (n, 1) of covariance R (n, n)."""

    __slots__ = ("P", "_eye", "x")

    def __init__(self, n: int) -> None:
        self._eye = np.eye(n)
        self.x: F64 = np.zeros((n, 1))
        self.P: F64 = np.eye(n)

    def predict(self, Q: F64) -> None:
        """The drift over a step: P <- P + Q (x is unchanged)."""
        self.P = self.P + Q

    def update(self, z: F64, R: F64) -> None:
        """Fold in a measurement z (n, 1) of covariance R (n, n)."""
        P = self.P
        S = P + R
        K = np.dot(P, np.linalg.inv(S))
        self.x = self.x + np.dot(K, z - self.x)
        I_K = self._eye - K
        self.P = np.dot(np.dot(I_K, P), I_K.T) + np.dot(np.dot(K, R), K.T)
