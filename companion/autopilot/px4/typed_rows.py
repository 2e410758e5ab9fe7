"""A PX4 parameter's row, typed as PX4 declares it (pure): missing, of the wrong type,
float-encoded (an INT32 holding a float's bytes) or int-encoded (a REAL32 holding an integer's
bytes), out of range, or judged by its rule; and which parameters PX4 applies after a reboot."""

from __future__ import annotations

from collections.abc import Callable, Mapping

from companion.autopilot.params import Judgement, Param, Row, Status, Target, labelled
from companion.autopilot.px4.encoding import float_encoded_int, int_encoded_float

REBOOT_PARAMS = frozenset({"EKF2_HGT_REF", "EKF2_EV_DELAY", "EKF2_DELAY_MAX"})
REBOOT_PREFIXES = ("MAV_", "SER_", "SYS_HAS_")


def needs_reboot(name: str) -> bool:
    """Whether PX4 applies a new value of ``name`` only after a reboot."""
    return name in REBOOT_PARAMS or name.startswith(REBOOT_PREFIXES)


def int_value(params: Mapping[str, Param], name: str, lo: float, hi: float) -> int | None:
    """An INT32's value as the user meant it (a float-encoded one decoded), or None."""
    p = params.get(name)
    if p is None or not p.is_int:
        return None
    f = float_encoded_int(int(p.value), lo, hi)
    return int(f) if f is not None else int(p.value)


def int_row(
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
    return Row(name, labelled(v, labels or {}), j.need, j.why, j.status, targets)


def float_row(
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
