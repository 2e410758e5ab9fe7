"""The EKF2 parameters that decide whether PX4 fuses our estimate (pure): vision fusion
(EKF2_EV_CTRL, EKF2_HGT_REF), timing (EKF2_EV_DELAY, EKF2_DELAY_MAX), how far EKF2 trusts us
(noise floors, quality, gate) and the sensors it fuses beside us (rangefinder, GNSS, the
magnetometer's heading)."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import partial

from companion.autopilot.params import Judgement, Param, Row, Status
from companion.autopilot.px4.link_context import LinkContext
from companion.autopilot.px4.port_rules import TIMESYNC_MODES, companion_instance
from companion.autopilot.px4.typed_rows import float_row, int_row, int_value

EV_HPOS, EV_VPOS, EV_VEL, EV_YAW = 1, 2, 4, 8
MAG_TYPE_NONE = 5
HGT_REF = {0: "baro", 1: "GNSS", 2: "range", 3: "vision"}
RNG_CTRL = {0: "off", 1: "conditional", 2: "enabled"}
NOISE_MD = {0: "from the message", 1: "from the parameters"}
MAG_TYPE = {0: "automatic", 1: "magnetic heading", 5: "none", 6: "init only"}
# EKF2 fuses a vision sample when its delayed horizon passes the sample's stamp; the horizon
# trails PX4's clock by EKF2_DELAY_MAX less this much (PX4 SITL, main 2026-03: fused minus
# sample time 156 ms with EKF2_DELAY_MAX 200, 236 ms with 300; docs/decisions.md, "A longer
# fusion horizon")
HORIZON_SHORTFALL_MS = 45.0


def ev_bits(mask: int) -> str:
    """EKF2_EV_CTRL bits in words."""
    names = [(EV_HPOS, "hpos"), (EV_VPOS, "height"), (EV_VEL, "velocity"), (EV_YAW, "yaw")]
    parts = [n for bit, n in names if mask & bit]
    return "+".join(parts) if parts else "nothing"


def ev_words(mask: int) -> str:
    """EKF2_EV_CTRL bits as the parts of our estimate they fuse."""
    names = [
        (EV_HPOS, "horizontal position"),
        (EV_VPOS, "height"),
        (EV_VEL, "velocity"),
        (EV_YAW, "yaw"),
    ]
    return ", ".join(n for bit, n in names if mask & bit) or "nothing"


def has_magnetometer(params: Mapping[str, Param]) -> bool | None:
    """Whether a magnetometer gives EKF2 a north-aligned heading: SYS_HAS_MAG counts them
    (newer PX4; 0 / 1 before) and EKF2_MAG_TYPE is not None (5); None when neither is there."""
    mag_type = int_value(params, "EKF2_MAG_TYPE", 0, 6)
    count = int_value(params, "SYS_HAS_MAG", 0, 4)
    if mag_type == MAG_TYPE_NONE or count == 0:
        return False
    if mag_type is None and count is None:
        return None
    return True


@dataclass(frozen=True, slots=True)
class _Ekf2Facts:
    """What the EKF2 rules weigh a value against: our output, the other EKF2 settings, the
    magnetometer and whether the companion's link time-syncs."""

    ctx: LinkContext
    odometry: bool  # we send ODOMETRY in LOCAL_FRD
    vpe: bool  # we send a NED pose: VISION_POSITION_ESTIMATE or ODOMETRY in LOCAL_NED
    velocity: bool  # we send ODOMETRY (either frame): it carries our velocity
    vpe_message: bool  # we send VISION_POSITION_ESTIMATE (no quality field)
    hgt_ref: int | None  # EKF2_HGT_REF
    ev_ctrl: int | None  # EKF2_EV_CTRL
    rng_ctrl: int | None  # EKF2_RNG_CTRL
    mag: bool | None  # has_magnetometer
    timesync: bool | None  # the companion's MAVLink mode streams TIMESYNC (None: unknown)
    message: str  # our message(s), in words


