"""EKF2's fusion as PX4's own topics show it through its MAVLink shell (pure): its fusion
flags, what PX4 made of our message (frame, quality, rate, its time stamp after the time sync),
whether the last sample passed the innovation gate, and the reasons when it did not fuse."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from companion.autopilot.params import Param
from companion.autopilot.px4.ekf2_observations import (
    EKF2_BUFFER_MATCH_MS,
    FUTURE_TOLERANCE_MS,
    GOOD_RATE_HZ,
    MIN_RATE_HZ,
    Observations,
    ShellView,
    dig,
    ev_buffer_length,
    fmt,
    frame_name,
    fresh,
    no_vision_reasons,
    raw_float,
    raw_int,
    sample_age_ms,
    timesync_converged,
)
from companion.autopilot.px4.ekf2_rules import EV_VEL
from companion.autopilot.px4.link_context import LinkContext
from companion.drivers.px4_shell_text import Fields, flag, number


def _on_off(fields: Fields, key: str) -> str:
    v = flag(fields, key)
    return "?" if v is None else ("on" if v else "off")


def diagnose_shell(
    sh: ShellView,
    params: Mapping[str, Param],
    ctx: LinkContext,
    svc: Mapping[str, Any] | None,
    reasons: list[str],
    evidence: list[str],
    warnings: list[str],
    obs: Observations,
) -> bool | None:
    """Diagnosis from PX4's own topics; whether EKF2 fuses our position (None: its flags did
    not come through, so it cannot tell)."""
    flags = sh.flags
    fused = _flags_evidence(flags, reasons, evidence)
    rates = sh.rates_hz or {}
    rate: float | None = rates.get("vehicle_visual_odometry", 0.0) if rates else None
    v, m = sh.visual, sh.mocap
    age_ms = sample_age_ms(v)
    _reception_evidence(v, m, rate, rates, age_ms, evidence)
    ts_fresh = fresh(sh.timesync)
    _timesync_evidence(sh, evidence, warnings)
    aid = sh.aid_pos if fresh(sh.aid_pos) else None
    _aid_evidence(aid, flags, evidence)
    if fused and aid is not None and _rejected(aid):
        fused = False
        reasons.append(_rejection_reason(v, params))
    if not fresh(v):
        _stopped_reasons(v, m, obs, svc, reasons)
        return fused

    assert v is not None
    _sample_reasons(v, rate, flags, params, reasons, warnings)
    _time_reasons(v, age_ms, rate, params, svc, ts_fresh, reasons, warnings)
    ev_ctrl = raw_int(params, "EKF2_EV_CTRL") or 0
    if (
        ev_ctrl & EV_VEL
        and v.get("velocity_frame") == 0
        and ctx.output != "vision_position_estimate"
    ):
        warnings.append(
            "velocity fusion enabled but PX4 cannot use our velocity (velocity_frame UNKNOWN): "
            "ODOMETRY child_frame_id must be MAV_FRAME_BODY_FRD (12)"
        )
    if not fused and not reasons and flag(aid, "innovation_rejected"):
        reasons.append(
            "EKF2 rejects our position at its innovation gate (EKF2_EVP_GATE): our estimate "
            "disagrees with EKF2's (frame, scale), or the covariance we send is too small"
        )
    return fused


def _flags_evidence(flags: Fields | None, reasons: list[str], evidence: list[str]) -> bool | None:
    """EKF2's fusion flags (estimator_status_flags): cs_ev_pos says whether it fuses us."""
    if flags is None:
        evidence.append("EKF2 (estimator_status_flags): no answer, or not in PX4's format")
        reasons.append(
            "PX4's shell answered, but not with EKF2's estimator_status_flags (never published, "
            "or output this check cannot read): EKF2's own fusion flags are unknown"
        )
        return None
    parts = ("ev_pos", "ev_hgt", "ev_vel", "ev_yaw", "yaw_align")
    fused = flag(flags, "cs_ev_pos")
    evidence.append(
        "EKF2 (estimator_status_flags): "
        + ", ".join(f"{p} {_on_off(flags, 'cs_' + p)}" for p in parts)
    )
    if fused is None:
        reasons.append("estimator_status_flags has no readable cs_ev_pos: cannot tell")
    return fused


def _reception_evidence(
    v: Fields | None,
    m: Fields | None,
    rate: float | None,
    rates: Mapping[str, float],
    age_ms: float | None,
    evidence: list[str],
) -> None:
    """What PX4 made of our messages: vehicle_visual_odometry, and vehicle_mocap_odometry."""
    if v is not None:
        quality = number(v, "quality")
        evidence.append(
            f"PX4 receives (vehicle_visual_odometry): {fmt(rate, '.1f')} Hz, pose_frame "
            f"{frame_name(v.get('pose_frame'))}, quality {fmt(quality, '.0f')}, sample "
            f"{fmt(age_ms, '.0f')} ms old on arrival, last "
            f"{fmt(number(v, 'timestamp_age_s'), '.2f')} s ago"
        )
    else:
        evidence.append("PX4 receives (vehicle_visual_odometry): never published")
    if m is not None:
        evidence.append(
            f"vehicle_mocap_odometry: {fmt(rates.get('vehicle_mocap_odometry'), '.1f')} Hz, "
            f"last {fmt(number(m, 'timestamp_age_s'), '.2f')} s ago"
        )


