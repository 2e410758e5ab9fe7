"""What the scale and roll/pitch take at a tracked frame: the lasers' readings, the VO's
prior, the scaled VO cloud; the scale methods and their metric trajectories (ScaleStage).

Frames: the camera frame (OpenCV, metres) for the lasers' hit points; ranges in metres,
times in microseconds.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from companion.attitude.estimator import CloudView, RollPitch, TiltStep
from companion.geometry import se3
from companion.geometry.camera import CameraModel
from companion.scale.laser import RangeHistory, laser_point_cam
from companion.scale.methods import MetricTrajectory, ScaleInput, make_methods
from companion.scale.options import ScaleOptions
from companion.types import F64, RangeSensorSpec, ScaleEstimate, VoOutput
from companion.vo.odometry import VisualOdometry

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


def frame_input(
    specs: dict[int, RangeSensorSpec],
    ranges: RangeHistory,
    T_cam_body: F64,
    out: VoOutput,
    vo: VisualOdometry,
    options: ScaleOptions,
) -> tuple[ScaleInput, dict[int, float]]:
    """What the scale methods take at the tracked frame of ``out`` (the lasers' readings at
    its time, the VO map's index and its ground prior), and the ranges [m] by sensor id."""
    readings = laser_readings(specs, ranges, T_cam_body, out.time_us, options)
    prior = ground_prior(vo.metric_sigma_rel)
    T_cam_vo = se3.inverse(out.T_vo_cam)
    inp = ScaleInput(out.time_us, out, T_cam_vo, dict(readings), vo.resets, prior)
    return inp, {sid: r.range_m for sid, r in readings.items()}


def roll_pitch(
    attitude: RollPitch | None,
    inp: ScaleInput,
    range_m: dict[int, float],
    est: ScaleEstimate | None,
    T_cam_body: F64,
    R_world_body: F64 | None,
) -> tuple[TiltStep | None, TiltInput | None]:
    """Roll/pitch at the frame of ``inp`` from the ranges [m] by sensor id, compensated with
    the VO cloud scaled by ``est`` (RollPitch.step), and what it took; (None, None) without
    roll/pitch or a finite VO pose. ``R_world_body``: the autopilot's attitude (3, 3)."""
    out = inp.vo
    if attitude is None or not np.all(np.isfinite(out.T_vo_cam)):
        return None, None
    R_vo_body = body_rotation_in_vo(out.T_vo_cam, T_cam_body)
    cloud = scaled_cloud(out, R_vo_body, est, lever_arm_m(out.T_vo_cam, T_cam_body))
    tilt = attitude.step(inp.time_us, range_m, cloud, inp.segment, R_world_body)
    return tilt, TiltInput(range_m, cloud)


def body_rotation_in_vo(T_vo_cam: F64, T_cam_body: F64) -> F64:
    """(3, 3) R_vo_body: the body's orientation in the VO frame, from the camera's pose (4, 4)
    and the camera mount (4, 4). (No T_vo_body: the body sits a metric lever arm from the
    camera, which has no place in unscaled VO units; see :func:`lever_arm_m`.)"""
    R: F64 = T_vo_cam[:3, :3] @ T_cam_body[:3, :3]
    return R


def lever_arm_m(T_vo_cam: F64, T_cam_body: F64) -> F64:
    """(3,) camera -> body lever arm [m] in the VO frame's axes: R_vo_cam @ t_cam_body
    (T_cam_body's translation is metric). The metric body position in the VO frame is
    ``scale * t_vo_cam + lever_arm_m``."""
    lever: F64 = T_vo_cam[:3, :3] @ T_cam_body[:3, 3]
    return lever


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


class ScaleStage:
    """Every scale method's estimate and metric trajectory over the tracked frames.

    A tracked frame's metric position is its VO position through the trajectory at the scale
    that the frames before left (:meth:`positions`), when they were of the same VO map
    (:meth:`ready`); the frame's own update of the scale (:meth:`update`) then runs after its
    pose is out, in the work after the pose. The trajectory adds each frame's VO motion at the
    scale of the frame before (MetricTrajectory: p += s_(k-1) (p_vo_k - p_vo_(k-1))), a
    filtered scale that moves by a fraction of its sigma a frame. At a map's first frame, and
    before any estimate, the update runs first (:class:`companion.pipeline.core.Pipeline`).
    """

    def __init__(
        self,
        camera: CameraModel,
        options: ScaleOptions,
        all_methods: bool = False,
        sensor_study: int = 0,
    ) -> None:
        methods = make_methods(camera, options, sensor_study)
        self.method_name = options.method
        self.methods = methods if all_methods else {self.method_name: methods[self.method_name]}
        self.trajectories = {name: MetricTrajectory() for name in self.methods}
        self.estimates: dict[str, ScaleEstimate | None] = dict.fromkeys(self.methods)
        # metric body positions (VO frame's axes) [m] by method, from the trajectories
        self.metric_positions: dict[str, F64 | None] = dict.fromkeys(self.methods)
        self.updated_segment: int | None = None  # the VO map of the last update

    def ready(self, segment: int) -> bool:
        """Whether the estimates are of VO map ``segment`` and the published method has one
        (a pose may then go out before this frame's update)."""
        return self.updated_segment == segment and self.estimates[self.method_name] is not None

    def update(self, inp: ScaleInput) -> None:
        """Every method's scale at the frame of ``inp`` (``estimates``)."""
        for name, method in self.methods.items():
            self.estimates[name] = method.step(inp)
        self.updated_segment = inp.segment

    def positions(self, inp: ScaleInput, lever_m: F64) -> None:
        """The metric body position of the frame of ``inp`` by method (``metric_positions``):
        the camera's VO position through each trajectory at the current estimate, plus the
        camera -> body lever arm ``lever_m`` (3,) [m] in the VO frame's axes; a method
        without an estimate keeps its last position."""
        c_vo = inp.vo.T_vo_cam[:3, 3]
        for name, est in self.estimates.items():
            if est is not None:
                cam_m = self.trajectories[name].step(c_vo, est.scale, inp.segment)
                self.metric_positions[name] = cam_m + lever_m
