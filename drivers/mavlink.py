"""MAVLink 2 links over UDP, TCP and serial for asyncio (pymavlink's v2.0 ardupilotmega dialect:
common plus ArduPilot's own messages, so that ArduPilot's EKF_STATUS_REPORT, SIMSTATE, ... are
CRC-checked and ignored instead of counted as bad frames: 7 % of an ArduCopter link was).

URLs (pymavlink's spelling):
- ``udpin:HOST:PORT``   listen on HOST:PORT; send to whoever spoke last (PX4 SITL's onboard
  instance sends to 14540: ``udpin:127.0.0.1:14540``);
- ``udpout:HOST:PORT``  send to HOST:PORT from an ephemeral port (or ``local_port``), receive
  the answers there (the form for a real autopilot on Ethernet: PX4 answers whoever spoke);
- ``tcp:HOST:PORT``     connect to a TCP server (reconnects with capped, jittered backoff);
- ``serial:DEVICE:BAUD`` or a bare ``/dev/...`` path (baud 921600) through pyserial.

Every received message reaches ``on_message(msg, rx_time_ns)`` on the event loop, stamped with
our monotonic clock at reception. Bad bytes are counted, never raised: pymavlink's robust
parser turns a bad CRC or length into BAD_DATA, and an exception inside the parser is caught
and counted. ``send`` never blocks: UDP sends at once, TCP/serial queue the bytes.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.drivers.backoff import Backoff
from companion.drivers.signing import RESERVE_UNITS, Signing, VerifyingMAVLink
from companion.errors import ConfigError

log = logging.getLogger("companion.mavlink")

OnMessage = Callable[[Any, int], None]
UDP_RCVBUF_BYTES = 1 << 20  # asked of the kernel for a UDP link (it caps it at net.core.rmem_max)
MAX_RESYNCS = 16  # per received chunk: byte-stream resynchronisations inside failed frames
PEER_SILENCE_S = 1.0  # udpin: the autopilot may move to a new address after this much silence
# udpin: sources claiming the autopilot's system id (its component 1) are tracked by address
# (at most CLAIMANTS_MAX, the longest silent forgotten first) with the message kinds each sent
# over the last CLAIM_WINDOW_S; see MavlinkLink.claimants for the rule that picks the autopilot
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
# serial: the reader thread hands each chunk over as it arrives, stamped then; the event loop
# parses at most SERIAL_TURN_BYTES per turn (bounded work per wake-up: a byte flood faster
# than the parser cannot starve the loop, its signal handlers or its timers), and at most
# SERIAL_BACKLOG_BYTES wait (1.4 s at 921600 baud): beyond it the oldest are dropped, counted
SERIAL_WAIT_S = 0.1  # the reader's longest wait for a byte (then it looks for closing)
SERIAL_READ_MAX_BYTES = 16384
SERIAL_TURN_BYTES = 4096
SERIAL_BACKLOG_BYTES = 131072
MAV_AUTOPILOT_INVALID = mavlink.MAV_AUTOPILOT_INVALID  # 8: a ground station, a companion


@dataclass(frozen=True, slots=True)
class LinkUrl:
    """A parsed link URL."""

    kind: str  # udpin, udpout, tcp, serial
    host: str
    port: int  # UDP/TCP port, or the serial baud rate

    @staticmethod
    def parse(url: str, key: str = "service.mavlink_url") -> LinkUrl:
        """Parse ``url``; ConfigError naming ``key`` when it is not one of the forms above."""
        if url.startswith("/dev/"):
            return LinkUrl("serial", url, 921600)
        kind, _, rest = url.partition(":")
        host, _, port = rest.rpartition(":")
        if kind not in ("udpin", "udpout", "tcp", "serial") or not host or not port.isdigit():
            raise ConfigError(
                f"{key}: expected udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or "
                f"serial:DEVICE:BAUD, got {url!r}"
            )
        return LinkUrl(kind, host, int(port))


@dataclass
class LinkStats:
    """Counters of one link (read by the status)."""

    rx_messages: int = 0
    rx_bad: int = 0  # BAD_DATA frames and parser exceptions
    rx_bytes: int = 0
    tx_messages: int = 0
    tx_dropped: int = 0  # nothing to send to yet, or the transport failed
    reconnects: int = 0
    handler_errors: int = 0  # exceptions raised by on_message (a bug, but the link lives)
    rx_skipped: int = 0  # whole frames of message ids nobody here reads: never parsed
    rx_foreign: int = 0  # whole frames of another system id: never parsed
    rx_other_address: int = 0  # datagrams from an address that is not the autopilot's: dropped
    peer_changes: int = 0  # udpin: the autopilot's address changed (after its silence)
    last_error: str = ""  # why the transport is down (serial: cannot open; tcp: refused)
    rx_overflow_bytes: int = 0  # serial: received faster than parsed, the oldest dropped
    rival_datagrams: int = 0  # udpin: from another address, claiming the autopilot's id
    rivals_seen: int = 0  # udpin: addresses other than the autopilot's that claimed its id


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


def frame_spans(data: bytes) -> list[tuple[int, int, int, int]] | None:
    """``(start, end, system_id, message_id)`` of each frame when ``data`` is exactly a run of
    whole MAVLink 1/2 frames (by their headers; nothing is checked), else None. A few
    microseconds per datagram: the cheap first look before pymavlink's parser."""
    out = []
    i, n = 0, len(data)
    while i < n:
        magic = data[i]
        if magic == 0xFD:  # v2: magic len incompat compat seq sys comp id(3) payload crc(2) [sig]
            if n - i < 12:
                return None
            end = i + 12 + data[i + 1] + (13 if data[i + 2] & 0x01 else 0)
            sysid, msgid = data[i + 5], data[i + 7] | data[i + 8] << 8 | data[i + 9] << 16
        elif magic == 0xFE:  # v1: magic len seq sys comp id payload crc(2)
            if n - i < 8:
                return None
            end = i + 8 + data[i + 1]
            sysid, msgid = data[i + 3], data[i + 5]
        else:
            return None
        if end > n:
            return None
        out.append((i, end, sysid, msgid))
        i = end
    return out


