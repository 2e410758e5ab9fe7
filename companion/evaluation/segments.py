"""Whole-flight and per-segment ATE, the constant-position baseline, and the steps at resets.

An ATE as a percentage of the path flatters a flight that hardly moves: a hover of 30 s with
a few centimetres of noise has a path of a metre and an estimate that stands still scores
well. The honest yardstick is what an estimate that knows nothing would score: a constant
position. Two constants, in metres (positions (N, 3), the estimate and the truth in one
frame's axes or aligned):

- the start held: ``sqrt(mean |gt_i - gt_0|^2)``, where an estimate that starts at the truth
  and never moves ends up (no alignment);
- the best constant: ``sqrt(mean |gt_i - mean(gt)|^2)``, the truth's spread about its mean.
  Under an SE(3) alignment every constant scores exactly this (a point set with no spread
  aligns onto the mean: Umeyama's translation), so ``ATE_SE3 / best constant`` is the fair
  ratio: 0 is perfect, 1 is no better than standing still.

A run is split into segments where its segment id changes (the published ``reset_counter``,
or the VO map's index): a re-initialised map starts a new segment. Each segment is aligned on
its own (its ATE says how good each map was), the whole flight once (it says how well the
segments fit together). The steps at resets compare the estimate's jump from the last
position of one segment to the first of the next with the truth's displacement over the
same frames (the published track continues from its last position: its step is ~0, and the
truth's step is what the anchoring loses).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from companion.evaluation.trajectory import ate_rmse
from companion.types import F64


@dataclass(frozen=True, slots=True)
class SegmentAte:
    """One segment: its id, frames, duration [s], SE(3)-aligned ATE [m] (None below 3 frames)
    and its own best-constant ATE [m] (the truth's spread about its mean over the segment)."""

    segment: int
    frames: int
    duration_s: float
    ate_se3_m: float | None
    constant_mean_m: float


@dataclass(frozen=True, slots=True)
class ResetStep:
    """The jump at a reset: time [s] of the first frame of the new segment, the estimate's
    step [m] from the last position before, the truth's displacement [m] over those frames."""

    time_s: float
    step_m: float
    true_step_m: float


@dataclass(frozen=True, slots=True)
class TrackAccuracy:
    """A track against the truth over the frames where both are finite: the whole-flight
    SE(3) ATE [m] (None below 3 frames), the two constant baselines [m], the ratios of the
    ATE to them (None when the baseline is 0), its segments and the steps at its resets."""

    frames: int
    ate_se3_m: float | None
    constant_start_m: float
    constant_mean_m: float
    ratio_to_start: float | None
    ratio_to_mean: float | None
    segments: tuple[SegmentAte, ...]
    reset_steps: tuple[ResetStep, ...]

    @property
    def largest_reset_step_m(self) -> float | None:
        """The largest step of the estimate at a reset [m] (None: no reset)."""
        return max((s.step_m for s in self.reset_steps), default=None)


def segment_bounds(segment_ids: Sequence[int] | F64) -> list[tuple[int, int]]:
    """[start, stop) index ranges of the runs of equal ids in ``segment_ids`` (N,), in order
    (an id that comes back after another is a new segment)."""
    ids = np.asarray(segment_ids)
    if len(ids) == 0:
        return []
    cuts = np.flatnonzero(ids[1:] != ids[:-1]) + 1
    edges = [0, *cuts.tolist(), len(ids)]
    return list(itertools.pairwise(edges))


def constant_position_ate(gt_m: F64) -> tuple[float, float]:
    """(start held, best constant) [m]: the RMS distance of the true positions (N, 3) from
    the first one, and from their mean (N >= 1)."""
    start = float(np.sqrt(np.mean(np.sum((gt_m - gt_m[0]) ** 2, axis=1))))
    mean = float(np.sqrt(np.mean(np.sum((gt_m - gt_m.mean(axis=0)) ** 2, axis=1))))
    return start, mean


def _ratio(ate_m: float | None, baseline_m: float) -> float | None:
    return None if ate_m is None or baseline_m <= 0.0 else ate_m / baseline_m


def _ate(est_m: F64, gt_m: F64) -> float | None:
    return ate_rmse(est_m, gt_m, "se3")[0] if len(est_m) >= 3 else None


def track_accuracy(
    time_s: F64, est_m: F64, gt_m: F64, segment_ids: Sequence[int] | F64
) -> TrackAccuracy:
    """The accuracy of a track: times (N,) [s], estimated and true positions (N, 3) [m] (NaN
    where unknown: those frames are left out) and the segment id (N,) of every frame."""
    ok = np.all(np.isfinite(est_m), axis=1) & np.all(np.isfinite(gt_m), axis=1)
    t, est, gt = time_s[ok], est_m[ok], gt_m[ok]
    ids = np.asarray(segment_ids)[ok]
    if len(t) == 0:
        return TrackAccuracy(0, None, 0.0, 0.0, None, None, (), ())
    ate = _ate(est, gt)
    start, mean = constant_position_ate(gt)
    segments: list[SegmentAte] = []
    steps: list[ResetStep] = []
    for a, b in segment_bounds(ids):
        segments.append(
            SegmentAte(
                int(ids[a]),
                b - a,
                float(t[b - 1] - t[a]),
                _ate(est[a:b], gt[a:b]),
                constant_position_ate(gt[a:b])[1],
            )
        )
        if a > 0:
            steps.append(
                ResetStep(
                    float(t[a]),
                    float(np.linalg.norm(est[a] - est[a - 1])),
                    float(np.linalg.norm(gt[a] - gt[a - 1])),
                )
            )
    return TrackAccuracy(
        len(t),
        ate,
        start,
        mean,
        _ratio(ate, start),
        _ratio(ate, mean),
        tuple(segments),
        tuple(steps),
    )
