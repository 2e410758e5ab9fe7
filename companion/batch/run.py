"""One task, run where an executor puts it: ``run_task`` (a pure function of its arguments,
importable by reference, as Ray ships it) runs ``python -m companion.cli ARGV`` in a fresh
temporary folder and returns the result folder's files as bytes, so that a cluster node
needs no shared disk for the results (only the inputs, at the same paths).

The command is the one a user types (``companion eval ...``, ``companion replay ...``): the
batch runs the CLI's own code path, in its own process (its own memory budget, its own
numba and OpenCV state), with the code of the package this process imported. Paths in the
command line are relative to the task's folder (``--out result``, ``--config config.toml``),
so that nothing the run writes names a temporary folder.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from companion.batch.cache import code_version, package_root
from companion.batch.spec import OUT, Task

RESULT = "result"  # the result folder inside the task's temporary folder
CONFIG = "config.toml"  # the config (or replay override) the task runs with, beside it
STDOUT = "stdout.txt"  # what the command printed, kept in the result folder
STDERR = "stderr.txt"


@dataclass(frozen=True)
class TaskResult:
    """What a task gives back: ``files`` (relative path -> bytes) on success; else ``error``
    (one line) and ``detail`` (the traceback, or the command's stderr). ``code``: the code
    version of the process that ran it; ``seconds``: its wall time."""

    name: str
    key: str
    ok: bool
    seconds: float
    code: str
    files: dict[str, bytes] = field(default_factory=dict)
    error: str = ""
    detail: str = ""


def command(task: Task, config_text: str | None) -> list[str]:
    """The ``companion`` arguments of ``task`` run in its folder (``{out}`` -> ``result``,
    ``--config config.toml`` when it has a config)."""
    argv = [a.replace(OUT, RESULT) for a in task.argv]
    if config_text is not None:
        argv += ["--config", CONFIG]
    return argv


def run_task(task: Task, key: str, config_text: str | None) -> TaskResult:
    """Run ``task`` (its config as TOML text, or None) in a new process of this package;
    never raises: a failure is a TaskResult with its error."""
    start = time.monotonic()
    code = ""
    try:
        code = code_version()
        with tempfile.TemporaryDirectory(prefix="companion-task-") as tmp:
            folder = Path(tmp)
            (folder / RESULT).mkdir()
            if config_text is not None:
                (folder / CONFIG).write_text(config_text)
            env = dict(os.environ)
            root = str(package_root().parent)  # the package this process runs, not another
            env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
            env["MPLBACKEND"] = "Agg"
            proc = subprocess.run(
                [sys.executable, "-m", "companion.cli", *command(task, config_text)],
                cwd=folder,
                env=env,
                capture_output=True,
                check=False,
            )
            (folder / RESULT / STDOUT).write_bytes(proc.stdout)
            (folder / RESULT / STDERR).write_bytes(proc.stderr)
            seconds = time.monotonic() - start
            if proc.returncode != 0:
                err = proc.stderr.decode(errors="replace")
                lines = [ln for ln in err.splitlines() if ln.strip()]
                why = lines[-1] if lines else "no message"
                return TaskResult(
                    task.name,
                    key,
                    False,
                    seconds,
                    code,
                    error=f"exit {proc.returncode}: {why}",
                    detail=err,
                )
            return TaskResult(task.name, key, True, seconds, code, read_tree(folder / RESULT))
    except Exception as e:  # this task's failure, reported; the batch goes on
        return TaskResult(
            task.name,
            key,
            False,
            time.monotonic() - start,
            code,
            error=f"{type(e).__name__}: {e}",
            detail=traceback.format_exc(),
        )


def read_tree(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` by its relative path (POSIX)."""
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def write_tree(root: Path, files: dict[str, bytes]) -> None:
    """Write ``files`` (relative path -> bytes) under ``root``; a path that leaves ``root`` is
    refused."""
    base = root.resolve()
    for rel, data in files.items():
        path = (root / rel).resolve()
        if base != path and base not in path.parents:
            raise ValueError(f"{rel}: outside the result folder")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
