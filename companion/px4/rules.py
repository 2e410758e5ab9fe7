"""The PX4 parameters that decide whether EKF2 fuses our estimate: what we need and why.

One row per parameter: its value, what we need, why (in PX4's terms), a status, and the
value(s) ``configure`` would write. FAIL: EKF2 will not fuse our estimate (or the link will not
work) as it is. WARN: it works, but not as well as it should, or not as DESIGN.md section 6
recommends. OK: as needed. INFO: context only.

The rules follow PX4 1.14+ (EKF2_EV_CTRL / EKF2_HGT_REF, which replaced EKF2_AID_MASK /
EKF2_HGT_MODE) and DESIGN.md section 6: VISION_POSITION_ESTIMATE is NED and needs a
north-aligned heading; ODOMETRY (LOCAL_FRD / BODY_FRD, VISION) works at any heading; we stamp at
exposure and PX4 converts through TIMESYNC, so EKF2_EV_DELAY stays 0 where the link time-syncs;
our covariance is real, so EKF2 should use it (EKF2_EV_NOISE_MD 0) with the noise parameters as
floors. Defaults differ between versions (EKF2_EV_CTRL: 15 before PX4 1.16, 0 since); PX4
after 1.16 configures ports with SER_<port>_PROT and MAV_ETH_EN instead of MAV_n_CONFIG, and
the link rows follow whichever the firmware has; where it has none of them (PX4 SITL, whose
start-up script starts the MAVLink instances) there is nothing to set, and no version string is
trusted for it (a build from an untagged commit reports v0.0.0).

EKF2_EV_CTRL bit 3 (yaw), as the real PX4 (SITL, main 2026-03) showed it: VISION_POSITION_ESTIMATE
needs it without a magnetometer (else EKF2's heading never aligns and NED is never fused) and may
have it with one; ODOMETRY (LOCAL_FRD) must not have it (EKF2 then never aligns its heading and
PX4 refuses to arm) and needs a magnetometer for the same reason.
"""

from __future__ import annotations

import enum
import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import partial

from companion.px4.encoding import float_encoded_int, int_encoded_float

EV_HPOS, EV_VPOS, EV_VEL, EV_YAW = 1, 2, 4, 8
PORT_CODES = {"TELEM1": 101, "TELEM2": 102, "TELEM3": 103, "TELEM4": 104, "ETHERNET": 1000}
MIN_SERIAL_BAUD = 460800  # ODOMETRY at 30 Hz (~8 kB/s) + TIMESYNC + PX4's onboard streams
TIMESYNC_MODES = frozenset({2, 5, 8, 9, 11})  # MAV_n_MODEs whose streams include TIMESYNC
MAG_TYPE_NONE = 5
LOOPBACK_HOSTS = ("127.", "localhost", "::1")
# SER_<tag>_PROT ports in PX4's port order (firmware after 1.16 numbers MAVLink instances so)
PORT_TAGS = ("TEL1", "TEL2", "TEL3", "TEL4", "GPS1", "GPS2", "GPS3", "RC", "WIFI", "EXT2")

HGT_REF = {0: "baro", 1: "GNSS", 2: "range", 3: "vision"}
MAV_MODE = {
    0: "Normal",
    1: "Custom",
    2: "Onboard",
    3: "OSD",
    4: "Magic",
    5: "Config",
    7: "Minimal",
    8: "External Vision",
    10: "Gimbal",
    11: "Onboard Low Bandwidth",
    12: "uAvionix",
    13: "Low Bandwidth",
}
SERIAL_PORT = {
    0: "disabled",
    101: "TELEM 1",
    102: "TELEM 2",
    103: "TELEM 3",
    104: "TELEM/SERIAL 4",
    201: "GPS 1",
    202: "GPS 2",
    300: "Radio Controller",
    301: "Wifi",
    1000: "Ethernet",
}
BROADCAST = {0: "never", 1: "always", 2: "multicast only"}
RNG_CTRL = {0: "off", 1: "conditional", 2: "enabled"}
NOISE_MD = {0: "from the message", 1: "from the parameters"}
MAG_TYPE = {0: "automatic", 1: "magnetic heading", 5: "none", 6: "init only"}
REBOOT_PARAMS = frozenset({"EKF2_HGT_REF", "EKF2_EV_DELAY", "EKF2_DELAY_MAX"})
# EKF2 fuses a vision sample when its delayed horizon passes the sample's stamp; the horizon
# trails PX4's clock by EKF2_DELAY_MAX less this much (PX4 SITL, main 2026-03: fused minus
# sample time 156 ms with EKF2_DELAY_MAX 200, 236 ms with 300; docs/decisions.md, "A longer
# fusion horizon")
HORIZON_SHORTFALL_MS = 45.0
REBOOT_PREFIXES = ("MAV_", "SER_", "SYS_HAS_")


