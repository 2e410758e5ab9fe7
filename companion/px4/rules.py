"""The PX4 parameters that decide whether EKF2 fuses our estimate: what we need and why.

One row per parameter: its value, what we need, why (in PX4's terms), a status, and the
value(s) ``configure`` would write. FAIL: EKF2 will not fuse our estimate (or the link will not
work) as it is. WARN: it works, but not as well as it should, or not as DESIGN.md section 6
recommends. OK: as needed. INFO: context only.

The rules follow PX4 1.14+ (EKF2_EV_CTRL / EKF2_HGT_REF, which replaced EKF2_AID_MASK /
EKF2_HGT_MODE) and DESIGN.md section 6: VISION_POSITION_ESTIMATE is NED and needs a
north-aligned heading; ODOMETRY (LOCAL_FRD / BODY_FRD, VISION) works at any heading; we stamp at
exposure and PX4 converts through TIMESYNC, so EKF2_EV_DELAY stays 0; our covariance is real,
so EKF2 should use it (EKF2_EV_NOISE_MD 0) with the noise parameters as floors.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from companion.px4.encoding import float_encoded_int, int_encoded_float

EV_HPOS, EV_VPOS, EV_VEL, EV_YAW = 1, 2, 4, 8
PORT_CODES = {"TELEM1": 101, "TELEM2": 102, "TELEM3": 103, "TELEM4": 104, "ETHERNET": 1000}
MIN_SERIAL_BAUD = 460800  # ODOMETRY at 30 Hz (~8 kB/s) + TIMESYNC + PX4's onboard streams

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
RNG_CTRL = {0: "off", 1: "conditional", 2: "enabled"}
NOISE_MD = {0: "from the message", 1: "from the parameters"}
MAG_TYPE = {0: "automatic", 1: "magnetic heading", 5: "none", 6: "init only"}
REBOOT_PARAMS = frozenset({"EKF2_HGT_REF", "EKF2_EV_DELAY", "EKF2_DELAY_MAX"})
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


def _ekf2_rows(params: Mapping[str, Param], ctx: LinkContext) -> list[Row]:
    odometry = ctx.output in ("odometry", "both")
    vpe = ctx.output in ("vision_position_estimate", "both")
    hgt_ref = _int_value(params, "EKF2_HGT_REF", 0, 3)
    ev_ctrl = _int_value(params, "EKF2_EV_CTRL", 0, 15)
    rng_ctrl = _int_value(params, "EKF2_RNG_CTRL", 0, 2)
    message = {"odometry": "ODOMETRY", "both": "both messages"}.get(
        ctx.output, "VISION_POSITION_ESTIMATE"
    )

    def ev_ctrl_judge(v: int) -> Judgement:
        required = EV_HPOS | (EV_VPOS if hgt_ref == 3 else 0)
        want = (EV_HPOS | EV_VPOS | EV_YAW) | (EV_VEL if odometry else 0)
        need = f"{want} ({ev_bits(want)})"
        if v & required != required:
            missing = ev_words(required & ~v)
            why = f"EKF2 ignores our {missing}: bit 0 enables horizontal position fusion"
            if required & EV_VPOS:
                why += ", bit 1 height (EKF2_HGT_REF = vision needs it)"
            return Judgement(Status.FAIL, need, why, v | want)
        if v & want != want:
            notes = {
                EV_VPOS: "height (our z is metric, from the rangefinders)",
                EV_VEL: "velocity (ODOMETRY carries it; it steadies the position)",
                EV_YAW: "yaw (without a magnetometer EKF2's heading comes from us)",
            }
            absent = [n for b, n in notes.items() if want & ~v & b]
            return Judgement(
                Status.WARN, need, "horizontal position fused; not " + ", ".join(absent), v | want
            )
        return Judgement(Status.OK, need, f"EKF2 fuses our {ev_words(v)} ({message})")

    def hgt_ref_judge(v: int) -> Judgement:
        need = "3 (vision)"
        if v == 3:
            return Judgement(Status.OK, need, "our metric height (range-aided VO) is the reference")
        if v == 2:
            if rng_ctrl == 0:
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
                "baro drifts and sees rotor wash; our vision height is steadier",
                3,
            )
        if v == 1 and ctx.gps_seen:
            return Judgement(
                Status.WARN, need, "GNSS height: metres of noise, fine only outdoors", 3
            )
        return Judgement(
            Status.FAIL, need, "GNSS height reference without a GNSS receiver (none seen)", 3
        )

    def qmin_judge(v: int) -> Judgement:
        if vpe:
            why = "VISION_POSITION_ESTIMATE has no quality field: PX4 stores 0, so any minimum "
            why += "rejects every sample"
            if v > 0:
                return Judgement(Status.FAIL, "0", why, 0)
            return Judgement(Status.OK, "0", why)
        if v > 50:
            why = "our ODOMETRY quality falls while the scale converges: EKF2 would drop vision"
            return Judgement(Status.WARN, "<= 50", why, 0)
        return Judgement(Status.OK, "<= 50", "EKF2 drops samples whose quality is below it")

    def rng_judge(v: int) -> Judgement:
        if hgt_ref == 2 and v != 2:
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

    def gps_judge(v: int) -> Judgement:
        if ctx.gps_seen is True:
            return Judgement(Status.OK, "any", "GNSS present: EKF2 fuses vision relative to it")
        if ctx.gps_seen is False and v != 0:
            return Judgement(
                Status.WARN,
                "0 (no GNSS)",
                "no GNSS receiver seen: 0 makes EKF2 stop waiting for one (vision alone)",
                0,
            )
        return Judgement(Status.OK, "0 without GNSS", "GNSS fusion off, or present")

    def delay_judge(v: float) -> Judgement:
        why = "we stamp at exposure and PX4 moves the stamp through TIMESYNC: a delay counts twice"
        if v <= 5.0:
            return Judgement(Status.OK, "0 ms", why)
        return Judgement(Status.WARN if v <= 20.0 else Status.FAIL, "0 ms", why, 0.0)

    def noise_md_judge(v: int) -> Judgement:
        why = "0: EKF2 uses the covariance we send, the EKF2_EV*_NOISE values as floors"
        if v == 0:
            return Judgement(Status.OK, "0 (from the message)", why)
        return Judgement(
            Status.WARN, "0 (from the message)", "our covariance is ignored; " + why, 0
        )

    def floor_judge(
        lo: float, hi: float, what: str, default: float
    ) -> Callable[[float], Judgement]:
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

    def gate_judge(v: float) -> Judgement:
        why = "innovation gate [SD] on our position"
        if v < 3.0:
            return Judgement(
                Status.WARN, "3..10", f"{why}: rejects us after a fast turn or a VO re-init", 5.0
            )
        if v > 10.0:
            return Judgement(Status.WARN, "3..10", f"{why}: lets outliers in", 5.0)
        return Judgement(Status.OK, "3..10", why)

    rows = [
        _int_row(params, "EKF2_EV_CTRL", 0, 15, ev_ctrl_judge),
        _int_row(params, "EKF2_HGT_REF", 0, 3, hgt_ref_judge, HGT_REF),
        _float_row(params, "EKF2_EV_DELAY", "ms", delay_judge),
        _int_row(params, "EKF2_EV_NOISE_MD", 0, 1, noise_md_judge, NOISE_MD),
        _float_row(params, "EKF2_EVP_NOISE", "m", floor_judge(0.01, 0.3, "position", 0.1)),
        _float_row(params, "EKF2_EVA_NOISE", "rad", floor_judge(0.05, 0.3, "angle", 0.1)),
        _int_row(params, "EKF2_EV_QMIN", 0, 100, qmin_judge),
        _float_row(params, "EKF2_EVP_GATE", "SD", gate_judge),
        _int_row(params, "EKF2_RNG_CTRL", 0, 2, rng_judge, RNG_CTRL),
        _int_row(params, "EKF2_GPS_CTRL", 0, 15, gps_judge),
    ]
    if vpe:

        def mag_judge(v: int) -> Judgement:
            no_mag = v == 5 or _int_value(params, "SYS_HAS_MAG", 0, 1) == 0
            yaw = ev_ctrl is not None and bool(ev_ctrl & EV_YAW)
            why = "VISION_POSITION_ESTIMATE is NED: EKF2 fuses it only with a north-aligned heading"
            if no_mag and not yaw:
                return Judgement(
                    Status.FAIL,
                    "a magnetometer, or EV yaw",
                    f"{why}, and it has neither a magnetometer nor our yaw (EKF2_EV_CTRL bit 3)",
                )
            return Judgement(Status.OK, "a heading source", why)

        rows.append(_int_row(params, "EKF2_MAG_TYPE", 0, 6, mag_judge, MAG_TYPE))
    return rows


def _link_rows(params: Mapping[str, Param], ctx: LinkContext) -> list[Row]:
    """The MAVLink instance on the companion's port: enabled there, Onboard, same rate/ports."""
    code = PORT_CODES[ctx.fc_port]
    configs = {i: _int_value(params, f"MAV_{i}_CONFIG", 0, 1000) for i in range(3)}
    found = [i for i, c in configs.items() if c == code]
    rows: list[Row] = []
    if found:
        inst = found[0]
        rows.append(
            Row(
                f"MAV_{inst}_CONFIG",
                _labelled(code, SERIAL_PORT),
                _labelled(code, SERIAL_PORT),
                f"MAVLink instance {inst} runs on {ctx.fc_port}, where the companion is wired",
                Status.OK,
            )
        )
    else:
        free = [i for i in (1, 2, 0) if configs.get(i) == 0]
        if not free:
            return [
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
        rows.append(
            Row(
                name,
                _labelled(current, SERIAL_PORT) if current is not None else "missing",
                _labelled(code, SERIAL_PORT),
                f"no MAVLink instance runs on {ctx.fc_port}, where the companion is wired "
                f"(instance {inst} is free)",
                Status.FAIL,
                (Target(name, code, True, True),),
            )
        )

    def mode_judge(v: int) -> Judgement:
        why = "Onboard: PX4 streams at companion rates and time-syncs this link"
        if v == 2:
            return Judgement(Status.OK, "2 (Onboard)", why)
        if v == 8:
            return Judgement(
                Status.WARN, "2 (Onboard)", "External Vision mode streams less; " + why, 2
            )
        return Judgement(Status.FAIL, "2 (Onboard)", why, 2)

    rows.append(_int_row(params, f"MAV_{inst}_MODE", 0, 13, mode_judge, MAV_MODE))
    if ctx.fc_port == "ETHERNET":
        if ctx.link_kind in ("udpin", "udpout"):
            key = "REMOTE_PRT" if ctx.link_kind == "udpin" else "UDP_PRT"
            what = "sends to" if ctx.link_kind == "udpin" else "listens on"

            def port_judge(v: int) -> Judgement:
                why = f"PX4 {what} this UDP port; the service uses {ctx.link_port}"
                status = Status.OK if v == ctx.link_port else Status.FAIL
                return Judgement(status, str(ctx.link_port), why, ctx.link_port)

            rows.append(_int_row(params, f"MAV_{inst}_{key}", 1, 65535, port_judge))
    else:
        tel = ctx.fc_port[-1]
        serial = ctx.link_kind == "serial"

        def baud_judge(v: int) -> Judgement:
            want = ctx.link_port if serial else 921600
            why = "both ends of the wire at the same rate"
            if serial and v != want:
                return Judgement(Status.FAIL, str(want), f"{why}; the service uses {want}", want)
            if v < MIN_SERIAL_BAUD:
                return Judgement(
                    Status.WARN,
                    f">= {MIN_SERIAL_BAUD}",
                    "too slow for 30 Hz ODOMETRY plus TIMESYNC and PX4's onboard streams",
                )
            return Judgement(Status.OK, str(want), why)

        rows.append(_int_row(params, f"SER_TEL{tel}_BAUD", 0, 3_000_000, baud_judge))
    for i, c in configs.items():
        if i != inst and c:
            mode = _int_value(params, f"MAV_{i}_MODE", 0, 13)
            rows.append(
                Row(
                    f"MAV_{i}_CONFIG",
                    _labelled(c, SERIAL_PORT),
                    "-",
                    f"another MAVLink link ({MAV_MODE.get(mode or 0, mode)} mode): not ours",
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
