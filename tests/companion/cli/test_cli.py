"""The ``companion`` command line: lazy start-up, help on every flag, exit codes, JSON errors,
a closed pipe, log levels, and where ``companion status`` / ``px4 check`` find the service."""

from __future__ import annotations

import argparse
import json
import os
import re
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from peers import free_port
from peers.status import SAMPLE, halt, serve_in_thread

import companion.drivers.status as status_mod
from companion.autopilot.options import CheckOptions
from companion.autopilot.px4.check import resolve
from companion.cli import COMMANDS, build_parser, main
from companion.cli.common import EXIT_CODES, EXIT_PROBLEMS, EXIT_UNREACHABLE, EXIT_USAGE
from companion.config import load_config
from companion.drivers.status import find_status_socket, status_path, user_status_path
from companion.errors import ConfigError

ROOT = Path(__file__).resolve().parents[3]
HEAVY = ("numpy", "scipy", "cv2", "sitl", "pymavlink", "mavsdk", "companion.pipeline")


def companion(*argv: str, **kw: object) -> subprocess.CompletedProcess[str]:
    """``python -m companion.cli ARGV`` in the repository (the console script's code)."""
    return subprocess.run(
        [sys.executable, "-m", "companion.cli", *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        **kw,  # type: ignore[arg-type]
    )


# ---------------------------------------------------------------- lazy start-up (no timing)
LOADED = textwrap.dedent(
    """
    import contextlib, io, json, sys
    from companion.cli import main
    heavy = {heavy!r}
    seen = {{}}
    for argv in {argvs!r}:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            code = main(argv)
        seen[" ".join(argv)] = [code, sorted(m for m in heavy if m in sys.modules),
                                "companion.cli.service" in sys.modules]
    print(json.dumps(seen))
    """
)


def loaded_modules(tmp_path: Path, *argvs: list[str]) -> dict[str, list[object]]:
    """Run main(argv) for each argv in order in a fresh interpreter: per argv, the exit code,
    the HEAVY modules loaded so far and whether companion.cli.service was imported."""
    code = LOADED.format(heavy=HEAVY, argvs=[list(a) for a in argvs])
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path)}
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, env=env, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)  # type: ignore[no-any-return]


def test_help_version_and_status_import_nothing_heavy(tmp_path: Path) -> None:
    """--help, --version and status (found or not) load neither NumPy, SciPy, OpenCV nor the
    simulator; a command that needs the config (`config`) does load NumPy: the check can fail."""
    seen = loaded_modules(
        tmp_path,
        ["--version"],
        ["--help"],
        ["status"],
        ["status", "--json"],
        ["status", "--socket", str(tmp_path / "none.sock")],
        ["config"],
    )
    assert seen["--version"] == [0, [], False]
    assert seen["--help"] == [0, [], False]
    assert seen["status"] == [EXIT_UNREACHABLE, [], True]  # its module, and nothing heavy
    assert seen["status --json"] == [EXIT_UNREACHABLE, [], True]
    assert seen[f"status --socket {tmp_path / 'none.sock'}"] == [EXIT_UNREACHABLE, [], True]
    code, heavy, _ = seen["config"]
    assert code == 0 and "numpy" in heavy  # the structural check sees a heavy import


def test_a_command_only_loads_its_own_module() -> None:
    """Parsing `status` fills only its parser; the others stay empty until used."""
    parser = build_parser()
    args = parser.parse_args(["status", "--json"])
    assert args.command == "status" and args.json is True
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    filled = {name for name, p in sub.choices.items() if p._loaded}  # type: ignore[attr-defined]
    assert filled == {"status"}


# ---------------------------------------------------------------- help
def walk(parser: argparse.ArgumentParser, path: str) -> list[str]:
    """Every flag, positional and command of the tree (loading each command) without help."""
    missing = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            missing += [f"{path} {c.dest}" for c in action._choices_actions if not c.help]
            for name, sub in action.choices.items():
                load = getattr(sub, "load", None)
                if load is not None:
                    load()
                missing += walk(sub, f"{path} {name}")
        elif not action.help:
            missing.append(f"{path} {'/'.join(action.option_strings) or action.dest}")
    return missing


def test_every_flag_of_every_command_has_help() -> None:
    parser = build_parser(load_all=True)
    assert walk(parser, "companion") == []
    # the tree is all there: one leaf we know, with its own flags and handler
    ns = parser.parse_args(["px4", "check", "--watch-s", "0"])
    assert ns.func.__name__ == "cmd_check" and ns.watch_s == 0


