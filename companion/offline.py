"""Offline runs of the Pipeline over recorded or simulated inputs (``companion eval | bench``).

This module orchestrates; it does no maths of its own: the Pipeline does the work and
``companion.evaluation`` the metrics. Inputs come as a time-ordered stream of CameraFrame /
RangeSample / AttitudeSample, from a dataset folder or straight from the simulator.
"""

from __future__ import annotations

import logging
import resource
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.config import Config
from companion.evaluation.scale import ScaleMetrics, methods_metrics
from companion.evaluation.vo import VoMetrics, vo_metrics
from companion.gc_pacing import GC_STAGE, GcPacing
from companion.geometry.camera import CameraModel
from companion.pipeline import Event, Pipeline
from companion.types import F64, CameraFrame, PoseEstimate, VoState
from companion.vo.focal_check import FocalRatio
from companion.vo.frame_clock import ClockReport

log = logging.getLogger("companion.offline")


@dataclass
class VoRun:
    """Per-frame VO results of one run.

    time_us (F,), state (F,) VoState values, T_vo_cam (F, 4, 4) (NaN unless tracking),
    features: tracked features of every frame the VO saw (its count may be below F),
    segment (F,) index of the VO map (it changes at every re-initialisation; -1 before the
    first), frame_ms (F,) time to each frame's pose [ms], total_ms (F,) including the keyframe
    work done after it, keyframe (F,) flags. poses: every pose the pipeline gave (the
    published method's, as the service would send it); errors: frames on which the
    pipeline raised (a replay skips them as the service did).
    """

    time_us: list[int] = field(default_factory=list)
    state: list[VoState] = field(default_factory=list)
    T_vo_cam: list[F64] = field(default_factory=list)
    segment: list[int] = field(default_factory=list)
    frame_ms: list[float] = field(default_factory=list)  # to the pose (the latency)
    total_ms: list[float] = field(default_factory=list)  # with the keyframe work after it
    # per frame: the wall time [ms] of each stage to the pose (the pipeline's and, nested as
    # "vo: ...", the VO's) and after it (keyframe, lens check): Pipeline.laps
    stage_ms: list[dict[str, float]] = field(default_factory=list)
    keyframe: list[bool] = field(default_factory=list)
    features: list[int] = field(default_factory=list)  # tracked, per frame given to the VO
    poses: list[PoseEstimate] = field(default_factory=list)
    errors: int = 0
    peak_rss_mb: float = 0.0
    resets: int = 0
    # frames not given to the VO, by reason (companion.evaluation.frames), errors included
    dropped: dict[str, int] = field(default_factory=dict)
    clock: ClockReport | None = None  # the camera's clock at the end (vo.steady_clock)
    gaps: int = 0  # new VO maps after more than vo.max_gap_ms without a usable frame
    lens_focal: FocalRatio | None = None  # the focal length checked in flight (LensStage)
    lens_warning: str | None = None
    gc: str = ""  # the garbage collector's work, paced between frames (GcPacing.summary)

    def tracking_mask(self) -> NDArray[np.bool_]:
        return np.array([s == VoState.TRACKING for s in self.state], dtype=bool)

    def metrics(self, gt_positions: F64) -> VoMetrics:
        """The VO's accuracy against the true camera positions (F, 3) at the frame times."""
        positions = np.array(self.T_vo_cam).reshape(-1, 4, 4)[:, :3, 3]
        return vo_metrics(
            self.time_us, self.tracking_mask(), self.segment, self.resets, positions, gt_positions
        )


def feed_step(pipe: Pipeline, step: Any) -> PoseEstimate | None:
    """One SITL step (``Scenario.steps()``) into the pipeline: its attitudes, accelerometer
    samples (a recording's) and ranges (in time order, dropouts left out), then its frame;
    returns the frame's pose."""
    for sample in (*step.attitudes, *getattr(step, "imus", ())):
        pipe.feed(sample)
    for r in step.ranges:
        if r.sample is not None:
            pipe.feed(r.sample)
    return pipe.feed_frame(step.frame)


