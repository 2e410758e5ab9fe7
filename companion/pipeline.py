"""The one synchronous entry into the algorithms: feed_attitude / feed_range / feed_frame.

The same Pipeline runs offline (``companion eval``), in the service, and in benchmarks; it is
deterministic (same inputs, same outputs) and does no I/O. Inputs must arrive in time order
per stream; attitude and ranges are buffered and looked up at each frame's capture time.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.attitude import ground as ground_fit
from companion.attitude.estimator import CloudView, RollPitch, TiltStep
from companion.attitude.fusion import corrected_rotation
from companion.attitude.gravity import (
    AttitudeCorrection,
    GravityEstimate,
    attitude_correction,
    gravity_from_motion,
)
from companion.attitude.heading import HeadingFix, MagHeading
from companion.attitude.pad import PadLevel
from companion.config import Config
from companion.dpose.estimator import Dpose
from companion.dpose.offset import DposeOffset
from companion.geometry import se3, so3
from companion.geometry.camera import CameraModel
from companion.scale.laser import RangeHistory, laser_point_cam
from companion.scale.methods import MetricTrajectory, ScaleInput, make_methods
from companion.types import (
    AttitudeSample,
    CameraFrame,
    GroundPlane,
    ImuSample,
    PoseEstimate,
    RangeSample,
    ScaleEstimate,
    VoOutput,
    VoState,
)
from companion.vo.frame_check import FrameCheck, FrameProblem
from companion.vo.odometry import Down, VisualOdometry

F64 = NDArray[np.float64]

ATTITUDE_MAX_GAP_US = 100_000  # an attitude older than this is not used for a frame
# the longest gap between two attitude samples that a frame's attitude is interpolated over
# (an autopilot's slowest default stream, ArduPilot's 4 Hz, is; a stall of seconds is not)
ATTITUDE_MAX_SPAN_US = 500_000
MIN_GROUND_SIGMA_REL = 0.01  # a ground start's scale is trusted to 1 % at best (the plane fit)
LANDED_HEIGHT_SIGMA_M = 0.02  # a configured landing-gear height: its uncertainty [m]
GROUND_REST_SPREAD_M = 0.02  # readings spreading more than this (or 3 sigma) are not at rest
VELOCITY_WINDOW_US = 150_000  # velocity = position difference over this long [us]
POSITION_SIGMA_FLOOR_M = 0.02  # added to the scale-derived position sigma [m]
SAMPLE_NOISE_ARM_M = 1.0  # one sample's position sigma: the scale's relative sigma times this [m]
VO_TILT_SIGMA_RAD = float(np.radians(0.5))  # roll/pitch sigma without the range fusion
VO_YAW_SIGMA_RAD = float(np.radians(2.0))  # yaw sigma of the VO (no absolute heading)
# vo.heading_source = magnetometer: the compass window ends when the VO sees the body move
# this far or turn this much from where the window started
MAG_STILL_MAX_MOVE_M = 0.1
MAG_STILL_MAX_TURN_RAD = float(np.radians(1.0))
IMU_BUFFER = 4096  # accelerometer samples kept (80 s at 50 Hz, 16 s at 250 Hz)
MOTION_BUFFER = 1024  # (time, map, R_vo_body, metric position) of the last frames kept
# the tilt correction of a 4 s window changes slowly: recomputed at most this often (~1 ms
# of Python per computation on the 2-core machine, docs/BENCHMARKS.md)
GRAVITY_REFRESH_US = 250_000
# the take-off pad's gravity (companion/attitude/pad.py): a plane of the readings every 10 ms
# (the TFmini's rate) while over the pad; at rest means still readings with the body at most
# PAD_REST_HEIGHT_M over their plane (a landing gear), and a sample further than
# PAD_MAX_ERROR_DEG from the autopilot's tilt is refused (a hit off the pad)
PAD_STEP_US = 10_000
PAD_REST_HEIGHT_M = 0.6
PAD_MAX_ERROR_DEG = 5.0
PAD_SIGMA_FLOOR_DEG = 0.1


class Pipeline:
    """VO (and, as they land, metric scale, attitude and d-Pose) over time-ordered inputs."""

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
        self.vo = VisualOdometry(self.camera, self.T_body_cam, config.vo)
        self.frame_check = FrameCheck(config.vo)
        self.frame_problem: FrameProblem | None = None  # of the last frame fed
        self.gaps = 0  # times tracking was dropped after a gap between usable frames
        self._last_good_us: int | None = None
        self._attitude: deque[AttitudeSample] = deque(maxlen=512)
        # frames kept from a VO that is not tracking because no attitude was at hand for them
        # once an attitude stream exists (a map's north is the autopilot's, never the camera's)
        self.held_for_attitude = 0
        # maps dropped because they had started without the autopilot's heading and its
        # attitude stream began later (ArduPilot's, asked for after its first HEARTBEAT)
        self.heading_restarts = 0
        # the published position's anchor for the current reset_counter: (reset_counter, the
        # NED offset [m] added to the rotated metric position) so that a new map continues
        # from the last published position whatever its heading (see _anchored)
        self._anchor: tuple[int, F64] | None = None
        self._last_position_ned_m: F64 | None = None
        # accelerometer samples and our own motion, for gravity in the VO frame
        self._imu: deque[ImuSample] = deque(maxlen=IMU_BUFFER)
        # (time, (VO map, reset counter), R_vo_body, metric position, autopilot R_world_body)
        self._motion: deque[tuple[int, tuple[int, int], F64, F64, F64 | None]] = deque(
            maxlen=MOTION_BUFFER
        )
        self.gravity: GravityEstimate | None = None  # the last window's gravity
        self.gravity_correction: AttitudeCorrection | None = None  # given to the VO
        self.gravity_used = 0  # frames that had one
        self._gravity_at: tuple[int, int] | None = None  # (time, VO map) of the last computation
        self.ranges = RangeHistory()
        o = config.vo
        self.pad: PadLevel | None = None  # the take-off pad's gravity for the VO's prior
        if o.pad_gravity_sigma_deg > 0:
            self.pad = PadLevel(
                int(o.pad_window_s * 1e6),
                float(np.radians(max(o.pad_gravity_sigma_deg, PAD_SIGMA_FLOOR_DEG))),
                float(np.radians(PAD_MAX_ERROR_DEG)),
            )
        self._pad_sampled_us = 0  # the last plane sampled over the pad
        # vo.heading_source = magnetometer: this VO map's compass window, the map it belongs to,
        # the body's VO position and yaw where it started, the mean turn since, frames in it
        self.mag_heading: MagHeading | None = None
        self._mag_window: tuple[int, F64, float] | None = None
        self._mag_turn = (0.0, 0)
        self.heading_fix: HeadingFix | None = None  # the fix the frame's heading took
        self.mag_heading_ended = False  # the body moved: no compass window any more
        self.specs = {r.sensor_id: r.spec() for r in config.rangefinders}
        self._beams_of: dict[tuple[int, ...], tuple[F64, F64]] = {}  # by sensor ids: origins, beams
        methods = make_methods(self.camera, config.scale, sensor_study)
        self.method_name = config.scale.method
        self.methods = methods if all_methods else {self.method_name: methods[self.method_name]}
        self.trajectories = {name: MetricTrajectory() for name in self.methods}
        self.estimates: dict[str, ScaleEstimate | None] = dict.fromkeys(self.methods)
        self.metric_positions: dict[str, F64 | None] = dict.fromkeys(self.methods)
        self.scale_input: ScaleInput | None = None
        self.vo_output: VoOutput | None = None
        # recent (time_us, reset_counter, position) for the velocity
        self._recent: deque[tuple[int, int, F64]] = deque(maxlen=16)
        self.last_scale_ms = 0.0  # time spent on the scale in the last frame [ms]
        self.attitude: RollPitch | None = None
        n_sensors = len(config.attitude.sensor_ids or self.specs)
        if config.attitude.enabled and n_sensors >= 3:
            self.attitude = RollPitch(self.specs, config.attitude)
        self.tilt: TiltStep | None = None  # the roll/pitch result of the last frame
        self.tilt_input: tuple[dict[int, float], CloudView] | None = None  # its input
        self.last_attitude_ms = 0.0  # time spent on roll/pitch in the last frame [ms]
        # d-Pose in the published pose (issue 18): armed on the published pose, then each of
        # its poses moves the published position (offset, added to the VO's) onto it
        self.dpose: Dpose | None = None
        if config.dpose.enabled and len(self.specs) == 4:
            self.dpose = Dpose(self.camera, self.T_body_cam, self.specs)
        d = config.dpose
        self.dpose_offset = DposeOffset(d.vo_drift_per_m, d.vo_drift_m_per_s, d.reset_m)
        self._first_frame_us: int | None = None  # d-Pose's arming clock starts here
        # d-Pose arming: (time [us], the pose and autopilot attitude at the window's start,
        # the four ranges [m] of every frame since)
        self._dpose_window: tuple[int, PoseEstimate, F64, list[dict[int, float]]] | None = None

    def feed_attitude(self, sample: AttitudeSample) -> None:
        """Buffer an attitude sample (ignored unless finite and newer than the last)."""
        if not np.all(np.isfinite(sample.quat_wxyz)):
            return
        if self._attitude and sample.time_us <= self._attitude[-1].time_us:
            return
        self._attitude.append(sample)
        self.vo.heading_required = True

    def feed_imu(self, sample: ImuSample) -> None:
        """Buffer an accelerometer sample (ignored unless finite and newer than the last)."""
        if not np.all(np.isfinite(sample.accel_frd_m_s2)):
            return
        if self._imu and sample.time_us <= self._imu[-1].time_us:
            return
        self._imu.append(sample)

    def feed_range(self, sample: RangeSample) -> None:
        """Buffer a distance-sensor sample (invalid, unknown or out-of-order ones are counted
        and dropped)."""
        if sample.sensor_id not in self.specs:
            self.ranges.rejected += 1
            return
        self.ranges.add(sample)

    def attitude_at(self, time_us: int) -> F64 | None:
        """R_world_body at ``time_us`` by slerp between the bracketing samples when they are at
        most ATTITUDE_MAX_SPAN_US apart, else the nearest one within ATTITUDE_MAX_GAP_US; None
        when there is none close enough."""
        if not self._attitude:
            return None
        # from the newest end: the times asked for are the last few frames' (a scan of the
        # whole buffer from its oldest end cost ~0.3 ms a call on a slow board)
        before = after = None
        for a in reversed(self._attitude):
            if a.time_us <= time_us:
                before = a
                break
            after = a
        if before is not None and after is not None:
            span_us = after.time_us - before.time_us
            if 0 < span_us <= ATTITUDE_MAX_SPAN_US:
                alpha = (time_us - before.time_us) / span_us
                R0 = so3.quat_to_matrix(before.quat_wxyz)
                R1 = so3.quat_to_matrix(after.quat_wxyz)
                return R0 @ so3.exp(alpha * so3.log(R0.T @ R1))
            # a gap in the stream (a stall): no slerp across it, the nearer if close enough
            if time_us - before.time_us <= after.time_us - time_us:
                after = None
            else:
                before = None
        near = before or after
        assert near is not None
        if abs(near.time_us - time_us) > ATTITUDE_MAX_GAP_US:
            return None
        return so3.quat_to_matrix(near.quat_wxyz)

    def feed_frame(self, frame: CameraFrame, checked: bool = False) -> PoseEstimate | None:
        """Run the VO and the scale on a frame; the metric pose once tracking with a scale.

        The VO result stays in ``vo_output``, every method's scale in ``estimates`` and the
        metric body positions (VO orientation) in ``metric_positions``.

        A frame that the camera check rejects (frozen, dark, saturated, blank, out of order:
        ``frame_problem``) gives no pose and is not seen by the VO; when usable frames
        resume more than ``vo.max_gap_ms`` after the last one, the VO drops its map and
        initialises anew, so the poses after a camera fault carry a new reset_counter.
        ``checked``: the caller already ran a FrameCheck on every delivered frame (the
        service does, in its camera reader), so it is not run again here."""
        if self._first_frame_us is None:
            self._first_frame_us = frame.time_us
        self.scale_input = None
        self.tilt = None
        self.tilt_input = None
        self.last_scale_ms = 0.0
        self.last_attitude_ms = 0.0
        self.frame_problem = None if checked else self.frame_check.check(frame)
        if self.frame_problem is not None:
            self.vo_output = None
            return None
        last = self._last_good_us
        if last is not None and frame.time_us - last > self.config.vo.max_gap_ms * 1e3:
            self.vo.lose()
            self.gaps += 1
        self._last_good_us = frame.time_us
        R_world_body = self.attitude_at(frame.time_us)
        vo = self.vo
        if vo.state == VoState.TRACKING and vo.heading_required and not vo.yaw_vo_known:
            # a map that started before the attitude stream did: its north is the camera's
            # first heading; it is dropped and the next one takes the autopilot's
            vo.lose()
            self.heading_restarts += 1
        if vo.state != VoState.TRACKING:
            if vo.heading_required and R_world_body is None:
                self.held_for_attitude += 1
                self.vo_output = None
                return None
            ref_us = vo.reference_time_us
            R_ref = None if ref_us is None else self.attitude_at(ref_us)
            if R_ref is not None:
                vo.set_reference_attitude(R_ref)
        plane = None
        if self.vo.state != VoState.TRACKING and self.config.vo.ground_init:
            plane = self.ground_plane(frame.time_us, R_world_body)
        c = self._gravity_correction(frame.time_us)
        g = None if c is None else (c.R_vo, c.sigma_rad)
        self.gravity_used += g is not None
        down = self._pad_gravity(frame.time_us, R_world_body)
        self.vo_output = out = self.vo.process(frame, R_world_body, plane, g, down)
        if out.state != VoState.TRACKING:
            return None
        t0 = time.perf_counter()
        T_cam_vo = se3.inverse(out.T_vo_cam)
        opts = self.config.scale
        lasers: dict[int, tuple[float, F64, float]] = {}
        for sid in sorted(self.specs):
            d = self.ranges.at(sid, frame.time_us, opts.max_range_gap_us, opts.max_range_age_us)
            if d is None:
                continue
            spec = self.specs[sid]
            lasers[sid] = (d, laser_point_cam(spec, self.T_cam_body, d), spec.sigma_m(d))
        prior = None
        if self.vo.metric_sigma_rel is not None:  # a map started on the ground: unit = 1 m
            prior = (1.0, max(self.vo.metric_sigma_rel, MIN_GROUND_SIGMA_REL))
        inp = ScaleInput(frame.time_us, out, T_cam_vo, lasers, self.vo.resets, prior)
        self.scale_input = inp
        # The camera's VO position is what the scale multiplies; the body sits a metric lever
        # arm away from it (see lever_m)
        c_vo = out.T_vo_cam[:3, 3]
        lever_m = self.lever_m(out)
        for name, method in self.methods.items():
            est = method.step(inp)
            self.estimates[name] = est
            if est is not None:
                cam_m = self.trajectories[name].step(c_vo, est.scale, inp.segment)
                self.metric_positions[name] = cam_m + lever_m
        self.last_scale_ms = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        self.tilt = self._tilt(frame.time_us, {sid: v[0] for sid, v in lasers.items()})
        self.last_attitude_ms = (time.perf_counter() - t0) * 1e3
        self._magnetometer_heading(frame.time_us)
        pose = self._pose(frame.time_us)
        self._remember_motion(frame.time_us, R_world_body)
        if pose is not None and self.dpose is not None:
            pose = self._dpose_corrected(frame, pose, {s: v[0] for s, v in lasers.items()})
        return pose

    def _dpose_corrected(
        self, frame: CameraFrame, pose: PoseEstimate, range_m: dict[int, float]
    ) -> PoseEstimate:
        """The published pose with d-Pose's correction (thesis abstract: the direct pose is
        metric and drift-free). Armed ``dpose.arm_after_s`` after the first frame,
        with the four lasers' readings then (the marks are left where they hit) and the
        published pose then as the pattern's place in the world. Afterwards every d-Pose
        pose (marks in view, translation sigma <= ``dpose.max_sigma_m``) updates the offset
        added to the VO's position towards d-Pose minus VO (companion/dpose/offset.py): with
        a gain from the VO's drift since the last one and d-Pose's sigma, at once and with a
        new reset_counter when the gap exceeds ``dpose.reset_m`` (EKF2 re-anchors its vision
        frame instead of fusing a jump)."""
        assert self.dpose is not None
        o = self.config.dpose
        R_ap = self.attitude_at(frame.time_us)
        if not self.dpose.armed:
            start_us = frame.time_us if self._first_frame_us is None else self._first_frame_us
            waited = (frame.time_us - start_us) * 1e-6 >= o.arm_after_s
            if waited and R_ap is not None and len(range_m) == 4:
                self._arm_dpose(frame.time_us, pose, R_ap, range_m)
        else:
            res = self.dpose.step(frame.time_us, frame.image_bgr, R_ap, range_m or None)
            sigma_m = np.inf if res is None else float(np.sqrt(np.max(np.diag(res.cov_6x6)[3:])))
            if res is not None and sigma_m <= o.max_sigma_m:
                self.dpose_offset.update(
                    pose.time_us, pose.position_ned_m, res.T_world_body[:3, 3], sigma_m
                )
            else:
                self.dpose_offset.move(pose.position_ned_m)
        off = self.dpose_offset
        if not off.resets and not np.any(off.offset_m):
            return pose
        return dataclasses.replace(
            pose,
            position_ned_m=pose.position_ned_m + off.offset_m,
            reset_counter=pose.reset_counter + off.resets,
        )

    @property
    def dpose_offset_m(self) -> F64:
        """(3,) [m] what d-Pose adds to the VO's position (companion/dpose/offset.py)."""
        return self.dpose_offset.offset_m

    @property
    def dpose_resets(self) -> int:
        """Corrections applied at once (each a new reset_counter)."""
        return self.dpose_offset.resets

    @property
    def dpose_used(self) -> int:
        """d-Pose poses that corrected the published position."""
        return self.dpose_offset.updates

    def _arm_dpose(
        self, time_us: int, pose: PoseEstimate, R_ap: F64, range_m: dict[int, float]
    ) -> None:
        """Arm d-Pose once the vehicle has hovered ``dpose.arm_window_s`` (the published
        position within ``dpose.arm_max_motion_m`` of the window's start): the pattern from
        the four ranges averaged over the window (each reading's noise divided by about the
        square root of the frames in it: the pattern's error is the bias of every later
        d-Pose pose), the world reference the published pose at the window's start (when the
        marks are left). A window where the vehicle moved starts again."""
        assert self.dpose is not None
        o = self.config.dpose
        w = self._dpose_window
        moved = w is not None and (
            float(np.linalg.norm(pose.position_ned_m - w[1].position_ned_m)) > o.arm_max_motion_m
        )
        if w is None or moved:
            w = self._dpose_window = (time_us, pose, R_ap, [])
        w[3].append(range_m)
        if (time_us - w[0]) * 1e-6 < o.arm_window_s:
            return
        mean_range_m = {s: float(np.mean([r[s] for r in w[3]])) for s in range_m}
        # the pattern's place: the published position and heading, the autopilot's roll and
        # pitch (drift-free; the published tilt carries the VO frame's, 0.76 deg in
        # config/pad.toml's seed 1, which tilted every d-Pose displacement from the pad's
        # centre: 1.6 cm of height 1.2 m off it; docs/decisions.md, "d-Pose's pattern tilt")
        roll, pitch, _ = so3.matrix_to_rpy(w[2])
        _, _, yaw = so3.matrix_to_rpy(so3.quat_to_matrix(w[1].quat_wxyz_ned_frd))
        T_world_body = se3.make(so3.rpy_to_matrix(roll, pitch, yaw), w[1].position_ned_m)
        self.dpose.arm(mean_range_m, T_world_body, w[2])
        self.dpose_offset.arm(w[1].time_us, w[1].position_ned_m)
        self._dpose_window = None

    def ground_plane(self, time_us: int, R_world_body: F64 | None) -> GroundPlane | None:
        """The ground under the camera in metres, or None (DESIGN.md section 4 reconstructs
        the plane from three sensors for roll/pitch; here it starts the VO map).

        The plane of the readings at rest (:meth:`rest_plane_body`) when the camera is within
        ``vo.ground_max_height_m`` of it. When >= 3 sensors read below their minimum instead
        (too close: on the ground), the plane is level at ``vo.landed_camera_height_m`` under
        the autopilot's attitude, if that height is configured."""
        o = self.config.vo
        rest = self.rest_plane_body(time_us)
        if rest is not None:
            return self._plane_in_camera(*rest, "ranges")
        t0 = time_us - int(o.ground_window_ms * 1e3)
        too_close = [s for s, t in self.ranges.too_close_us.items() if t >= t0]
        if len(too_close) >= 3 and o.landed_camera_height_m > 0 and R_world_body is not None:
            n_body = R_world_body.T @ np.array([0.0, 0.0, 1.0])  # level ground: gravity
            h_cam = o.landed_camera_height_m
            h_body = h_cam + float(n_body @ self.T_body_cam[:3, 3])
            return self._plane_in_camera(n_body, h_body, LANDED_HEIGHT_SIGMA_M, "landed")
        return None

    def rest_plane_body(self, time_us: int) -> tuple[F64, float, float] | None:
        """The ground plane of the readings at rest: (its downward normal (3,) in the body
        frame, the body origin's distance to it [m], that distance's sigma [m]), or None.

        From the readings of the last ``vo.ground_window_ms`` of each sensor (their median;
        none when any sensor's readings spread more than 3 sigma or 2 cm: the vehicle is not at
        rest, e.g. low over a roof edge), >= 3 sensors: the least-squares plane through
        their hit points in the body frame, refused unless it fits them within
        ``vo.ground_max_rms_m``. The distance's sigma propagates each median's sigma (reading
        sigma / sqrt(n)) through the fit."""
        o = self.config.vo
        t0 = time_us - int(o.ground_window_ms * 1e3)
        ids, med, sig = [], [], []
        for sid in sorted(self.specs):
            d = self.ranges.window(sid, t0, time_us)
            if len(d) < 3:
                continue
            m = float(np.median(d))
            sigma = self.specs[sid].sigma_m(m)
            mad = 1.4826 * float(np.median(np.abs(d - m)))  # robust spread of the window
            if mad > max(3.0 * sigma, GROUND_REST_SPREAD_M):
                return None  # readings moving: not at rest on the ground (a roof edge, a climb)
            ids.append(sid)
            med.append(m)
            sig.append(sigma * 1.25 / np.sqrt(len(d)))
        if len(ids) < 3:
            return None
        fit = self._range_plane(ids, np.array(med))
        if fit is None:
            return None
        n_body, h_body, M = fit
        sigma_a = float(np.sqrt(np.sum((M[0] * np.array(sig)) ** 2)))
        return n_body, h_body, max(sigma_a, 1e-3)

    def _range_plane(self, ids: list[int], range_m: F64) -> tuple[F64, float, F64] | None:
        """The plane through the hits of sensors ``ids`` at ``range_m`` (K,): (downward normal
        (3,), body origin's distance [m], the fit's (3, K) matrix), in the body frame; None
        when the hits are nearly on a line or fit no plane within ``vo.ground_max_rms_m``."""
        key = tuple(ids)
        beams_of = self._beams_of.get(key)
        if beams_of is None:
            T = np.stack([self.specs[s].T_body_rf for s in ids])
            beams_of = self._beams_of[key] = ground_fit.beams_body(T)
        origins, beams = beams_of
        pts = ground_fit.ground_points_body(origins, beams, range_m)
        (a, b, c), M = ground_fit.plane_fit(pts)
        rms = float(np.sqrt(np.mean((pts[:, 2] - (a + b * pts[:, 0] + c * pts[:, 1])) ** 2)))
        if rms > self.config.vo.ground_max_rms_m or ground_fit.spread_m(pts) < 0.05:
            return None
        n_body = ground_fit.normal_of(b, c)
        return n_body, float(n_body @ np.array([0.0, 0.0, a])), M

    def _pad_gravity(self, time_us: int, R_world_body: F64 | None) -> Down | None:
        """The take-off pad's gravity for this frame's keyframe (companion/attitude/pad.py),
        or None (off, no attitude, not over the pad, too few samples yet). At rest on the
        pad it measures the pad; at rest and over it (within ``vo.pad_radius_m`` of the rest,
        the last frame's position) it samples the readings' plane every PAD_STEP_US since the
        last frame against the autopilot's attitude at that instant."""
        pad = self.pad
        if pad is None or R_world_body is None:
            return None
        position = self.metric_positions.get(self.method_name)
        segment = (self.vo.resets, self.trajectories[self.method_name].reset_counter)
        rest = self.rest_plane_body(time_us)
        if rest is not None and rest[1] <= PAD_REST_HEIGHT_M:
            pad.at_rest(time_us, rest[0], R_world_body, position, segment)
        elif not pad.near(position, segment, self.config.vo.pad_radius_m):
            self._pad_sampled_us = time_us
            return None
        opts = self.config.scale
        t = max(self._pad_sampled_us, time_us - int(self.config.vo.pad_window_s * 1e6))
        while t + PAD_STEP_US <= time_us:
            t += PAD_STEP_US
            ids, range_m = [], []
            for sid in sorted(self.specs):
                d = self.ranges.at(sid, t, opts.max_range_gap_us, opts.max_range_age_us)
                if d is not None:
                    ids.append(sid)
                    range_m.append(d)
            R = self.attitude_at(t)
            fit = self._range_plane(ids, np.array(range_m)) if len(ids) >= 3 else None
            if fit is not None and R is not None:
                pad.sample(t, fit[0], R)
        self._pad_sampled_us = t
        return pad.down_body(time_us, R_world_body)

    def _plane_in_camera(
        self, n_body: F64, h_body: float, sigma_m: float, source: str
    ) -> GroundPlane | None:
        """The plane n_body . p = h_body (body frame) seen from the camera, if near enough."""
        R_body_cam, t_body_cam = self.T_body_cam[:3, :3], self.T_body_cam[:3, 3]
        n_cam = R_body_cam.T @ n_body
        d_cam = h_body - float(n_body @ t_body_cam)
        if not 0.0 < d_cam <= self.config.vo.ground_max_height_m:
            return None
        return GroundPlane(np.asarray(n_cam, dtype=np.float64), d_cam, sigma_m, source)

    def background_work(self) -> bool:
        """Work that the last frame's pose did not need (building a keyframe: triangulation
        and local bundle adjustment). The service runs it after publishing; if nobody calls
        it, the next feed_frame does it first. Returns whether there was any."""
        return self.vo.finish_pending()

    def _magnetometer_heading(self, time_us: int) -> None:
        """``vo.heading_source = magnetometer``: the VO frame's heading from our own compass
        (companion/attitude/heading.py). From a VO map's first tracking frame the IMU samples
        (SCALED_IMU's accelerometer, gyroscope and raw field) are averaged while the body
        stands still; once they span ``vo.mag_heading_min_s`` the frame's heading becomes
        the compass's body heading minus the body's yaw in the VO frame (its mean over the
        window), and it is refined with every frame until the body moves (the IMU, or the VO
        seeing it move MAG_STILL_MAX_MOVE_M or turn MAG_STILL_MAX_TURN_RAD). Then it stays
        for the map's life (a later change would turn the published trajectory about the
        map's origin), and no later map takes the compass's: the first motion is the take-off,
        and in the air the accelerometer is no level and the motors disturb the field (a map
        after a VO reset takes the autopilot's heading, which fused ours). On the ground the
        position is at that origin, so the turn moves it by millimetres; the published yaw
        steps by the compass's correction (< 2 deg on PX4 SIH), which EKF2 fuses as a yaw
        measurement."""
        o = self.config.vo
        if o.heading_source != "magnetometer" or self.mag_heading_ended:
            return
        p = self.metric_positions.get(self.method_name)
        R = self.R_vo_body()
        if p is None or R is None:
            return
        yaw_body_vo = so3.matrix_to_rpy(R)[2]
        w = self._mag_window
        h = self.mag_heading
        if h is None or w is None or w[0] != self.vo.resets:
            h = self.mag_heading = MagHeading(float(np.radians(o.mag_declination_deg)))
            h.last_us = time_us  # the window starts at the map's first pose
            w = self._mag_window = (self.vo.resets, np.array(p, dtype=np.float64), yaw_body_vo)
            self._mag_turn = (0.0, 0)
        start = h.last_us if h.last_us is not None else time_us
        fresh = []
        for sample in reversed(self._imu):  # from the newest end: only the last frame's
            if sample.time_us <= start:
                break
            if sample.time_us <= time_us:
                fresh.append(sample)
        for sample in reversed(fresh):
            h.add(sample)
        turn = math.remainder(yaw_body_vo - w[2], math.tau)  # wrapped to [-pi, pi]
        if (
            float(np.linalg.norm(p - w[1])) > MAG_STILL_MAX_MOVE_M
            or abs(turn) > MAG_STILL_MAX_TURN_RAD
        ):
            h.moved = True
        if h.moved:
            self.mag_heading_ended = True
            return
        total, n = self._mag_turn
        self._mag_turn = (total + turn, n + 1)
        fix = h.fix()
        if fix is None or fix.span_us < o.mag_heading_min_s * 1e6:
            return
        mean_yaw_body_vo = w[2] + self._mag_turn[0] / self._mag_turn[1]
        self.vo.yaw_vo_rad = math.remainder(fix.yaw_rad - mean_yaw_body_vo, math.tau)
        self.vo.yaw_vo_known = True
        self.heading_fix = fix

    def _remember_motion(self, time_us: int, R_world_body: F64 | None) -> None:
        """The body's rotation and metric position in the VO frame at this frame, for
        :meth:`_imu_gravity` (with the VO map and the published trajectory's reset counter:
        positions of different maps or across a jump are not differenced)."""
        p = self.metric_positions.get(self.method_name)
        R = self.R_vo_body()
        if p is None or R is None or self.config.vo.imu_gravity_window_s <= 0:
            return
        seg = (self.vo.resets, self.trajectories[self.method_name].reset_counter)
        self._motion.append((time_us, seg, R, np.array(p, dtype=np.float64), R_world_body))

    def _gravity_correction(self, time_us: int) -> AttitudeCorrection | None:
        """:meth:`_imu_gravity`, recomputed every GRAVITY_REFRESH_US of one VO map (the last
        one kept in between); kept in ``gravity_correction``."""
        last = self._gravity_at
        fresh = (
            last is not None
            and last[1] == self.vo.resets
            and 0 <= time_us - last[0] < GRAVITY_REFRESH_US
        )
        if not fresh:
            self.gravity_correction = self._imu_gravity(time_us)
            self._gravity_at = (time_us, self.vo.resets)
        return self.gravity_correction

    def _imu_gravity(self, time_us: int) -> AttitudeCorrection | None:
        """The correction of the autopilot's gravity from the accelerometer samples and our
        motion over the last ``vo.imu_gravity_window_s`` (companion/attitude/gravity.py:
        gravity in the current VO map's frame, then the autopilot's mean tilt error against it
        in the window); None without accelerometer samples or attitudes, before the window is
        covered, or off (window 0). The window's gravity stays in ``gravity``."""
        window_s = self.config.vo.imu_gravity_window_s
        if window_s <= 0 or not self._imu or not self._motion:
            return None
        if self.vo.state != VoState.TRACKING:
            return None
        seg = self._motion[-1][1]
        if seg[0] != self.vo.resets:
            return None
        t_from = self._motion[-1][0] - int((window_s + 0.5) * 1e6)
        rows = []
        for m in reversed(self._motion):
            if m[1] != seg or m[0] < t_from:
                break
            rows.append(m)
        if len(rows) < 3:
            return None
        rows.reverse()
        t_pose = np.array([r[0] for r in rows], dtype=np.int64)
        imu = []
        for s in reversed(self._imu):
            if s.time_us < t_pose[0]:
                break
            if s.time_us <= time_us:
                imu.append(s)
        if not imu:
            return None
        imu.reverse()
        self.gravity = est = gravity_from_motion(
            np.array([s.time_us for s in imu], dtype=np.int64),
            np.array([s.accel_frd_m_s2 for s in imu], dtype=np.float64),
            t_pose,
            np.stack([r[2] for r in rows]),
            np.stack([r[3] for r in rows]),
            window_s,
        )
        if est is None:
            return None
        # (our rotation, the autopilot's attitude) of the window's frames that had one
        pairs = [(r[2], r[4]) for r in rows if est.t0_us <= r[0] <= est.t1_us and r[4] is not None]
        if len(pairs) < 3:
            return None
        R_vo_body, R_world_body = (np.stack(x) for x in zip(*pairs, strict=True))
        return attitude_correction(est.down_vo, est.sigma_rad, R_vo_body, R_world_body)

    def _tilt(self, time_us: int, range_m: dict[int, float]) -> TiltStep | None:
        """Roll/pitch from the ranges at the frame, compensated with the scaled VO cloud."""
        out = self.vo_output
        R_vo_body = self.R_vo_body()
        if self.attitude is None or out is None or R_vo_body is None:
            return None
        est = self.estimates.get(self.method_name)
        points = np.zeros((0, 3))
        position = np.zeros(3)
        if est is not None and est.scale > 0:
            f = out.features
            points = f.points_vo[f.point_ids >= 0] * est.scale
            position = out.T_vo_cam[:3, 3] * est.scale + self.lever_m(out)
        cloud = CloudView(R_vo_body, position, points)
        self.tilt_input = (range_m, cloud)
        return self.attitude.step(
            time_us, range_m, cloud, self.vo.resets, self.attitude_at(time_us)
        )

    def _pose(self, time_us: int) -> PoseEstimate | None:
        est = self.estimates.get(self.method_name)
        p = self.metric_positions.get(self.method_name)
        R_vo_body = self.R_vo_body()
        if est is None or p is None or R_vo_body is None:
            return None
        R_world_vo = so3.rot_z(self.vo.yaw_vo_rad)
        reset_counter = self.trajectories[self.method_name].reset_counter
        position = self._anchored(R_world_vo @ p, reset_counter)
        velocity = self._velocity(time_us, reset_counter, position)
        # covariance over (x, y, z, roll, pitch, yaw), for an autopilot's filter that takes
        # it as one sample's white measurement noise (EKF2: R = max(ours, EKF2_EVP_NOISE^2)).
        # Position: a 2 cm floor plus the scale's relative sigma over one metre (the part of
        # our error that changes from sample to sample: a scale update moves the local map by
        # that much per metre). Not the drift since the map's origin (that sigma times the
        # distance travelled, until 2026-11-28): drift is correlated over minutes, no filter
        # averages it away, and as noise it only weighed our later samples less than the
        # earlier ones (docs/decisions.md, "What EKF2 adds to our height"). Roll/pitch from
        # the fused tilt (else a VO default); yaw from the VO default
        rel = est.sigma / est.scale if est.scale > 0 else 1.0
        cov = np.zeros((6, 6))
        sigma_p = rel * SAMPLE_NOISE_ARM_M + POSITION_SIGMA_FLOOR_M
        cov[:3, :3] = np.eye(3) * sigma_p**2
        cov[3:5, 3:5] = np.eye(2) * VO_TILT_SIGMA_RAD**2
        cov[5, 5] = VO_YAW_SIGMA_RAD**2
        fused = self.tilt.fused if self.tilt is not None else None
        if fused is not None and self.attitude is not None:
            R_vo_body = corrected_rotation(self.attitude.filter.tilt_error, R_vo_body)
            cov[3:5, 3:5] = fused.cov_rad2
        quality = int(np.clip(100.0 * (1.0 - 10.0 * rel), 0, 100)) if np.isfinite(rel) else 0
        return PoseEstimate(
            time_us,
            position,
            so3.matrix_to_quat(R_world_vo @ R_vo_body),
            velocity,
            cov,
            reset_counter,
            quality,
        )

    def _anchored(self, position_ned_m: F64, reset_counter: int) -> F64:
        """(3,) [m] the published NED position: the metric position turned by the map's
        heading plus the anchor of its reset_counter. A new map (a new reset_counter) is
        anchored at the last published position: the metric trajectory continues from there
        in its own axes (MetricTrajectory), but a map that starts on another heading than the
        last one would otherwise turn the whole track about the first map's origin and jump
        by up to twice the distance flown."""
        a = self._anchor
        if a is None or a[0] != reset_counter:
            last = self._last_position_ned_m
            offset = np.zeros(3) if last is None else last - position_ned_m
            self._anchor = a = (reset_counter, offset)
        anchored: F64 = position_ned_m + a[1]
        self._last_position_ned_m = anchored
        return anchored

    def _velocity(self, time_us: int, reset_counter: int, position: F64) -> F64:
        """NED velocity [m/s] as the difference over the last VELOCITY_WINDOW_US of poses of
        the same VO map (a longer base than one frame: frame-to-frame noise divided by 33 ms
        would dominate); NaN until such a pose exists (after a reset or a gap)."""
        recent = self._recent
        while recent and (
            recent[0][1] != reset_counter or time_us - recent[0][0] > VELOCITY_WINDOW_US
        ):
            recent.popleft()
        velocity = np.full(3, np.nan)
        if recent and time_us - recent[0][0] >= VELOCITY_WINDOW_US // 2:
            velocity = (position - recent[0][2]) / ((time_us - recent[0][0]) * 1e-6)
        recent.append((time_us, reset_counter, position))
        return velocity

    def R_vo_body(self) -> F64 | None:
        """(3, 3) the body's orientation in the VO frame at the last frame, or None. (No
        T_vo_body: the body sits a metric lever arm from the camera, which has no place in
        unscaled VO units; the metric body position is the scaled camera position plus
        :meth:`lever_m`.)"""
        out = self.vo_output
        if out is None or not np.all(np.isfinite(out.T_vo_cam)):
            return None
        R: F64 = out.T_vo_cam[:3, :3] @ self.T_cam_body[:3, :3]
        return R

    def lever_m(self, out: VoOutput) -> F64:
        """(3,) camera -> body lever arm [m] in the VO frame's axes: R_vo_cam @ t_cam_body
        (T_cam_body's translation is metric). The metric body position in the VO frame is
        ``scale * t_vo_cam + lever_m``."""
        lever: F64 = out.T_vo_cam[:3, :3] @ self.T_cam_body[:3, 3]
        return lever

    def status(self) -> PipelineStatus:
        """An immutable snapshot of what the last frame left (for a status display on another
        thread: it never reads the pipeline's own, mutating state)."""
        out = self.vo_output
        est = self.estimates.get(self.method_name)
        fused = self.tilt.fused if self.tilt is not None else None
        sigma_deg = None
        if fused is not None:
            sigma_deg = float(np.degrees(np.sqrt(np.max(np.diag(fused.cov_rad2)))))
        return PipelineStatus(
            vo_state=out.state.name if out is not None else "INITIALIZING",
            features=int(len(out.features.pixels)) if out is not None else 0,
            keyframes=len(self.vo.keyframes),
            vo_resets=self.vo.resets,
            vo_heading_deg=(
                float(np.degrees(self.vo.yaw_vo_rad)) if self.vo.yaw_vo_known else None
            ),
            mag_heading_sigma_deg=(
                float(np.degrees(fix.sigma_rad)) if (fix := self.heading_fix) is not None else None
            ),
            mag_heading_samples=fix.samples if fix is not None else 0,
            mag_heading_final=self.mag_heading_ended,
            gaps=self.gaps,
            held_for_attitude=self.held_for_attitude,
            heading_restarts=self.heading_restarts,
            method=self.method_name,
            scale=est.scale if est is not None else None,
            scale_sigma=est.sigma if est is not None else None,
            sensors_used=est.n_used if est is not None else 0,
            match_rates=tuple(sorted(self.methods[self.method_name].match_rates().items())),
            ranges_rejected=self.ranges.rejected,
            roll_deg=float(np.degrees(fused.roll_rad)) if fused is not None else None,
            pitch_deg=float(np.degrees(fused.pitch_rad)) if fused is not None else None,
            tilt_sigma_deg=sigma_deg,
            tilt_reasons=tuple(self.tilt.reasons) if self.tilt is not None else (),
        )


