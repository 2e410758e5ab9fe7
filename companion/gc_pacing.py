"""Python's cyclic garbage collector run between frames, not inside them.

CPython collects its youngest generation after ``threshold0`` (700) net allocations of
container objects, the middle one after ``threshold1 + 1`` (11) of those and the oldest after
``threshold2 + 1`` of those: wherever the allocation that crosses the line happens, that thread
stops and every other one waits on the GIL, the worker in the middle of a frame's pose too.
Measured (docs/decisions.md, "The garbage collector between frames"): the oldest generation
takes 15 ms in the service, 34-54 ms in the SITL autopilot's process, 37-46 ms in ``companion
bench vo``'s (the simulated world in it); the middle one about 1 ms.

:class:`GcPacing` keeps CPython's own schedule and moves it to a safe moment: at its first
:meth:`~GcPacing.after_frame` one full collection, then ``gc.freeze()`` (everything built at
start-up, the config, the pipeline, a simulated world, goes to the permanent generation that no
later collection scans); the youngest generation's automatic threshold is raised ``NET`` times
(the older ones count its collections), a net that still collects in a process whose frames
stopped; after each frame's work the collections the old thresholds would have made by then
(``gc.get_count()`` against them), oldest first.
:meth:`~GcPacing.close` gives the thresholds back and unfreezes. One pacer is active at a time
in a process (a second one does nothing): the collector and its thresholds are the process's.

Nothing computed changes: a collection frees unreachable cycles only, whenever it runs.
"""

from __future__ import annotations

import gc
import threading
import time
from typing import Any

NET = 100  # the automatic thresholds' factor while a pacer runs
GC_STAGE = "garbage collection"  # its name among the stages after the pose (a benchmark's)
_active_lock = threading.Lock()
_active: list[GcPacing] = []  # the pacer that holds the collector (at most one)


class GcPacing:
    """The collector's work after each frame (:meth:`after_frame`) instead of inside it.

    paced (3,): collections this pacer ran, by generation; paced_ms_max: the longest [ms];
    automatic: collections that started anywhere else while it was active (the net's, or a
    ``gc.collect()`` of other code); active: whether this pacer holds the collector."""

    def __init__(self) -> None:
        self.paced = [0, 0, 0]
        self.paced_ms_max = 0.0
        self.automatic = 0
        self.active = False
        self._thresholds = gc.get_threshold()
        self._started = False
        self._froze = False
        self._in_pace = False

    def after_frame(self) -> None:
        """Call after a frame's work (its pose out): the collections that are due."""
        if not self._started:
            self.start()
        if not self.active:
            return
        # CPython's order (Modules/gcmodule.c, collect_generations): the oldest generation
        # whose count passed its threshold; a generation's count is the collections of the
        # one below it since its own last (generation 0's: net allocations)
        counts = gc.get_count()
        for generation in (2, 1, 0):
            if counts[generation] > self._thresholds[generation] > 0:
                self._collect(generation)
                return

    def close(self) -> None:
        """The collector as it was: its thresholds back, the frozen objects unfrozen."""
        with _active_lock:
            if not self.active:
                return
            self.active = False
            _active.remove(self)
            gc.callbacks.remove(self._watch)
            gc.set_threshold(*self._thresholds)
            if self._froze:
                gc.unfreeze()

    def __enter__(self) -> GcPacing:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        """Take the collector (the first :meth:`after_frame` does, if not called before):
        one full collection, the survivors frozen, the youngest generation's automatic
        threshold raised."""
        self._started = True
        with _active_lock:
            if _active or not gc.isenabled():
                return  # another pacer, or a process that runs its own collections
            _active.append(self)
            self.active = True
            self._thresholds = gc.get_threshold()
            self._in_pace = True
            try:
                gc.collect()
            finally:
                self._in_pace = False
            self._froze = gc.get_freeze_count() == 0  # else another part of the process froze
            if self._froze:
                gc.freeze()
            t0, t1, t2 = self._thresholds
            gc.set_threshold(t0 * NET, t1, t2)
            gc.callbacks.append(self._watch)

    def _collect(self, generation: int) -> None:
        self._in_pace = True
        t_start = time.perf_counter()
        try:
            gc.collect(generation)
        finally:
            self._in_pace = False
        self.paced[generation] += 1
        self.paced_ms_max = max(self.paced_ms_max, (time.perf_counter() - t_start) * 1e3)

    def _watch(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start" and not self._in_pace:
            self.automatic += 1

    def summary(self) -> str:
        """One line: the collections paced between frames and those that were not."""
        g0, g1, g2 = self.paced
        return (
            f"garbage collection between frames: {g0} + {g1} + {g2} (generations 0, 1, 2), "
            f"longest {self.paced_ms_max:.1f} ms; {self.automatic} elsewhere"
        )
