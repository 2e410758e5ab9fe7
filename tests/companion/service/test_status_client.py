"""`companion status` (the client) on a hostile reply: whatever answers on the socket, the
command ends in one line (exit 1, or one JSON object under --json), never a traceback, and
prints no terminal escape it was sent (the issue "Reliability round 3")."""

from __future__ import annotations

import contextlib
import copy
import json
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from peers.status import SAMPLE as STATUS_SAMPLE

from companion.cli import main
from companion.drivers.status import printable

# the server tests' sample, with what the client must also take: a camera problem and its
# rejections, an unknown sigma (NaN), the match rates and a connected broker
SAMPLE: dict[str, Any] = copy.deepcopy(STATUS_SAMPLE)
SAMPLE["autopilot"]["signing"] = {
    "good_signatures": 10,
    "bad_signatures": 0,
    "refused": 0,
    "far_ahead_s": 0.5,
}
SAMPLE["camera"].update(problem=None, rejected={"size": 2})
SAMPLE["scale"].update(sigma=float("nan"), match_rate={"0": 0.9})
SAMPLE["attitude"]["reasons"] = ["sensor 2: edge?"]
SAMPLE["mqtt"] = {"enabled": True, "connected": True, "queued": 0, "dropped": 0}


@pytest.fixture
def serve(tmp_path: Path) -> Iterator[Any]:
    """serve(payload) -> the path of a Unix socket answering every client with payload."""
    servers: list[tuple[socket.socket, threading.Event, threading.Thread]] = []

    def start(payload: bytes) -> Path:
        path = tmp_path / f"s{len(servers)}.sock"
        srv = socket.socket(socket.AF_UNIX)
        srv.bind(str(path))
        srv.listen(4)
        srv.settimeout(0.1)
        stop = threading.Event()

        def run() -> None:
            while not stop.is_set():
                try:
                    conn, _ = srv.accept()
                except OSError:
                    continue
                with conn, contextlib.suppress(OSError):
                    conn.sendall(payload)

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        servers.append((srv, stop, thread))
        return path

    yield start
    for srv, stop, thread in servers:
        stop.set()
        thread.join(2)
        srv.close()


def _with(path: str, value: Any) -> bytes:
    """SAMPLE with the key at dotted ``path`` set to ``value``, as the reply's bytes."""
    st = copy.deepcopy(SAMPLE)
    *parents, key = path.split(".")
    node = st
    for p in parents:
        node = node[p]
    node[key] = value
    return json.dumps(st).encode()


def _status(path: Path, capsys: pytest.CaptureFixture[str], *flags: str) -> tuple[int, str, str]:
    code = main(["status", "--socket", str(path), *flags])
    out = capsys.readouterr()
    return code, out.out, out.err


HOSTILE = [
    ("recursion", b"[" * 200_000, "not JSON"),
    ("deep", ('{"a":' * 50 + "1" + "}" * 50).encode(), "nests deeper than 8"),
    ("5000-digits", b'{"uptime_s": ' + b"9" * 5000 + b"}", "not JSON"),
    ("huge-int", _with("output.published", 10**30), "'output.published' is an integer beyond"),
    ("infinity", _with("camera.fps", float("inf")), "'camera.fps' is not finite"),
    # the keys the schema did not check, which crashed the table
    ("signing-text", _with("autopilot.signing", "yes"), "'autopilot.signing' has type str"),
    ("signing-count", _with("autopilot.signing", {"good_signatures": "x"}), "good_signatures"),
    ("rejected-list", _with("camera.rejected", [1]), "'camera.rejected' has type list"),
    ("problem-number", _with("camera.problem", 5), "'camera.problem' has type int"),
    ("match-rate-text", _with("scale.match_rate", "x"), "'scale.match_rate' has type str"),
    ("reasons-number", _with("attitude.reasons", 5), "'attitude.reasons' has type int"),
    ("warnings-numbers", _with("warnings", [1, 2]), "'warnings[0]' has type int"),
    ("mqtt-queued-text", _with("mqtt.queued", "x"), "'mqtt.queued' has type str"),
    ("stamps-number", _with("camera.stamps", 3), "'camera.stamps' has type int"),
    ("long-text", _with("vo.state", "x" * 10_000), "'vo.state' is longer than"),
]


