"""The garbage collector paced between frames (companion/gc_pacing.py): it still frees every
cycle, on CPython's own schedule, never inside a frame, and leaves the collector as it was."""

from __future__ import annotations

import gc
import weakref

import pytest

from companion.cli.sim import flight_events, scenario
from companion.config import load_config
from companion.gc_pacing import GC_STAGE, GcPacing
from companion.offline import run_vo


class Node:
    """A reference cycle: only the cyclic collector frees it."""

    def __init__(self) -> None:
        self.me = self
        self.payload = [[] for _ in range(20)]  # tracked containers, as a frame makes them


def frame_of_garbage(n_cycles: int) -> list[weakref.ref[Node]]:
    """One 'frame' that leaves n_cycles unreachable cycles behind."""
    return [weakref.ref(Node()) for _ in range(n_cycles)]


@pytest.fixture
def collector_as_found():
    """The collector's state before the test, checked to be the same after it."""
    before = (gc.isenabled(), gc.get_threshold(), gc.get_freeze_count())
    yield before
    gc.enable()
    assert (gc.isenabled(), gc.get_threshold(), gc.get_freeze_count()) == before


def test_cycles_are_freed_between_frames_never_inside_them(collector_as_found) -> None:
    """Frames that leave cycles behind: every collection is the pacer's (none starts inside a
    frame), the old generations are collected on CPython's schedule (a middle one after every
    ``threshold1 + 1`` young ones, an old one after ``threshold2 + 1`` middle ones), the cycles
    are freed: the live ones stay bounded however many frames run."""
    _, t1, t2 = collector_as_found[1]
    started: list[int] = []

    def watch(phase: str, info: dict) -> None:
        if phase == "start":
            started.append(info["generation"])

    gc.callbacks.append(watch)
    try:
        with GcPacing() as pacer:
            pacer.start()  # the start-up's objects frozen
            refs: list[weakref.ref[Node]] = []
            during = []
            for _ in range(400):
                n_before = len(started)
                refs += frame_of_garbage(60)  # ~1,300 tracked objects: 2x threshold0
                during.append(len(started) - n_before)
                pacer.after_frame()
            live = sum(r() is not None for r in refs)
    finally:
        gc.callbacks.remove(watch)
    assert pacer.automatic == 0 and sum(during) == 0  # nothing inside a frame
    g0, g1, g2 = pacer.paced
    assert g0 + g1 + g2 >= 399  # ~every frame's garbage passes threshold0 once
    # CPython collects a generation once its count (the younger one's collections since its
    # last) *exceeds* its threshold: one middle collection after threshold1 + 1 young ones
    assert g1 == pytest.approx(g0 / (t1 + 1), abs=1)
    assert g2 == pytest.approx(g1 / (t2 + 1), abs=1) and g2 >= 2
    assert live <= 60 * (t1 + 2)  # at most the frames since the last middle collection
    assert len(refs) == 24_000


def test_a_second_pacer_and_a_disabled_collector_are_left_alone(collector_as_found) -> None:
    """One pacer holds the collector; a second one in the process, or one in a process that
    disabled the collector (it runs its own collections), changes nothing."""
    with GcPacing() as first, GcPacing() as second:
        first.after_frame()
        second.after_frame()
        assert first.active and not second.active
        assert gc.get_threshold()[0] == 100 * collector_as_found[1][0]
        assert gc.get_freeze_count() > 0  # the start-up's objects frozen
    assert gc.get_threshold() == collector_as_found[1]
    gc.disable()
    try:
        with GcPacing() as pacer:
            frame_of_garbage(10)
            pacer.after_frame()
            assert not pacer.active and pacer.paced == [0, 0, 0]
            assert not gc.isenabled()
    finally:
        gc.enable()


def test_an_offline_run_collects_only_after_its_frames(collector_as_found) -> None:
    """``run_vo`` (eval, bench vo) paces the collector as the service does: the whole run's
    collections after the frames' work, timed as a stage after the pose."""
    cfg = load_config(overrides={"sitl": {"terrain": "hills", "seconds": 4.0}})
    run = run_vo(cfg, flight_events(scenario(cfg)))
    assert run.gc.endswith("; 0 elsewhere"), run.gc
    assert run.gc.startswith("garbage collection between frames: ")
    assert len(run.stage_ms) == 120 and all(GC_STAGE in s for s in run.stage_ms)
    assert run.resets == 0 and run.tracking_mask().mean() > 0.8
