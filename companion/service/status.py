"""The service's state on a Unix socket, for `companion status` (and scripts).

Protocol: connect to the socket; the service writes one JSON object (UTF-8, one line) and closes.
Nothing is read from the client. A flood of connections is rate-limited (see ``StatusServer``): the
event loop, which carries the poses, is never monopolised by it. The socket file is created with
mode 0660 (owner and group: the `companion` user and its operators) and removed on exit.

Where: ``drivers.status.status_path`` (service.status_socket, else $RUNTIME_DIRECTORY/status.sock
under systemd: ``/run/companion/status.sock``, else per user); clients find it with
``drivers.status.find_status_socket`` (that path first, then the per-user one): no flags.

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
import logging
import os
import socket
import stat
import struct
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.errors import ConfigError

StatusProvider = Callable[[], dict[str, Any]]
KEY = "service.status_socket"
MAX_SUN_PATH_BYTES = 107  # sockaddr_un.sun_path holds 108 bytes with the terminating NUL
# what one client, or a flood of them, may take of the event loop
LISTEN_BACKLOG = 16  # connections the kernel holds for us; beyond, it refuses them itself
ACCEPTS_PER_S = 200.0  # connections accepted [1/s] on average (each is cheap: no reply yet)
ACCEPT_BURST = 20  # accepted at once at most (one pass of the loop)
REPLIES_PER_S = 50.0  # status replies (provider() calls) [1/s], all clients together
REPLY_BURST = 10
REPLIES_PER_PEER_S = 5.0  # replies [1/s] to one process (SO_PEERCRED), its burst below
REPLY_PEER_BURST = 5
MAX_PEERS_KEPT = 64  # peer processes whose rate is remembered (the least recent forgotten)
MAX_CLIENTS = 8  # replies being written at once (a client that does not read holds one)
WRITE_TIMEOUT_S = 1.0  # a reply not taken within this is dropped with its client
ACCEPT_RETRY_S = 0.5  # after accept() failed for want of descriptors or memory
PEERCRED = struct.Struct("3i")  # struct ucred: pid, uid, gid

log = logging.getLogger("companion.status")


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


@dataclass
class StatusSocketStats:
    """What the status socket did (counts since the start)."""

    served: int = 0  # replies written in full
    refused: int = 0  # connections closed unanswered: that peer over its rate, or too many
    timed_out: int = 0  # clients that did not take their reply within WRITE_TIMEOUT_S
    paused: int = 0  # times accepting stopped for the accept rate (a flood) or an fd shortage
    accept_errors: int = 0  # accept() failures other than "nothing waiting" (EMFILE, ...)


class RateLimit:
    """A token bucket: ``rate_hz`` events a second on average, ``burst`` at once at most."""

    def __init__(self, rate_hz: float, burst: int) -> None:
        self.rate_hz = rate_hz
        self.burst = float(burst)
        self.tokens = float(burst)
        self.t_s = time.monotonic()

    def _refill(self, now_s: float) -> None:
        self.tokens = min(self.burst, self.tokens + (now_s - self.t_s) * self.rate_hz)
        self.t_s = now_s

    def take(self, now_s: float) -> bool:
        """Whether an event may happen at ``now_s`` (monotonic [s]); spends a token if so."""
        self._refill(now_s)
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False

    def refund(self) -> None:
        """Give back the token of an event that did not happen after all."""
        self.tokens = min(self.burst, self.tokens + 1.0)

    def wait_s(self, now_s: float, tokens: float = 1.0) -> float:
        """Seconds from ``now_s`` until ``tokens`` tokens are there (at most the burst)."""
        self._refill(now_s)
        return max(0.0, (min(tokens, self.burst) - self.tokens) / self.rate_hz)


class StatusServer:
    """``async with StatusServer(path, provider):`` serves provider() to every client.

    No client can take the event loop (the pose path's) from the service: connections are
    accepted at ``ACCEPTS_PER_S`` at most (beyond it the socket is not read: connections
    wait in the kernel's backlog of ``LISTEN_BACKLOG``, then are refused by the kernel, at no
    cost to us); each peer process (SO_PEERCRED) gets ``REPLIES_PER_PEER_S`` replies a second,
    and all of them together ``REPLIES_PER_S`` (provider() is called only for those), so a
    flooding process is answered a few times a second while `companion status` from another
    one still is; at most ``MAX_CLIENTS`` replies are being written at once, each given up
    after ``WRITE_TIMEOUT_S``; nothing is ever read from a client (the protocol has no
    request: whatever a client sends is discarded with the connection)."""

    def __init__(self, path: str | Path, provider: StatusProvider, mode: int = 0o660) -> None:
        self.path = Path(path)
        self.provider = provider
        self.mode = mode
        self.stats = StatusSocketStats()
        self._sock: socket.socket | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._ours: tuple[int, int] | None = None  # (st_dev, st_ino) of the socket we made
        self._accepts = RateLimit(ACCEPTS_PER_S, ACCEPT_BURST)
        self._replies = RateLimit(REPLIES_PER_S, REPLY_BURST)
        self._peers: OrderedDict[tuple[int, int], RateLimit] = OrderedDict()  # (uid, pid)
        self._writing: dict[socket.socket, asyncio.TimerHandle] = {}  # -> its deadline
        self._resume: asyncio.TimerHandle | None = None
        self._errors_logged: set[int] = set()  # errnos of accept() failures said once

    @property
    def requests(self) -> int:
        """Replies served."""
        return self.stats.served

    async def __aenter__(self) -> StatusServer:
        check_socket_path(self.path)
        if self.path.is_socket():  # ours (checked above): a live service, or a stale file
            if _is_live(self.path):
                raise ConfigError(f"{KEY}: {self.path} is in use (is companion already running?)")
            self.path.unlink()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o117)  # never even briefly world-accessible
        try:
            sock.bind(str(self.path))
            sock.listen(LISTEN_BACKLOG)
        except OSError as e:
            sock.close()
            raise ConfigError(f"{KEY}: cannot listen on {self.path}: {e.strerror}") from None
        finally:
            os.umask(old)
        sock.setblocking(False)
        os.chmod(self.path, self.mode)  # explicit: the unit's UMask=0077 would hide it
        st = self.path.lstat()
        self._ours = (st.st_dev, st.st_ino)
        self._sock = sock
        self._loop = asyncio.get_running_loop()
        self._loop.add_reader(sock.fileno(), self._on_readable)
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._sock is not None and self._loop is not None:
            if self._resume is not None:
                self._resume.cancel()
            self._loop.remove_reader(self._sock.fileno())
            self._sock.close()
            self._sock = None
            for conn in list(self._writing):
                self._finish(conn)
        with contextlib.suppress(OSError):  # only the socket we made, not a replacement
            st = self.path.lstat()
            if (st.st_dev, st.st_ino) == self._ours:
                self.path.unlink()

    # ------------------------------------------------------------------ accepting
    def _on_readable(self) -> None:
        """Accept what waits, within the accept rate; past it, stop reading the socket
        until the next token (the loop is never held longer than ACCEPT_BURST accepts)."""
        assert self._sock is not None and self._loop is not None
        while True:
            now_s = time.monotonic()
            if not self._accepts.take(now_s):  # back for half a burst: few wake-ups in a flood
                self._pause(self._accepts.wait_s(now_s, ACCEPT_BURST / 2))
                return
            try:
                conn, _ = self._sock.accept()
            except (BlockingIOError, InterruptedError):
                self._accepts.refund()
                return
            except OSError as e:  # EMFILE, ENFILE, ENOBUFS: try again a little later
                self._accepts.refund()
                self.stats.accept_errors += 1
                if e.errno not in self._errors_logged:
                    self._errors_logged.add(e.errno or 0)
                    log.warning("status socket: cannot accept a connection: %s", e.strerror)
                self._pause(ACCEPT_RETRY_S)
                return
            self._serve(conn)

    def _pause(self, delay_s: float) -> None:
        """Stop reading the listening socket for ``delay_s`` seconds."""
        assert self._sock is not None and self._loop is not None
        self.stats.paused += 1
        self._loop.remove_reader(self._sock.fileno())
        self._resume = self._loop.call_later(delay_s, self._resume_accepting)

    def _resume_accepting(self) -> None:
        self._resume = None
        if self._sock is not None and self._loop is not None:
            self._loop.add_reader(self._sock.fileno(), self._on_readable)

    # ------------------------------------------------------------------ replying
    def _may_reply(self, conn: socket.socket, now_s: float) -> bool:
        """Whether this client gets a reply: fewer than MAX_CLIENTS being written, its peer
        process within its rate, and all peers within theirs."""
        if len(self._writing) >= MAX_CLIENTS:
            return False
        key = _peer(conn)
        bucket = self._peers.pop(key, None) or RateLimit(REPLIES_PER_PEER_S, REPLY_PEER_BURST)
        self._peers[key] = bucket  # the most recent last; the oldest go first
        while len(self._peers) > MAX_PEERS_KEPT:
            self._peers.popitem(last=False)
        if not bucket.take(now_s):
            return False
        if not self._replies.take(now_s):
            bucket.refund()
            return False
        return True

    def _serve(self, conn: socket.socket) -> None:
        """Write the status to a new client and close it; a reply the socket does not take
        at once is finished by the loop within WRITE_TIMEOUT_S."""
        assert self._loop is not None
        conn.setblocking(False)
        if not self._may_reply(conn, time.monotonic()):
            self.stats.refused += 1
            conn.close()
            return
        try:
            data = (json.dumps(self.provider(), default=jsonable) + "\n").encode()
        except Exception:  # a bug in the status: said, and this client closed unanswered
            log.exception("status socket: the status could not be made")
            conn.close()
            return
        try:
            sent = conn.send(data)
        except BlockingIOError:
            sent = 0
        except OSError:  # the client is gone already
            conn.close()
            return
        if sent == len(data):
            self.stats.served += 1
            conn.close()
            return
        rest = memoryview(data)[sent:]
        self._writing[conn] = self._loop.call_later(WRITE_TIMEOUT_S, self._timed_out, conn)
        self._loop.add_writer(conn.fileno(), self._write_more, conn, rest)

    def _write_more(self, conn: socket.socket, rest: memoryview) -> None:
        """The socket can take more of a reply."""
        assert self._loop is not None
        try:
            sent = conn.send(rest)
        except BlockingIOError:
            return
        except OSError:
            self._finish(conn)
            return
        if sent == len(rest):
            self.stats.served += 1
            self._finish(conn)
            return
        self._loop.add_writer(conn.fileno(), self._write_more, conn, rest[sent:])

    def _timed_out(self, conn: socket.socket) -> None:
        self.stats.timed_out += 1
        self._finish(conn)

    def _finish(self, conn: socket.socket) -> None:
        """Close a client whose reply was being written (done, failed or too slow)."""
        assert self._loop is not None
        deadline = self._writing.pop(conn, None)
        if deadline is not None:
            deadline.cancel()
        self._loop.remove_writer(conn.fileno())
        conn.close()


def _peer(conn: socket.socket) -> tuple[int, int]:
    """(uid, pid) of the process at the other end of a Unix socket ((-1, -1): unknown)."""
    try:
        creds = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, PEERCRED.size)
    except OSError:
        return (-1, -1)
    pid, uid, _gid = PEERCRED.unpack(creds)
    return (uid, pid)


def jsonable(value: Any) -> Any:
    """numpy scalars and arrays, sets and paths for json.dumps (its ``default``; the status
    socket's and the live page's)."""
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