def _ekf2_facts(params: Mapping[str, Param], ctx: LinkContext) -> _Ekf2Facts:
    """The settings the EKF2 rules depend on, read once."""
    inst = companion_instance(params, ctx)
    mode = int_value(params, f"MAV_{inst}_MODE", 0, 13) if inst is not None else None
    return _Ekf2Facts(
        ctx=ctx,
        odometry=ctx.output in ("odometry", "both") and ctx.odometry_frame != "local_ned",
        vpe=ctx.output in ("vision_position_estimate", "both")
        or (ctx.output == "odometry" and ctx.odometry_frame == "local_ned"),
        velocity=ctx.output in ("odometry", "both"),
        vpe_message=ctx.output in ("vision_position_estimate", "both"),
        hgt_ref=int_value(params, "EKF2_HGT_REF", 0, 3),
        ev_ctrl=int_value(params, "EKF2_EV_CTRL", 0, 15),
        rng_ctrl=int_value(params, "EKF2_RNG_CTRL", 0, 2),
        mag=has_magnetometer(params),
        timesync=None if mode is None else mode in TIMESYNC_MODES,
        message={"odometry": "ODOMETRY", "both": "both messages"}.get(
            ctx.output, "VISION_POSITION_ESTIMATE"
        ),
    )


def ekf2_rows(params: Mapping[str, Param], ctx: LinkContext) -> list[Row]:
    """Our output, then EKF2's parameters: vision fusion, timing, trust, the other sensors."""
    f = _ekf2_facts(params, ctx)
    return [
        *_output_rows(f),
        int_row(params, "EKF2_EV_CTRL", 0, 15, partial(_judge_ev_ctrl, f)),
        int_row(params, "EKF2_HGT_REF", 0, 3, partial(_judge_hgt_ref, f), HGT_REF),
        float_row(params, "EKF2_EV_DELAY", "ms", partial(_judge_ev_delay, f)),
        *(
            [float_row(params, "EKF2_DELAY_MAX", "ms", partial(_judge_delay_max, f))]
            if "EKF2_DELAY_MAX" in params  # (every EKF2 has it: a partial list may not)
            else []
        ),
        *_trust_rows(params, f),
        *_other_sensor_rows(params, f),
    ]


def _output_rows(f: _Ekf2Facts) -> list[Row]:
    """service.output: ODOMETRY needs a magnetometer to arm, and both messages interleave."""
    rows = []
    if f.odometry and f.mag is False:
        rows.append(
            Row(
                "service.output",
                f.ctx.output,
                "vision_position_estimate",
                "no magnetometer: EKF2 fuses ODOMETRY (LOCAL_FRD) but never aligns its heading, "
                "with or without our yaw, and PX4 refuses to arm; VISION_POSITION_ESTIMATE with "
                "EKF2_EV_CTRL bit 3 gives EKF2 our heading (seen on PX4 SITL, main 2026-03)",
                Status.FAIL,
            )
        )
    if f.ctx.output == "both":
        rows.append(
            Row(
                "service.output",
                "both",
                "odometry (or vision_position_estimate)",
                "VISION_POSITION_ESTIMATE and ODOMETRY both land on vehicle_visual_odometry: "
                "EKF2 gets one interleaved stream of NED and FRD samples (quality 0 and ours), "
                "and drops whichever is not newer than the last; send one of them",
                Status.WARN,
            )
        )
    return rows


def _trust_rows(params: Mapping[str, Param], f: _Ekf2Facts) -> list[Row]:
    """How far EKF2 trusts our samples: covariance source, noise floors, quality, gate."""
    return [
        int_row(params, "EKF2_EV_NOISE_MD", 0, 1, _judge_noise_md, NOISE_MD),
        float_row(params, "EKF2_EVP_NOISE", "m", _floor_judge(0.01, 0.3, "position", 0.1)),
        float_row(params, "EKF2_EVV_NOISE", "m/s", partial(_judge_evv_noise, f)),
        float_row(params, "EKF2_EVA_NOISE", "rad", _floor_judge(0.05, 0.3, "angle", 0.1)),
        int_row(params, "EKF2_EV_QMIN", 0, 100, partial(_judge_qmin, f)),
        float_row(params, "EKF2_EVP_GATE", "SD", _judge_gate),
    ]