class Status(enum.Enum):
    """How a parameter stands."""

    OK = "OK"
    WARN = "WARN"
    FAIL = "FAIL"
    INFO = "-"


@dataclass(frozen=True, slots=True)
class Param:
    """A parameter as read from the autopilot (type as PX4 declares it)."""

    name: str
    value: int | float
    is_int: bool


@dataclass(frozen=True, slots=True)
class Target:
    """A value to write (with the parameter's own type) and whether PX4 needs a reboot."""

    name: str
    value: int | float
    is_int: bool
    reboot: bool


@dataclass(frozen=True, slots=True)
class Row:
    """One line of the table."""

    name: str
    value: str
    need: str
    why: str
    status: Status
    targets: tuple[Target, ...] = ()


@dataclass(frozen=True, slots=True)
class LinkContext:
    """What the rules need to know about our side."""

    output: str = "vision_position_estimate"  # service.output
    fc_port: str = "ETHERNET"  # the autopilot port the companion is wired to
    link_kind: str = "udpin"  # the service's link: udpin, udpout, tcp or serial
    link_port: int = 14540  # its UDP/TCP port, or the serial baud rate
    gps_seen: bool | None = None  # a GNSS receiver reported while watching (None: not watched)
    link_host: str = "127.0.0.1"  # its host (UDP/TCP: where it listens or sends to)
    no_gnss: bool = False  # configure --no-gnss: also turn GNSS fusion off (EKF2_GPS_CTRL = 0)
    odometry_frame: str = "local_frd"  # service.odometry_frame
    # the oldest our samples' stamps can be when they leave: service.stale_frame_ms plus the
    # ODOMETRY centring's (service.odometry_centre_frames - 1) / 2 frames [ms]
    oldest_stamp_ms: float = 100.0
    velocity_sigma_m_s: float = 0.1  # service.odometry_velocity_sigma_m_s


@dataclass(frozen=True, slots=True)
class Judgement:
    """The verdict on one value; ``target`` is what configure writes unless OK."""

    status: Status
    need: str
    why: str
    target: int | float | None = None


def needs_reboot(name: str) -> bool:
    """Whether PX4 applies a new value of ``name`` only after a reboot."""
    return name in REBOOT_PARAMS or name.startswith(REBOOT_PREFIXES)


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


def _labelled(value: int, labels: Mapping[int, str]) -> str:
    return f"{value} ({labels[value]})" if value in labels else str(value)


def _int_value(params: Mapping[str, Param], name: str, lo: float, hi: float) -> int | None:
    """An INT32's value as the user meant it (a float-encoded one decoded), or None."""
    p = params.get(name)
    if p is None or not p.is_int:
        return None
    f = float_encoded_int(int(p.value), lo, hi)
    return int(f) if f is not None else int(p.value)


def _int_row(
    params: Mapping[str, Param],
    name: str,
    lo: float,
    hi: float,
    judge: Callable[[int], Judgement],
    labels: Mapping[int, str] | None = None,
) -> Row:
    """Row of an INT32 parameter: missing, float-encoded, out of range, or judged."""
    p = params.get(name)
    reboot = needs_reboot(name)
    if p is None:
        return Row(
            name,
            "missing",
            "present",
            "this firmware has no such parameter (the check knows PX4 1.14 and later)",
            Status.FAIL,
        )
    if not p.is_int:
        return Row(name, f"{p.value:g} (REAL32)", "INT32", "PX4 declares it INT32", Status.FAIL)
    v = int(p.value)
    f = float_encoded_int(v, lo, hi)
    if f is not None:
        meant = judge(int(f))
        target = int(f) if meant.status in (Status.OK, Status.INFO) else meant.target
        return Row(
            name,
            str(v),
            f"{meant.need}, as an INT32",
            f"float-encoded: {v} is 0x{v & 0xFFFFFFFF:08X}, the bytes of the float {f:g}; a "
            f"tool wrote {f:g} as a float into this INT32 and PX4 uses the integer {v}",
            Status.FAIL,
            (Target(name, int(target if target is not None else f), True, reboot),),
        )
    j = judge(v)
    if not lo <= v <= hi:
        j = Judgement(Status.FAIL, j.need, f"out of range ({lo:g}..{hi:g}); " + j.why, j.target)
    targets: tuple[Target, ...] = ()
    if j.status in (Status.FAIL, Status.WARN) and j.target is not None and j.target != v:
        targets = (Target(name, int(j.target), True, reboot),)
    return Row(name, _labelled(v, labels or {}), j.need, j.why, j.status, targets)