def dropped_frames(pipe: Pipeline, errors: int = 0) -> dict[str, int]:
    """The frames ``pipe`` did not give to its VO, by reason: the frame check's verdicts,
    the frames held for the autopilot's attitude, and ``errors`` (frames it raised on)."""
    counts = dict(pipe.frame_check.counts)
    counts["held_for_attitude"] = pipe.held_for_attitude
    counts["errors"] = errors
    return counts


def peak_rss_mb() -> float:
    """Peak resident set size of this process [MB]: Linux's VmHWM (the peak of this program's
    own memory), not getrusage's ru_maxrss, which Linux carries across exec from the parent
    (a process started by a 1.5 GB test worker reported 1.5 GB); ru_maxrss elsewhere."""
    try:
        with open("/proc/self/status", "rb") as fh:
            for line in fh:
                if line.startswith(b"VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_vo(
    config: Config,
    events: Iterable[Event],
    progress: Iterator[None] | None = None,
    camera: CameraModel | None = None,
    T_body_cam: F64 | None = None,
    checked: bool = False,
    observe: Callable[[CameraFrame, Pipeline], None] | None = None,
) -> VoRun:
    """Feed every event to a fresh Pipeline and record the VO output of every frame.

    ``checked``: the frames already passed the service's frame check (a recording of the
    service): the replay then does what the service did, frame for frame: no second check,
    and a frame on which the pipeline raises is logged, counted and skipped. ``observe``:
    called after each frame's work, outside the timed span (a benchmark's floor)."""
    pipe = Pipeline(config, camera, T_body_cam)
    run = VoRun()
    with GcPacing() as pacer:
        _run_frames(pipe, run, pacer, events, progress, checked, observe)
    run.gc = pacer.summary()
    run.resets = pipe.vo.resets
    run.peak_rss_mb = peak_rss_mb()
    run.dropped = dropped_frames(pipe, run.errors)
    run.gaps = pipe.gaps
    run.clock = pipe.clock.report() if pipe.clock is not None else None
    run.lens_focal, run.lens_warning = pipe.lens.result(), pipe.lens.warning
    return run


def _run_frames(
    pipe: Pipeline,
    run: VoRun,
    pacer: GcPacing,
    events: Iterable[Event],
    progress: Iterator[None] | None,
    checked: bool,
    observe: Callable[[CameraFrame, Pipeline], None] | None,
) -> None:
    """``run_vo``'s loop: each event into ``pipe``, each frame's results into ``run``."""
    for ev in events:
        if not isinstance(ev, CameraFrame):
            pipe.feed(ev)
        else:
            t0 = time.perf_counter()
            try:
                pose = pipe.feed_frame(ev, checked=checked)
            except Exception:
                if not checked:
                    raise
                log.exception("pipeline failed on frame %d (as in the service: skipped)", ev.seq)
                run.errors += 1
                continue
            if pose is not None:
                run.poses.append(pose)
            t1 = time.perf_counter()
            pipe.background_work()  # as the service does: after the pose is out
            t2 = time.perf_counter()
            pacer.after_frame()  # as the service does: after the frame's work
            t3 = time.perf_counter()
            run.frame_ms.append((t1 - t0) * 1e3)
            run.total_ms.append((t3 - t0) * 1e3)
            stages = dict(pipe.laps.ms)
            if "vo" in stages:  # the VO ran on this frame
                stages.update({f"vo: {k}": v for k, v in pipe.vo.laps.ms.items()})
            stages.update(pipe.background_laps.ms)
            stages[GC_STAGE] = (t3 - t2) * 1e3
            run.stage_ms.append(stages)
            if observe is not None:
                observe(ev, pipe)
            out = pipe.vo_output  # None: the frame check rejected the frame
            state = out.state if out is not None else VoState.LOST
            T = out.T_vo_cam if out is not None and state == VoState.TRACKING else None
            run.time_us.append(ev.time_us)
            run.state.append(state)
            run.keyframe.append(out is not None and out.is_keyframe)
            if out is not None:
                run.features.append(len(out.features.pixels))
            run.T_vo_cam.append(T if T is not None else np.full((4, 4), np.nan))
            seg = pipe.vo.resets if pipe.vo.ever_initialized else -1
            run.segment.append(seg)
            if progress is not None:
                next(progress, None)


