"""MQTT telemetry against a real Mosquitto broker started on 127.0.0.1 (installed by make)."""

from __future__ import annotations

import asyncio
import inspect
import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import aiomqtt
import pytest
from peers import MOSQUITTO, Broker

from companion.config import describe, load_config
from companion.service.mqtt import MqttPublisher, ReadBudget
from companion.service_options import MqttOptions


@pytest.fixture
def broker(tmp_path):
    if not Path(MOSQUITTO).exists():
        pytest.fail("mosquitto is not installed (make test installs it with apt-get)")
    b = Broker(tmp_path)
    b.start()
    yield b
    b.stop()


async def collect(port: int, topic: str, n: int, timeout_s: float = 10.0) -> list:
    got: list = []
    async with aiomqtt.Client("127.0.0.1", port) as sub:
        await sub.subscribe(topic)
        async with asyncio.timeout(timeout_s):
            async for msg in sub.messages:
                got.append((str(msg.topic), json.loads(msg.payload), msg.retain))
                if len(got) >= n:
                    break
    return got


def opts(port: int, **kw) -> MqttOptions:
    return MqttOptions(enabled=True, port=port, keepalive_s=2, **kw)


def test_status_pose_and_events_reach_a_subscriber(broker) -> None:
    async def run() -> list:
        async with MqttPublisher(opts(broker.port), 7) as pub:
            listener = asyncio.create_task(collect(broker.port, "companion/7/#", 4))
            await asyncio.sleep(0.5)
            pub.publish_status({"vo": "TRACKING"})
            pub.publish_pose({"position_ned_m": [1.0, 2.0, -3.0]})
            pub.publish_event("VO re-initialised: reset_counter 1")
            got = await listener
            assert pub.stats.connected and pub.stats.dropped == 0
            return got

    got = asyncio.run(run())
    by_topic = {t: (p, r) for t, p, r in got}
    assert by_topic["companion/7/status"][0]["state"] == "online"
    assert by_topic["companion/7/pose"][0]["position_ned_m"] == [1.0, 2.0, -3.0]
    assert "reset_counter 1" in by_topic["companion/7/events"][0]["event"]
    # the status is retained: a late subscriber gets the last one at once
    late = asyncio.run(collect(broker.port, "companion/7/status", 1, timeout_s=3))
    assert late[0][2] is True


def test_broker_down_never_blocks_and_oldest_are_dropped_then_resume(broker, monkeypatch) -> None:
    broker.stop()

    async def run() -> tuple[MqttPublisher, list[str], list]:
        async with MqttPublisher(opts(broker.port, queue_size=50), 3) as pub:
            # publishing is a plain call that only queues: no socket is touched in it (a
            # blocking connect would fail this); its cost is profiled, not timed here
            calls: list[str] = []
            real_connect, real_send = socket.socket.connect, socket.socket.send
            monkeypatch.setattr(socket.socket, "connect", lambda *a: calls.append("connect"))
            monkeypatch.setattr(socket.socket, "send", lambda *a: calls.append("send") or 0)
            for k in range(500):
                pub.publish_pose({"k": k})
            monkeypatch.setattr(socket.socket, "connect", real_connect)
            monkeypatch.setattr(socket.socket, "send", real_send)
            touched = list(calls)
            await asyncio.sleep(1.0)
            assert not pub.stats.connected
            assert pub.queued == 50 and pub.stats.dropped == 450
            broker.start()  # back: the publisher reconnects by itself (backoff <= a few s)
            got = await collect(broker.port, "companion/3/pose", 1, timeout_s=15)
            await asyncio.sleep(0.5)
            return pub, touched, got

    pub, touched, got = asyncio.run(run())
    assert not inspect.iscoroutinefunction(MqttPublisher.publish_pose) and touched == []
    assert pub.stats.connects >= 1 and pub.stats.published >= 1
    assert got[0][1]["k"] >= 450  # what survived the outage is the newest


