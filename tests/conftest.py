"""Shared fixtures: seeded worlds are expensive to build, so build each once per session."""

from __future__ import annotations

import contextlib
import os
import tempfile
import time
from collections.abc import Callable, Iterator
from functools import cache
from pathlib import Path

import pytest
from peers import (
    AUTOPILOTS_LOCK_ENV,
    MACHINE_LOCK_ENV,
    hold_autopilots,
    hold_machine,
    release_autopilots,
    release_machine,
    waited_s,
)

# matplotlib's FreeType module is loaded before anything in this process can load GStreamer:
# once GStreamer was initialised (its plugins bring the system's libfreetype), the first
# `import matplotlib.ft2font` (any plot) aborted the whole pytest process (SIGABRT, reproduced:
# tests/drivers/camera/test_camera_gst.py, then the ArduPilot loop's plot). Loading it first
# avoids that, whatever order the tests run in.
with contextlib.suppress(ImportError):  # no eval extra: nothing plots, nothing to protect
    import matplotlib.ft2font  # noqa: F401

from companion.config import Config, load_config
from companion.sitl.world.terrain import World, make_world


@cache
def _world(name: str, seed: int) -> World:
    return make_world(name, seed)


@pytest.fixture(scope="session")
def world() -> Callable[[str, int], World]:
    """world(name, seed) -> a cached World."""
    return _world


@pytest.fixture(scope="session")
def default_config() -> Config:
    """The built-in (SITL) configuration."""
    return load_config()


# `make test` runs the suite on two pytest-xdist workers (`--dist loadgroup`; `make test
# PYTEST_WORKERS=0`: serial).
# Tests that must not run beside each other, or that share an expensive module fixture, go to
# one worker together as one work unit (run one after the other there):
# - "autopilots": every test that starts a real PX4 or ArduPilot SITL. They use fixed instance
#   numbers and ports (PX4 1 and free_instance()'s 5-9, whose probe-then-start would race
#   between workers; ArduPilot 2, 3, 4 and 10-14), the launchers unpack their runtimes into one
#   cache on first use, and two autopilot flights at once would share two cores four ways.
# - a module whose module-scoped fixture is expensive (ArduPilot's fleet of six, calibration
#   flights, rendered datasets) stays on one worker, so that the fixture is built once.
# The groups are given here by module (and test) name, through xdist's scheduler hook: xdist's
# own `xdist_group` marks rename the items' node ids, which pytest >= 9.2 no longer lets a
# plugin do (the marks are silently ignored there: every test became its own unit).
_AUTOPILOTS = "autopilots"
_GROUP_OF_MODULE = {
    "test_px4_loop.py": _AUTOPILOTS,
    "test_px4_gps_hover.py": _AUTOPILOTS,
    "test_px4_real.py": _AUTOPILOTS,
    "test_ardupilot_check.py": _AUTOPILOTS,
    "test_ardupilot_loop.py": _AUTOPILOTS,
    "test_ardupilot_service.py": _AUTOPILOTS,
    "test_calibration.py": "test_calibration.py",
    "test_dataset.py": "test_dataset.py",
    "test_evaluation.py": "test_evaluation.py",
    "test_frame_check.py": "test_frame_check.py",
}
_MACHINE_EXCLUSIVE = {"test_px4_loop.py", "test_px4_gps_hover.py", "test_ardupilot_loop.py"}
# single tests that hold the machine alone for their whole run (FILE::TEST, parameters aside)
_MACHINE_EXCLUSIVE_TESTS = {
    # PX4 converts our stamps only while our TIMESYNC answers come back within its round-trip
    # limit: beside the other worker's CPU-bound tests they did not, not once in 190 s
    # (2026-12-01, the suite at aeb95be; 18-124 s to converge in the runs before)
    "test_px4_real.py::test_real_px4_time_sync_reported_converged_once_px4_converts_our_stamps",
}
_GROUP_OF_TEST = {
    "test_statustext_delivery.py::"
    "test_real_px4_forwards_our_statustext_to_its_ground_station_port": _AUTOPILOTS,
}