@dataclass
class ScaleRun:
    """Per-frame record of a run with every scale method (SITL ground truth included).

    time_us (F,); tracking (F,); segment (F,); scale[name] (F,) NaN without an estimate;
    position[name] (F, 3) metric body positions (VO orientation); gt_scale (F,);
    gt_position (F, 3) true body positions, gt_cam_position (F, 3) true camera positions;
    vo_position (F, 3) unscaled camera positions in the VO frame; yaw_vo_rad at initialisation.
    """

    methods: list[str]
    time_us: list[int] = field(default_factory=list)
    tracking: list[bool] = field(default_factory=list)
    segment: list[int] = field(default_factory=list)
    scale: dict[str, list[float]] = field(default_factory=dict)
    position: dict[str, list[F64]] = field(default_factory=dict)
    gt_scale: list[float] = field(default_factory=list)
    gt_position: list[F64] = field(default_factory=list)
    gt_cam_position: list[F64] = field(default_factory=list)
    vo_position: list[F64] = field(default_factory=list)
    yaw_vo_rad: float = 0.0
    points_vo: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    points_frame: int = -1  # the frame whose map points_vo holds
    resets: int = 0
    dropped: dict[str, int] = field(default_factory=dict)  # frames not given to the VO
    clock: ClockReport | None = None  # the camera's clock at the end (vo.steady_clock)
    gaps: int = 0  # new VO maps after more than vo.max_gap_ms without a usable frame
    lens_focal: FocalRatio | None = None  # the focal length checked in flight (LensStage)
    lens_warning: str | None = None

    def metrics(self, settle_s: float = 5.0) -> list[ScaleMetrics]:
        """The accuracy of every method of the run (companion.evaluation.scale)."""
        return methods_metrics(
            self.methods,
            np.array(self.time_us) * 1e-6,
            np.array(self.tracking),
            self.yaw_vo_rad,
            {n: np.array(v) for n, v in self.scale.items()},
            np.array(self.gt_scale),
            {n: np.array(v) for n, v in self.position.items()},
            np.array(self.gt_position),
            settle_s,
        )


def run_scale(
    config: Config,
    steps: Iterable[Any],
    world: Any | None,
    progress: Iterator[None] | None = None,
    keep_points_at_s: float = 30.0,
    sensor_study: int = 0,
    camera: CameraModel | None = None,
    T_body_cam: F64 | None = None,
) -> ScaleRun:
    """Run the Pipeline with every scale method over SITL steps (``Scenario.steps()``) or a
    dataset's (``dataset_steps``), recording the truth: true positions (NaN without ground
    truth) and the ground-truth scale of every frame, ray cast in ``world`` (NaN without
    one: a dataset that declares no simulated world has no true scale). ``camera`` and
    ``T_body_cam``: a dataset's own calibration (None: the config's)."""
    from companion.evaluation.scale import gt_scale
    from companion.geometry import se3

    pipe = Pipeline(config, camera, T_body_cam, all_methods=True, sensor_study=sensor_study)
    names = list(pipe.methods)
    run = ScaleRun(names, scale={n: [] for n in names}, position={n: [] for n in names})
    nan3 = np.full(3, np.nan)
    T_body_cam = pipe.T_body_cam
    for step in steps:
        feed_step(pipe, step)
        pipe.finish_frame()  # the frame's own scale (after its pose)
        out = pipe.vo_output  # None: the frame check rejected the frame
        tracking = out is not None and out.state == VoState.TRACKING
        run.time_us.append(step.frame.time_us)
        run.tracking.append(tracking)
        run.segment.append(pipe.vo.resets)
        run.gt_position.append(step.T_world_body[:3, 3].copy())
        run.vo_position.append(out.T_vo_cam[:3, 3].copy() if out and tracking else nan3)
        run.gt_cam_position.append((step.T_world_body @ T_body_cam)[:3, 3])
        for n in names:
            est = pipe.estimates[n] if tracking else None
            pos = pipe.metric_positions[n] if tracking else None
            run.scale[n].append(est.scale if est is not None else float("nan"))
            run.position[n].append(pos if pos is not None and est is not None else nan3)
        s_true = float("nan")
        if out is not None and tracking and world is not None:
            f = out.features
            has = f.point_ids >= 0
            if has.any():
                T_world_cam = step.T_world_body @ T_body_cam
                rays = pipe.camera.pixels_to_rays(f.pixels[has])
                hits = world.raycast(
                    np.repeat(T_world_cam[None, :3, 3], len(rays), axis=0),
                    rays @ T_world_cam[:3, :3].T,
                )
                true_depth = hits.t_m * rays[:, 2]
                vo_depth = se3.transform(se3.inverse(out.T_vo_cam), f.points_vo[has])[:, 2]
                s_true = gt_scale(true_depth, vo_depth)
                t_s = (step.frame.time_us - run.time_us[0]) * 1e-6
                if t_s <= keep_points_at_s:  # the map at that time (or the last, if shorter)
                    run.points_vo = f.points_vo[has].copy()
                    run.points_frame = len(run.time_us) - 1
        run.gt_scale.append(s_true)
        if progress is not None:
            next(progress, None)
    run.yaw_vo_rad = pipe.vo.yaw_vo_rad
    run.resets = pipe.vo.resets
    run.dropped = dropped_frames(pipe)
    run.gaps = pipe.gaps
    run.clock = pipe.clock.report() if pipe.clock is not None else None
    run.lens_focal, run.lens_warning = pipe.lens.result(), pipe.lens.warning
    return run


