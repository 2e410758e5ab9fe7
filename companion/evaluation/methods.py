"""The scale methods side by side on a dataset's ground-truth trajectory alone.

A real recording (or any dataset that declares no simulated world) has no true scale: that
comes from ray casting the simulator's terrain (``companion.evaluation.scale``), and a default
world would give numbers about a place that was never flown. What a ground-truth trajectory
does give, per method (docs/methods.md):

- metric ATE: RMSE of the method's metric body positions after an SE(3) alignment (no scale:
  the point is metric scale), also as % of the path, and the final-position error;
- Sim(3) ATE: the same with the scale aligned too, and that scale (``sim3_scale`` = the factor
  that best maps the method's positions onto the truth: 1.0 is a right metric scale, 1.02 a
  trajectory 2 % too short). The gap between the two ATEs is what the scale error costs.

Figures that need a true scale (scale MSE, mean absolute relative scale error) are reported
as unavailable with the reason, never computed. Positions are (F, 3) arrays, NaN where a
method has no estimate; times (F,) in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from companion.evaluation.segments import TrackAccuracy, track_accuracy
from companion.evaluation.trajectory import ate_rmse, final_error_m, path_length
from companion.types import F64

NO_WORLD = "no simulated world in the dataset: the true scale is ray cast in one"
WORLD_FIGURES = ("scale_mse", "scale_mean_abs_rel_pct")
TRAJECTORY_FIGURES = ("ate_se3_m", "ate_se3_pct", "ate_sim3_m", "sim3_scale", "final_error_m")


@dataclass(frozen=True, slots=True)
class MethodAccuracy:
    """One method's accuracy against a ground-truth trajectory; None = unavailable (the
    reason in ``unavailable``, by figure name)."""

    method: str
    frames: int
    path_m: float | None = None
    ate_se3_m: float | None = None
    ate_se3_pct: float | None = None
    ate_sim3_m: float | None = None
    sim3_scale: float | None = None
    final_error_m: float | None = None
    scale_mse: float | None = None
    scale_mean_abs_rel_pct: float | None = None
    unavailable: dict[str, str] = field(default_factory=dict)


def trajectory_accuracy(
    method: str,
    time_s: F64,
    position_m: F64,
    gt_position_m: F64,
    R_world_vo: F64,
    init_time_s: float,
    settle_s: float = 5.0,
    missing: str = "",
) -> MethodAccuracy:
    """Metric (SE3) and Sim(3) ATE of one method's positions (F, 3) (VO frame orientation;
    R_world_vo (3, 3) turns them into the world for the final-position error) against the
    true positions (F, 3), over the frames from ``init_time_s + settle_s`` where both exist.
    ``missing``: why the method may have no estimate (e.g. the dataset has no ranges), given
    as the reason when it has fewer than 3 frames."""
    no_scale = dict.fromkeys(WORLD_FIGURES, NO_WORLD)
    sel = (time_s >= init_time_s + settle_s) & np.all(np.isfinite(position_m), axis=1)
    sel &= np.all(np.isfinite(gt_position_m), axis=1)
    n = int(sel.sum())
    if n < 3:
        if not np.isfinite(gt_position_m).any():
            why = "no ground truth in the dataset"
        elif missing:
            why = missing
        else:
            why = f"{n} frames with an estimate {settle_s:g} s after initialisation"
        return MethodAccuracy(
            method, n, unavailable={**dict.fromkeys(TRAJECTORY_FIGURES, why), **no_scale}
        )
    est, gt = position_m[sel], gt_position_m[sel]
    ate_se3, _ = ate_rmse(est, gt, "se3")
    ate_sim3, sim3 = ate_rmse(est, gt, "sim3")
    length = path_length(gt)
    final = final_error_m(est, gt, R_world_vo)
    return MethodAccuracy(
        method,
        n,
        path_m=length,
        ate_se3_m=ate_se3,
        ate_se3_pct=100.0 * ate_se3 / length if length > 0 else None,
        ate_sim3_m=ate_sim3,
        sim3_scale=float(sim3.scale),
        final_error_m=final,
        unavailable=no_scale,
    )


def method_track(
    time_s: F64,
    position_m: F64,
    gt_position_m: F64,
    segment: F64,
    init_time_s: float,
    settle_s: float = 5.0,
) -> TrackAccuracy:
    """A method's whole-flight and per-segment ATE and its constant-position baselines
    (companion.evaluation.segments) over the frames :func:`trajectory_accuracy` evaluates
    (from ``init_time_s + settle_s``); ``segment`` (F,) the VO map index of every frame."""
    sel = time_s >= init_time_s + settle_s
    return track_accuracy(time_s[sel], position_m[sel], gt_position_m[sel], segment[sel])
