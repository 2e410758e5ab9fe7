"""Bounded reading of outside input (companion/bounded.py): nesting depth without recursion, and
regular files only, never more than the budget, refused by what the open descriptor is."""

from __future__ import annotations

import os
import socket
import stat
from pathlib import Path

import pytest

from companion.bounded import data_nesting, file_kind, read_regular_file
from companion.errors import ConfigError, DatasetError


def test_nesting_counts_tables_and_lists_without_recursion() -> None:
    assert data_nesting(3) == 0 and data_nesting({}) == 0
    assert data_nesting({"a": 1, "b": [1, 2]}) == 2
    assert data_nesting([[[]], {"x": {"y": [0]}}]) == 4
    deep: list = []
    for _ in range(30_000):  # a hostile document: far past Python's recursion limit
        deep = [deep]
    assert data_nesting(deep) == 30_000


def test_file_kinds_in_words() -> None:
    assert file_kind(stat.S_IFIFO | 0o600) == "a FIFO"
    assert file_kind(stat.S_IFDIR | 0o755) == "a directory"
    assert file_kind(stat.S_IFSOCK) == "a socket"
    assert file_kind(stat.S_IFREG | 0o644) == "a regular file"


def test_a_regular_file_within_budget_is_read_whole(tmp_path: Path) -> None:
    path = tmp_path / "a.toml"
    path.write_bytes(b"x" * 1000)
    assert read_regular_file(path, 1000) == b"x" * 1000
    with pytest.raises(ConfigError, match=r"larger than 999 bytes \(1000\)"):
        read_regular_file(path, 999)


def test_what_is_not_a_regular_file_is_refused_at_once_naming_it(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)  # no writer: a blocking open would hang here
    with pytest.raises(DatasetError, match=r"fifo: is a FIFO, not a regular file"):
        read_regular_file(fifo, 100, DatasetError)
    with pytest.raises(ConfigError, match=r"is a directory"):
        read_regular_file(tmp_path, 100)
    sock_path = tmp_path / "s.sock"
    with socket.socket(socket.AF_UNIX) as sock:
        sock.bind(str(sock_path))
        with pytest.raises(ConfigError, match=r"cannot read|is a socket"):
            read_regular_file(sock_path, 100)
    with pytest.raises(ConfigError, match=r"missing: file not found"):
        read_regular_file(tmp_path / "missing", 100)


def test_a_symlink_is_followed_only_when_allowed(tmp_path: Path) -> None:
    target = tmp_path / "key"
    target.write_bytes(b"secret")
    link = tmp_path / "link"
    link.symlink_to(target)
    assert read_regular_file(link, 100) == b"secret"
    with pytest.raises(ConfigError, match=r"link: cannot read: .*symlink|link: cannot read"):
        read_regular_file(link, 100, follow_symlinks=False)
