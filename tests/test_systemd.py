"""sd_notify against a real Unix datagram socket, the watchdog from the event loop, and the
unit file checked by systemd-analyze."""

from __future__ import annotations

import asyncio
import itertools
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from companion.service.systemd import SdNotify

UNIT = Path(__file__).resolve().parents[1] / "systemd" / "companion.service"


def listener(tmp_path: Path) -> tuple[socket.socket, str]:
    path = str(tmp_path / "notify.sock")
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(path)
    s.settimeout(2.0)
    return s, path


def test_ready_watchdog_stopping_reach_the_socket(tmp_path) -> None:
    s, path = listener(tmp_path)
    with s:
        sd = SdNotify({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"})
        assert sd.enabled and sd.watchdog_s == pytest.approx(2.0)
        assert sd.ready("link up")
        assert s.recv(4096).decode().split("\n") == ["READY=1", "STATUS=link up"]
        assert sd.watchdog()
        assert s.recv(4096) == b"WATCHDOG=1"
        assert sd.stopping()
        assert s.recv(4096).decode().startswith("STOPPING=1")


def test_outside_systemd_nothing_is_sent_and_other_pids_watchdog_is_ignored() -> None:
    sd = SdNotify({})
    assert not sd.enabled and not sd.ready("x") and sd.watchdog_s is None
    other = SdNotify(
        {"NOTIFY_SOCKET": "/nonexistent", "WATCHDOG_USEC": "1000", "WATCHDOG_PID": "1"}
    )
    assert other.watchdog_s is None  # meant for another process
    assert not other.notify("READY=1")  # a socket that is not there: False, no exception


def test_abstract_socket_names() -> None:
    assert SdNotify({"NOTIFY_SOCKET": "@/org/freedesktop/x"}).address == "\0/org/freedesktop/x"


def test_watchdog_pings_stop_when_the_event_loop_is_stuck(tmp_path) -> None:
    """The service's watchdog loop, driven by a real loop: pings every half interval, and
    none while the loop is blocked (systemd would then restart the service)."""
    from peers import service_config

    from companion.service.app import Service

    s, path = listener(tmp_path)
    s.setblocking(False)
    env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "200000"}
    cfg = service_config(tmp_path)
    stamps: list[tuple[float, bytes]] = []

    async def run() -> None:
        old = dict(os.environ)
        os.environ.update(env)
        try:
            service = Service(cfg)
        finally:
            os.environ.clear()
            os.environ.update(old)
        async with service:
            t_end = time.monotonic() + 1.0
            while time.monotonic() < t_end:
                await asyncio.sleep(0.01)
                drain()
            time.sleep(0.6)  # the loop is stuck: no pings can be sent
            blocked_until = time.monotonic()
            drain()
            stamps.append((blocked_until, b"--"))
            await asyncio.sleep(0.5)
            drain()

    def drain() -> None:
        while True:
            try:
                stamps.append((time.monotonic(), s.recv(4096)))
            except BlockingIOError:
                return

    with s:
        asyncio.run(run())
        drain()  # STOPPING=1 was sent on the way out
    msgs = [m for _, m in stamps]
    assert msgs[0].startswith(b"READY=1")
    before = msgs[: msgs.index(b"--")]
    assert before.count(b"WATCHDOG=1") >= 8  # 1 s at one ping per 0.1 s
    times = [t for t, m in stamps if m == b"WATCHDOG=1"]
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert max(gaps) >= 0.55  # the stuck second: nothing was sent
    assert any(m.startswith(b"STOPPING=1") for m in msgs)


def test_unit_file_passes_systemd_analyze_verify(tmp_path) -> None:
    if shutil.which("systemd-analyze") is None:  # Debian's systemd package has it
        pytest.fail("systemd-analyze is not installed: the unit file cannot be verified")
    text = UNIT.read_text()
    for key in (
        "Type=notify",
        "WatchdogSec=",
        "Restart=on-failure",
        "NoNewPrivileges=yes",
        "ProtectSystem=strict",
        "ProtectHome=yes",
        "PrivateTmp=yes",
        "RestrictAddressFamilies=",
        "SupplementaryGroups=dialout video",
        "RuntimeDirectory=companion",
        "StateDirectory=companion",
    ):
        assert key in text, key
    # the installed path does not exist here: point ExecStart at this interpreter
    unit = tmp_path / "companion.service"
    unit.write_text(
        text.replace("/opt/companion/.venv/bin/companion", f"{sys.executable} -m companion.cli")
    )
    r = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
