"""What a status display shows of the pipeline: a frozen snapshot taken after a frame."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from companion.vo.frame_clock import ClockReport

if TYPE_CHECKING:
    from companion.pipeline.core import Pipeline


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
    # frames held by the attitude-wait rule (Pipeline.hold_for_attitude)
    waited_for_attitude: int = 0
    gravity_frames: int = 0  # frames whose VO took the accelerometer's tilt correction
    dpose_armed: bool = False  # d-Pose has its pattern
    dpose_used: int = 0  # d-Pose poses that corrected the published position
    dpose_resets: int = 0  # of them, corrections applied at once (each a new reset_counter)
    # the camera's clock over the last frames (vo.steady_clock; None before enough frames)
    clock: ClockReport | None = None
    # frames the frame check kept from the VO, by verdict (FrameProblem value, count), the
    # verdicts seen only: ("frozen", 35) = 35 repeated (duplicated) images
    frames_refused: tuple[tuple[str, int], ...] = ()
    # the camera's focal length checked in flight (companion/vo/focal_check.py): the median
    # f_true / f_file over keyframe pairs, its spread (1.4826 MAD), the pairs; the warning once
    # it is confidently more than 5 % off
    lens_focal_ratio: float | None = None
    lens_focal_spread: float | None = None
    lens_focal_samples: int = 0
    lens_k1_delta: float | None = None  # k1_true - k1_file, checked in flight
    lens_brief: str | None = None  # the warning's short form: "k1 +0.021", "focal x1.100"
    # [vo] learn_lens: the (fx, fy, k1) taken in flight, None while the file's are in use
    lens_learned: tuple[float, float, float] | None = None
    lens_warning: str | None = None
    # the published method's scale filter: how long it has gated out every measurement [s] (a
    # scale held while the VO's unit moved) and its restarts at them ([scale] gate_recover_s)
    scale_outside_gate_s: float = 0.0
    scale_recoveries: int = 0


def status_of(pipe: Pipeline) -> PipelineStatus:
    """The snapshot of what the pipeline's last frame left (reads, never changes, it)."""
    out = pipe.vo_output
    vo = pipe.vo
    est = pipe.estimates.get(pipe.method_name)
    tilt = pipe.pose_tilt  # the roll/pitch the last pose went out with
    fused = tilt.fused if tilt is not None else None
    sigma_deg = None
    if fused is not None:
        sigma_deg = float(np.degrees(np.sqrt(np.max(np.diag(fused.cov_rad2)))))
    fix = pipe.compass.fix
    offset = pipe.dpose_stage.offset
    focal = pipe.lens.estimate()
    outside_gate_s, recoveries = pipe.methods[pipe.method_name].filter_state()
    return PipelineStatus(
        vo_state=out.state.name if out is not None else "INITIALIZING",
        features=int(len(out.features.pixels)) if out is not None else 0,
        keyframes=len(vo.map.keyframes),
        vo_resets=vo.resets,
        vo_heading_deg=float(np.degrees(vo.yaw_vo_rad)) if vo.yaw_vo_known else None,
        mag_heading_sigma_deg=float(np.degrees(fix.sigma_rad)) if fix is not None else None,
        mag_heading_samples=fix.samples if fix is not None else 0,
        mag_heading_final=pipe.compass.ended,
        gaps=pipe.gaps,
        held_for_attitude=pipe.held_for_attitude,
        heading_restarts=pipe.heading_restarts,
        method=pipe.method_name,
        scale=est.scale if est is not None else None,
        scale_sigma=est.sigma if est is not None else None,
        sensors_used=est.n_used if est is not None else 0,
        match_rates=tuple(sorted(pipe.methods[pipe.method_name].match_rates().items())),
        ranges_rejected=pipe.ranges.rejected,
        roll_deg=float(np.degrees(fused.roll_rad)) if fused is not None else None,
        pitch_deg=float(np.degrees(fused.pitch_rad)) if fused is not None else None,
        tilt_sigma_deg=sigma_deg,
        tilt_reasons=tuple(tilt.reasons) if tilt is not None else (),
        waited_for_attitude=pipe.waited_for_attitude,
        gravity_frames=pipe.imu_gravity.frames,
        dpose_armed=pipe.dpose_stage.armed,
        dpose_used=offset.updates,
        dpose_resets=offset.resets,
        clock=pipe.clock.report() if pipe.clock is not None else None,
        frames_refused=tuple((k, n) for k, n in pipe.frame_check.counts.items() if n),
        lens_focal_ratio=focal.ratio if focal is not None else None,
        lens_focal_spread=focal.spread if focal is not None else None,
        lens_focal_samples=focal.samples if focal is not None else 0,
        lens_k1_delta=focal.k1_delta if focal is not None else None,
        lens_brief=pipe.lens.brief,
        lens_learned=(pipe.camera.fx, pipe.camera.fy, pipe.camera.k1) if pipe.lens.taken else None,
        lens_warning=pipe.lens.warning,
        scale_outside_gate_s=outside_gate_s,
        scale_recoveries=recoveries,
    )
