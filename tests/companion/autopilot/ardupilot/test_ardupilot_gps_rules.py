"""`companion autopilot check | configure --with-gps` on ArduPilot: EKF3 source set 1 on GPS,
set 2 on our external navigation (companion.autopilot.ardupilot.gps_rules; the research
probes in docs/gps.md).

A parameter set as docs/gps.md lists it passes; each wrong value is named with its verdict,
its reason and the value configure writes; configure (through a fake of the pymavlink session)
writes exactly the listed values; without the flag the vision-only rules are as they were.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest

from companion.autopilot.ardupilot.check import evaluate_rows
from companion.autopilot.ardupilot.link import Watched
from companion.autopilot.ardupilot.rules import ArduPilotContext
from companion.autopilot.options import CheckOptions
from companion.autopilot.params import Param, Row, Status, Target
from companion.config import load_config

GOOD: dict[str, int | float] = {
    "VISO_TYPE": 3,
    "VISO_POS_X": 0.0,
    "VISO_POS_Y": 0.0,
    "VISO_POS_Z": 0.0,
    "VISO_ORIENT": 0,
    "VISO_SCALE": 1.0,
    "VISO_DELAY_MS": 10,
    "VISO_QUAL_MIN": 0,
    "VISO_POS_M_NSE": 0.1,
    "VISO_YAW_M_NSE": 0.1,
    "EK3_SRC1_POSXY": 3,
    "EK3_SRC1_VELXY": 3,
    "EK3_SRC1_POSZ": 1,
    "EK3_SRC1_VELZ": 3,
    "EK3_SRC1_YAW": 1,
    "EK3_SRC2_POSXY": 6,
    "EK3_SRC2_VELXY": 6,
    "EK3_SRC2_POSZ": 1,
    "EK3_SRC2_VELZ": 6,
    "EK3_SRC2_YAW": 1,
    "EK3_SRC_OPTIONS": 0,
    "GPS1_TYPE": 1,
    "COMPASS_DEC": 0.0,
    "COMPASS_AUTODEC": 1,
    "MAV_SYSID": 1,
    "ARMING_CHECK": 1,
}
GPS = ArduPilotContext(output="odometry", gps_seen=True, origin_seen=True, with_gps=True)
SET2 = ("EK3_SRC2_POSXY", "EK3_SRC2_VELXY", "EK3_SRC2_POSZ", "EK3_SRC2_VELZ", "EK3_SRC2_YAW")


def _typed(values: dict[str, int | float]) -> dict[str, Param]:
    return {k: Param(k, v, isinstance(v, int)) for k, v in values.items()}


def _rows(values: dict[str, int | float], ctx: ArduPilotContext = GPS) -> dict[str, Row]:
    return {r.name: r for r in evaluate_rows(_typed(values), ctx)}


def test_the_listed_set_passes_with_gps() -> None:
    rows = _rows(GOOD)
    bad = {n: r.status for n, r in rows.items() if r.status in (Status.FAIL, Status.WARN)}
    assert bad == {}
    names = list(rows)
    assert names[names.index("EK3_SRC1_YAW") + 1 : names.index("EK3_SRC1_YAW") + 6] == list(SET2)
    assert "EK3_SRC_OPTIONS" in rows and "COMPASS_DEC" not in rows
    assert rows["COMPASS_AUTODEC"].status is Status.OK
    assert "0.035 m" in rows["VISO_TYPE"].why
    vpe = ArduPilotContext(
        output="vision_position_estimate", gps_seen=True, origin_seen=True, with_gps=True
    )
    vpe_rows = _rows({**GOOD, "EK3_SRC2_VELXY": 0, "EK3_SRC2_VELZ": 0}, vpe)
    assert vpe_rows["EK3_SRC2_VELXY"].status is Status.OK  # the probe's set (no velocity)
    assert vpe_rows["EK3_SRC2_VELZ"].status is Status.OK


@pytest.mark.parametrize(
    ("name", "value", "status", "target", "reason"),
    [
        ("VISO_TYPE", 1, Status.WARN, 3, "5.85 m in the probe"),
        ("VISO_TYPE", 2, Status.WARN, 3, "drops our data after a reset_counter change"),
        ("VISO_TYPE", 0, Status.FAIL, 3, "no set 2"),
        ("EK3_SRC1_POSXY", 6, Status.FAIL, 3, "set 1 is the GPS set"),
        ("EK3_SRC1_VELXY", 6, Status.WARN, 3, "velocity from GPS"),
        ("EK3_SRC1_POSZ", 3, Status.WARN, 1, "cannot be set 2's"),
        ("EK3_SRC1_YAW", 6, Status.WARN, 1, "must not be ours"),
        ("EK3_SRC1_YAW", 8, Status.WARN, 1, "lost with the GPS"),
        ("EK3_SRC2_POSXY", 0, Status.FAIL, 6, "stopped aiding"),
        ("EK3_SRC2_POSXY", 3, Status.FAIL, 6, "switched to when GPS is lost"),
        ("EK3_SRC2_VELXY", 3, Status.FAIL, 6, "GPS horizontal velocity"),
        ("EK3_SRC2_VELXY", 0, Status.WARN, 6, "our ODOMETRY carries"),
        ("EK3_SRC2_POSZ", 6, Status.WARN, 1, "not set 1's"),
        ("EK3_SRC2_POSZ", 3, Status.FAIL, 1, "GPS height"),
        ("EK3_SRC2_VELZ", 3, Status.FAIL, 6, "GPS vertical velocity"),
        ("EK3_SRC2_YAW", 6, Status.WARN, 1, "resets the yaw"),
        ("EK3_SRC2_YAW", 3, Status.FAIL, 1, "GPS heading"),
        ("EK3_SRC_OPTIONS", 1, Status.WARN, 0, "FuseAllVelocities"),
        ("GPS1_TYPE", 0, Status.FAIL, 1, "needs one"),
        ("COMPASS_AUTODEC", 0, Status.INFO, None, "declination by hand"),
    ],
)
def test_each_wrong_value_is_named_with_its_reason(
    name: str, value: int, status: Status, target: int | None, reason: str
) -> None:
    row = _rows({**GOOD, name: value})[name]
    assert row.status is status, row
    assert reason in row.why
    if target is None:
        assert row.targets == ()
    else:
        (t,) = row.targets
        assert t.value == target and t.is_int


def test_set_2_follows_set_1s_height_source() -> None:
    """Our height in both sets is as good as baro in both: only a difference steps."""
    rows = _rows({**GOOD, "EK3_SRC1_POSZ": 6, "EK3_SRC2_POSZ": 6})
    assert rows["EK3_SRC1_POSZ"].status is Status.OK
    assert rows["EK3_SRC2_POSZ"].status is Status.OK
    differ = _rows({**GOOD, "EK3_SRC1_POSZ": 6, "EK3_SRC2_POSZ": 1})["EK3_SRC2_POSZ"]
    assert differ.status is Status.WARN and differ.targets[0].value == 6
    unseen = ArduPilotContext(output="odometry", gps_seen=False, origin_seen=True, with_gps=True)
    gps = _rows(GOOD, unseen)["GPS1_TYPE"]
    assert gps.status is Status.WARN and gps.targets == ()


def test_without_the_flag_the_vision_only_rules_stand() -> None:
    """The vision-only set-up (set 1 ours, VISO_TYPE 1, no GPS) is right without --with-gps and
    wrong with it; the GPS set-up is wrong without the flag."""
    vision = {
        **GOOD,
        "VISO_TYPE": 1,
        "EK3_SRC1_POSXY": 6,
        "EK3_SRC1_VELXY": 6,
        "EK3_SRC1_POSZ": 6,
        "EK3_SRC1_VELZ": 6,
        "EK3_SRC1_YAW": 6,
        "GPS1_TYPE": 0,
    }
    alone_ctx = ArduPilotContext(output="odometry", gps_seen=False, origin_seen=True)
    alone = _rows(vision, alone_ctx)
    assert all(r.status in (Status.OK, Status.INFO) for r in alone.values()), alone
    assert not set(SET2) & set(alone)
    together = _rows(vision)
    assert together["EK3_SRC1_POSXY"].status is Status.FAIL
    assert together["GPS1_TYPE"].status is Status.FAIL
    assert _rows(GOOD, alone_ctx)["EK3_SRC1_POSXY"].status is Status.FAIL


class FakeArduPilot:
    """The blocking pymavlink session as configure uses it, over a parameter store."""

    url, system_id, autopilot = "udpin:127.0.0.1:14550", 1, "ArduPilot"

    def __init__(self, store: dict[str, Param]) -> None:
        self.store = store
        self.written: list[Target] = []

    def __call__(self, *args: Any) -> FakeArduPilot:
        return self

    def __enter__(self) -> FakeArduPilot:
        return self

    def close(self) -> None:
        pass

    def armed(self) -> bool:
        return False

    def params(self) -> dict[str, Param]:
        return dict(self.store)

    def watch(self, seconds: float) -> Watched:
        return Watched(origin=(473977000, 85456000, 489400), gps_seen=True)

    def write(self, target: Target) -> None:
        self.written.append(target)
        self.store[target.name] = Param(target.name, float(target.value), target.is_int)

    def read(self, name: str) -> float:
        return float(self.store[name].value)


def test_configure_with_gps_writes_exactly_the_listed_values(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """From the vision-only set-up to the listed one: set 1 GPS, set 2 ExtNav, VOXL."""
    from companion.autopilot.ardupilot import configure

    vision = {
        **GOOD,
        "VISO_TYPE": 1,
        "EK3_SRC1_POSXY": 6,
        "EK3_SRC1_VELXY": 6,
        "EK3_SRC1_VELZ": 6,
        "EK3_SRC1_YAW": 6,
        "EK3_SRC2_POSXY": 0,
        "EK3_SRC2_VELXY": 0,
        "EK3_SRC2_VELZ": 0,
        "EK3_SRC2_YAW": 0,
        "EK3_SRC_OPTIONS": 1,
    }
    rangefinders = {
        f"RNGFND{n}_{k}": v for n in range(1, 5) for k, v in (("TYPE", 1), ("ORIENT", 25))
    }
    fake = FakeArduPilot(_typed({**vision, **rangefinders}))
    monkeypatch.setattr(configure, "ArduPilotLink", fake)
    toml = tmp_path / "companion.toml"
    toml.write_text('[service]\noutput = "odometry"\n')
    opts = CheckOptions(url=fake.url, socket=str(tmp_path / "none"), yes=True, with_gps=True)
    report = asyncio.run(configure.run_configure(load_config(toml), opts, show=lambda s: None))
    assert report.written and report.problems == 0
    written = {t.name: t.value for t in fake.written}
    assert written == {
        "VISO_TYPE": 3,
        "EK3_SRC1_POSXY": 3,
        "EK3_SRC1_VELXY": 3,
        "EK3_SRC1_VELZ": 3,
        "EK3_SRC1_YAW": 1,
        "EK3_SRC2_POSXY": 6,
        "EK3_SRC2_VELXY": 6,
        "EK3_SRC2_VELZ": 6,
        "EK3_SRC2_YAW": 1,
        "EK3_SRC_OPTIONS": 0,
    }
    assert {t.name for t in fake.written if t.reboot} == {"VISO_TYPE"}
    assert all(r.status in (Status.OK, Status.INFO) for r in report.rows_after)
