"""Metric-scale metrics (docs/methods.md).

Ground-truth scale at a frame: the median over tracked map points of true depth / VO depth,
the true depth by ray casting the simulator's terrain from the true camera pose. Errors are
measured from ``settle_s`` (5 s) after initialisation: scale MSE, mean absolute relative scale
error; the metric ATE aligns with SE(3) only (no scale: the point is metric scale).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.evaluation.trajectory import ate_rmse, final_error_m, path_length
from companion.geometry import so3
from companion.types import F64


@dataclass(frozen=True, slots=True)
class ScaleMetrics:
    """Accuracy of one scale method over one run."""

    method: str
    frames: int
    scale_mse: float
    scale_mean_abs_rel_pct: float
    ate_m: float
    ate_pct: float
    final_error_m: float
    path_m: float


def gt_scale(true_depth_m: F64, vo_depth: F64) -> float:
    """Median of true/VO depth over the points with both depths positive (NaN if none)."""
    ok = np.isfinite(true_depth_m) & np.isfinite(vo_depth) & (vo_depth > 0) & (true_depth_m > 0)
    return float(np.median(true_depth_m[ok] / vo_depth[ok])) if ok.any() else float("nan")


def scale_metrics(
    method: str,
    time_s: F64,
    scale: F64,
    scale_true: F64,
    position_m: F64,
    gt_position_m: F64,
    R_world_vo: F64,
    init_time_s: float,
    settle_s: float = 5.0,
) -> ScaleMetrics:
    """Metrics of one method. Arrays are per frame (F,) / (F, 3); NaN rows = no estimate.

    position_m are the method's metric positions in the VO frame's orientation; R_world_vo
    turns them into the world (the yaw at initialisation) for the final-position error, which
    is measured with the start of the evaluated span aligned to the truth.
    """
    sel = (time_s >= init_time_s + settle_s) & np.isfinite(scale) & np.isfinite(scale_true)
    sel &= np.all(np.isfinite(position_m), axis=1)
    n = int(sel.sum())
    if n < 3:
        nan = float("nan")
        return ScaleMetrics(method, n, nan, nan, nan, nan, nan, nan)
    rel = (scale[sel] - scale_true[sel]) / scale_true[sel]
    est = position_m[sel]
    gt = gt_position_m[sel]
    ate, _ = ate_rmse(est, gt, "se3")
    length = path_length(gt)
    final = final_error_m(est, gt, R_world_vo)
    return ScaleMetrics(
        method,
        n,
        float(np.mean((scale[sel] - scale_true[sel]) ** 2)),
        float(100 * np.mean(np.abs(rel))),
        ate,
        100 * ate / length,
        final,
        length,
    )


def methods_metrics(
    methods: Sequence[str],
    time_s: F64,
    tracking: NDArray[np.bool_],
    yaw_vo_rad: float,
    scale: Mapping[str, F64],
    scale_true: F64,
    position_m: Mapping[str, F64],
    gt_position_m: F64,
    settle_s: float = 5.0,
) -> list[ScaleMetrics]:
    """:func:`scale_metrics` of every method of one run (empty if the VO never tracked): the
    errors count from ``settle_s`` after the first tracked frame; the VO frame's yaw at
    initialisation turns the methods' positions into the world."""
    if not tracking.any():
        return []
    init = float(time_s[np.argmax(tracking)])
    R = so3.rot_z(yaw_vo_rad)
    return [
        scale_metrics(
            n, time_s, scale[n], scale_true, position_m[n], gt_position_m, R, init, settle_s
        )
        for n in methods
    ]
