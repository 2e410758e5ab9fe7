"""Configuration: defaults, validation messages naming the key, CLI exit code 2."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from companion.cli import main
from companion.config import Config, describe, load_config
from companion.errors import ConfigError

REPO = Path(__file__).resolve().parents[3]


def test_defaults_are_valid_and_follow_design() -> None:
    cfg = load_config()
    assert isinstance(cfg, Config)
    T = cfg.camera.T_body_cam()
    # downward camera, image top towards the nose (docs/architecture.md, "Frames, units, names")
    assert np.allclose(T[:3, :3] @ [0, 0, 1], [0, 0, 1])
    assert np.allclose(T[:3, :3] @ [0, -1, 0], [1, 0, 0], atol=1e-12)
    rf = cfg.rangefinders
    assert len(rf) == 4
    xy = np.array([r.mount.xyz_m[:2] for r in rf])
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2)[np.triu_indices(4, 1)]
    assert d.min() >= 0.3 and d.max() <= 0.6  # "about 0.3-0.6 m apart"
    assert len(np.unique(np.round(d, 3))) == 6  # asymmetric: all six distances differ
    for r in rf:  # slightly tilted outwards
        beam = r.mount.T_body_sensor()[:3, 2]
        pos = np.array(r.mount.xyz_m[:2])
        assert beam[2] > np.cos(np.radians(6))
        assert float(np.dot(beam[:2], pos)) > 0


@pytest.mark.parametrize("name", ["sitl.toml", "default.toml"])
def test_shipped_config_files_load(name: str) -> None:
    cfg = load_config(REPO / "config" / name)
    assert cfg.camera.width > 0


NOT_CONFIGS = {"real_sequences.toml"}  # the real sequences' manifest


@pytest.mark.parametrize(
    "path",
    sorted(p for p in (REPO / "config").rglob("*.toml") if p.name not in NOT_CONFIGS),
    ids=lambda p: str(p.relative_to(REPO / "config")),
)
def test_every_config_file_in_the_repository_loads(path: Path) -> None:
    """The effects' files, the look-alikes of the real sequences and the presets: a key
    renamed in the code and not in a shipped file fails here, not in a user's eval."""
    assert load_config(path).camera.width > 0


def test_a_config_file_extends_another(tmp_path: Path) -> None:
    (tmp_path / "base.toml").write_text(
        "[camera]\nfx = 300.0\nfy = 300.0\n[vo]\nmax_features = 150\n"
    )
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "mine.toml").write_text('extends = "../base.toml"\n[camera]\nfy = 310.0\n')
    cfg = load_config(tmp_path / "sub" / "mine.toml")
    assert (cfg.camera.fx, cfg.camera.fy, cfg.vo.max_features) == (300.0, 310.0, 150)
    realistic = load_config(REPO / "config" / "like_real" / "downward_checkerboard.toml")
    assert (
        realistic.sitl.render.readout_ms
        == load_config(REPO / "config" / "realistic.toml").sitl.render.readout_ms
        > 0
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('extends = "a.toml"\n', "a loop"),
        ("extends = 3\n", "extends: the path of a config file"),
        ('extends = "missing.toml"\n', "missing.toml"),
    ],
)
def test_a_bad_extends_names_the_file(tmp_path: Path, text: str, message: str) -> None:
    (tmp_path / "a.toml").write_text(text)
    with pytest.raises(ConfigError, match=message) as e:
        load_config(tmp_path / "a.toml")
    assert "a.toml" in str(e.value)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"camera": {"fx": -5}}, "camera.fx: must be > 0"),
        ({"camera": {"fxx": 1}}, "camera.fxx: unknown key"),
        ({"camera": {"width": 640.5}}, "camera.width: expected an integer"),
        ({"camera": {"mount": {"xyz_m": [1, 2]}}}, "camera.mount.xyz_m: expected 3 values"),
        ({"sitl": {"terrain": "moon"}}, "sitl.terrain: must be one of"),
        ({"sitl": {"render": {"noise_sigma_dn": "x"}}}, "sitl.render.noise_sigma_dn"),
        ({"sitl": {"takeoff_landing": 1}}, "sitl.takeoff_landing: expected true or false"),
        (
            {"service": {"frame_wait_ms": 150.0}},
            "service.frame_wait_ms: must be < stale_frame_ms",
        ),
        (
            {"rangefinders": [{"sensor_id": 1, "min_m": 5.0, "max_m": 2.0}]},
            "rangefinders[0].max_m: must be > min_m",
        ),
        ({"rangefinders": [{"sensor_id": 1}, {"sensor_id": 1}]}, "sensor_id values must be unique"),
        ({"rangefinders": [{"dropout_prob": 1.5}]}, "rangefinders[0].dropout_prob: must be <= 1"),
        ({"camera": {"rate_hz": float("nan")}}, "camera.rate_hz: must be finite"),
    ],
)
def test_bad_values_name_their_key(overrides: dict, message: str) -> None:
    with pytest.raises(ConfigError) as e:
        load_config(overrides=overrides)
    assert message in str(e.value)


