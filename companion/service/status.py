"""The service's state on a Unix socket, for `companion status` (and scripts).

Protocol: connect to the socket; the service writes one JSON object (UTF-8, one line) and
closes. The socket file is created with mode 0660 (owner and group: the `companion` user and
its operators) and removed on exit.

Both ends distrust the path (docs/security.md):
- the service only ever removes a file that is a socket owned by its own user (a stale one
  left by a crashed run); anything else at the path (a regular file, a directory, somebody
  else's socket) is a config error naming ``service.status_socket``, never deleted;
- ``companion status`` refuses a socket in a world-writable folder (``/tmp``) unless it is
  owned by itself or root (anyone could have created it there), reads at most
  ``MAX_STATUS_BYTES`` within a deadline, and checks the reply's shape before it shows it.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import socket
import stat
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion.errors import CompanionError, ConfigError

StatusProvider = Callable[[], dict[str, Any]]
KEY = "service.status_socket"
MAX_SUN_PATH_BYTES = 107  # sockaddr_un.sun_path holds 108 bytes with the terminating NUL
MAX_STATUS_BYTES = 1 << 20  # a real status is a few kB


class StatusError(CompanionError):
    """What answered on the status socket is not a companion service we can trust."""


def check_socket_path(path: Path, key: str = KEY) -> None:
    """Raise ConfigError naming ``key`` unless the service may create its socket at ``path``:
    no NUL, short enough for AF_UNIX, in an existing directory, and either free or a socket
    of our own (stale or live: :meth:`StatusServer.__aenter__` tells which)."""
    text = str(path)
    if "\x00" in text:
        raise ConfigError(f"{key}: a path cannot contain a NUL byte: {text!r}")
    if len(os.fsencode(text)) > MAX_SUN_PATH_BYTES:
        raise ConfigError(
            f"{key}: {len(os.fsencode(text))} bytes is longer than a Unix socket path may be "
            f"({MAX_SUN_PATH_BYTES}): {text}"
        )
    if not path.parent.is_dir():
        raise ConfigError(f"{key}: no directory {path.parent}")
    try:
        st = path.lstat()
    except FileNotFoundError:
        return
    except OSError as e:
        raise ConfigError(f"{key}: cannot inspect {path}: {e.strerror}") from None
    if stat.S_ISDIR(st.st_mode):
        raise ConfigError(f"{key}: {path} is a directory; give the socket's own path")
    if not stat.S_ISSOCK(st.st_mode):
        raise ConfigError(
            f"{key}: {path} exists and is not a socket (it is never removed); choose another path"
        )
    if st.st_uid != os.geteuid():
        raise ConfigError(
            f"{key}: {path} is a socket owned by uid {st.st_uid}, not by us "
            f"(uid {os.geteuid()}); it is never removed: choose another path"
        )


class StatusServer:
    """``async with StatusServer(path, provider):`` serves provider() to every client."""

    def __init__(self, path: str | Path, provider: StatusProvider, mode: int = 0o660) -> None:
        self.path = Path(path)
        self.provider = provider
        self.mode = mode
        self._server: asyncio.AbstractServer | None = None
        self._ours: tuple[int, int] | None = None  # (st_dev, st_ino) of the socket we made
        self.requests = 0

    async def __aenter__(self) -> StatusServer:
        check_socket_path(self.path)
        if self.path.is_socket():  # ours (checked above): a live service, or a stale file
            if _is_live(self.path):
                raise ConfigError(f"{KEY}: {self.path} is in use (is companion already running?)")
            self.path.unlink()
        old = os.umask(0o117)  # never even briefly world-accessible
        try:
            self._server = await asyncio.start_unix_server(self._client, path=str(self.path))
        except OSError as e:
            raise ConfigError(f"{KEY}: cannot listen on {self.path}: {e.strerror}") from None
        finally:
            os.umask(old)
        os.chmod(self.path, self.mode)  # explicit: the unit's UMask=0077 would hide it
        st = self.path.lstat()
        self._ours = (st.st_dev, st.st_ino)
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
        with contextlib.suppress(OSError):  # only the socket we made, not a replacement
            st = self.path.lstat()
            if (st.st_dev, st.st_ino) == self._ours:
                self.path.unlink()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.requests += 1
        try:
            writer.write((json.dumps(self.provider(), default=_jsonable) + "\n").encode())
            await writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError, OSError):
                await writer.wait_closed()


def _jsonable(value: Any) -> Any:
    """numpy scalars and arrays, sets and paths for json.dumps."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, (set, frozenset)):
        return sorted(value)
    return str(value)