@pytest.mark.parametrize(("name", "payload", "message"), HOSTILE, ids=[h[0] for h in HOSTILE])
def test_a_hostile_reply_is_one_line_in_table_and_json_mode(
    name: str, payload: bytes, message: str, serve: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    path = serve(payload)
    code, out, err = _status(path, capsys)
    assert code == 1 and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1 and message in err, err
    code, out, err = _status(path, capsys, "--json")
    assert code == 1 and "Traceback" not in err + out, err
    lines = out.strip().splitlines()
    assert len(lines) == 1 and message in json.loads(lines[0])["error"], out


def test_terminal_escapes_from_the_service_are_never_printed(
    serve: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    """A hostile camera's error text (its driver's message reaches the status verbatim) with
    a clear-screen, a title change and a bell: the table shows them as '?', the JSON
    escapes them."""
    evil = "no frames: \x1b[2J\x1b]0;owned\x07 \u202eevil\x9b31m"
    st = copy.deepcopy(SAMPLE)
    st["camera"]["problem"] = evil
    st["warnings"] = [evil]
    st["camera"]["rejected"] = {"\x1b[31mred": 1}
    path = serve(json.dumps(st).encode())
    code, out, err = _status(path, capsys)
    assert code == 0, err
    for bad in ("\x1b", "\x07", "\u202e", "\x9b"):
        assert bad not in out
    assert "NO FRAMES: ?[2J?]0;OWNED? ?EVIL?31M FRAMES" in out
    code, out, err = _status(path, capsys, "--json")
    assert code == 0 and "\x1b" not in out and "\\u001b" in out


def test_printable_keeps_text_and_cuts_it() -> None:
    assert printable("caméra 3 ✓") == "caméra 3 ✓"
    assert printable("a\tb\nc") == "a?b?c"
    assert len(printable("x" * 1000, 50)) == 50


def test_json_mode_prints_standard_json(serve: Any, capsys: pytest.CaptureFixture[str]) -> None:
    """An unknown value (NaN) is null under --json: Python wrote NaN, which jq refuses."""

    def refuse(constant: str) -> None:
        raise ValueError(f"{constant} is not standard JSON")

    code, out, err = _status(serve(json.dumps(SAMPLE).encode()), capsys, "--json")
    assert code == 0, err
    assert json.loads(out, parse_constant=refuse)["scale"]["sigma"] is None


def test_a_busy_service_is_asked_again_until_it_answers(tmp_path: Path) -> None:
    """The status server closes connections without a reply while a local flood has spent its
    reply rate (companion/service/status.py): the client connects again until its deadline
    and shows the status the service gives then (before: "reply is not JSON" at once), and
    says the service is busy when no reply came in time."""
    from companion.drivers.status import StatusError, read_status

    path = tmp_path / "busy.sock"
    srv = socket.socket(socket.AF_UNIX)
    srv.bind(str(path))
    srv.listen(16)
    refused = 5  # the first connections closed without a reply
    seen: list[int] = []

    def run() -> None:
        while True:
            try:
                conn, _ = srv.accept()
            except OSError:
                return
            with conn:
                seen.append(1)
                if len(seen) > refused:
                    conn.sendall(json.dumps(SAMPLE).encode())

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        status = read_status(path, timeout_s=5.0)
        assert status is not None and status["vo"]["state"] == "TRACKING"
        assert len(seen) == refused + 1
        refused = 10**9  # never answers now
        with pytest.raises(StatusError, match=r"reply within 0\.3 s"):
            read_status(path, timeout_s=0.3)
    finally:
        srv.close()
        thread.join(2)
