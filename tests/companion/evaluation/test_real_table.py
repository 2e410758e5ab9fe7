"""The "Real sequences" table (companion/evaluation/real_table.py) from eval documents."""

from __future__ import annotations

from typing import Any

from companion.evaluation.real_table import real_row, real_sequences_table


def method(name: str, ate_m: float | None, scale: float = 1.0) -> dict[str, Any]:
    return {
        "method": name,
        "frames": 100,
        "ate_se3_m": ate_m,
        "ate_se3_pct": None if ate_m is None else 100 * ate_m / 2.0,
        "sim3_scale": scale,
    }


def doc(ours_m: float | None, baselines_m: tuple[float | None, ...]) -> dict[str, Any]:
    names = ("B7 window-ML", "B8 per-frame", "B9 plane")
    return {
        "frames": {"frames": 190},
        "vo": {
            "tracking_ratio": 0.984,
            "resets": 2,
            "ate_sim3_m": 0.016,
            "ate_sim3_pct": 0.72,
            "path_m": 2.25,
            "segment_frames": 187,
        },
        "methods": [method("M-MSCwK", ours_m, 1.013)]
        + [method(n, b) for n, b in zip(names, baselines_m, strict=True)],
        "tracks": {"M-MSCwK": {"ratio_to_mean": 0.036}},
    }


def test_a_row_reports_the_published_method_against_the_best_baseline() -> None:
    row = real_row("teddy", doc(0.005, (0.131, 0.006, None)))
    assert row[:4] == ["teddy", "190", "98.4 %", "2"]
    assert row[4] == "0.016 m = 0.72 % of 2.25 m (187 fr.)"
    assert row[5] == "0.005 m = 0.25 % (100 fr.)" and row[6] == "0.036" and row[7] == "1.013"
    assert row[8] == "B8 per-frame 0.006 m" and row[9] == "yes"


def test_losing_to_one_baseline_is_said_and_no_estimate_is_not_a_number() -> None:
    assert real_row("a", doc(0.007, (0.131, 0.006, 0.009)))[9] == "NO"
    row = real_row("b", doc(None, (None, None, None)))
    assert row[5] == row[6] == row[7] == "no estimate" and row[8] == row[9] == "-"


def test_the_table_has_one_line_per_sequence_under_its_header() -> None:
    text = real_sequences_table([("a", doc(0.005, (0.1, 0.2, 0.3))), ("b", doc(None, (1, 2, 3)))])
    lines = text.splitlines()
    assert len(lines) == 4 and "M-MSCwK metric ATE" in lines[0] and lines[2].startswith("| a |")
