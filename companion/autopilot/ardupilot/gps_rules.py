"""ArduPilot with GPS and our vision together (``--with-gps``): EKF3's source set 1 on GPS, set
2 on our external navigation, switched by the service (MAV_CMD_SET_EKF_SOURCE_SET) at GPS loss
and back (pure; docs/gps.md).

Why, as measured on the real ArduCopter SITL (V4.7.0-dev) on 2026-11-29 (probes on the ground,
not yet missions): EKF3 uses one source set at a time and resets its position to the new source
at every switch. With VISO_TYPE 1 (MAVLink) nothing aligns our frame to EKF3's, and the switch
to ExtNav jumped 5.85 m (our frame offset by (5, -3) m); with VISO_TYPE 3 (VOXL) ArduPilot keeps
our position aligned to its own while GPS is the active source (yaw once, position
continuously): 0.035 m. Back to GPS the reset is our drift (0.89 m) unless the service first
slews its output onto the GPS position: 0.039 m. A set whose height or heading source differs
from the other's resets those at the switch too, so set 2 keeps set 1's.

FAIL: the handover cannot work as set (no GPS, no set to switch to, GPS in the set for a GPS
loss). WARN: it works, with a step at a switch (another height or heading source, no
autopilot-side alignment) or with less of us than we send.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import partial

from companion.autopilot.ardupilot.rules import (
    BARO,
    COMPASS,
    EXTNAV,
    GPS,
    GPS_TYPES,
    NONE,
    SOURCES,
    VISO_TYPES,
    YAW_SOURCES,
    ArduPilotContext,
    param_row,
    value_of,
)
from companion.autopilot.params import Judgement, Param, Row, Status

VOXL = 3
GPS_YAWS = (2, 3, 8)  # GSF, GPS, GPS with compass fallback: all lost with the GPS
FUSE_ALL_VELOCITIES = 1  # EK3_SRC_OPTIONS bit 0
SET1 = {"POSXY": GPS, "VELXY": GPS, "POSZ": BARO, "VELZ": GPS, "YAW": COMPASS}
DROPPED = ("COMPASS_DEC", "COMPASS_AUTODEC")  # GPS looks the declination up


def with_gps(rows: list[Row], params: Mapping[str, Param], ctx: ArduPilotContext) -> list[Row]:
    """The vision-only ``rows`` with VISO_TYPE, EK3_SRC1_* and the GPS type judged for GPS and
    vision together, source set 2 and EK3_SRC_OPTIONS after set 1, COMPASS_AUTODEC instead of
    the hand-set declination's rows."""
    gps_name = "GPS1_TYPE" if "GPS1_TYPE" in params else "GPS_TYPE"
    replaced = {
        "VISO_TYPE": param_row(params, "VISO_TYPE", _judge_viso_type, VISO_TYPES),
        gps_name: param_row(params, gps_name, partial(_judge_gps_type, ctx), GPS_TYPES),
        **{
            f"EK3_SRC1_{axis}": param_row(
                params,
                f"EK3_SRC1_{axis}",
                partial(_judge_set1, axis),
                YAW_SOURCES if axis == "YAW" else SOURCES,
            )
            for axis in SET1
        },
    }
    out: list[Row] = []
    for r in rows:
        if r.name in DROPPED:
            continue
        out.append(replaced.pop(r.name, r))
        if r.name == "EK3_SRC1_YAW":
            out += set2_rows(params, ctx)
    if "COMPASS_AUTODEC" in params:
        out.append(param_row(params, "COMPASS_AUTODEC", _judge_autodec))
    return out + list(replaced.values())


def set2_rows(params: Mapping[str, Param], ctx: ArduPilotContext) -> list[Row]:
    """EK3_SRC2_* (our external navigation, height and heading as set 1's) and
    EK3_SRC_OPTIONS."""
    posz1 = value_of(params, "EK3_SRC1_POSZ")
    posz_want = int(posz1) if posz1 is not None and posz1 not in (GPS, NONE) else BARO
    return [
        param_row(params, "EK3_SRC2_POSXY", _judge_set2_posxy, SOURCES),
        param_row(params, "EK3_SRC2_VELXY", partial(_judge_set2_vel, ctx, "horizontal"), SOURCES),
        param_row(params, "EK3_SRC2_POSZ", partial(_judge_set2_posz, posz_want), SOURCES),
        param_row(params, "EK3_SRC2_VELZ", partial(_judge_set2_vel, ctx, "vertical"), SOURCES),
        param_row(params, "EK3_SRC2_YAW", _judge_set2_yaw, YAW_SOURCES),
        param_row(params, "EK3_SRC_OPTIONS", _judge_src_options),
    ]


def _name(v: float, labels: Mapping[int, str] = SOURCES) -> str:
    return f"{int(v)} ({labels.get(int(v), '?')})"


def _judge_viso_type(v: float) -> Judgement:
    need = "3 (VOXL)"
    if v == VOXL:
        return Judgement(
            Status.OK,
            need,
            "ArduPilot keeps our position aligned to its own while GPS is the active source "
            "(yaw once, position continuously): 0.035 m at the switch to ExtNav in the probe",
        )
    if v == 0:
        return Judgement(Status.FAIL, need, "visual odometry off: no set 2 to switch to", VOXL)
    why = (
        "MAVLink: nothing aligns our frame to EKF3's, and the switch to ExtNav resets to ours "
        "as it is: 5.85 m in the probe (0.035 m with 3)"
        if v == 1
        else f"{_name(v, VISO_TYPES)}: the same alignment as 3, but it drops our data after a "
        "reset_counter change; 3 does not"
    )
    return Judgement(Status.WARN, need, why, VOXL)


