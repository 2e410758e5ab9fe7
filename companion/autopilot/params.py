"""The parameter model both autopilots are checked with (pure).

A :class:`Param` is one parameter as read from the autopilot (its value and whether the
autopilot declares it an integer). Each autopilot's rules turn the parameters into one
:class:`Row` per parameter: its value as shown, what we need, why, a :class:`Status`, and the
:class:`Target` value(s) ``configure`` would write. A rule's verdict on one value is a
:class:`Judgement`. FAIL: the EKF will not fuse our estimate (or the link will not work) as it
is; WARN: it works, but not as well as it should; OK: as needed; INFO: context only.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass

from companion.drivers.status import printable


class Status(enum.Enum):
    """How a parameter stands."""

    OK = "OK"
    WARN = "WARN"
    FAIL = "FAIL"
    INFO = "-"


@dataclass(frozen=True, slots=True)
class Param:
    """A parameter as read from the autopilot (type as the autopilot declares it)."""

    name: str
    value: int | float
    is_int: bool


@dataclass(frozen=True, slots=True)
class Target:
    """A value to write (with the parameter's own type) and whether the autopilot applies it
    only after a reboot."""

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
class Judgement:
    """The verdict on one value; ``target`` is what configure writes unless OK."""

    status: Status
    need: str
    why: str
    target: int | float | None = None


def labelled(value: int, labels: Mapping[int, str]) -> str:
    """``value`` with its meaning in brackets, when ``labels`` knows it: ``6 (ExternalNav)``."""
    return f"{value} ({labels[value]})" if value in labels else str(value)


def targets_of(rows: list[Row]) -> list[Target]:
    """Every value configure should write (FAIL and WARN rows), once per parameter."""
    out: dict[str, Target] = {}
    for r in rows:
        if r.status in (Status.FAIL, Status.WARN):
            for t in r.targets:
                out.setdefault(t.name, t)
    return list(out.values())


def finite_params(params: dict[str, Param]) -> tuple[dict[str, Param], tuple[Row, ...]]:
    """The parameters whose value is a finite number, and a FAIL row for each other one: a
    NaN or an infinity as read (a damaged parameter store, a hostile peer) is no value any
    rule can judge, and must not reach one (``int(nan)`` raised a traceback)."""
    finite = {k: p for k, p in params.items() if math.isfinite(p.value)}
    bad = tuple(
        Row(
            printable(name, 16),
            str(p.value),
            "a finite number",
            "not a number as read: set it (companion autopilot configure, or the GCS)",
            Status.FAIL,
        )
        for name, p in sorted(params.items())
        if name not in finite
    )
    return finite, bad


def judge_either(
    ok: bool,
    need: str,
    why_ok: str,
    why_not: str,
    status_not: Status,
    target: int | float | None = None,
) -> Judgement:
    """The verdict of a rule with one right answer: OK (``why_ok``) when ``ok``, else
    ``status_not`` (``why_not``) with the ``target`` configure writes."""
    if ok:
        return Judgement(Status.OK, need, why_ok)
    return Judgement(status_not, need, why_not, target)
