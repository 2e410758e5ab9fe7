"""Fleet telemetry over MQTT (aiomqtt): ``<prefix>/<system_id>/status`` (retained, with the
last will ``offline``), ``.../pose`` and ``.../events``.

It never blocks or slows the pipeline: ``publish_*`` only append to a bounded queue (the oldest
message is dropped and counted when it is full) and wake the sender task. The sender connects
with capped, jittered backoff (0.5 s doubling to 10 s), announces ``online`` (retained), and
drains the queue; when the broker goes away it reconnects and carries on with what is queued.
The password is passed to the client only, never logged.

Nothing is subscribed, so every PUBLISH the broker sends is unasked (a hostile or broken
broker): it is counted as it is parsed (``MqttStats.unasked``) and dropped, never queued
(aiomqtt's incoming queue, which nobody reads, held every one: 50 MB pushed cost 75 MB of
memory, and more at each reconnection) and never acknowledged (no PUBACK queued per message
for a broker that does not read them; a compliant broker stops at its in-flight window);
QoS 2 ones, which paho holds until their PUBREL, are dropped after each read. A packet
longer than ``MAX_PACKET_BYTES`` closes the connection before its body is read (paho would
read all of it, up to 256 MB, into memory). Reading the broker's socket takes at most
``READ_SHARE`` of the event loop's time (the loop that sends the poses): past it the socket
is left unread for the rest of the window and TCP slows the broker down (a 50 MB flood,
parsed flat out, cut the pose rate from 30 to 26 Hz in a SITL flight). The retained
``online`` goes out at QoS 1 without waiting for its PUBACK: behind a flood it came later
than aiomqtt's 5 s timeout, which dropped the connection (the flapping every 5 s).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import math
import ssl
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from companion.drivers.backoff import Backoff
from companion.service_options import MqttOptions

MAX_BACKOFF_S = 10.0  # reconnection attempts at least this often (before the jitter)
STOP_TIMEOUT_S = 2.0  # a clean stop waits this long at most for the "offline" status to go out
OFFLINE = b'{"state": "offline"}'
ONLINE = b'{"state": "online"}'
MAX_TOPIC_SHOWN = 80  # characters of an unasked topic quoted in the log (the broker's text)
MAX_PACKET_BYTES = 256 * 1024  # the largest packet read from the broker (it owes us none)
READ_SHARE = 0.1  # of the event loop's time that reading the broker's socket may take
READ_WINDOW_S = 0.1  # the window that share is held over [s]
READ_PAUSE_KEEPALIVE_SHARE = 0.25  # the longest pause in reading, of the keepalive


log = logging.getLogger("companion.mqtt")


@dataclass
class MqttStats:
    connected: bool = False
    published: int = 0
    dropped: int = 0  # oldest messages dropped because the queue was full
    connects: int = 0
    last_error: str = ""
    errors: int = 0  # failed connections and lost ones
    unasked: int = 0  # PUBLISH from the broker on topics never subscribed to: dropped
    unasked_bytes: int = 0  # their payloads [bytes]
    oversized: int = 0  # connections closed on a packet larger than MAX_PACKET_BYTES


class MqttPublisher:
    """``async with MqttPublisher(opts, system_id) as mqtt: mqtt.publish_status({...})``."""

    def __init__(self, opts: MqttOptions, system_id: int) -> None:
        self.opts = opts
        base = f"{opts.topic_prefix}/{system_id}"
        self.topic_status = f"{base}/status"
        self.topic_pose = f"{base}/pose"
        self.topic_events = f"{base}/events"
        self.stats = MqttStats()
        self._queue: deque[tuple[str, bytes, bool]] = deque(maxlen=opts.queue_size)
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._stopping = False
        self._offline_sent = asyncio.Event()
        self._unasked_logged = False  # one warning per connection

    @property
    def queued(self) -> int:
        return len(self._queue)

    async def __aenter__(self) -> MqttPublisher:
        self._task = asyncio.create_task(self._run(), name="mqtt")
        return self

    async def __aexit__(self, *exc: object) -> None:
        """A clean stop says ``offline`` (retained) itself, as the broker's last will says it
        for a crash; at most ``STOP_TIMEOUT_S`` is spent on it (a broker that is away)."""
        if self._task is None:
            return
        self._stopping = True
        self._wake.set()
        if self.stats.connected:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._offline_sent.wait(), STOP_TIMEOUT_S)
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task

    # ------------------------------------------------------------------ producers
    def _put(self, topic: str, payload: dict[str, Any], retain: bool) -> None:
        if len(self._queue) == self._queue.maxlen:
            self.stats.dropped += 1  # deque drops the oldest on append
        self._queue.append((topic, json.dumps(payload, default=str).encode(), retain))
        self._wake.set()

    def publish_status(self, status: dict[str, Any]) -> None:
        self._put(self.topic_status, {"state": "online", **status}, retain=True)

    def publish_pose(self, pose: dict[str, Any]) -> None:
        self._put(self.topic_pose, pose, retain=False)

    def publish_event(self, text: str, **fields: Any) -> None:
        self._put(self.topic_events, {"event": text, **fields}, retain=False)

    # ------------------------------------------------------------------ sender
    def _client(self) -> Any:
        import aiomqtt

        o = self.opts
        tls_context = None
        if o.tls:
            try:
                tls_context = ssl.create_default_context(cafile=o.ca_file or None)
            except (OSError, ssl.SSLError) as e:  # it went away after the config check
                raise OSError(f"CA file {o.ca_file or '(system)'}: {e}") from e
        return _client_class()(
            o.host,
            o.port,
            username=o.username or None,
            password=o.password or None,
            will=aiomqtt.Will(self.topic_status, OFFLINE, qos=1, retain=True),
            keepalive=o.keepalive_s,
            tls_context=tls_context,
            timeout=5.0,
            unasked=self._unasked,
            oversized=self._oversized,
        )

    def _unasked(self, topic: bytes, payload_bytes: int) -> None:
        """Count a PUBLISH nobody asked for (dropped as it arrives); say so once per
        connection, with its topic shortened (the broker's bytes, shown escaped)."""
        self.stats.unasked += 1
        self.stats.unasked_bytes += payload_bytes
        if not self._unasked_logged:
            self._unasked_logged = True
            log.warning(
                "MQTT: the broker sends messages on topics never subscribed to (first: %r); "
                "dropped and counted",
                topic[:MAX_TOPIC_SHOWN].decode(errors="replace"),
            )

    def _oversized(self, packet_bytes: int) -> None:
        """The broker announced a packet larger than MAX_PACKET_BYTES: the connection is
        closed before its body is read (and opened again after the backoff)."""
        self.stats.oversized += 1
        log.warning(
            "MQTT: the broker sent a packet of %d bytes (at most %d are read): disconnecting",
            packet_bytes,
            MAX_PACKET_BYTES,
        )

    async def _run(self) -> None:
        """Connect, drain, reconnect: every failure (the broker, TLS, a bad CA file, a bug) is
        logged and retried with backoff; this task never dies silently."""
        import aiomqtt

        backoff = Backoff(0.5, MAX_BACKOFF_S)
        while True:
            try:
                async with self._client() as client:
                    self.stats.connected = True
                    self.stats.connects += 1
                    self.stats.last_error = ""
                    self._unasked_logged = False
                    backoff.reset()
                    log.info("MQTT connected to %s:%d", self.opts.host, self.opts.port)
                    online = asyncio.create_task(self._announce(client))
                    try:
                        await self._drain(client)
                    finally:
                        online.cancel()
                    return  # stopped: "offline" sent
            except asyncio.CancelledError:
                raise
            except aiomqtt.MqttError as e:
                self._failed(str(e) or type(e).__name__)
            except Exception as e:  # TLS set-up, a CA file gone, a bug: said, then retried
                self._failed(f"{type(e).__name__}: {e}")
            finally:
                self.stats.connected = False
            if self._stopping:
                return
            await asyncio.sleep(backoff.next_s())

    async def _drain(self, client: Any) -> None:
        """Send what is queued as it comes (QoS 0), until a stop: then ``offline``."""
        while True:
            while self._queue:  # drained before "offline" on a stop too
                topic, payload, retain = self._queue[0]
                await client.publish(topic, payload, qos=0, retain=retain)
                self._queue.popleft()  # only once it went out
                self.stats.published += 1
            if self._stopping:
                await client.publish(self.topic_status, OFFLINE, qos=1, retain=True)
                self._offline_sent.set()
                return
            self._wake.clear()
            await self._wake.wait()

    async def _announce(self, client: Any) -> None:
        """The retained ``online`` at QoS 1, its PUBACK awaited for as long as it takes (it
        may come behind a flood) beside the queue's draining; a lost connection ends it."""
        import aiomqtt

        with contextlib.suppress(aiomqtt.MqttError):
            await client.publish(self.topic_status, ONLINE, qos=1, retain=True, timeout=math.inf)

    def _failed(self, why: str) -> None:
        """Log a failure: every one while connected, then once per distinct error (a broker
        that stays away must not fill the journal every few seconds)."""
        if self.stats.connected:
            log.warning("MQTT connection lost: %s", why)
        elif why != self.stats.last_error:
            log.warning(
                "MQTT: cannot connect to %s:%d: %s (retrying every %.0f s or less)",
                self.opts.host,
                self.opts.port,
                why,
                MAX_BACKOFF_S,
            )
        self.stats.last_error = why
        self.stats.errors += 1


class ReadBudget:
    """How long reading may go on: at most ``share`` of the time in each ``window_s`` [s].
    No pause is longer than ``max_pause_s``, so the keepalive always hears from the broker:
    uncapped, one read stretched to 0.3 s by a loaded machine paused the socket for 2.7 s, and
    paho closed the connection for a PINGRESP it could not read. (The time is the wall
    clock's: counted in CPU time, reading took more of a loaded machine's wall time, and the
    poses' rate fell below 1 - share of the rate before in CI.)"""

    def __init__(self, share: float, window_s: float, max_pause_s: float) -> None:
        self.share = share
        self.window_s = window_s
        self.max_pause_s = max_pause_s
        self.window_start_s = -math.inf
        self.busy_s = 0.0

    def spend(self, start_s: float, end_s: float) -> float:
        """Count a read from ``start_s`` to ``end_s`` (perf_counter [s]); the seconds to stop
        reading for now (0: none), so that the share holds over the window, at most
        ``max_pause_s``."""
        if start_s - self.window_start_s >= self.window_s:
            self.window_start_s, self.busy_s = start_s, 0.0
        self.busy_s += end_s - start_s
        if self.busy_s <= self.share * self.window_s:
            return 0.0
        pause_s = self.window_start_s + self.busy_s / self.share - end_s
        return min(self.max_pause_s, max(0.0, pause_s))


@functools.cache
def _client_class() -> type[Any]:
    """aiomqtt's Client for a publisher that subscribes to nothing (aiomqtt 2's private
    hooks, covered by tests/e2e/test_listeners.py): every PUBLISH from the broker goes to
    ``unasked(topic, payload bytes)`` as it is parsed, none is queued or acknowledged, QoS 2
    ones held for their PUBREL are dropped after each read, a packet longer than
    MAX_PACKET_BYTES closes the connection before its body is read (``oversized(length)``),
    and reading takes at most ``READ_SHARE`` of the loop's time."""
    import aiomqtt

    class Client(aiomqtt.Client):
        def __init__(
            self,
            *args: Any,
            unasked: Callable[[bytes, int], None],
            oversized: Callable[[int], None],
            **kwargs: Any,
        ) -> None:
            super().__init__(*args, **kwargs)
            self._unasked = unasked
            self._oversized = oversized
            self._client.manual_ack_set(True)  # no PUBACK queued per unasked message

        def _on_message(self, client: Any, userdata: Any, message: Any) -> None:
            """paho's on_message: counted, never converted nor queued."""
            self._unasked(message._topic, len(message.payload))

        def _on_socket_open(self, client: Any, userdata: Any, sock: Any) -> None:
            loop = self._loop
            fd = sock.fileno()
            max_pause_s = READ_PAUSE_KEEPALIVE_SHARE * max(1, int(client.keepalive))
            budget = ReadBudget(READ_SHARE, READ_WINDOW_S, max_pause_s)
            recv = client._sock_recv

            def bounded_recv(bufsize: int) -> bytes:
                """paho's socket read, refused for the body of an oversized packet."""
                length = int(client._in_packet["remaining_length"])
                if length > MAX_PACKET_BYTES:
                    self._oversized(length)
                    raise OSError(f"a packet of {length} bytes from the broker")
                return bytes(recv(bufsize))

            client._sock_recv = bounded_recv

            def read() -> None:
                start_s = time.perf_counter()
                try:
                    while True:
                        client.loop_read()
                        # a TLS socket may hold decoded bytes the selector does not see
                        if hasattr(client._sock, "pending") and client._sock.pending() > 0:
                            continue
                        break
                except Exception as exc:  # a broken connection: aiomqtt's handling
                    if not self._disconnected.done():
                        self._disconnected.set_exception(exc)
                    return
                held = client._in_messages  # QoS 2 messages waiting for their PUBREL
                for message in held.values():
                    self._unasked(message._topic, len(message.payload))
                held.clear()  # (a PUBREL for one of them is then ignored)
                pause_s = budget.spend(start_s, time.perf_counter())
                if pause_s > 0.0 and client._sock is sock:
                    loop.remove_reader(fd)
                    loop.call_later(pause_s, resume)

            def resume() -> None:
                if client._sock is sock:  # still this connection's socket, still open
                    loop.add_reader(fd, read)

            def create_misc_task() -> None:
                self._misc_task = loop.create_task(self._misc_loop())

            # paho calls this from the executor thread that connects
            loop.call_soon_threadsafe(loop.add_reader, fd, read)
            loop.call_soon_threadsafe(create_misc_task)

    return Client
