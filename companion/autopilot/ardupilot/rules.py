"""The ArduPilot parameters that decide whether EKF3 fuses our estimate: what we need and why.

The same table as PX4's (:mod:`companion.autopilot.params`: one row per parameter, FAIL / WARN
/ OK / INFO, the values ``configure`` would write), in ArduPilot's terms (ArduCopter 4.x,
AP_VisualOdom and EKF3's source sets), as the real ArduCopter SITL showed them
(docs/decisions.md, "ArduPilot's dialect"):

- VISO_TYPE = 1 (MAVLink): else ArduPilot drops VISION_POSITION_ESTIMATE and ODOMETRY;
  a reboot applies it;
- VISO_POS_X/Y/Z = 0 and VISO_ORIENT = 0: our estimate is the body origin's pose in the body
  frame already (the camera's mount is removed on our side), ArduPilot would move and rotate it
  again; VISO_SCALE = 1 (our position is metric);
- VISO_DELAY_MS: ArduPilot maps our ``time_usec`` into its clock by its jitter correction (the
  fastest sample is taken as zero lag) and EKF3 moves it back by VISO_DELAY_MS: it should be our
  exposure-to-send latency (the service's status says it);
- VISO_QUAL_MIN: VISION_POSITION_ESTIMATE has no quality field and ArduPilot reads it as 0
  (unknown), so anything above 0 drops it; ODOMETRY's quality is ours (1..100);
- EK3_SRC1_POSXY / POSZ / YAW = 6 (ExternalNav); VELXY / VELZ = 6 with ODOMETRY (it carries the
  velocity), 0 with VISION_POSITION_ESTIMATE (none comes); GPS (3) in any of them beside our
  position mixes two frames in one filter;
- GPS1_TYPE: 0 where no GPS is fitted (ArduPilot waits for the one it is told of), and then the
  EKF needs an origin (SET_GPS_GLOBAL_ORIGIN: the service's [service.ardupilot] set_origin);
- RNGFNDn_TYPE / ORIENT: a sensor the service takes from the autopilot's DISTANCE_SENSOR (id =
  n - 1, ArduPilot's instance) must be there and point down (25);
- SYSID_THISMAV = the service's system_id (it ignores every other system); ARMING_CHECK != 0.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial

from companion.autopilot.params import (
    Judgement,
    Param,
    Row,
    Status,
    Target,
    judge_either,
    labelled,
)

EXTNAV, GPS, BARO, RANGE, COMPASS, NONE = 6, 3, 1, 2, 1, 0
SOURCES = {
    0: "None",
    1: "Baro",
    2: "RangeFinder",
    3: "GPS",
    4: "Beacon",
    5: "OpticalFlow",
    6: "ExternalNav",
    7: "WheelEncoder",
}
YAW_SOURCES = {
    0: "None",
    1: "Compass",
    2: "GSF",
    3: "GPS",
    6: "ExternalNav",
    8: "GPS with compass fallback",
}
VISO_TYPES = {0: "None", 1: "MAVLink", 2: "IntelT265", 3: "VOXL"}
GPS_TYPES = {0: "None", 1: "Auto", 2: "uBlox"}
ORIENT_DOWN = 25
REBOOT_PARAMS = frozenset({"VISO_TYPE", "GPS1_TYPE", "GPS_TYPE"})
REBOOT_PREFIXES = ("RNGFND", "SERIAL")


@dataclass(frozen=True, slots=True)
class ArduPilotContext:
    """What the rules need to know about our side (and what the watch saw)."""

    output: str = "odometry"  # service.output
    system_id: int = 1  # service.system_id
    set_origin: bool = False  # [service.ardupilot] set_origin
    autopilot_sensor_ids: tuple[int, ...] = ()  # rangefinders taken from DISTANCE_SENSOR
    latency_ms: float | None = None  # the service's exposure-to-send latency (p50), if running
    gps_seen: bool | None = None  # a GPS with a fix type >= 1 (None: not watched)
    origin_seen: bool | None = None  # the EKF holds an origin (None: not watched)
    no_gnss: bool = False  # configure --no-gnss: also turn the GPS off (GPS1_TYPE = 0)
    declination_deg: float | None = None  # [service.ardupilot] declination_deg, when set
    with_gps: bool = False  # --with-gps: GPS (set 1) and our vision (set 2) together
    odometry: bool = field(init=False)  # we send ODOMETRY
    vpe: bool = field(init=False)  # we send VISION_POSITION_ESTIMATE

    def __post_init__(self) -> None:
        object.__setattr__(self, "odometry", self.output in ("odometry", "both"))
        object.__setattr__(self, "vpe", self.output in ("vision_position_estimate", "both"))


def needs_reboot(name: str) -> bool:
    """Whether ArduPilot applies a new value of ``name`` only after a reboot."""
    return name in REBOOT_PARAMS or name.startswith(REBOOT_PREFIXES)


def value_of(params: Mapping[str, Param], name: str) -> float | None:
    p = params.get(name)
    return float(p.value) if p is not None else None


def param_row(
    params: Mapping[str, Param],
    name: str,
    judge: Callable[[float], Judgement],
    labels: Mapping[int, str] | None = None,
    unit: str = "",
) -> Row:
    """A parameter's row: missing, or judged (ArduPilot carries every value as a float: an
    integer parameter is the float of the integer, never its bytes)."""
    p = params.get(name)
    if p is None:
        return Row(
            name,
            "missing",
            "present",
            "this firmware has no such parameter (ArduCopter 4.x has it; a feature left out "
            "of the build, or VISO_TYPE / RNGFND off hides its group until a reboot)",
            Status.FAIL,
        )
    v = float(p.value)
    j = judge(v)
    shown = labelled(int(v), labels) if p.is_int and labels else (f"{v:g} {unit}".strip())
    targets: tuple[Target, ...] = ()
    if j.status in (Status.FAIL, Status.WARN) and j.target is not None and j.target != v:
        value: int | float = int(j.target) if p.is_int else float(j.target)
        targets = (Target(name, value, p.is_int, needs_reboot(name)),)
    return Row(name, shown, j.need, j.why, j.status, targets)


def evaluate(params: Mapping[str, Param], ctx: ArduPilotContext) -> list[Row]:
    """Every row: visual odometry, EKF3's sources, GPS and origin, rangefinders, the link."""
    return [
        *_viso_rows(params, ctx),
        *_source_rows(params, ctx),
        *_gps_rows(params, ctx),
        *_rangefinder_rows(params, ctx),
        # MAV_SYSID since ArduPilot 4.7 (SYSID_THISMAV before)
        param_row(
            params,
            "MAV_SYSID" if "MAV_SYSID" in params else "SYSID_THISMAV",
            partial(_judge_sysid, ctx),
        ),
        param_row(params, "ARMING_CHECK", _judge_arming),
    ]


