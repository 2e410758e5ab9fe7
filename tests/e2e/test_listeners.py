"""Every listener of the service under a flood: a hostile MQTT broker pushing what was never
asked for, and a local process hammering the status socket."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np
import pytest
from peers.hostile_mqtt import HostileBroker
from peers.status import SAMPLE

ROOT = Path(__file__).resolve().parents[2]
FLOOD_BYTES = 50 * 1024 * 1024
FLOOD_PAYLOAD_BYTES = 1000
FLIGHT_FLOOD_BYTES = 20 * 1024 * 1024  # what is read at READ_SHARE within the flight
POSE_HZ = 30.0

# The publisher as the service runs it, in a process of its own (its memory is measured
# alone): a pose queued on the camera's schedule, an event-loop probe (a 10 ms sleep, how
# late it wakes), and a line of figures every 0.25 s; it stops at a line on stdin.
PUBLISHER = """
import asyncio, json, sys, time
from companion.service.mqtt import MqttPublisher
from companion.service_options import MqttOptions

def kb(key):
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1])

async def main(port, pose_hz):
    loop = asyncio.get_running_loop()
    base_kb = kb("VmRSS")
    lags = []

    async def probe():
        while True:
            t = loop.time()
            await asyncio.sleep(0.01)
            lags.append(loop.time() - t - 0.01)

    stop = asyncio.Event()
    loop.add_reader(sys.stdin.fileno(), stop.set)
    opts = MqttOptions(enabled=True, port=port, keepalive_s=2)
    async with MqttPublisher(opts, 7) as pub:
        probe_task = asyncio.create_task(probe())
        k, t0 = 0, loop.time()
        while not stop.is_set():
            pub.publish_pose({"k": k})
            k += 1
            if k % 8 == 0:
                ordered = sorted(lags)
                figures = {
                    "stats": vars(pub.stats), "base_kb": base_kb, "hwm_kb": kb("VmHWM"),
                    "cpu_s": time.process_time(), "wall_s": loop.time(),
                    "lag_max_s": ordered[-1] if ordered else 0.0,
                    "lag_p99_s": ordered[int(0.99 * len(ordered))] if ordered else 0.0,
                }
                print(json.dumps(figures), flush=True)
            await asyncio.sleep(max(0.0, t0 + k / pose_hz - loop.time()))
        probe_task.cancel()

asyncio.run(main(int(sys.argv[1]), float(sys.argv[2])))
"""


async def start_publisher(port: int) -> asyncio.subprocess.Process:
    """The publisher's process, its stdin and stdout piped."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return await asyncio.create_subprocess_exec(
        sys.executable,
        "-c",
        PUBLISHER,
        str(port),
        str(POSE_HZ),
        stdin=asyncio.subprocess.PIPE,
        stdout=asyncio.subprocess.PIPE,
        env=env,
    )


async def latest_figures(proc: asyncio.subprocess.Process) -> dict:
    """The publisher's figures of now: the lines waiting are skipped (its ``wall_s`` and
    our time.monotonic() are the same clock)."""
    now_s = time.monotonic()
    return await figures_until(proc, lambda f: f["wall_s"] >= now_s - 0.1, 10)


async def figures_until(proc: asyncio.subprocess.Process, done, timeout_s: float) -> dict:
    """The publisher's figures, line after line, until done(figures) or the timeout."""
    assert proc.stdout is not None
    async with asyncio.timeout(timeout_s):
        while True:
            line = await proc.stdout.readline()
            assert line, "the publisher ended"
            figures = json.loads(line)
            if done(figures):
                return figures


@contextlib.asynccontextmanager
async def connected_publisher(
    port: int,
) -> AsyncIterator[tuple[asyncio.subprocess.Process, dict]]:
    """The publisher's process and its first figures once connected to the broker on
    ``port``; on exit it is told to stop and awaited."""
    proc = await start_publisher(port)
    try:
        # 90 s: it did not report a connection within 30 s on a 2-core host with the suite's
        # other worker and two flights beside it (2026-12-02); connecting is what counts here
        yield proc, await figures_until(proc, lambda f: f["stats"]["connected"], 90)
    finally:
        assert proc.stdin is not None
        proc.stdin.write(b"stop\n")
        await proc.wait()


