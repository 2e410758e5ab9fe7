"""Laps (companion/vo/stage_times.py): each stage is charged the time since the one before."""

from __future__ import annotations

import time

from companion.vo.stage_times import Laps


def test_laps_charge_each_stage_its_own_time_add_repeats_and_start_anew() -> None:
    laps = Laps()
    t0 = time.perf_counter()
    laps.start()
    time.sleep(0.02)
    laps.lap("slow")
    laps.lap("fast")
    time.sleep(0.01)
    laps.lap("slow")  # a stage that runs twice in a frame: its times add
    elapsed_ms = (time.perf_counter() - t0) * 1e3
    first = laps.ms
    assert list(first) == ["slow", "fast"]
    assert first["slow"] >= 30.0 - 1.0  # sleep never returns early (1 ms for the clock's grain)
    # no time is charged twice, whatever the load: the laps add up to at most the span
    assert first["fast"] >= 0.0 and first["slow"] + first["fast"] <= elapsed_ms
    laps.start()
    assert laps.ms == {} and first["slow"] >= 29.0  # a reader's dict is not cleared
