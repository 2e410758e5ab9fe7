"""A hostile MQTT broker for the tests: a small asyncio server speaking the real wire protocol
(MQTT 3.1.1 and 5: CONNECT/CONNACK, SUBSCRIBE/SUBACK, PUBLISH/PUBACK, PINGREQ/PINGRESP) that,
once a client is connected, pushes PUBLISH packets on topics nobody subscribed to (QoS 0 and
1, alternately) as fast as the client takes them, while it answers the client's own packets
as a broker should (so a connection lost is the client's doing, not this broker's)."""

from __future__ import annotations

import asyncio
import struct
from dataclasses import dataclass, field

CONNECT, CONNACK, PUBLISH, PUBACK = 0x10, 0x20, 0x30, 0x40
SUBSCRIBE, SUBACK, PINGREQ, PINGRESP, DISCONNECT = 0x80, 0x90, 0xC0, 0xD0, 0xE0
MQTT_V5 = 5


def encode_length(n: int) -> bytes:
    """MQTT's variable-length 'remaining length' (1-4 bytes, 7 bits each)."""
    out = bytearray()
    while True:
        byte, n = n % 128, n // 128
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


def packet(first_byte: int, body: bytes) -> bytes:
    """A whole control packet: fixed header (type and flags, remaining length) + body."""
    return bytes([first_byte]) + encode_length(len(body)) + body


def utf8(text: str | bytes) -> bytes:
    """An MQTT UTF-8 string: 2-byte big-endian length + bytes (given as bytes: sent as they
    are, valid UTF-8 or not)."""
    raw = text.encode() if isinstance(text, str) else text
    return struct.pack("!H", len(raw)) + raw


def publish(topic: str | bytes, payload: bytes, qos: int, mid: int, version: int) -> bytes:
    """A PUBLISH packet (no properties on MQTT 5)."""
    body = utf8(topic) + (struct.pack("!H", mid) if qos else b"")
    if version == MQTT_V5:
        body += b"\x00"  # property length
    return packet(PUBLISH | (qos << 1), body + payload)


async def read_packet(reader: asyncio.StreamReader) -> tuple[int, bytes]:
    """(first byte, body) of the next packet from the client."""
    first = (await reader.readexactly(1))[0]
    length, mult = 0, 1
    for _ in range(4):
        byte = (await reader.readexactly(1))[0]
        length += (byte & 0x7F) * mult
        mult *= 128
        if not byte & 0x80:
            break
    return first, await reader.readexactly(length)


@dataclass
class FloodReport:
    """What the broker saw: connections, what it pushed, what the client sent it."""

    connections: int = 0
    versions: list[int] = field(default_factory=list)
    flood_bytes: int = 0  # PUBLISH bytes pushed (whole packets)
    flood_messages: int = 0
    flood_done: bool = False
    closed_by_client_during_flood: int = 0
    pubacks_from_client: int = 0  # for our QoS 1 pushes
    client_publishes: dict[str, int] = field(default_factory=dict)  # topic -> count
    client_publish_log: list[tuple[float, str]] = field(default_factory=list)  # (time, topic)