def _other_sensor_rows(params: Mapping[str, Param], f: _Ekf2Facts) -> list[Row]:
    """The sensors EKF2 fuses beside us: rangefinder, GNSS, magnetometer (the heading)."""
    return [
        int_row(params, "EKF2_RNG_CTRL", 0, 2, partial(_judge_rng_ctrl, f), RNG_CTRL),
        int_row(params, "EKF2_GPS_CTRL", 0, 15, partial(_judge_gps_ctrl, f)),
        int_row(params, "EKF2_MAG_TYPE", 0, 6, partial(_judge_mag_type, f), MAG_TYPE),
    ]


def _ev_ctrl_wanted(f: _Ekf2Facts) -> tuple[int, int, bool]:
    """EKF2_EV_CTRL bits required (else nothing is fused), wanted, and whether yaw is needed."""
    required = EV_HPOS | (EV_VPOS if f.hgt_ref == 3 else 0)
    yaw_needed = f.vpe and not f.odometry and f.mag is False
    want = EV_HPOS | EV_VPOS | (EV_VEL if f.velocity else 0) | (EV_YAW if yaw_needed else 0)
    return required, want, yaw_needed


def _judge_ev_ctrl(f: _Ekf2Facts, v: int) -> Judgement:
    """EKF2_EV_CTRL: which parts of our estimate EKF2 fuses, and the yaw bit by output."""
    # what PX4 itself showed (docs/decisions.md, "EV yaw"): VISION_POSITION_ESTIMATE is NED
    # and is fused only once EKF2's heading is aligned: by the magnetometer, or by our yaw
    # (bit 3); ODOMETRY in LOCAL_FRD is fused at any heading, but its yaw (bit 3) never
    # aligns EKF2's heading and stops the magnetometer's: PX4 then refuses to arm
    required, want, yaw_needed = _ev_ctrl_wanted(f)
    need = f"{want} ({ev_bits(want)})"
    failed = _ev_ctrl_failure(f, v, required, want, yaw_needed)
    if failed is not None:
        return failed
    if v & want != want:
        notes = {
            EV_VPOS: "height (our z is metric, from the rangefinders)",
            EV_VEL: "velocity (ODOMETRY carries it; it steadies the position)",
        }
        absent = [n for b, n in notes.items() if want & ~v & b]
        return Judgement(
            Status.WARN, need, "horizontal position fused; not " + ", ".join(absent), v | want
        )
    if f.vpe and v & EV_YAW and f.mag:
        return Judgement(
            Status.OK,
            f"{need} or {want | EV_YAW} ({ev_bits(want | EV_YAW)})",
            f"EKF2 fuses our {ev_words(v)} ({f.message}); with bit 3 our heading replaces "
            "the magnetometer's, which keeps EKF2's heading and our NED frame together "
            "(both ours) where the magnetometer is disturbed; without it the magnetometer "
            "gives north and our heading drift shows as position innovations",
        )
    if f.vpe and f.mag and not v & EV_YAW:
        return Judgement(
            Status.OK,
            f"{need} or {want | EV_YAW} ({ev_bits(want | EV_YAW)})",
            f"EKF2 fuses our {ev_words(v)} ({f.message}); the magnetometer gives the "
            "north-aligned heading VISION_POSITION_ESTIMATE needs (where it is disturbed, "
            "indoors: bit 3 and EKF2_MAG_TYPE = 5)",
        )
    return Judgement(Status.OK, need, f"EKF2 fuses our {ev_words(v)} ({f.message})")