def _timesync_evidence(sh: ShellView, evidence: list[str], warnings: list[str]) -> None:
    """PX4's time sync (timesync_status): converged, round trip; a warning until it converges."""
    ts = sh.timesync
    converged = timesync_converged(sh)
    if ts is not None:
        rtt_us = number(ts, "round_trip_time")
        state = {
            True: "converged (our stamps converted)",
            False: "NOT converged (PX4 stamps our samples at arrival)",
            None: "convergence unknown",
        }[converged]
        evidence.append(
            f"PX4 time sync (timesync_status): {state}, round trip "
            f"{fmt(rtt_us / 1000 if rtt_us is not None else None, '.2f')} ms, last answer "
            f"{fmt(number(ts, 'timestamp_age_s'), '.2f')} s ago"
        )
    if converged is False:
        warnings.append(
            "PX4's time sync has not converged yet: it stamps our samples with their arrival "
            "time, so the latency is not compensated (PX4's filter needs ~500 TIMESYNC answers: "
            "~10 s after the service starts, which asks PX4 for TIMESYNC at 50 Hz, ~50 s at "
            "PX4's own 10 Hz; check again then)"
        )


def _aid_evidence(aid: Fields | None, flags: Fields | None, evidence: list[str]) -> None:
    """EKF2's last vision position sample (estimator_aid_src_ev_pos), and dead reckoning."""
    if aid is not None:
        ratio = aid.get("test_ratio")
        evidence.append(
            f"EKF2 vision position (estimator_aid_src_ev_pos): fused {_on_off(aid, 'fused')}, "
            f"innovation rejected {_on_off(aid, 'innovation_rejected')}"
            + (f", test ratio {ratio}" if isinstance(ratio, list) else "")
        )
    if flags is not None and flag(flags, "cs_inertial_dead_reckoning"):
        evidence.append(
            "EKF2 is dead-reckoning: its local position stays valid for EKF2_NOAID_TOUT after "
            "the last aiding, without us"
        )


def _rejected(aid: Fields) -> bool:
    """EKF2's vision position fusion is on but did not fuse the last sample."""
    aid_fused, rejected = flag(aid, "fused"), flag(aid, "innovation_rejected")
    return aid_fused is False or (aid_fused is None and rejected is True)


def _rejection_reason(v: Fields | None, params: Mapping[str, Param]) -> str:
    """Why an active vision fusion refuses our samples: below EKF2_EV_QMIN, or the gate."""
    gate = raw_float(params, "EKF2_EVP_GATE", 5.0)
    qmin = raw_int(params, "EKF2_EV_QMIN") or 0
    quality = number(v, "quality")
    if qmin > 0 and quality is not None and quality < qmin:
        return (  # ev_pos_control marks a low-quality sample rejected
            f"active but not fused: our quality {quality:.0f} is below EKF2_EV_QMIN = "
            f"{qmin}, and EKF2 marks such samples rejected"
        )
    return (
        f"active but rejected at EKF2_EVP_GATE ({gate:g} SD): EKF2's vision position "
        "fusion is on (cs_ev_pos) but its innovation test refuses our samples "
        "(estimator_aid_src_ev_pos: not fused): our estimate disagrees with EKF2's "
        "(frame, scale, heading), or the covariance we send is too small"
    )


def _stopped_reasons(
    v: Fields | None,
    m: Fields | None,
    obs: Observations,
    svc: Mapping[str, Any] | None,
    reasons: list[str],
) -> None:
    """No fresh vehicle_visual_odometry: it stopped, went to the mocap topic, or never came."""
    age = number(v, "timestamp_age_s")
    if v is not None and age is not None and not fresh(m):
        reasons.append(
            f"our estimate stopped: PX4 received it until {age:.1f} s ago and nothing "
            "since (EKF2 stops vision fusion 400 ms after the last sample): the sender "
            "stopped, or its link broke"
        )
    if fresh(m):
        reasons.append(
            "wrong estimator_type: our ODOMETRY arrives as MAV_ESTIMATOR_TYPE_MOCAP, which "
            "PX4 puts on vehicle_mocap_odometry and EKF2 never reads; send "
            "MAV_ESTIMATOR_TYPE_VISION (2)"
        )
    else:
        no_vision_reasons(obs, svc, reasons)


