"""d-Pose in the published pose (issue 18): armed on the published pose, then each of its
poses moves the published position (an offset added to the VO's) onto it.

Frames: the published pose is NED / FRD; ranges are the four lasers' [m] by sensor id.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from companion.config import Config
from companion.dpose.estimator import Dpose
from companion.dpose.offset import DposeOffset
from companion.geometry import se3, so3
from companion.geometry.camera import CameraModel
from companion.types import F64, CameraFrame, PoseEstimate, RangeSensorSpec


@dataclass
class ArmWindow:
    """The hover that arms d-Pose: where it started, and the four ranges and the autopilot's
    attitude of every frame."""

    start_us: int
    pose: PoseEstimate  # the published pose at the window's start
    range_m: list[dict[int, float]] = field(default_factory=list)  # per frame since
    R_world_body: list[F64] = field(default_factory=list)  # (3, 3) per frame since


class DposeStage:
    """d-Pose and the offset it keeps on the published position (``dpose`` None: off)."""

    def __init__(
        self,
        config: Config,
        camera: CameraModel,
        T_body_cam: F64,
        specs: dict[int, RangeSensorSpec],
    ) -> None:
        self.options = o = config.dpose
        self.dpose: Dpose | None = None
        if o.enabled and len(specs) == 4:
            self.dpose = Dpose(camera, T_body_cam, specs)
        self.offset = DposeOffset(o.vo_drift_per_m, o.vo_drift_m_per_s, o.reset_m)
        self._window: ArmWindow | None = None

    @property
    def armed(self) -> bool:
        """d-Pose has its pattern (armed on the published pose)."""
        return self.dpose is not None and self.dpose.armed

    def corrected(
        self,
        frame: CameraFrame,
        first_frame_us: int,
        pose: PoseEstimate,
        R_world_body: F64 | None,
        range_m: dict[int, float],
    ) -> PoseEstimate:
        """The published pose with d-Pose's correction (thesis abstract: the direct pose is
        metric and drift-free). Armed ``dpose.arm_after_s`` after the first frame
        (``first_frame_us``), with the four lasers' readings then (the marks are left where
        they hit) and the published pose then as the pattern's place in the world.
        Afterwards every d-Pose pose (marks in view, translation sigma <=
        ``dpose.max_sigma_m``) updates the offset added to the VO's position towards d-Pose
        minus VO (companion/dpose/offset.py): with a gain from the VO's drift since the last
        one and d-Pose's sigma, at once and with a new reset_counter when the gap exceeds
        ``dpose.reset_m`` (EKF2 re-anchors its vision frame instead of fusing a jump)."""
        assert self.dpose is not None
        o = self.options
        if not self.dpose.armed:
            waited = (frame.time_us - first_frame_us) * 1e-6 >= o.arm_after_s
            if waited and R_world_body is not None and len(range_m) == 4:
                self._arm(frame.time_us, pose, R_world_body, range_m)
        else:
            res = self.dpose.step(frame.time_us, frame.image_bgr, R_world_body, range_m or None)
            sigma_m = np.inf if res is None else float(np.sqrt(np.max(np.diag(res.cov_6x6)[3:])))
            if res is not None and sigma_m <= o.max_sigma_m:
                self.offset.update(
                    pose.time_us, pose.position_ned_m, res.T_world_body[:3, 3], sigma_m
                )
            else:
                self.offset.move(pose.position_ned_m)
        off = self.offset
        if not off.resets and not np.any(off.offset_m):
            return pose
        return dataclasses.replace(
            pose,
            position_ned_m=pose.position_ned_m + off.offset_m,
            reset_counter=pose.reset_counter + off.resets,
        )

    def _arm(
        self, time_us: int, pose: PoseEstimate, R_world_body: F64, range_m: dict[int, float]
    ) -> None:
        """Arm d-Pose once the vehicle has hovered ``dpose.arm_window_s`` (the published
        position within ``dpose.arm_max_motion_m`` of the window's start): the pattern from
        the four ranges averaged over the window (each reading's noise divided by about the
        square root of the frames in it: the pattern's error is the bias of every later
        d-Pose pose) and the autopilot's attitude averaged over it likewise, the world
        reference the published pose at the window's start (when the marks are left). A
        window where the vehicle moved starts again."""
        assert self.dpose is not None
        o = self.options
        w = self._window
        moved = w is not None and (
            float(np.linalg.norm(pose.position_ned_m - w.pose.position_ned_m)) > o.arm_max_motion_m
        )
        if w is None or moved:
            w = self._window = ArmWindow(time_us, pose)
        w.range_m.append(range_m)
        w.R_world_body.append(R_world_body)
        if (time_us - w.start_us) * 1e-6 < o.arm_window_s:
            return
        mean_range_m = {s: float(np.mean([r[s] for r in w.range_m])) for s in range_m}
        # the pattern's place: the published position and heading, the autopilot's roll and
        # pitch (drift-free; the published tilt carries the VO frame's, 0.76 deg in
        # config/pad.toml's seed 1, which tilted every d-Pose displacement from the pad's
        # centre: 1.6 cm of height 1.2 m off it; docs/decisions.md, "d-Pose's pattern tilt"),
        # averaged over the window as the ranges are: one attitude sample's noise (~0.1 deg)
        # is a bias of every later d-Pose position (0.5 cm at 3 m)
        R_world_body_arm = so3.mean(w.R_world_body)
        roll, pitch, _ = so3.matrix_to_rpy(R_world_body_arm)
        _, _, yaw = so3.matrix_to_rpy(so3.quat_to_matrix(w.pose.quat_wxyz_ned_frd))
        T_world_body = se3.make(so3.rpy_to_matrix(roll, pitch, yaw), w.pose.position_ned_m)
        self.dpose.arm(mean_range_m, T_world_body, R_world_body_arm)
        self.offset.arm(w.pose.time_us, w.pose.position_ned_m)
        self._window = None
