"""The roll/pitch and d-Pose reports (companion.reporting.pose) of synthetic runs whose
errors are known in closed form: the tables must show them, the files must all be written."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from companion.offline import SERIES, AttitudeRun, DposeRun
from companion.reporting import write_attitude, write_dpose


def test_the_attitude_report_shows_each_estimates_rmse(tmp_path: Path) -> None:
    run = AttitudeRun()
    n = 600  # 20 s at 30 Hz
    for k in range(n):
        run.time_us.append(k * 33_333)
    truth = np.column_stack([0.05 * np.sin(np.arange(n) / 40), 0.03 * np.cos(np.arange(n) / 55)])
    offsets_deg = {"vo": 1.0, "ground": 0.5, "gravity": 0.25, "fused": 0.1, "fused_ranges": 0.2}
    run.series["truth"] = [tuple(r) for r in truth]
    for name, deg in offsets_deg.items():  # a constant roll error, pitch exact
        est = truth + np.array([math.radians(deg), 0.0])
        run.series[name] = [tuple(r) for r in est]
    run.series["ground"][:300] = [(math.nan, math.nan)] * 300  # half missing
    run.reasons = {"too steep": 7, "too few hits": 2}
    assert set(run.series) == set(SERIES)
    table = write_attitude(run, tmp_path, "synthetic")
    rows = {r["estimate"]: r for r in json.loads((tmp_path / "attitude_metrics.json").read_text())}
    for name, deg in offsets_deg.items():
        assert abs(rows[name]["roll_rmse_deg"] - deg) < 1e-9, (name, rows[name])
        assert rows[name]["pitch_rmse_deg"] < 1e-9
    # after the first 5 s (settling): 300 of the 450 frames have the range estimate
    assert abs(rows["ground"]["available"] - 300 / 450) < 0.01, rows["ground"]
    assert rows["vo"]["available"] == 1.0
    assert "| VO rotation alone | 1.000 deg | 0.000 deg | 100.0 % |" in table
    text = (tmp_path / "attitude.md").read_text()
    assert table in text and "too steep" in text
    assert (tmp_path / "attitude_metrics.csv").read_text().count("\n") == 1 + len(offsets_deg)
    assert (tmp_path / "attitude.png").stat().st_size > 1000


def test_the_dpose_report_shows_each_estimates_error_by_height(tmp_path: Path) -> None:
    run = DposeRun()
    n = 300
    heights = np.linspace(1.0, 8.0, n)
    for k in range(n):
        run.time_us.append(k * 33_333)
        run.height_m.append(float(heights[k]))
        truth = np.eye(4)
        truth[:3, 3] = [0.1 * k / n, 0.0, -heights[k]]
        run.truth.append(truth)
        d = truth.copy()
        d[:3, 3] += [0.01, 0.0, 0.0]  # d-Pose 1 cm off in x
        run.dpose.append(d if k % 10 else np.full((4, 4), np.nan))  # one frame in ten missing
        v = truth.copy()
        v[:3, 3] += [0.0, 0.05, 0.0]  # the VO 5 cm off in y
        run.vo.append(v)
    run.reasons = {"a mark not found": 30}
    table = write_dpose(run, tmp_path, "synthetic")
    rows = json.loads((tmp_path / "dpose_metrics.json").read_text())
    dpose_all = next(r for r in rows if r["estimate"] == "d-Pose" and r["heights"] == "all")
    vo_all = next(r for r in rows if r["estimate"] == "VO (M-MSCwK)" and r["heights"] == "all")
    assert abs(dpose_all["t_rmse_m"] - 0.01) < 1e-9 and abs(vo_all["t_rmse_m"] - 0.05) < 1e-9
    assert abs(dpose_all["available"] - 0.9) < 1e-9 and vo_all["available"] == 1.0
    assert dpose_all["r_rmse_deg"] < 1e-6
    assert "| d-Pose | all | 300 | 90.0 % |" in table and "0.010 m" in table
    assert "30 frames: a mark not found" in (tmp_path / "dpose.md").read_text()
    assert (tmp_path / "dpose.png").stat().st_size > 1000
