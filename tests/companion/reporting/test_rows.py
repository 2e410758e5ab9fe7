"""`companion report --rows` (companion/reporting/rows.py): one line per flight over its
NAME-SEED folders, the published method against the baselines."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from companion.cli import main
from companion.reporting.rows import name_and_seed, read_rows, rows_table, tracked_share

METHODS = ("MSC", "MSCwK", "M-MSC", "M-MSCwK", "B7 window-ML", "B8 per-frame", "B9 plane")


def _flight(root: Path, name: str, ate_pct: dict[str, float], resets: int | None) -> Path:
    folder = root / name
    folder.mkdir(parents=True)
    rows = [{"method": m, "ate_pct": ate_pct.get(m, 1.0), "ate_m": 0.1} for m in METHODS]
    (folder / "scale_metrics.json").write_text(json.dumps(rows))
    doc = {"config": "x", "frames": {}, "tracks": {}}
    if resets is not None:
        doc["vo_resets"] = resets
    (folder / "eval.json").write_text(json.dumps(doc))
    return folder


def test_folders_group_by_name_with_seeds_in_order(tmp_path: Path) -> None:
    dirs = [
        _flight(tmp_path, "rs-3", {"M-MSCwK": 0.30, "B8 per-frame": 0.2}, 2),
        _flight(tmp_path, "rs-1", {"M-MSCwK": 0.10, "B8 per-frame": 0.2}, 0),
        _flight(tmp_path, "lens-1", {"M-MSCwK": 0.45, "B9 plane": 0.40}, None),
    ]
    real = tmp_path / "real-1"
    real.mkdir()
    (real / "scale_metrics.json").write_text(json.dumps({"sequence": "a real one"}))
    (tmp_path / "notes").mkdir()
    rows = read_rows([*dirs, real, tmp_path / "notes", tmp_path / "missing-2"])
    assert [r.name for r in rows] == ["rs", "lens"]
    rs, lens = rows
    assert rs.seeds == [1, 3] and rs.ate_pct == [0.10, 0.30] and rs.resets == [0, 2]
    assert rs.mean_pct == pytest.approx(0.20)
    assert not rs.beats("B8 per-frame") and rs.beats("B7 window-ML")  # 0.20 vs 0.20: not below
    assert lens.resets == [None] and not lens.beats("B9 plane")
    lost = _flight(tmp_path, "lens-2", {}, 49)
    (lost / "scale_metrics.json").write_text("[]")  # the VO never gave a pose
    lens = read_rows([dirs[2], lost])[0]
    assert lens.seeds == [1, 2] and lens.mean_pct == pytest.approx(0.45)
    assert "| lens | 1, 2 | 0.450 / no pose | 0.450 % | ? / 49 |" in rows_table([lens])
    text = rows_table(rows, {"rs": "rolling shutter"})
    assert "| rolling shutter | 1, 3 | 0.100 / 0.300 | 0.200 % | 0 / 2 |" in text
    assert "| lens | 1 | 0.450 | 0.450 % | ? |" in text and text.count("\n") == 3


def test_names_and_seeds() -> None:
    assert name_and_seed(Path("a/rolling_shutter_vo-12")) == ("rolling_shutter_vo", 12)
    assert name_and_seed(Path("hills-lawnmower-2")) == ("hills-lawnmower", 2)
    assert name_and_seed(Path("tum_fr1_rpy")) is None and name_and_seed(Path("-3")) is None


def test_the_cli_prints_the_rows_or_exits_when_there_are_none(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = _flight(tmp_path, "ideal-1", {"M-MSCwK": 0.036}, 0)
    assert main(["report", "--rows", str(folder)]) == 0
    assert "| ideal | 1 | 0.036 | 0.036 % | 0 |" in capsys.readouterr().out
    assert main(["report", "--rows", str(tmp_path / "nothing")]) != 0
    assert "no NAME-SEED folder" in capsys.readouterr().err


def test_the_detailed_table_gives_the_lowest_tracking_and_the_mean_scale_error(
    tmp_path: Path,
) -> None:
    dirs = []
    head = "# timestamp tx ty tz qx qy qz qw\n"
    for seed, (skip, scale_pct) in enumerate(((0, 0.2), (30, 0.4)), 1):
        folder = _flight(tmp_path, f"hills-lawnmower-{seed}", {"M-MSCwK": 0.3}, 0)
        rows = json.loads((folder / "scale_metrics.json").read_text())
        for r in rows:
            r["scale_mean_abs_rel_pct"] = scale_pct
        (folder / "scale_metrics.json").write_text(json.dumps(rows))
        t = np.arange(300) / 30.0  # 10 s of frames; the first pose at 2 s
        (folder / "groundtruth.tum").write_text(
            head + "".join(f"{x:.6f} 0 0 0 0 0 0 1\n" for x in t)
        )
        posed = np.delete(t[60:], np.arange(50, 50 + skip))  # seed 2: 30 of 240 without one
        (folder / "M-MSCwK.tum").write_text(
            head + "".join(f"{x:.6f} 0 0 0 0 0 0 1\n" for x in posed)
        )
        dirs.append(folder)
    (row,) = read_rows(dirs)
    assert row.tracked == pytest.approx([1.0, 210 / 240])
    assert tracked_share(tmp_path) != tracked_share(tmp_path)  # no files: NaN
    text = rows_table([row], {"hills-lawnmower": "hills / lawnmower"}, detail=True)
    assert text.splitlines()[1].count("|") == 10  # nine columns
    assert text.splitlines()[2].endswith("| yes, yes, yes | 87.5 % | 0.30 % |")
    assert "87.5 %" not in rows_table([row])  # the plain table keeps its seven columns
