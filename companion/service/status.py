"""The service's state on a Unix socket, for `companion status` (and scripts).

Protocol: connect to the socket; the service writes one JSON object (UTF-8, one line) and
closes. The socket file is created with mode 0660 (owner and group: the `companion` user and
its operators), replaced if a stale one is left by a crashed run, and removed on exit.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion.errors import ConfigError

StatusProvider = Callable[[], dict[str, Any]]


class StatusServer:
    """``async with StatusServer(path, provider):`` serves provider() to every client."""

    def __init__(self, path: str | Path, provider: StatusProvider, mode: int = 0o660) -> None:
        self.path = Path(path)
        self.provider = provider
        self.mode = mode
        self._server: asyncio.AbstractServer | None = None
        self.requests = 0

    async def __aenter__(self) -> StatusServer:
        if not self.path.parent.is_dir():
            raise ConfigError(f"service.status_socket: no directory {self.path.parent}")
        if self.path.exists() or self.path.is_symlink():
            if _is_live(self.path):
                raise ConfigError(
                    f"service.status_socket: {self.path} is in use (is companion already running?)"
                )
            self.path.unlink()
        old = os.umask(0o117)  # never even briefly world-accessible
        try:
            self._server = await asyncio.start_unix_server(self._client, path=str(self.path))
        finally:
            os.umask(old)
        os.chmod(self.path, self.mode)
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
        with contextlib.suppress(FileNotFoundError):
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


def read_status(path: str | Path, timeout_s: float = 2.0) -> dict[str, Any] | None:
    """The status served at path, or None when nothing is listening there."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout_s)
        try:
            s.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError):
            return None
        chunks = []
        while True:
            data = s.recv(65536)
            if not data:
                break
            chunks.append(data)
    out: dict[str, Any] = json.loads(b"".join(chunks).decode())
    return out