class Parser:
    """Bytes -> MAVLink messages (robust: bad frames are counted and skipped). With a signing
    state (``drivers.signing``), frames are checked against it; refused ones are bad data.

    ``wanted`` (message ids) and ``system_id``: on datagrams made of whole frames, the frames
    of other message ids or other systems are skipped by their header alone (counted, never
    CRC-checked or unpacked): a link that reads five message types does not pay for the
    autopilot's other streams, nor for a flood of frames it would throw away."""

    def __init__(
        self,
        signing_state: Any = None,
        wanted: frozenset[int] | None = None,
        system_id: int | None = None,
    ) -> None:
        self.signing_state = signing_state
        self.wanted = wanted
        self.system_id = system_id
        self.mav = self._new()

    def _prefilter(self, data: bytes, stats: LinkStats) -> bytes:
        """The frames of ``data`` worth parsing (all of it unless it is whole frames)."""
        spans = frame_spans(data)
        if spans is None:
            return data  # garbage or a partial frame: pymavlink's robust parser decides
        keep = []
        for start, end, sysid, msgid in spans:
            if self.system_id is not None and sysid != self.system_id:
                stats.rx_foreign += 1
            elif self.wanted is not None and msgid not in self.wanted:
                stats.rx_skipped += 1
            else:
                keep.append(data[start:end])
        return data if len(keep) == len(spans) else b"".join(keep)

    def _new(self) -> Any:
        mav = VerifyingMAVLink(None)
        mav.robust_parsing = True
        if self.signing_state is not None:
            mav.signing = self.signing_state
        return mav

    def _restart_at(self, data: bytes) -> None:
        """Parse from the next start-of-frame marker in ``data`` (the state reset in place)."""
        starts = [i for i in (data.find(b"\xfd"), data.find(b"\xfe")) if i >= 0]
        mav = self.mav
        mav.buf = bytearray(data[min(starts) :]) if starts else bytearray()
        mav.buf_index = 0
        mav.expected_length = mavlink.HEADER_LEN_V1 + 2

    def feed(self, data: bytes, stats: LinkStats, datagram: bool = False) -> list[Any]:
        """The messages in ``data`` (bad frames counted in ``stats.rx_bad``; frames of a
        message id we do not know are bad too: pymavlink returns them before checking their
        CRC or signature).

        ``datagram``: ``data`` is one UDP datagram, a unit of its own: bytes left over at its
        end (a truncated frame, a length byte that promised more) are dropped instead of
        swallowing the start of the next datagram. On a byte stream (serial, TCP), a frame
        that fails its CRC is searched again from its next start marker: its length byte may
        be the corrupted one, and then good frames start inside what pymavlink took for it
        (at most ``MAX_RESYNCS`` times per call, so that a flood of markers costs no more
        than pymavlink's own parsing)."""
        out: list[Any] = []
        resyncs = 0
        if datagram and (self.wanted is not None or self.system_id is not None):
            data = self._prefilter(data, stats)
            if not data:
                return out
        try:
            msg = self.mav.parse_char(data)
            while msg is not None:
                kind = msg.get_type()
                if kind != "BAD_DATA" and not kind.startswith("UNKNOWN_"):
                    out.append(msg)
                else:
                    stats.rx_bad += 1
                    raw = bytes(getattr(msg, "data", b"") or b"")
                    if (
                        not datagram
                        and kind == "BAD_DATA"
                        and resyncs < MAX_RESYNCS
                        and len(raw) > 1
                        and raw[0] in (0xFD, 0xFE)
                        and "signature" not in str(getattr(msg, "reason", ""))
                    ):
                        resyncs += 1
                        self._restart_at(raw[1:] + bytes(self.mav.buf[self.mav.buf_index :]))
                msg = self.mav.parse_char(b"")
        except Exception:  # pymavlink raises on some malformed payloads: count, go on
            stats.rx_bad += 1
            self.mav = self._new()
        if datagram and self.mav.buf_len() > 0:
            stats.rx_bad += 1
            self._restart_at(b"")
        stats.rx_messages += len(out)
        return out