# ---------------------------------------------------------------- visual odometry
def _viso_rows(params: Mapping[str, Param], ctx: ArduPilotContext) -> list[Row]:
    rows = [param_row(params, "VISO_TYPE", _judge_viso_type, VISO_TYPES)]
    if value_of(params, "VISO_TYPE") in (None, 0.0) and "VISO_POS_X" not in params:
        return rows  # the group is hidden until VISO_TYPE is set and the autopilot rebooted
    for axis in "XYZ":
        rows.append(param_row(params, f"VISO_POS_{axis}", _judge_offset, unit="m"))
    rows += [
        param_row(params, "VISO_ORIENT", _judge_orient),
        param_row(params, "VISO_SCALE", _judge_scale),
        param_row(params, "VISO_DELAY_MS", partial(_judge_delay, ctx), unit="ms"),
        param_row(params, "VISO_QUAL_MIN", partial(_judge_qual_min, ctx)),
        param_row(params, "VISO_POS_M_NSE", _noise_judge(0.05, 0.5, "position", 0.1), unit="m"),
        param_row(params, "VISO_YAW_M_NSE", _noise_judge(0.05, 0.5, "yaw", 0.1), unit="rad"),
    ]
    return rows


def _judge_viso_type(v: float) -> Judgement:
    if v == 0:
        status, why = (
            Status.FAIL,
            "visual odometry is off: ArduPilot drops VISION_POSITION_ESTIMATE and ODOMETRY "
            "(and the VISO_* parameters appear only after a reboot)",
        )
    else:
        status, why = (
            Status.WARN,
            f"{VISO_TYPES.get(int(v), int(v))}: a camera backend that re-aligns our yaw and "
            "position to its own conventions; the companion is a plain MAVLink source",
        )
    ok = "AP_VisualOdom takes our VISION_POSITION_ESTIMATE / ODOMETRY"
    return judge_either(v == 1, "1 (MAVLink)", ok, why, status, 1)


