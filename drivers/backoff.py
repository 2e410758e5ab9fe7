"""Capped, jittered exponential backoff for reconnecting links (docs/service.md).

``Backoff(first_s, cap_s)``: each ``next_s()`` is the current delay times a uniform factor in
[0.5, 1.5) (so that many vehicles, or many links of one, do not retry in step), and the delay
doubles up to ``cap_s``; ``reset()`` after a success starts again from ``first_s``.
"""

from __future__ import annotations

import random


class Backoff:
    """The delays between attempts of one reconnecting loop."""

    def __init__(self, first_s: float, cap_s: float, rng: random.Random | None = None) -> None:
        if not 0 < first_s <= cap_s:
            raise ValueError(f"backoff: need 0 < first_s <= cap_s, got {first_s}, {cap_s}")
        self.first_s, self.cap_s = first_s, cap_s
        self.delay_s = first_s
        self._rng = rng or random.Random()

    def next_s(self) -> float:
        """The wait before the next attempt [s]; the following one will be up to twice it."""
        wait = self.delay_s * self._rng.uniform(0.5, 1.5)
        self.delay_s = min(self.delay_s * 2.0, self.cap_s)
        return wait

    def reset(self) -> None:
        """After a success: the next failure waits about ``first_s`` again."""
        self.delay_s = self.first_s