def _judge_gps_type(ctx: ArduPilotContext, v: float) -> Judgement:
    if v == 0:
        return Judgement(Status.FAIL, "1 (Auto)", "no GPS configured: --with-gps needs one", 1)
    if ctx.gps_seen is False:
        return Judgement(
            Status.WARN, "1 (Auto)", "a GPS is configured but none reported while watching"
        )
    return Judgement(Status.OK, "1 (Auto)", "the GPS of source set 1")


def _judge_set1(axis: str, v: float) -> Judgement:
    """EK3_SRC1_*: the GPS set, as ArduPilot's defaults have it."""
    want = SET1[axis]
    labels = YAW_SOURCES if axis == "YAW" else SOURCES
    need = _name(want, labels)
    if v == want:
        return Judgement(Status.OK, need, "set 1 is the GPS set (ArduPilot's default)")
    if axis == "POSXY":
        why = f"{_name(v)}: set 1 is the GPS set, set 2 ours (the vision-only set-up has ours here)"
        return Judgement(Status.FAIL, need, why, want)
    if axis == "POSZ" and v in (EXTNAV, 2):
        return Judgement(
            Status.OK, f"{need}, or as set 2's", f"height from {_name(v)} in both sets: no step"
        )
    if axis == "POSZ":
        why = f"height from {_name(v)}: GPS height is metres of noise and cannot be set 2's"
        return Judgement(Status.WARN if v == GPS else Status.FAIL, need, why, want)
    if axis == "YAW":
        why = (
            "our yaw as EKF3's heading: the service aligns our output to that heading, which "
            "must not be ours"
            if v == EXTNAV
            else f"heading from {_name(v, labels)}: lost with the GPS, and set 2's must match"
        )
        return Judgement(Status.WARN if v else Status.FAIL, need, why, want)
    return Judgement(Status.WARN, need, f"{_name(v)}: set 1 takes its velocity from GPS", want)


def _judge_set2_posxy(v: float) -> Judgement:
    if v == EXTNAV:
        return Judgement(Status.OK, "6 (ExternalNav)", "set 2, for a GPS loss, is ours")
    return Judgement(
        Status.FAIL,
        "6 (ExternalNav)",
        f"{_name(v)}: set 2 is what EKF3 is switched to when GPS is lost; without our position "
        "it stops aiding ('EKF3 IMU0 stopped aiding' in the probe)",
        EXTNAV,
    )


def _judge_set2_vel(ctx: ArduPilotContext, what: str, v: float) -> Judgement:
    want = EXTNAV if ctx.odometry else NONE
    need = _name(want)
    if v == GPS:
        why = f"GPS {what} velocity in the set for a GPS loss"
        return Judgement(Status.FAIL, need, why, want)
    if v == want:
        why = "our ODOMETRY carries it" if ctx.odometry else "VISION_POSITION_ESTIMATE has none"
        return Judgement(Status.OK, need, why)
    if v == EXTNAV:
        why = f"VISION_POSITION_ESTIMATE carries no velocity: EKF3 waits for a {what} one"
        return Judgement(Status.FAIL, need, why, want)
    return Judgement(Status.WARN, need, f"{_name(v)}: our ODOMETRY carries the {what} one", want)


def _judge_set2_posz(want: int, v: float) -> Judgement:
    need = f"{_name(want)}, as EK3_SRC1_POSZ"
    if v == GPS:
        return Judgement(Status.FAIL, need, "GPS height in the set for a GPS loss", want)
    if v == want:
        return Judgement(Status.OK, need, "the same as set 1's: a switch resets only xy")
    return Judgement(
        Status.WARN,
        need,
        f"{_name(v)}, not set 1's: every switch resets the height to another source (a step)",
        want,
    )


def _judge_set2_yaw(v: float) -> Judgement:
    need = "1 (Compass), as EK3_SRC1_YAW"
    if v == COMPASS:
        return Judgement(Status.OK, need, "the same heading source as set 1's: no yaw reset")
    if v in GPS_YAWS:
        why = f"{_name(v, YAW_SOURCES)}: a GPS heading in the set for a GPS loss"
        return Judgement(Status.FAIL, need, why, COMPASS)
    return Judgement(
        Status.WARN,
        need,
        f"{_name(v, YAW_SOURCES)}: a heading source other than set 1's resets the yaw at "
        "every switch",
        COMPASS,
    )


def _judge_src_options(v: float) -> Judgement:
    if int(v) & FUSE_ALL_VELOCITIES:
        return Judgement(
            Status.WARN,
            "0",
            "bit 0 (FuseAllVelocities): EKF3 fuses the GPS velocity on set 2 too, and the GPS "
            "may be the bad one",
            int(v) & ~FUSE_ALL_VELOCITIES,
        )
    return Judgement(Status.OK, "0", "only the active set's velocity sources are fused")


def _judge_autodec(v: float) -> Judgement:
    if v != 0:
        return Judgement(
            Status.OK, "1", "ArduPilot looks the declination up from the GPS fix (COMPASS_DEC)"
        )
    return Judgement(
        Status.INFO, "1", "declination by hand (COMPASS_DEC): right only if it is the site's"
    )
