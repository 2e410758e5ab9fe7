"""VO accuracy against ground truth: the Sim(3)-aligned ATE of the longest tracked segment."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.evaluation.trajectory import ate_rmse, path_length
from companion.types import F64


@dataclass(frozen=True, slots=True)
class VoMetrics:
    """Accuracy of a VO run against ground truth (positions of the body)."""

    frames: int
    first_tracking_s: float
    tracking_ratio: float  # of the frames after the first initialisation
    resets: int
    segment_frames: int  # frames of the longest tracked segment (the one evaluated)
    path_m: float
    ate_sim3_m: float
    ate_sim3_pct: float
    sim3_scale: float


def vo_metrics(
    time_us: Sequence[int],
    tracking: NDArray[np.bool_],
    segment: Sequence[int],
    resets: int,
    positions: F64,
    gt_positions: F64,
) -> VoMetrics:
    """Sim(3)-aligned ATE of the longest segment: the VO camera positions (F, 3) (NaN where
    not tracking) against the true camera positions gt_positions (F, 3) at the frame times
    time_us (F,); segment (F,) is the VO map index of each frame."""
    n = len(tracking)
    if not tracking.any():
        return VoMetrics(
            n, float("nan"), 0.0, resets, 0, 0.0, float("nan"), float("nan"), float("nan")
        )
    first = int(np.argmax(tracking))
    t0 = time_us[0]
    seg = np.array(segment)
    best = max(set(seg[tracking].tolist()), key=lambda s: int(np.sum(tracking & (seg == s))))
    sel = tracking & (seg == best)
    est = positions[sel]
    gt = gt_positions[sel]
    ate, align = ate_rmse(est, gt, "sim3")
    length = path_length(gt)
    return VoMetrics(
        n,
        (time_us[first] - t0) * 1e-6,
        float(tracking[first:].mean()),
        resets,
        int(sel.sum()),
        length,
        ate,
        100.0 * ate / length if length > 0 else float("nan"),
        align.scale,
    )
