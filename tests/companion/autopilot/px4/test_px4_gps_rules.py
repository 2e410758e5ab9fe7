"""`companion px4 check | configure --with-gps`: PX4's parameters for GPS and our vision
together (companion.autopilot.px4.gps_rules; the research probes in docs/gps.md).

A parameter set as docs/gps.md lists it passes; each wrong value is named with its verdict, its
reason and the value configure writes; configure (through fakes of the MAVSDK session) writes
exactly the listed values; without the flag the vision-only rules are as they were.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest

from companion import cli
from companion.autopilot.options import CheckOptions
from companion.autopilot.params import Param, Row, Status, Target
from companion.autopilot.px4.link_context import LinkContext
from companion.autopilot.px4.rules import evaluate
from companion.config import load_config

GOOD: dict[str, int | float] = {
    "EKF2_EV_CTRL": 7,
    "EKF2_HGT_REF": 3,
    "EKF2_GPS_CTRL": 7,
    "SYS_HAS_GPS": 1,
    "EKF2_GPS_MODE": 0,
    "EKF2_GPS_P_NOISE": 0.5,
    "COM_POS_FS_EPH": 5.0,
    "SYS_HAS_MAG": 1,
    "EKF2_MAG_TYPE": 0,
    "EKF2_RNG_CTRL": 1,
    "EKF2_EV_DELAY": 0.0,
    "EKF2_DELAY_MAX": 200.0,
    "EKF2_EV_NOISE_MD": 0,
    "EKF2_EVP_NOISE": 0.1,
    "EKF2_EVV_NOISE": 0.1,
    "EKF2_EVA_NOISE": 0.1,
    "EKF2_EV_QMIN": 0,
    "EKF2_EVP_GATE": 5.0,
}
GPS = LinkContext("odometry", gps_seen=True, with_gps=True)
GPS_ROWS = ("SYS_HAS_GPS", "EKF2_GPS_MODE", "EKF2_GPS_P_NOISE", "COM_POS_FS_EPH")


def _typed(values: dict[str, int | float]) -> dict[str, Param]:
    return {k: Param(k, v, isinstance(v, int)) for k, v in values.items()}


def _rows(values: dict[str, int | float], ctx: LinkContext = GPS) -> dict[str, Row]:
    return {r.name: r for r in evaluate(_typed(values), ctx)}


def test_the_listed_set_passes_with_gps() -> None:
    rows = _rows(GOOD)
    bad = {n: r.status for n, r in rows.items() if r.status in (Status.FAIL, Status.WARN)}
    assert bad == {}
    assert set(GPS_ROWS) <= set(rows)
    names = list(rows)
    assert names.index("EKF2_GPS_CTRL") + 1 == names.index("SYS_HAS_GPS")  # the GPS rows together
    assert rows["COM_POS_FS_EPH"].status is Status.INFO
    assert "0.095 m" in rows["EKF2_EV_CTRL"].why and "0.29 m" in rows["EKF2_EV_CTRL"].why
    assert "0.2-0.27 m" in rows["EKF2_HGT_REF"].why
    vpe = _rows({**GOOD, "EKF2_EV_CTRL": 3}, LinkContext(with_gps=True, gps_seen=True))
    assert vpe["EKF2_EV_CTRL"].status is Status.OK  # no velocity in VISION_POSITION_ESTIMATE
    baro = _rows({**GOOD, "EKF2_HGT_REF": 0})["EKF2_HGT_REF"]
    assert baro.status is Status.OK  # GNSS height a biased aid as with vision


@pytest.mark.parametrize(
    ("name", "value", "status", "target", "reason"),
    [
        ("EKF2_EV_CTRL", 15, Status.FAIL, 7, "bit 3 (our yaw) with GPS"),
        ("EKF2_EV_CTRL", 4, Status.FAIL, 7, "bit 0 off"),
        ("EKF2_EV_CTRL", 5, Status.FAIL, 7, "EKF2_HGT_REF = vision needs our height"),
        ("EKF2_EV_CTRL", 3, Status.WARN, 7, "velocity not fused"),
        ("EKF2_HGT_REF", 1, Status.WARN, 3, "a 0.2-0.27 m step in the probe"),
        ("EKF2_HGT_REF", 2, Status.OK, None, "rangefinder height"),
        ("EKF2_GPS_CTRL", 0, Status.FAIL, 7, "never fuses the GPS position"),
        ("EKF2_GPS_CTRL", 1, Status.WARN, 7, "altitude (bit 1) or velocity (bit 2)"),
        ("SYS_HAS_GPS", 0, Status.FAIL, 1, "PX4 expects no GPS"),
        ("EKF2_GPS_MODE", 1, Status.INFO, None, "dead reckoning"),
        ("EKF2_GPS_P_NOISE", 2.0, Status.WARN, 0.5, "outside"),
    ],
)
def test_each_wrong_value_is_named_with_its_reason(
    name: str, value: int | float, status: Status, target: int | float | None, reason: str
) -> None:
    row = _rows({**GOOD, name: value})[name]
    assert row.status is status, row
    assert reason in row.why
    if target is None:
        assert row.targets == ()
    else:
        (t,) = row.targets
        assert t.value == target and t.is_int == isinstance(value, int)


def test_a_missing_receiver_and_a_range_height_without_the_rangefinder() -> None:
    unseen = _rows(GOOD, LinkContext("odometry", gps_seen=False, with_gps=True))
    assert unseen["EKF2_GPS_CTRL"].status is Status.WARN
    assert "no GNSS receiver" in unseen["EKF2_GPS_CTRL"].why
    range_off = _rows({**GOOD, "EKF2_HGT_REF": 2, "EKF2_RNG_CTRL": 0})["EKF2_HGT_REF"]
    assert range_off.status is Status.FAIL and range_off.targets[0].value == 3
    older = _rows({k: v for k, v in GOOD.items() if k not in ("SYS_HAS_GPS", "EKF2_GPS_MODE")})
    assert "SYS_HAS_GPS" not in older and "EKF2_GPS_MODE" not in older  # PX4 1.14 lacks them


def test_without_the_flag_the_vision_only_rules_stand() -> None:
    """The vision-only set-up (VISION_POSITION_ESTIMATE, our yaw, no magnetometer, GNSS off)
    is right without --with-gps, and wrong with it."""
    vision = {**GOOD, "EKF2_EV_CTRL": 11, "EKF2_GPS_CTRL": 0, "EKF2_MAG_TYPE": 5}
    alone = _rows(vision, LinkContext(gps_seen=False))
    assert alone["EKF2_EV_CTRL"].status is Status.OK
    assert alone["EKF2_GPS_CTRL"].status is Status.OK
    assert not set(GPS_ROWS) & set(alone)
    together = _rows(vision, LinkContext(gps_seen=True, with_gps=True))
    assert together["EKF2_EV_CTRL"].status is Status.FAIL
    assert together["EKF2_GPS_CTRL"].status is Status.FAIL


class FakePx4:
    """MAVSDK's session as configure uses it, over a parameter store."""

    url, system_id, autopilot = "udpin://127.0.0.1:14550", 1, "PX4"

    def __init__(self, store: dict[str, Param]) -> None:
        self.store = store
        self.written: list[Target] = []

    def __call__(self, *args: Any) -> FakePx4:
        return self

    async def __aenter__(self) -> FakePx4:
        return self

    async def __aexit__(self, *exc: Any) -> None:
        return None

    async def armed(self) -> bool:
        return False

    async def params(self) -> dict[str, Param]:
        return dict(self.store)

    async def watch(self, seconds: float) -> dict[str, Any]:
        return {"gps_seen": True}

    async def write(self, target: Target) -> None:
        self.written.append(target)
        self.store[target.name] = Param(target.name, target.value, target.is_int)

    async def read(self, name: str, is_int: bool) -> int | float:
        return self.store[name].value


