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

The reasons follow docs/service.md and EKF2: >= 5 Hz to start (samples < 200 ms apart),
NED only with a north-aligned heading, estimator_type VISION (MOCAP goes to a topic EKF2 does
not read), a frame PX4 knows, quality >= EKF2_EV_QMIN, time stamps that, once converted, are
younger than EKF2's buffer horizon (EKF2_DELAY_MAX + 100 ms), and samples that pass the
innovation gate (EKF2_EVP_GATE). When EKF2 fuses us, what would have been a reason is a
warning.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from companion.autopilot.params import Param
from companion.autopilot.px4.ekf2_observations import (
    GNSS_DISAGREE_M,
    LPOS_EDGE_S,
    MIN_RATE_HZ,
    POS_HORIZ_REL,
    Observations,
    ShellView,
    dig,
    fmt,
    fresh,
    no_vision_reasons,
    raw_float,
    raw_int,
    timesync_converged,
)
from companion.autopilot.px4.ekf2_rules import EV_HPOS, EV_VEL
from companion.autopilot.px4.ekf2_shell_diagnosis import diagnose_shell
from companion.autopilot.px4.encoding import float_encoded_int
from companion.autopilot.px4.link_context import LinkContext
from companion.autopilot.verdict import Verdict
from companion.drivers.px4_shell_text import flag


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
        fused = diagnose_shell(sh, params, ctx, svc, reasons, evidence, warnings, obs)
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
    ev_ctrl = raw_int(params, "EKF2_EV_CTRL")
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
            f"{fmt(obs.lpos_max_gap_s, '.1f')} s)"
            if obs.local_positions and obs.lpos_first_s is not None and obs.lpos_last_s is not None
            else ""
        )
    )
    for text in obs.statustexts[-3:]:
        evidence.append(f"PX4 says: {text}")


def _rate_reason(fused: bool | None, svc: Mapping[str, Any] | None, reasons: list[str]) -> None:
    """Not fused, and the service publishes below EKF2's 5 Hz (unless a reason says so)."""
    svc_rate = dig(svc, "output", "rate_hz")
    svc_msg = dig(svc, "output", "message")
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
    ev_ctrl = raw_int(params, "EKF2_EV_CTRL") or 0
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
    aid = sh.aid_gnss if fresh(sh.aid_gnss) else None
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
        no_vision_reasons(obs, svc, reasons)
        return False
    doubts: list[str] = []
    gps_ctrl = raw_int(params, "EKF2_GPS_CTRL")
    if obs.gps_seen and gps_ctrl != 0:
        doubts.append(
            "a GNSS receiver reports and EKF2_GPS_CTRL fuses it: GNSS may be what makes the "
            "local position valid"
        )
    of_ctrl = raw_int(params, "EKF2_OF_CTRL")
    if of_ctrl:
        doubts.append(
            f"EKF2_OF_CTRL = {of_ctrl}: optical flow may be what makes the local position valid"
        )
    published = dig(svc, "output", "published") or 0
    rate = dig(svc, "output", "rate_hz") or 0.0
    if svc is None:
        doubts.append(
            "the service is not running here (no status socket): nothing says we are publishing"
        )
    elif not published or rate < MIN_RATE_HZ:
        doubts.append(
            f"the service is not publishing (rate {rate:.1f} Hz, VO {dig(svc, 'vo', 'state')}): "
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
    noaid_s = raw_float(params, "EKF2_NOAID_TOUT", 5e6) / 1e6
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
    rate = dig(svc, "output", "rate_hz")
    rtt = dig(svc, "autopilot", "timesync_rtt_ms")
    converged = dig(svc, "autopilot", "timesync_converged")
    evidence.append(
        f"service: sends {dig(svc, 'output', 'message')} at "
        f"{rate if isinstance(rate, (int, float)) else float('nan'):.1f} Hz "
        f"({dig(svc, 'output', 'published')} sent), VO {dig(svc, 'vo', 'state')}, "
        f"time sync {'converged' if converged else 'NOT converged'}"
        + (f" (rtt {rtt:.2f} ms)" if isinstance(rtt, (int, float)) else "")
    )
    if converged is False:
        warnings.append(
            "the service's own time sync with the autopilot has not converged: TIMESYNC is not "
            "getting through both ways on this link"
        )
