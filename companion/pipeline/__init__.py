"""The pipeline: every per-frame decision from a camera frame to the pose to publish.

``core`` holds :class:`Pipeline` (the order of the stages); ``inputs`` the buffered attitude
and accelerometer samples; ``ground`` the ranges' ground plane and the pad's gravity;
``gravity`` the accelerometer's tilt correction; ``heading`` the compass heading;
``scale_stage`` the scale methods and what the scale and roll/pitch take; ``output`` the
published pose; ``dpose_stage`` d-Pose's correction of it; ``lens_stage`` the focal length
checked in flight; ``status`` the frozen snapshot for displays.
"""

from companion.pipeline.core import AFTER_POSE, Pipeline
from companion.pipeline.inputs import (
    ATTITUDE_MAX_GAP_US,
    ATTITUDE_MAX_SPAN_US,
    AttitudeHistory,
    Event,
    Sample,
)
from companion.pipeline.scale_stage import LaserReading, TiltInput
from companion.pipeline.status import PipelineStatus

__all__ = [
    "AFTER_POSE",
    "ATTITUDE_MAX_GAP_US",
    "ATTITUDE_MAX_SPAN_US",
    "AttitudeHistory",
    "Event",
    "LaserReading",
    "Pipeline",
    "PipelineStatus",
    "Sample",
    "TiltInput",
]