def _float_row(
    params: Mapping[str, Param], name: str, unit: str, judge: Callable[[float], Judgement]
) -> Row:
    """Row of a REAL32 parameter: missing, int-encoded or judged."""
    p = params.get(name)
    reboot = needs_reboot(name)
    if p is None:
        return Row(name, "missing", "present", "this firmware has no such parameter", Status.FAIL)
    v = float(p.value)
    i = int_encoded_float(v) if not p.is_int else None
    if i is not None:
        meant = judge(float(i))
        target = float(i) if meant.status is Status.OK else meant.target
        return Row(
            name,
            f"{v:.3g}",
            f"{meant.need}, as a REAL32",
            f"int-encoded: {v:.3g} is the bytes of the integer {i}; a tool wrote {i} as an "
            "INT32 into this float parameter",
            Status.FAIL,
            (Target(name, float(target if target is not None else i), False, reboot),),
        )
    j = judge(v)
    targets: tuple[Target, ...] = ()
    if j.status in (Status.FAIL, Status.WARN) and j.target is not None:
        targets = (Target(name, float(j.target), p.is_int, reboot),)
    return Row(name, f"{v:g} {unit}".strip(), j.need, j.why, j.status, targets)


def evaluate(params: Mapping[str, Param], ctx: LinkContext) -> list[Row]:
    """Every row, EKF2 first, then the companion's MAVLink instance."""
    return [*_ekf2_rows(params, ctx), *_link_rows(params, ctx)]


def has_magnetometer(params: Mapping[str, Param]) -> bool | None:
    """Whether a magnetometer gives EKF2 a north-aligned heading: SYS_HAS_MAG counts them
    (newer PX4; 0 / 1 before) and EKF2_MAG_TYPE is not None (5); None when neither is there."""
    mag_type = _int_value(params, "EKF2_MAG_TYPE", 0, 6)
    count = _int_value(params, "SYS_HAS_MAG", 0, 4)
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
    inst = _companion_instance(params, ctx)
    mode = _int_value(params, f"MAV_{inst}_MODE", 0, 13) if inst is not None else None
    return _Ekf2Facts(
        ctx=ctx,
        odometry=ctx.output in ("odometry", "both") and ctx.odometry_frame != "local_ned",
        vpe=ctx.output in ("vision_position_estimate", "both")
        or (ctx.output == "odometry" and ctx.odometry_frame == "local_ned"),
        velocity=ctx.output in ("odometry", "both"),
        vpe_message=ctx.output in ("vision_position_estimate", "both"),
        hgt_ref=_int_value(params, "EKF2_HGT_REF", 0, 3),
        ev_ctrl=_int_value(params, "EKF2_EV_CTRL", 0, 15),
        rng_ctrl=_int_value(params, "EKF2_RNG_CTRL", 0, 2),
        mag=has_magnetometer(params),
        timesync=None if mode is None else mode in TIMESYNC_MODES,
        message={"odometry": "ODOMETRY", "both": "both messages"}.get(
            ctx.output, "VISION_POSITION_ESTIMATE"
        ),
    )


