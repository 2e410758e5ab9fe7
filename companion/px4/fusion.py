"""Is our estimate fused by EKF2, and if not, the most likely reason (pure: observations in).

Evidence, strongest first:
- PX4's own flags through its MAVLink shell: ``estimator_status_flags.cs_ev_pos`` (EKF2 fuses
  our horizontal position), ``vehicle_visual_odometry`` (what PX4 made of our message: frame,
  quality, its time stamp after the time-sync conversion against its arrival time),
  ``vehicle_mocap_odometry``, ``timesync_status`` and ``uorb top`` (the rate PX4 receives);
- MAVLink streams: ESTIMATOR_STATUS (POS_HORIZ_REL) and LOCAL_POSITION_NED (PX4 sends it only
  while the local position is valid), STATUSTEXT (PX4 complains about an unsupported
  estimator_type);
- the service's status socket: what it sends, at which rate, and its time sync.

The reasons follow DESIGN.md section 6 and EKF2: >= 5 Hz to start (samples < 200 ms apart),
NED only with a north-aligned heading, estimator_type VISION (MOCAP goes to a topic EKF2 does
not read), a frame PX4 knows, quality >= EKF2_EV_QMIN, and time stamps that, once converted,
are younger than EKF2's buffer horizon (EKF2_DELAY_MAX + 100 ms).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from companion.px4.encoding import float_encoded_int
from companion.px4.rules import EV_HPOS, EV_VEL, LinkContext, Param
from companion.px4.shell import Fields

MIN_RATE_HZ = 5.0  # EKF2's EV_MAX_INTERVAL = 200 ms
GOOD_RATE_HZ = 20.0  # PX4's docs ask for 30-50 Hz
FRESH_S = 1.0  # a topic older than this is not being published any more
POS_HORIZ_REL = 8  # ESTIMATOR_STATUS_FLAGS
POSE_FRAMES = {0: "UNKNOWN", 1: "NED", 2: "FRD"}


@dataclass(frozen=True, slots=True)
class ShellView:
    """What PX4's shell showed; a topic is None when never published."""

    visual: Fields | None = None  # listener vehicle_visual_odometry
    mocap: Fields | None = None  # listener vehicle_mocap_odometry
    flags: Fields | None = None  # listener estimator_status_flags
    aid_pos: Fields | None = None  # listener estimator_aid_src_ev_pos
    timesync: Fields | None = None  # listener timesync_status
    rates_hz: Mapping[str, float] | None = None  # uorb top -1


@dataclass(frozen=True, slots=True)
class Observations:
    """Everything check saw while watching."""

    watch_s: float = 0.0  # how long it watched [s]
    estimator_flags: int | None = None  # the last ESTIMATOR_STATUS.flags
    local_positions: int = 0  # LOCAL_POSITION_NED messages received
    gps_seen: bool = False  # a GPS_RAW_INT with a receiver (fix_type >= 1)
    statustexts: tuple[str, ...] = ()  # STATUSTEXT texts
    shell: ShellView | None = None  # None: no shell answer
    service: Mapping[str, Any] | None = None  # the service's status (None: not running)


@dataclass(frozen=True, slots=True)
class Verdict:
    """fused: True / False / None (cannot tell); reasons: most likely first."""

    fused: bool | None
    headline: str
    reasons: tuple[str, ...]
    evidence: tuple[str, ...]
    warnings: tuple[str, ...]


def _get(d: Mapping[str, Any] | None, *keys: str) -> Any:
    for k in keys:
        if not isinstance(d, Mapping) or k not in d:
            return None
        d = d[k]
    return d


def _raw_int(params: Mapping[str, Param], name: str) -> int | None:
    p = params.get(name)
    return int(p.value) if p is not None and p.is_int else None


def _raw_float(params: Mapping[str, Param], name: str, default: float) -> float:
    p = params.get(name)
    return float(p.value) if p is not None else default


def _frame_name(frame: Any) -> str:
    return POSE_FRAMES.get(frame, str(frame)) if isinstance(frame, int) else str(frame)


def _fresh(fields: Fields | None) -> bool:
    if fields is None:
        return False
    age = fields.get("timestamp_age_s")
    return isinstance(age, (int, float)) and age < FRESH_S


