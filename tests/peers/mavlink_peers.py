"""A peer's clock, one MAVLink message decoded and STATUSTEXT chunks joined: helpers of the
time sync, wire, STATUSTEXT and service tests."""

from __future__ import annotations

from typing import Any

from companion.drivers.messages import STATUSTEXT_CHARS


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


def join_chunks(msgs: list[Any]) -> list[tuple[int, str]]:
    """(severity, text) of received STATUSTEXTs, chunks of one id joined (as QGC does)."""
    out: list[tuple[int, str]] = []
    parts: dict[int, list[str]] = {}
    for m in msgs:
        if int(m.id) == 0:
            out.append((int(m.severity), str(m.text)))
            continue
        parts.setdefault(int(m.id), []).append(str(m.text))
        if len(m.text) < STATUSTEXT_CHARS:  # the NUL: the last chunk
            out.append((int(m.severity), "".join(parts.pop(int(m.id)))))
    return out


class EncodingLink:
    """A link that keeps what is sent (the messages, not bytes) and has an encoder: what the
    service's GPS frame and its handover actions use of the link."""

    def __init__(self) -> None:
        from pymavlink.dialects.v20 import common as mavlink

        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
        self.sent: list[Any] = []

    def send(self, msg: Any) -> bool:
        self.sent.append(msg)
        return True