def test_last_will_says_offline_when_the_service_dies(broker, tmp_path) -> None:
    script = tmp_path / "pub.py"
    script.write_text(
        "import asyncio, sys\n"
        "from companion.service.mqtt import MqttPublisher\n"
        "from companion.service_options import MqttOptions\n"
        "async def main():\n"
        f"    async with MqttPublisher(MqttOptions(enabled=True, port={broker.port}), 9) as p:\n"
        "        p.publish_status({'vo': 'TRACKING'})\n"
        "        await asyncio.sleep(0.5)\n"
        "        print('up', flush=True)\n"
        "        await asyncio.sleep(60)\n"
        "asyncio.run(main())\n"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[3])}
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, env=env)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == b"up"

        async def watch() -> list:
            listener = asyncio.create_task(collect(broker.port, "companion/9/status", 2))
            await asyncio.sleep(0.5)
            proc.send_signal(signal.SIGKILL)  # no DISCONNECT: the broker sends the will
            return await listener

        got = asyncio.run(watch())
    finally:
        proc.kill()
        proc.wait()
    states = [payload["state"] for _, payload, _ in got]
    assert states[0] == "online" and states[-1] == "offline"


def test_the_password_is_never_in_the_startup_log() -> None:
    cfg = load_config(overrides={"service": {"mqtt": {"password": "hunter2", "username": "u"}}})
    text = "\n".join(describe(cfg))
    assert "hunter2" not in text
    assert "service.mqtt.password = '***'" in text


def test_a_clean_stop_says_offline_too(broker) -> None:
    async def run() -> None:
        async with MqttPublisher(opts(broker.port), 5) as pub:
            pub.publish_status({"vo": "TRACKING"})
            pub.publish_event("stopping")
            for _ in range(100):
                if pub.stats.published >= 2:
                    break
                await asyncio.sleep(0.05)

    asyncio.run(run())
    got = asyncio.run(collect(broker.port, "companion/5/status", 1, timeout_s=3))
    assert got[0][1] == {"state": "offline"} and got[0][2] is True  # retained, after the stop


def test_a_failing_connection_is_logged_and_retried_never_silent(tmp_path, caplog) -> None:
    """A CA file that went away after the config check (or any other failure inside the
    sender) used to end the task silently and the stop in a traceback."""
    missing = tmp_path / "ca.pem"

    async def run() -> MqttPublisher:
        async with MqttPublisher(opts(1, tls=True, ca_file=str(missing)), 4) as pub:
            for _ in range(100):
                if pub.stats.errors >= 2:
                    break
                await asyncio.sleep(0.1)
            assert pub._task is not None and not pub._task.done()  # alive, retrying
        return pub

    with caplog.at_level("WARNING", logger="companion.mqtt"):
        pub = asyncio.run(run())  # and the stop raises nothing
    assert pub.stats.errors >= 2 and "ca.pem" in pub.stats.last_error
    said = [r.getMessage() for r in caplog.records if "cannot connect" in r.getMessage()]
    assert len(said) == 1 and "ca.pem" in said[0]  # once per distinct error, not per retry


def test_the_read_budget_holds_its_share_and_never_starves_the_keepalive() -> None:
    """Reading the broker's socket may take 10 % of each 0.1 s: within it no pause; past it a
    pause that brings the share back; and no pause is longer than its cap (a quarter of the
    keepalive), however long a read took (a loaded machine stretches one)."""
    budget = ReadBudget(0.1, 0.1, max_pause_s=0.5)
    assert budget.spend(0.0, 0.005) == 0.0  # 5 ms of the 10 ms allowed
    pause_s = budget.spend(0.006, 0.020)  # 19 ms read: the window lasts 0.19 s
    assert pause_s == pytest.approx(0.19 - 0.020)
    assert budget.spend(1.0, 1.001) == 0.0  # a new window
    # a read of 0.3 s would ask for 3 s of pause: capped
    assert budget.spend(3.0, 3.3) == 0.5
