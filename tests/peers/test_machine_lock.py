"""The suite's own machine locks (tests/peers/): what keeps two runs of `make test` on one
machine from flying their flights beside each other or taking each other's autopilot ports."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

import peers
from peers import AUTOPILOTS_LOCK_ENV, _not_counted

TESTS = Path(__file__).parents[1]  # where `import peers` finds the package
# a process standing for one test run: it holds the autopilots' lock, says so, and on a line
# from its stdin writes a marker file and lets the lock go; or (argv "probe") takes the lock
# and reports whether the first one's marker was there when it got it
RUN = """
import sys
from pathlib import Path
import peers
marker = Path(sys.argv[1])
peers.hold_autopilots(poll_s=0.02)
if sys.argv[2] == "probe":
    print("after the other" if marker.exists() else "beside the other", flush=True)
else:
    print("held", flush=True)
    sys.stdin.readline()
    marker.write_text("released")
    peers.release_autopilots()
"""


def _run(marker: Path, role: str, env: dict[str, str]) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", RUN, str(marker), role],
        cwd=TESTS,
        env=env,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )


def test_a_second_run_waits_for_the_first_runs_autopilots(tmp_path: Path) -> None:
    """Two processes on one lock file (as two runs' workers are on the machine's): the second
    gets the autopilots only after the first let them go."""
    env = {**os.environ, AUTOPILOTS_LOCK_ENV: str(tmp_path / "autopilots.lock")}
    marker = tmp_path / "first-released"
    first = _run(marker, "hold", env)
    second = None
    try:
        assert first.stdout is not None and first.stdout.readline().strip() == "held"
        second = _run(marker, "probe", env)
        time.sleep(0.5)  # room for a broken lock to let the second one in beside the first
        assert first.stdin is not None
        first.stdin.write("\n")
        first.stdin.flush()
        assert second.stdout is not None
        assert second.stdout.readline().strip() == "after the other"
    finally:
        for p in (first, second):
            if p is not None:
                p.kill()
                p.communicate()


def test_a_wait_for_the_machine_is_not_counted_in_the_tests_time_limit() -> None:
    """pytest-timeout (signal method, pyproject's 600 s) arms ITIMER_REAL for every test; a
    wait for a lock moves it on by the wait, so a flight's limit is its own work's."""
    remaining_s, interval_s = signal.getitimer(signal.ITIMER_REAL)
    assert remaining_s > 0, "no pytest-timeout alarm: the suite's limits are not armed"
    try:
        _not_counted(time.monotonic() - 30.0)  # as if this test had waited 30 s for the lock
        extended_s, _ = signal.getitimer(signal.ITIMER_REAL)
        assert extended_s > remaining_s + 29.0
    finally:
        signal.setitimer(signal.ITIMER_REAL, remaining_s, interval_s)


def test_a_wait_longer_than_the_tests_limit_does_not_end_the_test(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The alarm moves on while the test waits, not only once it has the lock: here the other
    run holds the autopilots 2.5 s against a limit of 1 s left (three tests of the second of
    two runs on 2026-11-27 ended in their wait so, 60-300 s)."""
    env = {**os.environ, AUTOPILOTS_LOCK_ENV: str(tmp_path / "autopilots.lock")}
    monkeypatch.setenv(AUTOPILOTS_LOCK_ENV, env[AUTOPILOTS_LOCK_ENV])
    monkeypatch.setattr(peers, "_autopilots", [])  # this worker's own hold, if any, aside
    other = _run(tmp_path / "released", "hold", env)
    remaining_s, interval_s = signal.getitimer(signal.ITIMER_REAL)
    assert remaining_s > 0, "no pytest-timeout alarm: the suite's limits are not armed"
    try:
        assert other.stdout is not None and other.stdout.readline().strip() == "held"
        threading.Timer(2.5, _release, (other,)).start()
        signal.setitimer(signal.ITIMER_REAL, 1.0, interval_s)  # 1 s left of this test's limit
        t0 = time.monotonic()
        peers.hold_autopilots(poll_s=0.05)  # pytest-timeout fails the test here if it fires
        waited_s = time.monotonic() - t0
        left_s, _ = signal.getitimer(signal.ITIMER_REAL)
        peers.release_autopilots()
        assert waited_s >= 2.0 and left_s > 0.5  # the wait was given back as it went
    finally:
        signal.setitimer(signal.ITIMER_REAL, remaining_s, interval_s)
        other.kill()
        other.communicate()


def _release(holder: subprocess.Popen[str]) -> None:
    assert holder.stdin is not None
    holder.stdin.write("\n")
    holder.stdin.flush()
