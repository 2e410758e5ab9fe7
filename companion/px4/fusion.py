"""Is our estimate fused by EKF2, and if not, the most likely reason (pure: observations in).

Evidence, strongest first:
- PX4's own topics through its MAVLink shell: ``estimator_status_flags.cs_ev_pos`` (EKF2's
  vision position fusion is active) together with ``estimator_aid_src_ev_pos`` (whether the
  last sample passed the innovation gate and was fused), ``vehicle_visual_odometry`` (what PX4
  made of our message: frame, quality, its time stamp after the time-sync conversion against
  its arrival time), ``vehicle_mocap_odometry``, ``timesync_status`` and ``uorb top`` (the rate
  PX4 receives);
- MAVLink streams: ESTIMATOR_STATUS (POS_HORIZ_REL) and LOCAL_POSITION_NED (PX4 sends it only
  while the local position is valid), STATUSTEXT (PX4 complains about an unsupported
  estimator_type);
- the service's status socket: what it sends, at which rate, and its time sync.

A valid local position alone does not say who makes it valid: GNSS, optical flow
(EKF2_OF_CTRL) or EKF2_NOAID_TOUT of dead reckoning after the last aiding all give one. So
without the shell the verdict is "fused" only when none of those can be it: no GNSS, optical
flow off, the service publishing, and a valid position all through a watch at least
EKF2_NOAID_TOUT long; otherwise "cannot tell".

The reasons follow DESIGN.md section 6 and EKF2: >= 5 Hz to start (samples < 200 ms apart),
NED only with a north-aligned heading, estimator_type VISION (MOCAP goes to a topic EKF2 does
not read), a frame PX4 knows, quality >= EKF2_EV_QMIN, time stamps that, once converted, are
younger than EKF2's buffer horizon (EKF2_DELAY_MAX + 100 ms), and samples that pass the
innovation gate (EKF2_EVP_GATE). When EKF2 fuses us, what would have been a reason is a
warning.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from companion.drivers.px4_shell_text import Fields, flag, number
from companion.px4.encoding import float_encoded_int
from companion.px4.rules import EV_HPOS, EV_VEL, LinkContext, Param

MIN_RATE_HZ = 5.0  # EKF2's EV_MAX_INTERVAL = 200 ms
GOOD_RATE_HZ = 20.0  # PX4's docs ask for 30-50 Hz
FRESH_S = 1.0  # a topic older than this is not being published any more
FUTURE_TOLERANCE_MS = 20.0  # stamps this far ahead of PX4's clock are jitter, not an error
LPOS_EDGE_S = 2.0  # LOCAL_POSITION_NED comes at >= 1 Hz (PX4's Normal mode): gaps above this
POS_HORIZ_REL = 8  # ESTIMATOR_STATUS_FLAGS
POSE_FRAMES = {0: "UNKNOWN", 1: "NED", 2: "FRD"}
GNSS_DISAGREE_M = 2.0  # GNSS position innovation beyond this, with vision fused: they disagree
EKF2_BUFFER_MATCH_MS = 100.0  # RingBuffer::pop_first_older_than: time <= horizon < time + 100


@dataclass(frozen=True, slots=True)
class ShellView:
    """What PX4's shell showed; a topic is None when never published (or not parsed)."""

    visual: Fields | None = None  # listener vehicle_visual_odometry
    mocap: Fields | None = None  # listener vehicle_mocap_odometry
    flags: Fields | None = None  # listener estimator_status_flags
    aid_pos: Fields | None = None  # listener estimator_aid_src_ev_pos
    timesync: Fields | None = None  # listener timesync_status
    aid_gnss: Fields | None = None  # listener estimator_aid_src_gnss_pos
    rates_hz: Mapping[str, float] | None = None  # uorb top -1


@dataclass(frozen=True, slots=True)
class Observations:
    """Everything check saw while watching."""

    watch_s: float = 0.0  # how long it watched [s]
    estimator_flags: int | None = None  # the last ESTIMATOR_STATUS.flags
    local_positions: int = 0  # LOCAL_POSITION_NED messages received
    lpos_first_s: float | None = None  # the first one, after the watch started [s]
    lpos_last_s: float | None = None  # the last one, after the watch started [s]
    lpos_max_gap_s: float | None = None  # the longest gap between two of them [s]
    gps_seen: bool = False  # a GPS_RAW_INT with a receiver (fix_type >= 1)
    statustexts: tuple[str, ...] = ()  # STATUSTEXT texts
    shell: ShellView | None = None  # None: no shell answer
    service: Mapping[str, Any] | None = None  # the service's status (None: not running)