class MavlinkLink:
    """One MAVLink link as an async context manager (the transport lives inside it)."""

    def __init__(
        self,
        url: str,
        system_id: int,
        component_id: int,
        on_message: OnMessage,
        signing: Signing | None = None,
        local_port: int = 0,
        wanted: frozenset[int] | None = None,
    ) -> None:
        """``local_port``: udpout sends from this port (0: an ephemeral one). PX4 keeps the
        first sender's address until it reboots, so a fixed port survives our restarts.
        ``wanted``: the message ids ``on_message`` reads (None: all); with it, frames of
        other ids and other systems are skipped unparsed (see :class:`Parser`)."""
        self.url = LinkUrl.parse(url)
        self.local_port = local_port
        self.on_message = on_message
        self.peer_system_id = system_id  # udpin answers the address this system spoke from
        self.mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self.stats = LinkStats()
        self._parser = Parser(None, wanted, system_id if wanted is not None else None)
        self.signing = signing
        if signing is not None:  # one signing state for what we send and what we parse
            signing.apply(self.mav, self._parser.mav)
            self._parser.signing_state = self.mav.signing
        self._transport: asyncio.DatagramTransport | None = None
        self._peer: tuple[str, int] | None = None
        self._peer_heard_ns = 0  # udpin: when the autopilot's address last sent us anything
        self.claimants: dict[tuple[str, int], Claimant] = {}  # udpin: who claims the autopilot
        self._rival_checked_ns = 0  # the last rival HEARTBEAT parsed
        self._rival_logged_ns = 0  # the last new rival logged
        self._rivals_logged = 0  # stats.rivals_seen when it was logged
        self._writer: asyncio.StreamWriter | None = None
        self._serial: Any = None
        self._tasks: list[asyncio.Task[None]] = []
        self._closing = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._errors_logged: dict[tuple[str, str], float] = {}
        # serial: chunks (arrival time [ns], bytes) the reader thread handed over, not parsed
        self._rx_chunks: deque[tuple[int, bytes]] = deque()
        self._rx_backlog_bytes = 0
        self._rx_lock = threading.Lock()
        self._rx_wake_pending = False  # a _drain_serial is scheduled on the loop

    # ------------------------------------------------------------------ lifecycle
    async def __aenter__(self) -> MavlinkLink:
        self._loop = asyncio.get_running_loop()
        u = self.url
        if u.kind in ("udpin", "udpout"):
            local = (u.host, u.port)
            self._peer = None
            if u.kind == "udpout":  # its numeric address: replies are matched against it
                try:
                    infos = await self._loop.getaddrinfo(u.host, u.port, type=socket.SOCK_DGRAM)
                except OSError as e:
                    raise ConfigError(
                        f"service.mavlink_url: cannot resolve {u.host}: {e}"
                    ) from None
                family, peer = infos[0][0], infos[0][4]
                self._peer = (str(peer[0]), int(peer[1]))
                # from local_port (0: an ephemeral one) on every address of the peer's family
                local = ("::" if family == socket.AF_INET6 else "0.0.0.0", self.local_port)
            try:
                transport, _ = await self._loop.create_datagram_endpoint(
                    lambda: _Udp(self), local_addr=local, remote_addr=None
                )
            except OSError as e:  # port in use, address not ours: a set-up error, not a crash
                raise ConfigError(
                    f"service.mavlink_url: cannot listen on {local[0]}:{local[1]} ({e.strerror}"
                    "; is another program, or another companion, using it?)"
                ) from None
            self._transport = transport
            sock = transport.get_extra_info("socket")
            if sock is not None:  # room for a burst while the loop is busy (capped by rmem_max)
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RCVBUF_BYTES)
        elif u.kind == "tcp":
            self._tasks.append(asyncio.create_task(self._tcp_loop(), name="mavlink-tcp"))
        else:
            self._open_serial()
        if self.signing is not None:
            self._tasks.append(asyncio.create_task(self._signing_loop(), name="mavlink-signing"))
        return self

    async def _signing_loop(self) -> None:
        """Once a second: the signing timestamp follows the wall clock, persisted ahead."""
        assert self.signing is not None
        while not self._closing:
            self.signing.tick()
            await asyncio.sleep(1.0)

    async def __aexit__(self, *exc: object) -> None:
        self._closing = True
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        if self._transport is not None:
            self._transport.close()
        if self._writer is not None:
            self._writer.close()
        if self._serial is not None:
            with contextlib.suppress(Exception):
                self._serial.close()

    @property
    def connected(self) -> bool:
        """Whether there is somebody to send to."""
        return (
            (self._transport is not None and self._peer is not None)
            or self._writer is not None
            or (self._serial is not None and self._serial.is_open)
        )

    # ------------------------------------------------------------------ I/O
    def _received(
        self,
        data: bytes,
        addr: tuple[str, int] | None = None,
        datagram: bool = False,
        rx_ns: int | None = None,
    ) -> None:
        """Bytes received (from ``addr`` on UDP) at ``rx_ns`` (our monotonic clock [ns];
        None: now), parsed and handed to ``on_message``."""
        self.stats.rx_bytes += len(data)
        now = time.monotonic_ns() if rx_ns is None else rx_ns
        moving = False  # udpin: a datagram from a new address while the autopilot is silent
        spans = frame_spans(data) if addr is not None and self.url.kind == "udpin" else None
        heartbeat = spans is not None and self._note_claims(addr, spans, data, now)
        if addr is not None and self._peer is not None and addr != self._peer:
            silent_s = (now - self._peer_heard_ns) * 1e-9
            if self.url.kind == "udpout" or silent_s < PEER_SILENCE_S:
                self.stats.rx_other_address += 1  # a spoofer or a flood: not even parsed
                if heartbeat:
                    self._rival_heartbeat(addr, spans, data, now)
                return
            moving = True
        for msg in self._parser.feed(data, self.stats, datagram):
            if moving:
                if not self._is_autopilot_heartbeat(msg):
                    continue  # only the autopilot's own heartbeat may move the address
                assert addr is not None
                self._peer, moving = addr, False
                self.stats.peer_changes += 1
            elif (
                addr is not None
                and self._peer is None
                and self.authentic(msg)
                and msg.get_srcSystem() == self.peer_system_id
            ):
                self._peer = addr  # udpin: the autopilot's address, learned once
            if addr is not None and addr == self._peer:
                self._peer_heard_ns = now
            try:
                self.on_message(msg, now)
            except Exception as e:  # a handler bug must not take the link down: said, counted
                self.stats.handler_errors += 1
                self._log_limited("handler failed on", msg.get_type(), e, self.stats.handler_errors)

    def _note_claims(
        self,
        addr: tuple[str, int] | None,
        spans: list[tuple[int, int, int, int]] | None,
        data: bytes,
        now_ns: int,
    ) -> bool:
        """Record the frames of a datagram that claim to be the autopilot's (its system id,
        component 1, by header) under their source address; True when one is a HEARTBEAT."""
        assert addr is not None and spans is not None
        heartbeat = False
        claimant = None
        for start, _, sysid, msgid in spans:
            component = data[start + 6] if data[start] == 0xFD else data[start + 4]
            if sysid != self.peer_system_id or component != 1:
                continue
            if claimant is None:
                claimant = self.claimants.get(addr) or self._new_claimant(addr, now_ns)
                claimant.last_ns = now_ns
            if msgid in claimant.kinds or len(claimant.kinds) < CLAIM_KINDS_MAX:
                claimant.kinds[msgid] = now_ns
            if msgid == MSG_ID_HEARTBEAT:
                claimant.heartbeats_ns.append(now_ns)
                heartbeat = True
        return heartbeat

    def _new_claimant(self, addr: tuple[str, int], now_ns: int) -> Claimant:
        """A new source claiming the autopilot (the longest silent other one forgotten when
        CLAIMANTS_MAX are known)."""
        if len(self.claimants) >= CLAIMANTS_MAX:
            others = [a for a in self.claimants if a != self._peer]
            del self.claimants[min(others, key=lambda a: self.claimants[a].last_ns)]
        claimant = self.claimants[addr] = Claimant(first_ns=now_ns)
        return claimant

    def _rival_heartbeat(
        self,
        addr: tuple[str, int],
        spans: list[tuple[int, int, int, int]] | None,
        data: bytes,
        now_ns: int,
    ) -> None:
        """A HEARTBEAT as the autopilot from an address that is not the autopilot's while it
        talks: said (the first time per address, at most once per RIVAL_LOG_INTERVAL_S, the
        others counted), and the link moves to it when it is the better candidate
        (:meth:`better_than_peer`). On a signed link an unsigned one is said, never followed.
        Parsed at most every HEARTBEAT_CHECK_S per address, RIVAL_CHECKS_INTERVAL_S in all."""
        claimant = self.claimants[addr]
        self.stats.rival_datagrams += 1
        if (claimant.checked_ns and now_ns - claimant.checked_ns < HEARTBEAT_CHECK_S * 1e9) or (
            now_ns - self._rival_checked_ns < RIVAL_CHECKS_INTERVAL_S * 1e9
        ):
            return
        new = claimant.checked_ns == 0
        claimant.checked_ns = self._rival_checked_ns = now_ns
        assert spans is not None
        frames = [data[a:b] for a, b, _, msgid in spans if msgid == MSG_ID_HEARTBEAT]
        msgs = self._parser.feed(frames[0], LinkStats(), datagram=True)
        if not msgs or msgs[0].get_type() != "HEARTBEAT":
            return
        own = self._is_autopilot_heartbeat(msgs[0])
        if not own and (self.signing is None or msgs[0].autopilot == MAV_AUTOPILOT_INVALID):
            return  # a ground station's or a companion's HEARTBEAT with that id: not a claim
        if new:  # the autopilot's, or unsigned on a signed link
            self.stats.rivals_seen += 1
        if own and self.better_than_peer(addr, now_ns):
            old = self._peer
            log.warning(
                "autopilot link: system %d now at %s, which sends the autopilot's stream "
                "(%d message kinds in %.0f s against %d); %s claimed it first and is "
                "ignored (a spoofer, or a second route to the autopilot)",
                self.peer_system_id,
                address_text(addr),
                claimant.kinds_since(now_ns - int(CLAIM_WINDOW_S * 1e9)),
                CLAIM_WINDOW_S,
                self._peer_kinds(now_ns),
                address_text(old),
            )
            self._peer, self._peer_heard_ns = addr, now_ns
            self.stats.peer_changes += 1
        elif new and now_ns - self._rival_logged_ns >= RIVAL_LOG_INTERVAL_S * 1e9:
            log.warning(
                "autopilot link: a second source claims system %d: %s (%s%d message kinds "
                "in %.0f s); the link stays with %s (%d kinds)%s",
                self.peer_system_id,
                address_text(addr),
                "" if own else "not signed, ",
                claimant.kinds_since(now_ns - int(CLAIM_WINDOW_S * 1e9)),
                CLAIM_WINDOW_S,
                address_text(self._peer),
                self._peer_kinds(now_ns),
                f" ({self.stats.rivals_seen - self._rivals_logged - 1} more since the last said)"
                if self.stats.rivals_seen - self._rivals_logged > 1
                else "",
            )
            self._rival_logged_ns, self._rivals_logged = now_ns, self.stats.rivals_seen

    def _peer_kinds(self, now_ns: int) -> int:
        """Message kinds the autopilot's address sent as the autopilot over CLAIM_WINDOW_S."""
        peer = self.claimants.get(self._peer) if self._peer is not None else None
        return 0 if peer is None else peer.kinds_since(now_ns - int(CLAIM_WINDOW_S * 1e9))

    def better_than_peer(self, addr: tuple[str, int], now_ns: int) -> bool:
        """Whether the source at ``addr`` (whose authentic autopilot HEARTBEAT was just
        checked) should be the autopilot's address instead of the current one.

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
        peer = self.claimants.get(self._peer) if self._peer is not None else None
        peer_is_stream = peer is not None and peer.is_stream(now_ns)
        return self.claimants[addr].is_stream(now_ns) and not peer_is_stream

    def rival_address(self, now_ns: int) -> str | None:
        """``host:port`` of the source other than the autopilot's that claimed its system id
        most recently within the last 10 s (None: nobody else), for the operator."""
        rivals = [
            (c.last_ns, addr)
            for addr, c in self.claimants.items()
            if addr != self._peer and c.checked_ns and now_ns - c.last_ns < 10_000_000_000
        ]
        return address_text(max(rivals)[1]) if rivals else None

    def claimants_status(self, now_ns: int) -> list[dict[str, Any]]:
        """The sources that claimed the autopilot's system id within the last 10 s (for the
        status): address, whether the link sends to it, message kinds over CLAIM_WINDOW_S,
        seconds since heard. More than one: somebody else speaks as the autopilot."""
        since_ns = now_ns - int(CLAIM_WINDOW_S * 1e9)
        return [
            {
                "address": address_text(addr),
                "autopilot": addr == self._peer,
                "kinds": c.kinds_since(since_ns),
                "heard_s_ago": round((now_ns - c.last_ns) * 1e-9, 2),
            }
            for addr, c in self.claimants.items()
            if now_ns - c.last_ns < 10_000_000_000
        ]

    def _is_autopilot_heartbeat(self, msg: Any) -> bool:
        """The autopilot's own HEARTBEAT (its system id, component 1, a real autopilot type),
        authentic when the link is signed."""
        return bool(
            msg.get_type() == "HEARTBEAT"
            and msg.get_srcSystem() == self.peer_system_id
            and msg.get_srcComponent() == 1
            and msg.autopilot != MAV_AUTOPILOT_INVALID
            and self.authentic(msg)
        )

    def _log_limited(self, what: str, kind: str, e: Exception, count: int) -> None:
        """The first error of each (what, message type) in full, then one line per 10 s."""
        now = time.monotonic()
        last = self._errors_logged.get((what, kind))
        if last is None:
            log.error("%s %s", what, kind, exc_info=e)
        elif now - last >= 10.0:
            log.error("%s %s again (%d errors so far): %r", what, kind, count, e)
        else:
            return
        self._errors_logged[(what, kind)] = now

    def authentic(self, msg: Any) -> bool:
        """Whether ``msg`` may change state: always without signing; with signing, only when
        its signature was verified (an unsigned HEARTBEAT is let through for visibility, but
        it must not redirect our output or keep a silent autopilot looking alive)."""
        return self.signing is None or bool(msg.get_signed())

    def send(self, msg: Any) -> bool:
        """Encode and send a pymavlink message; False when it could not be sent."""
        store = self.signing.store if self.signing is not None else None
        if store is not None and self.mav.signing.timestamp > store.persisted - RESERVE_UNITS // 2:
            assert self.signing is not None
            self.signing.tick()  # a signed frame from the peer moved it far forward: persist first
        try:
            buf = msg.pack(self.mav)
        except Exception as e:  # a value out of its field's range: a bug upstream, said
            self.stats.tx_dropped += 1
            self._log_limited("cannot pack", msg.get_type(), e, self.stats.tx_dropped)
            return False
        self.mav.seq = (self.mav.seq + 1) % 256  # pack() does not count: the peer's loss stats
        return self.send_bytes(buf)

    def send_bytes(self, buf: bytes) -> bool:
        """Send raw bytes (already a MAVLink frame)."""
        try:
            if self._transport is not None and self._peer is not None:
                self._transport.sendto(buf, self._peer)
            elif self._writer is not None:
                self._writer.write(buf)
            elif self._serial is not None and self._serial.is_open:
                self._serial.write(buf)
            else:
                self.stats.tx_dropped += 1
                return False
        except Exception:
            self.stats.tx_dropped += 1
            return False
        self.stats.tx_messages += 1
        return True

    async def _tcp_loop(self) -> None:
        backoff = Backoff(0.5, 10.0)
        while not self._closing:
            try:
                reader, writer = await asyncio.open_connection(self.url.host, self.url.port)
            except OSError as e:
                self.stats.last_error = f"cannot connect to {self.url.host}:{self.url.port}: {e}"
                await asyncio.sleep(backoff.next_s())
                continue
            backoff.reset()
            self.stats.last_error = ""
            self._writer = writer
            try:
                while data := await reader.read(4096):
                    self._received(data)
                    await asyncio.sleep(0)  # a turn of the loop per chunk, even in a flood
            except OSError:
                pass
            finally:
                self._writer = None
                writer.close()
            self.stats.reconnects += 1
            await asyncio.sleep(backoff.next_s())

    def _open_serial(self) -> None:
        thread = threading.Thread(target=self._serial_reader, name="mavlink-serial", daemon=True)
        thread.start()

    def _serial_reader(self) -> None:
        """Read the port (a thread): each chunk as soon as its first byte is there, stamped
        then, queued for the event loop (:meth:`_hand_over`). When the port fails (a USB
        adapter unplugged), close it and reopen it with capped, jittered backoff.

        ``read(4096)`` with a 0.1 s timeout (before) returned only at the time-out unless 4096
        bytes came: every message reached the loop 0-100 ms late and PX4's TIMESYNC round
        trips were 52 ms at the median (its limit is 10 ms)."""
        import serial  # pyserial

        loop = self._loop
        assert loop is not None
        backoff = Backoff(0.2, 5.0)
        while not self._closing:
            if self._serial is None or not self._serial.is_open:
                try:
                    self._serial = serial.Serial(
                        self.url.host, self.url.port, timeout=SERIAL_WAIT_S
                    )
                    backoff.reset()
                    self.stats.last_error = ""
                except (OSError, ValueError, serial.SerialException) as e:
                    self.stats.last_error = f"cannot open {self.url.host}: {e}"
                    time.sleep(backoff.next_s())
                    continue
            try:  # what is there, or wait for one byte (read returns on it) and take the rest
                waiting = self._serial.in_waiting
                data = self._serial.read(min(max(1, waiting), SERIAL_READ_MAX_BYTES))
                if data and not waiting and (rest := self._serial.in_waiting):
                    data += self._serial.read(min(rest, SERIAL_READ_MAX_BYTES))
            except Exception:  # unplugged (OSError, SerialException), or closed under us
                if self._closing:  # __aexit__ closed the port while we were reading
                    return
                self.stats.reconnects += 1
                with contextlib.suppress(Exception):
                    self._serial.close()
                continue
            if data and not self._closing and self._hand_over(bytes(data), time.monotonic_ns()):
                with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
                    loop.call_soon_threadsafe(self._drain_serial)

    def _hand_over(self, data: bytes, rx_ns: int) -> bool:
        """Queue a chunk the reader thread read at ``rx_ns``; the oldest queued bytes go
        (counted) beyond SERIAL_BACKLOG_BYTES. True when the loop must be woken for it (no
        wake-up pending: one at a time, so a flood cannot fill the loop's queue)."""
        with self._rx_lock:
            self._rx_chunks.append((rx_ns, data))
            self._rx_backlog_bytes += len(data)
            while self._rx_backlog_bytes > SERIAL_BACKLOG_BYTES and len(self._rx_chunks) > 1:
                _, old = self._rx_chunks.popleft()
                self._rx_backlog_bytes -= len(old)
                self.stats.rx_overflow_bytes += len(old)
            wake = not self._rx_wake_pending
            self._rx_wake_pending = True
        return wake

    def _drain_serial(self) -> None:
        """On the event loop: parse at most SERIAL_TURN_BYTES of the queued chunks, each with
        its arrival stamp; while more wait, again at the loop's next turn (after its I/O,
        signals and timers)."""
        budget = SERIAL_TURN_BYTES
        while budget > 0:
            with self._rx_lock:
                if not self._rx_chunks or self._closing:
                    self._rx_wake_pending = False
                    return
                rx_ns, data = self._rx_chunks.popleft()
                if len(data) > budget:  # the rest next turn, with the same stamp
                    self._rx_chunks.appendleft((rx_ns, data[budget:]))
                    data = data[:budget]
                self._rx_backlog_bytes -= len(data)
            budget -= len(data)
            try:
                self._received(data, rx_ns=rx_ns)
            except Exception as e:  # a bug: said, and the link keeps draining
                self.stats.handler_errors += 1
                self._log_limited("serial chunk failed in", "_received", e, 1)
        assert self._loop is not None
        self._loop.call_soon(self._drain_serial)


class _Udp(asyncio.DatagramProtocol):
    def __init__(self, link: MavlinkLink) -> None:
        self.link = link

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.link._received(data, (str(addr[0]), int(addr[1])), True)

    def error_received(self, exc: Exception) -> None:  # ICMP port unreachable etc.
        self.link.stats.tx_dropped += 1