def diagnose(obs: Observations, params: Mapping[str, Param], ctx: LinkContext) -> Verdict:
    """The verdict on fusion from what was observed and the parameters as PX4 holds them."""
    reasons: list[str] = []
    evidence: list[str] = []
    warnings: list[str] = []
    svc = obs.service
    svc_rate = _get(svc, "output", "rate_hz")
    svc_msg = _get(svc, "output", "message")
    _service_evidence(svc, evidence, warnings)

    ev_ctrl = _raw_int(params, "EKF2_EV_CTRL")
    if ev_ctrl is None:
        reasons.append("EKF2_EV_CTRL is missing: this firmware predates PX4 1.14")
    elif not ev_ctrl & EV_HPOS:
        f = float_encoded_int(ev_ctrl, 0, 15)
        how = f" (the bytes of the float {f:g}: written as a float)" if f is not None else ""
        reasons.append(
            f"EKF2_EV_CTRL = {ev_ctrl}{how} has bit 0 (horizontal position) clear as EKF2 "
            "reads it: EKF2 ignores our position; `companion px4 configure` sets it"
        )

    lpos_valid = obs.local_positions > 0 or bool((obs.estimator_flags or 0) & POS_HORIZ_REL)
    flags_text = f"0x{obs.estimator_flags:03x}" if obs.estimator_flags is not None else "none"
    evidence.append(
        f"MAVLink: ESTIMATOR_STATUS flags {flags_text} "
        f"(horizontal position {'valid' if lpos_valid else 'not valid'}), "
        f"{obs.local_positions} LOCAL_POSITION_NED in {obs.watch_s:.1f} s"
    )
    for text in obs.statustexts[-3:]:
        evidence.append(f"PX4 says: {text}")

    sh = obs.shell
    fused: bool | None
    if sh is not None:
        fused = _diagnose_shell(sh, params, ctx, svc, reasons, evidence, warnings, obs)
        if fused and not lpos_valid:
            warnings.append(
                "EKF2 fuses vision but this link saw no valid local position "
                "(LOCAL_POSITION_NED / ESTIMATOR_STATUS): is it streamed here?"
            )
    else:
        evidence.append("PX4 shell: no answer (fusion inferred from MAVLink streams)")
        gps_ctrl = _raw_int(params, "EKF2_GPS_CTRL") or 0
        if lpos_valid and (not obs.gps_seen or gps_ctrl == 0):
            fused = True
        elif lpos_valid:
            fused = None
            reasons.append("a local position is valid, but GNSS may be what makes it valid")
        else:
            fused = False
            _no_vision_reasons(obs, svc, reasons)

    if (
        fused is False
        and svc_rate is not None
        and svc_rate < MIN_RATE_HZ
        and not any("rate" in r or "publishes" in r for r in reasons)
    ):
        reasons.append(
            f"the service publishes only {svc_rate:.1f} Hz of {svc_msg}: EKF2 needs >= 5 Hz"
        )
    if fused is False and not reasons:
        reasons.append("EKF2 receives valid vision but has not started fusing it")
    if fused:
        headline = "FUSED: EKF2 fuses our estimate"
        if sh is None:
            headline += " (inferred: valid local position without GNSS)"
    elif fused is None:
        headline = "UNKNOWN: cannot tell whether EKF2 fuses our estimate"
    else:
        headline = "NOT FUSED: EKF2 does not fuse our estimate"
    return Verdict(fused, headline, tuple(reasons), tuple(evidence), tuple(warnings))


def _service_evidence(
    svc: Mapping[str, Any] | None, evidence: list[str], warnings: list[str]
) -> None:
    if svc is None:
        evidence.append("service: not running here (no status socket)")
        return
    rate = _get(svc, "output", "rate_hz")
    rtt = _get(svc, "autopilot", "timesync_rtt_ms")
    converged = _get(svc, "autopilot", "timesync_converged")
    evidence.append(
        f"service: sends {_get(svc, 'output', 'message')} at "
        f"{rate if rate is not None else float('nan'):.1f} Hz "
        f"({_get(svc, 'output', 'published')} sent), VO {_get(svc, 'vo', 'state')}, "
        f"time sync {'converged' if converged else 'NOT converged'}"
        + (f" (rtt {rtt:.2f} ms)" if isinstance(rtt, (int, float)) else "")
    )
    if converged is False:
        warnings.append(
            "the service's own time sync with the autopilot has not converged: TIMESYNC is not "
            "getting through both ways on this link"
        )


