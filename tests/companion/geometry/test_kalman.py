"""RandomWalkKalman (companion/geometry/kalman.py): the estimates of filterpy's general filter
with identity matrices to the last bit, and the textbook behaviour of the random walk."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from companion.geometry.kalman import RandomWalkKalman

filterpy_kalman = pytest.importorskip("filterpy.kalman", reason="filterpy is in the dev extra")


@pytest.mark.parametrize("n", [1, 2])
def test_the_same_bits_as_the_general_filter_with_identity_matrices(n: int) -> None:
    rng = np.random.default_rng(n)
    ours = RandomWalkKalman(n)
    ref = filterpy_kalman.KalmanFilter(dim_x=n, dim_z=n)
    ref.F, ref.H = np.eye(n), np.eye(n)
    x0, P0 = rng.normal(size=(n, 1)), np.diag(rng.uniform(0.1, 2.0, n))
    ours.x, ours.P, ref.x, ref.P = x0.copy(), P0.copy(), x0.copy(), P0.copy()
    for _ in range(500):
        Q = np.eye(n) * rng.uniform(0.0, 1e-3)
        ours.predict(Q)
        ref.Q = Q
        ref.predict()
        A = rng.normal(size=(n, n))
        R = A @ A.T * 0.1 + np.eye(n) * 1e-3  # a full covariance, as the tilt filter's
        z = rng.normal(size=(n, 1))
        ours.update(z, R)
        ref.update(z, R=R)
        assert np.array_equal(ours.x, ref.x) and np.array_equal(ours.P, ref.P)


def test_a_constant_measured_again_and_again_is_found_with_a_shrinking_sigma() -> None:
    kf = RandomWalkKalman(1)
    kf.x, kf.P = np.array([[0.0]]), np.array([[100.0]])
    rng = np.random.default_rng(4)
    sigmas = []
    for _ in range(400):
        kf.predict(np.array([[0.0]]))  # no drift: the mean of the measurements
        kf.update(np.array([[3.0 + rng.normal(0.0, 0.5)]]), np.array([[0.25]]))
        sigmas.append(float(np.sqrt(kf.P[0, 0])))
    assert abs(kf.x[0, 0] - 3.0) < 3 * 0.5 / np.sqrt(400)
    assert sigmas[-1] == pytest.approx(0.5 / np.sqrt(400), rel=0.01)  # sigma / sqrt(N)
    assert all(b <= a for a, b in itertools.pairwise(sigmas))