def _tilt_of(R_world_body: F64) -> tuple[float, float]:
    """(roll, pitch) [rad] of a rotation (yaw does not enter)."""
    from companion.attitude.ground import tilt_from_normal

    return tilt_from_normal(R_world_body.T @ np.array([0.0, 0.0, 1.0]))


@dataclass
class AttitudeRun:
    """Per-frame roll/pitch [rad] of one SITL run, NaN where an estimate is missing.

    Series (F, 2) over (roll, pitch): truth; vo (VO rotation alone); ground (ranges relative to
    the ground under the hits); gravity (ranges, terrain-compensated); fused (the published
    attitude: the VO rotation with the configured anchors); fused_ranges (the fusion fed with
    the compensated range tilts alone, no autopilot anchor, for comparison).
    attitude_ms (F,) cost of the roll/pitch step; reasons: how often each refusal was seen.
    frames: what a replay needs (time_us, ranges used, cloud, segment, T_world_body).
    """

    time_us: list[int] = field(default_factory=list)
    series: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    attitude_ms: list[float] = field(default_factory=list)
    reasons: dict[str, int] = field(default_factory=dict)
    frames: list[tuple[int, Any, int, F64, F64 | None]] = field(default_factory=list)
    ranges_used: list[dict[int, float]] = field(default_factory=list)  # with frames

    def array(self, name: str) -> F64:
        return np.array(self.series[name], dtype=np.float64).reshape(-1, 2)


SERIES = ("truth", "vo", "ground", "gravity", "fused", "fused_ranges")