def test_the_registry_help_is_each_modules_own() -> None:
    """`companion --help` shows COMMANDS' help without importing the modules: it must say
    what the module itself says (a module changing its help fails here, not silently)."""
    parser = build_parser(load_all=True)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert list(sub.choices) == [c.name for c in COMMANDS]
    for c in COMMANDS:
        assert sub.choices[c.name].module_help == c.help, c.name  # type: ignore[attr-defined]


def test_top_level_help_lists_commands_flags_and_exit_codes(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    for c in COMMANDS:
        assert re.search(rf"^\s+{c.name}\s+{re.escape(c.help)}", text, re.M), c.name
    for flag in ("--version", "-v, --verbose", "--log-level LEVEL"):
        assert flag in text
    for code, meaning in EXIT_CODES:
        assert re.search(rf"^\s+{code}\s+{re.escape(meaning)}$", text, re.M), code
    assert "Command line of" not in text  # not the module docstring


def test_a_command_help_shows_its_flags_and_the_log_flags(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["status", "--help"]) == 0
    text = capsys.readouterr().out
    assert "usage: companion status" in text
    for flag in ("--socket", "--json", "--watch", "--config", "--log-level"):
        assert flag in text


# ---------------------------------------------------------------- exit codes, JSON errors
def test_exit_code_table_in_docs_matches_the_code() -> None:
    """docs/service.md, "Exit codes": one row per code in EXIT_CODES, nothing else."""
    doc = (ROOT / "docs/service.md").read_text()
    section = doc.split("## Exit codes", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| `?(\d+)`? \|", section, re.M)
    assert [int(r) for r in rows] == [code for code, _ in EXIT_CODES]


def test_status_json_not_running_is_a_json_object(tmp_path: Path) -> None:
    none = tmp_path / "none.sock"
    proc = companion("status", "--json", "--socket", str(none))
    assert proc.returncode == EXIT_UNREACHABLE == 3
    obj = json.loads(proc.stdout)
    assert obj["exit_code"] == 3 and obj["socket"] == str(none)
    assert "not running" in obj["error"] and proc.stderr == ""


def test_json_errors_for_bad_usage_bad_config_and_an_untrusted_socket(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # a flag status does not know: usage error, exit 2, as JSON because --json was given
    assert main(["status", "--json", "--bogus"]) == EXIT_USAGE
    out, err = capsys.readouterr()
    obj = json.loads(out)
    assert obj == {"error": obj["error"], "exit_code": 2, "kind": "usage"} and err == ""
    assert "--bogus" in obj["error"]
    # a config that is not TOML: config error, exit 2, naming the file
    bad = tmp_path / "bad.toml"
    bad.write_text("[service\n")
    assert main(["status", "--json", "--config", str(bad)]) == EXIT_USAGE
    obj = json.loads(capsys.readouterr().out)
    assert obj["exit_code"] == 2 and obj["kind"] == "config error" and str(bad) in obj["error"]
    # something that is not a socket at the path: a StatusError (exit 1), as JSON
    plain = tmp_path / "plain"
    plain.write_text("x")
    assert main(["status", "--json", "--socket", str(plain)]) == EXIT_PROBLEMS
    obj = json.loads(capsys.readouterr().out)
    assert obj["exit_code"] == 1 and "not a socket" in obj["error"]
    # the same without --json: text on stderr, nothing on stdout
    assert main(["status", "--socket", str(plain)]) == EXIT_PROBLEMS
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("companion: error: ") and "not a socket" in err


def test_usage_error_without_json_is_argparse_text(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["status", "--bogus"]) == EXIT_USAGE
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("usage: companion") and "--bogus" in err
    assert main([]) == EXIT_USAGE  # no command
    assert "COMMAND" in capsys.readouterr().err


@pytest.mark.timeout(120)
def test_px4_check_without_an_autopilot_exits_3_not_1(tmp_path: Path) -> None:
    """Nothing on the link: 3 (unreachable), not 1 (problems found: test_px4_stub.py)."""
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[service]\nstatus_socket = "{tmp_path / "none.sock"}"\n')
    url = f"udpin://127.0.0.1:{free_port(socket.SOCK_DGRAM)}"
    proc = companion(
        "px4", "check", "--config", str(cfg), "--url", url, "--timeout-s", "1", "--watch-s", "0"
    )
    assert proc.returncode == EXIT_UNREACHABLE, proc.stderr
    assert "companion: unreachable: no autopilot heartbeat on" in proc.stderr
    assert "Traceback" not in proc.stderr


# ---------------------------------------------------------------- a closed pipe
@pytest.mark.parametrize("buffered", [True, False])
@pytest.mark.parametrize(
    "argv",
    [
        ["config"],
        ["--help"],
        ["--version"],
        ["status", "--help"],
        ["status", "--json", "--socket", "/nonexistent/s.sock"],
    ],
)
def test_a_closed_stdout_ends_quietly_with_141(argv: list[str], buffered: bool) -> None:
    """The reader is gone before anything is written (the end of `| head -1`): exit 141 and
    not a word on stderr (no BrokenPipeError traceback, no 'Exception ignored'), whether
    stdout is buffered (a write fails at the flush) or not (PYTHONUNBUFFERED: at the write)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    if not buffered:
        env["PYTHONUNBUFFERED"] = "1"
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "companion.cli", *argv],
            cwd=ROOT,
            stdout=write_end,
            stderr=subprocess.PIPE,
            text=True,
            timeout=120,
            env=env,
        )
    finally:
        os.close(write_end)
    assert proc.returncode == 141, proc.stderr
    assert proc.stderr == ""


def test_config_into_head_through_a_shell() -> None:
    """`companion config | head -1` as a user types it: one line, nothing on stderr."""
    cmd = f"set -o pipefail; {sys.executable} -m companion.cli config | head -1"
    proc = subprocess.run(
        ["bash", "-c", cmd], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert proc.stdout.count("\n") == 1 and proc.stdout.startswith("camera.")
    assert proc.stderr == ""
    # the whole output is longer than a pipe's first read: head closes it early (141), or
    # the output fitted in the pipe before head exited (0); never anything else
    assert proc.returncode in (0, 141)


# ---------------------------------------------------------------- log levels
def service_toml(tmp_path: Path) -> Path:
    """A service config with no peers: link and camera on free loopback ports, state and
    status socket in tmp_path."""
    path = tmp_path / "svc.toml"
    path.write_text(
        "[service]\n"
        f'mavlink_url = "udpin:127.0.0.1:{free_port(socket.SOCK_DGRAM)}"\n'
        f'camera_url = "sitl://127.0.0.1:{free_port()}"\n'
        f'status_socket = "{tmp_path / "status.sock"}"\n'
        f'state_dir = "{tmp_path / "state"}"\n'
    )
    return path


@pytest.mark.timeout(180)
def test_run_honours_the_log_level(tmp_path: Path) -> None:
    """-v shows run's start-up config dump (DEBUG); the default is INFO; --log-level ERROR
    silences INFO; either position (before or after the command) works."""
    cfg = str(service_toml(tmp_path))
    verbose = companion("-v", "run", "--config", cfg, "--duration", "0.5")
    assert verbose.returncode == 0, verbose.stderr
    assert re.search(r"DEBUG companion: config camera\.width = 640", verbose.stderr)
    default = companion("run", "--config", cfg, "--duration", "0.5")
    assert default.returncode == 0, default.stderr
    assert " INFO companion: link " in default.stderr and " DEBUG " not in default.stderr
    quiet = companion("run", "--config", cfg, "--duration", "0.5", "--log-level", "error")
    assert quiet.returncode == 0, quiet.stderr
    assert " INFO " not in quiet.stderr and " DEBUG " not in quiet.stderr


def test_a_bad_log_level_is_a_usage_error_naming_it(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--log-level", "LOUD", "status"]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert "--log-level" in err and "'LOUD'" in err
    assert main(["status", "--log-level", "chatty"]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert "--log-level" in err and "'CHATTY'" in err


def test_a_bad_time_scale_is_a_usage_error_naming_it(capsys: pytest.CaptureFixture[str]) -> None:
    for cmd, bad in (("sitl", "0"), ("sitl", "1.5"), ("demo", "fast"), ("demo", "-0.5")):
        argv = ["sitl", "run"] if cmd == "sitl" else ["demo"]
        assert main([*argv, "--time-scale", bad]) == EXIT_USAGE
        err = capsys.readouterr().err
        assert "--time-scale" in err and bad in err


# ---------------------------------------------------------------- where the service is
@pytest.fixture
def fixed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """SYSTEM_STATUS_SOCKET moved into tmp_path/run/companion (absent until a test makes
    it); the per-user path in tmp_path/user; not under systemd."""
    path = tmp_path / "run" / "companion" / "status.sock"
    monkeypatch.setattr(status_mod, "SYSTEM_STATUS_SOCKET", path)
    (tmp_path / "user").mkdir()
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "user"))
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    return path


def test_lookup_order(fixed: Path, tmp_path: Path) -> None:
    user = tmp_path / "user" / "companion.sock"
    # nothing under /run/companion: the per-user path
    assert find_status_socket("") == user_status_path() == user
    # the folder alone (the unit stopped with the socket gone) is not enough
    fixed.parent.mkdir(parents=True)
    assert find_status_socket("") == user
    # the socket there: it, before the per-user one (even when that one exists too)
    fixed.touch()
    user.touch()
    assert find_status_socket("") == fixed
    # an explicit path (--socket, service.status_socket) always wins
    assert find_status_socket(str(tmp_path / "mine.sock")) == tmp_path / "mine.sock"


def test_lookup_when_the_service_folder_cannot_be_searched(
    fixed: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A user outside the service's group cannot even see whether the socket is there: the
    lookup picks it anyway, so that reading it says "permission denied", not "not running"."""
    real_lstat = Path.lstat

    def lstat(self: Path) -> os.stat_result:
        if self == fixed:
            raise PermissionError(13, "Permission denied", str(self))
        return real_lstat(self)

    monkeypatch.setattr(Path, "lstat", lstat)
    assert find_status_socket("") == fixed


def test_the_unit_the_default_config_and_the_lookup_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    """systemd/companion.service's RuntimeDirectory is where the service puts its socket (its
    $RUNTIME_DIRECTORY), which is the fixed path clients look at first; config/default.toml
    leaves service.status_socket to that default."""
    unit = (ROOT / "systemd/companion.service").read_text()
    runtime = re.findall(r"^RuntimeDirectory=(\S+)$", unit, re.M)
    assert runtime == ["companion"]
    monkeypatch.setenv("RUNTIME_DIRECTORY", f"/run/{runtime[0]}")
    assert status_path(load_config(ROOT / "config/default.toml").service.status_socket) == (
        status_mod.SYSTEM_STATUS_SOCKET
    )
    assert Path("/run/companion/status.sock") == status_mod.SYSTEM_STATUS_SOCKET
    assert str(status_mod.SYSTEM_STATUS_SOCKET) in (ROOT / "docs/service.md").read_text()


def test_status_finds_a_real_server_at_the_fixed_path_without_flags(
    fixed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A real StatusServer on the fixed path (what the unit runs) and another on the per-user
    path: `companion status` with no flag reads the fixed one; once that stops, the other."""
    fixed.parent.mkdir(parents=True)
    system_status = {**SAMPLE, "uptime_s": 111.0}
    user_status = {**SAMPLE, "uptime_s": 222.0}
    stop_user, t_user = serve_in_thread(tmp_path / "user" / "companion.sock", lambda: user_status)
    try:
        stop_sys, t_sys = serve_in_thread(fixed, lambda: system_status)
        try:
            assert main(["status", "--json"]) == 0
            assert json.loads(capsys.readouterr().out) == system_status
            assert stop_sys["server"].requests == 1
        finally:
            halt(stop_sys, t_sys)
        assert not fixed.exists()  # removed on exit
        assert main(["status", "--json"]) == 0
        assert json.loads(capsys.readouterr().out) == user_status
    finally:
        halt(stop_user, t_user)
    assert main(["status"]) == EXIT_UNREACHABLE
    assert "not running" in capsys.readouterr().out


def test_px4_check_sees_the_service_at_the_fixed_path(fixed: Path) -> None:
    """The service under systemd holds the link: check (same lookup) says so and refuses the
    link instead of calling the service absent; with no service there it goes ahead."""
    cfg = load_config(overrides={"service": {"mavlink_url": "udpin:127.0.0.1:14540"}})
    assert cfg.service.status_socket == ""
    fixed.parent.mkdir(parents=True)
    stop, t = serve_in_thread(fixed, lambda: SAMPLE)
    try:
        with pytest.raises(ConfigError, match=rf"running service holds .*{re.escape(str(fixed))}"):
            resolve(cfg, CheckOptions())
    finally:
        halt(stop, t)
    target = resolve(cfg, CheckOptions())
    assert target.socket == find_status_socket("") != fixed


def test_a_refused_dataset_is_exit_2_for_every_command(tmp_path: Path) -> None:
    """A dataset the reader refuses (here a meta.toml that is not TOML) is a bad input naming
    its file, exit 2, for every command that reads one (`sitl sheet` said exit 1), and one
    JSON object with --json."""
    (tmp_path / "meta.toml").write_text("x = [[[\n")
    for args in (["sitl", "sheet", str(tmp_path)], ["eval", str(tmp_path), "--no-progress"]):
        proc = companion(*args)
        assert proc.returncode == 2, (args, proc.stderr)
        assert "meta.toml" in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
