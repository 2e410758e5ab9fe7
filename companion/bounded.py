"""Bounded reading of what comes from outside (configs, state files, keys, datasets, a status
reply): regular files only, opened without blocking, and parsed data's nesting depth. Light
enough for `companion status` and the drivers to import (no NumPy)."""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path
from typing import Any

from companion.errors import CompanionError, ConfigError


def data_nesting(value: Any) -> int:
    """How deeply ``value`` (parsed TOML or JSON: dicts and lists) nests: 0 for a scalar, 1 for
    a flat table or list. Iterative, so a hostile 30,000-deep document costs no recursion."""
    deepest = 0
    stack: list[tuple[Any, int]] = [(value, 0)]
    while stack:
        item, depth = stack.pop()
        deepest = max(deepest, depth)
        if isinstance(item, dict):
            stack.extend((v, depth + 1) for v in item.values())
        elif isinstance(item, list):
            stack.extend((v, depth + 1) for v in item)
    return deepest


_FILE_KINDS = (
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISDIR, "a directory"),
)


def file_kind(mode: int) -> str:
    """What a file of st_mode ``mode`` is, in words ("a FIFO", "a regular file")."""
    return next((name for test, name in _FILE_KINDS if test(mode)), "a regular file")


def read_regular_file(
    path: Path,
    max_bytes: int,
    error: type[CompanionError] = ConfigError,
    *,
    follow_symlinks: bool = True,
) -> bytes:
    """The bytes of the regular file ``path`` (at most ``max_bytes``), opened without blocking
    and checked on the open descriptor (fstat, not by name): a FIFO, a device, a socket or a
    directory is refused at once, as is a larger file; ``follow_symlinks=False``: a symlink
    as the last component is refused (O_NOFOLLOW). Every failure raises ``error`` naming the
    file."""
    flags = os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | os.O_NOCTTY
    if not follow_symlinks:
        flags |= os.O_NOFOLLOW
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise error(f"{path}: file not found") from None
    except (OSError, ValueError) as e:  # ValueError: a NUL byte in the name
        reason = "a symlink (not followed)" if getattr(e, "errno", 0) == errno.ELOOP else e
        raise error(f"{path}: cannot read: {getattr(e, 'strerror', None) or reason}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{path}: is {file_kind(st.st_mode)}, not a regular file: not read")
        if st.st_size > max_bytes:
            raise error(f"{path}: larger than {max_bytes} bytes ({st.st_size}): not read")
        chunks: list[bytes] = []
        size = 0
        while size <= max_bytes:
            chunk = os.read(fd, min(1 << 20, max_bytes + 1 - size))
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except OSError as e:
        raise error(f"{path}: cannot read: {e.strerror or e}") from None
    finally:
        os.close(fd)
    if size > max_bytes:
        raise error(f"{path}: larger than {max_bytes} bytes: not read")
    return b"".join(chunks)
