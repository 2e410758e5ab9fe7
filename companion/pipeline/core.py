"""The one synchronous entry into the algorithms: feed the samples, then each frame.

The same Pipeline runs offline (``companion eval``), in the service, and in benchmarks; it is
deterministic (same inputs, same outputs) and does no I/O. Inputs must arrive in time order
per stream; attitude and ranges are buffered and looked up at each frame's capture time.
Every per-frame decision is the Pipeline's: the frame check (:meth:`Pipeline.check_frame`),
whether a frame waits for the autopilot's attitude (:meth:`Pipeline.hold_for_attitude`), the
VO, the metric scale, roll/pitch, the compass heading, the published pose and d-Pose. A pose
goes out with the scale and roll/pitch of the frame before (of the same VO map); the frame's
own update of them is work after the pose (:meth:`Pipeline.finish_frame`), with the keyframe.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from companion.attitude.estimator import RollPitch, TiltStep
from companion.config import Config
from companion.geometry import se3
from companion.geometry.camera import CameraModel
from companion.pipeline.dpose_stage import DposeStage
from companion.pipeline.gravity import MotionGravity, MotionSample, Segment
from companion.pipeline.ground import PadGravity, RangeGround
from companion.pipeline.heading import CompassHeading
from companion.pipeline.inputs import AttitudeHistory, Sample
from companion.pipeline.lens_stage import LensStage, take_lens
from companion.pipeline.output import PoseOutput
from companion.pipeline.scale_stage import (
    ScaleStage,
    TiltInput,
    body_rotation_in_vo,
    frame_input,
    lever_arm_m,
    roll_pitch,
)
from companion.pipeline.status import PipelineStatus, status_of
from companion.scale.laser import RangeHistory
from companion.scale.methods import ScaleInput
from companion.types import (
    F64,
    AttitudeSample,
    CameraFrame,
    ImuSample,
    PoseEstimate,
    RangeSample,
    VoOutput,
    VoState,
)
from companion.vo.frame_check import FrameCheck, FrameProblem
from companion.vo.frame_clock import FrameClock
from companion.vo.odometry import VisualOdometry
from companion.vo.stage_times import Laps

AFTER_POSE: tuple[str, ...] = ("scale update", "roll/pitch update", "keyframe decision")
AFTER_POSE += ("keyframe", "local BA", "lens check")  # Pipeline.background_work's, in order


class Pipeline:
    """VO, metric scale, roll/pitch, heading and d-Pose over time-ordered inputs."""

    def __init__(
        self,
        config: Config,
        camera: CameraModel | None = None,
        T_body_cam: F64 | None = None,
        all_methods: bool = False,
        sensor_study: int = 0,
    ) -> None:
        """``camera`` and ``T_body_cam`` override the config's (a dataset's own calibration);
        ``all_methods`` runs every scale method side by side (evaluation), not only the
        configured one."""
        self.config = config
        self.camera = camera or config.camera.model()
        self.T_body_cam = config.camera.T_body_cam() if T_body_cam is None else T_body_cam
        self.T_cam_body = se3.inverse(self.T_body_cam)
        self.vo = VisualOdometry(self.camera, self.T_body_cam, config.vo, config.camera.readout_s)
        self.frame_check = FrameCheck(config.vo)  # the one check of every delivered frame
        self.frame_problem: FrameProblem | None = None  # of the last frame fed
        # re-times the usable frames when their stamps jitter (None: vo.steady_clock off)
        self.clock = FrameClock() if config.vo.steady_clock else None
        self.gaps = 0  # times tracking was dropped after a gap between usable frames
        self._last_good_us: int | None = None
        self._first_frame_us: int | None = None  # d-Pose's arming clock starts here
        self.attitudes = AttitudeHistory()
        self.held_for_attitude = 0  # frames kept from a VO not tracking: no attitude yet
        self.waited_for_attitude = 0  # frames held by hold_for_attitude (no stream yet)
        self._first_held_us: int | None = None
        # maps dropped: begun before the autopilot's attitude stream (ArduPilot's comes late)
        self.heading_restarts = 0
        self.imu_gravity = MotionGravity(config.vo.imu_gravity_window_s)
        self.ranges = RangeHistory()
        self.ground = RangeGround(config, self.T_body_cam, self.ranges)
        self.specs = self.ground.specs
        self.pad = PadGravity(config, self.ground)
        self.compass = CompassHeading(config.vo)
        self.scale = ScaleStage(self.camera, config.scale, all_methods, sensor_study)
        self.method_name = self.scale.method_name
        self.methods, self.trajectories = self.scale.methods, self.scale.trajectories
        self.estimates, self.metric_positions = self.scale.estimates, self.scale.metric_positions
        self.scale_input: ScaleInput | None = None
        self.vo_output: VoOutput | None = None
        self.output = PoseOutput()
        self.attitude: RollPitch | None = None
        n_sensors = len(config.attitude.sensor_ids or self.specs)
        if config.attitude.enabled and n_sensors >= 3:
            self.attitude = RollPitch(self.specs, config.attitude)
        self.tilt: TiltStep | None = None  # the roll/pitch update of the last frame
        self.tilt_input: TiltInput | None = None  # its input
        self.pose_tilt: TiltStep | None = None  # the last update's: the next pose's roll/pitch
        self._pending: tuple[ScaleInput, dict[int, float], F64 | None] | None = None
        # the wall time [ms] of each stage of the last frame, to its pose and after it
        self.laps = Laps()
        self.background_laps = Laps()
        self.dpose_stage = DposeStage(config, self.camera, self.T_body_cam, self.specs)
        self.lens = LensStage(self.camera, self.T_body_cam, config.vo.learn_lens)

    def feed_attitude(self, sample: AttitudeSample) -> None:
        """Buffer an attitude sample (ignored unless finite and newer than the last)."""
        if self.attitudes.add(sample):
            self.vo.heading_required = True

    def feed_imu(self, sample: ImuSample) -> None:
        """Buffer an accelerometer sample (ignored unless finite and newer than the last)."""
        self.imu_gravity.imu.add(sample)

    def feed_range(self, sample: RangeSample) -> None:
        """Buffer a distance-sensor sample (invalid, unknown or late ones: counted, dropped)."""
        if sample.sensor_id not in self.specs:
            self.ranges.rejected += 1
            return
        self.ranges.add(sample)

    def feed(self, sample: Sample) -> None:
        """Buffer a sample of any stream (each in time order): the way in for all but frames."""
        if isinstance(sample, AttitudeSample):
            self.feed_attitude(sample)
        elif isinstance(sample, ImuSample):
            self.feed_imu(sample)
        else:
            self.feed_range(sample)

    def attitude_at(self, time_us: int) -> F64 | None:
        """(3, 3) R_world_body at ``time_us`` (AttitudeHistory.at), or None."""
        return self.attitudes.at(time_us)

    def check_frame(self, frame: CameraFrame) -> FrameProblem | None:
        """The camera check (frozen, dark, saturated, blank, out of order; counted in
        ``frame_check.counts``) of every delivered frame, also those never fed (a frozen frame
        is compared with the frame before it); :meth:`feed_frame` runs it unless ``checked``."""
        return self.frame_check.check(frame)

    def hold_for_attitude(self, frame: CameraFrame, autopilot_seen: bool) -> bool:
        """Whether to hold this frame from a VO that has not started: its frame's heading is
        the autopilot's attitude at its start (else the camera's first heading, turning the
        two frames by it for the whole flight). ArduPilot streams ATTITUDE only once asked,
        after its first HEARTBEAT; after ``service.attitude_wait_s`` from the first frame
        held the VO starts without one. Without an autopilot (``autopilot_seen`` False: a
        replay, a bench test) nothing is held. Held frames: ``waited_for_attitude``."""
        if (
            not autopilot_seen
            or self.vo.state == VoState.TRACKING
            or self.attitude_at(frame.time_us) is not None
        ):
            return False
        if self._first_held_us is None:
            self._first_held_us = frame.time_us
        wait_us = self.config.service.attitude_wait_s * 1e6
        if wait_us <= 0 or frame.time_us - self._first_held_us > wait_us:
            return False
        self.waited_for_attitude += 1
        return True

    def feed_frame(self, frame: CameraFrame, checked: bool = False) -> PoseEstimate | None:
        """Run the VO and the scale on a frame; the metric pose once tracking with a scale.

        The VO result stays in ``vo_output``, every method's scale in ``estimates`` and the
        metric body positions (VO orientation) in ``metric_positions``.

        A frame that the camera check rejects (``frame_problem``) gives no pose and is not
        seen by the VO; when usable frames resume more than ``vo.max_gap_ms`` after the last
        one, the VO drops its map and initialises anew, so the poses after a camera fault
        carry a new reset_counter. ``checked``: :meth:`check_frame` already ran on this frame
        (the service's camera reader runs it on every delivered frame)."""
        self.finish_frame()  # if background_work did not
        laps = self.laps
        laps.start()
        if self._first_frame_us is None:
            self._first_frame_us = frame.time_us
        self.scale_input = None
        self.tilt = None
        self.tilt_input = None
        self.frame_problem = None if checked else self.check_frame(frame)
        laps.lap("frame check")
        if self.frame_problem is not None:
            self.vo_output = None
            return None
        if self.clock is not None:
            steady_us = self.clock.time_us(frame.seq, frame.time_us)
            if steady_us != frame.time_us:
                frame = dataclasses.replace(frame, time_us=steady_us)
        last = self._last_good_us
        if last is not None and frame.time_us - last > self.config.vo.max_gap_ms * 1e3:
            self.vo.lose()
            self.gaps += 1
        self._last_good_us = frame.time_us
        R_world_body = self.attitude_at(frame.time_us)  # the frame's attitude, for every stage
        laps.lap("clock")
        out = self._vo_step(frame, R_world_body)
        self.vo_output = out
        if out is not None and self.lens.observe(
            out, R_world_body, self.vo.resets, self.vo.pixels_at_stamp
        ):
            self.camera = take_lens(self.lens, self.vo, self.methods, self.dpose_stage.dpose)
        laps.lap("vo")
        if out is None or out.state != VoState.TRACKING:
            return None
        inp, range_m = frame_input(
            self.specs, self.ranges, self.T_cam_body, out, self.vo, self.config.scale
        )
        self.scale_input = inp
        first = not self.scale.ready(inp.segment)  # a map's first frame: its update first
        if first:
            self.scale.update(inp)
        self.scale.positions(inp, self.lever_m(out))
        laps.lap("scale")
        if first:
            self._update_tilt(inp, range_m, R_world_body)
        else:
            self._pending = (inp, range_m, R_world_body)
        laps.lap("roll/pitch")
        position_vo_m = self.metric_positions.get(self.method_name)
        R_vo_body = self.R_vo_body()
        self.compass.step(frame.time_us, position_vo_m, R_vo_body, self.vo, self.imu_gravity.imu)
        pose = self._pose(frame.time_us)
        if position_vo_m is not None and R_vo_body is not None:
            p = np.array(position_vo_m, dtype=np.float64)
            motion = MotionSample(frame.time_us, self._segment(), R_vo_body, p, R_world_body)
            self.imu_gravity.remember(motion)
        laps.lap("heading, output")
        if pose is not None and self.dpose_stage.dpose is not None:
            assert self._first_frame_us is not None
            pose = self.dpose_stage.corrected(
                frame, self._first_frame_us, pose, R_world_body, dict(range_m)
            )
            laps.lap("d-Pose")
        return pose

    def _segment(self) -> Segment:
        """The current (VO map, published reset counter)."""
        return Segment(self.vo.resets, self.trajectories[self.method_name].reset_counter)

    def _vo_step(self, frame: CameraFrame, R_world_body: F64 | None) -> VoOutput | None:
        """The VO on a usable frame, with the priors it takes at a start (the reference
        attitude, the ground plane) and at keyframes (the IMU's and the pad's gravity); None
        when the frame is held for want of an attitude (``held_for_attitude``)."""
        vo = self.vo
        if vo.state == VoState.TRACKING and vo.heading_required and not vo.yaw_vo_known:
            # a map that started before the attitude stream did: its north is the camera's
            # first heading; it is dropped and the next one takes the autopilot's
            vo.lose()
            self.heading_restarts += 1
        if vo.state != VoState.TRACKING:
            if vo.heading_required and R_world_body is None:
                self.held_for_attitude += 1
                return None
            ref_us = vo.reference_time_us
            R_ref = None if ref_us is None else self.attitude_at(ref_us)
            if R_ref is not None:
                vo.set_reference_attitude(R_ref)
        plane = None
        if vo.state != VoState.TRACKING and self.config.vo.ground_init:
            plane = self.ground.ground_plane(frame.time_us, R_world_body)
        tracking = vo.state == VoState.TRACKING
        c = self.imu_gravity.at_frame(frame.time_us, tracking, vo.resets)
        g = None if c is None else (c.R_vo, c.sigma_rad)
        position_vo_m = self.metric_positions.get(self.method_name)
        down = self.pad.down(
            frame.time_us, R_world_body, position_vo_m, self._segment(), self.attitude_at
        )
        return vo.process(frame, R_world_body, plane, g, down)

    def finish_frame(self, laps: Laps | None = None) -> None:
        """The last tracked frame's scale and roll/pitch update (``_pending``), after its pose
        (ScaleStage): in :meth:`background_work`, else first in the next :meth:`feed_frame`."""
        if self._pending is None:
            return
        inp, range_m, R_world_body = self._pending
        self._pending = None
        self.scale.update(inp)
        if laps is not None:
            laps.lap("scale update")
        self._update_tilt(inp, range_m, R_world_body)
        if laps is not None:
            laps.lap("roll/pitch update")

    def _update_tilt(
        self, inp: ScaleInput, range_m: dict[int, float], R_world_body: F64 | None
    ) -> None:
        """Roll/pitch at the frame of ``inp`` (``tilt``, ``tilt_input``; ``pose_tilt``)."""
        est = self.estimates.get(self.method_name)
        self.tilt, self.tilt_input = roll_pitch(
            self.attitude, inp, range_m, est, self.T_cam_body, R_world_body
        )
        self.pose_tilt = self.tilt

    def _pose(self, time_us: int) -> PoseEstimate | None:
        """The published pose of the frame (companion/pipeline/output.py), before d-Pose."""
        est = self.estimates.get(self.method_name)
        p = self.metric_positions.get(self.method_name)
        R_vo_body = self.R_vo_body()
        if est is None or p is None or R_vo_body is None:
            return None
        reset_counter = self.trajectories[self.method_name].reset_counter
        tilt_error = self.attitude.filter.tilt_error if self.attitude is not None else None
        yaw, tilt = self.vo.yaw_vo_rad, self.pose_tilt  # the tilt: the last update's
        return self.output.pose(time_us, est, p, R_vo_body, yaw, reset_counter, tilt, tilt_error)

    def R_vo_body(self) -> F64 | None:
        """(3, 3) the body's orientation in the VO frame at the last frame, or None."""
        out = self.vo_output
        if out is None or not np.all(np.isfinite(out.T_vo_cam)):
            return None
        return body_rotation_in_vo(out.T_vo_cam, self.T_cam_body)

    def lever_m(self, out: VoOutput) -> F64:
        """(3,) camera -> body lever arm [m] in the VO frame's axes (``lever_arm_m``)."""
        return lever_arm_m(out.T_vo_cam, self.T_cam_body)

    def background_work(self) -> bool:
        """Work that the last frame's pose did not need (AFTER_POSE), run by the service after
        publishing, else by the next feed_frame first. Whether a keyframe or a lens check ran."""
        laps = self.background_laps
        laps.start()
        self.finish_frame(laps)
        self.vo.decide_keyframe()  # (else in finish_pending)
        laps.lap("keyframe decision")
        built = self.vo.finish_pending()
        laps.lap("keyframe")
        busy = self.vo.refine_map() or built
        laps.lap("local BA")
        lens = self.lens.work(busy)
        laps.lap("lens check")
        return lens or built

    def status(self) -> PipelineStatus:
        """An immutable snapshot of what the last frame left (for a status display on another
        thread: it never reads the pipeline's own, mutating state)."""
        return status_of(self)
