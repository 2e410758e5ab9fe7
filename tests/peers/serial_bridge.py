"""A serial cable to the UDP SITL autopilot: a pty the service opens as ``serial:PATH:BAUD``.

The SITL autopilot (sitl/stub/autopilot.py) speaks UDP: it listens on one port and sends to the
companion's. :class:`PtySerialBridge` binds the companion's port and relays, on the running
event loop: each datagram from the autopilot is written to the pty's near end (a serial line
carries bytes, not datagrams), and the bytes the service writes to its end are cut back into
whole MAVLink frames (v1 and v2, signed or not) and sent one frame per datagram, as a
telemetry radio or a serial-to-UDP router would.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import tty
from collections.abc import AsyncIterator

V1_START, V2_START = 0xFE, 0xFD
SIGNED = 0x01  # MAVLink 2 incompat_flags: a 13-byte signature follows the checksum


def frame_length(buf: bytes | bytearray) -> int | None:
    """The length of the MAVLink frame at the start of ``buf`` (which starts with a start
    marker), or None while its header is incomplete."""
    if buf[0] == V1_START:
        return None if len(buf) < 2 else 6 + buf[1] + 2
    if len(buf) < 3:
        return None
    return 10 + buf[1] + 2 + (13 if buf[2] & SIGNED else 0)


class PtySerialBridge(asyncio.DatagramProtocol):
    """``bridge = PtySerialBridge()``: the service's serial device is ``bridge.path``; then
    ``async with bridge.relay(autopilot_port, companion_port)`` on the event loop."""

    def __init__(self) -> None:
        self.autopilot = ("127.0.0.1", 0)
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        tty.setraw(self.master)
        self.path = os.ttyname(self.slave)
        self._buf = bytearray()
        self._transport: asyncio.DatagramTransport | None = None
        self.to_service_bytes = 0
        self.frames_to_autopilot = 0

    @contextlib.asynccontextmanager
    async def relay(self, autopilot_port: int, companion_port: int) -> AsyncIterator[None]:
        """Relay between the pty and the autopilot listening on ``autopilot_port``, which
        sends to ``companion_port`` (bound here) until the block ends; then the pty closes."""
        loop = asyncio.get_running_loop()
        self.autopilot = ("127.0.0.1", autopilot_port)
        os.set_blocking(self.master, False)
        self._transport, _ = await loop.create_datagram_endpoint(
            lambda: self, local_addr=("127.0.0.1", companion_port), family=socket.AF_INET
        )
        loop.add_reader(self.master, self._from_service)
        try:
            yield
        finally:
            loop.remove_reader(self.master)
            self._transport.close()
            for fd in (self.master, self.slave):
                with contextlib.suppress(OSError):
                    os.close(fd)

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        """From the autopilot: onto the line (dropped, as a full UART would, if it is full)."""
        with contextlib.suppress(BlockingIOError, OSError):
            self.to_service_bytes += os.write(self.master, data)

    def _from_service(self) -> None:
        try:
            self._buf += os.read(self.master, 65536)
        except (BlockingIOError, OSError):
            return
        buf = self._buf
        while buf:
            start = next((i for i, b in enumerate(buf) if b in (V1_START, V2_START)), None)
            if start is None:
                buf.clear()
                break
            del buf[:start]
            n = frame_length(buf)
            if n is None or len(buf) < n:
                break
            if self._transport is not None:
                self._transport.sendto(bytes(buf[:n]), self.autopilot)
                self.frames_to_autopilot += 1
            del buf[:n]
