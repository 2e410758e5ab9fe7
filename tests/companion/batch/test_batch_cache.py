"""The batch's cache and its failures (companion/batch/cache.py, runner.py, run.py): a re-run
computes nothing; a changed config value or input file re-runs that task alone; a failed task
is reported with its error and traceback while the others finish.

The tasks are real runs of the CLI in their own processes: ``companion config`` (it prints the
effective configuration, so a config value shows in its result) with an input file hashed."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest

from companion.batch.cache import KeyMaker, code_version, content_hash, sources_sha256
from companion.batch.executors import Job, SerialExecutor
from companion.batch.run import TaskResult
from companion.batch.runner import run_batch
from companion.batch.spec import Task
from companion.errors import BatchError, ConfigError


class Counting(SerialExecutor):
    """The serial executor, remembering which tasks it was given."""

    def __init__(self) -> None:
        self.ran: list[str] = []

    def run(self, jobs: Sequence[Job]) -> Iterator[TaskResult]:
        self.ran += [j.task.name for j in jobs]
        yield from super().run(jobs)


def _config_task(name: str, features: int, inputs: tuple[str, ...] = ()) -> Task:
    return Task("sequence", name, ("config",), inputs, None, (("vo.max_features", features),))


def _stdout(out: Path, name: str) -> str:
    return (out / name / "stdout.txt").read_text()


def test_a_rerun_computes_nothing_and_a_change_reruns_that_task_alone(tmp_path: Path) -> None:
    data = tmp_path / "input"
    data.mkdir()
    (data / "frames.csv").write_text("time_us,seq,filename\n0,0,a.png\n")
    tasks = [_config_task("a", 150), _config_task("b", 160), _config_task("c", 170, (str(data),))]
    out = tmp_path / "out"
    first = Counting()
    report = run_batch(tasks, first, out, log=lambda _: None)
    assert first.ran == ["c", "a", "b"]  # the longest first: c replays one frame
    assert [o.status for o in report.outcomes.values()] == ["ran"] * 3
    assert "max_features = 160" in _stdout(out, "b")  # the override reached the run
    again = Counting()
    report = run_batch(tasks, again, out, log=lambda _: None)
    assert again.ran == []  # nothing computed
    assert {o.status for o in report.outcomes.values()} == {"cached"}
    # a config value of one task changed: that task alone runs again
    tasks[1] = _config_task("b", 180)
    third = Counting()
    run_batch(tasks, third, out, log=lambda _: None)
    assert third.ran == ["b"]
    assert "max_features = 180" in _stdout(out, "b")
    # an input file's bytes changed: that task alone
    (data / "frames.csv").write_text("time_us,seq,filename\n0,0,b.png\n")
    fourth = Counting()
    run_batch(tasks, fourth, out, log=lambda _: None)
    assert fourth.ran == ["c"]
    # back to the first value: from the cache (results are kept by key, not by name)
    tasks[1] = _config_task("b", 160)
    fifth = Counting()
    run_batch(tasks, fifth, out, log=lambda _: None)
    assert fifth.ran == []
    assert "max_features = 160" in _stdout(out, "b")


def test_a_failed_task_is_reported_and_the_others_finish(tmp_path: Path) -> None:
    bad = Task("sequence", "bad", ("config", "--no-such-flag"))
    tasks = [_config_task("good-1", 150), bad, _config_task("good-2", 160)]
    out = tmp_path / "out"
    report = run_batch(tasks, SerialExecutor(), out, log=lambda _: None)
    assert [o.status for o in report.outcomes.values()] == ["ran", "failed", "ran"]
    (failed,) = report.failed
    assert failed.task.name == "bad" and failed.folder is None
    assert failed.error.startswith("exit 2:") and "--no-such-flag" in failed.error
    assert "--no-such-flag" in (out / "failed" / "bad" / "error.txt").read_text()
    assert (out / "failed" / "bad" / "traceback.txt").read_text().strip()
    assert not (out / "bad").exists()
    # a failure is never cached: the next batch tries it again, the others come from the cache
    again = Counting()
    report = run_batch(tasks, again, out, log=lambda _: None)
    assert again.ran == ["bad"]
    assert report.count("cached") == 2 and report.count("failed") == 1


def test_a_bad_config_key_is_refused_before_anything_runs(tmp_path: Path) -> None:
    ran = Counting()
    task = Task("sequence", "x", ("config",), overrides=(("vo.no_such_key", 1),))
    with pytest.raises(ConfigError, match="no_such_key"):
        run_batch([_config_task("ok", 150), task], ran, tmp_path, log=lambda _: None)
    assert ran.ran == []
    with pytest.raises(BatchError, match="two different tasks"):
        run_batch([_config_task("a", 1), _config_task("a", 2)], ran, tmp_path)


def test_the_key_follows_the_code_the_inputs_and_the_spec_not_the_name(tmp_path: Path) -> None:
    f = tmp_path / "in.txt"
    f.write_text("one")
    task = _config_task("a", 150, (str(f),))
    k1 = KeyMaker("code-1").key(task)
    assert KeyMaker("code-1").key(task) == k1
    assert KeyMaker("code-2").key(task) != k1  # another code version
    assert KeyMaker("code-1").key(_config_task("renamed", 150, (str(f),))) == k1
    assert KeyMaker("code-1").key(_config_task("a", 151, (str(f),))) != k1
    f.write_text("two")
    assert KeyMaker("code-1").key(task) != k1
    # a folder's hash: its files' names and bytes
    d = tmp_path / "d"
    (d / "sub").mkdir(parents=True)
    (d / "sub" / "x").write_bytes(b"1")
    h = content_hash(d)
    (d / "sub" / "x").rename(d / "sub" / "y")
    assert content_hash(d) != h
    with pytest.raises(BatchError, match="no such file"):
        content_hash(tmp_path / "absent")
    assert len(code_version()) == 64


def test_the_code_version_follows_what_a_task_runs_not_how_its_table_is_drawn(
    tmp_path: Path,
) -> None:
    for rel in ("vo/odometry.py", "batch/plans.py", "batch/runner.py", "cli/results.py"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("x = 1\n")
    before = sources_sha256(tmp_path)
    (tmp_path / "batch" / "plans.py").write_text("x = 2  # a new table\n")
    (tmp_path / "cli" / "results.py").write_text("x = 2  # a reworded column\n")
    (tmp_path / "vo" / "notes.txt").write_text("not code")
    assert sources_sha256(tmp_path) == before
    for rel in ("vo/odometry.py", "batch/runner.py"):  # what computes, or runs, a result
        (tmp_path / rel).write_text("x = 3\n")
        changed = sources_sha256(tmp_path)
        assert changed != before
        before = changed


def test_the_longest_tasks_go_first(tmp_path: Path) -> None:
    from companion.batch.runner import length_s
    from companion.batch.spec import flight, sequence

    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "frames.csv").write_text("time_us,seq,filename\n" + "0,0,a.png\n" * 90)
    assert length_s(sequence("s", seq)) == 3.0  # 90 frames at 30 Hz
    assert length_s(sequence("gone", tmp_path / "absent")) == 0.0
    assert length_s(flight("f", "hills", "circle", 1, 600.0)) == 600.0

    class NotRun(SerialExecutor):
        """Records the order it is given the jobs in and runs none of them."""

        def __init__(self) -> None:
            self.order: list[str] = []

        def run(self, jobs: Sequence[Job]) -> Iterator[TaskResult]:
            for j in jobs:
                self.order.append(j.task.name)
                yield TaskResult(j.task.name, j.key, False, 0.0, "", error="not run")

    tasks = [
        _config_task("none", 150),
        flight("short", "flat", "hover", 1, 5.0),
        sequence("seq", seq),
        flight("long", "hills", "circle", 1, 600.0),
    ]
    executor = NotRun()
    report = run_batch(tasks, executor, tmp_path / "out", log=lambda _: None)
    assert executor.order == ["long", "short", "seq", "none"]
    assert list(report.outcomes) == ["none", "short", "seq", "long"]  # reported as given