def _judge_offset(v: float) -> Judgement:
    why = "our estimate is the body origin's (the camera's mount is removed on our side): "
    moved = f"ArduPilot would move it by another {v:g} m, an error that turns with the attitude"
    return judge_either(
        abs(v) <= 0.01, "0", why + "no offset to correct", why + moved, Status.WARN, 0.0
    )


def _judge_orient(v: float) -> Judgement:
    return judge_either(
        v == 0,
        "0 (forward)",
        "our pose is in the body frame (FRD) already",
        f"ArduPilot rotates our pose by orientation {int(v)}: it is the body's (FRD) already",
        Status.FAIL,
        0,
    )


def _judge_scale(v: float) -> Judgement:
    why_not = f"ArduPilot multiplies our metric position by {v:g}"
    ok = "our position is metric (the scale is ours)"
    return judge_either(abs(v - 1.0) < 1e-6, "1", ok, why_not, Status.FAIL, 1.0)


def _judge_delay(ctx: ArduPilotContext, v: float) -> Judgement:
    why = (
        "ArduPilot maps our time_usec into its clock taking the fastest sample as zero lag; "
        "EKF3 then moves every sample back by this: our exposure-to-send latency"
    )
    lat = ctx.latency_ms
    if lat is None:
        status = Status.OK if 0 <= v <= 250 else Status.FAIL
        return Judgement(
            status, "the service's latency (0..250)", why + " (the service is not running: unknown)"
        )
    want = int(round(min(250.0, max(0.0, lat))))
    if abs(v - lat) <= max(10.0, 0.3 * lat):
        return Judgement(Status.OK, f"~{want}", f"{why}; the service measures {lat:.0f} ms")
    return Judgement(
        Status.WARN,
        f"~{want}",
        f"{why}; the service measures {lat:.0f} ms, EKF3 would fuse our samples "
        f"{abs(v - lat):.0f} ms {'too early' if v < lat else 'too late'}",
        want,
    )


def _judge_qual_min(ctx: ArduPilotContext, v: float) -> Judgement:
    if ctx.vpe and v > 0:
        return Judgement(
            Status.FAIL,
            "0",
            "VISION_POSITION_ESTIMATE has no quality: ArduPilot reads it as 0 (unknown) and "
            f"drops every sample below VISO_QUAL_MIN = {v:g}",
            0,
        )
    if v > 50:
        return Judgement(
            Status.WARN,
            "<= 50",
            f"our ODOMETRY quality (1..100, from the scale's relative sigma) drops below {v:g} "
            "while the scale converges: ArduPilot would drop those samples",
            0,
        )
    return Judgement(
        Status.OK,
        "<= 50",
        "ArduPilot fuses samples with quality >= this (ours: 1..100 on ODOMETRY, 0 = unknown on "
        "VISION_POSITION_ESTIMATE)",
    )


def _noise_judge(lo: float, hi: float, what: str, target: float) -> Callable[[float], Judgement]:
    def judge(v: float) -> Judgement:
        why = f"EKF3's floor under our {what} noise (our covariance is used above it)"
        if lo <= v <= hi:
            return Judgement(Status.OK, f"{lo:g}..{hi:g}", why)
        side = "below" if v < lo else "above"
        return Judgement(Status.WARN, f"{lo:g}..{hi:g}", f"{why}: {side} the useful range", target)

    return judge


