"""``companion autopilot check | configure`` against the real ArduCopter (SITL): the right
set-up and four broken ones each get their verdict; configure writes and reads back.

Each scenario has its own ArduCopter (parameters applied at boot: VISO_TYPE and GPS1_TYPE
need it) with a companion stand-in (tests/peers/ardupilot.py: the true state sent back as ODOMETRY,
the EKF origin sent as the service sends it) on SERIAL0 and the checker on SERIAL1. They are all
started together when the first test needs one (instances 3 and 10-14: TCP 5790-5793 and
5860-5903), so that their 15-25 s of EKF start-up pass side by side instead of one after the
other; each test then checks its own instance (still at least that long after its boot) and
stops it. Nothing asserts speed.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from peers.ardupilot import MAV_FRAME_LOCAL_NED, SKIP_REASON, TruthSender

from companion.autopilot.ardupilot import rules
from companion.autopilot.ardupilot.check import format_check, run_check
from companion.autopilot.ardupilot.configure import run_configure
from companion.autopilot.ardupilot.rules import ArduPilotContext, evaluate
from companion.autopilot.options import CheckOptions
from companion.autopilot.params import Param, Status
from companion.autopilot.report import CheckReport
from companion.config import Config, load_config
from companion.sitl.loops import ardupilot_sitl
from companion.sitl.loops.ardupilot_flight import EXTNAV_BOOT_PARAMS
from companion.sitl.loops.ardupilot_sitl import ArduPilotSitl, port

INSTANCES = {  # one ArduCopter per test, all running at once
    "right": 3,
    "viso_type_0": 10,
    "no_origin": 11,
    "odometry_local_ned": 12,
    "gps_and_vision": 13,
    "configure": 14,
}
real = pytest.mark.skipif(not ardupilot_sitl.available(), reason=SKIP_REASON)
RIGHT = {**EXTNAV_BOOT_PARAMS, "VISO_POS_M_NSE": 0.1, "VISO_YAW_M_NSE": 0.1}


def _config(tmp: Path, instance: int, set_origin: bool = True) -> Config:
    base = load_config(None)
    return load_config(
        None,
        {
            "service": {
                "output": "odometry",
                "mavlink_url": f"tcp:127.0.0.1:{port(0, instance)}",
                "status_socket": str(tmp / "no-service.sock"),
                "ardupilot": {
                    "set_origin": set_origin,
                    "origin_lat_deg": -35.363261,
                    "origin_lon_deg": 149.16523,
                    "origin_alt_m": 584.0,
                },
            },
            # TFminis on the companion's UARTs: no RNGFND rows
            "rangefinders": [
                {**_rf_dict(rf), "serial": f"/dev/ttyUSB{rf.sensor_id}"} for rf in base.rangefinders
            ],
        },
    )


def _rf_dict(rf: Any) -> dict[str, Any]:
    from companion.config import to_dict

    d: dict[str, Any] = to_dict(rf)
    return d


def _opts(instance: int, **kw: Any) -> CheckOptions:
    values: dict[str, Any] = {"watch_s": 6.0, "timeout_s": 20.0, **kw}
    return CheckOptions(url=f"tcp:127.0.0.1:{port(1, instance)}", **values)


@dataclass(frozen=True)
class Scenario:
    params: dict[str, float] = field(default_factory=dict)  # on top of RIGHT
    frame_id: int = 20
    set_origin: bool = True
    fused: bool = False
    reason: str = ""  # in the verdict's first reason (or, fused, its "but")
    row: tuple[str, Status] | None = None


SCENARIOS = {
    "right": Scenario(fused=True),
    "viso_type_0": Scenario(
        {"VISO_TYPE": 0}, reason="VISO_TYPE = 0", row=("VISO_TYPE", Status.FAIL)
    ),
    "no_origin": Scenario(
        set_origin=False, reason="EKF3 has no origin", row=("EKF origin", Status.FAIL)
    ),
    "odometry_local_ned": Scenario(frame_id=MAV_FRAME_LOCAL_NED, reason="frame_id 1 (LOCAL_NED)"),
    "gps_and_vision": Scenario(
        {"GPS1_TYPE": 1, "SIM_GPS1_ENABLE": 1, "EK3_SRC1_VELXY": 3},
        reason="GPS and vision both sources",
        row=("EK3_SRC1_VELXY", Status.FAIL),
    ),
}


BROKEN = {"VISO_ORIENT": 2, "VISO_SCALE": 2.0, "VISO_QUAL_MIN": 90, "EK3_SRC1_VELXY": 3}
CONFIGURE = Scenario(BROKEN)  # the configure test's ArduCopter: the right sender


def _wait_ekf(sender: TruthSender, booted_s: float, seconds: float) -> None:
    """Let EKF3 initialise (and, where it can, start on our data): 'using external nav data'
    or ``seconds`` after the boot at ``booted_s`` (monotonic), whichever comes first."""
    end = booted_s + seconds
    while time.monotonic() < end:
        if any("is using external nav" in t for t in sender.texts):
            time.sleep(2.0)
            return
        time.sleep(0.2)


@dataclass
class Booted:
    """One scenario's running ArduCopter and its companion stand-in."""

    instance: int
    tmp: Path
    sender: TruthSender
    booted_s: float  # monotonic time at which it was up
    stack: contextlib.ExitStack

    def stop(self) -> None:
        self.stack.close()