@dataclass(frozen=True, slots=True)
class Verdict:
    """fused: True / False / None (cannot tell); reasons: most likely first (for None: why
    it cannot tell; for True: why PX4 will not fly on it all the same, e.g. no heading
    alignment, GNSS fighting us); warnings: what is wrong but does not stop fusion;
    timesync_converged: PX4's time sync on our stamps (None: not seen)."""

    fused: bool | None
    headline: str
    reasons: tuple[str, ...]
    evidence: tuple[str, ...]
    warnings: tuple[str, ...]
    timesync_converged: bool | None = None

    @property
    def ok(self) -> bool:
        """Fused, with nothing that keeps PX4 from flying on it."""
        return self.fused is True and not self.reasons


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
    if isinstance(frame, int) and not isinstance(frame, bool):
        return POSE_FRAMES.get(frame, str(frame))
    return "?"


def _fmt(v: float | None, spec: str, unknown: str = "?") -> str:
    return format(v, spec) if v is not None and math.isfinite(v) else unknown


def _fresh(fields: Fields | None) -> bool:
    age = number(fields, "timestamp_age_s")
    return age is not None and age < FRESH_S


def sample_age_ms(v: Fields | None) -> float | None:
    """How old our sample was when PX4 received it (``timestamp - timestamp_sample``, after
    PX4's time-sync conversion) [ms]; negative: stamped in PX4's future; None: unknown."""
    t, s = number(v, "timestamp"), number(v, "timestamp_sample")
    if t is not None and s is not None and t > 0 and s > 0:
        return (t - s) / 1000.0
    before = number(v, "timestamp_sample_before_timestamp_us")
    return before / 1000.0 if before is not None else None


def ev_buffer_length(params: Mapping[str, Param]) -> int:
    """EKF2's observation buffer length (EstimatorInterface::initialise_interface):
    min(round(1.5 * delay / period), max(2, ceil(delay / period))), delay the larger of
    EKF2_DELAY_MAX and EKF2_EV_DELAY [ms], period EKF2_PREDICT_US."""
    delay_max = _raw_float(params, "EKF2_DELAY_MAX", 200.0)
    delay_ms = max(delay_max, _raw_float(params, "EKF2_EV_DELAY", 0.0))
    period_ms = max(0.1, _raw_float(params, "EKF2_PREDICT_US", 10000.0) / 1000.0)
    return min(round(1.5 * delay_ms / period_ms), max(2, math.ceil(delay_ms / period_ms)))


def diagnose(obs: Observations, params: Mapping[str, Param], ctx: LinkContext) -> Verdict:
    """The verdict on fusion from what was observed and the parameters as PX4 holds them."""
    reasons: list[str] = []
    evidence: list[str] = []
    warnings: list[str] = []
    svc = obs.service
    _service_evidence(svc, evidence, warnings)
    _ev_ctrl_reasons(params, reasons)
    lpos_valid = obs.local_positions > 0 or bool((obs.estimator_flags or 0) & POS_HORIZ_REL)
    _mavlink_evidence(obs, lpos_valid, evidence)

    sh = obs.shell
    fused: bool | None
    blockers: list[str] = []
    converged: bool | None = None
    if sh is not None:
        fused = _diagnose_shell(sh, params, ctx, svc, reasons, evidence, warnings, obs)
        converged = timesync_converged(sh)
        blockers = _blockers(sh, params, fused, reasons)
        if fused and not lpos_valid:
            warnings.append(
                "EKF2 fuses vision but this link saw no valid local position "
                "(LOCAL_POSITION_NED / ESTIMATOR_STATUS): is it streamed here?"
            )
    else:
        fused = _infer_without_shell(obs, params, svc, lpos_valid, reasons, evidence)
    _rate_reason(fused, svc, reasons)
    headline = _headline(fused, sh is None, blockers, reasons, warnings)
    return Verdict(fused, headline, tuple(reasons), tuple(evidence), tuple(warnings), converged)


def _ev_ctrl_reasons(params: Mapping[str, Param], reasons: list[str]) -> None:
    """EKF2_EV_CTRL missing or without bit 0, as EKF2 reads it: our position is ignored."""
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


