"""The one synchronous entry into the algorithms: feed_attitude / feed_range / feed_frame.

The same Pipeline runs offline (``companion eval``), in the service, and in benchmarks; it is
deterministic (same inputs, same outputs) and does no I/O. Inputs must arrive in time order
per stream; attitude and ranges are buffered and looked up at each frame's capture time.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from numpy.typing import NDArray

from companion.config import Config
from companion.geometry import se3, so3
from companion.geometry.camera import CameraModel
from companion.types import AttitudeSample, CameraFrame, PoseEstimate, RangeSample, VoOutput
from companion.vo.odometry import VisualOdometry

F64 = NDArray[np.float64]

ATTITUDE_MAX_GAP_US = 100_000  # an attitude older than this is not used for a frame


class Pipeline:
    """VO (and, as they land, metric scale, attitude and d-Pose) over time-ordered inputs."""

    def __init__(
        self, config: Config, camera: CameraModel | None = None, T_body_cam: F64 | None = None
    ) -> None:
        """``camera`` and ``T_body_cam`` override the config's (a dataset's own calibration)."""
        self.config = config
        self.camera = camera or config.camera.model()
        self.T_body_cam = config.camera.T_body_cam() if T_body_cam is None else T_body_cam
        self.T_cam_body = se3.inverse(self.T_body_cam)
        self.vo = VisualOdometry(self.camera, self.T_body_cam, config.vo)
        self._attitude: deque[AttitudeSample] = deque(maxlen=512)
        self._ranges: deque[RangeSample] = deque(maxlen=2048)
        self.vo_output: VoOutput | None = None

    def feed_attitude(self, sample: AttitudeSample) -> None:
        """Buffer an attitude sample (ignored unless finite and newer than the last)."""
        if not np.all(np.isfinite(sample.quat_wxyz)):
            return
        if self._attitude and sample.time_us <= self._attitude[-1].time_us:
            return
        self._attitude.append(sample)

    def feed_range(self, sample: RangeSample) -> None:
        """Buffer a distance-sensor sample (used by the metric scale)."""
        self._ranges.append(sample)

    def attitude_at(self, time_us: int) -> F64 | None:
        """R_world_body at ``time_us`` by slerp between the bracketing samples (or the nearest
        one within ATTITUDE_MAX_GAP_US), None when there is none close enough."""
        if not self._attitude:
            return None
        samples = self._attitude
        after = next((a for a in samples if a.time_us >= time_us), None)
        before = next((a for a in reversed(samples) if a.time_us <= time_us), None)
        if before is not None and after is not None and after.time_us > before.time_us:
            alpha = (time_us - before.time_us) / (after.time_us - before.time_us)
            R0 = so3.quat_to_matrix(before.quat_wxyz)
            R1 = so3.quat_to_matrix(after.quat_wxyz)
            return R0 @ so3.exp(alpha * so3.log(R0.T @ R1))
        near = before or after
        assert near is not None
        if abs(near.time_us - time_us) > ATTITUDE_MAX_GAP_US:
            return None
        return so3.quat_to_matrix(near.quat_wxyz)

    def feed_frame(self, frame: CameraFrame) -> PoseEstimate | None:
        """Run the VO on a frame. Returns a metric pose once the scale exists (not yet: None);
        the VO result is in ``vo_output``."""
        self.vo_output = self.vo.process(frame, self.attitude_at(frame.time_us))
        return None

    def T_vo_body(self) -> F64 | None:
        """The current body pose in the VO frame (unscaled), or None unless tracking."""
        out = self.vo_output
        if out is None or not np.all(np.isfinite(out.T_vo_cam)):
            return None
        T: F64 = out.T_vo_cam @ self.T_cam_body
        return T
