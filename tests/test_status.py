"""The status socket and `companion status` against a real Unix socket."""

from __future__ import annotations

import asyncio
import json
import os
import stat
import threading

import pytest

from companion.cli import EXIT_NOT_RUNNING, format_status, main
from companion.errors import ConfigError
from companion.service.status import StatusServer, read_status, status_path

SAMPLE = {
    "uptime_s": 12.5,
    "autopilot": {
        "url": "udpin:127.0.0.1:14540",
        "heartbeat_age_s": 0.4,
        "system_id": 1,
        "timesync_converged": True,
        "timesync_offset_ms": 10608.123,
        "timesync_rtt_ms": 0.21,
        "rates_acknowledged": [30, 132],
        "rx_messages": 1000,
        "rx_bad": 2,
    },
    "camera": {
        "url": "sitl://127.0.0.1:5600",
        "fps": 29.9,
        "frames": 370,
        "dropped": 1,
        "last_frame_age_s": 0.02,
    },
    "vo": {"state": "TRACKING", "features": 180, "keyframes": 9, "resets": 0},
    "scale": {
        "method": "M-MSCwK",
        "value": 5.93,
        "sigma": 0.004,
        "sensors_used": 4,
        "ranges_in": 2400,
        "ranges_rejected": 0,
    },
    "attitude": {
        "roll_deg": 1.2,
        "pitch_deg": -0.4,
        "sigma_deg": 0.05,
        "compensation": True,
        "reasons": ["sensor 2: hit 0.31 m off the surface around it (edge?)"],
    },
    "output": {
        "message": "vision_position_estimate",
        "rate_hz": 30.0,
        "published": 300,
        "reset_counter": 0,
        "latency_ms_p50": 12.1,
    },
    "mqtt": {"enabled": False},
    "warnings": ["camera: stream ended; reopening"],
}


def serve_in_thread(path, provider):
    """Run a StatusServer on its own event loop in a thread; returns (stop, thread)."""
    ready = threading.Event()
    stop: dict = {}

    def run() -> None:
        async def main_() -> None:
            stop["event"] = asyncio.Event()
            stop["loop"] = asyncio.get_running_loop()
            async with StatusServer(path, provider) as srv:
                stop["server"] = srv
                ready.set()
                await stop["event"].wait()

        asyncio.run(main_())

    t = threading.Thread(target=run)
    t.start()
    assert ready.wait(5)
    return stop, t


def halt(stop, t) -> None:
    stop["loop"].call_soon_threadsafe(stop["event"].set)
    t.join(5)


def test_status_socket_serves_json_with_group_only_permissions(tmp_path) -> None:
    path = tmp_path / "status.sock"
    stop, t = serve_in_thread(path, lambda: SAMPLE)
    try:
        assert stat.S_IMODE(os.stat(path).st_mode) == 0o660
        assert read_status(path) == SAMPLE
        assert read_status(path) == SAMPLE
        assert stop["server"].requests == 2
    finally:
        halt(stop, t)
    assert not path.exists()  # removed on exit
    assert read_status(path) is None


def test_a_stale_socket_is_replaced_and_a_live_one_refused(tmp_path) -> None:
    import socket

    path = tmp_path / "status.sock"
    stale = socket.socket(socket.AF_UNIX)
    stale.bind(str(path))  # a file left by a crashed run, nobody listening
    stale.close()
    stop, t = serve_in_thread(path, lambda: SAMPLE)
    try:
        assert read_status(path) == SAMPLE

        async def second() -> None:
            async with StatusServer(path, lambda: {}):
                pass

        with pytest.raises(ConfigError, match=r"service\.status_socket: .* in use"):
            asyncio.run(second())
    finally:
        halt(stop, t)


def test_cli_status_not_running_exits_3(tmp_path, capsys) -> None:
    rc = main(["status", "--socket", str(tmp_path / "none.sock")])
    out = capsys.readouterr().out
    assert rc == EXIT_NOT_RUNNING == 3
    assert out.count("\n") == 1 and "not running" in out


def test_cli_status_table_and_json(tmp_path, capsys) -> None:
    path = tmp_path / "status.sock"
    stop, t = serve_in_thread(path, lambda: SAMPLE)
    try:
        assert main(["status", "--socket", str(path), "--json"]) == 0
        assert json.loads(capsys.readouterr().out) == SAMPLE
        assert main(["status", "--socket", str(path)]) == 0
        table = capsys.readouterr().out
    finally:
        halt(stop, t)
    assert table == format_status(SAMPLE) + "\n"
    for text in (
        "TRACKING",
        "29.9 fps",
        "1 dropped",
        "M-MSCwK",
        "converged",
        "30.0 Hz",
        "camera: stream ended",
        "edge?",
        "disabled",
    ):
        assert text in table, text


def test_default_socket_paths(monkeypatch) -> None:
    monkeypatch.setenv("RUNTIME_DIRECTORY", "/run/companion")
    assert str(status_path("")) == "/run/companion/status.sock"
    monkeypatch.delenv("RUNTIME_DIRECTORY")
    monkeypatch.setenv("XDG_RUNTIME_DIR", "/run/user/1000")
    assert str(status_path("")) == "/run/user/1000/companion.sock"
    assert str(status_path("/x/y.sock")) == "/x/y.sock"
