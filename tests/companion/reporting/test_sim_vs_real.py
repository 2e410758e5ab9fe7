"""`companion report --sim-vs-real` (companion/reporting/sim_vs_real.py): a real sequence's
published error beside its simulated look-alike's, the 2x test, and the plot."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from companion.cli import main
from companion.reporting.sim_vs_real import real_errors, seed_folders, sim_errors


def _real(folder: Path, ate_m: float, ate_pct: float, resets: int) -> Path:
    folder.mkdir(parents=True)
    doc = {
        "methods": [{"method": "M-MSCwK", "ate_se3_m": ate_m, "ate_se3_pct": ate_pct}],
        "vo": {"resets": resets},
        "tracks": {"M-MSCwK": {"ratio_to_mean": 0.5}},
    }
    (folder / "scale_metrics.json").write_text(json.dumps(doc))
    return folder


def _sim(folder: Path, ate_m: float, ate_pct: float, resets: int | None) -> Path:
    folder.mkdir(parents=True)
    rows = [{"method": "M-MSCwK", "ate_m": ate_m, "ate_pct": ate_pct}]
    (folder / "scale_metrics.json").write_text(json.dumps(rows))
    doc: dict = {"tracks": {"M-MSCwK": {"ratio_to_mean": 0.1}}}
    if resets is not None:
        doc["vo_resets"] = resets
    (folder / "eval.json").write_text(json.dumps(doc))
    return folder


def test_the_sides_are_read_and_averaged(tmp_path: Path) -> None:
    real = real_errors(_real(tmp_path / "real" / "rislab", 0.4, 2.0, 24))
    assert (real.ate_m, real.ate_pct, real.ratio_to_constant, real.resets) == (0.4, 2.0, 0.5, 24)
    _sim(tmp_path / "like-2", 0.3, 3.0, 4)
    _sim(tmp_path / "like-1", 0.1, 1.0, 0)
    _sim(tmp_path / "likely-1", 9.0, 9.0, 9)  # another flight's name
    (tmp_path / "like-3").mkdir()  # no evaluation in it
    folders = seed_folders(tmp_path / "like")
    assert [f.name for f in folders] == ["like-1", "like-2"]
    sim = sim_errors(folders)
    assert sim.runs == 2 and sim.ate_pct == pytest.approx(2.0) and sim.resets == pytest.approx(2)
    _sim(tmp_path / "old-1", 0.1, 1.0, None)
    assert sim_errors([tmp_path / "old-1"]).resets is None  # not recorded: not a zero
    lost = _sim(tmp_path / "lost-1", 0.0, 0.0, 49)
    (lost / "scale_metrics.json").write_text("[]")  # the VO never gave a pose
    both = sim_errors([tmp_path / "like-1", lost])
    assert (both.runs, both.no_estimate, both.ate_pct, both.resets) == (2, 1, 1.0, 24.5)
    with pytest.raises(ValueError, match="no estimate in any of 1"):
        sim_errors([lost])
    with pytest.raises(ValueError, match="simulated flight's folder"):
        real_errors(tmp_path / "like-1")


def test_the_cli_compares_the_pairs_and_draws_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    near = _real(tmp_path / "real_near", 0.4, 2.0, 24)
    far = _real(tmp_path / "real_far", 0.4, 2.0, 24)
    _sim(tmp_path / "near-1", 0.3, 1.5, 3)  # 0.75 of the real: within 2x
    _sim(tmp_path / "far-1", 0.01, 0.05, 0)  # 40 times better than reality: not within
    plot = tmp_path / "img" / "sim_vs_real.png"  # its folder made
    pairs = [f"{near}={tmp_path / 'near'}", f"{far}={tmp_path / 'far'}"]
    assert main(["report", "--sim-vs-real", *pairs, "--plot", str(plot)]) == 0
    text = capsys.readouterr().out
    assert "| real_near / near | 0.300 m = 1.500 % (1) | 0.400 m = 2.000 % | 0.75 | yes |" in text
    assert "| real_far / far | 0.010 m = 0.050 % (1) | 0.400 m = 2.000 % | 0.025 | NO |" in text
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["report", "--sim-vs-real", f"{near}={tmp_path / 'none'}"]) == 2
    assert "SIM_PREFIX-SEED" in capsys.readouterr().err