def _ev_ctrl_failure(
    f: _Ekf2Facts, v: int, required: int, want: int, yaw_needed: bool
) -> Judgement | None:
    """EKF2_EV_CTRL values that leave our position unfused or PX4 unable to arm, or None."""
    need = f"{want} ({ev_bits(want)})"
    if v & required != required:
        missing = ev_words(required & ~v)
        why = f"EKF2 ignores our {missing}: bit 0 enables horizontal position fusion"
        if required & EV_VPOS:
            why += ", bit 1 height (EKF2_HGT_REF = vision needs it)"
        keep = v & ~EV_YAW if f.odometry else v
        return Judgement(Status.FAIL, need, why, keep | want)
    if f.odometry and v & EV_YAW:
        return Judgement(
            Status.FAIL,
            need,
            "bit 3 (yaw) with ODOMETRY in LOCAL_FRD: EKF2 fuses our yaw instead of the "
            "magnetometer's but never aligns its heading with it (cs_yaw_align stays "
            "false), and PX4 refuses to arm ('heading estimate not stable'); as seen on PX4 "
            "SITL (main, 2026-03), with a magnetometer and without",
            (v & ~EV_YAW) | want,
        )
    if yaw_needed and not v & EV_YAW:
        return Judgement(
            Status.FAIL,
            need,
            "no magnetometer (SYS_HAS_MAG = 0 or EKF2_MAG_TYPE = 5): EKF2 has no "
            "north-aligned heading unless it takes ours (bit 3), and it fuses "
            "VISION_POSITION_ESTIMATE (NED) only with one: without bit 3 our position is "
            "never fused",
            v | want,
        )
    return None


def _judge_hgt_ref(f: _Ekf2Facts, v: int) -> Judgement:
    """EKF2_HGT_REF: our range-aided height suits flat ground; baro, range, GNSS weighed."""
    need = "3 (vision), over flat ground"
    flat = (
        "our height follows the rangefinders (height above ground): as the reference it "
        "suits flat ground only, as PX4 says of range and vision height; over uneven "
        "terrain keep baro (0) and fuse our height with EKF2_EV_CTRL bit 1"
    )
    if v == 3:
        return Judgement(Status.OK, need, "our metric height (range-aided VO); " + flat)
    if v == 2:
        if f.rng_ctrl == 0:
            return Judgement(
                Status.FAIL, need, "range reference but EKF2_RNG_CTRL = 0 (range off)", 3
            )
        return Judgement(
            Status.OK, need, "rangefinder height: fine over flat ground (PX4's advice)"
        )
    if v == 0:
        return Judgement(
            Status.WARN,
            need,
            "baro drifts and sees rotor wash; over flat ground our vision height is "
            "steadier (over uneven terrain baro is the right reference)",
            3,
        )
    if v == 1:
        if f.ctx.gps_seen:
            why = "GNSS height: metres of noise, fine only outdoors"
        elif f.ctx.gps_seen is False:
            why = (
                "GNSS height reference, but no GNSS receiver reported while watching: EKF2 "
                "falls back to another height source (baro)"
            )
        else:
            why = (
                "GNSS height reference (a receiver was not watched for: --watch-s 0); "
                "without one EKF2 falls back to another height source (baro)"
            )
        return Judgement(Status.WARN, need, f"{why}; {flat}", 3)
    return Judgement(Status.FAIL, need, "not a height source PX4 knows", 3)


def _judge_delay_max(f: _Ekf2Facts, v: float) -> Judgement:
    """EKF2_DELAY_MAX: its fusion horizon (HORIZON_SHORTFALL_MS less) must reach back as far
    as our oldest stamps (service.stale_frame_ms plus the ODOMETRY centring)."""
    oldest = f.ctx.oldest_stamp_ms
    need_ms = 10.0 * math.ceil((oldest + HORIZON_SHORTFALL_MS) / 10.0)
    need = f">= {need_ms:g} ms"
    why = (
        f"EKF2 fuses each of our samples when its delayed horizon (~EKF2_DELAY_MAX - "
        f"{HORIZON_SHORTFALL_MS:g} ms behind PX4's clock) passes the sample's stamp, and our "
        f"stamps leave up to {oldest:.0f} ms old (service.stale_frame_ms and the ODOMETRY "
        "centring)"
    )
    if v >= need_ms:
        return Judgement(Status.OK, need, why)
    return Judgement(
        Status.WARN,
        need,
        f"{why}: a sample older than ~{v - HORIZON_SHORTFALL_MS:.0f} ms arrives behind the "
        "horizon and is fused late, at the horizon's instant (up to 100 ms off), or dropped; "
        "raise it (PX4 applies it after a reboot) or lower service.stale_frame_ms",
        need_ms,
    )


