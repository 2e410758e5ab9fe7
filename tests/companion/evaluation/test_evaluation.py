"""Evaluation: Umeyama alignment identities, and `companion eval` checked against evo_ape."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.cli import main
from companion.config import load_config
from companion.drivers.dataset import read_tum
from companion.evaluation.trajectory import ate_rmse, path_length, umeyama
from companion.geometry import so3
from companion.sitl.world.dataset import record


def test_umeyama_recovers_a_similarity_exactly() -> None:
    rng = np.random.default_rng(4)
    est = rng.normal(size=(100, 3))
    R = so3.exp([0.3, -0.2, 0.9])
    gt = 2.5 * est @ R.T + [1.0, -2.0, 0.5]
    a = umeyama(est, gt, with_scale=True)
    assert np.allclose(a.R, R) and np.isclose(a.scale, 2.5) and np.allclose(a.t, [1, -2, 0.5])
    assert ate_rmse(est, gt, "sim3")[0] < 1e-12
    # rigid alignment cannot absorb the scale
    assert ate_rmse(est, gt, "se3")[0] > 0.5
    noisy = gt + rng.normal(0, 0.01, gt.shape)
    assert 0.005 < ate_rmse(est, noisy, "sim3")[0] < 0.02
    assert np.isclose(path_length(np.array([[0, 0, 0], [3, 4, 0], [3, 4, 12.0]])), 17.0)


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    base = tmp_path_factory.mktemp("eval")
    cfg = load_config(
        overrides={
            "sitl": {"terrain": "urban", "trajectory": "figure8", "seconds": 12.0, "seed": 3}
        }
    )
    record(cfg, base / "urban", progress=False)
    assert main(["eval", str(base / "urban"), "--out", str(base / "out"), "--no-progress"]) == 0
    return base / "out"


def test_eval_writes_trajectories_and_meets_accuracy(evaluated: Path) -> None:
    m = json.loads((evaluated / "metrics.json").read_text())
    assert m["resets"] == 0 and m["tracking_ratio"] >= 0.98
    assert m["ate_sim3_pct"] < 1.0
    t_vo, _ = read_tum(evaluated / "vo.tum")
    t_gt, _ = read_tum(evaluated / "groundtruth.tum")
    assert len(t_vo) == m["segment_frames"] and len(t_gt) == m["frames"]
    assert np.isin(np.round(t_vo, 6), np.round(t_gt, 6)).all()
    assert "ate_sim3_m" in (evaluated / "report.md").read_text()


def test_eval_straight_from_the_simulator_agrees_with_the_recording(evaluated: Path) -> None:
    """`companion eval --terrain ... --seed ...` (no dataset on disk) renders the flight the
    fixture recorded: same frames, and the same accuracy up to what the recording's JPEG
    compression changes (2.7 vs 2.9 cm; a ground truth one frame off would add ~10 cm)."""
    out = evaluated.parent / "sim"
    args = ["--terrain", "urban", "--trajectory", "figure8", "--seconds", "12", "--seed", "3"]
    assert main(["eval", *args, "--out", str(out), "--no-progress"]) == 0
    sim = json.loads((out / "metrics.json").read_text())
    rec = json.loads((evaluated / "metrics.json").read_text())
    assert sim["frames"] == rec["frames"] and sim["resets"] == rec["resets"] == 0
    assert sim["tracking_ratio"] >= 0.98 and sim["ate_sim3_pct"] < 1.0
    assert sim["ate_sim3_m"] == pytest.approx(rec["ate_sim3_m"], abs=0.008)
    assert (out / "report.md").read_text().startswith("# VO on sitl-urban-figure8-12s-seed3")


def test_ate_agrees_with_evo_ape(evaluated: Path) -> None:
    evo_ape = Path(sys.executable).parent / "evo_ape"
    assert evo_ape.exists(), "evo (the eval extra) must be installed: make installs it"
    proc = subprocess.run(
        [str(evo_ape), "tum", str(evaluated / "groundtruth.tum"), str(evaluated / "vo.tum"), "-as"],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    match = re.search(r"rmse\s+([0-9.]+)", proc.stdout)
    assert match, proc.stdout
    ours = json.loads((evaluated / "metrics.json").read_text())["ate_sim3_m"]
    assert abs(float(match.group(1)) - ours) < 1e-3


def test_eval_all_methods_on_a_recording(evaluated: Path) -> None:
    """`companion eval DATASET --methods all`: every scale method on the VO of one recording,
    with tables, one TUM trajectory per method and the plots."""
    out = evaluated.parent / "all"
    code = main(
        [
            "eval",
            str(evaluated.parent / "urban"),
            "--methods",
            "all",
            "--out",
            str(out),
            "--no-progress",
        ]
    )
    assert code == 0
    rows = {r["method"]: r for r in json.loads((out / "scale_metrics.json").read_text())}
    assert set(rows) == {
        "MSC",
        "MSCwK",
        "M-MSC",
        "M-MSCwK",
        "B7 window-ML",
        "B8 per-frame",
        "B9 plane",
    }
    assert rows["M-MSCwK"]["scale_mean_abs_rel_pct"] < 1.0 and rows["M-MSCwK"]["ate_pct"] < 1.0
    assert json.loads((out / "eval.json").read_text())["vo_resets"] == 0
    for name in (
        "scale.png",
        "scale_error.png",
        "trajectory.png",
        "point_cloud.png",
        "M-MSCwK.tum",
        "groundtruth.tum",
        "scale_metrics.csv",
        "report.md",
    ):
        assert (out / name).stat().st_size > 0, name


def test_eval_phases_on_a_take_off_from_the_ground(tmp_path, capsys) -> None:
    """`companion eval --phases`: the published poses of a flight that starts on the ground,
    by phase (issue 18), written to phases.json."""
    import json

    from companion.cli import main

    rc = main(
        [
            "eval",
            "--phases",
            "--terrain",
            "flat",
            "--trajectory",
            "hover",
            "--takeoff-landing",
            "--seconds",
            "12",
            "--no-progress",
            "--out",
            str(tmp_path),
        ]
    )
    assert rc == 0, capsys.readouterr().err
    s = json.loads((tmp_path / "phases.json").read_text())
    assert s["first_pose_s"] <= 0.2 and s["vo_resets"] == 0
    assert s["phases"]["ground"]["frames"] > 30 and s["phases"]["ground"]["max_m"] <= 0.05
    assert s["phases"]["climb"]["frames"] > 30 and s["phases"]["landed"]["frames"] > 0
    assert "| ground |" in capsys.readouterr().out


# ------------------------------------------------------------------ datasets without a world
def as_converted_recording(sim: Path, out: Path, ranges: bool = True) -> Path:
    """The simulated recording ``sim`` as a real clip converted to our format would be: no
    [sitl] table (no world), no true distances; without ``ranges`` no distance sensors
    either (no ranges.csv, none declared in calibration.toml)."""
    import csv
    import shutil
    import tomllib

    import tomli_w

    shutil.copytree(sim, out)
    meta = tomllib.loads((out / "meta.toml").read_text())
    del meta["sitl"]
    (out / "meta.toml").write_text(tomli_w.dumps({**meta, "source": "converted"}))
    with (out / "ranges.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    if ranges:
        with (out / "ranges.csv").open("w", newline="") as fh:
            w = csv.DictWriter(fh, [k for k in rows[0] if k != "true_distance_m"])
            w.writeheader()
            w.writerows({k: v for k, v in r.items() if k != "true_distance_m"} for r in rows)
    else:
        (out / "ranges.csv").unlink()
        calib = tomllib.loads((out / "calibration.toml").read_text())
        del calib["rangefinders"]
        calib["matrices"] = {"T_body_cam": calib["matrices"]["T_body_cam"]}
        (out / "calibration.toml").write_text(tomli_w.dumps(calib))
    return out


EVAL_WITHOUT_SITL = """
import json, sys
from companion.cli import main
code = main(sys.argv[1:])
print(json.dumps({"code": code, "sitl": sorted(
    m for m in sys.modules if m == "sitl" or m.startswith("sitl."))}))