def _no_vision_reasons(
    obs: Observations, svc: Mapping[str, Any] | None, reasons: list[str]
) -> None:
    """Nothing of ours reaches EKF2's vision topic: why, most likely first."""
    unsupported = [t for t in obs.statustexts if "estimator_type" in t]
    if unsupported:
        reasons.append(
            f"PX4 drops our ODOMETRY ('{unsupported[-1]}'): estimator_type must be "
            "MAV_ESTIMATOR_TYPE_VISION (2)"
        )
    if svc is None:
        reasons.append(
            "no vision message reaches the autopilot, and the service is not running here "
            "(start `companion run`, or give --socket)"
        )
        return
    published = _get(svc, "output", "published") or 0
    rate = _get(svc, "output", "rate_hz") or 0.0
    if not published or rate <= 0.0:
        reasons.append(
            f"the service runs but publishes nothing (VO {_get(svc, 'vo', 'state')}): it sends "
            "only while the VO tracks and the metric scale is initialised"
        )
    else:
        reasons.append(
            f"the service sends {_get(svc, 'output', 'message')} at {rate:.1f} Hz, but none "
            "reaches EKF2: check the link (MAV_n_CONFIG, baud rate, signing) and that the "
            "service talks to this autopilot"
        )


def _diagnose_shell(
    sh: ShellView,
    params: Mapping[str, Param],
    ctx: LinkContext,
    svc: Mapping[str, Any] | None,
    reasons: list[str],
    evidence: list[str],
    warnings: list[str],
    obs: Observations,
) -> bool:
    """Diagnosis from PX4's own topics; returns whether EKF2 fuses our position."""
    flags = sh.flags or {}
    fused = bool(flags.get("cs_ev_pos"))
    parts = ("ev_pos", "ev_hgt", "ev_vel", "ev_yaw", "yaw_align")
    evidence.append(
        "EKF2 (estimator_status_flags): "
        + ", ".join(f"{p} {'on' if flags.get('cs_' + p) else 'off'}" for p in parts)
    )
    rates = sh.rates_hz or {}
    rate = rates.get("vehicle_visual_odometry", 0.0)
    v, m = sh.visual, sh.mocap
    if v is not None:
        age_ms = (v.get("timestamp", 0) - v.get("timestamp_sample", 0)) / 1000.0
        evidence.append(
            f"PX4 receives (vehicle_visual_odometry): {rate:.1f} Hz, pose_frame "
            f"{_frame_name(v.get('pose_frame'))}, quality "
            f"{v.get('quality')}, sample {age_ms:.0f} ms old on arrival, last "
            f"{v.get('timestamp_age_s', math.nan):.2f} s ago"
        )
    else:
        evidence.append("PX4 receives (vehicle_visual_odometry): never published")
    if m is not None:
        evidence.append(
            f"vehicle_mocap_odometry: {rates.get('vehicle_mocap_odometry', 0.0):.1f} Hz, last "
            f"{m.get('timestamp_age_s', math.nan):.2f} s ago"
        )
    ts = sh.timesync
    ts_fresh = _fresh(ts)
    if ts is not None:
        evidence.append(
            f"PX4 time sync (timesync_status): round trip {ts.get('round_trip_time', 0) / 1000:.2f}"
            f" ms, last answer {ts.get('timestamp_age_s', math.nan):.2f} s ago"
        )

    if flags.get("cs_inertial_dead_reckoning"):
        evidence.append(
            "EKF2 is dead-reckoning: its local position stays valid for EKF2_NOAID_TOUT after "
            "the last aiding, without us"
        )
    if not _fresh(v):
        if _fresh(m):
            reasons.append(
                "wrong estimator_type: our ODOMETRY arrives as MAV_ESTIMATOR_TYPE_MOCAP, which "
                "PX4 puts on vehicle_mocap_odometry and EKF2 never reads; send "
                "MAV_ESTIMATOR_TYPE_VISION (2)"
            )
        else:
            _no_vision_reasons(obs, svc, reasons)
        return fused

    assert v is not None
    if rate < MIN_RATE_HZ:
        reasons.append(
            f"rate too low: PX4 receives our estimate at {rate:.1f} Hz; EKF2 starts vision "
            "fusion only with samples less than 200 ms apart (>= 5 Hz), and PX4 asks for 30-50 Hz"
        )
    elif rate < GOOD_RATE_HZ:
        warnings.append(f"PX4 receives our estimate at {rate:.1f} Hz; PX4 asks for 30-50 Hz")
    frame = v.get("pose_frame")
    position = v.get("position") or []
    if frame == 0 or any(not math.isfinite(x) for x in position[:2]):
        reasons.append(
            "wrong frame: PX4 cannot place our position (pose_frame UNKNOWN, position NaN); "
            "ODOMETRY frame_id must be MAV_FRAME_LOCAL_FRD (20) or LOCAL_NED (1) (or their "
            "FLU/ENU twins), child_frame_id MAV_FRAME_BODY_FRD (12)"
        )
    elif frame == 1 and not flags.get("cs_yaw_align"):
        reasons.append(
            "wrong frame for this vehicle: our position is NED (VISION_POSITION_ESTIMATE, or "
            "ODOMETRY in LOCAL_NED) and EKF2 has no north-aligned heading (no magnetometer, "
            'no EV yaw): send ODOMETRY in LOCAL_FRD (service.output = "odometry"), which EKF2 '
            "fuses at any heading, or enable EKF2_EV_CTRL bit 3 (yaw)"
        )
    qmin = _raw_int(params, "EKF2_EV_QMIN") or 0
    quality = v.get("quality")
    if qmin > 0 and isinstance(quality, int) and quality < qmin:
        note = " (VISION_POSITION_ESTIMATE has no quality: PX4 uses 0)" if frame == 1 else ""
        reasons.append(f"quality {quality} below EKF2_EV_QMIN = {qmin}{note}")
    delay_max = _raw_float(params, "EKF2_DELAY_MAX", 200.0)
    ev_delay = _raw_float(params, "EKF2_EV_DELAY", 0.0)
    limit_ms = delay_max + 100.0 - ev_delay
    age_ms = (v.get("timestamp", 0) - v.get("timestamp_sample", 0)) / 1000.0
    sync_note = (
        "PX4's time sync works, so the stamps themselves are off: stamp with the exposure time "
        "in the clock you answer TIMESYNC with"
        if ts_fresh
        else "PX4 gets no TIMESYNC answers on this link"
    )
    if age_ms > limit_ms:
        reasons.append(
            f"stale timestamps: after PX4's time-sync conversion our samples are {age_ms:.0f} ms "
            f"old on arrival; EKF2 only uses samples younger than ~{limit_ms:.0f} ms "
            f"(EKF2_DELAY_MAX + 100 ms - EKF2_EV_DELAY): {sync_note}"
        )
    elif age_ms < -20.0:
        reasons.append(
            f"timestamps in the future: after PX4's time-sync conversion our samples are "
            f"{-age_ms:.0f} ms ahead of PX4's clock, and EKF2's buffer drops them: {sync_note}"
        )
    if not ts_fresh:
        warnings.append(
            "PX4 has no recent TIMESYNC answer on the companion's link: it stamps our "
            "messages with their arrival time (latency not compensated)"
        )
    ev_ctrl = _raw_int(params, "EKF2_EV_CTRL") or 0
    if (
        ev_ctrl & EV_VEL
        and v.get("velocity_frame") == 0
        and ctx.output != "vision_position_estimate"
    ):
        warnings.append(
            "velocity fusion enabled but PX4 cannot use our velocity (velocity_frame UNKNOWN): "
            "ODOMETRY child_frame_id must be MAV_FRAME_BODY_FRD (12)"
        )
    if not fused and not reasons and (sh.aid_pos or {}).get("innovation_rejected"):
        reasons.append(
            "EKF2 rejects our position at its innovation gate (EKF2_EVP_GATE): our estimate "
            "disagrees with EKF2's (frame, scale), or the covariance we send is too small"
        )
    return fused
