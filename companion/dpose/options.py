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
    blend: float = opt(0.3, "share of a small correction applied per d-Pose frame", gt=0, le=1)
    max_sigma_m: float = opt(
        0.05, "d-Pose poses with a larger translation sigma are not used [m]", gt=0
    )
