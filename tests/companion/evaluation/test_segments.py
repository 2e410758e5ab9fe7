"""Whole-flight and per-segment ATE, the constant-position baseline, the steps at resets, and
the line that counts the frames not given to the VO (companion.evaluation.segments, .frames)."""

from __future__ import annotations

import numpy as np

from companion.evaluation.frames import dropped_line, dropped_total
from companion.evaluation.methods import method_track
from companion.evaluation.segments import constant_position_ate, segment_bounds, track_accuracy
from companion.evaluation.trajectory import ate_rmse
from companion.geometry import so3


def _figure8(n: int = 300, seed: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Times [s] (n,) and true positions (n, 3) [m] of a seeded figure eight at 30 Hz."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 30.0
    phase = rng.uniform(0, 2 * np.pi)
    gt = np.stack(
        [4 * np.sin(0.4 * t + phase), 2 * np.sin(0.8 * t + phase), -3 - 0.2 * np.cos(t)], axis=1
    )
    return t, gt


def test_segment_bounds_are_the_runs_of_equal_ids() -> None:
    assert segment_bounds([0, 0, 1, 1, 1, 0]) == [(0, 2), (2, 5), (5, 6)]
    assert segment_bounds([3]) == [(0, 1)]
    assert segment_bounds([]) == []


def test_the_constant_baselines_by_hand() -> None:
    start, mean = constant_position_ate(np.array([[0.0, 0, 0], [2.0, 0, 0]]))
    assert np.isclose(start, np.sqrt(2.0)) and np.isclose(mean, 1.0)


def test_a_perfect_estimate_has_ate_0_and_ratio_0_whatever_its_frame() -> None:
    t, gt = _figure8()
    moved = gt @ so3.exp([0.1, -0.2, 1.3]).T + [5.0, -1.0, 2.0]  # an SE(3) away: aligned out
    acc = track_accuracy(t, moved, gt, np.zeros(len(t)))
    assert acc.frames == len(t) and acc.ate_se3_m is not None and acc.ate_se3_m < 1e-9
    assert acc.ratio_to_mean is not None and acc.ratio_to_mean < 1e-9
    assert acc.ratio_to_start is not None and acc.ratio_to_start < 1e-9
    assert len(acc.segments) == 1 and acc.reset_steps == () and acc.largest_reset_step_m is None
    assert acc.constant_mean_m > 1.0  # the figure eight spreads metres about its mean


def test_a_constant_estimate_scores_the_best_constant_exactly() -> None:
    """Under an SE(3) alignment any constant lands on the truth's mean: its ATE is the best
    constant's, so its ratio is 1 (no better than standing still)."""
    t, gt = _figure8()
    still = np.repeat([[7.0, 1.0, -2.0]], len(t), axis=0)
    acc = track_accuracy(t, still, gt, np.zeros(len(t)))
    assert acc.ate_se3_m is not None and np.isclose(acc.ate_se3_m, acc.constant_mean_m)
    assert acc.ratio_to_mean is not None and np.isclose(acc.ratio_to_mean, 1.0)
    assert acc.constant_mean_m <= acc.constant_start_m  # the mean is the best constant


def test_a_hover_makes_the_constant_baseline_about_zero() -> None:
    """A hover with 2 mm of jitter: both constants are millimetres, so an estimate 5 cm off
    scores a ratio >> 1 (where its ATE as % of a path of metres of jitter would flatter it)."""
    rng = np.random.default_rng(3)
    n = 600
    t = np.arange(n) / 30.0
    gt = np.array([1.0, 2.0, -3.0]) + rng.normal(0, 0.002, (n, 3))
    acc = track_accuracy(t, gt + rng.normal(0, 0.05, (n, 3)), gt, np.zeros(n))
    assert acc.constant_mean_m < 0.005 and acc.constant_start_m < 0.01
    assert acc.ratio_to_mean is not None and acc.ratio_to_mean > 10.0
    hovering = track_accuracy(t, np.repeat(gt[:1], n, axis=0), gt, np.zeros(n))
    assert hovering.ate_se3_m is not None and hovering.ate_se3_m < 0.005


def test_a_known_jump_is_one_segment_each_side_and_a_step_at_the_reset() -> None:
    """The estimate follows the truth (1 cm noise), then a new map starts 2 m off at frame
    k: each segment alone is as good as the noise, the whole flight is not, and the step at
    the reset is the jump plus the truth's own step."""
    t, gt = _figure8(400, seed=11)
    rng = np.random.default_rng(11)
    k = 170
    est = gt + rng.normal(0, 0.01, gt.shape)
    jump = np.array([2.0, 0.0, 0.0])
    est[k:] += jump
    ids = np.r_[np.zeros(k), np.ones(len(t) - k)]
    acc = track_accuracy(t, est, gt, ids)
    assert [s.frames for s in acc.segments] == [k, len(t) - k]
    assert [s.segment for s in acc.segments] == [0, 1]
    assert np.isclose(acc.segments[0].duration_s, (k - 1) / 30.0)
    for s in acc.segments:
        assert s.ate_se3_m is not None and 0.01 < s.ate_se3_m < 0.03  # sqrt(3) * 1 cm
    assert acc.ate_se3_m is not None and acc.ate_se3_m > 0.3  # the jump shows in the whole
    (step,) = acc.reset_steps
    assert np.isclose(step.time_s, t[k])
    assert np.isclose(step.true_step_m, np.linalg.norm(gt[k] - gt[k - 1]))
    assert np.isclose(step.step_m, np.linalg.norm(est[k] - est[k - 1]))
    assert 1.9 < step.step_m < 2.1 and acc.largest_reset_step_m == step.step_m
    assert np.isclose(acc.ate_se3_m, ate_rmse(est, gt, "se3")[0])


def test_frames_without_an_estimate_are_left_out_and_the_settle_time_applies() -> None:
    t, gt = _figure8()
    est = gt.copy()
    est[:50] = np.nan
    acc = track_accuracy(t, est, gt, np.zeros(len(t)))
    assert acc.frames == len(t) - 50 and acc.ate_se3_m is not None and acc.ate_se3_m < 1e-9
    assert track_accuracy(t, np.full_like(gt, np.nan), gt, np.zeros(len(t))).frames == 0
    settled = method_track(t, gt, gt, np.zeros(len(t)), init_time_s=1.0, settle_s=5.0)
    assert settled.frames == int(np.sum(t >= 6.0))


def test_the_dropped_frames_line_names_every_reason_with_its_count() -> None:
    counts = {"frozen": 35, "out_of_order": 2, "dark": 0, "held_for_attitude": 0}
    assert dropped_total(counts) == 37
    assert dropped_line(723, counts) == (
        "eval: 37 of 723 frames not given to the VO: 35 frozen (duplicated), 2 out of order"
    )
    assert dropped_line(723, {"frozen": 0, "errors": 0}) is None
    line = dropped_line(10, {"errors": 1, "blank": 2, "odd": 3})
    assert line == "eval: 6 of 10 frames not given to the VO: 2 blank, 1 the pipeline raised, 3 odd"