def test_a_retired_key_loads_with_a_warning_and_a_typo_still_fails(caplog) -> None:
    """A recording's config.toml carries every option it ran with; one removed since (here
    dpose.blend, 743f76c on 2026-11-25) must not make the recording unreadable."""
    with caplog.at_level("WARNING"):
        cfg = load_config(overrides={"dpose": {"blend": 0.3, "reset_m": 0.04}})
    assert cfg.dpose.reset_m == 0.04
    assert "dpose.blend: no longer used" in caplog.text
    with pytest.raises(ConfigError, match=r"dpose\.blendd: unknown key"):
        load_config(overrides={"dpose": {"blendd": 0.3}})


def test_describe_walks_every_field() -> None:
    lines = describe(load_config())
    assert any(line.startswith("camera.fx = 460.0  # focal length") for line in lines)
    assert any(line.startswith("rangefinders[3].sigma_a_m") for line in lines)
    assert any(line.startswith("sitl.render.laser_marks") for line in lines)


def test_cli_exits_2_on_bad_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[camera]\nfx = -1.0\n")
    code = main(["sitl", "record", "--config", str(bad), "--out", str(tmp_path / "x")])
    assert code == 2
    assert "camera.fx: must be > 0" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()  # nothing half-started
    broken = tmp_path / "broken.toml"
    broken.write_text("[camera\n")
    assert main(["config", "--config", str(broken)]) == 2
    assert main(["config", "--config", str(tmp_path / "missing.toml")]) == 2
    assert main(["sitl", "record", "--seconds", "-3", "--out", str(tmp_path / "y")]) == 2
    assert main(["sitl", "record", "--terrain", "moon", "--out", str(tmp_path / "y")]) == 2


def test_cli_config_prints_options(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["config"]) == 0
    assert "sitl.terrain = 'hills'" in capsys.readouterr().out


