"""The service's state on a Unix socket, for `companion status` (and scripts).

Protocol: connect to the socket; the service writes one JSON object (UTF-8, one line) and
closes. The socket file is created with mode 0660 (owner and group: the `companion` user and
its operators) and removed on exit.

Where: ``drivers.status.status_path`` (service.status_socket, else $RUNTIME_DIRECTORY/status.sock
under systemd: ``/run/companion/status.sock`` for systemd/companion.service, else per user);
clients find it with ``drivers.status.find_status_socket`` (that fixed path first, then the
per-user one), so the two agree without flags (tests/test_cli.py).

Both ends distrust the path (docs/security.md; the client side is ``drivers.status``):
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
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion.errors import ConfigError

StatusProvider = Callable[[], dict[str, Any]]
KEY = "service.status_socket"
MAX_SUN_PATH_BYTES = 107  # sockaddr_un.sun_path holds 108 bytes with the terminating NUL


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