def _judge_ev_delay(f: _Ekf2Facts, v: float) -> Judgement:
    """EKF2_EV_DELAY: 0 where PX4 time-syncs our exposure stamps, else the link's latency."""
    if f.timesync is False:
        return Judgement(
            Status.INFO,
            "the link's latency",
            "this link's MAVLink mode streams no TIMESYNC, so PX4 stamps our messages at "
            "arrival: EKF2_EV_DELAY is then what compensates the latency (see MAV_n_MODE)",
        )
    need = "0 ms, with TIMESYNC working"
    why = (
        "we stamp at exposure and PX4 moves the stamp into its clock through TIMESYNC: a "
        "delay on top counts the latency twice (while PX4's time sync works on this link: "
        "`check` watches it; without it PX4 stamps at arrival and the measured latency "
        "belongs here)"
    )
    if v <= 5.0:
        return Judgement(Status.OK, need, why)
    return Judgement(
        Status.WARN,
        need,
        f"EKF2 takes each sample as {v:g} ms older than its stamp says, against the state "
        f"of that earlier instant; {why}",
        0.0,
    )


def _judge_noise_md(v: int) -> Judgement:
    """EKF2_EV_NOISE_MD: our covariance is real, so EKF2 should take it from the message."""
    why = "0: EKF2 uses the covariance we send, the EKF2_EV*_NOISE values as floors"
    if v == 0:
        return Judgement(Status.OK, "0 (from the message)", why)
    return Judgement(Status.WARN, "0 (from the message)", "our covariance is ignored; " + why, 0)


def _judge_evv_noise(f: _Ekf2Facts, v: float) -> Judgement:
    """EKF2_EVV_NOISE: the floor under our velocity variance. Above the sigma we send
    (service.odometry_velocity_sigma_m_s) EKF2 weighs our velocity at the floor instead, and
    its own integration of the accelerometer decides more of its height (docs/decisions.md,
    "What EKF2 adds to our height")."""
    ours = f.ctx.velocity_sigma_m_s
    if not f.velocity:
        return Judgement(Status.OK, "any", f"not used: {f.message} carries no velocity")
    need = f"0.01..{ours:g} (our velocity sigma)"
    why = f"floor on the velocity variance EKF2 takes from us; we send {ours:g} m/s"
    if v < 0.01:
        return Judgement(Status.FAIL, need, f"below PX4's minimum; {why}", max(ours, 0.01))
    if v > ours * 1.001:
        return Judgement(
            Status.WARN,
            need,
            f"above our sigma: EKF2 weighs our velocity at {v:g} m/s, not as measured ({why})",
            max(ours, 0.01),
        )
    return Judgement(Status.OK, need, why)


def _floor_judge(lo: float, hi: float, what: str, default: float) -> Callable[[float], Judgement]:
    """EKF2_EV*_NOISE: a floor on our variance, within PX4's minimum and our accuracy."""

    def judge(v: float) -> Judgement:
        need = f"{lo:g}..{hi:g}"
        why = f"floor on the {what} variance EKF2 takes from us"
        if v < lo:
            return Judgement(Status.FAIL, need, f"below PX4's minimum; {why}", default)
        if v > hi:
            return Judgement(
                Status.WARN,
                need,
                f"above our accuracy: EKF2 under-trusts vision ({why})",
                default,
            )
        return Judgement(Status.OK, need, why)

    return judge


