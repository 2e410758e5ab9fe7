"""`companion autopilot check` (PX4 and ArduPilot) on parameters that are NaN or infinite as
read (a damaged parameter store, a hostile peer): a FAIL row naming each, never a traceback
(``int(nan)`` raised ValueError, ``int(inf)`` OverflowError; the issue "Reliability round 3")."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path
from typing import Any

import pytest

from companion.autopilot.options import CheckOptions
from companion.autopilot.params import Param, Status
from companion.autopilot.px4.link_context import LinkContext
from companion.config import load_config

BAD = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


@pytest.mark.parametrize("value", BAD.values(), ids=BAD.keys())
def test_ardupilot_check_fails_a_non_finite_parameter_by_name(
    value: float, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from companion.autopilot.ardupilot import check as ardupilot_check
    from companion.autopilot.reach import LinkTarget
    from companion.drivers.mavlink import LinkUrl

    params = {
        "VISO_TYPE": Param("VISO_TYPE", value, True),  # an integer parameter sent as NaN
        "VISO_DELAY_MS": Param("VISO_DELAY_MS", 10, True),
        "MAV_SYSID": Param("MAV_SYSID", 1, True),
    }

    class Link:
        url, system_id, autopilot = "udpin:127.0.0.1:14550", 1, "ArduPilot"

    monkeypatch.setattr(
        ardupilot_check,
        "resolve_link",
        lambda cfg, opts: LinkTarget(
            "udpin:127.0.0.1:14550", LinkUrl.parse("udpin:127.0.0.1:14550"), tmp_path / "none"
        ),
    )
    monkeypatch.setattr(ardupilot_check, "_session", lambda *a: (Link(), params, False, None, None))
    report = asyncio.run(ardupilot_check.run_check(load_config(), CheckOptions(watch_s=0)))
    row = next(r for r in report.rows if r.name == "VISO_TYPE" and r.need == "a finite number")
    assert row.status is Status.FAIL and row.value == str(value)
    assert report.n_params == 3 and "VISO_TYPE" in ardupilot_check.format_check(report)


@pytest.mark.parametrize("value", BAD.values(), ids=BAD.keys())
def test_px4_check_fails_a_non_finite_parameter_by_name(
    value: float, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from companion.autopilot.px4 import check
    from companion.autopilot.px4.check import Px4Target

    params = {
        "EKF2_EV_DELAY": Param("EKF2_EV_DELAY", value, False),
        "EKF2_EV_CTRL": Param("EKF2_EV_CTRL", 15, True),
        "EKF2_HGT_REF": Param("EKF2_HGT_REF", 3, True),
    }

    class Link:
        system_id, autopilot = 1, "PX4"

        def __init__(self, *args: Any) -> None:
            pass

        async def __aenter__(self) -> Link:
            return self

        async def __aexit__(self, *exc: Any) -> None:
            return None

        async def params(self) -> dict[str, Param]:
            return params

        async def armed(self) -> bool:
            return False

    monkeypatch.setattr(
        check, "resolve", lambda cfg, opts: Px4Target("udp://:14550", LinkContext(), tmp_path / "x")
    )
    monkeypatch.setattr(check, "Px4Link", Link)
    report = asyncio.run(check.run_check(load_config(), CheckOptions(watch_s=0)))
    row = next(r for r in report.rows if r.need == "a finite number")
    assert row.name == "EKF2_EV_DELAY" and row.status is Status.FAIL
    assert "EKF2_EV_DELAY" in check.format_check(report)