"""


def eval_in_fresh_process(*args: str) -> dict:
    """`companion eval ARGS` in a new interpreter; its exit code and the sitl modules loaded."""
    proc = subprocess.run(
        [sys.executable, "-c", EVAL_WITHOUT_SITL, "eval", *args, "--no-progress"],
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    result["stdout"] = proc.stdout
    return result


def test_eval_without_a_world_never_touches_the_simulator(evaluated: Path) -> None:
    """A dataset that declares no simulated world (a converted real clip): every scale method
    side by side by metric (SE3) and Sim(3) ATE against its ground truth; the figures that
    need a true scale are unavailable, never computed from a default world; `sitl` is never
    imported."""
    real = as_converted_recording(evaluated.parent / "urban", evaluated.parent / "converted")
    from companion.drivers.dataset import open_dataset

    ds = open_dataset(real)
    assert ds.sitl is None and not ds.has_world and ds.has_ground_truth
    assert np.isnan(ds.true_range_m).all() and len(ds.rangefinders) == 4
    out = evaluated.parent / "converted-all"
    result = eval_in_fresh_process(str(real), "--methods", "all", "--out", str(out))
    assert result["code"] == 0 and result["sitl"] == []
    doc = json.loads((out / "scale_metrics.json").read_text())
    assert doc["world"] is None and doc["distance_sensors"] == [0, 1, 2, 3]
    rows = {r["method"]: r for r in doc["methods"]}
    assert {"MSC", "MSCwK", "M-MSC", "M-MSCwK", "B7 window-ML", "B8 per-frame"} <= set(rows)
    for r in rows.values():
        assert r["scale_mse"] is None and r["scale_mean_abs_rel_pct"] is None
        assert "no simulated world" in r["unavailable"]["scale_mse"]
    best = rows["M-MSCwK"]
    # the accuracy the simulated evaluation of the same recording shows (< 1 % of the path)
    assert best["frames"] > 100 and best["ate_se3_pct"] < 1.0
    assert best["ate_sim3_m"] <= best["ate_se3_m"]  # a scale fit can only lower the RMSE
    assert abs(best["sim3_scale"] - 1.0) < 0.02
    assert doc["vo"]["ate_sim3_pct"] < 1.0  # the raw VO, Sim(3)-aligned
    report = (out / "report.md").read_text()
    assert "unavailable" in report and "Sim(3) ATE" in report
    assert (out / "M-MSCwK.tum").stat().st_size > 0 and (out / "groundtruth.tum").exists()
    assert not (out / "point_cloud.png").exists()  # needs the true terrain


def test_eval_without_ranges_invents_no_sensors(evaluated: Path) -> None:
    """No distance sensors declared, no ranges: no method gets a scale (each says why), and
    none of the built-in simulated sensors appears; the VO is still evaluated."""
    real = as_converted_recording(
        evaluated.parent / "urban", evaluated.parent / "no-ranges", ranges=False
    )
    from companion.cli.evaluate_dataset import dataset_config
    from companion.drivers.dataset import open_dataset

    ds = open_dataset(real)
    assert ds.rangefinders == [] and ds.ranges == []
    assert dataset_config(ds, None).rangefinders == ()
    out = evaluated.parent / "no-ranges-all"
    result = eval_in_fresh_process(str(real), "--methods", "all", "--out", str(out))
    assert result["code"] == 0 and result["sitl"] == []
    doc = json.loads((out / "scale_metrics.json").read_text())
    assert doc["distance_sensors"] == []
    for r in doc["methods"]:
        assert r["frames"] == 0 and r["ate_se3_m"] is None
        assert "no distance sensors" in r["unavailable"]["ate_se3_m"]
    assert doc["vo"]["tracking_ratio"] >= 0.98  # the VO itself runs as before
    vo_out = evaluated.parent / "no-ranges-vo"
    result = eval_in_fresh_process(str(real), "--out", str(vo_out))
    assert result["code"] == 0 and result["sitl"] == []
    assert json.loads((vo_out / "metrics.json").read_text())["ate_sim3_pct"] < 1.0
    assert not (vo_out / "poses.csv").exists()  # no scale, no metric pose


def test_markdown_table_is_the_header_the_rule_and_a_line_per_row() -> None:
    from companion.evaluation.tables import markdown_table

    table = markdown_table(["method", "ATE"], [["MSC", "0.120 m"], ["B8", "unavailable"]])
    assert table.splitlines() == [
        "| method | ATE |",
        "|---|---|",
        "| MSC | 0.120 m |",
        "| B8 | unavailable |",
    ]
