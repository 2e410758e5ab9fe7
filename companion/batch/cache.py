"""The batch cache's key: what a task's result depends on, hashed.

``task_key`` = SHA-256 over (the spec's kind, argv, config and overrides; the SHA-256 of the
config file's bytes; the content hash of every input folder or file; the code version). The
task's name is not in it: the same work under two names is done once.

``code_version`` = SHA-256 over every ``.py`` file of the ``companion`` package as imported,
``drivers/`` and ``sitl/`` with it (the package's links to them are followed), path and bytes:
uncommitted edits count, ``__pycache__`` and the tests do not. Left out: the modules that only
choose the tasks and draw the tables from their results (``TABLE_ONLY``): a task runs
``python -m companion.cli eval|replay`` in a process of its own and none of them is on its
path, so a new table or a reworded column re-runs nothing.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path

import companion
from companion.batch.spec import Task
from companion.errors import BatchError

CHUNK = 1 << 20  # bytes read at a time when hashing a file
# relative to the package: which tables and tasks exist, and how they are drawn
TABLE_ONLY = frozenset({"batch/plans.py", "batch/results_md.py", "cli/results.py"})


def package_root() -> Path:
    """The folder of the ``companion`` package this process imported."""
    return Path(companion.__file__).resolve().parent


@functools.cache
def code_version() -> str:
    """SHA-256 (hex) of the imported package's Python sources, ``drivers/`` and ``sitl/``
    included, ``TABLE_ONLY`` not; computed once per process."""
    return sources_sha256(package_root())


def sources_sha256(root: Path) -> str:
    """SHA-256 (hex) of the ``.py`` files under ``root`` (relative path and bytes, sorted;
    links followed), ``TABLE_ONLY`` left out."""
    h = hashlib.sha256()
    for path in sorted(_py_files(root)):
        rel = path.relative_to(root).as_posix()
        if rel in TABLE_ONLY:
            continue
        h.update(rel.encode() + b"\0")
        h.update(path.read_bytes() + b"\0")
    return h.hexdigest()


def _py_files(root: Path) -> list[Path]:
    out: list[Path] = []
    for folder, dirs, files in os.walk(root, followlinks=True):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__" and not d.startswith("."))
        out.extend(Path(folder) / f for f in files if f.endswith(".py"))
    return out


def file_sha256(path: Path) -> str:
    """SHA-256 (hex) of one file's bytes."""
    h = hashlib.sha256()
    with path.open("rb") as fh:
        while chunk := fh.read(CHUNK):
            h.update(chunk)
    return h.hexdigest()


def content_hash(path: Path) -> str:
    """SHA-256 (hex) of a file's bytes, or of a folder's files (relative paths and bytes, in
    sorted order; links followed). BatchError naming the path when it does not exist."""
    if path.is_file():
        return file_sha256(path)
    if not path.is_dir():
        raise BatchError(f"{path}: no such file or folder (a task's input)")
    h = hashlib.sha256()
    for folder, dirs, files in os.walk(path, followlinks=True):
        dirs[:] = sorted(dirs)
        for f in sorted(files):
            p = Path(folder) / f
            h.update(p.relative_to(path).as_posix().encode() + b"\0")
            h.update(file_sha256(p).encode())
    return h.hexdigest()


class KeyMaker:
    """Task keys for one batch: input hashes computed once per path."""

    def __init__(self, code: str | None = None) -> None:
        self.code = code_version() if code is None else code
        self._hashes: dict[str, str] = {}

    def _hash(self, path: str) -> str:
        if path not in self._hashes:
            self._hashes[path] = content_hash(Path(path))
        return self._hashes[path]

    def key(self, task: Task) -> str:
        """The cache key of ``task`` (SHA-256 hex)."""
        doc = {
            "kind": task.kind,
            "argv": list(task.argv),
            "config": task.config,
            "config_sha256": None if task.config is None else self._hash(task.config),
            "overrides": [[k, repr(v)] for k, v in task.overrides],
            "inputs": {p: self._hash(p) for p in task.inputs},
            "code": self.code,
        }
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()
