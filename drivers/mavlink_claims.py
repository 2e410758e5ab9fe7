"""Who claims to be the autopilot on a udpin link: every source address sending frames with
the autopilot's system id (component 1) is tracked (``Claimants``) with the message kinds it
sent over the last CLAIM_WINDOW_S and its HEARTBEATs, so that the link can tell the autopilot's
stream from a spoofer's few forged messages (``Claimants.better_than``)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

# udpin: sources claiming the autopilot's system id (its component 1) are tracked by address
# (at most CLAIMANTS_MAX, the longest silent forgotten first) with the message kinds each sent
# over the last CLAIM_WINDOW_S; see Claimants.better_than for the rule that picks the autopilot
CLAIM_WINDOW_S = 2.0
CLAIMANTS_MAX = 8
CLAIM_KINDS_MAX = 64  # message ids remembered per source (a flood of made-up ids is capped)
HEARTBEAT_CHECK_S = 0.5  # a rival's HEARTBEAT is parsed at most this often
RIVAL_CHECKS_INTERVAL_S = 0.02  # and rivals' HEARTBEATs altogether (a flood from many ports)
RIVAL_LOG_INTERVAL_S = 10.0  # new rivals are logged at most this often (the rest counted)
# an autopilot's stream over CLAIM_WINDOW_S: this many kinds of message or more, and its
# HEARTBEAT at an autopilot's cadence (1 Hz: 1 to HEARTBEATS_IN_WINDOW_MAX of them)
STREAM_KINDS_MIN = 5
HEARTBEATS_IN_WINDOW_MAX = 4
MSG_ID_HEARTBEAT = 0


@dataclass
class Claimant:
    """A UDP source sending frames as the autopilot (its system id, component 1)."""

    first_ns: int  # first heard [ns, our monotonic clock]
    last_ns: int = 0  # last heard
    checked_ns: int = 0  # its last HEARTBEAT parsed and checked (a rival's, rate-limited)
    kinds: dict[int, int] = field(default_factory=dict)  # message id -> last heard [ns]
    # its last HEARTBEAT frames (by header) [ns]
    heartbeats_ns: deque[int] = field(default_factory=lambda: deque(maxlen=8))

    def kinds_since(self, since_ns: int) -> int:
        """How many message kinds it sent since ``since_ns``."""
        return sum(1 for t in self.kinds.values() if t >= since_ns)

    def is_stream(self, now_ns: int) -> bool:
        """Whether it sent an autopilot's stream over the last CLAIM_WINDOW_S: at least
        STREAM_KINDS_MIN kinds of message, and HEARTBEATs at an autopilot's 1 Hz (a flood,
        or a spoofer in a hurry, sends them by the tens or hundreds)."""
        since_ns = now_ns - int(CLAIM_WINDOW_S * 1e9)
        heartbeats = sum(1 for t in self.heartbeats_ns if t >= since_ns)
        return (
            1 <= heartbeats <= HEARTBEATS_IN_WINDOW_MAX
            and self.kinds_since(since_ns) >= STREAM_KINDS_MIN
        )


def address_text(addr: tuple[str, int] | None) -> str:
    """``host:port`` of a UDP address ("" for None)."""
    return "" if addr is None else f"{addr[0]}:{addr[1]}"


Address = tuple[str, int]
Span = tuple[int, int, int, int]  # (start, end, system_id, message_id) of a frame (frame_spans)


class Claimants:
    """The sources claiming the autopilot's system id ``system_id`` (component 1), by address
    (at most CLAIMANTS_MAX; the longest silent one that is not the autopilot's ``peer``
    forgotten first). ``by_address``: address -> Claimant."""

    def __init__(self, system_id: int) -> None:
        self.system_id = system_id
        self.by_address: dict[Address, Claimant] = {}

    def note(self, addr: Address, spans: list[Span], data: bytes, now_ns: int, peer: Any) -> bool:
        """Record the frames of a datagram (``spans`` of ``data``) that claim to be the
        autopilot's (its system id, component 1, by header) under their source address;
        True when one is a HEARTBEAT. ``peer``: the autopilot's address (None: not known)."""
        heartbeat = False
        claimant = None
        for start, _, sysid, msgid in spans:
            component = data[start + 6] if data[start] == 0xFD else data[start + 4]
            if sysid != self.system_id or component != 1:
                continue
            if claimant is None:
                claimant = self.by_address.get(addr) or self._new(addr, now_ns, peer)
                claimant.last_ns = now_ns
            if msgid in claimant.kinds or len(claimant.kinds) < CLAIM_KINDS_MAX:
                claimant.kinds[msgid] = now_ns
            if msgid == MSG_ID_HEARTBEAT:
                claimant.heartbeats_ns.append(now_ns)
                heartbeat = True
        return heartbeat

    def _new(self, addr: Address, now_ns: int, peer: Any) -> Claimant:
        """A new source claiming the autopilot (the longest silent other one forgotten when
        CLAIMANTS_MAX are known)."""
        if len(self.by_address) >= CLAIMANTS_MAX:
            others = [a for a in self.by_address if a != peer]
            del self.by_address[min(others, key=lambda a: self.by_address[a].last_ns)]
        claimant = self.by_address[addr] = Claimant(first_ns=now_ns)
        return claimant

    def kinds_of(self, addr: Address | None, now_ns: int) -> int:
        """Message kinds ``addr`` sent as the autopilot over CLAIM_WINDOW_S (0: none, None)."""
        claimant = self.by_address.get(addr) if addr is not None else None
        return 0 if claimant is None else claimant.kinds_since(now_ns - int(CLAIM_WINDOW_S * 1e9))

    def better_than(self, addr: Address, peer: Address | None, now_ns: int) -> bool:
        """Whether the source at ``addr`` (whose authentic autopilot HEARTBEAT was just
        checked) should be the autopilot's address instead of ``peer``.

        Who spoke first proves nothing (a spoofer that did kept the link for a whole flight).
        On a signed link only signed frames can move it (checked before): the signed source
        wins. Unsigned, the autopilot is the source that sends an autopilot's stream
        (:meth:`Claimant.is_stream`: PX4's onboard mode streams ~25 kinds of message to its
        companion link, ArduPilot's SRn streams ~20, each with one HEARTBEAT a second),
        where a spoofer that only wants the link sends a HEARTBEAT and what it means to
        forge. A source that is not a stream holds the link only until a stream claims it; a
        stream holds it while it talks (a later claimant, however rich, is named and never
        followed: nobody takes the link from the autopilot by imitating it). A spoofer that
        speaks first and imitates a whole stream cannot be told from the autopilot without
        signing; it keeps the link, but is named in the status and the log."""
        current = self.by_address.get(peer) if peer is not None else None
        peer_is_stream = current is not None and current.is_stream(now_ns)
        return self.by_address[addr].is_stream(now_ns) and not peer_is_stream

    def rival_address(self, peer: Address | None, now_ns: int) -> str | None:
        """``host:port`` of the source other than ``peer`` that claimed the system id most
        recently within the last 10 s (None: nobody else)."""
        rivals = [
            (c.last_ns, addr)
            for addr, c in self.by_address.items()
            if addr != peer and c.checked_ns and now_ns - c.last_ns < 10_000_000_000
        ]
        return address_text(max(rivals)[1]) if rivals else None

    def status(self, peer: Address | None, now_ns: int) -> list[dict[str, Any]]:
        """The sources that claimed the system id within the last 10 s: address, whether it
        is ``peer``, message kinds over CLAIM_WINDOW_S, seconds since heard."""
        since_ns = now_ns - int(CLAIM_WINDOW_S * 1e9)
        return [
            {
                "address": address_text(addr),
                "autopilot": addr == peer,
                "kinds": c.kinds_since(since_ns),
                "heard_s_ago": round((now_ns - c.last_ns) * 1e-9, 2),
            }
            for addr, c in self.by_address.items()
            if now_ns - c.last_ns < 10_000_000_000
        ]
