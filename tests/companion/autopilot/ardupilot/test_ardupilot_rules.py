"""The ArduPilot rules on the heading (pure; the real ArduCopter runs in test_ardupilot_check).

With EK3_SRC1_YAW = 1 EKF3's heading is the compass's plus COMPASS_DEC, and without GPS nobody
looks the declination up: the check must say so, compare it with the site's when the config
gives one, and configure must write the site's value (radians, ArduPilot's unit).
"""

from __future__ import annotations

import math

import pytest

from companion.autopilot.ardupilot.rules import (
    DECLINATION_TOL_RAD,
    ArduPilotContext,
    evaluate,
)
from companion.autopilot.params import Param, Row, Status

SITE_DEG = 12.87


def _params(yaw_source: int, dec_rad: float, autodec: int = 1) -> dict[str, Param]:
    values: dict[str, tuple[float, bool]] = {
        "VISO_TYPE": (1, True),
        "EK3_SRC1_POSXY": (6, True),
        "EK3_SRC1_VELXY": (6, True),
        "EK3_SRC1_POSZ": (6, True),
        "EK3_SRC1_VELZ": (6, True),
        "EK3_SRC1_YAW": (yaw_source, True),
        "COMPASS_DEC": (dec_rad, False),
        "COMPASS_AUTODEC": (autodec, True),
        "GPS1_TYPE": (0, True),
    }
    return {k: Param(k, int(v) if is_int else v, is_int) for k, (v, is_int) in values.items()}


def _row(rows: list[Row], name: str) -> Row | None:
    return next((r for r in rows if r.name == name), None)


def test_extnav_heading_has_no_declination_rows() -> None:
    rows = evaluate(_params(6, 0.0), ArduPilotContext(declination_deg=SITE_DEG))
    assert _row(rows, "COMPASS_DEC") is None
    assert _row(rows, "COMPASS_AUTODEC") is None


def test_compass_heading_without_a_site_declination_warns_on_zero() -> None:
    rows = evaluate(_params(1, 0.0), ArduPilotContext())
    dec = _row(rows, "COMPASS_DEC")
    assert dec is not None and dec.status is Status.WARN
    assert "magnetic north" in dec.why and "declination_deg" in dec.why
    assert dec.targets == ()  # nothing to write: we do not know the site's value
    by_hand = _row(evaluate(_params(1, 0.2), ArduPilotContext()), "COMPASS_DEC")
    assert by_hand is not None and by_hand.status is Status.INFO
    assert "11.46 deg" in by_hand.why


@pytest.mark.parametrize("error_deg", [-7.0, -0.5, 0.5, 20.0])
def test_a_wrong_declination_fails_and_configure_writes_the_sites(error_deg: float) -> None:
    ctx = ArduPilotContext(declination_deg=SITE_DEG)
    rows = evaluate(_params(1, math.radians(SITE_DEG + error_deg), autodec=0), ctx)
    dec = _row(rows, "COMPASS_DEC")
    assert dec is not None and dec.status is Status.FAIL
    assert f"{error_deg:+.2f} deg" in dec.why
    (target,) = dec.targets
    assert target.name == "COMPASS_DEC" and not target.is_int
    assert target.value == pytest.approx(math.radians(SITE_DEG), abs=1e-12)


def test_the_sites_declination_passes_within_tolerance() -> None:
    ctx = ArduPilotContext(declination_deg=SITE_DEG)
    for off in (0.0, 0.9 * DECLINATION_TOL_RAD, -0.9 * DECLINATION_TOL_RAD):
        rows = evaluate(_params(1, math.radians(SITE_DEG) + off, autodec=0), ctx)
        dec = _row(rows, "COMPASS_DEC")
        assert dec is not None and dec.status is Status.OK, dec
        autodec = _row(rows, "COMPASS_AUTODEC")
        assert autodec is not None and autodec.status is Status.OK


def test_automatic_declination_beside_a_site_value_is_turned_off() -> None:
    ctx = ArduPilotContext(declination_deg=SITE_DEG)
    rows = evaluate(_params(1, math.radians(SITE_DEG), autodec=1), ctx)
    autodec = _row(rows, "COMPASS_AUTODEC")
    assert autodec is not None and autodec.status is Status.WARN
    assert [(t.name, t.value) for t in autodec.targets] == [("COMPASS_AUTODEC", 0)]