def _ekf2_rows(params: Mapping[str, Param], ctx: LinkContext) -> list[Row]:
    """Our output, then EKF2's parameters: vision fusion, timing, trust, the other sensors."""
    f = _ekf2_facts(params, ctx)
    return [
        *_output_rows(f),
        _int_row(params, "EKF2_EV_CTRL", 0, 15, partial(_judge_ev_ctrl, f)),
        _int_row(params, "EKF2_HGT_REF", 0, 3, partial(_judge_hgt_ref, f), HGT_REF),
        _float_row(params, "EKF2_EV_DELAY", "ms", partial(_judge_ev_delay, f)),
        *(
            [_float_row(params, "EKF2_DELAY_MAX", "ms", partial(_judge_delay_max, f))]
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
        _int_row(params, "EKF2_EV_NOISE_MD", 0, 1, _judge_noise_md, NOISE_MD),
        _float_row(params, "EKF2_EVP_NOISE", "m", _floor_judge(0.01, 0.3, "position", 0.1)),
        _float_row(params, "EKF2_EVV_NOISE", "m/s", partial(_judge_evv_noise, f)),
        _float_row(params, "EKF2_EVA_NOISE", "rad", _floor_judge(0.05, 0.3, "angle", 0.1)),
        _int_row(params, "EKF2_EV_QMIN", 0, 100, partial(_judge_qmin, f)),
        _float_row(params, "EKF2_EVP_GATE", "SD", _judge_gate),
    ]


def _other_sensor_rows(params: Mapping[str, Param], f: _Ekf2Facts) -> list[Row]:
    """The sensors EKF2 fuses beside us: rangefinder, GNSS, magnetometer (the heading)."""
    return [
        _int_row(params, "EKF2_RNG_CTRL", 0, 2, partial(_judge_rng_ctrl, f), RNG_CTRL),
        _int_row(params, "EKF2_GPS_CTRL", 0, 15, partial(_judge_gps_ctrl, f)),
        _int_row(params, "EKF2_MAG_TYPE", 0, 6, partial(_judge_mag_type, f), MAG_TYPE),
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


def _uart_order(params: Mapping[str, Param]) -> dict[str, int]:
    """Firmware after PX4 1.16: SER_<tag>_PROT of each port, in PX4's port order."""
    prots: dict[str, int] = {}
    for name in params:
        m = re.fullmatch(r"SER_(\w+)_PROT", name)
        value = _int_value(params, name, 0, 1000) if m else None
        if m and value is not None:
            prots[m.group(1)] = value
    rank = {t: i for i, t in enumerate(PORT_TAGS)}
    return dict(sorted(prots.items(), key=lambda kv: (rank.get(kv[0], len(rank)), kv[0])))


def _has_mav_config(params: Mapping[str, Param]) -> bool:
    return any(f"MAV_{i}_CONFIG" in params for i in range(3))


def _has_port_params(params: Mapping[str, Param]) -> bool:
    """The firmware assigns MAVLink instances to ports by parameters (MAV_n_CONFIG, or
    SER_<port>_PROT / MAV_ETH_EN after PX4 1.16). PX4 SITL has none of them: its start-up
    script starts each instance (``mavlink start -u 14580 -m onboard -o 14540``), and its
    MAV_n_* parameters are unused, so PX4 does not even list them over MAVLink."""
    return (
        _has_mav_config(params)
        or "MAV_ETH_EN" in params
        or any(re.fullmatch(r"SER_\w+_PROT", n) for n in params)
    )


def _companion_instance(params: Mapping[str, Param], ctx: LinkContext) -> int | None:
    """The MAVLink instance that runs on the companion's port, or None (none runs there)."""
    if not _has_port_params(params):
        return None
    if _has_mav_config(params):
        code = PORT_CODES[ctx.fc_port]
        found = [i for i in range(3) if _int_value(params, f"MAV_{i}_CONFIG", 0, 1000) == code]
        return found[0] if found else None
    uarts = [t for t, v in _uart_order(params).items() if v == 1]
    if ctx.fc_port == "ETHERNET":
        on = _int_value(params, "MAV_ETH_EN", 0, 1) == 1
        return len(uarts) if on and len(uarts) < 3 else None
    tag = "TEL" + ctx.fc_port[-1]
    return uarts.index(tag) if tag in uarts and uarts.index(tag) < 3 else None


def _port_rows(params: Mapping[str, Param], ctx: LinkContext) -> tuple[int | None, list[Row]]:
    """The instance on the companion's port and its row(s): MAV_n_CONFIG (PX4 up to 1.16), or
    SER_<port>_PROT / MAV_ETH_EN (after 1.16, where MAVLink instances are numbered in port
    order, Ethernet's after the UARTs')."""
    code = PORT_CODES[ctx.fc_port]
    if not _has_port_params(params):
        return None, [
            Row(
                "MAVLink ports",
                "set by the start-up script",
                "-",
                "this firmware has no MAV_n_CONFIG, SER_<port>_PROT or MAV_ETH_EN (PX4 SITL: "
                "its start-up script starts each MAVLink instance with its ports and mode), so "
                "no parameter says which instance is the companion's; whether our messages "
                "arrive and PX4 time-syncs is watched below",
                Status.INFO,
            )
        ]
    if _has_mav_config(params):
        return _mav_config_port_rows(params, ctx, code)
    uarts = [t for t, v in _uart_order(params).items() if v == 1]
    if ctx.fc_port == "ETHERNET":
        return _ethernet_port_rows(params, uarts)
    return _uart_port_rows(params, ctx, uarts)


def _mav_config_port_rows(
    params: Mapping[str, Param], ctx: LinkContext, code: int
) -> tuple[int | None, list[Row]]:
    """PX4 up to 1.16: the MAV_n_CONFIG naming the companion's port, else a free instance."""
    configs = {i: _int_value(params, f"MAV_{i}_CONFIG", 0, 1000) for i in range(3)}
    found = [i for i, c in configs.items() if c == code]
    if found:
        inst = found[0]
        return inst, [
            Row(
                f"MAV_{inst}_CONFIG",
                _labelled(code, SERIAL_PORT),
                _labelled(code, SERIAL_PORT),
                f"MAVLink instance {inst} runs on {ctx.fc_port}, where the companion is wired",
                Status.OK,
            )
        ]
    free = [i for i in (1, 2, 0) if configs.get(i) == 0]
    if not free:
        return None, [
            Row(
                "MAV_n_CONFIG",
                ", ".join(f"{i}: {configs[i]}" for i in range(3)),
                f"one instance on {ctx.fc_port}",
                "no MAVLink instance runs on the companion's port and none is free",
                Status.FAIL,
            )
        ]
    inst = free[0]
    name = f"MAV_{inst}_CONFIG"
    current = configs.get(inst)
    return inst, [
        Row(
            name,
            _labelled(current, SERIAL_PORT) if current is not None else "missing",
            _labelled(code, SERIAL_PORT),
            f"no MAVLink instance runs on {ctx.fc_port}, where the companion is wired "
            f"(instance {inst} is free)",
            Status.FAIL,
            (Target(name, code, True, True),),
        )
    ]


def _ethernet_port_rows(
    params: Mapping[str, Param], uarts: list[str]
) -> tuple[int | None, list[Row]]:
    """After PX4 1.16: MAV_ETH_EN, whose instance comes after the MAVLink UARTs (three at most)."""
    name = "MAV_ETH_EN"
    on = _int_value(params, name, 0, 1)
    inst = len(uarts)
    if on is None or inst > 2:
        why = (
            "this firmware has neither MAV_n_CONFIG nor MAV_ETH_EN: no MAVLink on Ethernet"
            if on is None
            else f"all three MAVLink instances run on UARTs ({', '.join(uarts)})"
        )
        return None, [Row(name, str(on), "1 (on)", why, Status.FAIL)]
    why = (
        f"MAVLink on Ethernet runs as instance {inst}, after the {inst} MAVLink UART "
        "port(s) (PX4 after 1.16: MAV_ETH_EN replaced MAV_n_CONFIG = 1000)"
    )
    if on == 1:
        return inst, [Row(name, "1 (on)", "1 (on)", why, Status.OK)]
    return inst, [Row(name, "0 (off)", "1 (on)", why, Status.FAIL, (Target(name, 1, True, True),))]


def _uart_port_rows(
    params: Mapping[str, Param], ctx: LinkContext, uarts: list[str]
) -> tuple[int | None, list[Row]]:
    """After PX4 1.16: SER_<port>_PROT = MAVLink, its instance numbered in port order."""
    tag = "TEL" + ctx.fc_port[-1]
    name = f"SER_{tag}_PROT"
    prot = _uart_order(params).get(tag)
    if prot is None:
        why = "this firmware has neither MAV_n_CONFIG nor SER_<port>_PROT for this port"
        return None, [Row(name, "missing", "1 (MAVLink)", why, Status.FAIL)]
    rank = {t: i for i, t in enumerate(PORT_TAGS)}
    after = sorted({*uarts, tag}, key=lambda t: (rank.get(t, len(rank)), t))
    inst = after.index(tag)
    if inst > 2:
        why = f"MAVLink already runs on three ports before {tag} ({', '.join(uarts)})"
        return None, [Row(name, _labelled(prot, {1: "MAVLink"}), "1 (MAVLink)", why, Status.FAIL)]
    why = f"MAVLink instance {inst} on {ctx.fc_port} (PX4 after 1.16 numbers them in port order)"
    if prot == 1:
        return inst, [Row(name, "1 (MAVLink)", "1 (MAVLink)", why, Status.OK)]
    return inst, [
        Row(
            name,
            str(prot),
            "1 (MAVLink)",
            f"{ctx.fc_port} runs another protocol; {why}",
            Status.FAIL,
            (Target(name, 1, True, True),),
        )
    ]


def _partner_row(params: Mapping[str, Param], ctx: LinkContext, inst: int, mode: int | None) -> Row:
    """Who speaks first on the companion's UDP link. PX4 on a flight controller (NuttX) sends
    on a UDP instance only to the address of the first packet it receives (its partner, kept
    until it reboots); before that it broadcasts, on MAV_n_REMOTE_PRT, only with
    MAV_n_BROADCAST = 1 and never in Onboard mode (mavlink_main.cpp). PX4 SITL (POSIX) sends
    to 127.0.0.1:MAV_n_REMOTE_PRT from the start, as the SITL stub does."""
    name = f"MAV_{inst}_BROADCAST"
    b = _int_value(params, name, 0, 2)
    value = _labelled(b, BROADCAST) if b is not None else "missing"
    udp_prt = _int_value(params, f"MAV_{inst}_UDP_PRT", 1, 65535)
    udpout = f"udpout:<autopilot IP>:{udp_prt if udp_prt is not None else '<MAV_n_UDP_PRT>'}"
    if ctx.link_host.startswith(LOOPBACK_HOSTS):
        return Row(
            name,
            value,
            "any (same host)",
            "the service and PX4 share a host (SITL): PX4's POSIX build sends to "
            f"127.0.0.1:MAV_{inst}_REMOTE_PRT from the start, so either side may speak first",
            Status.OK,
        )
    if ctx.link_kind == "udpout":
        return Row(
            name,
            value,
            "any (the service speaks first)",
            "the service sends first and PX4 takes it as its partner (address and port) until "
            "it reboots: the service sends from an ephemeral port, so after a restart of the "
            "service PX4 streams to the old one (no ATTITUDE, DISTANCE_SENSOR, TIMESYNC): "
            "reboot the autopilot after restarting the service",
            Status.WARN,
        )
    broadcasts = b == 1 and mode is not None and mode != 2
    if broadcasts and ctx.link_host in ("0.0.0.0", ""):
        return Row(
            name,
            value,
            "1 (always), not in Onboard mode",
            f"PX4 broadcasts on MAV_{inst}_REMOTE_PRT until a partner speaks; the service "
            f"listens on {ctx.link_host}:{ctx.link_port}, answers, and becomes the partner",
            Status.OK,
        )
    target: tuple[Target, ...] = ()
    if mode in (8, 11) and b == 0 and ctx.link_host in ("0.0.0.0", ""):
        target = (Target(name, 1, True, needs_reboot(name)),)
    return Row(
        name,
        value,
        f"the service to send first ({udpout})",
        "PX4 on the flight controller sends on this instance only to the address of the first "
        "packet it receives, and broadcasts only with MAV_n_BROADCAST = 1 and never in "
        f"Onboard mode: the listening service (udpin:{ctx.link_host}:{ctx.link_port}) and PX4 "
        f"wait for each other. Make the service speak first: service.mavlink_url = {udpout}"
        + (" (or broadcast: 1 here, the service on 0.0.0.0)" if target else ""),
        Status.FAIL,
        target,
    )


def _link_rows(params: Mapping[str, Param], ctx: LinkContext) -> list[Row]:
    """The MAVLink instance on the companion's port: enabled there, a mode that time-syncs,
    the same rate, UDP ports and who speaks first."""
    inst, rows = _port_rows(params, ctx)
    if inst is None:
        return rows
    mode = _int_value(params, f"MAV_{inst}_MODE", 0, 13)
    rows.append(_int_row(params, f"MAV_{inst}_MODE", 0, 13, _judge_mode, MAV_MODE))
    if ctx.fc_port == "ETHERNET":
        rows += _udp_rows(params, ctx, inst, mode)
    else:
        rows.append(_baud_row(params, ctx))
    rows += _other_link_rows(params, inst)
    return rows


def _judge_mode(v: int) -> Judgement:
    """MAV_n_MODE: a mode that streams TIMESYNC, so PX4 moves our stamps into its clock."""
    need = "2 (Onboard)"
    if v == 2:
        why = "Onboard: companion-rate streams, and TIMESYNC at 10 Hz, so PX4 moves our "
        why += "stamps into its clock"
        return Judgement(Status.OK, need, why)
    if v == 8:
        why = "External Vision: TIMESYNC at 10 Hz and the streams a VIO needs"
        return Judgement(Status.OK, need, why)
    if v == 11:
        why = "Onboard Low Bandwidth: TIMESYNC at 10 Hz with fewer streams (right on a slow "
        why += "serial link)"
        return Judgement(Status.OK, need, why)
    if v in TIMESYNC_MODES:
        why = f"{MAV_MODE.get(v, v)} mode time-syncs, but streams for another peer"
        return Judgement(Status.WARN, need, why, 2)
    return Judgement(
        Status.WARN,
        need,
        f"{MAV_MODE.get(v, v)} mode streams no TIMESYNC: PX4 still fuses our messages but "
        "stamps them at arrival (latency not compensated), at ground-station stream rates",
        2,
    )


def _udp_rows(
    params: Mapping[str, Param], ctx: LinkContext, inst: int, mode: int | None
) -> list[Row]:
    """Ethernet over UDP: PX4's port matches the service's, and who speaks first."""
    if ctx.link_kind not in ("udpin", "udpout"):
        return []
    key = "REMOTE_PRT" if ctx.link_kind == "udpin" else "UDP_PRT"
    what = "sends to" if ctx.link_kind == "udpin" else "listens on"

    def port_judge(v: int) -> Judgement:
        why = f"PX4 {what} this UDP port; the service uses {ctx.link_port}"
        status = Status.OK if v == ctx.link_port else Status.FAIL
        return Judgement(status, str(ctx.link_port), why, ctx.link_port)

    return [
        _int_row(params, f"MAV_{inst}_{key}", 1, 65535, port_judge),
        _partner_row(params, ctx, inst, mode),
    ]


def _baud_row(params: Mapping[str, Param], ctx: LinkContext) -> Row:
    """A serial port: SER_TELn_BAUD at the service's rate, and fast enough for our streams."""
    tel = ctx.fc_port[-1]
    serial = ctx.link_kind == "serial"

    def baud_judge(v: int) -> Judgement:
        want = ctx.link_port if serial else 921600
        why = "both ends of the wire at the same rate"
        if v == 0:
            return Judgement(
                Status.WARN,
                str(want),
                f"0 = Auto: PX4 chooses the rate; set the service's {want} so that both ends "
                "surely match",
                want,
            )
        if serial and v != want:
            return Judgement(Status.FAIL, str(want), f"{why}; the service uses {want}", want)
        if v < MIN_SERIAL_BAUD:
            return Judgement(
                Status.WARN,
                f">= {MIN_SERIAL_BAUD}",
                "too slow for 30 Hz ODOMETRY plus TIMESYNC and PX4's onboard streams",
            )
        return Judgement(Status.OK, str(want), why)

    return _int_row(params, f"SER_TEL{tel}_BAUD", 0, 3_000_000, baud_judge, {0: "Auto"})


def _other_link_rows(params: Mapping[str, Param], inst: int) -> list[Row]:
    """The other MAVLink instances with a port (MAV_n_CONFIG): context, not ours."""
    rows = []
    for i in range(3):
        c = _int_value(params, f"MAV_{i}_CONFIG", 0, 1000)
        if i != inst and c:
            other = _int_value(params, f"MAV_{i}_MODE", 0, 13)
            rows.append(
                Row(
                    f"MAV_{i}_CONFIG",
                    _labelled(c, SERIAL_PORT),
                    "-",
                    f"another MAVLink link ({MAV_MODE.get(other or 0, other)} mode): not ours",
                    Status.INFO,
                )
            )
    return rows


def targets_of(rows: list[Row]) -> list[Target]:
    """Every value configure should write (FAIL and WARN rows), once per parameter."""
    out: dict[str, Target] = {}
    for r in rows:
        if r.status in (Status.FAIL, Status.WARN):
            for t in r.targets:
                out.setdefault(t.name, t)
    return list(out.values())
