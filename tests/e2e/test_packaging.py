"""Packaging (issue 20 item 4): the service runs on its runtime dependencies alone, the wheel and
the sdist hold what a board needs, and the installed unit, the install script and the default
config agree with each other."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import tarfile
import tomllib
import zipfile
from pathlib import Path

import pytest
from peers.refuse_extras import EXTRAS_ONLY, REFUSE_EXTRAS

REPO = Path(__file__).resolve().parents[2]

# Runs in a fresh interpreter: a meta path finder refuses (and records) every import of the
# extras' modules, then the board's whole product is imported and the service's commands run:
# `--version`, `config` and `run` for 1.5 s on the board config (no devices: it waits for them).
_PROBE = (
    r"""
import contextlib, importlib, io, json, pkgutil, sys

BLOCKED = set(sys.argv[1].split(","))
"""
    + REFUSE_EXTRAS
    + r"""
out = {"exit": {}, "import_errors": {}}

import companion
from companion.cli import main

def walk(path, prefix):
    # pkgutil.walk_packages imports every package to look inside: the simulator's too
    for mod in pkgutil.iter_modules(path, prefix):
        if mod.name.endswith(".__main__") or mod.name == "companion.sitl":
            continue  # __main__ runs the CLI; the simulator is the sim extra (refused below)
        try:
            module = importlib.import_module(mod.name)
        except ImportError as e:
            out["import_errors"][mod.name] = str(e)
            continue
        if mod.ispkg:
            walk(module.__path__, mod.name + ".")


walk(companion.__path__, "companion.")

config = sys.argv[2]
for name, argv in (
    ("version", ["--version"]),
    ("config", ["config", "--config", config]),
    ("run", ["run", "--config", config, "--duration", "1.5"]),
):
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        out["exit"][name] = main(argv)
    out.setdefault("stdout", {})[name] = buf.getvalue()

out["service_path_attempts"] = list(attempts)
# the finder itself works: the simulator is refused here, though this venv has it
try:
    import companion.sitl.world.terrain  # noqa: F401
    out["sitl_refused"] = False
except ModuleNotFoundError:
    out["sitl_refused"] = True
out["attempts_after_check"] = list(attempts)
print("PROBE " + json.dumps(out))
"""
)


def board_config(tmp_path: Path) -> Path:
    """config/default.toml as shipped, with the devices moved to paths that do not exist (a CI
    machine with a /dev/video0 must not have its camera opened) and the status socket and
    state kept in tmp_path; the drivers are the board's: serial link, V4L2/VideoCapture."""
    text = (REPO / "config" / "default.toml").read_text()
    extra = (
        f'mavlink_url = "serial:{tmp_path}/ttyAMA0:921600"\n'
        'camera_url = "/dev/video-absent-companion-test"\n'
        f'status_socket = "{tmp_path}/status.sock"\n'
        f'state_dir = "{tmp_path}/state"\n'
    )
    text = re.sub(r"^(mavlink_url|camera_url) = .*\n", "", text, flags=re.M)
    assert text.count("[service]\n") == 1
    path = tmp_path / "board.toml"
    path.write_text(text.replace("[service]\n", "[service]\n" + extra))
    return path


