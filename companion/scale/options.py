"""Options of the metric-scale estimation (composed into the config as [scale])."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from companion.options import opt

ScaleMethodName = Literal[
    "MSC", "MSCwK", "M-MSC", "M-MSCwK", "B7 window-ML", "B8 per-frame", "B9 plane"
]


@dataclass(frozen=True, slots=True)
class ScaleOptions:
    """MSC matching, the scale Kalman filter and the range/frame time alignment."""

    method: ScaleMethodName = opt("M-MSCwK", "the scale method whose poses are published")
    patch_half_px: float = opt(
        12.0, "half side of the search patch around the laser pixel [px]", gt=0
    )
    slope_factor: float = opt(0.5, "relative depth change per normalised pixel offset", ge=0)
    edge_radius_px: float = opt(
        36.0, "depth-step check: map points within this distance of the laser pixel [px]", gt=0
    )
    edge_depth_rel: float = opt(
        0.1,
        "refuse a match when those points' depths span more than this fraction of their "
        "median (the beam may be on the other side of a building edge); 0 = no check",
        ge=0,
    )
    mmsc_min_sensors: int = opt(
        2,
        "M-MSC: a keyframe updates the scale only when at least this many sensors' matches "
        "agree (capped at the number of sensors seen); 1 = any single match",
        ge=1,
    )
    max_range_gap_us: int = opt(60_000, "widest gap between two range samples to interpolate", gt=0)
    max_range_age_us: int = opt(40_000, "a range sample older than this is stale", gt=0)
    random_walk_per_s: float = opt(
        0.01, "scale drift: relative sigma of the random walk per sqrt(second)", ge=0
    )
    gate_chi2: float = opt(
        6.63, "chi-square gate (1 dof) on a scale measurement's innovation", gt=0
    )
    gate_recover_s: float = opt(
        0.0,
        "MSCwK / M-MSCwK: after this long [s] with every measurement outside the gate, and "
        "90 % of those of that time within gate_recover_spread of their median, restart the "
        "filter at their median (companion/scale/kalman.py); 0 = never (the default: on a "
        "real camera it also followed matches that agreed and were wrong, docs/methods.md)",
        ge=0,
    )
    gate_recover_spread: float = opt(
        0.1, "gate_recover_s: the gated-out measurements' largest relative spread", gt=0
    )
    init_sigma_rel: float = opt(0.2, "relative sigma of the initial scale", gt=0)
    reuse_memory_s: float = opt(
        30.0,
        "MSCwK / M-MSCwK: a sensor's match on the same map point again within this long is the "
        "same measurement again: its n-th use has its sigma times sqrt(n) (companion/scale/"
        "methods.py, ReuseCounter); 0 = every frame's match independent",
        ge=0,
    )
    fusion_outlier_sigmas: float = opt(
        3.0, "M-MSC: drop measurements this many sigmas from the weighted median", gt=0
    )
    b7_window_s: float = opt(5.0, "B7 window-ML: window length [s]", gt=0)
    b7_min_step_m: float = opt(0.05, "B7: minimum metric displacement of a pair [m]", gt=0)
