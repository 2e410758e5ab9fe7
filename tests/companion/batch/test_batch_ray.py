"""The batch on Ray gives what it gives serially (companion/batch/executors.py): a local Ray
on this machine's cores, and a real multi-process cluster on 127.0.0.1 (a head and a second
node started with ``ray start``, the runner connecting by address). Skipped, saying why, when
Ray (the ``cluster`` extra) is not installed; without it ``--executor ray`` is exit 2 naming
the extra.

Teardown stops only what these tests started: the processes whose command line names the
cluster's own temporary folder, and their children (never a bare ``ray stop``, which would
end every Ray of this user on the machine)."""

from __future__ import annotations

import contextlib
import importlib.util
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from companion.batch import spec
from companion.batch.executors import RayExecutor, SerialExecutor
from companion.batch.runner import BatchReport, run_batch
from companion.cli import main

REPO = Path(__file__).resolve().parents[3]
HAS_RAY = importlib.util.find_spec("ray") is not None
needs_ray = pytest.mark.skipif(
    not HAS_RAY, reason="Ray is not installed (pip install 'companion[cluster]')"
)
SECONDS = 2.0  # short flights: the VO alone, a few seconds each
FLIGHTS = [
    spec.flight(f"{t}-lawnmower-{s}", t, "lawnmower", s, SECONDS, ("--methods", "vo"))
    for t, s in (("flat", 1), ("hills", 2), ("flat", 3), ("hills", 4))
]
METRICS = ("metrics.json", "vo.tum", "poses.csv")


def _files(report: BatchReport) -> dict[str, dict[str, bytes]]:
    out = {}
    for name, o in report.outcomes.items():
        assert o.status == "ran" and o.folder is not None, (name, o.error)
        out[name] = {f: (o.folder / f).read_bytes() for f in METRICS}
    return out


@pytest.fixture(scope="module")
def serial(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, bytes]]:
    """The four flights run one after another in this process's order."""
    out = tmp_path_factory.mktemp("serial")
    return _files(run_batch(FLIGHTS, SerialExecutor(), out, log=lambda _: None))


def test_without_ray_the_ray_executor_is_exit_2_naming_the_extra(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails as if not installed
    argv = ["sweep", "--grid", "vo.max_features=150", "--flights", "flat-lawnmower-1"]
    code = main([*argv, "--executor", "ray", "--out", str(tmp_path)])
    assert code == 2
    assert "pip install 'companion[cluster]'" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing ran


@needs_ray
@pytest.mark.slow
def test_ray_local_gives_the_serial_results(
    serial: dict[str, dict[str, bytes]], tmp_path: Path
) -> None:
    executor = RayExecutor(num_cpus=2)
    try:
        report = run_batch(FLIGHTS[:2], executor, tmp_path, log=lambda _: None)
    finally:
        executor.close()
    local = _files(report)
    assert local == {n: serial[n] for n in local}
    assert len(local) == 2 and all(b"ate_sim3_m" in f["metrics.json"] for f in local.values())


# ------------------------------------------------------------------------------ the cluster
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _ours(marker: str) -> list[int]:
    """Pids whose command line names ``marker`` (the cluster's temp folder), and children."""
    found = set()
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        with contextlib.suppress(OSError):
            if marker in (proc / "cmdline").read_bytes().decode(errors="replace"):
                found.add(int(proc.name))
    children = set()
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                ppid = int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
                if ppid in found:
                    children.add(int(proc.name))
    return sorted(found | children)


def _stop(marker: str) -> None:
    """SIGTERM to this cluster's processes, SIGKILL to those still there after 5 s."""
    for sig, wait_s in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 2.0)):
        pids = _ours(marker)
        for pid in pids:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, sig)
        end = time.monotonic() + wait_s
        while pids and time.monotonic() < end:
            pids = [p for p in pids if Path(f"/proc/{p}").exists() and not _zombie(p)]
            time.sleep(0.2)


def _zombie(pid: int) -> bool:
    with contextlib.suppress(OSError, IndexError):
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    return True


@pytest.fixture
def cluster(monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """A head and a second node, one CPU each, on 127.0.0.1 (Ray's token authentication, its
    token in the user's ~/.ray/auth_token as for any local Ray; no dashboard; a 200 MB object
    store each); yields the head's address."""
    ray_bin = Path(sys.executable).parent / "ray"
    if not ray_bin.exists():
        pytest.skip(f"no `ray` command beside {sys.executable}")
    temp = tempfile.mkdtemp(prefix="ray-", dir="/tmp")  # short: Ray's socket paths live in it
    env = {
        "RAY_AUTH_MODE": "token",  # the second node and the driver too, not the head alone
        "RAY_USAGE_STATS_ENABLED": "0",
        "PYTHONPATH": os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p),
    }
    for k, v in env.items():
        monkeypatch.setenv(k, v)  # the nodes, and the driver in this process
    port = _free_port()
    common = ["--node-ip-address", "127.0.0.1", "--num-cpus", "1", "--temp-dir", temp]
    common += ["--object-store-memory", str(200 * 10**6), "--disable-usage-stats"]
    head = [str(ray_bin), "start", "--head", "--port", str(port), "--include-dashboard=false"]
    node = [str(ray_bin), "start", "--address", f"127.0.0.1:{port}"]
    try:
        for cmd in (head + common, node + common):
            subprocess.run(cmd, check=True, capture_output=True, timeout=180, env=os.environ)
        yield f"127.0.0.1:{port}"
    finally:
        _stop(temp)
        shutil.rmtree(temp, ignore_errors=True)


@needs_ray
@pytest.mark.slow
def test_a_two_node_cluster_gives_the_serial_results(
    serial: dict[str, dict[str, bytes]], cluster: str, tmp_path: Path
) -> None:
    executor = RayExecutor(address=cluster)
    try:
        assert "2 node(s), 2 CPUs" in executor.description
        report = run_batch(FLIGHTS, executor, tmp_path, log=lambda _: None)
    finally:
        executor.close()
    assert _files(report) == serial  # the same bytes, flight by flight
