"""What the scale and roll/pitch take at a tracked frame: the lasers' readings, the VO's
prior, the scaled VO cloud.

Frames: the camera frame (OpenCV, metres) for the lasers' hit points; ranges in metres,
times in microseconds.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from companion.attitude.estimator import CloudView
from companion.scale.laser import RangeHistory, laser_point_cam
from companion.scale.options import ScaleOptions
from companion.types import F64, RangeSensorSpec, ScaleEstimate, VoOutput

MIN_GROUND_SIGMA_REL = 0.01  # a ground start's scale is trusted to 1 % at best (the plane fit)


class LaserReading(NamedTuple):
    """One distance sensor's reading at a frame, as the scale methods take it
    (``ScaleInput.lasers``' values)."""

    range_m: float  # the range along the beam [m]
    point_cam: F64  # (3,) where the beam hits, in the camera frame [m]
    sigma_m: float  # the range's sigma [m]


def laser_readings(
    specs: dict[int, RangeSensorSpec],
    ranges: RangeHistory,
    T_cam_body: F64,
    time_us: int,
    options: ScaleOptions,
) -> dict[int, LaserReading]:
    """The reading of every sensor with one at ``time_us`` (within ``max_range_gap_us`` /
    ``max_range_age_us``), by sensor id in increasing order."""
    lasers: dict[int, LaserReading] = {}
    for sid in sorted(specs):
        d = ranges.at(sid, time_us, options.max_range_gap_us, options.max_range_age_us)
        if d is None:
            continue
        spec = specs[sid]
        lasers[sid] = LaserReading(d, laser_point_cam(spec, T_cam_body, d), spec.sigma_m(d))
    return lasers


def ground_prior(metric_sigma_rel: float | None) -> tuple[float, float] | None:
    """(scale, sigma) of a VO map that started on the ground plane (its unit is 1 m, to the
    plane fit's relative sigma, at best MIN_GROUND_SIGMA_REL), else None."""
    if metric_sigma_rel is None:
        return None
    return (1.0, max(metric_sigma_rel, MIN_GROUND_SIGMA_REL))


class TiltInput(NamedTuple):
    """What the roll/pitch estimator took at a frame (a replay feeds it again)."""

    range_m: dict[int, float]  # the ranges at the frame [m] by sensor id
    cloud: CloudView  # the body's orientation, metric position and the scaled VO map


def scaled_cloud(
    out: VoOutput, R_vo_body: F64, est: ScaleEstimate | None, lever_m: F64
) -> CloudView:
    """The VO's view for roll/pitch: the body orientation (3, 3) in the VO frame, its metric
    position (3,) [m] (the camera's scaled position plus ``lever_m``) and the map's points
    (N, 3) [m] scaled by ``est`` (none, at the origin, before a scale)."""
    points = np.zeros((0, 3))
    position = np.zeros(3)
    if est is not None and est.scale > 0:
        f = out.features
        points = f.points_vo[f.point_ids >= 0] * est.scale
        position = out.T_vo_cam[:3, 3] * est.scale + lever_m
    return CloudView(R_vo_body, position, points)