class HostileBroker:
    """``async with HostileBroker(flood_bytes) as b: ... b.port, b.report``."""

    def __init__(
        self,
        flood_bytes: int,
        payload_bytes: int = 1000,
        start: asyncio.Event | None = None,
        qos_levels: tuple[int, ...] = (0, 1),
        oversized_bytes: int = 0,
        topic: bytes = b"hostile/",
        puback_delay_s: float = 0.0,
    ) -> None:
        self.flood_total = flood_bytes
        self.start = start  # the flood waits for it (None: at once after CONNACK)
        self.qos_levels = qos_levels  # cycled through (QoS 2: never a PUBREL)
        self.oversized_bytes = oversized_bytes  # > 0: one PUBLISH this long instead
        self.topic = topic  # the flood's topics start with it (not UTF-8 if so wished)
        self.puback_delay_s = puback_delay_s  # our PUBACK to the client's QoS 1, this late
        self.payload = b"x" * payload_bytes
        self.report = FloodReport()
        self.port = 0
        self._server: asyncio.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()

    async def __aenter__(self) -> HostileBroker:
        self._server = await asyncio.start_server(self._client, "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self._server is not None
        self._server.close()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.report.connections += 1
        flood: asyncio.Task[None] | None = None
        try:
            first, body = await read_packet(reader)
            assert first & 0xF0 == CONNECT, first
            version = body[6]  # after the protocol name "\x00\x04MQTT"
            self.report.versions.append(version)
            ack = b"\x00\x00" + (b"\x00" if version == MQTT_V5 else b"")
            writer.write(packet(CONNACK, ack))
            flood = asyncio.create_task(self._flood(writer, version))
            self._tasks.add(flood)
            while True:
                first, body = await read_packet(reader)
                kind = first & 0xF0
                if kind == PUBLISH:
                    mid = self._client_published(first, body)
                    if mid is not None:
                        ack = packet(PUBACK, struct.pack("!H", mid))
                        loop = asyncio.get_running_loop()
                        loop.call_later(self.puback_delay_s, writer.write, ack)
                elif kind == PUBACK:
                    self.report.pubacks_from_client += 1
                elif kind == SUBSCRIBE:
                    writer.write(packet(SUBACK, body[:2] + b"\x00"))
                elif kind == PINGREQ:
                    writer.write(packet(PINGRESP, b""))
                elif kind == DISCONNECT:
                    return
        except (asyncio.IncompleteReadError, ConnectionError):
            if flood is not None and not flood.done():
                self.report.closed_by_client_during_flood += 1
        finally:
            if flood is not None:
                flood.cancel()
            writer.close()

    def _client_published(self, first: int, body: bytes) -> int | None:
        """Count the client's own PUBLISH by topic; its packet id if it wants a PUBACK."""
        (n,) = struct.unpack_from("!H", body)
        topic = body[2 : 2 + n].decode()
        self.report.client_publishes[topic] = self.report.client_publishes.get(topic, 0) + 1
        self.report.client_publish_log.append((asyncio.get_running_loop().time(), topic))
        if (first >> 1) & 0x03:
            return int(struct.unpack_from("!H", body, 2 + n)[0])
        return None

    async def _flood(self, writer: asyncio.StreamWriter, version: int) -> None:
        """PUBLISH on unsubscribed topics, QoS 0 and 1 alternately, as fast as the client
        reads (the transport's buffer is drained before the next batch)."""
        if self.start is not None:
            await self.start.wait()
        if self.oversized_bytes:
            await self._oversized(writer, version)
            return
        k = 0
        while self.report.flood_bytes < self.flood_total:
            for _ in range(64):
                k += 1
                qos = self.qos_levels[k % len(self.qos_levels)]
                topic = self.topic + str(k % 1000).encode()
                data = publish(topic, self.payload, qos, k % 65535 + 1, version)
                writer.write(data)
                self.report.flood_bytes += len(data)
                self.report.flood_messages += 1
            await writer.drain()
        self.report.flood_done = True

    async def _oversized(self, writer: asyncio.StreamWriter, version: int) -> None:
        """One PUBLISH of ``oversized_bytes``, its body sent 64 kB at a time."""
        head = utf8("hostile/big") + (b"\x00" if version == MQTT_V5 else b"")
        body_bytes = self.oversized_bytes - len(head)
        writer.write(bytes([PUBLISH]) + encode_length(self.oversized_bytes) + head)
        chunk = b"x" * 65536
        while body_bytes > 0:
            writer.write(chunk[:body_bytes])
            self.report.flood_bytes += min(body_bytes, len(chunk))
            body_bytes -= len(chunk)
            await writer.drain()
        self.report.flood_messages += 1
        self.report.flood_done = True
