"""The scale filter's gate recovery (companion/scale/kalman.py, ``[scale] gate_recover_s``):
a step in the VO's unit is followed once the gated-out measurements agree for long enough;
outliers that disagree, or last less, never move it; off, it holds the old scale."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from companion.scale.kalman import ScaleKalman

FRAME_US = 33_333  # 30 Hz


def _fly(kf: ScaleKalman, truth: np.ndarray, sigma: float = 0.01, seed: int = 1) -> np.ndarray:
    """Feed truth (N,) with 1 % noise at 30 Hz; the filter's scale after each frame (N,)."""
    rng = np.random.default_rng(seed)
    out = np.empty(len(truth))
    for k, s in enumerate(truth):
        kf.update(k * FRAME_US, float(s * (1.0 + rng.normal(0.0, sigma))), sigma * float(s))
        out[k] = kf.scale
    return out


def test_a_step_of_the_vo_unit_is_followed_after_the_recovery_time() -> None:
    truth = np.r_[np.full(300, 1.0), np.full(300, 1.4)]  # the unit changes 40 % at 10 s
    kf = ScaleKalman(0.01, 6.63, recover_s=1.0)
    kf.initialize(0, 1.0, 0.01)
    est = _fly(kf, truth)
    assert kf.recoveries == 1
    k_back = int(np.argmax(np.abs(est / truth - 1.0)[300:] < 0.03)) + 300
    assert 300 + 30 <= k_back <= 300 + 45  # 1 s (30 frames) of rejections, then restarted
    assert np.all(np.abs(est[k_back:] / 1.4 - 1.0) < 0.02)
    assert np.all(np.abs(est[:300] - 1.0) < 0.02)  # nothing happened before the step


def test_off_the_filter_holds_the_old_scale_for_minutes(caplog: pytest.LogCaptureFixture) -> None:
    truth = np.r_[np.full(300, 1.0), np.full(1800, 1.4)]  # a minute after the step
    kf = ScaleKalman(0.01, 6.63)
    kf.initialize(0, 1.0, 0.01)
    est = _fly(kf, truth)
    assert kf.recoveries == 0 and abs(est[-1] - 1.0) < 0.05  # what the recovery is for
    assert not caplog.records


def test_outliers_that_disagree_or_stop_in_time_never_restart_it(
    caplog: pytest.LogCaptureFixture,
) -> None:
    rng = np.random.default_rng(5)
    kf = ScaleKalman(0.01, 6.63, recover_s=1.0)
    kf.initialize(0, 1.0, 0.01)
    k = 0
    for _ in range(90):  # 3 s of wild matches, each far outside the gate and the others
        kf.update(k * FRAME_US, float(rng.choice([0.3, 3.0]) * rng.uniform(0.8, 1.2)), 0.01)
        k += 1
    for _ in range(25):  # then agreeing ones for 0.8 s: the last 1 s does not agree
        kf.update(k * FRAME_US, 2.0, 0.01)
        k += 1
    kf.update(k * FRAME_US, 1.0, 0.01)  # a good one ends the run
    k += 1
    for _ in range(25):  # agreeing again, for less than 1 s
        kf.update(k * FRAME_US, 2.0, 0.01)
        k += 1
    assert kf.recoveries == 0 and abs(kf.scale - 1.0) < 0.01
    with caplog.at_level(logging.WARNING, logger="companion.scale.kalman"):
        for _ in range(10):
            kf.update(k * FRAME_US, 2.0, 0.01)
            k += 1
    assert kf.recoveries == 1 and kf.scale == pytest.approx(2.0)
    assert "restarted there" in caplog.text and "agree on 2.0000 (it held 1.0" in caplog.text


def test_the_time_outside_the_gate_is_reported_until_a_measurement_passes() -> None:
    kf = ScaleKalman(0.01, 6.63)
    kf.initialize(0, 1.0, 0.01)
    kf.update(0, 1.0, 0.01)
    assert kf.outside_gate_s == 0.0
    for k in range(1, 61):  # 2 s of a scale 40 % off
        kf.update(k * FRAME_US, 1.4, 0.01)
    assert kf.outside_gate_s == pytest.approx(59 * FRAME_US * 1e-6)
    kf.update(61 * FRAME_US, 1.0, 0.01)
    assert kf.outside_gate_s == 0.0 and kf.recoveries == 0
