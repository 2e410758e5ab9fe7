"""Every test that starts a real autopilot runs in the "autopilots" work unit (tests/conftest.py):
one after the other on one worker, holding the autopilots' lock, so that no two PX4 or
ArduPilot SITLs share instance numbers or the two cores. A module that names a real autopilot
and is missing from the group would fly beside the rest of the suite (a closed-loop flight
under load: PX4's lockstep clock drifts, heartbeats arrive late)."""

from __future__ import annotations

import re
from pathlib import Path

import conftest

TESTS = Path(__file__).resolve().parent
# what a test module uses to start a real autopilot
REAL_AUTOPILOT = re.compile(
    r"SHARED_PX4|SHARED_ARDUPILOT|px4_peer|Px4Sitl|ArduPilotSitl|peers\.ardupilot|ardupilot_sitl\."
)


def _modules_that_start_an_autopilot() -> list[Path]:
    return sorted(
        p
        for p in TESTS.rglob("test_*.py")
        if p != Path(__file__) and REAL_AUTOPILOT.search(p.read_text())
    )


def test_the_scan_finds_the_autopilot_modules() -> None:
    names = {p.name for p in _modules_that_start_an_autopilot()}
    assert {"test_px4_loop.py", "test_px4_real.py", "test_ardupilot_loop.py"} <= names, names


def test_every_test_that_starts_a_real_autopilot_is_in_the_autopilots_unit() -> None:
    for path in _modules_that_start_an_autopilot():
        rel = path.relative_to(TESTS.parent).as_posix()
        source = path.read_text()
        tests = re.findall(r"^(?:async )?def (test_\w+)", source, flags=re.M)
        starting = [
            t
            for t in tests
            if REAL_AUTOPILOT.search(_body(source, t)) or conftest._GROUP_OF_MODULE.get(path.name)
        ]
        if REAL_AUTOPILOT.search(source.split("\ndef ", 1)[0]):  # module-level: all of them
            starting = tests
        for t in starting:
            assert conftest.xdist_unit(f"{rel}::{t}") == conftest._AUTOPILOTS, (
                f"{rel}::{t} starts a real autopilot but is not in the autopilots unit "
                "(tests/conftest.py, _GROUP_OF_MODULE / _GROUP_OF_TEST)"
            )


def test_closed_loop_flights_have_the_machine_alone() -> None:
    loops = {p.name for p in (TESTS / "sitl" / "loops").glob("test_*.py")}
    flying = {n for n in loops if conftest._GROUP_OF_MODULE.get(n) == conftest._AUTOPILOTS}
    assert {"test_px4_loop.py", "test_px4_gps_hover.py", "test_ardupilot_loop.py"} <= flying
    assert flying <= conftest._MACHINE_EXCLUSIVE, flying - conftest._MACHINE_EXCLUSIVE


def test_the_single_tests_that_hold_the_machine_alone_exist() -> None:
    for name in conftest._MACHINE_EXCLUSIVE_TESTS:
        file, test = name.split("::")
        (path,) = TESTS.rglob(file)
        assert re.search(rf"^def {test}\(", path.read_text(), flags=re.M), name
        assert conftest.machine_alone(f"{path.relative_to(TESTS.parent).as_posix()}::{test}")
    assert not conftest.machine_alone("tests/e2e/test_px4_real.py::test_stub_gives_the_reason")


def _body(source: str, test: str) -> str:
    """The text of one top-level test function (up to the next top-level statement)."""
    start = re.search(rf"^(?:async )?def {test}\b", source, flags=re.M)
    assert start is not None
    rest = source[start.end() :]
    end = re.search(r"^\S", rest, flags=re.M)
    return rest[: end.start()] if end else rest
