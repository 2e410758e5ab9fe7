"""The publisher: a pose from the pipeline shaped for the autopilot and sent.

Inputs: the frame a pose was made of and the pose (``PoseEstimate``: NED [m], quaternion
w, x, y, z NED <- FRD, stamp at the frame's exposure in our clock [us]), the autopilot's kind,
its latest body rates [rad/s] and whether PX4 stamps our poses on arrival (the autopilot
session's). Outputs: VISION_POSITION_ESTIMATE and / or ODOMETRY on the link
(``service.output``), the send counters and latencies in ``ServiceStats``, the pose to the
recorder, ``last_pose`` (for MQTT). A pose whose frame is older than ``stale_frame_ms`` is not
sent; the ``reset_counter`` on the wire never repeats an earlier run's (``ResetCounter``).
With [gps] align, each pose goes out in the autopilot's GPS frame (``gps_frame``: fed our pose
as the pipeline made it); without it the pose is passed on untouched.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.drivers import ardupilot, messages
from companion.service.autopilot_session import AutopilotSession
from companion.service.gps_frame import GpsFrame
from companion.service.recorder import Recorder
from companion.service.runtime import AutopilotKind, Runtime
from companion.service.state import ResetCounter
from companion.types import CameraFrame, PoseEstimate


@dataclass(eq=False, repr=False)
class Publisher:
    """Poses out, as the autopilot wants them."""

    rt: Runtime
    link: Any
    session: AutopilotSession
    resets: ResetCounter
    recorder: Recorder
    gps: GpsFrame | None = None  # [gps] align: our poses in the autopilot's GPS frame
    last_pose: PoseEstimate | None = field(init=False, default=None)  # the last one sent
    # for centred ODOMETRY
    _recent_poses: deque[PoseEstimate] = field(init=False, default_factory=lambda: deque(maxlen=15))

    def __post_init__(self) -> None:
        # centred ODOMETRY: no window over a gap longer than the age limit, and no stamp older
        # than the budget `px4 check` holds EKF2's horizon to (the config is frozen)
        self._centre_max_gap_us = 1e3 * self.rt.config.service.stale_frame_ms
        self._oldest_stamp_us = 1e3 * self.rt.config.oldest_stamp_ms()

    def publish(self, frame: CameraFrame, pose: PoseEstimate | None) -> None:
        """Send the pose made of ``frame`` (None or not finite: counted as not published)."""
        s = self.rt.stats
        if pose is None or not messages.is_finite_pose(pose):
            s.not_published += 1
            return
        age_ms = (self.rt.clock() / 1e3 - frame.time_us) / 1e3
        if age_ms > self.rt.config.service.stale_frame_ms:  # too old to help the autopilot
            s.stale += 1
            return
        if self.gps is not None:  # in the autopilot's frame (its reset counter stepped by jumps)
            pose = self.gps.align(pose)
        # the counter on the wire never repeats the last one an earlier run sent
        pose = dataclasses.replace(pose, reset_counter=self.resets.wire(pose.reset_counter))
        o = self.rt.config.service.output
        sent = False
        # PX4 stamping on arrival: each message as of its sending, stamped then
        send_us = self.rt.clock() // 1000 if self.session.stamp_at_send() else None
        if o in ("vision_position_estimate", "both"):
            vpe = pose if send_us is None else messages.pose_at(pose, send_us)
            sent |= self.link.send(messages.vision_position_estimate(self.link.mav, vpe))
        if o in ("odometry", "both"):
            sent |= self._send_odometry(pose, send_us)
        if sent:
            t = self.rt.clock()
            if s.published and pose.reset_counter != s.last_reset_counter:
                jumped = self.gps is not None and self.gps.jumped
                what = "frame aligned to GPS at once" if jumped else "VO re-initialised"
                self.rt.warn(f"{what}: reset_counter {pose.reset_counter}")
            s.published += 1
            s.stamped_at_send += send_us is not None
            s.publish_times_ns.append(t)
            s.latency_ms.append((t / 1e3 - frame.time_us) / 1e3)
            s.last_reset_counter = pose.reset_counter
            s.sent.append(pose)
            self.recorder.pose(pose)
            self.last_pose = pose

    def _send_odometry(self, pose: PoseEstimate, send_us: int | None) -> bool:
        """ODOMETRY for ``pose`` (centred on the last N poses when asked); whether it went."""
        so = self.rt.config.service
        rates = self.session.attitude_rates
        wire = pose
        n = so.odometry_centre_frames
        if n:
            wire = self._centred(pose, n)
        if self.rt.stats.autopilot_kind is AutopilotKind.ARDUPILOT:
            # 0 would read "unknown" to AP_VisualOdom
            wire = dataclasses.replace(
                pose, quality_pct=ardupilot.ardupilot_quality(pose.quality_pct)
            )
        if send_us is not None:
            wire = messages.pose_at(wire, send_us)
        odo = messages.odometry(
            self.link.mav, wire, rates, so.odometry_velocity_sigma_m_s, frame=so.odometry_frame
        )
        return bool(odo is not None and self.link.send(odo))

    def _centred(self, pose: PoseEstimate, n: int) -> PoseEstimate:
        """The pose centred on the last ``n`` (velocity from the window; without a full
        window: the newest pose with an unknown velocity)."""
        self._recent_poses.append(pose)
        recent = list(self._recent_poses)[-n:]
        centred = (
            messages.centred_pose(recent, self._centre_max_gap_us) if len(recent) == n else None
        )
        if centred is not None and self.rt.clock() / 1e3 - centred.time_us > self._oldest_stamp_us:
            # a window over a skipped frame is centred more than (N - 1) / 2 frames
            # back: past the oldest stamp `px4 check` holds EKF2's horizon to, the
            # newest pose goes out with the window's velocity (EKF2 drops samples
            # older than its horizon: one went out 275 ms old against its 236,
            # 2026-11-27, d7a0c08)
            centred = dataclasses.replace(pose, velocity_ned_m_s=centred.velocity_ned_m_s)
        if centred is not None:
            return centred
        return dataclasses.replace(pose, velocity_ned_m_s=np.full(3, np.nan))
