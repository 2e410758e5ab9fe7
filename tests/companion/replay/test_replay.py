"""``companion replay`` (companion/replay.py, companion/cli/replay.py) on a flight recorded as
the service records it (peers.recordings): with its own options the replay is what flew, bit
for bit; an override laid over its options key by key changes the poses and ``companion
compare`` says so; a broken recording is reported and the others still measured; a bad
override is exit 2 naming its key."""

from __future__ import annotations

import dataclasses
import json
import shutil
import tomllib
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import tomli_w
from peers.recordings import service_recording, simulated_flight

from companion.cli import main
from companion.config import to_dict
from companion.drivers.dataset import Dataset, PublishedPose, open_dataset
from companion.errors import ConfigError
from companion.geometry import so3
from companion.replay import (
    against_published,
    finite_or_none,
    read_override,
    recording_id,
    replay_config,
    replay_recording,
    spread_ms,
)
from companion.types import PoseEstimate


@pytest.fixture(scope="module")
def rec(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 4 s figure eight over the town (320x240, seeded) as the recorder writes it, with its
    ground truth."""
    root = tmp_path_factory.mktemp("replay")
    return service_recording(simulated_flight(root / "flight", 4.0), root / "rec")


@pytest.fixture(scope="module")
def own(rec: Path) -> dict[str, Any]:
    """The recording replayed with its own options (OpenCV on one thread, then as before)."""
    threads = cv2.getNumThreads()
    entry = replay_recording(rec)
    assert cv2.getNumThreads() == threads
    return entry


def toml_file(path: Path, table: dict[str, Any]) -> Path:
    path.write_text(tomli_w.dumps(table))
    return path


def test_with_its_own_options_the_replay_is_what_flew_bit_for_bit(
    rec: Path, own: dict[str, Any]
) -> None:
    m = own["metrics"]
    ds = open_dataset(rec)
    assert own["software"] == "companion test" and own["id"] == recording_id(ds)
    assert m["frames"] == m["frames_replayed"] == len(ds) == 120
    assert m["published_poses"] == m["published_matched"] == m["poses"] == len(ds.published)
    assert m["published_missing"] == 0 and m["replayed_not_published"] == 0
    assert m["identical"] is True
    for key in ("position_diff_max_m", "yaw_diff_max_deg", "angle_diff_max_deg"):
        assert m[key] == 0.0, key
    assert m["velocity_diff_max_m_s"] == 0.0
    # the VO starts after its first frames and then tracks the seeded flight through
    assert 0.6 < m["tracked_fraction"] <= 1.0 and m["vo_resets"] == 0
    assert m["reset_counter_steps"] == 0 and m["pipeline_errors"] == 0
    cpu = [m[f"cpu_ms_{k}"] for k in ("median", "p95", "p99", "max")]
    assert 0.0 < cpu[0] <= cpu[1] <= cpu[2] <= cpu[3]
    assert cpu[0] <= m["cpu_ms_mean"] * 3  # a mean, not a sum
    # the ground truth: the published track of a figure eight of metres, within centimetres
    assert 5.0 < m["path_m"] < 20.0
    assert 0.0 < m["ate_m"] < 0.15
    assert m["ate_pct_path"] == pytest.approx(100.0 * m["ate_m"] / m["path_m"], rel=1e-12)
    assert 0.0 < m["ate_to_best_constant"] < 0.1  # far better than standing still


def test_override_keys_lay_over_the_recordings_own_options(rec: Path, tmp_path: Path) -> None:
    """Only the keys the override names change; the recording's other keys stay its own,
    not the built-in defaults (a recording that flew a non-default klt_window_px keeps it),
    and the calibration is the recording's."""
    flew = tmp_path / "flew"
    shutil.copytree(rec, flew)
    algo = tomllib.loads((flew / "config.toml").read_text())
    algo["vo"]["klt_window_px"] = algo["vo"]["klt_window_px"] + 4
    (flew / "config.toml").write_text(tomli_w.dumps(algo))
    ds = open_dataset(flew)
    assert ds.config is not None
    over = read_override(toml_file(tmp_path / "o.toml", {"vo": {"max_features": 90}}))
    cfg = replay_config(ds.config, over)
    assert cfg.vo.max_features == 90 and ds.config.vo.max_features != 90
    assert cfg.vo.klt_window_px == algo["vo"]["klt_window_px"]
    assert to_dict(dataclasses.replace(cfg.vo, max_features=ds.config.vo.max_features)) == to_dict(
        ds.config.vo
    )
    for same in ("scale", "attitude", "dpose", "camera", "rangefinders"):
        assert getattr(cfg, same) == getattr(ds.config, same), same
    assert replay_config(ds.config, None) is ds.config


@pytest.mark.parametrize(
    ("table", "named"),
    [
        ({"vo": {"max_featurez": 100}}, "vo.max_featurez: unknown key"),
        ({"vo": {"max_features": 5}}, "vo.max_features: must be >= 20"),
        ({"scale": {"method": "guess"}}, "scale.method"),
        ({"camera": {"fx": 300.0}}, "camera: a replay keeps each recording's calibration"),
        ({"rangefinders": [{"sensor_id": 1}]}, "rangefinders: a replay keeps"),
        ({"service": {"output": "odometry"}}, "service: a replay keeps"),
    ],
)
def test_a_bad_override_is_refused_naming_its_key(
    tmp_path: Path, table: dict[str, Any], named: str
) -> None:
    with pytest.raises(ConfigError, match=named):
        read_override(toml_file(tmp_path / "bad.toml", table))


def test_an_override_that_does_not_fit_a_recording_names_the_key(rec: Path, tmp_path: Path) -> None:
    over = read_override(toml_file(tmp_path / "o.toml", {"attitude": {"sensor_ids": [7, 8, 9]}}))
    with pytest.raises(
        ConfigError, match=r"attitude.sensor_ids: no rangefinder with id \[7, 8, 9\]"
    ):
        replay_config(open_dataset(rec).config, over)


def _pose(time_us: int, p: list[float], yaw_deg: float, v: list[float]) -> PoseEstimate:
    q = so3.matrix_to_quat(so3.rpy_to_matrix(0.02, -0.01, np.radians(yaw_deg)))
    return PoseEstimate(time_us, np.array(p), q, np.array(v), np.eye(6), 0, 80)


def _sent(pose: PoseEstimate) -> PublishedPose:
    return PublishedPose(
        pose.time_us,
        pose.position_ned_m.copy(),
        pose.quat_wxyz_ned_frd.copy(),
        pose.velocity_ned_m_s.copy(),
        pose.reset_counter + 7,  # the wire's counter: not compared
        pose.quality_pct,
    )


def test_the_difference_from_what_flew_in_metres_and_degrees() -> None:
    """Four sent poses: one replayed the same (NaN velocity on both sides agrees), one
    moved 0.3 m, turned 10 deg in yaw and 0.05 m/s faster, one not replayed, one whose
    velocity the replay does not know yet; and one replayed pose the service did not send."""
    nan3 = [float("nan")] * 3
    mine = [
        _pose(1_000, [1.0, 2.0, -3.0], 30.0, nan3),
        _pose(2_000, [1.3, 2.0, -3.0], 40.0, [0.1, 0.05, 0.0]),
        _pose(4_000, [0.0, 0.0, 0.0], 0.0, [0.0, 0.0, 0.0]),
        _pose(5_000, [0.0, 0.0, 0.0], 0.0, nan3),
    ]
    sent = [_sent(mine[0]), _sent(_pose(2_000, [1.0, 2.0, -3.0], 30.0, [0.1, 0.0, 0.0]))]
    sent.append(_sent(_pose(3_000, [0.0, 0.0, 0.0], 0.0, nan3)))
    sent.append(_sent(_pose(5_000, [0.0, 0.0, 0.0], 0.0, [9.0, 9.0, 9.0])))
    d = against_published(sent, mine)
    assert d["published_poses"] == 4 and d["published_matched"] == 3
    assert d["published_missing"] == 1 and d["replayed_not_published"] == 1
    assert d["position_diff_max_m"] == pytest.approx(0.3, abs=1e-12)
    assert d["yaw_diff_max_deg"] == pytest.approx(10.0, abs=1e-9)
    assert 9.9 < d["angle_diff_max_deg"] < 10.1  # about a tilted body's z: close to 10
    assert d["velocity_diff_max_m_s"] == pytest.approx(0.05, abs=1e-12)
    assert d["velocity_known_one_side"] == 1 and d["identical"] is False
    same = against_published(sent[:1], mine[:1])
    assert same["identical"] is True and same["angle_diff_max_deg"] == 0.0
    # a yaw across +-180 deg is 2 deg, not 358
    across = against_published(
        [_sent(_pose(1, [0, 0, 0], 179.0, nan3))], [_pose(1, [0, 0, 0], -179.0, nan3)]
    )
    assert across["yaw_diff_max_deg"] == pytest.approx(2.0, abs=1e-9)


def test_json_gets_no_nan() -> None:
    doc = finite_or_none({"a": [1.0, float("nan")], "b": {"c": float("inf"), "d": 2, "e": None}})
    assert doc == {"a": [1.0, None], "b": {"c": None, "d": 2, "e": None}}


def test_cpu_spread_of_known_values() -> None:
    s = spread_ms("cpu_ms", [float(v) for v in range(1, 101)])
    assert s["cpu_ms_median"] == 50.5 and s["cpu_ms_max"] == 100.0 and s["cpu_ms_mean"] == 50.5
    assert s["cpu_ms_p95"] == pytest.approx(95.05) and s["cpu_ms_p99"] == pytest.approx(99.01)
    assert all(v is None for v in spread_ms("x", []).values())


def test_the_recording_id_follows_the_flight_not_the_folder(rec: Path, tmp_path: Path) -> None:
    moved = tmp_path / "elsewhere"
    shutil.copytree(rec, moved)
    assert recording_id(open_dataset(moved)) == recording_id(open_dataset(rec))


def _broken(rec: Path, out: Path) -> Path:
    """``rec`` whose 80th image is cut short (a disk that lost its tail)."""
    shutil.copytree(rec, out)
    image = out / "images" / "000080.png"
    image.write_bytes(image.read_bytes()[:200])
    return out


def test_replay_and_compare_from_the_command_line(
    rec: Path, own: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A broken recording and a missing one get their errors (exit 1) while the good one is
    measured; an override of vo.max_features changes the poses, and compare says what
    changed; a file compared with itself is the same everywhere."""
    broken = _broken(rec, tmp_path / "broken")
    a_json, b_json = tmp_path / "a.json", tmp_path / "b.json"
    code = main(
        [
            "replay",
            str(broken),
            str(rec),
            str(tmp_path / "none"),
            "--json",
            str(a_json),
            "--no-progress",
        ]
    )
    assert code == 1
    a = json.loads(a_json.read_text())
    assert a["format"] == "companion-replay" and a["failed"] == 2 and a["override"] is None
    assert a["software"]["version"] and a["created"].startswith("20")
    bad, good, missing = a["recordings"]
    assert bad["kind"] == "dataset error" and "frame 80" in bad["error"], bad
    assert missing["kind"] == "dataset error" and "none" in missing["error"]
    assert good["metrics"]["identical"] is True
    # the KLT floor of `bench vo` beside it: the same poses, its figures there
    assert good["metrics"]["klt_floor_ms"] > 0.0 and good["metrics"]["frame_to_floor"] > 0.0
    assert good["metrics"]["poses"] == own["metrics"]["poses"]
    out = capsys.readouterr().out
    assert "broken: FAILED" in out and "rec: 120 frames" in out and "identical to what flew" in out

    over = toml_file(tmp_path / "over.toml", {"vo": {"max_features": 90}})
    assert (
        main(["replay", str(rec), "--config", str(over), "--json", str(b_json), "--no-progress"])
        == 0
    )
    b = json.loads(b_json.read_text())
    assert b["override"]["sha256"] == __import__("hashlib").sha256(over.read_bytes()).hexdigest()
    mb = b["recordings"][0]["metrics"]
    assert mb["identical"] is False and mb["position_diff_max_m"] > 1e-3
    assert b["recordings"][0]["config"].endswith("over.toml")
    capsys.readouterr()

    assert main(["compare", str(a_json), str(b_json), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    by_status = {r["name"]: r for r in result["recordings"]}
    assert (
        by_status["broken"]["status"] == "only in A" and by_status["none"]["status"] == "only in A"
    )
    rows = {r["metric"]: r for r in by_status["rec"]["rows"]}
    assert rows["identical"]["verdict"] == "changed"
    assert rows["position_diff_max_m"]["verdict"] == "changed"
    assert rows["position_diff_max_m"]["diff"] == pytest.approx(mb["position_diff_max_m"])
    assert rows["frames"]["verdict"] == "same"

    assert main(["compare", str(a_json), str(a_json)]) == 0
    text = capsys.readouterr().out
    assert "rec (id:" in text and "metrics the same" in text
    assert not any(w in text for w in (" better", " worse", " changed"))
    assert main(["compare", str(a_json), str(a_json), "--json", "--fail-if-worse"]) == 0
    self_compare = json.loads(capsys.readouterr().out)
    assert set(self_compare["counts"]) == {"same"} and self_compare["worse"] == 0


def test_a_bad_override_key_is_exit_2_before_any_recording_is_read(
    rec: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = toml_file(tmp_path / "bad.toml", {"vo": {"max_featurez": 90}})
    out = tmp_path / "out.json"
    assert main(["replay", str(rec), "--config", str(bad), "--json", str(out)]) == 2
    err = capsys.readouterr().err
    assert "config error" in err and "vo.max_featurez: unknown key" in err, err
    assert not out.exists()


def test_companion_help_lists_replay_and_compare(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    assert "replay" in text and "re-run flight recordings" in text and "compare" in text


def test_a_recording_that_crashes_mid_replay_is_reported_and_the_others_measured(
    rec: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Reading frame 40 of one recording raises something no reader should (a bug, not a bad
    file): that recording's entry says so, the next one is still replayed, exit 1."""
    crashes = tmp_path / "crashes"
    shutil.copytree(rec, crashes)
    real = Dataset.load_frame

    def load_frame(self: Dataset, index: int) -> Any:
        if self.path.name == "crashes" and index == 40:
            raise RuntimeError("a bug in the reader")
        return real(self, index)

    monkeypatch.setattr(Dataset, "load_frame", load_frame)
    out = tmp_path / "out.json"
    assert main(["replay", str(crashes), str(rec), "--json", str(out), "--no-progress"]) == 1
    first, second = json.loads(out.read_text())["recordings"]
    assert first["kind"] == "crash (RuntimeError)" and first["error"] == "a bug in the reader"
    assert second["metrics"]["identical"] is True and second["metrics"]["frames"] == 120


def test_an_mcap_recording_replays_as_a_folder_does(tmp_path: Path) -> None:
    """A recording in the default format (one MCAP file, grey images) replays bit for bit to
    what it published, and its folder twin (`companion dataset convert`) gives the same
    metrics: the replay reads recordings through open_dataset, whatever their format."""
    from peers.clip_recordings import record_clip

    recorder, poses = record_clip(tmp_path / "clip", frames=40)
    mcap = tmp_path / "clip.mcap"
    assert recorder.path == mcap and len(poses) > 10
    from_mcap = replay_recording(mcap)["metrics"]
    assert from_mcap["identical"] is True and from_mcap["published_matched"] == len(poses)
    assert main(["dataset", "convert", str(mcap), str(tmp_path / "folder")]) == 0
    from_folder = replay_recording(tmp_path / "folder")["metrics"]
    for key in ("frames", "poses", "identical", "vo_resets", "position_diff_max_m"):
        assert from_folder[key] == from_mcap[key], key