@pytest.mark.parametrize("qos_levels", [(0, 1), (2,)], ids=["qos0+1", "qos2"])
def test_a_hostile_broker_flood_is_dropped_counted_and_costs_no_memory(qos_levels) -> None:
    """A broker pushing 50 MB of PUBLISH on topics never subscribed to (QoS 0 and 1, or QoS 2
    without the PUBREL that would deliver them: paho held every one for it): the
    publisher drops and counts them, its memory stays flat, it keeps its one connection and
    keeps sending poses at the camera's rate, reading the broker within its share of the
    event loop's time. Before: every message was kept in aiomqtt's incoming queue, which
    nobody reads (+75 MB here; QoS 2: +153 MB in paho's), each was acknowledged, and reading
    took all the CPU it could."""

    async def run() -> tuple[dict, dict, HostileBroker, tuple[float, float]]:
        async with (
            HostileBroker(FLOOD_BYTES, FLOOD_PAYLOAD_BYTES, None, qos_levels) as broker,
            connected_publisher(broker.port) as (proc, start),
        ):
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            while not broker.report.flood_done:
                await asyncio.sleep(0.1)
            n = broker.report.flood_messages
            end = await figures_until(proc, lambda f: f["stats"].get("unasked", 0) >= n, 60)
            window = (t0, loop.time())
            after = await latest_figures(proc)
            busy = (end["cpu_s"] - start["cpu_s"]) / (end["wall_s"] - start["wall_s"])
            return end, after, broker, window, busy

    end, after, broker, (t0, t1), busy = asyncio.run(run())
    report = broker.report
    log = report.client_publish_log
    poses = [t for t, topic in log if t0 <= t < t1 and topic.endswith("/pose")]
    print(report.flood_messages, report.flood_bytes, t1 - t0, len(poses), busy, end, after)
    stats = end["stats"]
    assert report.flood_done and report.flood_bytes >= FLOOD_BYTES
    assert stats["unasked"] == report.flood_messages
    assert stats["unasked_bytes"] >= FLOOD_BYTES * 0.9
    growth_mb = (end["hwm_kb"] - end["base_kb"]) / 1024
    assert growth_mb <= 20.0, growth_mb
    assert report.connections == 1 and report.closed_by_client_during_flood == 0
    assert stats["connects"] == 1 and stats["errors"] == 0 and after["stats"]["connected"]
    assert report.pubacks_from_client == 0  # nothing unasked is acknowledged (no PUBACK)
    # the poses went out on the camera's schedule all through the flood (the queue holds 200:
    # a sender starved for more than a few seconds would have dropped some)
    assert len(poses) >= 0.9 * POSE_HZ * (t1 - t0), (len(poses), t1 - t0)
    assert after["stats"]["dropped"] == 0
    # the publisher's process (its event loop) was busy a fraction of the time, not flat out
    # reading (READ_SHARE, and the poses; before: 100 % of a core until the flood was read)
    assert busy <= 0.3, busy


def test_an_oversized_packet_from_the_broker_is_never_read() -> None:
    """A broker announcing a 100 MB PUBLISH (and sending it): the connection is closed before
    its body is read, the publisher's memory stays flat, it says so and connects again.
    Before: paho read all of it into memory, and aiomqtt queued it."""
    from companion.service.mqtt import MAX_PACKET_BYTES

    big = 100 * 1024 * 1024

    async def run() -> tuple[dict, HostileBroker]:
        async with (
            HostileBroker(FLOOD_BYTES, oversized_bytes=big) as broker,
            connected_publisher(broker.port) as (proc, _),
        ):
            end = await figures_until(proc, lambda f: f["stats"]["connects"] >= 3, 60)
            return end, broker

    end, broker = asyncio.run(run())
    print(end, broker.report.flood_bytes, broker.report.connections)
    assert big > 100 * MAX_PACKET_BYTES
    assert (end["hwm_kb"] - end["base_kb"]) / 1024 <= 20.0, end
    assert end["stats"]["oversized"] >= 2 and broker.report.connections >= 3
    assert end["stats"]["unasked"] == 0  # nothing of it was taken as a message