def test_the_service_never_imports_the_simulator_or_evaluation_extras(tmp_path: Path) -> None:
    config = board_config(tmp_path)
    r = subprocess.run(
        [sys.executable, "-c", _PROBE, ",".join(EXTRAS_ONLY), str(config)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    line = next((x for x in r.stdout.splitlines() if x.startswith("PROBE ")), None)
    assert line is not None, r.stdout[-3000:] + r.stderr[-3000:]
    out = json.loads(line[len("PROBE ") :])
    # the finder is not a no-op: with it, the simulator cannot be imported, and it was seen
    assert out["sitl_refused"] and "companion.sitl" in out["attempts_after_check"]
    # nothing on the service path (every module of companion and drivers, the commands a board
    # runs) even tried to import an extra, and every module imported
    assert out["service_path_attempts"] == [], out["service_path_attempts"]
    assert out["import_errors"] == {}, out["import_errors"]
    assert out["exit"] == {"version": 0, "config": 0, "run": 0}, (out["exit"], r.stderr[-3000:])
    assert "companion " in out["stdout"]["version"]
    assert "service.mavlink_url = 'serial:" in out["stdout"]["config"]
    # `run` started the service on the board's drivers and waited for the missing devices
    assert "does not exist (yet): waiting for it" in r.stderr, r.stderr[-3000:]


def test_runtime_dependencies_leave_the_extras_out() -> None:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    runtime = {re.split(r"[<>=!~ ;\[]", d)[0].lower() for d in project["dependencies"]}
    extras = project["optional-dependencies"]
    heavy_ones = ("numba", "scikit-image", "matplotlib", "evo", "pandas", "mypy", "pytest", "ray")
    for heavy in (*heavy_ones, "filterpy"):
        assert heavy not in runtime, heavy
    for needed in (
        "numpy",
        "scipy",
        "opencv-python-headless",
        "pymavlink",
        "mavsdk",
        "pyserial",
        "aiohttp",  # the live page
    ):
        assert needed in runtime, needed
    assert {"sim", "eval", "dev", "cluster"} <= set(extras)
    assert any(d.startswith("ray") for d in extras["cluster"])  # the batch runner, not a board
    assert any(d.startswith("numba") for d in extras["sim"])
    assert any(d.startswith("scikit-image") for d in extras["sim"])
    # make venv / test / demo install every extra (CI and the demo need the simulator, the
    # cluster test Ray)
    assert "pip install -q -e '.[dev,eval,sim,cluster]'" in (REPO / "Makefile").read_text()


def test_wheel_and_sdist_hold_what_a_board_needs(tmp_path: Path) -> None:
    """`python -m build` on a copy of the tree (the shared working tree stays untouched)."""
    pytest.importorskip("build", reason="python -m build: pip install build (the dev extra)")
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE", "MANIFEST.in", "Makefile"):
        shutil.copy2(REPO / name, src / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    for name in ("companion", "drivers", "sitl", "config", "systemd", "docs", "tests"):
        shutil.copytree(REPO / name, src / name, ignore=ignore)
    dist = tmp_path / "dist"
    r = subprocess.run(
        [sys.executable, "-m", "build", "--outdir", str(dist), str(src)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    (wheel,) = dist.glob("companion-*-py3-none-any.whl")
    (sdist,) = dist.glob("companion-*.tar.gz")

    names = set(zipfile.ZipFile(wheel).namelist())
    for path in (
        "companion/cli/__init__.py",
        "companion/service/app.py",
        "companion/py.typed",
        "companion/service/web_page.html",  # the live page, package data
        "companion/drivers/camera/__init__.py",
        "companion/drivers/mavlink.py",
        "companion/drivers/rangefinder.py",
        "companion/sitl/world/terrain.py",  # for the sim extra
    ):
        assert path in names, path
    # one import package: drivers/ and sitl/ install as companion.drivers and companion.sitl
    # (docs/decisions.md, "One installed package")
    top = {n.split("/", 1)[0] for n in names if not n.split("/", 1)[0].endswith(".dist-info")}
    assert top == {"companion"}, top
    meta = next(n for n in names if n.endswith(".dist-info/METADATA"))
    requires = [
        line.split(":", 1)[1].strip()
        for line in zipfile.ZipFile(wheel).read(meta).decode().splitlines()
        if line.startswith("Requires-Dist:")
    ]
    unconditional = [d for d in requires if "extra ==" not in d]
    assert not any(d.startswith(("numba", "scikit-image", "matplotlib")) for d in unconditional)
    assert any(d.startswith("numba") and 'extra == "sim"' in d for d in requires)
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert "companion = companion.cli:main" in zipfile.ZipFile(wheel).read(entry_points).decode()

    with tarfile.open(sdist) as tar:
        members = {m.split("/", 1)[1] for m in tar.getnames() if "/" in m}
    for path in (
        "Makefile",
        "config/default.toml",
        "config/sitl.toml",
        "systemd/companion.service",
        "systemd/board-install.sh",
        "docs/install.md",
        "companion/service/app.py",
        "companion/drivers/camera/__init__.py",
    ):
        assert path in members, path


def _script_default(name: str) -> str:
    text = (REPO / "systemd" / "board-install.sh").read_text()
    m = re.search(rf"^{name}=(?:\$\{{{name}:-)?([^}}\s]+)\}}?", text, flags=re.M)
    assert m, name
    return m.group(1)


def test_unit_install_script_and_docs_agree_on_paths() -> None:
    unit = (REPO / "systemd" / "companion.service").read_text()
    prefix, sysconf = _script_default("PREFIX"), _script_default("SYSCONFDIR")
    state, user = _script_default("STATEDIR"), _script_default("SERVICE_USER")
    assert (prefix, sysconf, state, user) == (
        "/opt/companion",
        "/etc/companion",
        "/var/lib/companion",
        "companion",
    )
    exec_start = re.search(r"^ExecStart=(.*)$", unit, flags=re.M)
    assert exec_start is not None
    assert exec_start.group(1) == f"{prefix}/venv/bin/companion run --config {sysconf}/config.toml"
    assert f"User={user}\n" in unit and f"Group={user}\n" in unit
    assert f"StateDirectory={Path(state).name}\n" in unit and state.startswith("/var/lib/")
    assert f"Documentation=file://{prefix}/README.md" in unit
    # the Jetson's and the Pi's UARTs that config/default.toml names are allowed devices
    for device_class in ("ttyAMA", "ttyS", "ttyTHS", "ttyACM", "ttyUSB", "video4linux"):
        assert f"DeviceAllow=char-{device_class} rw" in unit, device_class
    install_md = (REPO / "docs" / "install.md").read_text()
    assert f"{prefix}/venv/bin/companion" in install_md
    assert "make install" in install_md


def test_default_config_is_a_real_board_and_sitl_config_the_simulator() -> None:
    from companion.config import load_config

    board = load_config(REPO / "config" / "default.toml").service
    assert re.fullmatch(r"serial:/dev/\w+:921600", board.mavlink_url), board.mavlink_url
    assert re.fullmatch(r"/dev/video\d+", board.camera_url), board.camera_url
    sim = load_config(REPO / "config" / "sitl.toml").service
    assert sim.mavlink_url.startswith("udpin:127.0.0.1:")
    assert sim.camera_url.startswith("sitl://127.0.0.1:")


_PROBE_SIM = r"""
import importlib.abc, sys

BLOCKED = set(sys.argv[1].split(","))


class RefuseExtras(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None


sys.meta_path.insert(0, RefuseExtras())
from companion.cli import main

sys.exit(main(["sitl", "record", "--seconds", "1", "--out", sys.argv[2]]))
"""


def test_a_simulator_command_without_the_sim_extra_names_the_extra(tmp_path: Path) -> None:
    """On a board (runtime dependencies only) `companion sitl ...` exits 1 with one line naming
    the extra to install, not a traceback."""
    r = subprocess.run(
        [sys.executable, "-c", _PROBE_SIM, "numba,llvmlite,skimage,tomli_w", str(tmp_path / "d")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 1, r.stderr[-3000:]
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    assert "needs the 'sim' extra" in r.stderr and "pip install 'companion[sim]'" in r.stderr
    assert not (tmp_path / "d").exists()


ON_USE_ONLY = ("aiohttp", "mcap", "zstandard", "google.protobuf", "foxglove_schemas_protobuf")


def test_the_page_and_mcap_packages_load_only_when_used() -> None:
    """The service with [web] off and no MCAP recording loads neither aiohttp nor the MCAP
    stack (15 MB of the process's memory at start on x86); a replay of a folder neither."""
    probe = (
        "import sys, json\n"
        "import companion.service.app, companion.cli.service, companion.drivers.dataset\n"
        "from companion.service.recorder import Recorder\n"
        f"print(json.dumps(sorted(m for m in {ON_USE_ONLY!r} if m in sys.modules)))\n"
        "from companion.drivers.dataset.recording import make_writer\n"
        "import companion.service.web, companion.drivers.dataset.mcap_reader\n"
        f"print(json.dumps(sorted(m for m in {ON_USE_ONLY!r} if m in sys.modules)))\n"
    )
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    before, after = (json.loads(line) for line in r.stdout.splitlines()[-2:])
    assert before == [], before
    assert after == sorted(ON_USE_ONLY)  # the probe sees them when they are loaded