def _config_error(path: Path, capsys: pytest.CaptureFixture[str]) -> str:
    """`companion config --config path`: exit 2, one clear line, no traceback."""
    assert main(["config", "--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.startswith("companion: config error: "), err
    return err


def test_unreadable_config_files_exit_2_naming_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "conf.d"
    folder.mkdir()
    assert "is a directory" in _config_error(folder, capsys)
    not_a_dir = tmp_path / "plain"
    not_a_dir.write_text("")
    assert "cannot read" in _config_error(not_a_dir / "x.toml", capsys)
    latin1 = tmp_path / "latin1.toml"
    latin1.write_bytes(b'[sitl]\nterrain = "h\xe9ll"\n')
    assert "not UTF-8" in _config_error(latin1, capsys)
    huge = tmp_path / "huge.toml"
    huge.write_text("[camera]\nwidth = " + "9" * 400 + "\n")
    assert "camera.width: integer out of range" in _config_error(huge, capsys)
    huger = tmp_path / "huger.toml"
    huger.write_text("[camera]\nfx = " + "9" * 5000 + "\n")  # beyond Python's int parsing
    assert "not valid TOML" in _config_error(huger, capsys)


def test_config_validates_what_run_needs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`companion config` fails on what `companion run` would fail on, naming the key."""
    sock = tmp_path / "status.sock"
    cases = {
        'signing = { key_file = "/nonexistent/key" }': "service.signing.key_file",
        'mqtt = { enabled = true, tls = true, ca_file = "/nonexistent/ca.pem" }': (
            "service.mqtt.ca_file"
        ),
        'camera_url = "bogus://camera"': "service.camera_url: unknown URL scheme",
        'camera_url = "no-such-file.mp4"': "service.camera_url",
        'camera_url = "sitl://nohost"': "service.camera_url",
        'mavlink_url = "udp://x"': "service.mavlink_url",
        f'status_socket = "{tmp_path / "plain"}"': "service.status_socket",
    }
    (tmp_path / "plain").write_text("not a socket\n")
    for line, key in cases.items():
        path = tmp_path / "c.toml"
        extra = "" if "status_socket" in line else f'status_socket = "{sock}"\n'
        path.write_text(f"[service]\n{extra}{line}\n")
        assert key in _config_error(path, capsys), line
    assert (tmp_path / "plain").read_text() == "not a socket\n"


# ---------------------------------------------------- hostile configs (Reliability round 3)
@pytest.mark.parametrize(
    ("line", "key"),
    [
        ('mavlink_url = "udpin:127.0.0.1:99999"', "service.mavlink_url: port must be 1..65535"),
        ('mavlink_url = "tcp:127.0.0.1:0"', "service.mavlink_url: port must be 1..65535"),
        ('mavlink_url = "serial:/dev/ttyS0:99999999999"', "service.mavlink_url: baud rate"),
        ("mqtt = { keepalive_s = 100000 }", "service.mqtt.keepalive_s: must be <= 65535"),
        ('mqtt = { topic_prefix = "fleet/#" }', "service.mqtt.topic_prefix"),
        ('mqtt = { topic_prefix = "a+b" }', "service.mqtt.topic_prefix"),
        ('mqtt = { topic_prefix = "" }', "service.mqtt.topic_prefix"),
        ('state_dir = "/tmp/a\\u0000b"', "service.state_dir: a NUL byte"),
        ('camera_url = "folder:/tmp\\u0000x"', "service.camera_url: a NUL byte"),
    ],
)
def test_config_refuses_what_run_would_refuse(
    line: str, key: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Values that passed `companion config` and failed at `run` (OverflowError on the port,
    a reader thread dying on the baud rate, a broker never reached or dropping the
    connection, a NUL byte in a path): exit 2 naming the key."""
    path = tmp_path / "c.toml"
    path.write_text(f'[service]\nstatus_socket = "{tmp_path / "s.sock"}"\n{line}\n')
    assert key in _config_error(path, capsys)


def test_a_rangefinder_baud_rate_is_bounded(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "c.toml"
    path.write_text('[[rangefinders]]\nserial = "/dev/ttyUSB0:99999999999"\n')
    assert "rangefinders[0].serial: baud rate" in _config_error(path, capsys)
    path.write_text('[[rangefinders]]\nserial = "/dev/ttyUSB0:115200"\n')
    assert load_config(path).rangefinders[0].serial == "/dev/ttyUSB0:115200"


@pytest.mark.parametrize(
    "text",
    [
        "x = " + "[" * 30_000 + "]" * 30_000,
        "x = " + "{a = " * 30_000 + "1" + "}" * 30_000,
        "[" + ".".join(["a"] * 30_000) + "]\nx = 1",
        ".".join(["a"] * 30_000) + " = 1",
    ],
    ids=["arrays", "inline-tables", "table-header", "dotted-key"],
)
def test_toml_nested_30000_deep_is_refused_before_parsing(
    text: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A RecursionError traceback (or seconds of parsing) before; now exit 2 at once."""
    path = tmp_path / "deep.toml"
    path.write_text(text + "\n")
    start = time.monotonic()
    assert "nested deeper than 16" in _config_error(path, capsys)
    assert time.monotonic() - start < 1.0


def test_toml_nesting_ignores_strings_and_comments() -> None:
    """Brackets and dots inside strings and comments are not nesting: a real config of
    depth 3 reads as such, whatever its strings hold."""
    from companion.toml_files import toml_nesting

    text = (
        'a = "[[[[.]]]]"\nb = \'{{{{\'\n# [[[[[[[[[[\nc = """\n[[[[\n"""\n[t.u]\nv = [[1], [2]]\n'
    )
    assert toml_nesting(text) <= 3


def test_a_fifo_config_or_state_file_is_refused_at_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A config file, or the state_dir's reset_counter, that is a FIFO: `companion config`
    hung on it; now exit 2 naming the file or the key, without waiting for a writer."""
    fifo = tmp_path / "config.toml"
    os.mkfifo(fifo)
    start = time.monotonic()
    assert "is a FIFO, not a regular file" in _config_error(fifo, capsys)
    state = tmp_path / "state"
    state.mkdir()
    os.mkfifo(state / "reset_counter")
    path = tmp_path / "c.toml"
    path.write_text(f'[service]\nstatus_socket = "{tmp_path / "s.sock"}"\nstate_dir = "{state}"\n')
    assert "service.state_dir:" in _config_error(path, capsys)
    assert time.monotonic() - start < 5.0
    run = subprocess.run(
        [sys.executable, "-m", "companion.cli", "run", "--config", str(path), "--duration", "1"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 2 and "service.state_dir:" in run.stderr, run.stderr


@pytest.mark.parametrize(
    ("table", "key"),
    [
        ("handover = 'gps'", "gps.handover"),
        ("max_eph_m = 0", "gps.max_eph_m"),
        ("min_window_s = 30", "gps.min_window_s"),
        ("slew_rate_m_s = -0.1", "gps.slew_rate_m_s"),
        ("align = 'yes'", "gps.align"),
        ("handover = 'px4'", "gps.handover"),  # without align = true
    ],
)
def test_a_bad_gps_option_names_its_key_and_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], table: str, key: str
) -> None:
    assert load_config().gps.align is False and load_config().gps.handover == "none"
    bad = tmp_path / "gps.toml"
    bad.write_text(f"[gps]\n{table}\n")
    assert main(["config", "--config", str(bad)]) == 2
    assert key in capsys.readouterr().err