def _mavlink_evidence(obs: Observations, lpos_valid: bool, evidence: list[str]) -> None:
    """What the MAVLink streams showed: EKF2's status flags, local positions, PX4's texts."""
    flags_text = f"0x{obs.estimator_flags:03x}" if obs.estimator_flags is not None else "none"
    evidence.append(
        f"MAVLink: ESTIMATOR_STATUS flags {flags_text} "
        f"(horizontal position {'valid' if lpos_valid else 'not valid'}), "
        f"{obs.local_positions} LOCAL_POSITION_NED in {obs.watch_s:.1f} s"
        + (
            f" (first after {obs.lpos_first_s:.1f} s, last {obs.lpos_last_s:.1f} s, longest gap "
            f"{_fmt(obs.lpos_max_gap_s, '.1f')} s)"
            if obs.local_positions and obs.lpos_first_s is not None and obs.lpos_last_s is not None
            else ""
        )
    )
    for text in obs.statustexts[-3:]:
        evidence.append(f"PX4 says: {text}")


def _rate_reason(fused: bool | None, svc: Mapping[str, Any] | None, reasons: list[str]) -> None:
    """Not fused, and the service publishes below EKF2's 5 Hz (unless a reason says so)."""
    svc_rate = _get(svc, "output", "rate_hz")
    svc_msg = _get(svc, "output", "message")
    if (
        fused is False
        and svc_rate is not None
        and svc_rate < MIN_RATE_HZ
        and not any("rate" in r or "publishes" in r for r in reasons)
    ):
        reasons.append(
            f"the service publishes only {svc_rate:.1f} Hz of {svc_msg}: EKF2 needs >= 5 Hz"
        )


def _headline(
    fused: bool | None,
    inferred: bool,
    blockers: list[str],
    reasons: list[str],
    warnings: list[str],
) -> str:
    """The headline; reasons become warnings when EKF2 fuses us, blockers become reasons."""
    if fused is False and not reasons:
        reasons.append("EKF2 receives valid vision but has not started fusing it")
    if fused is True and reasons:
        # fused all the same: what would have been a reason is worth a look, not a verdict
        warnings[:0] = reasons
        reasons.clear()
    if fused is True and blockers:
        reasons.extend(blockers)
        return "FUSED, BUT PX4 WILL NOT FLY ON IT: EKF2 fuses our position, yet"
    if fused:
        headline = "FUSED: EKF2 fuses our estimate"
        if inferred:
            headline += " (inferred: a valid local position all along, with no other aiding)"
        return headline
    if fused is None:
        return "UNKNOWN: cannot tell whether EKF2 fuses our estimate"
    reasons[:0] = [b for b in blockers if b not in reasons]
    return "NOT FUSED: EKF2 does not fuse our estimate"


def timesync_converged(sh: ShellView) -> bool | None:
    """Whether PX4's time sync converts our stamps: once its filter converged (~500 TIMESYNC
    answers: ~10 s at the 50 Hz the service asks for, ~50 s at PX4's own 10 Hz) it moves our
    time_usec into its clock; before that it stamps each sample with its arrival time, so
    ``timestamp_sample`` equals ``timestamp`` exactly (a converted stamp has microseconds of
    its own). None: no fresh sample or no TIMESYNC."""
    v = sh.visual
    if not _fresh(v) or not _fresh(sh.timesync):
        return None
    t, ts = number(v, "timestamp"), number(v, "timestamp_sample")
    before = number(v, "timestamp_sample_before_timestamp_us")
    if t is not None and ts is not None and t > 0 and ts > 0:
        return t != ts
    return before != 0 if before is not None else None


