"""A peer's clock and one MAVLink message decoded: helpers of the time sync, wire and service
tests."""

from __future__ import annotations

from typing import Any


class PeerClock:
    """A peer clock with an offset and a drift against ours (ns)."""

    def __init__(self, offset_ns: int, drift_ppm: float) -> None:
        self.offset_ns, self.drift = offset_ns, drift_ppm * 1e-6

    def __call__(self, local_ns: int) -> int:
        return int(local_ns * (1 + self.drift)) - self.offset_ns


def decode(buf: bytes) -> Any:
    """The one MAVLink message in ``buf`` (parsed as the link parses; nothing bad in it)."""
    from companion.drivers.mavlink_parser import LinkStats, Parser

    parser = Parser()
    stats = LinkStats()
    msgs = parser.feed(buf, stats)
    assert stats.rx_bad == 0 and len(msgs) == 1
    return msgs[0]
