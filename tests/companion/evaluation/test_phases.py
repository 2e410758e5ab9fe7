"""The whole-flight ATE of `companion eval --phases` (companion/evaluation/phases.py): a
percentage of the path only where the path is long enough to carry one."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.evaluation.phases import MIN_PATH_FOR_PCT_M, flight_ate


def test_a_flight_that_stayed_on_the_ground_has_no_percentage_of_its_path() -> None:
    rng = np.random.default_rng(3)
    truth = np.zeros((120, 3)) + rng.normal(0.0, 1e-5, (120, 3))  # the truth's own jitter
    est = truth + rng.normal(0.0, 0.01, (120, 3))
    ate_m, pct = flight_ate(est, truth)
    assert 0.005 < ate_m < 0.03 and math.isnan(pct)  # was ~1e14 % before the floor


def test_a_straight_flight_gives_its_ate_over_its_path() -> None:
    truth = np.column_stack([np.linspace(0.0, 10.0, 101), np.zeros(101), np.zeros(101)])
    est = truth.copy()
    est[:, 1] += np.where(np.arange(101) % 2 == 0, 0.05, -0.05)  # +-5 cm sideways
    ate_m, pct = flight_ate(est, truth)
    assert ate_m == pytest.approx(0.05, abs=1e-3)
    assert pct == pytest.approx(100.0 * ate_m / 10.0)
    short = truth * (0.99 * MIN_PATH_FOR_PCT_M / 10.0)  # under the floor: no percentage
    assert math.isnan(flight_ate(short + 0.001, short)[1])