def test_topics_that_are_not_utf8_are_counted_and_the_connection_kept() -> None:
    """A broker pushing messages whose topics are not UTF-8 (QoS 0 and 1): counted and
    dropped like the others, on one connection. Before: aiomqtt decoded each topic in paho's
    on_message; the first UnicodeDecodeError dropped the connection, and so at each one."""

    async def run() -> tuple[dict, HostileBroker]:
        async with (
            HostileBroker(1024 * 1024, topic=b"hostile/\xff\xfe/") as broker,
            connected_publisher(broker.port) as (proc, _),
        ):
            while not broker.report.flood_done:
                await asyncio.sleep(0.1)
            n = broker.report.flood_messages
            end = await figures_until(proc, lambda f: f["stats"]["unasked"] >= n, 30)
            return end, broker

    end, broker = asyncio.run(run())
    print(end["stats"], broker.report.connections)
    assert end["stats"]["unasked"] == broker.report.flood_messages >= 1000
    assert broker.report.connections == 1 and end["stats"]["errors"] == 0


def test_a_late_puback_for_online_does_not_drop_the_connection() -> None:
    """The broker acknowledges the retained ``online`` (QoS 1) 7 s late, as a PUBACK queued
    behind a flood comes: the connection is kept and the poses flow meanwhile. Before: aiomqtt
    gave up on it after 5 s and the connection was dropped, then again at each reconnection
    (the flapping every 5 s)."""

    async def run() -> tuple[dict, HostileBroker]:
        async with (
            HostileBroker(0, puback_delay_s=7.0) as broker,
            connected_publisher(broker.port) as (proc, _),
        ):
            await asyncio.sleep(8.0)
            end = await latest_figures(proc)
            return end, broker

    end, broker = asyncio.run(run())
    print(end["stats"], broker.report.connections, broker.report.client_publishes)
    assert broker.report.connections == 1
    assert end["stats"]["connects"] == 1 and end["stats"]["errors"] == 0
    assert broker.report.client_publishes.get("companion/7/pose", 0) >= 0.9 * POSE_HZ * 7.0


# ---------------------------------------------------------------- the status socket

# A local process opening and closing connections to a Unix socket as fast as it can
# (non-blocking connects: one refused by a full backlog is retried at once), for N seconds.
CONNECTION_FLOOD = """
import json, socket, sys, time
path, seconds = sys.argv[1], float(sys.argv[2])
end = time.monotonic() + seconds
attempts = connected = 0
while time.monotonic() < end:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.setblocking(False)
    attempts += 1
    try:
        s.connect(path)
        connected += 1
    except OSError:
        pass
    s.close()
print(json.dumps({"attempts": attempts, "connected": connected}))
"""
FLOOD_S = 3.0