def _judge_qmin(f: _Ekf2Facts, v: int) -> Judgement:
    """EKF2_EV_QMIN: VISION_POSITION_ESTIMATE has no quality; ours falls while scale settles."""
    if f.vpe_message:
        why = "VISION_POSITION_ESTIMATE has no quality field: PX4 stores 0, so any minimum "
        why += "rejects every sample"
        if v > 0:
            return Judgement(Status.FAIL, "0", why, 0)
        return Judgement(Status.OK, "0", why)
    if v > 50:
        why = "our ODOMETRY quality falls while the scale converges: EKF2 would drop vision"
        return Judgement(Status.WARN, "<= 50", why, 0)
    return Judgement(Status.OK, "<= 50", "EKF2 drops samples whose quality is below it")


def _judge_gate(v: float) -> Judgement:
    """EKF2_EVP_GATE: wide enough for a fast turn or a VO re-init, narrow enough for outliers."""
    why = "innovation gate [SD] on our position"
    if v < 3.0:
        return Judgement(
            Status.WARN, "3..10", f"{why}: rejects us after a fast turn or a VO re-init", 5.0
        )
    if v > 10.0:
        return Judgement(Status.WARN, "3..10", f"{why}: lets outliers in", 5.0)
    return Judgement(Status.OK, "3..10", why)


def _judge_rng_ctrl(f: _Ekf2Facts, v: int) -> Judgement:
    """EKF2_RNG_CTRL: PX4's own rangefinder use; a range height reference needs it on."""
    if f.hgt_ref == 2 and v != 2:
        return Judgement(
            Status.FAIL if v == 0 else Status.WARN,
            "2 (enabled)",
            "EKF2_HGT_REF = range needs the rangefinder fused all the time",
            2,
        )
    return Judgement(
        Status.OK,
        "any",
        "PX4's own use of one rangefinder for height; ours read DISTANCE_SENSOR either way",
    )


def _judge_gps_ctrl(f: _Ekf2Facts, v: int) -> Judgement:
    """EKF2_GPS_CTRL: GNSS fused beside us, or off where there is none (--no-gnss)."""
    if f.ctx.gps_seen is True:
        return Judgement(Status.OK, "any", "GNSS present: EKF2 fuses vision alongside it")
    if v == 0:
        return Judgement(Status.OK, "any", "GNSS fusion off")
    if f.ctx.no_gnss:
        return Judgement(Status.WARN, "0 (--no-gnss)", "GNSS fusion off, as asked", 0)
    seen = (
        "no GNSS receiver reported while watching"
        if f.ctx.gps_seen is False
        else "a GNSS receiver was not watched for"
    )
    return Judgement(
        Status.INFO,
        "any",
        f"{seen}: with nothing to fuse the setting changes nothing now; 0 would keep a "
        "receiver fitted later out of the solution (`configure --no-gnss` writes it)",
    )


def _judge_mag_type(f: _Ekf2Facts, v: int) -> Judgement:
    """EKF2_MAG_TYPE: the heading source our output needs (magnetometer, or our yaw in NED)."""
    yaw = f.ev_ctrl is not None and bool(f.ev_ctrl & EV_YAW)
    if f.odometry:
        why = (
            "ODOMETRY in LOCAL_FRD is fused at any heading, but only the magnetometer "
            "aligns EKF2's heading then (our yaw does not): without it PX4 refuses to arm"
        )
        if f.mag is False:
            return Judgement(Status.FAIL, "a magnetometer", why)
        return Judgement(Status.OK, "a magnetometer", why)
    why = "VISION_POSITION_ESTIMATE is NED: EKF2 fuses it only with a north-aligned heading"
    if f.mag is False and not yaw:
        return Judgement(
            Status.INFO,
            "a magnetometer, or EV yaw",
            f"{why}, and it has neither a magnetometer nor our yaw: see EKF2_EV_CTRL",
        )
    if f.mag is False:
        return Judgement(Status.OK, "a heading source", f"{why}: ours (EKF2_EV_CTRL bit 3)")
    return Judgement(Status.OK, "a heading source", why)