def _blockers(
    sh: ShellView, params: Mapping[str, Param], fused: bool | None, reasons: list[str]
) -> list[str]:
    """What keeps PX4 from flying on our estimate although EKF2 may fuse it: no heading
    alignment, or GNSS and vision disagreeing (both seen on PX4 SITL, main 2026-03)."""
    out: list[str] = []
    flags, v = sh.flags, sh.visual
    if flags is None:
        return out
    frame = v.get("pose_frame") if v is not None else None
    ev_ctrl = _raw_int(params, "EKF2_EV_CTRL") or 0
    if fused and flag(flags, "cs_yaw_align") is False:
        why = (
            "its heading is not aligned (estimator_status_flags.cs_yaw_align false): PX4 "
            "refuses to arm ('heading estimate not stable')"
        )
        if frame == 2 and flag(flags, "cs_ev_yaw"):
            why += (
                "; with ODOMETRY in LOCAL_FRD our yaw (EKF2_EV_CTRL bit 3) replaces the "
                "magnetometer but never aligns the heading: clear bit 3"
            )
        elif frame == 2:
            why += (
                "; ODOMETRY in LOCAL_FRD leaves the alignment to the magnetometer, and none "
                "is used: send VISION_POSITION_ESTIMATE with EKF2_EV_CTRL bit 3 (our heading)"
            )
        out.append(why)
    gnss = any(flag(flags, k) for k in ("cs_gnss_pos", "cs_gnss_vel", "cs_gnss_fault"))
    ev = any(flag(flags, k) for k in ("cs_ev_pos", "cs_ev_vel", "cs_ev_hgt"))
    aid = sh.aid_gnss if _fresh(sh.aid_gnss) else None
    innovation = aid.get("innovation") if aid is not None else None
    ratio = aid.get("test_ratio") if aid is not None else None
    innov_m = (
        max(abs(x) for x in innovation[:2] if math.isfinite(x))
        if isinstance(innovation, list) and any(math.isfinite(x) for x in innovation[:2])
        else None
    )
    ratio_max = (
        max(x for x in ratio[:2] if math.isfinite(x))
        if isinstance(ratio, list) and any(math.isfinite(x) for x in ratio[:2])
        else None
    )
    disagree = (
        flag(flags, "cs_gnss_fault") is True
        or flag(aid, "innovation_rejected") is True
        or (ratio_max is not None and ratio_max > 1.0)
        or (innov_m is not None and innov_m > GNSS_DISAGREE_M)
    )
    if gnss and ev and disagree:
        seen = []
        if innov_m is not None:
            seen.append(f"GNSS position innovation {innov_m:.1f} m")
        if ratio_max is not None:
            seen.append(f"test ratio {ratio_max:.2g}")
        if flag(aid, "innovation_rejected"):
            seen.append("GNSS position rejected")
        if flag(flags, "cs_gnss_fault"):
            seen.append("cs_gnss_fault")
        out.append(
            "GNSS and vision fight: EKF2 fuses both and they disagree ("
            + ", ".join(seen)
            + "), so EKF2 rejects one or the other in turn and PX4 refuses to arm ('horizontal "
            "position/velocity unstable'); where there is no usable GNSS turn it off "
            "(EKF2_GPS_CTRL = 0: `companion px4 configure --no-gnss`), else our estimate is "
            "off (frame, heading, scale or velocity)"
            + (
                " (EKF2_EV_CTRL bit 2 fuses our velocity, which has no bias estimate)"
                if ev_ctrl & EV_VEL
                else ""
            )
        )
    return [b for b in out if b not in reasons]


def _infer_without_shell(
    obs: Observations,
    params: Mapping[str, Param],
    svc: Mapping[str, Any] | None,
    lpos_valid: bool,
    reasons: list[str],
    evidence: list[str],
) -> bool | None:
    """The verdict from MAVLink streams alone: fused only when nothing else can make the
    local position valid; None (cannot tell) otherwise."""
    evidence.append("PX4 shell: no answer (fusion inferred from MAVLink streams)")
    if not lpos_valid:
        if obs.estimator_flags is None:
            reasons.append(
                "this link streams neither ESTIMATOR_STATUS nor LOCAL_POSITION_NED, and PX4's "
                "shell did not answer: nothing tells whether EKF2 has a position"
            )
            return None
        _no_vision_reasons(obs, svc, reasons)
        return False
    doubts: list[str] = []
    gps_ctrl = _raw_int(params, "EKF2_GPS_CTRL")
    if obs.gps_seen and gps_ctrl != 0:
        doubts.append(
            "a GNSS receiver reports and EKF2_GPS_CTRL fuses it: GNSS may be what makes the "
            "local position valid"
        )
    of_ctrl = _raw_int(params, "EKF2_OF_CTRL")
    if of_ctrl:
        doubts.append(
            f"EKF2_OF_CTRL = {of_ctrl}: optical flow may be what makes the local position valid"
        )
    published = _get(svc, "output", "published") or 0
    rate = _get(svc, "output", "rate_hz") or 0.0
    if svc is None:
        doubts.append(
            "the service is not running here (no status socket): nothing says we are publishing"
        )
    elif not published or rate < MIN_RATE_HZ:
        doubts.append(
            f"the service is not publishing (rate {rate:.1f} Hz, VO {_get(svc, 'vo', 'state')}): "
            "the local position is valid without us"
        )
    first, last, gap = obs.lpos_first_s, obs.lpos_last_s, obs.lpos_max_gap_s
    covered = (
        obs.local_positions > 0
        and first is not None
        and last is not None
        and first <= LPOS_EDGE_S
        and obs.watch_s - last <= LPOS_EDGE_S
        and (gap is None or gap <= LPOS_EDGE_S)
    )
    if not covered:
        doubts.append(
            "the local position was not valid all through the watch (LOCAL_POSITION_NED "
            "missing at its start, its end or in between, or not streamed on this link)"
        )
    noaid_s = _raw_float(params, "EKF2_NOAID_TOUT", 5e6) / 1e6
    if obs.watch_s < noaid_s:
        doubts.append(
            f"watched {obs.watch_s:.1f} s, less than EKF2_NOAID_TOUT ({noaid_s:g} s): dead "
            "reckoning after an earlier aiding keeps the position valid that long "
            f"(--watch-s {math.ceil(noaid_s)})"
        )
    reasons.extend(doubts)
    return None if doubts else True


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
        f"{rate if isinstance(rate, (int, float)) else float('nan'):.1f} Hz "
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
            "reaches EKF2: check the link (MAV_n_CONFIG, baud rate, signing, UDP partner) and "
            "that the service talks to this autopilot"
        )