# ---------------------------------------------------------------- EKF3 sources
def _source_rows(params: Mapping[str, Param], ctx: ArduPilotContext) -> list[Row]:
    return [
        param_row(
            params,
            "EK3_SRC1_POSXY",
            partial(_judge_pos_source, ctx, "horizontal position"),
            SOURCES,
        ),
        param_row(
            params,
            "EK3_SRC1_VELXY",
            partial(_judge_vel_source, ctx, "horizontal velocity"),
            SOURCES,
        ),
        param_row(params, "EK3_SRC1_POSZ", partial(_judge_posz_source, ctx), SOURCES),
        param_row(
            params, "EK3_SRC1_VELZ", partial(_judge_vel_source, ctx, "vertical velocity"), SOURCES
        ),
        param_row(params, "EK3_SRC1_YAW", _judge_yaw_source, YAW_SOURCES),
        *_declination_rows(params, ctx),
    ]


def _declination_rows(params: Mapping[str, Param], ctx: ArduPilotContext) -> list[Row]:
    """COMPASS_DEC / COMPASS_AUTODEC, when EKF3 takes its heading from the compass.

    Our frame's heading is the autopilot's when our VO starts, so with a compass heading EKF3's
    north is true north only if the declination is right. ArduPilot looks it up from a GPS
    position (COMPASS_AUTODEC); without GPS it stays COMPASS_DEC [rad], and every error in it
    turns the whole flight (7 deg = 2.4 m at 20 m from home)."""
    if value_of(params, "EK3_SRC1_YAW") != COMPASS:
        return []
    rows = [param_row(params, "COMPASS_DEC", partial(_judge_declination, ctx), unit="rad")]
    if ctx.declination_deg is not None:
        rows.append(param_row(params, "COMPASS_AUTODEC", _judge_autodec))
    return rows


DECLINATION_TOL_RAD = 0.005  # 0.3 deg: 0.1 m at 20 m from home


def _judge_declination(ctx: ArduPilotContext, v: float) -> Judgement:
    if ctx.declination_deg is None:
        if v == 0.0:
            return Judgement(
                Status.WARN,
                "the site's declination",
                "0: without GPS (no automatic look-up) EKF3's north is magnetic north; set "
                "[service.ardupilot] set_declination and declination_deg to the site's and "
                "`autopilot configure` writes it",
            )
        return Judgement(
            Status.INFO,
            "the site's declination",
            f"{math.degrees(v):.2f} deg, set by hand ([service.ardupilot] declination_deg "
            "would let the check compare it)",
        )
    want = math.radians(ctx.declination_deg)
    need = f"{want:.4f} ({ctx.declination_deg:g} deg)"
    if abs(v - want) <= DECLINATION_TOL_RAD:
        return Judgement(Status.OK, need, "the site's declination: EKF3's north is true north")
    return Judgement(
        Status.FAIL,
        need,
        f"{math.degrees(v):.2f} deg, not the site's {ctx.declination_deg:g} deg: EKF3's frame "
        f"turns by {math.degrees(v) - ctx.declination_deg:+.2f} deg from true north",
        want,
    )


def _judge_autodec(v: float) -> Judgement:
    return judge_either(
        v == 0.0,
        "0",
        "the declination is ours (COMPASS_DEC)",
        "automatic declination: a GPS fix would overwrite the site's COMPASS_DEC",
        Status.WARN,
        0.0,
    )


def _judge_pos_source(ctx: ArduPilotContext, what: str, v: float) -> Judgement:
    need = "6 (ExternalNav)"
    if v == EXTNAV:
        return Judgement(Status.OK, need, f"EKF3 takes its {what} from us")
    why = f"EKF3 takes its {what} from {SOURCES.get(int(v), int(v))}, not from us"
    if v == GPS:
        why += ": GPS and vision both, in two frames (ours starts where the VO started)"
    return Judgement(Status.FAIL, need, why, EXTNAV)


