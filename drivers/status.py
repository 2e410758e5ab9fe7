"""The client side of the service's status socket: where it is, and what is believed of it.

``companion status`` and ``companion px4 check`` read the running service's state here (the
server is ``companion.service.status``). Protocol: connect; the service writes one JSON object
(UTF-8, one line) and closes. Nothing that answers is trusted blindly (docs/security.md): in a
folder anyone can write to (``/tmp``) the socket must be owned by us or root; at most
``MAX_STATUS_BYTES`` are read within a deadline; the reply must have the status's shape.
"""

from __future__ import annotations

import json
import math
import os
import socket
import stat
import time
import unicodedata
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.bounded import data_nesting
from companion.errors import CompanionError

MAX_STATUS_BYTES = 1 << 20  # a real status is a few kB


class StatusError(CompanionError):
    """What answered on the status socket is not a companion service we can trust."""


# Where the service listens under systemd/companion.service (RuntimeDirectory=companion, so
# $RUNTIME_DIRECTORY/status.sock): a client looks here first (tests/companion/cli/test_cli.py
# checks that the unit and config/default.toml agree with it).
SYSTEM_STATUS_SOCKET = Path("/run/companion/status.sock")


def status_path(configured: str) -> Path:
    """Where the service listens for service.status_socket (see its help for the empty
    default): ``configured``; else $RUNTIME_DIRECTORY/status.sock under systemd (the unit's
    RuntimeDirectory: :data:`SYSTEM_STATUS_SOCKET`); else :func:`user_status_path`."""
    if configured:
        return Path(configured)
    if os.environ.get("RUNTIME_DIRECTORY"):  # systemd's RuntimeDirectory=
        return Path(os.environ["RUNTIME_DIRECTORY"].split(":")[0]) / "status.sock"
    return user_status_path()


def user_status_path() -> Path:
    """A service started by hand: $XDG_RUNTIME_DIR/companion.sock, else
    /tmp/companion-UID.sock."""
    if os.environ.get("XDG_RUNTIME_DIR"):
        return Path(os.environ["XDG_RUNTIME_DIR"]) / "companion.sock"
    return Path("/tmp") / f"companion-{os.getuid()}.sock"


def find_status_socket(configured: str = "") -> Path:
    """Where a client (``companion status``, ``px4 check``) looks for the service: the
    configured path (``--socket`` or service.status_socket) when given; else
    :data:`SYSTEM_STATUS_SOCKET` when something is there (the service under systemd), or when
    its folder cannot be searched (the caller is not in the service's group: reading then
    says so, instead of "not running"); else :func:`user_status_path`.

    The client does not use $RUNTIME_DIRECTORY: a client run from another unit has that
    unit's folder there, not the service's."""
    if configured:
        return Path(configured)
    try:
        SYSTEM_STATUS_SOCKET.lstat()
    except PermissionError:
        return SYSTEM_STATUS_SOCKET
    except OSError:  # absent (no directory, no socket): the service is not under systemd
        return user_status_path()
    return SYSTEM_STATUS_SOCKET


def check_trusted(path: Path) -> None:
    """StatusError unless the socket at ``path`` may be believed: in a folder that others
    cannot write to, or owned by us or root (a world-writable folder such as /tmp lets anyone
    create the path before the service does)."""
    try:
        st, parent = path.lstat(), path.parent.stat()
    except OSError:
        return  # nothing there: connect() says so
    if not stat.S_ISSOCK(st.st_mode):
        raise StatusError(f"{path} is not a socket")
    others_write = parent.st_mode & stat.S_IWOTH
    if others_write and st.st_uid not in (os.geteuid(), 0):
        raise StatusError(
            f"{path} is owned by uid {st.st_uid}, not by us or root, in a folder anyone can "
            f"write to ({path.parent}): not trusted"
        )


def read_status(
    path: str | Path, timeout_s: float = 2.0, max_bytes: int = MAX_STATUS_BYTES
) -> dict[str, Any] | None:
    """The status served at path, or None when nothing is listening there. StatusError when
    the socket is not trusted (:func:`check_trusted`) or the reply is too long, too slow, not
    JSON or not shaped as a status (:func:`validate_status`)."""
    path = Path(path)
    check_trusted(path)
    deadline = time.monotonic() + timeout_s
    while True:  # a busy server (a local connection flood) is asked again until the deadline
        data = _read_once(path, deadline, timeout_s, max_bytes)
        if data is None:
            return None
        if data or time.monotonic() >= deadline:
            break
        time.sleep(RETRY_S)  # closed without a reply: its reply rate was spent; again
    if not data:
        raise StatusError(f"{path}: no reply within {timeout_s:g} s (the service is busy)")
    out = parse_status(bytes(data), str(path))
    validate_status(out)
    return out  # type: ignore[no-any-return]