def _sample_reasons(
    v: Fields,
    rate: float | None,
    flags: Fields | None,
    params: Mapping[str, Param],
    reasons: list[str],
    warnings: list[str],
) -> None:
    """Our samples as PX4 holds them: rate (>= 5 Hz), a frame it can place, enough quality."""
    if rate is not None and rate < MIN_RATE_HZ:
        reasons.append(
            f"rate too low: PX4 receives our estimate at {rate:.1f} Hz; EKF2 starts vision "
            "fusion only with samples less than 200 ms apart (>= 5 Hz), and PX4 asks for 30-50 Hz"
        )
    elif rate is not None and rate < GOOD_RATE_HZ:
        warnings.append(f"PX4 receives our estimate at {rate:.1f} Hz; PX4 asks for 30-50 Hz")
    frame = v.get("pose_frame")
    position = v.get("position")
    position = position if isinstance(position, list) else []
    yaw_align = flag(flags, "cs_yaw_align")
    if frame == 0 or any(not math.isfinite(x) for x in position[:2]):
        reasons.append(
            "wrong frame: PX4 cannot place our position (pose_frame UNKNOWN, position NaN); "
            "ODOMETRY frame_id must be MAV_FRAME_LOCAL_FRD (20) or LOCAL_NED (1) (or their "
            "FLU/ENU twins), child_frame_id MAV_FRAME_BODY_FRD (12)"
        )
    elif frame == 1 and yaw_align is False:
        reasons.append(
            "wrong frame for this vehicle: our position is NED (VISION_POSITION_ESTIMATE, or "
            "ODOMETRY in LOCAL_NED) and EKF2 has no north-aligned heading (no magnetometer, "
            "no EV yaw): enable EKF2_EV_CTRL bit 3, whose yaw aligns EKF2's heading in NED "
            "(ODOMETRY in LOCAL_FRD would be fused, but EKF2's heading would still never "
            "align and PX4 would not arm)"
        )
    qmin = raw_int(params, "EKF2_EV_QMIN") or 0
    quality = number(v, "quality")
    said = any("EKF2_EV_QMIN" in r for r in reasons)
    if qmin > 0 and quality is not None and quality < qmin and not said:
        note = " (VISION_POSITION_ESTIMATE has no quality: PX4 uses 0)" if frame == 1 else ""
        reasons.append(f"quality {quality:.0f} below EKF2_EV_QMIN = {qmin}{note}")


def _time_reasons(
    v: Fields,
    age_ms: float | None,
    rate: float | None,
    params: Mapping[str, Param],
    svc: Mapping[str, Any] | None,
    ts_fresh: bool,
    reasons: list[str],
    warnings: list[str],
) -> None:
    """Stamps too old for EKF2's buffer, or ahead of PX4's clock (held, then fused late, or
    lost when the buffer overflows first); and whether PX4's time sync works."""
    delay_max = raw_float(params, "EKF2_DELAY_MAX", 200.0)
    ev_delay = raw_float(params, "EKF2_EV_DELAY", 0.0)
    limit_ms = delay_max + EKF2_BUFFER_MATCH_MS - ev_delay
    sync_note = (
        "PX4's time sync works, so the stamps themselves are off: stamp with the exposure time "
        "in the clock you answer TIMESYNC with"
        if ts_fresh
        else "PX4 gets no TIMESYNC answers on this link"
    )
    if age_ms is None:
        warnings.append(
            "PX4's vehicle_visual_odometry gave no readable timestamp_sample: the age of our "
            "samples on arrival is unknown"
        )
    elif age_ms > limit_ms:
        reasons.append(
            f"stale timestamps: after PX4's time-sync conversion our samples are {age_ms:.0f} ms "
            f"old on arrival; EKF2 only uses samples younger than ~{limit_ms:.0f} ms "
            f"(EKF2_DELAY_MAX + 100 ms - EKF2_EV_DELAY): {sync_note}"
        )
    elif age_ms < -FUTURE_TOLERANCE_MS:
        ahead_ms = -age_ms
        hz = rate or dig(svc, "output", "rate_hz") or 30.0
        length = ev_buffer_length(params)
        span_ms = length / max(hz, 1e-3) * 1000.0
        wait_ms = ahead_ms - ev_delay + delay_max  # from arrival until the horizon reaches it
        if wait_ms >= span_ms:
            reasons.append(
                f"timestamps in the future: after PX4's time-sync conversion our samples are "
                f"{ahead_ms:.0f} ms ahead of PX4's clock; EKF2 holds each until its delayed "
                f"horizon (EKF2_DELAY_MAX = {delay_max:g} ms) reaches the stamp, {wait_ms:.0f} ms "
                f"after arrival, but its buffer of {length} samples (~{span_ms:.0f} ms at "
                f"{hz:.0f} Hz) overwrites them first: they are lost ({sync_note})"
            )
        else:
            warnings.append(
                f"timestamps {ahead_ms:.0f} ms in PX4's future: EKF2 holds each sample until "
                f"its delayed horizon reaches the stamp, so it is fused late by {ahead_ms:.0f} ms "
                f"(against the state of a later instant than it was measured): {sync_note}"
            )
    if not ts_fresh:
        warnings.append(
            "PX4 has no recent TIMESYNC answer on the companion's link: it stamps our "
            "messages with their arrival time (latency not compensated)"
        )
