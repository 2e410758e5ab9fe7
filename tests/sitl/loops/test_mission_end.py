"""The closed loops' mission end (sitl/loops/loop_flight.py, ``LoopFlight._settle_over``): the
landing waits until the autopilot's own position has settled over the last waypoint."""

from __future__ import annotations

import time
from collections.abc import Callable
from types import SimpleNamespace

import numpy as np
import pytest

import companion.sitl.loops.loop_flight as lc
from companion.sitl.loops.processes import REPO


class FakeGcs:
    """pump() advances real time a little and reports the autopilot's LOCAL_POSITION_NED as
    ``path(t)`` (t since the first pump) at 20 Hz, as the loops' ground station records it."""

    def __init__(self, tel: lc.LoopTelemetry, path: Callable[[float], np.ndarray]) -> None:
        self.tel, self.path = tel, path
        self.setpoint: tuple[np.ndarray, np.ndarray] | None = None
        self.t0: float | None = None

    def pump(self, seconds: float) -> None:
        end = time.monotonic() + max(seconds, 0.05)
        while time.monotonic() < end:
            now = time.monotonic()
            self.t0 = now if self.t0 is None else self.t0
            p = self.path(now - self.t0)
            self.tel.lpos.append((time.monotonic_ns(), 0, *(float(x) for x in p)))
            time.sleep(0.05)


def flight(path: Callable[[float], np.ndarray]) -> lc.LoopFlight:
    f = lc.LoopFlight(SimpleNamespace(out=REPO))
    f.gcs = FakeGcs(f.tel, path)
    f._check_alive = lambda: None  # type: ignore[method-assign]
    return f


def test_the_landing_waits_until_the_braking_overshoot_has_come_back() -> None:
    home = np.array([0.0, 0.0, -5.0])

    def overshoot(t: float) -> np.ndarray:  # 1.2 m past home, back with a 0.3 s time constant
        return home + np.array([0.0, -1.2 * np.exp(-t / 0.3), 0.0])

    f = flight(overshoot)
    t0 = time.monotonic()
    f._settle_over(home)
    waited = time.monotonic() - t0
    assert f.gcs.setpoint is not None and np.allclose(f.gcs.setpoint[0], home)
    assert not f.notes
    # within 0.15 m from t = 0.3 ln(1.2 / 0.15) = 0.62 s, then a whole second of it
    assert waited >= lc.SETTLE_S + 0.5, waited
    last = np.array([r[2:5] for r in f.tel.lpos[-5:]])
    assert np.all(np.hypot(last[:, 0], last[:, 1]) <= lc.SETTLE_M)


def test_a_vehicle_that_never_settles_lands_after_the_timeout_with_a_note(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(lc, "SETTLE_TIMEOUT_S", 2.0)
    home = np.zeros(3)
    f = flight(lambda t: home + np.array([0.3 * np.sin(2.0 * t), 0.0, 0.0]))  # +-0.3 m
    t0 = time.monotonic()
    f._settle_over(home)
    assert time.monotonic() - t0 >= 2.0
    assert f.notes and "did not settle" in f.notes[0]