class Fleet:
    """The ArduCopters of the tests that were selected, all started at the first request."""

    def __init__(self, cases: list[str], factory: pytest.TempPathFactory) -> None:
        self.cases, self.factory = cases, factory
        self.booted: dict[str, Booted] = {}

    def _boot(self, case: str) -> Booted:
        sc = CONFIGURE if case == "configure" else SCENARIOS[case]
        instance, tmp = INSTANCES[case], self.factory.mktemp(case)
        stack = contextlib.ExitStack()
        try:
            stack.enter_context(ArduPilotSitl(tmp / "ap", "odom", {**RIGHT, **sc.params}, instance))
            sender = stack.enter_context(
                TruthSender(port(0, instance), frame_id=sc.frame_id, set_origin=sc.set_origin)
            )
        except BaseException:
            stack.close()
            raise
        return Booted(instance, tmp, sender, time.monotonic(), stack)

    def get(self, case: str) -> Booted:
        if case not in self.booted:
            for c in [case, *self.cases]:
                if c not in self.booted:
                    self.booted[c] = self._boot(c)
        return self.booted[case]

    def close(self) -> None:
        for b in self.booted.values():
            b.stop()


@pytest.fixture(scope="module")
def fleet(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Fleet]:
    if not ardupilot_sitl.available():
        pytest.skip(SKIP_REASON)
    cases = []
    for item in request.session.items:  # only the selected tests' instances
        if item.module is request.module and "fleet" in getattr(item, "fixturenames", ()):
            spec = getattr(item, "callspec", None)
            cases.append(spec.params["case"] if spec is not None else "configure")
    f = Fleet(cases, tmp_path_factory)
    try:
        yield f
    finally:
        f.close()


def _run(fleet: Fleet, case: str) -> CheckReport[ArduPilotContext]:
    sc, b = SCENARIOS[case], fleet.get(case)
    try:
        _wait_ekf(b.sender, b.booted_s, 25.0)
        return asyncio.run(run_check(_config(b.tmp, b.instance, sc.set_origin), _opts(b.instance)))
    finally:
        b.stop()


@real
@pytest.mark.timeout(120)
@pytest.mark.parametrize("case", list(SCENARIOS))
def test_real_ardupilot_gives_each_set_up_its_verdict(fleet: Fleet, case: str) -> None:
    sc = SCENARIOS[case]
    report = _run(fleet, case)
    text = format_check(report)
    assert report.autopilot == "ArduPilot", text
    v = report.verdict
    assert v is not None, text
    if sc.fused:
        assert v.fused is True and v.ok, text
        assert report.problems == 0, text
        assert all(r.status is not Status.FAIL for r in report.rows), text
        return
    assert report.problems > 0, text
    assert v.reasons and sc.reason in v.reasons[0], text
    if case != "gps_and_vision":  # GPS velocity with our position: fused, but mixed
        assert v.fused is False, text
    if sc.row is not None:
        name, status = sc.row
        assert any(r.name == name and r.status is status for r in report.rows), text


