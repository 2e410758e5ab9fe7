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
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.drivers.backoff import Backoff
from companion.drivers.mavlink_claims import (
    CLAIM_WINDOW_S,
    HEARTBEAT_CHECK_S,
    MSG_ID_HEARTBEAT,
    RIVAL_CHECKS_INTERVAL_S,
    RIVAL_LOG_INTERVAL_S,
    Claimants,
    address_text,
)
from companion.drivers.mavlink_parser import LinkStats, Parser, frame_spans
from companion.drivers.serial_backlog import SERIAL_TURN_BYTES, SerialBacklog
from companion.drivers.signing import RESERVE_UNITS, Signing
from companion.errors import ConfigError

log = logging.getLogger("companion.mavlink")

OnMessage = Callable[[Any, int], None]
UDP_RCVBUF_BYTES = 1 << 20  # asked of the kernel for a UDP link (it caps it at net.core.rmem_max)
PEER_SILENCE_S = 1.0  # udpin: the autopilot may move to a new address after this much silence
# serial: see drivers/serial_backlog.py for how the reader thread's chunks reach the loop
SERIAL_WAIT_S = 0.1  # the reader's longest wait for a byte (then it looks for closing)
SERIAL_READ_MAX_BYTES = 16384
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
        self.claims = Claimants(system_id)  # udpin: who claims to be the autopilot
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
        self._rx_backlog = SerialBacklog()

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
        heartbeat = (
            spans is not None
            and addr is not None
            and self.claims.note(addr, spans, data, now, self._peer)
        )
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
        claimant = self.claims.by_address[addr]
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
                self.claims.kinds_of(self._peer, now_ns),
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
                self.claims.kinds_of(self._peer, now_ns),
                f" ({self.stats.rivals_seen - self._rivals_logged - 1} more since the last said)"
                if self.stats.rivals_seen - self._rivals_logged > 1
                else "",
            )
            self._rival_logged_ns, self._rivals_logged = now_ns, self.stats.rivals_seen

    def better_than_peer(self, addr: tuple[str, int], now_ns: int) -> bool:
        """Whether the source at ``addr`` should be the autopilot's address instead of the
        current one (the rule: :meth:`Claimants.better_than`)."""
        return self.claims.better_than(addr, self._peer, now_ns)

    def rival_address(self, now_ns: int) -> str | None:
        """``host:port`` of the source other than the autopilot's that claimed its system id
        most recently within the last 10 s (None: nobody else), for the operator."""
        return self.claims.rival_address(self._peer, now_ns)

    def claimants_status(self, now_ns: int) -> list[dict[str, Any]]:
        """The sources that claimed the autopilot's system id within the last 10 s (for the
        status): address, whether the link sends to it, message kinds over CLAIM_WINDOW_S,
        seconds since heard. More than one: somebody else speaks as the autopilot."""
        return self.claims.status(self._peer, now_ns)

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
        then, queued for the event loop (:meth:`SerialBacklog.hand_over`). When the port fails
        (a USB adapter unplugged), close it and reopen it with capped, jittered backoff.

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
            if (
                data
                and not self._closing
                and self._rx_backlog.hand_over(bytes(data), time.monotonic_ns(), self.stats)
            ):
                with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
                    loop.call_soon_threadsafe(self._drain_serial)

    def _drain_serial(self) -> None:
        """On the event loop: parse at most SERIAL_TURN_BYTES of the queued chunks, each with
        its arrival stamp; while more wait, again at the loop's next turn (after its I/O,
        signals and timers)."""
        budget = SERIAL_TURN_BYTES
        while budget > 0:
            chunk = self._rx_backlog.take(budget, self._closing)
            if chunk is None:
                return
            rx_ns, data = chunk
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
