"""The processes of a closed loop (``companion sitl px4 | ardupilot``): started in their own
process groups with their output in a log, stopped in reverse order; how to run ``companion``
from this interpreter; the signal handler that stops a flight as Ctrl-C does.
"""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]


# The loop puts three machines' work on one: the autopilot with its simulated vehicle, the
# world's camera and sensors (the bridge) and the companion. On a vehicle they never compete
# for a core; here, on a busy 2-core host, the companion's load starved PX4 itself (its
# receipt of our messages 100-1,200 ms late, EKF2 refusing them as too old: 2026-11-27, bfdc1dc).
# The companion runs at a lower priority, so that when the host is short of CPU it is the
# companion that drops frames (counted and reported), not the world or the autopilot.
SERVICE_NICE = 5
BRIDGE_NICE = 5


class Procs:
    """The processes this run started (own process groups), stopped in reverse order."""

    def __init__(self) -> None:
        self.items: list[tuple[str, subprocess.Popen[bytes], int]] = []

    def start(
        self, name: str, argv: list[str], log: Path, nice: int = 0, **kw: Any
    ) -> subprocess.Popen[bytes]:
        """Start ``argv`` in its own session, output to ``log``; ``nice`` > 0 lowers its CPU
        priority (every thread it starts inherits it)."""
        fh = log.open("wb")
        pre = functools.partial(os.nice, nice) if nice else None
        p = subprocess.Popen(
            argv,
            stdout=fh,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            preexec_fn=pre,  # only os.nice: takes no lock in the forked child
            **kw,
        )
        fh.close()
        self.items.append((name, p, signal.SIGTERM))
        return p

    def stop(self, name: str, sig: int = signal.SIGTERM, timeout_s: float = 15.0) -> None:
        for n, p, _ in self.items:
            if n == name and p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, sig)
                try:
                    p.wait(timeout_s)
                except subprocess.TimeoutExpired:
                    with contextlib.suppress(ProcessLookupError):
                        os.killpg(p.pid, signal.SIGKILL)
                    p.wait(5)

    def stop_all(self) -> None:
        for name, _, _ in reversed(self.items):
            self.stop(name)


def companion_argv() -> list[str]:
    """How to run ``companion`` from this interpreter (its script, else ``-m companion.cli``)."""
    exe = Path(sys.executable).parent / "companion"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "companion.cli"]


def raise_interrupt(signum: int, frame: Any) -> None:
    """A signal handler (SIGTERM) that stops the flight as Ctrl-C does."""
    raise KeyboardInterrupt
