"""Options of d-Pose in the published pose (composed into the config as [dpose])."""

from __future__ import annotations

from dataclasses import dataclass

from companion.options import opt


@dataclass(frozen=True, slots=True)
class DposeOptions:
    """d-Pose reaching the autopilot: when the four marks are in view, the published position
    is the direct metric pose (the VO's drift removed)."""

    enabled: bool = opt(
        False, "correct the published position with d-Pose (needs exactly four rangefinders)"
    )
    arm_after_s: float = opt(
        1.0, "arm (the marks are left) this long after the first camera frame [s]", ge=0
    )
    arm_window_s: float = opt(
        0.4, "the four ranges are averaged over this long of hover when d-Pose is armed [s]", ge=0
    )
    arm_max_motion_m: float = opt(
        0.02, "the hover while arming: the published position within this of its start [m]", gt=0
    )
    reset_m: float = opt(
        0.05,
        "a correction larger than this is applied at once with a new reset_counter [m]; "
        "smaller ones are blended in without one",
        gt=0,
    )
    vo_drift_per_m: float = opt(
        0.005,
        "the VO's position drift per metre travelled since the last d-Pose pose [m/m]: how "
        "far the offset may have gone stale (with d-Pose's own sigma, it sets how much of a "
        "correction is taken at once)",
        ge=0,
    )
    vo_drift_m_per_s: float = opt(
        0.001, "the VO's position drift per second, also at rest [m/s]", ge=0
    )
    max_sigma_m: float = opt(
        0.05, "d-Pose poses with a larger translation sigma are not used [m]", gt=0
    )