WRONG: dict[str, int | float] = {
    "EKF2_EV_CTRL": 15,
    "EKF2_HGT_REF": 1,
    "EKF2_GPS_CTRL": 0,
    "SYS_HAS_GPS": 0,
    "EKF2_GPS_P_NOISE": 2.0,
}
LISTED = {"EKF2_EV_CTRL": 7, "EKF2_HGT_REF": 3, "EKF2_GPS_CTRL": 7, "SYS_HAS_GPS": 1}


def test_configure_with_gps_writes_exactly_the_listed_values(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from companion.autopilot.px4 import configure

    fake = FakePx4(_typed({**GOOD, **WRONG}))
    monkeypatch.setattr(configure, "Px4Link", fake)
    opts = CheckOptions(url=fake.url, socket=str(tmp_path / "none"), yes=True, with_gps=True)
    report = asyncio.run(configure.run_configure(load_config(), opts, show=lambda s: None))
    assert report.written and report.problems == 0
    written = {t.name: t.value for t in fake.written}
    assert written == {**LISTED, "EKF2_GPS_P_NOISE": 0.5}
    assert all(t.is_int for t in fake.written if t.name in LISTED)
    reboot = {t.name for t in fake.written if t.reboot}
    assert reboot == {"EKF2_HGT_REF", "SYS_HAS_GPS"}
    assert all(r.status in (Status.OK, Status.INFO) for r in report.rows_after)


def test_with_gps_and_no_gnss_are_refused_together() -> None:
    argv = ["px4", "configure", "--with-gps", "--no-gnss", "--yes"]
    assert cli.main(argv) == 2
