"""Where a frame's time goes: the wall time of each named stage of the last frame.

Read by ``companion bench vo`` (its per-stage table) and by the status; the cost is one
``time.perf_counter()`` call per stage.
"""

from __future__ import annotations

import time


class Laps:
    """The wall time [ms] of the named stages of one frame, in the order they ran.

    :meth:`start` begins a frame (a new dict: a reader holding the last frame's keeps it);
    :meth:`lap` charges the time since the previous lap (or the start) to ``name``, adding
    to it when a stage runs twice in a frame."""

    __slots__ = ("_t", "ms")

    def __init__(self) -> None:
        self.ms: dict[str, float] = {}
        self._t = time.perf_counter()

    def start(self) -> None:
        self.ms = {}
        self._t = time.perf_counter()

    def lap(self, name: str) -> None:
        t = time.perf_counter()
        self.ms[name] = self.ms.get(name, 0.0) + (t - self._t) * 1e3
        self._t = t
