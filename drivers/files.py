"""Durable small files: write to a temporary file beside the target, fsync, rename, fsync the
folder. A crash or a power cut leaves the old content or the new one, never a torn or empty
file; a full disk leaves the old file in place and raises OSError.

The service runs as root: a file it creates is always a new one (O_CREAT | O_EXCL) and never
reached through a symbolic link (O_NOFOLLOW), so that a link planted in a folder (the
recorder's, the state folder) cannot make it write elsewhere. The temporary name is random:
nobody can plant a link there in advance.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from pathlib import Path
from typing import IO, Any

NEW_FILE_FLAGS = os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
TEMP_NAME_ATTEMPTS = 16  # random names tried before giving up (a collision is ~2^-64 each)


def create_new(path: str | Path, mode: int = 0o644) -> int:
    """A descriptor of a new file ``path``, open for writing: FileExistsError when anything is
    there already (a file, a symbolic link, even a dangling one), never following a link."""
    return os.open(path, os.O_WRONLY | NEW_FILE_FLAGS, mode)


def open_new(path: str | Path, binary: bool = False, mode: int = 0o644, **kw: Any) -> IO[Any]:
    """``open(path, "w")`` on a file that :func:`create_new` creates (``binary``: "wb")."""
    fd = create_new(path, mode)
    try:
        return open(fd, "wb" if binary else "w", **kw)
    except BaseException:
        os.close(fd)
        raise


def _temp_name(path: Path) -> Path:
    """A random hidden name beside ``path`` (unpredictable: nothing can wait there)."""
    return path.with_name(f".{path.name}.{secrets.token_hex(8)}.tmp")


def _new_temp_file(path: Path, mode: int) -> tuple[Path, int]:
    """A new temporary file beside ``path`` under a random name, and its descriptor (a name
    taken, by chance or by a planted link, is passed over; FileExistsError after
    TEMP_NAME_ATTEMPTS)."""
    for _ in range(TEMP_NAME_ATTEMPTS - 1):
        tmp = _temp_name(path)
        with contextlib.suppress(FileExistsError):
            return tmp, create_new(tmp, mode)
    tmp = _temp_name(path)
    return tmp, create_new(tmp, mode)


def atomic_write(path: str | Path, data: bytes, mode: int = 0o600) -> None:
    """Replace ``path`` with ``data`` atomically (the file gets ``mode``); OSError on failure,
    with the temporary file removed and ``path`` untouched. A symbolic link at ``path`` is
    replaced by the file, its target left alone."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp, fd = _new_temp_file(path, mode)
    try:
        try:
            view = memoryview(data)
            while view:
                n = os.write(fd, view)
                view = view[n:]
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    with contextlib.suppress(OSError):  # the rename itself durable
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
