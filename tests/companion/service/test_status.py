"""The status socket and `companion status` against a real Unix socket."""

from __future__ import annotations

import asyncio
import json
import os
import stat
import threading

import pytest
from peers.status import SAMPLE, halt, serve_in_thread

from companion.cli import EXIT_NOT_RUNNING, format_status, main
from companion.drivers.status import read_status, status_path
from companion.errors import ConfigError
from companion.service.status import StatusServer


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
        "PX4 stamps on arrival: poses sent as of sending (12)",
        "stamps jitter 15.7 ms rms: 412 frames re-timed",
        "focal x0.914, k1 -0.004 over 134 pairs  camera focal length looks 8.5 % too large",
    ):
        assert text in table, text


def test_default_socket_paths(monkeypatch) -> None:
    monkeypatch.setenv("RUNTIME_DIRECTORY", "/run/companion")
    assert str(status_path("")) == "/run/companion/status.sock"
    monkeypatch.delenv("RUNTIME_DIRECTORY")
    monkeypatch.setenv("XDG_RUNTIME_DIR", "/run/user/1000")
    assert str(status_path("")) == "/run/user/1000/companion.sock"
    assert str(status_path("/x/y.sock")) == "/x/y.sock"


# ---------------------------------------------------------------- what is never removed


def _start(path):
    async def enter() -> None:
        async with StatusServer(path, lambda: SAMPLE):
            pass

    asyncio.run(enter())


def test_a_regular_file_at_the_socket_path_is_never_deleted(tmp_path) -> None:
    victim = tmp_path / "passwd"
    victim.write_text("root:x:0:0\n")
    with pytest.raises(ConfigError, match=r"service\.status_socket: .* not a socket"):
        _start(victim)
    assert victim.read_text() == "root:x:0:0\n"


def test_a_directory_or_a_symlink_at_the_socket_path_is_a_config_error(tmp_path) -> None:
    folder = tmp_path / "dir"
    folder.mkdir()
    with pytest.raises(ConfigError, match=r"service\.status_socket: .* is a directory"):
        _start(folder)
    target = tmp_path / "target"
    target.write_text("keep")
    link = tmp_path / "link.sock"
    link.symlink_to(target)
    with pytest.raises(ConfigError, match=r"service\.status_socket: .* not a socket"):
        _start(link)
    assert link.is_symlink() and target.read_text() == "keep"


def test_a_socket_of_another_user_is_never_deleted(tmp_path) -> None:
    import socket

    path = tmp_path / "theirs.sock"
    s = socket.socket(socket.AF_UNIX)
    s.bind(str(path))
    s.close()
    os.chown(path, 4242, 4242)  # the tests run as root (make test installs with apt-get)
    with pytest.raises(ConfigError, match=r"owned by uid 4242"):
        _start(path)
    assert path.is_socket()


@pytest.mark.parametrize(
    ("name", "message"),
    [("a\x00b.sock", "NUL"), ("x" * 120 + ".sock", "longer than a Unix socket path")],
)
def test_impossible_socket_paths_are_config_errors(tmp_path, name, message) -> None:
    with pytest.raises(ConfigError, match=rf"service\.status_socket: .*{message}"):
        _start(tmp_path / name)


# ---------------------------------------------------------------- what the client believes


def fake_server(path, payload: bytes, repeat: int = 1):
    """A Unix socket at path that answers every client with payload * repeat."""
    import socket

    srv = socket.socket(socket.AF_UNIX)
    srv.bind(str(path))
    srv.listen(4)
    stop = threading.Event()

    def serve() -> None:
        srv.settimeout(0.1)
        while not stop.is_set():
            try:
                conn, _ = srv.accept()
            except OSError:
                continue
            with conn:
                try:
                    for _ in range(repeat):
                        conn.sendall(payload)
                except OSError:
                    pass

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    return stop, srv, t


@pytest.mark.parametrize(
    ("payload", "repeat", "message"),
    [
        (b'{"hello": 1}\n', 1, "missing 'uptime_s'"),
        (json.dumps({**SAMPLE, "vo": {"state": 3}}).encode(), 1, "'vo.state' has type int"),
        (b"\xff\xfe not json", 1, "not JSON"),
        (b"[1, 2, 3]", 1, "expected an object"),
        (b"x" * 65536, 64, "longer than"),  # 4 MiB: more than any status
    ],
)
def test_cli_status_refuses_what_is_not_a_status(tmp_path, capsys, payload, repeat, message):
    path = tmp_path / "fake.sock"
    stop, srv, t = fake_server(path, payload, repeat)
    try:
        rc = main(["status", "--socket", str(path)])
    finally:
        stop.set()
        t.join(2)
        srv.close()
    err = capsys.readouterr().err
    assert rc == 1, err
    assert message in err and "Traceback" not in err


def test_a_socket_of_another_user_in_a_world_writable_folder_is_not_trusted(tmp_path) -> None:
    from companion.drivers.status import StatusError

    shared = tmp_path / "tmp"
    shared.mkdir()
    shared.chmod(0o1777)  # as /tmp
    path = shared / "companion-0.sock"
    stop, srv, t = fake_server(path, json.dumps(SAMPLE).encode())
    try:
        assert read_status(path) == SAMPLE  # ours: believed
        os.chown(path, 4242, 4242)  # somebody else's, made before the service started
        with pytest.raises(StatusError, match="not trusted"):
            read_status(path)
        shared.chmod(0o755)  # a folder only its owner writes to: the owner vouches for it
        assert read_status(path) == SAMPLE
    finally:
        stop.set()
        t.join(2)
        srv.close()


def test_the_frame_line_says_state_agreement_alignment_and_gps() -> None:
    assert "frame" not in SAMPLE or not SAMPLE["frame"].get("enabled")
    (off,) = [x for x in format_status(SAMPLE).splitlines() if x.startswith("frame ")]
    assert off.split(None, 1)[1] == "own (gps.align off)"
    frame = {
        "enabled": True,
        "state": "held",
        "agreement_m": None,
        "to_target_m": 0.0,
        "yaw_deg": 36.94,
        "translation_ned_m": [5.01, -2.98, 0.0],
        "age_s": 4.2,
        "reason": "GPS lost",
        "gps": {"good": False, "reasons": ["fix type 1 < 3", "3 satellites < 6"], "origin": True},
        "handover": [],
    }
    (line,) = [
        x for x in format_status({**SAMPLE, "frame": frame}).splitlines() if x.startswith("frame ")
    ]
    for text in ("held", "agree -", "yaw 36.94°", "(5.01, -2.98, 0.00) m", "fit age 4.2 s"):
        assert text in line, line
    assert "GPS bad: fix type 1 < 3; 3 satellites < 6" in line


def test_a_scale_filter_held_outside_its_gate_gets_its_own_row() -> None:
    assert not [x for x in format_status(SAMPLE).splitlines() if x.lstrip().startswith("filter")]
    held = {**SAMPLE, "scale": {**SAMPLE["scale"], "outside_gate_s": 37.2, "recoveries": 0}}
    (row,) = [x for x in format_status(held).splitlines() if x.lstrip().startswith("filter")]
    assert row.split(None, 1)[1] == "every measurement outside its gate for 37.2 s"
    held["scale"] = {**SAMPLE["scale"], "outside_gate_s": 0.4, "recoveries": 2}
    (row,) = [x for x in format_status(held).splitlines() if x.lstrip().startswith("filter")]
    assert row.split(None, 1)[1] == "restarted at them 2 time(s)"