def _judge_vel_source(ctx: ArduPilotContext, what: str, v: float) -> Judgement:
    if v == GPS:
        return Judgement(
            Status.FAIL,
            "6 (ExternalNav)" if ctx.odometry else "0 (None)",
            f"GPS {what} beside our position: GPS and vision both sources, two frames in one "
            "filter (ours is the VO's, turned and shifted from GPS's)",
            EXTNAV if ctx.odometry else NONE,
        )
    if ctx.odometry:
        if v == EXTNAV:
            return Judgement(Status.OK, "6 (ExternalNav)", f"our ODOMETRY carries the {what}")
        if v == NONE:
            return Judgement(
                Status.WARN,
                "6 (ExternalNav)",
                f"our ODOMETRY carries the {what}; EKF3 does not use it",
                EXTNAV,
            )
        return Judgement(
            Status.WARN,
            "6 (ExternalNav)",
            f"{what} from {SOURCES.get(int(v), int(v))} beside our position",
            EXTNAV,
        )
    if v == EXTNAV:
        return Judgement(
            Status.FAIL,
            "0 (None)",
            f"VISION_POSITION_ESTIMATE carries no velocity: EKF3 waits for a {what} that never "
            "comes",
            NONE,
        )
    return Judgement(Status.OK, "0 (None)", "VISION_POSITION_ESTIMATE carries no velocity")


def _judge_posz_source(ctx: ArduPilotContext, v: float) -> Judgement:
    if v == EXTNAV:
        return Judgement(Status.OK, "6 (ExternalNav)", "EKF3 takes its height from us")
    if v in (BARO, RANGE):
        return Judgement(
            Status.OK,
            "6 (ExternalNav) or 1 (Baro)",
            f"height from {SOURCES[int(v)]}: works; ours is the VO's, drift-free with the scale",
        )
    return _judge_pos_source(ctx, "height", v)


def _judge_yaw_source(v: float) -> Judgement:
    if v == EXTNAV:
        return Judgement(
            Status.OK,
            "6 (ExternalNav)",
            "EKF3 takes its heading from our attitude; ours is the autopilot's when our VO "
            "started, which before our data has no heading reference: EKF3's north is then the "
            "vehicle's first heading (local flight is unaffected; global positions turn with it)",
        )
    if v == COMPASS:
        return Judgement(
            Status.OK,
            "6 (ExternalNav) or 1 (Compass)",
            "heading from the compass (+ COMPASS_DEC): our frame's heading is the autopilot's "
            "when our VO starts, so EKF3's north is true north (a compass disturbed by the "
            "site, indoors or near steel, is better left out: 6)",
        )
    return Judgement(
        Status.FAIL,
        "6 (ExternalNav)",
        f"heading from {YAW_SOURCES.get(int(v), int(v))}: without GPS EKF3 never aligns it",
        EXTNAV,
    )


# ---------------------------------------------------------------- GPS and the origin
def _gps_rows(params: Mapping[str, Param], ctx: ArduPilotContext) -> list[Row]:
    name = "GPS1_TYPE" if "GPS1_TYPE" in params else "GPS_TYPE"
    rows = [param_row(params, name, partial(_judge_gps_type, ctx), GPS_TYPES)]
    gps_on = (value_of(params, name) or 0) != 0
    uses_gps = any(
        value_of(params, f"EK3_SRC1_{s}") == GPS for s in ("POSXY", "VELXY", "POSZ", "VELZ")
    )
    rows.append(_origin_row(ctx, gps_on and uses_gps))
    return rows


