"""Laps (companion/vo/stage_times.py): each stage is charged the time since the one before."""

from __future__ import annotations

import time

from companion.vo.stage_times import Laps


def test_laps_charge_each_stage_its_own_time_add_repeats_and_start_anew() -> None:
    laps = Laps()
    laps.start()
    time.sleep(0.02)
    laps.lap("slow")
    laps.lap("fast")
    time.sleep(0.01)
    laps.lap("slow")  # a stage that runs twice in a frame: its times add
    first = laps.ms
    assert list(first) == ["slow", "fast"]
    assert first["slow"] >= 30.0 - 1.0  # sleep never returns early (1 ms for the clock's grain)
    assert 0.0 <= first["fast"] < first["slow"]
    laps.start()
    assert laps.ms == {} and first["slow"] >= 29.0  # a reader's dict is not cleared
