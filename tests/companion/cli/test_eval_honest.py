"""`companion eval DIR` on datasets with what real cameras bring: --config honoured (or refused
by key), every frame not given to the VO counted, the published track split at its resets,
continuing across them, and measured against a constant position."""

from __future__ import annotations

import csv
import json
import shutil
import tomllib
from pathlib import Path

import pytest
import tomli_w
from peers import small_camera

from companion.cli import main
from companion.config import load_config
from companion.sitl.world.dataset import record

DUPLICATED = (20, 21, 22, 100)  # frames written twice in a row (the copy 1/60 s later)
GAP = (150, 200)  # frames left out: 1.67 s without frames, beyond vo.max_gap_ms: a new map


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 12 s figure eight over the town, 320x240, recorded as a dataset (seeded)."""
    overrides = small_camera()
    overrides["sitl"] = {"terrain": "urban", "trajectory": "figure8", "seconds": 12.0, "seed": 3}
    out = tmp_path_factory.mktemp("honest") / "urban"
    record(load_config(overrides=overrides), out, progress=False)
    return out


def real_like(
    sim: Path,
    out: Path,
    duplicated: tuple[int, ...] = (),
    gap: tuple[int, int] | None = None,
    algorithm: dict | None = None,
    frames: int | None = None,
) -> Path:
    """``sim`` as a converted real clip (no world, no true distances) whose camera repeated
    the frames ``duplicated`` (the same image file listed twice, the copy with a new stamp
    half a frame later) and delivered nothing for the frames of ``gap``; ``algorithm``: a
    config.toml of the recording's own algorithm options; ``frames``: the first frames only."""
    shutil.copytree(sim, out)
    meta = tomllib.loads((out / "meta.toml").read_text())
    del meta["sitl"]
    (out / "meta.toml").write_text(tomli_w.dumps({**meta, "source": "converted"}))
    with (out / "frames.csv").open() as fh:
        rows = list(csv.DictReader(fh))[:frames]
    kept: list[dict[str, str]] = []
    for i, row in enumerate(rows):
        if gap is not None and gap[0] <= i < gap[1]:
            continue
        kept.append(row)
        if i in duplicated:
            kept.append({**row, "time_us": str(int(row["time_us"]) + 16_666)})
    with (out / "frames.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, ["time_us", "seq", "filename"])
        w.writeheader()
        w.writerows(kept)
    if algorithm is not None:
        (out / "config.toml").write_text(tomli_w.dumps(algorithm))
    return out


def evaluate(tmp_path: Path, dataset: Path, *flags: str) -> tuple[int, Path]:
    out = tmp_path / "out"
    code = main(["eval", str(dataset), "--out", str(out), "--no-progress", *flags])
    return code, out


def toml_file(path: Path, table: dict) -> Path:
    path.write_text(tomli_w.dumps(table))
    return path


@pytest.mark.parametrize(
    ("table", "key"),
    [
        ({"vo": {"max_featurez": 100}}, "vo.max_featurez: unknown key"),
        ({"vo": {"max_features": 5}}, "vo.max_features"),  # below its bound (>= 20)
        ({"scale": {"method": "guess"}}, "scale.method"),
        ({"attitude": {"sensor_ids": [7, 8, 9]}}, "attitude.sensor_ids"),  # not the dataset's
    ],
)
def test_a_bad_config_for_a_dataset_is_exit_2_naming_the_key(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], table: dict, key: str
) -> None:
    data = real_like(recorded, tmp_path / "clip")
    bad = toml_file(tmp_path / "bad.toml", table)
    code, out = evaluate(tmp_path, data, "--config", str(bad))
    err = capsys.readouterr().err
    assert code == 2 and "config error" in err and key in err, err
    assert not (out / "vo.tum").exists()  # refused before the run


