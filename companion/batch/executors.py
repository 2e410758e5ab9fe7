"""Executors: where a batch's tasks run, behind one interface (``run(jobs)`` yields each
job's TaskResult as it finishes; ``close()``).

- ``SerialExecutor``: one after another, in this process's order.
- ``RayExecutor``: Ray tasks, one CPU each. ``address`` None and no ``RAY_ADDRESS``: a local
  Ray on this machine's cores, started and stopped here (no dashboard, a small object
  store); otherwise the running cluster at that address (``ray start --head`` on one node,
  ``ray start --address HEAD:PORT`` on the others). Ray is imported here only, when chosen:
  without it, BatchError naming the extra ``companion[cluster]``.

The results are the same whichever runs them: a task is a pure function of its spec and
of the code, and each runs in its own process either way.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from typing import Any, NamedTuple, Protocol

from companion.batch.run import TaskResult, run_task
from companion.batch.spec import Task
from companion.errors import BatchError

LOCAL_OBJECT_STORE_BYTES = 200 * 2**20  # results are folders of a few MB; the RAM is the tasks'
EXECUTORS = ("serial", "ray")


class Job(NamedTuple):
    """A task to run: its spec, its cache key and its config as TOML text (or None)."""

    task: Task
    key: str
    config_text: str | None


class Executor(Protocol):
    """Runs jobs; yields a TaskResult per job as each finishes (any order)."""

    description: str

    def run(self, jobs: Sequence[Job]) -> Iterator[TaskResult]: ...

    def close(self) -> None: ...


class SerialExecutor:
    """Every job in this process's thread, one after another."""

    description = "serial (in this process, one task at a time)"

    def run(self, jobs: Sequence[Job]) -> Iterator[TaskResult]:
        for job in jobs:
            yield run_task(*job)

    def close(self) -> None:
        pass


class RayExecutor:
    """Every job as a Ray task of one CPU, on a local Ray or on the cluster at ``address``."""

    def __init__(self, address: str | None = None, num_cpus: int | None = None) -> None:
        try:
            import ray as ray_module
        except ModuleNotFoundError:
            raise BatchError(
                "--executor ray needs Ray, which is not installed: pip install 'companion[cluster]'"
            ) from None
        ray: Any = ray_module
        self._ray = ray
        address = address or os.environ.get("RAY_ADDRESS") or None
        kwargs: dict[str, Any] = {"log_to_driver": False, "configure_logging": False}
        try:
            if address:
                ray.init(address=address, **kwargs)
                where = f"the Ray cluster at {address}"
            else:
                cpus = num_cpus or os.cpu_count() or 1
                ray.init(
                    address="local",
                    num_cpus=cpus,
                    include_dashboard=False,
                    object_store_memory=LOCAL_OBJECT_STORE_BYTES,
                    **kwargs,
                )
                where = "a local Ray"
        except (ConnectionError, RuntimeError, ValueError) as e:
            raise BatchError(f"Ray at {address or 'local'}: {e}") from None
        cpus_total = int(ray.cluster_resources().get("CPU", 0))
        nodes = sum(1 for n in ray.nodes() if n.get("Alive"))
        self.description = f"ray ({where}: {nodes} node(s), {cpus_total} CPUs)"
        self._remote = ray.remote(num_cpus=1, max_retries=0)(run_task)

    def run(self, jobs: Sequence[Job]) -> Iterator[TaskResult]:
        ray = self._ray
        pending = {self._remote.remote(*job): job for job in jobs}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                job = pending.pop(ref)
                try:
                    yield ray.get(ref)
                except Exception as e:  # the worker died, the node was lost
                    yield TaskResult(
                        job.task.name, job.key, False, 0.0, "", error=f"{type(e).__name__}: {e}"
                    )

    def close(self) -> None:
        self._ray.shutdown()


def make_executor(name: str, address: str | None = None) -> Executor:
    """The executor called ``name`` (``serial`` or ``ray``); BatchError for another, or for
    ``--address`` without Ray."""
    if name == "serial":
        if address:
            raise BatchError("--address is for --executor ray")
        return SerialExecutor()
    if name == "ray":
        return RayExecutor(address)
    raise BatchError(f"--executor {name}: one of {', '.join(EXECUTORS)}")