def run_attitude(
    config: Config,
    steps: Iterable[Any],
    progress: Iterator[None] | None = None,
    keep_frames: bool = False,
) -> AttitudeRun:
    """Run the Pipeline over SITL steps and record every roll/pitch estimate with the truth."""
    import dataclasses
    import re

    from companion.attitude.estimator import RollPitch

    pipe = Pipeline(config)
    if pipe.attitude is None:
        raise ValueError("roll/pitch needs 3 distance sensors and attitude.enabled")
    # the fusion fed by the compensated range tilts alone (no autopilot anchor), for comparison
    ranges_only = dataclasses.replace(config.attitude, fuse_ranges=True, autopilot_sigma_deg=0.0)
    ablation = RollPitch(pipe.specs, ranges_only)
    run = AttitudeRun(series={n: [] for n in SERIES})
    nan2 = (float("nan"), float("nan"))
    for step in steps:
        feed_step(pipe, step)
        pipe.finish_frame()  # the frame's own roll/pitch (after its pose)
        run.time_us.append(step.frame.time_us)
        row: dict[str, tuple[float, float]] = dict.fromkeys(SERIES, nan2)
        row["truth"] = _tilt_of(step.T_world_body[:3, :3])
        tilt, inp = pipe.tilt, pipe.tilt_input
        if tilt is not None and inp is not None:
            row["vo"] = _tilt_of(inp.cloud.R_vo_body)
            for name, est in (("ground", tilt.ground), ("gravity", tilt.gravity)):
                if est is not None:
                    row[name] = (est.roll_rad, est.pitch_rad)
            if tilt.fused is not None:
                row["fused"] = (tilt.fused.roll_rad, tilt.fused.pitch_rad)
            ap_now = pipe.attitude_at(step.frame.time_us)  # the frame's, resolved once
            other = ablation.step(
                step.frame.time_us, inp.range_m, inp.cloud, pipe.vo.resets, ap_now
            )
            if other.fused is not None:
                row["fused_ranges"] = (other.fused.roll_rad, other.fused.pitch_rad)
            for reason in tilt.reasons:
                key = re.sub(r"[0-9.]+ m", "x m", reason)
                run.reasons[key] = run.reasons.get(key, 0) + 1
            if keep_frames:
                run.frames.append(
                    (step.frame.time_us, inp.cloud, pipe.vo.resets, step.T_world_body, ap_now)
                )
                run.ranges_used.append(dict(inp.range_m))
        for name in SERIES:
            run.series[name].append(row[name])
        run.attitude_ms.append(pipe.laps.ms.get("roll/pitch", 0.0))
        if progress is not None:
            next(progress, None)
    return run


def replay_attitude(
    run: AttitudeRun,
    specs: dict[int, Any],
    opts: Any,
    ranges_at: Any,
) -> dict[str, F64]:
    """Re-run the roll/pitch estimator over the VO views recorded in ``run`` (keep_frames)
    with other sensors: ``ranges_at(time_us)`` gives their valid readings {id: metres}.
    Returns the (F, 2) series "ground", "gravity" and "fused" [rad] (NaN where refused)."""
    from companion.attitude.estimator import RollPitch

    est = RollPitch(specs, opts)
    out = {n: np.full((len(run.frames), 2), np.nan) for n in ("ground", "gravity", "fused")}
    for k, (time_us, cloud, segment, _, R_ap) in enumerate(run.frames):
        step = est.step(time_us, ranges_at(time_us), cloud, segment, R_ap)
        for name, tilt in (
            ("ground", step.ground),
            ("gravity", step.gravity),
            ("fused", step.fused),
        ):
            if tilt is not None:
                out[name][k] = (tilt.roll_rad, tilt.pitch_rad)
    return out


@dataclass
class DposeRun:
    """Per-frame d-Pose and VO poses of a SITL flight, relative to the arming pose.

    time_us (F,); height_m (F,) true height above the marks; truth, dpose, vo: (F, 4, 4)
    T_pattern_body (the body relative to its pose at arming; NaN where missing); reasons:
    how often d-Pose gave no pose and why; dpose_ms (F,) its cost per frame.
    """

    time_us: list[int] = field(default_factory=list)
    height_m: list[float] = field(default_factory=list)
    truth: list[F64] = field(default_factory=list)
    dpose: list[F64] = field(default_factory=list)
    vo: list[F64] = field(default_factory=list)
    reasons: dict[str, int] = field(default_factory=dict)
    dpose_ms: list[float] = field(default_factory=list)
    arm_time_us: int = 0


