"""A batch: tasks -> result folders, through the cache and an executor.

Layout under the batch's output folder ``out``::

    out/cache/KEY/          a task's result, by its key (companion/batch/cache.py): the files
                            its command wrote, stdout.txt, stderr.txt and batch.json
    out/NAME -> cache/KEY   the task's name, a link to its current result
    out/failed/NAME/        error.txt (one line) and traceback.txt of a task that failed

A task whose key has a result is not run again (``cached``); the others go to the executor.
A failed task is reported and the rest go on; it is never cached (the next batch tries again).
"""

from __future__ import annotations

import datetime
import json
import os
import shutil
import sys
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal, TextIO

from companion.batch.cache import KeyMaker
from companion.batch.executors import Executor, Job
from companion.batch.run import TaskResult, write_tree
from companion.batch.spec import Task, nested, to_toml
from companion.config import Config, from_dict
from companion.errors import BatchError
from companion.toml_files import merge, read_config_toml

Status = Literal["ran", "cached", "failed"]
SECTIONS_OF_REPLAY = ("vo", "scale", "attitude", "dpose")


@dataclass(frozen=True)
class Outcome:
    """One task's end in a batch: ``folder``, its result (``out/NAME``, a link into the
    cache; None when it failed)."""

    task: Task
    key: str
    status: Status
    folder: Path | None
    seconds: float = 0.0
    error: str = ""


@dataclass
class BatchReport:
    """Every task's outcome, by name, in the order given."""

    outcomes: dict[str, Outcome] = field(default_factory=dict)

    def count(self, status: Status) -> int:
        """How many tasks ended so."""
        return sum(1 for o in self.outcomes.values() if o.status == status)

    @property
    def failed(self) -> list[Outcome]:
        """The tasks that failed."""
        return [o for o in self.outcomes.values() if o.status == "failed"]


def config_text(task: Task) -> str | None:
    """The TOML the task runs with: its config file with its overrides laid over (None when it
    has neither). Checked here as ``companion run`` would check it (ConfigError naming the
    key), before anything runs; a replay's override holds algorithm sections only."""
    if task.config is None and not task.overrides:
        return None
    data = read_config_toml(Path(task.config)) if task.config is not None else {}
    data = merge(data, nested(task.overrides))
    if task.kind == "replay" or (task.kind == "sweep" and task.argv[0] == "replay"):
        bad = sorted(set(data) - set(SECTIONS_OF_REPLAY))
        if bad:
            raise BatchError(
                f"{task.name}: a replay's override holds [vo] [scale] [attitude] "
                f"[dpose] only, not {', '.join(bad)}"
            )
    else:
        from_dict(Config, data)  # an unknown key or a bad value: ConfigError naming it
    return to_toml(data)


