"""Is our estimate fused by EKF3, and if not, the most likely reason (pure: observations in).

Evidence (as the real ArduCopter SITL showed it, docs/decisions.md "ArduPilot's dialect"):
- EKF_STATUS_REPORT.flags: with our position fused EKF3 reports a relative horizontal position
  (EKF_POS_HORIZ_REL) and leaves constant-position mode (EKF_CONST_POS_MODE); 0x33f fused,
  0xa7 (attitude, velocities, height, constant position) not;
- GLOBAL_POSITION_INT: a non-zero lat/lon once EKF3 holds an origin;
- our own messages as ArduPilot forwards them to the checking link (frame ids, quality, rate);
- STATUSTEXT: "PreArm: VisOdom: not healthy" (no sample accepted within 300 ms: nothing comes,
  or every one is dropped for its frame), "is using external nav data";
- the service's status socket.
Without GPS and with optical flow off, a relative horizontal position can only be ours.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from companion.autopilot.ardupilot.link import CompanionSeen, Watched
from companion.autopilot.ardupilot.rules import EXTNAV, GPS, SOURCES, ArduPilotContext, value_of
from companion.autopilot.params import Param
from companion.autopilot.verdict import Verdict
from companion.drivers.ardupilot import ekf_navigates

MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD = 20, 12
FRAMES = {1: "LOCAL_NED", 8: "BODY_NED", 12: "BODY_FRD", 20: "LOCAL_FRD", 21: "LOCAL_FLU"}
MIN_RATE_HZ = 5.0  # below this EKF3 times our samples out between them


@dataclass(frozen=True, slots=True)
class ArduPilotObservations:
    """Everything check saw while watching."""

    watch_s: float
    watched: Watched
    service: Mapping[str, Any] | None = None  # the service's status (None: not running)


def _frame(f: int | None) -> str:
    return f"{f} ({FRAMES.get(f, '?')})" if f is not None else "?"


def diagnose(
    obs: ArduPilotObservations, params: Mapping[str, Param], ctx: ArduPilotContext
) -> Verdict:
    """The verdict: fused or not, the most likely reasons first, what was seen."""
    w = obs.watched
    flags = w.ekf_flags
    evidence = [f"EKF_STATUS_REPORT.flags {hex(flags) if flags is not None else 'none seen'}"]
    ours = {k: v for k, v in w.companion.items() if v.count}
    for kind, c in ours.items():
        extra = (
            f", frame_id {_frame(c.frame_id)}, child_frame_id {_frame(c.child_frame_id)}, "
            f"quality {c.quality}"
            if kind == "ODOMETRY"
            else ""
        )
        evidence.append(f"{kind} from component {c.component} at {c.rate_hz():.1f} Hz{extra}")
    origin = w.origin is not None or (w.position is not None and w.position != (0, 0))
    evidence.append(
        "EKF origin: "
        + (
            f"{w.origin[0] * 1e-7:.7f}, {w.origin[1] * 1e-7:.7f}, {w.origin[2] * 1e-3:.1f} m"
            if w.origin
            else ("held" if origin else "none (GLOBAL_POSITION_INT at 0, 0)")
        )
    )
    texts = [
        t for t in w.statustexts if "VisOdom" in t or "external nav" in t or "origin" in t.lower()
    ]
    evidence += [f"STATUSTEXT: {t}" for t in dict.fromkeys(texts)]
    svc = obs.service
    if svc is not None:
        out = svc.get("output", {}) if isinstance(svc.get("output"), Mapping) else {}
        evidence.append(f"the service sends {out.get('message')} at {out.get('rate_hz', 0):.1f} Hz")
    rel = flags is not None and bool(ekf_navigates(flags))
    fused = rel and value_of(params, "EK3_SRC1_POSXY") == EXTNAV and bool(ours) and origin
    reasons = _mixed(params, ctx) if fused else _why_not(obs, params, ctx, origin, ours)
    warnings = _warnings(ours, params, ctx)
    if fused:
        headline = "EKF3 fuses our estimate" + (" (but see below)" if reasons else "")
        return Verdict(True, headline, tuple(reasons), tuple(evidence), tuple(warnings))
    return Verdict(
        False, "EKF3 does NOT fuse our estimate", tuple(reasons), tuple(evidence), tuple(warnings)
    )


def _mixed(params: Mapping[str, Param], ctx: ArduPilotContext) -> list[str]:
    """Fused, and yet EKF3 takes part of its state from GPS in another frame."""
    gps = [s for s in ("VELXY", "POSZ", "VELZ") if value_of(params, f"EK3_SRC1_{s}") == GPS]
    if not gps:
        return []
    names = ", ".join(f"EK3_SRC1_{s} = 3 (GPS)" for s in gps)
    return [
        f"GPS and vision both sources: {names} beside our position (EK3_SRC1_POSXY = 6): two "
        "frames in one filter, the GPS one north-aligned at the GPS origin, ours where our VO "
        "started; set them to 6 (ODOMETRY) or 0 (VISION_POSITION_ESTIMATE)"
    ]


def _why_not(
    obs: ArduPilotObservations,
    params: Mapping[str, Param],
    ctx: ArduPilotContext,
    origin: bool,
    ours: dict[str, CompanionSeen],
) -> list[str]:
    """Why EKF3 does not fuse us, most likely first."""
    reasons = []
    viso = value_of(params, "VISO_TYPE")
    if viso is not None and viso != 1:
        reasons.append(
            f"VISO_TYPE = {int(viso)}: ArduPilot's visual odometry is "
            + ("off" if viso == 0 else "another backend")
            + ": it drops VISION_POSITION_ESTIMATE and ODOMETRY from the companion (set 1, reboot)"
        )
    odo = ours.get("ODOMETRY")
    if odo is not None and (
        odo.frame_id != MAV_FRAME_LOCAL_FRD or odo.child_frame_id != MAV_FRAME_BODY_FRD
    ):
        reasons.append(
            f"ODOMETRY with frame_id {_frame(odo.frame_id)} / child_frame_id "
            f"{_frame(odo.child_frame_id)}: ArduPilot drops every ODOMETRY that is not "
            f"frame_id {MAV_FRAME_LOCAL_FRD} (LOCAL_FRD) with child_frame_id {MAV_FRAME_BODY_FRD} "
            "(BODY_FRD, body-frame velocity)"
        )
    qmin = value_of(params, "VISO_QUAL_MIN") or 0.0
    if odo is not None and odo.quality is not None and odo.quality < qmin:
        reasons.append(f"ODOMETRY quality {odo.quality} < VISO_QUAL_MIN {qmin:g}: dropped")
    if "VISION_POSITION_ESTIMATE" in ours and qmin > 0:
        reasons.append(
            "VISION_POSITION_ESTIMATE has no quality (read as 0) and "
            f"VISO_QUAL_MIN = {qmin:g}: dropped"
        )
    if not ours:
        svc = obs.service
        if svc is None:
            reasons.append(
                "no VISION_POSITION_ESTIMATE or ODOMETRY from the companion reaches ArduPilot "
                "(none forwarded to this link), and the service is not running"
            )
        else:
            reasons.append(
                "the service runs but ArduPilot forwards none of its messages to this link: it "
                "sends to another port or system, or is not publishing (status: vo "
                f"{svc.get('vo', {}).get('state') if isinstance(svc.get('vo'), Mapping) else '?'})"
            )
    for kind, c in ours.items():
        if c.count > 1 and c.rate_hz() < MIN_RATE_HZ:
            reasons.append(
                f"{kind} at {c.rate_hz():.1f} Hz: below {MIN_RATE_HZ:g} Hz EKF3 times out"
            )
    if not origin:
        reasons.append(
            "EKF3 has no origin (GLOBAL_POSITION_INT at 0, 0; no GPS_GLOBAL_ORIGIN): without GPS "
            "it never uses our position until the companion sends SET_GPS_GLOBAL_ORIGIN after "
            "'EKF3 IMU0 initialised' ([service.ardupilot] set_origin = true"
            + (", which is set: is the service on this autopilot?)" if ctx.set_origin else ")")
        )
    src = value_of(params, "EK3_SRC1_POSXY")
    if src is not None and src != EXTNAV:
        reasons.append(
            f"EK3_SRC1_POSXY = {int(src)} ({SOURCES.get(int(src), '?')}): EKF3 takes its position "
            "from elsewhere (6 = ExternalNav)"
        )
    reasons += _mixed(params, ctx)
    if not reasons:
        reasons.append(
            "nothing found in the parameters or our messages; EKF3 may still be initialising "
            "(watch longer: --watch-s 15)"
        )
    return reasons


def _warnings(
    ours: dict[str, CompanionSeen], params: Mapping[str, Param], ctx: ArduPilotContext
) -> list[str]:
    out = []
    if "ODOMETRY" in ours and "VISION_POSITION_ESTIMATE" in ours:
        out.append(
            "both VISION_POSITION_ESTIMATE and ODOMETRY arrive: AP_VisualOdom takes both as one "
            "stream of poses; send one (service.output)"
        )
    return out
