"""The chunks a serial reader thread hands over to the event loop (drivers/mavlink.py).

The reader thread hands each chunk over as it arrives, stamped then; the event loop parses at
most SERIAL_TURN_BYTES per turn (bounded work per wake-up: a byte flood faster than the parser
cannot starve the loop, its signal handlers or its timers), and at most SERIAL_BACKLOG_BYTES
wait (1.4 s at 921600 baud): beyond it the oldest are dropped, counted.
"""

from __future__ import annotations

import threading
from collections import deque

from companion.drivers.mavlink_parser import LinkStats

SERIAL_TURN_BYTES = 4096
SERIAL_BACKLOG_BYTES = 131072


class SerialBacklog:
    """Chunks (arrival time [ns, our monotonic clock], bytes) handed over by a reader thread
    and not parsed yet; thread-safe. ``wake_pending``: a drain is scheduled on the loop."""

    def __init__(self) -> None:
        self.chunks: deque[tuple[int, bytes]] = deque()
        self.backlog_bytes = 0
        self.lock = threading.Lock()
        self.wake_pending = False

    def hand_over(self, data: bytes, rx_ns: int, stats: LinkStats) -> bool:
        """Queue a chunk the reader thread read at ``rx_ns``; the oldest queued bytes go
        (counted in ``stats.rx_overflow_bytes``) beyond SERIAL_BACKLOG_BYTES. True when the
        loop must be woken for it (no wake-up pending: one at a time, so a flood cannot fill
        the loop's queue)."""
        with self.lock:
            self.chunks.append((rx_ns, data))
            self.backlog_bytes += len(data)
            while self.backlog_bytes > SERIAL_BACKLOG_BYTES and len(self.chunks) > 1:
                _, old = self.chunks.popleft()
                self.backlog_bytes -= len(old)
                stats.rx_overflow_bytes += len(old)
            wake = not self.wake_pending
            self.wake_pending = True
        return wake

    def take(self, budget: int, closing: bool) -> tuple[int, bytes] | None:
        """The oldest chunk with its stamp, at most ``budget`` bytes of it (the rest stays,
        with the same stamp); None when nothing waits or the link is ``closing`` (the pending
        wake-up is then over)."""
        with self.lock:
            if not self.chunks or closing:
                self.wake_pending = False
                return None
            rx_ns, data = self.chunks.popleft()
            if len(data) > budget:
                self.chunks.appendleft((rx_ns, data[budget:]))
                data = data[:budget]
            self.backlog_bytes -= len(data)
        return rx_ns, data