def _judge_gps_type(ctx: ArduPilotContext, v: float) -> Judgement:
    if v == 0:
        return Judgement(
            Status.OK,
            "0 (None) without a GPS",
            "no GPS: EKF3 needs an EKF origin from the companion (SET_GPS_GLOBAL_ORIGIN)",
        )
    if ctx.gps_seen is False or ctx.no_gnss:
        return Judgement(
            Status.WARN,
            "0 (None)",
            "a GPS is configured but none reports: ArduPilot waits for it (pre-arm 'GPS 1: "
            "was not found') and its EKF origin comes from nowhere else"
            + (" (configure --no-gnss turns it off)" if not ctx.no_gnss else ""),
            0 if ctx.no_gnss else None,
        )
    return Judgement(
        Status.INFO,
        "-",
        "a GPS beside us: fine as long as EK3_SRC1_* does not use it (source set 2 may, for a "
        "switch-over)",
    )


def _origin_row(ctx: ArduPilotContext, from_gps: bool) -> Row:
    name, need = "EKF origin", "set (service or GPS)"
    seen = ctx.origin_seen
    shown = {True: "held", False: "none", None: "not watched"}[seen]
    if seen:
        return Row(
            name,
            shown,
            need,
            "EKF3 has an origin (GLOBAL_POSITION_INT reports a position)",
            Status.OK,
        )
    if ctx.set_origin:
        why = (
            "the service sends SET_GPS_GLOBAL_ORIGIN ([service.ardupilot] set_origin) each "
            "second until EKF3 holds it"
        )
        if seen is False:
            why += "; none held yet: is the service running on this autopilot?"
        return Row(name, shown, need, why, Status.OK if seen is None else Status.WARN)
    if from_gps:
        return Row(name, shown, need, "EKF3 takes its origin from the GPS", Status.INFO)
    return Row(
        name,
        shown,
        need,
        "without GPS EKF3 has no origin and never uses our position: set [service.ardupilot] "
        "set_origin = true with the site's origin_lat_deg / origin_lon_deg / origin_alt_m (it "
        "must arrive after 'EKF3 IMU0 initialised': the service resends it until held)",
        Status.FAIL,
    )


# ---------------------------------------------------------------- rangefinders, link
def _rangefinder_rows(params: Mapping[str, Param], ctx: ArduPilotContext) -> list[Row]:
    rows = []
    for sid in ctx.autopilot_sensor_ids:
        n = sid + 1
        rows.append(param_row(params, f"RNGFND{n}_TYPE", partial(_judge_rng_type, sid)))
        if (value_of(params, f"RNGFND{n}_TYPE") or 0) != 0:
            rows.append(param_row(params, f"RNGFND{n}_ORIENT", partial(_judge_rng_orient, sid)))
    return rows


def _judge_rng_type(sid: int, v: float) -> Judgement:
    if v != 0:
        return Judgement(
            Status.OK,
            "a rangefinder",
            f"ArduPilot streams it as DISTANCE_SENSOR id {sid} (instance {sid}), our sensor {sid}",
        )
    return Judgement(
        Status.FAIL,
        "a rangefinder",
        f"our sensor {sid} is read from the autopilot's DISTANCE_SENSOR id {sid}, and "
        f"RNGFND{sid + 1} is off: no scale from it",
    )


def _judge_rng_orient(sid: int, v: float) -> Judgement:
    if v == ORIENT_DOWN:
        return Judgement(Status.OK, "25 (down)", "the service takes downward sensors only")
    return Judgement(
        Status.FAIL,
        "25 (down)",
        f"orientation {int(v)}: the service drops DISTANCE_SENSOR id {sid} unless it points down",
        ORIENT_DOWN,
    )


def _judge_sysid(ctx: ArduPilotContext, v: float) -> Judgement:
    if int(v) == ctx.system_id:
        return Judgement(Status.OK, str(ctx.system_id), "the service listens to this system id")
    return Judgement(
        Status.FAIL,
        str(ctx.system_id),
        f"the service (service.system_id = {ctx.system_id}) ignores every message of system "
        f"{int(v)}: set service.system_id = {int(v)}",
    )


def _judge_arming(v: float) -> Judgement:
    if v != 0:
        return Judgement(Status.OK, "1 (all)", "pre-arm checks on (VisOdom health among them)")
    return Judgement(
        Status.WARN,
        "1 (all)",
        "no pre-arm checks: ArduPilot arms without a position or with our estimate unhealthy",
        1,
    )