def _stderr_log(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def run_batch(
    tasks: Sequence[Task],
    executor: Executor,
    out: Path,
    cache: Path | None = None,
    log: Callable[[str], None] = _stderr_log,
) -> BatchReport:
    """Run ``tasks`` (names unique; the same name twice must be the same spec) on ``executor``
    with the cache in ``cache`` (default ``out/cache``); returns every task's outcome."""
    cache = out / "cache" if cache is None else cache
    unique: dict[str, Task] = {}
    for t in tasks:
        if unique.setdefault(t.name, t) != t:
            raise BatchError(f"{t.name}: two different tasks under one name")
    keys = KeyMaker()
    jobs = [Job(t, keys.key(t), config_text(t)) for t in unique.values()]
    report = BatchReport()
    todo: list[Job] = []
    for job in jobs:
        folder = cache / job.key
        if (folder / "batch.json").is_file():
            _link(out, job.task.name, folder)
            _clear_failed(out, job.task.name)
            report.outcomes[job.task.name] = Outcome(
                job.task, job.key, "cached", out / job.task.name
            )
        else:
            todo.append(job)
    todo.sort(key=lambda j: -length_s(j.task))  # the longest first: no long tail on a pool
    log(
        f"batch: {len(jobs)} task(s), {len(jobs) - len(todo)} from the cache, "
        f"{len(todo)} to run on {executor.description}"
    )
    for i, result in enumerate(executor.run(todo), 1):
        job = next(j for j in todo if j.key == result.key and j.task.name == result.name)
        outcome = _store(job, result, out, cache, keys.code)
        report.outcomes[job.task.name] = outcome
        what = "ok" if outcome.status == "ran" else f"FAILED: {outcome.error}"
        log(f"[{i}/{len(todo)}] {job.task.name}: {what} ({result.seconds:.1f} s)")
    ordered = {t.name: report.outcomes[t.name] for t in unique.values()}
    return BatchReport(ordered)


def length_s(task: Task, frame_rate_hz: float = 30.0) -> float:
    """How much flight a task replays [s], its cost's proxy for ordering a batch: a simulated
    flight's ``--seconds`` (60 unless given), a dataset's frames at ``frame_rate_hz``
    (0 when it cannot be read: such a task goes last)."""
    argv = task.argv
    if task.kind == "flight" or (task.kind == "sweep" and not task.inputs):
        i = argv.index("--seconds") if "--seconds" in argv else -1
        return float(argv[i + 1]) if 0 <= i < len(argv) - 1 else 60.0
    if not task.inputs:
        return 0.0
    try:
        with (Path(task.inputs[0]) / "frames.csv").open("rb") as fh:
            return max(sum(1 for _ in fh) - 1, 0) / frame_rate_hz
    except OSError:
        return 0.0


def _store(job: Job, result: TaskResult, out: Path, cache: Path, code: str) -> Outcome:
    """Put a finished task's result in the cache and link its name (or record its failure)."""
    error, detail = result.error, result.detail
    if result.ok and result.code != code:
        error = (
            f"ran on other code ({result.code[:12]}, this batch's is {code[:12]}): "
            "install the same companion on every node"
        )
        detail = error
    if result.ok and not error:
        tmp = cache / f"{job.key}.tmp-{os.getpid()}"
        shutil.rmtree(tmp, ignore_errors=True)
        write_tree(tmp, result.files)
        meta = {
            "task": asdict(job.task),
            "key": job.key,
            "code": code,
            "seconds": round(result.seconds, 3),
            "finished": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "config": job.config_text,
        }
        (tmp / "batch.json").write_text(json.dumps(meta, indent=2) + "\n")
        folder = cache / job.key
        shutil.rmtree(folder, ignore_errors=True)
        tmp.rename(folder)
        _link(out, job.task.name, folder)
        _clear_failed(out, job.task.name)
        return Outcome(job.task, job.key, "ran", out / job.task.name, result.seconds)
    failed = out / "failed" / job.task.name
    failed.mkdir(parents=True, exist_ok=True)
    (failed / "error.txt").write_text(error + "\n")
    (failed / "traceback.txt").write_text(detail or error)
    return Outcome(job.task, job.key, "failed", None, result.seconds, error)


def _link(out: Path, name: str, folder: Path) -> None:
    """``out/name`` -> ``folder`` (a relative link); a real folder there is not ours: refused."""
    link = out / name
    link.parent.mkdir(parents=True, exist_ok=True)
    if link.is_symlink():
        link.unlink()
    elif link.exists():
        raise BatchError(
            f"{link}: exists and is not a batch's link: move it or choose another --out"
        )
    link.symlink_to(os.path.relpath(folder, link.parent), target_is_directory=True)


def _clear_failed(out: Path, name: str) -> None:
    shutil.rmtree(out / "failed" / name, ignore_errors=True)


def print_failures(report: BatchReport, out: Path, stream: TextIO | None = None) -> None:
    """One line per failed task, with where its traceback is."""
    for o in report.failed:
        print(
            f"FAILED {o.task.name}: {o.error} (traceback: {out / 'failed' / o.task.name})",
            file=stream or sys.stderr,
        )