async def connection_flood(path: Path, seconds: float) -> dict:
    """Run CONNECTION_FLOOD against ``path``; its counts."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-c",
        CONNECTION_FLOOD,
        str(path),
        str(seconds),
        stdout=asyncio.subprocess.PIPE,
    )
    out, _ = await proc.communicate()
    return dict(json.loads(out))


def test_a_status_socket_connection_flood_leaves_the_event_loop_to_the_service(tmp_path) -> None:
    """Another local process connects as fast as it can for 3 s. The event loop (the pose
    path's) spends a small share of its time on it, the status is made a few times a second
    for that process (not thousands), and `companion status` is answered right after it
    (in it, its connection may find the kernel's backlog full). Before: every connection was
    served (6,600/s here), the loop thread spent 74 % of the flood on it and a 10 ms sleep
    woke up to 140 ms late."""
    from companion.drivers.status import read_status
    from companion.service.status import REPLIES_PER_PEER_S, REPLY_PEER_BURST, StatusServer

    path = tmp_path / "status.sock"
    made: list[float] = []

    def provider() -> dict:
        made.append(time.monotonic())
        return SAMPLE

    async def run() -> tuple[dict, float, int, dict | None]:
        async with StatusServer(path, provider):
            loop = asyncio.get_running_loop()
            flood = asyncio.create_task(connection_flood(path, FLOOD_S))
            await asyncio.sleep(0.5)  # the flood is on
            cpu0, wall0, made0 = time.thread_time(), loop.time(), len(made)
            await asyncio.sleep(2.0)
            share = (time.thread_time() - cpu0) / (loop.time() - wall0)
            made_in_flood = len(made) - made0
            counts = await flood
            await asyncio.sleep(0.2)  # the backlog the flood left: 17 / ACCEPTS_PER_S
            after = await asyncio.to_thread(read_status, path, 1.0)
        return counts, share, made_in_flood, after

    counts, share, made_in_flood, after = asyncio.run(run())
    print(counts, f"loop thread busy {share:.1%}", made_in_flood)
    assert counts["attempts"] >= 1000, counts  # a real flood
    # 2 s measured: the flooder's replies at its rate (and its burst)
    assert made_in_flood <= REPLIES_PER_PEER_S * 2.0 + REPLY_PEER_BURST, made_in_flood
    assert share <= 0.25, share
    assert after == SAMPLE


def test_a_client_that_never_reads_is_dropped_and_others_are_served(tmp_path) -> None:
    """Clients that connect and never read a status larger than the socket's buffer: each
    is closed within the write timeout (before: held open forever, one task and one
    descriptor each), and a client that reads is served meanwhile."""
    import socket

    from companion.drivers.status import read_status
    from companion.service.status import WRITE_TIMEOUT_S, StatusServer

    path = tmp_path / "status.sock"
    big = {**SAMPLE, "warnings": ["x" * 1000] * 4000}  # 4 MB

    reply_bytes = len(json.dumps(big)) + 1

    async def run() -> tuple[list[int], dict | None, object]:
        async with StatusServer(path, lambda: big) as srv:
            idle = []
            for _ in range(4):
                s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                s.connect(str(path))
                idle.append(s)
            await asyncio.sleep(0.2)
            reader = await asyncio.to_thread(read_status, path, 5.0, 8 << 20)

            def bytes_until_closed(s: socket.socket) -> int:
                """What this client gets of its reply (now reading) before the end."""
                s.settimeout(10.0)
                got = 0
                with contextlib.suppress(OSError):
                    while chunk := s.recv(1 << 20):  # then EOF, or a reset
                        got += len(chunk)
                s.close()
                return got

            await asyncio.sleep(WRITE_TIMEOUT_S + 0.5)
            got = [await asyncio.to_thread(bytes_until_closed, s) for s in idle]
            return got, reader, srv.stats

    got, reader, stats = asyncio.run(run())
    print(reply_bytes, got, stats)
    assert reader == big
    # cut off: only what the socket's buffer took before the timeout (before: all of it,
    # once the client read at last, the server having waited for it)
    assert all(n < reply_bytes for n in got), got
    assert stats.timed_out == 4, stats  # type: ignore[attr-defined]


# ---------------------------------------------------------------- both, in a flight

FLIGHT_S = 28.0
BEFORE_S = (3.0, 7.0)  # flight time: no attack
STATUS_FLOOD_S = (7.0, 13.0)  # another process floods the status socket
MQTT_FLOOD_AT_S = 14.0  # the broker starts pushing FLIGHT_FLOOD_BYTES unasked
DRAIN_WALL_S = 120.0  # the longest wait for the service to have read the whole flood
STATUS_FLOOD_SHARE = 0.8  # of the pose rate before it, kept in the status socket's flood


def rss_kb() -> int:
    """This process's resident memory [kB]."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise RuntimeError("no VmRSS")


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_poses_keep_the_camera_rate_through_a_status_flood_and_a_hostile_broker(tmp_path) -> None:
    """The real service in a SITL flight at 30 Hz (the 320x240 camera): from 7 to 13 s of
    flight another process floods the status socket, from 14 s the MQTT broker (a hostile
    one) pushes 20 MB on topics never subscribed to. The pose rate stays within READ_SHARE
    (10 %) of the rate before in the broker's flood, and above STATUS_FLOOD_SHARE of it in the
    status flood (whose process burns a core of its own), the broker's connection is kept, the whole
    flood is counted in the status (the service runs on after the flight until it is read),
    and the memory does not grow by more than 20 MB in it. Before: 5.4 poses/s here in the
    status flood (16-19 in the issue's, the autopilot in another process), 25.9 in the
    broker's flood with its messages dropped but read flat out, and with them kept +75 MB per
    50 MB and the connection flapping."""
    from peers import sitl_flight

    from companion.service.app import Service
    from companion.service.mqtt import READ_SHARE
    from companion.sitl.stub.autopilot import SimAutopilot

    start_mqtt = asyncio.Event()

    async def fly() -> tuple[SimAutopilot, dict, dict, dict]:
        async with HostileBroker(FLIGHT_FLOOD_BYTES, FLOOD_PAYLOAD_BYTES, start_mqtt) as broker:
            cfg, opts = sitl_flight(
                tmp_path,
                FLIGHT_S,
                small=True,
                service={"mqtt": {"enabled": True, "port": broker.port, "keepalive_s": 2}},
            )
            stub = SimAutopilot(cfg, opts)
            stub_task = asyncio.create_task(stub.run(tmp_path / "autopilot"))
            sock = Path(cfg.service.status_socket)

            def t_flight() -> float:
                return float(stub.t_sim_of_mono(time.monotonic_ns()))

            async def until(t_s: float) -> None:
                while t_flight() < t_s:
                    await asyncio.sleep(0.02)

            async with Service(cfg) as service:

                async def attacks() -> dict:
                    await until(STATUS_FLOOD_S[0])
                    counts = await connection_flood(sock, STATUS_FLOOD_S[1] - STATUS_FLOOD_S[0])
                    await until(MQTT_FLOOD_AT_S)
                    rss0, peak = rss_kb(), 0
                    start_mqtt.set()
                    assert service.mqtt is not None
                    mqtt = service.mqtt
                    taken = lambda: mqtt.stats.unasked >= broker.report.flood_messages  # noqa: E731
                    # the drain may outlast the flight on a loaded box: the service keeps
                    # running after it (below) until the flood is read, or DRAIN_WALL_S
                    give_up = time.monotonic() + DRAIN_WALL_S
                    while not (broker.report.flood_done and taken()):
                        if time.monotonic() > give_up:
                            break
                        if t_flight() < FLIGHT_S - 1:  # after it, the stub's report is built here
                            peak = max(peak, rss_kb())
                        await asyncio.sleep(0.05)
                    flood_end = min(t_flight(), FLIGHT_S - 1)
                    return {
                        "status_flood": counts,
                        "growth_mb": (peak - rss0) / 1024,
                        "mqtt_flood_s": (MQTT_FLOOD_AT_S, flood_end),
                        "status": service.status(),
                    }

                attack = asyncio.create_task(attacks())

                def flight_over(_: object) -> None:
                    # stop once the attacks are measured (the flood drained), not before
                    attack.add_done_callback(lambda _: service.stop())

                stub_task.add_done_callback(flight_over)
                await service.run()
                seen = await attack
                summary = service.summary()
            report = await stub_task
            seen["broker"] = broker.report
        return stub, report, summary, seen

    stub, report, summary, seen = asyncio.run(fly())
    rec = [r for r in stub.stats.received if r.kind == report["message"]]
    t_pose = np.array([r.t_sim_s for r in rec])

    def rate(lo: float, hi: float) -> float:
        return float(((t_pose >= lo) & (t_pose < hi)).sum() / (hi - lo))

    before = rate(*BEFORE_S)
    in_status = rate(STATUS_FLOOD_S[0] + 0.5, STATUS_FLOOD_S[1] - 0.5)
    lo, hi = seen["mqtt_flood_s"]
    in_mqtt = rate(lo + 0.5, min(max(hi, lo + 2.0), FLIGHT_S - 0.5))
    broker = seen["broker"]
    print(f"poses/s before {before:.1f}, status flood {in_status:.1f}, MQTT flood {in_mqtt:.1f}")
    print(seen["status_flood"], seen["growth_mb"], seen["mqtt_flood_s"], summary["mqtt"])
    print(summary["status_socket"], broker.flood_messages, broker.connections)
    print("poses per flight second", np.bincount(t_pose.astype(int)).tolist())
    assert seen["status_flood"]["attempts"] >= 1000  # a real flood
    assert broker.flood_done and broker.connections == 1
    assert broker.closed_by_client_during_flood == 0
    assert summary["mqtt"]["connects"] == 1 and summary["mqtt"]["errors"] == 0
    assert seen["status"]["mqtt"]["unasked"] == broker.flood_messages
    assert seen["growth_mb"] <= 20.0, seen["growth_mb"]
    # reading the broker may take READ_SHARE of the loop's time by design; the world, the
    # stub and this broker share this process's core with the service, so on a busy box
    # that share comes off the pose rate (27.2-28.6 Hz measured alone on a 2-core AMD EPYC)
    assert in_mqtt >= (1.0 - READ_SHARE) * before, (before, in_status, in_mqtt)
    # the flooding process burns a core of its own: with another test beside it on 2 cores
    # 24.4 of 27.5 poses/s (0.89) were measured; the fault this guards against gave 5.4 of 30
    assert in_status >= STATUS_FLOOD_SHARE * before, (before, in_status, in_mqtt)