def _on_off(fields: Fields, key: str) -> str:
    v = flag(fields, key)
    return "?" if v is None else ("on" if v else "off")


def _diagnose_shell(
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
    ts_fresh = _fresh(sh.timesync)
    _timesync_evidence(sh, evidence, warnings)
    aid = sh.aid_pos if _fresh(sh.aid_pos) else None
    _aid_evidence(aid, flags, evidence)
    if fused and aid is not None and _rejected(aid):
        fused = False
        reasons.append(_rejection_reason(v, params))
    if not _fresh(v):
        _stopped_reasons(v, m, obs, svc, reasons)
        return fused

    assert v is not None
    _sample_reasons(v, rate, flags, params, reasons, warnings)
    _time_reasons(v, age_ms, rate, params, svc, ts_fresh, reasons, warnings)
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
            f"PX4 receives (vehicle_visual_odometry): {_fmt(rate, '.1f')} Hz, pose_frame "
            f"{_frame_name(v.get('pose_frame'))}, quality {_fmt(quality, '.0f')}, sample "
            f"{_fmt(age_ms, '.0f')} ms old on arrival, last "
            f"{_fmt(number(v, 'timestamp_age_s'), '.2f')} s ago"
        )
    else:
        evidence.append("PX4 receives (vehicle_visual_odometry): never published")
    if m is not None:
        evidence.append(
            f"vehicle_mocap_odometry: {_fmt(rates.get('vehicle_mocap_odometry'), '.1f')} Hz, "
            f"last {_fmt(number(m, 'timestamp_age_s'), '.2f')} s ago"
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
            f"{_fmt(rtt_us / 1000 if rtt_us is not None else None, '.2f')} ms, last answer "
            f"{_fmt(number(ts, 'timestamp_age_s'), '.2f')} s ago"
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
    gate = _raw_float(params, "EKF2_EVP_GATE", 5.0)
    qmin = _raw_int(params, "EKF2_EV_QMIN") or 0
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
    if v is not None and age is not None and not _fresh(m):
        reasons.append(
            f"our estimate stopped: PX4 received it until {age:.1f} s ago and nothing "
            "since (EKF2 stops vision fusion 400 ms after the last sample): the sender "
            "stopped, or its link broke"
        )
    if _fresh(m):
        reasons.append(
            "wrong estimator_type: our ODOMETRY arrives as MAV_ESTIMATOR_TYPE_MOCAP, which "
            "PX4 puts on vehicle_mocap_odometry and EKF2 never reads; send "
            "MAV_ESTIMATOR_TYPE_VISION (2)"
        )
    else:
        _no_vision_reasons(obs, svc, reasons)


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
    qmin = _raw_int(params, "EKF2_EV_QMIN") or 0
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
    delay_max = _raw_float(params, "EKF2_DELAY_MAX", 200.0)
    ev_delay = _raw_float(params, "EKF2_EV_DELAY", 0.0)
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
        hz = rate or _get(svc, "output", "rate_hz") or 30.0
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