def _file_name(nodeid: str) -> str:
    """A test's file name: the keys above (file names are unique in tests/)."""
    return nodeid.split("::", 1)[0].rsplit("/", 1)[-1]


def _test_name(nodeid: str) -> str:
    """FILE::TEST of a node id, without its parameters."""
    return _file_name(nodeid) + "::" + nodeid.split("::", 1)[-1].split("[", 1)[0]


def machine_alone(nodeid: str) -> bool:
    """Whether a test holds the machine alone for its whole run."""
    return (
        _file_name(nodeid) in _MACHINE_EXCLUSIVE or _test_name(nodeid) in _MACHINE_EXCLUSIVE_TESTS
    )


def xdist_unit(nodeid: str) -> str:
    """The work unit of a test under `--dist loadgroup`: its group, else the test itself."""
    test = _file_name(nodeid) + "::" + nodeid.split("::", 1)[-1]
    return _GROUP_OF_TEST.get(test) or _GROUP_OF_MODULE.get(_file_name(nodeid)) or nodeid


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist (absent: nothing calls it)
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object:
    """Load scheduling by work units (xdist_unit), handed out in the workers' collection order
    (pytest_collection_modifyitems below puts the long ones first)."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class ByUnit(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return xdist_unit(nodeid)

    config.option.loadscopereorder = False  # not by the number of tests: by our order
    return ByUnit(config, log)


def pytest_configure(config: pytest.Config) -> None:
    """The machine's locks (tests/peers/): one pair per machine and user, in the system's
    temp folder, so that the workers of this run and any other run of the suite on this
    machine share them (an environment that sets them already keeps its own)."""
    folder = Path(tempfile.gettempdir()) / f"companion-tests-{os.getuid()}"
    folder.mkdir(mode=0o700, exist_ok=True)
    os.environ.setdefault(MACHINE_LOCK_ENV, str(folder / "machine.lock"))
    os.environ.setdefault(AUTOPILOTS_LOCK_ENV, str(folder / "autopilots.lock"))


@pytest.hookimpl(tryfirst=True)  # before the test's fixtures (module fixtures render too)
def pytest_runtest_setup(item: pytest.Item) -> None:
    """Every test holds the machine shared, a closed loop with a real autopilot alone; a SITL
    flight asks for it alone once its camera is prerendered (tests/peers/). The real
    autopilots' tests first hold their instance numbers against another run of the suite."""
    if xdist_unit(item.nodeid) == _AUTOPILOTS:
        hold_autopilots()
    hold_machine(exclusive=machine_alone(item.nodeid))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    try:
        return (yield)
    finally:
        release_machine()
        if nextitem is None or xdist_unit(nextitem.nodeid) != _AUTOPILOTS:
            release_autopilots()  # the autopilots' module fixtures were torn down above
        if log := os.environ.get("COMPANION_TEST_WAIT_LOG"):  # where the suite's time goes
            with open(log, "a") as fh:  # one line per test: worker, test, seconds waited
                worker = os.environ.get("PYTEST_XDIST_WORKER", "-")
                fh.write(f"{worker}\t{item.nodeid}\t{waited_s():.2f}\t{time.time():.2f}\n")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """On xdist workers, the real autopilots first (about 6 min of flights and checks, one
    after the other on one worker, the longest unit), then the rest in file order, which
    spreads the SITL flights (test_e2e, test_faults, test_recorder, test_robustness,
    test_statustext) among the CPU-bound tests that run beside them. The sort is stable and
    depends on the items alone: every worker collects the same order, as xdist requires, and
    a module's tests stay together (their module fixtures are built once)."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return

    def rank(item: pytest.Item) -> int:
        if _file_name(item.nodeid) in _MACHINE_EXCLUSIVE:
            return 0  # at the start: the other worker waits for them once, not mid-test
        return 1 if xdist_unit(item.nodeid) == _AUTOPILOTS else 2

    items.sort(key=rank)