@dataclass(frozen=True, slots=True)
class PipelineStatus:
    """What a status display shows of the pipeline, frozen after a frame (Pipeline.status)."""

    vo_state: str  # VoState name
    features: int  # tracked features in the last frame
    keyframes: int  # keyframes in the VO map
    vo_resets: int  # VO re-initialisations so far
    # heading of the VO frame's x axis [deg]: the autopilot's at the VO's initialisation; None
    # when no autopilot attitude was at hand then (the frame's x axis is the first heading)
    vo_heading_deg: float | None
    # vo.heading_source = magnetometer: the compass fix the heading took (its white-noise sigma
    # and the samples averaged); None / 0 while the heading is still the autopilot's
    mag_heading_sigma_deg: float | None
    mag_heading_samples: int
    mag_heading_final: bool  # the vehicle moved: the compass no longer refines the heading
    gaps: int  # resets forced by a gap without usable frames
    # frames kept from a VO that was not tracking: no autopilot attitude at hand for them
    held_for_attitude: int
    # maps dropped because they started before the autopilot's attitude stream did
    heading_restarts: int
    method: str  # the published scale method
    scale: float | None  # its scale (metres per VO unit), None before the first
    scale_sigma: float | None
    sensors_used: int  # sensors in its last update
    match_rates: tuple[tuple[int, float], ...]  # (sensor id, share of frames with a match)
    ranges_rejected: int  # range samples the pipeline refused
    roll_deg: float | None  # fused roll/pitch from the distance sensors
    pitch_deg: float | None
    tilt_sigma_deg: float | None
    tilt_reasons: tuple[str, ...]  # why a sensor was left out of the roll/pitch
