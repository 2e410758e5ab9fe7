"""What the service must never show or break: credentials in camera URLs (in logs, the status and
the report), a full disk under its exit report and recorder, a FIFO planted where its state or
key files go."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from peers import free_port, service_config

from companion.drivers.status import read_status
from companion.service.app import Service


def test_credentials_in_the_camera_url_are_never_shown(tmp_path, caplog) -> None:
    from peers import MOSQUITTO, Broker

    from companion.config import describe

    if not os.path.exists(MOSQUITTO):
        pytest.fail("mosquitto is not installed (make test installs it with apt-get)")
    broker = Broker(tmp_path)
    broker.start()
    url = f"rtsp://pilot:hunter2secret@127.0.0.1:{free_port()}/live"
    cfg = service_config(
        tmp_path, camera_url=url, mqtt={"enabled": True, "port": broker.port, "keepalive_s": 2}
    )
    import aiomqtt

    async def main() -> tuple[list[bytes], dict | None, dict]:
        got: list[bytes] = []

        async def listen() -> None:
            async with aiomqtt.Client("127.0.0.1", broker.port) as sub:
                await sub.subscribe("companion/#")
                async for msg in sub.messages:
                    got.append(bytes(msg.payload))  # type: ignore[arg-type]

        listener = asyncio.create_task(listen())
        async with Service(cfg) as service:
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not any(
                "cannot open" in w for w in service.stats.warnings
            ):
                await asyncio.sleep(0.1)
            await asyncio.sleep(1.5)  # a status or two on MQTT
            status = await asyncio.to_thread(read_status, tmp_path / "status.sock")
            summary = service.summary()
        listener.cancel()
        return got, status, summary

    try:
        with caplog.at_level("DEBUG"):
            got, status, summary = asyncio.run(main())
    finally:
        broker.stop()
    shown = "\n".join(
        [*(g.decode() for g in got), json.dumps(status), json.dumps(summary, default=str)]
        + [r.getMessage() for r in caplog.records]
        + describe(cfg)
    )
    assert "cannot open" in shown  # the driver's error quoting the URL did reach everything...
    assert "rtsp://pilot:***@127.0.0.1" in shown
    assert "hunter2secret" not in shown  # ...with the password masked everywhere
    assert len(got) >= 2


def test_redaction_knows_gstreamer_credentials_and_passwords_with_at() -> None:
    from companion.redact import redact_text, redact_url, url_secrets

    pipeline = (
        "gst:rtspsrc location=rtsp://pilot:p@ss@w0rd@cam.local/live user-id=gstuser "
        'user-pw="hunter2 secret" proxy-id=proxyman proxy-pw=pr0xy@pw ! decodebin ! '
        "videoconvert ! appsink srtsrc passphrase=longpassphrase"
    )
    shown = redact_url(pipeline)
    for secret in ("p@ss@w0rd", "ss@w0rd", "w0rd", "gstuser", "hunter2", "proxyman", "pr0xy"):
        assert secret not in shown, (secret, shown)
    assert "longpassphrase" not in shown
    assert "rtsp://pilot:***@cam.local/live" in shown and "user-pw=*** proxy-id=***" in shown
    assert "! decodebin ! videoconvert ! appsink" in shown  # the rest as it was
    secrets = url_secrets(pipeline)
    assert {"p@ss@w0rd", "hunter2 secret", "pr0xy@pw", "longpassphrase"} <= set(secrets)
    error = "camera gst: rtspsrc0: Unauthorized (hunter2 secret; p%40ss@w0rd)"
    assert "hunter2" not in redact_text(error, secrets)  # a secret quoted anywhere
    # a one-letter password: masked in its URL, never searched for in every warning
    text = "camera: pipeline stopped; reopening (appsink), autopilot happy"
    assert redact_text(text, url_secrets("rtsp://u:p@cam/x")) == text
    assert redact_url("rtsp://u:p@cam/x") == "rtsp://u:***@cam/x"
    assert redact_text(text, ["p", "pp", "ing"]) == text


def test_gst_credentials_are_never_shown(tmp_path, caplog) -> None:
    """A gst: camera with credentials in its location (a password with '@') and in
    souphttpsrc's properties, against a camera that is not there: GStreamer's error quotes
    the location; neither the log, the warnings, the status nor the summary shows them, and
    a warning with many 'p' is left as it is."""
    pytest.importorskip("gi")
    from companion.config import describe

    url = (
        f"gst:souphttpsrc location=http://pilot:p@ssw0rd@127.0.0.1:{free_port()}/cam.mjpg "
        "user-id=gstpilot user-pw=hunter2@s3kr1t proxy-id=proxyman proxy-pw=pr0xy@pw "
        "! multipartdemux ! jpegdec ! videoconvert ! appsink"
    )
    cfg = service_config(tmp_path, camera_url=url)
    plain = "camera: pipeline stopped; reopening (appsink), autopilot happy"

    async def main() -> tuple[dict, dict, list[str]]:
        async with Service(cfg) as service:
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not any(
                "reopening until" in w for w in service.stats.warnings
            ):
                await asyncio.sleep(0.1)
            service.runtime.warn(plain)
            status = await asyncio.to_thread(read_status, tmp_path / "status.sock")
            return status or {}, service.summary(), list(service.stats.warnings)

    with caplog.at_level("DEBUG"):
        status, summary, warnings = asyncio.run(main())
    shown = "\n".join(
        [json.dumps(status), json.dumps(summary, default=str), *warnings]
        + [r.getMessage() for r in caplog.records]
        + describe(cfg)
    )
    assert any("reopening until" in w for w in warnings), warnings
    assert "http://pilot:***@127.0.0.1" in shown and "user-pw=***" in shown
    for secret in ("ssw0rd", "gstpilot", "hunter2", "s3kr1t", "proxyman", "pr0xy"):
        assert secret not in shown, secret
    assert warnings[-1] == plain


@pytest.fixture
def full_disk(tmp_path):
    """A 64 kB tmpfs filled to the last byte (mounting needs root: make test runs as root)."""
    mnt = tmp_path / "full"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)])
    if r.returncode != 0:
        pytest.skip("cannot mount a tmpfs to fill (needs root): the full-disk case is not run")
    try:
        (mnt / "report.json").write_text('{"old": true}\n')  # a report of an earlier run
        with open(mnt / "filler", "wb", buffering=0) as fh, contextlib.suppress(OSError):
            while True:
                fh.write(b"\0" * 4096)
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)])


def run_service_alone(
    tmp_path: Path, duration_s: str, *args: str, tables: str = ""
) -> subprocess.CompletedProcess[str]:
    """`companion run --duration duration_s *args` with no peers: the autopilot link on a free
    loopback UDP port, a camera URL where nothing listens, its status socket and state in
    ``tmp_path``; ``tables``: more of the config (TOML)."""
    conf = tmp_path / "c.toml"
    conf.write_text(
        "[service]\n"
        f'mavlink_url = "udpin:127.0.0.1:{free_port(socket.SOCK_DGRAM)}"\n'
        f'camera_url = "sitl://127.0.0.1:{free_port()}"\n'
        f'status_socket = "{tmp_path / "s.sock"}"\n'
        f'state_dir = "{tmp_path / "state"}"\n' + tables
    )
    run = ["run", "--config", str(conf), "--duration", duration_s, *args]
    return subprocess.run(
        [sys.executable, "-m", "companion.cli", *run],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).resolve().parents[2],
    )


def test_an_exit_report_on_a_full_disk_is_a_warning_and_leaves_no_torn_file(
    tmp_path, full_disk
) -> None:
    r = run_service_alone(tmp_path, "1", "--report", str(full_disk / "report.json"))
    assert r.returncode == 0, r.stderr
    assert "exit report not written" in r.stderr and "Traceback" not in r.stderr
    assert (full_disk / "report.json").read_text() == '{"old": true}\n'  # untouched
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler", "report.json"]


def test_a_used_record_dir_on_a_full_disk_is_a_warning_never_an_exit(tmp_path, full_disk) -> None:
    """record.dir without {start}, holding an earlier run, on a full disk (a reboot of a
    drone whose recordings filled its card): the service runs, says why it does not
    record, and exits 0 at the end of its run (it used to exit 2 at each start: a restart
    loop with no output at all)."""
    rec = full_disk / "rec"
    rec.mkdir()
    (rec / "meta.toml").touch()  # an earlier run's (an inode: no byte of data needed)
    r = run_service_alone(tmp_path, "2", tables=f'[record]\ndir = "{rec}"\n')
    assert r.returncode == 0, r.stderr
    said = [line for line in r.stderr.splitlines() if "recorder:" in line]
    assert said and "Traceback" not in r.stderr
    assert any("cannot record into" in line for line in said), said
    assert sorted(p.name for p in rec.iterdir()) == ["meta.toml"]  # the earlier run: as it was


def test_a_fifo_planted_at_a_state_or_key_file_is_refused_at_once(tmp_path) -> None:
    """The service reads its reset counter, signing timestamp and key at start-up; a FIFO put
    at one of those paths after `companion config` checked them (or by a hostile local user)
    blocked the read for good (an open for reading waits for a writer). Each is now refused
    at once: the reset counter takes its base from the clock, the timestamp and the key are a
    config error naming the key."""
    import threading

    from companion.drivers.signing import TimestampStore, load_key
    from companion.errors import ConfigError
    from companion.service.state import ResetCounter

    outcomes: dict[str, str] = {}

    def attempt(name: str, call: Any) -> threading.Thread:
        def run() -> None:
            try:
                call()
                outcomes[name] = "read"
            except ConfigError as e:
                outcomes[name] = f"refused: {e}"

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        return thread

    fifos = {name: tmp_path / name for name in ("reset_counter", "timestamp", "key")}
    for path in fifos.values():
        os.mkfifo(path, 0o600)
    threads = {
        "reset_counter": attempt("reset_counter", lambda: ResetCounter(fifos["reset_counter"])),
        "timestamp": attempt("timestamp", lambda: TimestampStore(fifos["timestamp"]).read()),
        "key": attempt("key", lambda: load_key(fifos["key"])),
    }
    try:
        for name, thread in threads.items():
            thread.join(5.0)
            assert not thread.is_alive(), f"{name}: blocked on the FIFO"
    finally:  # a blocked reader (the old code) is let go: a writer opens and closes
        for name, thread in threads.items():
            if thread.is_alive():
                with contextlib.suppress(OSError):
                    os.close(os.open(fifos[name], os.O_WRONLY | os.O_NONBLOCK))
    assert outcomes["reset_counter"] == "read", outcomes  # base from the clock, warned
    assert outcomes["timestamp"].startswith("refused") and "FIFO" in outcomes["timestamp"]
    assert outcomes["key"].startswith("refused") and "regular file" in outcomes["key"]