def _is_live(path: Path) -> bool:
    """Whether a process accepts connections on the socket at path."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(0.5)
        try:
            s.connect(str(path))
        except OSError:
            return False
        return True


def status_path(configured: str) -> Path:
    """The socket path for service.status_socket (see its help for the empty default)."""
    if configured:
        return Path(configured)
    if os.environ.get("RUNTIME_DIRECTORY"):  # systemd's RuntimeDirectory=
        return Path(os.environ["RUNTIME_DIRECTORY"].split(":")[0]) / "status.sock"
    if os.environ.get("XDG_RUNTIME_DIR"):
        return Path(os.environ["XDG_RUNTIME_DIR"]) / "companion.sock"
    return Path("/tmp") / f"companion-{os.getuid()}.sock"


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
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout_s)
        try:
            s.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError):
            return None
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
                break
            data += chunk
            if len(data) > max_bytes:
                raise StatusError(f"{path}: reply longer than {max_bytes} bytes: not a status")
    try:
        out = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise StatusError(f"{path}: the reply is not JSON ({e})") from None
    validate_status(out)
    return out  # type: ignore[no-any-return]


# The shape `companion status` relies on: section -> key -> accepted types (None allowed
# where a value may be unknown). Extra keys are fine (newer services add some).
_NUM = (int, float)
_OPT_NUM = (int, float, type(None))
STATUS_SCHEMA: dict[str, Any] = {
    "uptime_s": _NUM,
    "warnings": list,
    "autopilot": {
        "url": str,
        "heartbeat_age_s": _OPT_NUM,
        "system_id": (int, type(None)),
        "timesync_converged": bool,
        "timesync_offset_ms": _OPT_NUM,
        "timesync_rtt_ms": _OPT_NUM,
        "rx_messages": int,
        "rx_bad": int,
    },
    "camera": {
        "url": str,
        "fps": _NUM,
        "frames": int,
        "dropped": int,
        "last_frame_age_s": _OPT_NUM,
    },
    "vo": {"state": str, "features": int, "keyframes": int, "resets": int},
    "scale": {
        "method": str,
        "value": _OPT_NUM,
        "sigma": _OPT_NUM,
        "sensors_used": int,
        "ranges_in": int,
        "ranges_rejected": int,
    },
    "attitude": {
        "roll_deg": _OPT_NUM,
        "pitch_deg": _OPT_NUM,
        "sigma_deg": _OPT_NUM,
        "compensation": bool,
    },
    "output": {
        "message": str,
        "rate_hz": _NUM,
        "published": int,
        "reset_counter": int,
        "latency_ms_p50": _OPT_NUM,
    },
    "mqtt": {"enabled": bool},
}


def validate_status(obj: Any, schema: dict[str, Any] = STATUS_SCHEMA, where: str = "") -> None:
    """StatusError naming the first key whose value is missing or of the wrong type."""
    if not isinstance(obj, dict):
        raise StatusError(f"status{where}: expected an object, got {type(obj).__name__}")
    for key, want in schema.items():
        name = f"{where}.{key}" if where else key
        if key not in obj:
            raise StatusError(f"status: missing {name!r}")
        value = obj[key]
        if isinstance(want, dict):
            validate_status(value, want, name)
        elif isinstance(value, bool) and bool not in (want if isinstance(want, tuple) else (want,)):
            raise StatusError(f"status: {name!r} is a boolean, expected a number")
        elif not isinstance(value, want):
            raise StatusError(f"status: {name!r} has type {type(value).__name__}")
