"""Error of a published trajectory by flight phase (issue 18: from the ground up).

A flight with take-off and landing is cut into phases from the true height above the ground
h(t) [m] and its rate: ``ground`` (before take-off, h below ``ground_m``), ``climb`` (rising
faster than ``rate_m_s``), ``cruise``, ``descent`` (sinking faster than ``rate_m_s``) and
``landed`` (after touchdown). Errors are of the published positions in the published frame:
local NED whose origin is the first published pose and whose yaw is the autopilot's heading
then, so both are taken relative to the first published pose and no alignment is fitted: what
the autopilot would see. The whole-flight metric ATE (SE(3)
alignment, docs/methods.md) is given beside it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.evaluation.trajectory import ate_rmse, path_length
from companion.types import F64

PHASES = ("ground", "climb", "cruise", "descent", "landed")
# a whole-flight ATE as % of a path shorter than this says nothing: a flight that stayed on the
# ground has a path of the truth's millimetres, and its centimetre errors came out as 1e14 %
MIN_PATH_FOR_PCT_M = 1.0


@dataclass(frozen=True, slots=True)
class PhaseErrors:
    """Per phase: frames, RMS and max position error [m] (NaN when the phase has none)."""

    phase: str
    frames: int
    rmse_m: float
    max_m: float


def phase_labels(
    time_s: F64, height_m: F64, ground_m: float = 0.35, rate_m_s: float = 0.3
) -> NDArray[np.str_]:
    """(N,) the phase of each sample from the true height above ground (N,) [m]."""
    rate = np.gradient(height_m, time_s) if len(time_s) > 1 else np.zeros_like(height_m)
    airborne = np.flatnonzero(height_m >= ground_m)
    labels = np.full(len(time_s), "cruise", dtype="<U7")
    labels[rate > rate_m_s] = "climb"
    labels[rate < -rate_m_s] = "descent"
    if len(airborne):
        labels[: airborne[0]][height_m[: airborne[0]] < ground_m] = "ground"
        after = np.arange(len(time_s)) > airborne[-1]
        labels[after & (height_m < ground_m)] = "landed"
    else:
        labels[:] = "ground"
    return labels


def published_errors(est_m: F64, gt_m: F64) -> F64:
    """(N,) |(est - est[0]) - (gt - gt[0])| [m]: the published positions (N, 3) and the truth
    (N, 3) both taken from the first published pose (the published origin is the camera at
    the VO's first keyframe, a lever arm from the body: a constant offset the autopilot
    never sees as motion)."""
    moved = (est_m - est_m[0]) - (gt_m - gt_m[0])
    return np.asarray(np.linalg.norm(moved, axis=1), dtype=np.float64)


def relative_errors(est_m: F64, gt_m: F64, i: int) -> F64:
    """(N,) |(est - est[i]) - (gt - gt[i])| [m]: both taken from sample i (d-Pose: the arming
    pose, the marks' reference)."""
    moved = (est_m - est_m[i]) - (gt_m - gt_m[i])
    return np.asarray(np.linalg.norm(moved, axis=1), dtype=np.float64)


def by_phase(errors_m: F64, labels: NDArray[np.str_]) -> list[PhaseErrors]:
    """RMS and max error per phase, in PHASES order."""
    out = []
    for ph in PHASES:
        e = errors_m[labels == ph]
        rmse = float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")
        out.append(PhaseErrors(ph, int(len(e)), rmse, float(e.max()) if len(e) else float("nan")))
    return out


def flight_ate(est_m: F64, gt_m: F64) -> tuple[float, float]:
    """Whole-flight metric ATE [m] (SE(3) alignment, no scale) and as % of the true path
    (NaN for a path shorter than MIN_PATH_FOR_PCT_M); est_m, gt_m: (N, 3) positions [m]."""
    ate, _ = ate_rmse(est_m, gt_m, "se3")
    length = path_length(gt_m)
    return ate, 100.0 * ate / length if length >= MIN_PATH_FOR_PCT_M else float("nan")