@real
@pytest.mark.timeout(120)
def test_real_ardupilot_configure_writes_and_reads_back(fleet: Fleet) -> None:
    """A broken parameter set (VISO_ORIENT, VISO_SCALE, VISO_QUAL_MIN, EK3_SRC1_VELXY from GPS):
    configure plans exactly those, writes them, reads each back, and check is clean after."""
    b = fleet.get("configure")
    cfg = _config(b.tmp, b.instance)
    try:
        _wait_ekf(b.sender, b.booted_s, 15.0)
        report = asyncio.run(run_configure(cfg, _opts(b.instance, yes=True), show=lambda s: None))
        after = asyncio.run(run_check(cfg, _opts(b.instance, watch_s=0.0)))
    finally:
        b.stop()
    planned = {c.target.name: c.target.value for c in report.planned}
    assert planned == {"VISO_ORIENT": 0, "VISO_SCALE": 1.0, "VISO_QUAL_MIN": 0, "EK3_SRC1_VELXY": 6}
    assert report.written and all(c.ok for c in report.changes), report.changes
    assert {c.target.name: c.after for c in report.changes} == planned
    assert not [r for r in after.rows if r.status is Status.FAIL], format_check(after)


# ------------------------------------------------------------------ the rules alone (pure)
def _params(values: Mapping[str, float]) -> dict[str, Param]:
    ints = {k for k in values if not k.endswith(("_NSE", "_SCALE"))}
    return {k: Param(k, int(v) if k in ints else float(v), k in ints) for k, v in values.items()}


BASE = {
    **RIGHT,
    "VISO_POS_X": 0.0,
    "VISO_POS_Y": 0.0,
    "VISO_POS_Z": 0.0,
    "VISO_ORIENT": 0,
    "VISO_SCALE": 1.0,
    "VISO_DELAY_MS": 10,
    "VISO_QUAL_MIN": 0,
    "MAV_SYSID": 1,
    "ARMING_CHECK": 1,
}


def _row(rows: list[Any], name: str) -> Any:
    return next(r for r in rows if r.name == name)


def test_rules_vpe_needs_no_velocity_source_and_quality_min_0() -> None:
    ctx = ArduPilotContext(output="vision_position_estimate", set_origin=True)
    rows = evaluate(_params({**BASE, "VISO_QUAL_MIN": 10}), ctx)
    assert _row(rows, "VISO_QUAL_MIN").status is Status.FAIL
    assert _row(rows, "EK3_SRC1_VELXY").status is Status.FAIL  # 6 with VPE: never comes
    ok = evaluate(_params({**BASE, "EK3_SRC1_VELXY": 0, "EK3_SRC1_VELZ": 0}), ctx)
    assert not [r for r in ok if r.status is Status.FAIL], ok


def test_rules_rangefinders_from_the_autopilot_must_exist_and_point_down() -> None:
    ctx = ArduPilotContext(autopilot_sensor_ids=(0, 1), set_origin=True)
    rows = evaluate(
        _params({**BASE, "RNGFND1_TYPE": 100, "RNGFND1_ORIENT": 0, "RNGFND2_TYPE": 0}), ctx
    )
    assert _row(rows, "RNGFND1_ORIENT").status is Status.FAIL
    assert _row(rows, "RNGFND1_ORIENT").targets[0].value == rules.ORIENT_DOWN
    assert _row(rows, "RNGFND2_TYPE").status is Status.FAIL


def test_rules_delay_follows_the_service_latency() -> None:
    ctx = ArduPilotContext(latency_ms=45.0, set_origin=True)
    row = _row(evaluate(_params(BASE), ctx), "VISO_DELAY_MS")
    assert row.status is Status.WARN and row.targets[0].value == 45
    ok = _row(evaluate(_params({**BASE, "VISO_DELAY_MS": 40}), ctx), "VISO_DELAY_MS")
    assert ok.status is Status.OK


def test_rules_system_id_mismatch_and_no_origin_fail() -> None:
    ctx = ArduPilotContext(system_id=2, origin_seen=False)
    rows = evaluate(_params(BASE), ctx)
    assert _row(rows, "MAV_SYSID").status is Status.FAIL
    assert _row(rows, "EKF origin").status is Status.FAIL
