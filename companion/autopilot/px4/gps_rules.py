"""PX4 with GPS and our vision together (``--with-gps``): the EKF2 rules that change, and the
GPS rows they add (pure; docs/gps.md).

Why, as measured on the real PX4 SITL (SIH, main 02e73e3b6f) on 2026-11-29 (probes on the
ground, not yet missions): while GNSS is fused, EKF2 fuses our position relative to its own
(an offset, the EV position bias estimator, our variance floored at EKF2_GPS_P_NOISE); at GNSS
loss it resets to our position minus that offset (0.095 m step with GNSS switched off at the
loss, 0.29 m at EKF2's own time-out 7 s later); at the return, with EKF2_GPS_MODE 0, GNSS may
not reset the position while ours is fused: EKF2 pulls towards it at 0.06-0.09 m/s, or, with our
frame more than ~2 m off, never takes it. With EKF2_HGT_REF 1 (GNSS height) the height was
reset at the return: a 0.2-0.27 m step; with 3 (vision) 0.009 m.

FAIL: the handover cannot work as set (no GPS position, our position or height not fused, our
yaw fed back into the heading the service aligns to). WARN: it works, with a step at a switch
or without a part of our estimate. INFO: context.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import partial

from companion.autopilot.params import Judgement, Param, Row, Status
from companion.autopilot.px4.ekf2_rules import EV_HPOS, EV_VEL, EV_VPOS, EV_YAW, HGT_REF, ev_bits
from companion.autopilot.px4.link_context import LinkContext
from companion.autopilot.px4.typed_rows import float_row, int_row, int_value

GPS_POS, GPS_ALT, GPS_VEL = 1, 2, 4
GPS_MODE = {0: "auto", 1: "dead reckoning"}
REPLACED = ("EKF2_EV_CTRL", "EKF2_HGT_REF", "EKF2_GPS_CTRL")


def with_gps(rows: list[Row], params: Mapping[str, Param], ctx: LinkContext) -> list[Row]:
    """The vision-only ``rows`` with EKF2_EV_CTRL, EKF2_HGT_REF and EKF2_GPS_CTRL judged for
    GPS and vision together, and the GPS rows after EKF2_GPS_CTRL (or at the end)."""
    velocity = ctx.output in ("odometry", "both")
    hgt_ref = int_value(params, "EKF2_HGT_REF", 0, 3)
    rng_ctrl = int_value(params, "EKF2_RNG_CTRL", 0, 2)
    replaced = {
        "EKF2_EV_CTRL": int_row(
            params, "EKF2_EV_CTRL", 0, 15, partial(_judge_ev_ctrl, velocity, hgt_ref)
        ),
        "EKF2_HGT_REF": int_row(
            params, "EKF2_HGT_REF", 0, 3, partial(_judge_hgt_ref, rng_ctrl), HGT_REF
        ),
        "EKF2_GPS_CTRL": int_row(params, "EKF2_GPS_CTRL", 0, 15, partial(_judge_gps_ctrl, ctx)),
    }
    added = _added_rows(params)
    out: list[Row] = []
    for r in rows:
        out.append(replaced.pop(r.name, r))
        if r.name == "EKF2_GPS_CTRL":
            out += added
            added = []
    return out + list(replaced.values()) + added


def _added_rows(params: Mapping[str, Param]) -> list[Row]:
    """SYS_HAS_GPS, EKF2_GPS_MODE, EKF2_GPS_P_NOISE, COM_POS_FS_EPH (each where the firmware
    has it: the older ones lack some)."""
    rows = []
    if "SYS_HAS_GPS" in params:
        rows.append(int_row(params, "SYS_HAS_GPS", 0, 1, _judge_has_gps))
    if "EKF2_GPS_MODE" in params:
        rows.append(int_row(params, "EKF2_GPS_MODE", 0, 1, _judge_gps_mode, GPS_MODE))
    rows.append(float_row(params, "EKF2_GPS_P_NOISE", "m", _judge_gps_p_noise))
    if "COM_POS_FS_EPH" in params:
        rows.append(float_row(params, "COM_POS_FS_EPH", "m", _judge_fs_eph))
    return rows


def _judge_ev_ctrl(velocity: bool, hgt_ref: int | None, v: int) -> Judgement:
    """EKF2_EV_CTRL with GPS: position, height (velocity with ODOMETRY), never our yaw."""
    want = EV_HPOS | EV_VPOS | (EV_VEL if velocity else 0)
    need = f"{want} ({ev_bits(want)}), no yaw"
    fix = (v & ~EV_YAW) | want
    if not v & EV_HPOS:
        return Judgement(
            Status.FAIL,
            need,
            "bit 0 off: EKF2 ignores our horizontal position, so nothing holds the position "
            "when GPS is lost",
            fix,
        )
    if v & EV_YAW:
        return Judgement(
            Status.FAIL,
            need,
            "bit 3 (our yaw) with GPS: PX4's heading must come from the magnetometer and GNSS "
            "(EKF-GSF) so that the service can align our output to it; fused, our yaw makes "
            "that reference partly ours (the alignment chases itself), and PX4 takes EV yaw "
            "beside GPS only in a NED frame (in FRD it resets its heading to ours)",
            fix,
        )
    if hgt_ref == 3 and not v & EV_VPOS:
        return Judgement(
            Status.FAIL, need, "bit 1 off: EKF2_HGT_REF = vision needs our height", fix
        )
    if v & want != want:
        return Judgement(
            Status.WARN, need, f"{ev_bits(want & ~v)} not fused: EKF2 takes less of us", fix
        )
    return Judgement(
        Status.OK,
        need,
        "while GNSS is fused EKF2 fuses our position relative to its own (the EV position "
        "bias estimator; our variance floored at EKF2_GPS_P_NOISE); at GNSS loss it resets "
        "to our position minus that offset: 0.095 m with the service switching GNSS off at "
        "once, 0.29 m at EKF2's own time-out (probe, 2026-11-29)",
    )


def _judge_hgt_ref(rng_ctrl: int | None, v: int) -> Judgement:
    """EKF2_HGT_REF with GPS: not GNSS, whose height comes back with a step."""
    need = "3 (vision) or 0 (baro)"
    step = (
        "with GNSS as the height reference EKF2 reset its height to GNSS when GPS came back: "
        "a 0.2-0.27 m step in the probe (0.009 m with 3)"
    )
    if v == 3:
        return Judgement(Status.OK, need, "our height: GNSS height becomes a biased aid; " + step)
    if v == 0:
        return Judgement(Status.OK, need, "baro: GNSS height is a biased aid, no reset at return")
    if v == 2:
        if rng_ctrl == 0:
            return Judgement(Status.FAIL, need, "range reference with EKF2_RNG_CTRL = 0", 3)
        return Judgement(Status.OK, need, "rangefinder height (flat ground): no GNSS step")
    if v == 1:
        return Judgement(Status.WARN, need, step, 3)
    return Judgement(Status.FAIL, need, "not a height source PX4 knows", 3)


def _judge_gps_ctrl(ctx: LinkContext, v: int) -> Judgement:
    """EKF2_GPS_CTRL with GPS: lon/lat, altitude and velocity fused."""
    want = GPS_POS | GPS_ALT | GPS_VEL
    need = "7 (lon/lat, altitude, velocity)"
    if not v & GPS_POS:
        return Judgement(
            Status.FAIL,
            need,
            "bit 0 off: EKF2 never fuses the GPS position, so there is no GPS-aided frame "
            "to align our output to (the service itself sets 0 during a denial, and 7 back)",
            v | want,
        )
    if v & want != want:
        return Judgement(
            Status.WARN, need, "altitude (bit 1) or velocity (bit 2) not fused", v | want
        )
    if ctx.gps_seen is False:
        return Judgement(
            Status.WARN, need, "no GNSS receiver reported while watching: --with-gps needs one"
        )
    return Judgement(
        Status.OK,
        need,
        "GNSS position, altitude and velocity fused (bit 3: a dual-antenna heading, only "
        "with such a receiver)",
    )


def _judge_has_gps(v: int) -> Judgement:
    """SYS_HAS_GPS: PX4 expects a receiver."""
    if v == 1:
        return Judgement(Status.OK, "1", "PX4 expects a GPS receiver")
    return Judgement(
        Status.FAIL,
        "1",
        "0: PX4 expects no GPS (its checks ignore one; in SITL the simulated receiver is off)",
        1,
    )


def _judge_gps_mode(v: int) -> Judgement:
    """EKF2_GPS_MODE: who may reset the position to GNSS."""
    if v == 0:
        return Judgement(
            Status.OK,
            "0 (auto)",
            "GNSS may not reset the position while our position is fused: no jump onto GPS at "
            "the return (EKF2 pulls at 0.06-0.09 m/s, or refuses GPS beyond its gate until "
            "the service slews onto it)",
        )
    return Judgement(
        Status.INFO,
        "0 (auto)",
        "dead reckoning: GNSS resets are forbidden whenever any other aiding is active; acceptable",
    )


def _judge_gps_p_noise(v: float) -> Judgement:
    """EKF2_GPS_P_NOISE: also the floor under our variance while GNSS is fused."""
    why = (
        "GNSS position noise, and the floor under our position variance while GNSS is fused: "
        "while GPS is good it, not we, anchors the position"
    )
    if 0.3 <= v <= 1.0:
        return Judgement(Status.OK, "0.3..1 (PX4's 0.5)", why)
    return Judgement(Status.WARN, "0.3..1 (PX4's 0.5)", f"{why}; {v:g} m is outside", 0.5)


def _judge_fs_eph(v: float) -> Judgement:
    """COM_POS_FS_EPH: context only (the probe saw no failsafe with PX4's 5 m)."""
    return Judgement(
        Status.INFO,
        "5 (PX4's default)",
        "the position failsafe's horizontal error: with 5 m no failsafe was seen at GPS loss "
        "with our position fused (probe on the ground, 2026-11-29)",
    )