def test_the_config_file_and_else_the_recordings_own_choose_the_vo_options(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The tracked features per frame follow vo.max_features: the built-in 200 (a median
    above 100 on this flight), 100 from --config, 90 from the recording's config.toml, and
    --config over the recording's. A [camera] in the file that is not the dataset's is named
    in a warning and not used (the run tracks as with the dataset's own)."""

    def median_features(code: int, out: Path) -> float:
        assert code == 0
        return float(json.loads((out / "eval.json").read_text())["frames"]["features_median"])

    clip = real_like(recorded, tmp_path / "clip", frames=150)
    default = median_features(*evaluate(tmp_path / "a", clip))
    assert default > 100
    cfg = toml_file(tmp_path / "few.toml", {"vo": {"max_features": 100}, "camera": {"fx": 300.0}})
    code, out = evaluate(tmp_path / "b", clip, "--config", str(cfg))
    assert median_features(code, out) <= 100
    err = capsys.readouterr().err
    assert "camera.fx differs from the dataset's own calibration" in err
    assert f"Algorithm options from {cfg}." in (out / "report.md").read_text()
    assert json.loads((out / "metrics.json").read_text())["tracking_ratio"] > 0.9
    own = real_like(recorded, tmp_path / "own", (), None, {"vo": {"max_features": 90}}, 150)
    code, out = evaluate(tmp_path / "c", own)
    assert median_features(code, out) <= 90
    assert "the recording's config.toml" in (out / "report.md").read_text()
    code, out = evaluate(tmp_path / "d", own, "--config", str(cfg))
    assert 90 < median_features(code, out) <= 100


def test_duplicated_frames_are_counted_exactly_and_said(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    clip = real_like(recorded, tmp_path / "dup", duplicated=DUPLICATED)
    frames = len(list(csv.DictReader((clip / "frames.csv").open())))
    n = len(DUPLICATED)
    line = f"eval: {n} of {frames} frames not given to the VO: {n} frozen (duplicated)"
    code, out = evaluate(tmp_path / "vo", clip)
    assert code == 0 and line in capsys.readouterr().err.splitlines()
    doc = json.loads((out / "eval.json").read_text())["frames"]
    assert doc["not_given_to_vo"] == {"frozen": n} and doc["given_to_vo"] == frames - n
    assert line in (out / "report.md").read_text()
    code, out = evaluate(tmp_path / "all", clip, "--methods", "all")
    assert code == 0 and line in capsys.readouterr().err.splitlines()
    scale = json.loads((out / "scale_metrics.json").read_text())
    assert scale["frames"]["not_given_to_vo"] == {"frozen": n}
    assert line in (out / "report.md").read_text()


def test_after_a_reset_the_published_track_continues_and_each_segment_is_scored(
    recorded: Path, tmp_path: Path
) -> None:
    """A camera that delivers nothing for 1.67 s: the VO starts a new map. The first pose of
    the new map continues from the last published one (the pipeline anchors it there: a
    step of millimetres, where the vehicle flew metres in the gap), each map alone is
    centimetres from the truth, and the whole flight shows what the gap cost."""
    clip = real_like(recorded, tmp_path / "gap", gap=GAP)
    code, out = evaluate(tmp_path, clip)
    assert code == 0
    doc = json.loads((out / "eval.json").read_text())
    assert doc["frames"]["gaps"] == 1 and doc["frames"]["not_given_to_vo"] == {}
    pub = doc["tracks"]["published"]
    assert [s["segment"] for s in pub["segments"]] == [0, 1]
    assert all(s["frames"] >= 90 and s["ate_se3_m"] < 0.1 for s in pub["segments"])
    (step,) = pub["reset_steps"]
    assert step["step_m"] < 0.05 and pub["largest_reset_step_m"] == step["step_m"]
    assert step["true_step_m"] > 2.0  # flown in the gap, unseen
    assert pub["ate_se3_m"] > 5 * max(s["ate_se3_m"] for s in pub["segments"])
    assert 0 < pub["ratio_to_mean"] < 1 and pub["constant_mean_m"] > 1.0
    report = (out / "report.md").read_text()
    assert "| published |" in report and "reset at" in report


def test_the_methods_are_scored_against_a_constant_position(recorded: Path, tmp_path: Path) -> None:
    clip = real_like(recorded, tmp_path / "clip")
    code, out = evaluate(tmp_path, clip, "--methods", "all")
    assert code == 0
    doc = json.loads((out / "scale_metrics.json").read_text())
    rows = {r["method"]: r for r in doc["methods"]}
    assert set(doc["tracks"]) == set(rows)
    for name, track in doc["tracks"].items():
        assert track["frames"] == rows[name]["frames"]
        assert track["ate_se3_m"] == pytest.approx(rows[name]["ate_se3_m"], rel=1e-9)
        ratio = track["ate_se3_m"] / track["constant_mean_m"]
        assert track["ratio_to_mean"] == pytest.approx(ratio, rel=1e-9)
        assert track["constant_mean_m"] > 1.0
        assert track["constant_mean_m"] <= track["constant_start_m"]
        if abs(rows[name]["sim3_scale"] - 1.0) < 0.02:  # a right scale: far below a constant
            assert track["ratio_to_mean"] < 0.05, name
    assert doc["tracks"]["M-MSCwK"]["ratio_to_mean"] < 0.05
    assert "best constant" in (out / "report.md").read_text()


def test_a_dataset_without_a_config_of_its_own_takes_the_files_options_and_no_sensors(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A dataset that brings no config (EuRoC): the algorithm options are the file's, the
    sensors none (it declares none), and the file's own sensors are named in a warning."""
    import dataclasses

    from companion.cli.evaluate_dataset import config_source, dataset_config
    from companion.drivers.dataset import open_dataset

    ds = dataclasses.replace(open_dataset(real_like(recorded, tmp_path / "clip")), config=None)
    table = {"vo": {"max_features": 77}, "rangefinders": [{"sensor_id": 4}]}
    cfg = dataset_config(ds, toml_file(tmp_path / "vehicle.toml", table))
    assert cfg.vo.max_features == 77 and cfg.rangefinders == () and cfg.attitude.sensor_ids == ()
    err = capsys.readouterr().err
    assert "rangefinders (ids [4]) differ from the sensors the dataset declares (ids [])" in err
    assert dataset_config(ds, None).vo.max_features == 200  # the built-in options
    assert config_source(ds, None) == "the built-in defaults"