def run_dpose(config: Config, scenario: Any, arm_time_s: float) -> DposeRun:
    """Fly the SITL scenario (its rangefinders are the four d-Pose lasers, marks painted at
    arm_time_s): arm d-Pose at the first frame at or after arm_time_s with the lasers'
    readings, the true body pose (the world reference) and the autopilot's attitude; then run
    d-Pose and the VO pipeline on every frame."""
    from companion.dpose.estimator import Dpose
    from companion.geometry import se3

    pipe = Pipeline(config)
    dpose = Dpose(pipe.camera, pipe.T_body_cam, pipe.specs)
    run = DposeRun()
    nan44 = np.full((4, 4), np.nan)
    T_arm: F64 | None = None
    vo_anchor: tuple[F64, F64] | None = None  # (VO pose, true pose) at the first VO pose
    vo_reset = -1
    ranges_at = scenario.ranges.valid_at
    for step in scenario.steps():
        pose = feed_step(pipe, step)
        pipe.background_work()
        t_us = step.frame.time_us
        R_ap = pipe.attitude_at(t_us)
        if T_arm is None:
            if t_us * 1e-6 + 1e-9 < arm_time_s or R_ap is None:
                continue
            dpose.arm(ranges_at(t_us), step.T_world_body, R_ap)
            T_arm = step.T_world_body.copy()
            run.arm_time_us = t_us
        truth = se3.inverse(T_arm) @ step.T_world_body
        t0 = time.perf_counter()
        res = dpose.step(t_us, step.frame.image_bgr, R_ap, ranges_at(t_us))
        run.dpose_ms.append((time.perf_counter() - t0) * 1e3)
        if res is None:
            key = dpose.last_reason.split(" (")[0]
            run.reasons[key] = run.reasons.get(key, 0) + 1
        vo_rel = nan44
        if pose is not None:
            T_vo = se3.from_quat(pose.quat_wxyz_ned_frd, pose.position_ned_m)
            if vo_anchor is None or pose.reset_counter != vo_reset:
                # the VO is relative: anchor it to the truth once (and after a reset)
                vo_anchor, vo_reset = (T_vo, truth), pose.reset_counter
            vo_rel = vo_anchor[1] @ se3.inverse(vo_anchor[0]) @ T_vo
        run.time_us.append(t_us)
        assert dpose.pattern is not None
        run.height_m.append(float(dpose.pattern[:, 2].mean() - truth[2, 3]))
        run.truth.append(truth)
        run.dpose.append(res.T_pattern_body if res is not None else nan44)
        run.vo.append(vo_rel)
    return run


@dataclass
class PublishedRun:
    """What the autopilot would receive over a simulated flight: per published pose its time
    [s], position (3,) NED [m] and reset_counter, with the true body position (3,) and the
    true height above the surface [m] at that frame."""

    time_s: list[float] = field(default_factory=list)
    position: list[F64] = field(default_factory=list)
    reset_counter: list[int] = field(default_factory=list)
    truth: list[F64] = field(default_factory=list)
    height_m: list[float] = field(default_factory=list)
    vo_own: list[F64] = field(default_factory=list)  # the VO's position without d-Pose's offset
    dpose_used: list[bool] = field(default_factory=list)  # d-Pose corrected this pose
    dpose_armed_s: float | None = None  # when d-Pose was armed (None: never)
    vo_resets: int = 0
    frames: int = 0

    def array(self, name: str) -> F64:
        return np.asarray(getattr(self, name), dtype=np.float64)


def run_published(
    config: Config, steps: Iterable[Any], world: Any, progress: Iterator[None] | None = None
) -> PublishedRun:
    """The Pipeline as the service runs it (the published method, keyframe work after each
    pose) over SITL steps, recording every published pose against the truth."""
    pipe = Pipeline(config)
    run = PublishedRun()
    t0_us: int | None = None
    for step in steps:
        used = pipe.dpose_stage.offset.updates
        pose = feed_step(pipe, step)
        pipe.background_work()
        t0_us = step.frame.time_us if t0_us is None else t0_us
        run.frames += 1
        if pipe.dpose_stage.armed and run.dpose_armed_s is None:
            run.dpose_armed_s = (step.frame.time_us - t0_us) * 1e-6
        if pose is not None:
            x, y = step.T_world_body[0, 3], step.T_world_body[1, 3]
            ground = float(world.surface_height(np.array([x]), np.array([y]))[0])
            run.time_s.append((step.frame.time_us - t0_us) * 1e-6)
            run.position.append(pose.position_ned_m)
            run.reset_counter.append(pose.reset_counter)
            run.truth.append(step.T_world_body[:3, 3].copy())
            run.height_m.append(-float(step.T_world_body[2, 3]) - ground)
            run.vo_own.append(pose.position_ned_m - pipe.dpose_stage.offset.offset_m)
            run.dpose_used.append(pipe.dpose_stage.offset.updates > used)
        if progress is not None:
            next(progress)
    run.vo_resets = pipe.vo.resets
    return run