RETRY_S = 0.05  # between two connections to a busy status socket


def _read_once(path: Path, deadline: float, timeout_s: float, max_bytes: int) -> bytes | None:
    """One connection's reply (b"" when the server closed it without one, or its backlog was
    full); None when nothing listens at ``path``."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(max(deadline - time.monotonic(), 0.001))
        try:
            s.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError):
            return None
        except PermissionError:
            raise StatusError(
                f"{path}: permission denied: run as the service's user or a member of its "
                "group (`sudo usermod -aG companion $USER`, then log in again)"
            ) from None
        except (BlockingIOError, TimeoutError):  # the listen backlog is full: busy
            return b""
        except OSError as e:
            raise StatusError(f"{path}: cannot connect: {e.strerror or e}") from None
        data = bytearray()
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise StatusError(f"{path}: no complete reply within {timeout_s:g} s")
            s.settimeout(left)
            try:
                chunk = s.recv(65536)
            except TimeoutError:
                raise StatusError(f"{path}: no complete reply within {timeout_s:g} s") from None
            except OSError as e:
                raise StatusError(f"{path}: read failed: {e.strerror or e}") from None
            if not chunk:
                return bytes(data)
            data += chunk
            if len(data) > max_bytes:
                raise StatusError(f"{path}: reply longer than {max_bytes} bytes: not a status")


MAX_STATUS_DEPTH = 8  # a status nests 3 deep; more is not a status


def parse_status(data: bytes, where: str) -> Any:
    """The JSON value of a reply; StatusError for anything that is not bounded JSON: bad
    UTF-8 or syntax, an integer too long to read (ValueError), nesting that recurses
    (RecursionError) or deeper than MAX_STATUS_DEPTH."""
    try:
        out = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as e:  # JSONDecodeError: ValueError
        raise StatusError(f"{where}: the reply is not JSON ({str(e)[:200]})") from None
    if data_nesting(out) > MAX_STATUS_DEPTH:
        raise StatusError(f"{where}: the reply nests deeper than {MAX_STATUS_DEPTH}: not a status")
    return out


# The shape `companion status` relies on: section -> key -> accepted types (None allowed
# where a value may be unknown); Opt(...) for keys a service may leave out (older ones), whose
# value is checked when present; ListOf / MapOf for the lists and tables the table prints.
# Extra keys are fine (newer services add some) and are not printed.
@dataclass(frozen=True)
class Opt:
    """A key that may be absent; when present its value must be ``spec``."""

    spec: Any


@dataclass(frozen=True)
class ListOf:
    """A list whose items are all ``item`` (types)."""

    item: Any


@dataclass(frozen=True)
class MapOf:
    """A table of string keys whose values are all ``value`` (types)."""

    value: Any


_NUM = (int, float)
_OPT_NUM = (int, float, type(None))
MAX_STATUS_INT = 2**53  # counters and ids: within what JSON numbers carry exactly
MAX_STATUS_TEXT = 4096  # characters of one string
STATUS_SCHEMA: dict[str, Any] = {
    "uptime_s": _NUM,
    "warnings": ListOf(str),
    "autopilot": {
        "url": str,
        "heartbeat_age_s": _OPT_NUM,
        "system_id": (int, type(None)),
        "timesync_converged": bool,
        "timesync_offset_ms": _OPT_NUM,
        "timesync_rtt_ms": _OPT_NUM,
        "rx_messages": int,
        "rx_bad": int,
        "px4_converts_stamps": Opt((bool, type(None))),
        "stamped_at_send": Opt(int),
        "signing": Opt((MapOf(_NUM), type(None))),
    },
    "camera": {
        "url": str,
        "fps": _NUM,
        "frames": int,
        "dropped": int,
        "last_frame_age_s": _OPT_NUM,
        "stamps": Opt((str, type(None))),
        "problem": Opt((str, type(None))),
        "rejected": Opt((MapOf(int), type(None))),
    },
    "vo": {"state": str, "features": int, "keyframes": int, "resets": int},
    "scale": {
        "method": str,
        "value": _OPT_NUM,
        "sigma": _OPT_NUM,
        "sensors_used": int,
        "ranges_in": int,
        "ranges_rejected": int,
        "match_rate": Opt((MapOf(_NUM), type(None))),
    },
    "attitude": {
        "roll_deg": _OPT_NUM,
        "pitch_deg": _OPT_NUM,
        "sigma_deg": _OPT_NUM,
        "compensation": bool,
        "reasons": Opt(ListOf(str)),
    },
    "output": {
        "message": str,
        "rate_hz": _NUM,
        "published": int,
        "reset_counter": int,
        "latency_ms_p50": _OPT_NUM,
    },
    "mqtt": {
        "enabled": bool,
        "connected": Opt(bool),
        "queued": Opt(int),
        "dropped": Opt(int),
    },
    "web": Opt(  # the live page (companion/service/web.py)
        {
            "enabled": bool,
            "url": Opt(str),
            "listening": Opt(bool),
            "viewers": Opt(int),
            "problem": Opt((str, type(None))),
        }
    ),
}


def validate_status(obj: Any, schema: dict[str, Any] = STATUS_SCHEMA, where: str = "") -> None:
    """StatusError naming the first key whose value is missing or of the wrong type, an
    integer beyond MAX_STATUS_INT, a number that is not finite (NaN: unknown, allowed) or a
    string longer than MAX_STATUS_TEXT."""
    if not isinstance(obj, dict):
        raise StatusError(f"status{where}: expected an object, got {type(obj).__name__}")
    for key, want in schema.items():
        name = f"{where}.{key}" if where else key
        if key not in obj:
            if isinstance(want, Opt):
                continue
            raise StatusError(f"status: missing {name!r}")
        _check_value(obj[key], want.spec if isinstance(want, Opt) else want, name)


def _check_value(value: Any, want: Any, name: str) -> None:
    """StatusError unless ``value`` is what ``want`` (a type, a tuple of them, a nested
    schema, ListOf, MapOf) accepts."""
    if isinstance(want, dict):
        validate_status(value, want, name)
        return
    options = want if isinstance(want, tuple) else (want,)
    for option in options:
        if isinstance(option, ListOf) and isinstance(value, list):
            for i, item in enumerate(value):
                _check_value(item, option.item, f"{name}[{i}]")
            return
        if isinstance(option, MapOf) and isinstance(value, dict):
            for k, item in value.items():
                _check_value(item, option.value, f"{name}.{printable(k, 40)}")
            return
    plain = tuple(o for o in options if isinstance(o, type))
    if isinstance(value, bool) and bool not in plain:
        raise StatusError(f"status: {name!r} is a boolean, expected a number")
    if not plain or not isinstance(value, plain):
        raise StatusError(f"status: {name!r} has type {type(value).__name__}")
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > MAX_STATUS_INT:
        raise StatusError(f"status: {name!r} is an integer beyond {MAX_STATUS_INT}")
    if isinstance(value, float) and math.isinf(value):
        raise StatusError(f"status: {name!r} is not finite")
    if isinstance(value, str) and len(value) > MAX_STATUS_TEXT:
        raise StatusError(f"status: {name!r} is longer than {MAX_STATUS_TEXT} characters")


def printable(text: str, limit: int = 300) -> str:
    """``text`` safe to print on a terminal: control and format characters (ESC and the
    terminal sequences it starts, C1 controls, bidirectional overrides) shown as ``?``, and
    cut to ``limit`` characters. A hostile camera's error text reaches the status verbatim."""
    cut = text if len(text) <= limit else text[: limit - 3] + "..."
    return "".join("?" if unicodedata.category(c) in ("Cc", "Cf") else c for c in cut)


def json_safe(value: Any) -> Any:
    """A copy of a status with NaN (an unknown value) as null: standard JSON for ``--json``
    (Python writes NaN, which strict parsers such as jq refuse)."""
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, list):
        return [json_safe(v) for v in value]
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    return value


def printable_status(value: Any) -> Any:
    """A copy of a (validated) status with every string, keys included, :func:`printable`."""
    if isinstance(value, str):
        return printable(value)
    if isinstance(value, list):
        return [printable_status(v) for v in value]
    if isinstance(value, dict):
        return {printable(str(k), 80): printable_status(v) for k, v in value.items()}
    return value
