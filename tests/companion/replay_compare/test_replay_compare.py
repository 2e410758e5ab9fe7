"""``companion compare`` (companion/replay_compare.py): verdicts by direction and tolerance
(CPU within its noise is the same), recordings matched by id wherever their folder lies,
recordings in one file only, a recording that failed, and files that are not replays."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import pytest

from companion.errors import ConfigError
from companion.replay_compare import (
    METRICS,
    MetricRule,
    compare,
    compare_text,
    read_replay,
    verdict,
)


def metrics(**changes: Any) -> dict[str, Any]:
    m: dict[str, Any] = {
        "frames": 300,
        "frames_replayed": 300,
        "poses": 250,
        "tracked_fraction": 0.9,
        "vo_resets": 1,
        "reset_counter_steps": 1,
        "pipeline_errors": 0,
        "cpu_ms_median": 10.0,
        "cpu_ms_p95": 20.0,
        "cpu_ms_p99": 30.0,
        "cpu_ms_max": 40.0,
        "cpu_ms_mean": 12.0,
        "published_matched": 250,
        "published_missing": 0,
        "position_diff_max_m": 0.0,
        "position_diff_p95_m": 0.0,
        "yaw_diff_max_deg": 0.0,
        "angle_diff_max_deg": 0.0,
        "identical": True,
        "ate_m": 0.05,
        "ate_pct_path": 0.5,
        "ate_to_best_constant": 0.02,
    }
    m.update(changes)
    return m


def document(*entries: dict[str, Any]) -> dict[str, Any]:
    return {
        "format": "companion-replay",
        "version": 1,
        "created": "2026-11-29T00:00:00+00:00",
        "software": {"version": "0.1.0", "commit": "abc", "dirty": False},
        "override": None,
        "recordings": list(entries),
        "failed": sum("error" in e for e in entries),
    }


def entry(path: str, rid: str, **changes: Any) -> dict[str, Any]:
    return {"path": path, "name": Path(path).name, "id": rid, "metrics": metrics(**changes)}


def test_verdicts_by_direction_and_tolerance() -> None:
    cpu = METRICS["cpu_ms_median"]
    assert verdict(cpu, 10.0, 10.9) == "same"  # within 10 %: the machine's noise
    assert verdict(cpu, 10.0, 11.5) == "worse" and verdict(cpu, 10.0, 8.5) == "better"
    tail = METRICS["cpu_ms_p99"]
    assert verdict(tail, 30.0, 36.0) == "same" and verdict(tail, 30.0, 39.0) == "worse"
    assert verdict(METRICS["poses"], 250, 251) == "better"
    assert verdict(METRICS["vo_resets"], 1, 2) == "worse"
    assert verdict(METRICS["tracked_fraction"], 0.9, 0.901) == "same"
    assert verdict(METRICS["ate_m"], 0.05, 0.0504) == "same"  # within 1 %
    assert verdict(METRICS["ate_m"], 0.05, 0.06) == "worse"
    assert verdict(METRICS["position_diff_max_m"], 0.0, 0.2) == "changed"  # no direction
    assert verdict(METRICS["identical"], True, False) == "changed"
    # fewer features: less CPU and a lower KLT floor, so a higher ratio; not "worse"
    assert verdict(METRICS["frame_to_floor"], 3.10, 4.25) == "changed"
    assert verdict(METRICS["frame_to_floor"], 3.10, 3.30) == "same"
    assert verdict(METRICS["identical"], True, True) == "same"
    assert verdict(METRICS["ate_m"], None, 0.05) == "new"
    assert verdict(METRICS["ate_m"], 0.05, None) == "gone"
    assert verdict(MetricRule("lower", 0.5), 1.0, 1.5) == "same"  # the absolute tolerance


def test_a_file_against_itself_is_the_same_everywhere() -> None:
    doc = document(entry("/r/a", "1111"), entry("/r/b", "2222", ate_m=None))
    result = compare(doc, copy.deepcopy(doc))
    assert result["worse"] == 0 and set(result["counts"]) == {"same"}
    assert all(r["verdict"] == "same" for rec in result["recordings"] for r in rec["rows"])
    assert all(r["verdict"] == "same" for r in result["total"])
    assert "all 22 metrics the same" in "\n".join(compare_text(result))


def test_matched_by_id_wherever_the_folder_lies_and_totals_over_both() -> None:
    a = document(entry("/old/a", "1111"), entry("/old/gone", "3333"))
    b = document(
        entry("/new/a", "1111", poses=260, cpu_ms_median=13.0, vo_resets=0, ate_m=0.04),
        entry("/new/fresh", "4444"),
    )
    result = compare(a, b)
    recs = {r["key"]: r for r in result["recordings"]}
    assert recs["id:1111"]["status"] == "both" and recs["id:1111"]["path_b"] == "/new/a"
    assert recs["id:3333"]["status"] == "only in A" and recs["id:4444"]["status"] == "only in B"
    rows = {r["metric"]: r for r in recs["id:1111"]["rows"]}
    assert rows["poses"]["verdict"] == "better" and rows["poses"]["diff"] == 10.0
    assert rows["cpu_ms_median"]["verdict"] == "worse"
    assert rows["vo_resets"]["verdict"] == "better" and rows["ate_m"]["verdict"] == "better"
    total = {r["metric"]: r for r in result["total"]}
    assert total["recordings"]["a"] == total["recordings"]["b"] == 1  # those in both
    assert total["poses"]["a"] == 250 and total["poses"]["b"] == 260
    assert result["worse"] == 1
    text = "\n".join(compare_text(result))
    assert "cpu_ms_median: 10 -> 13 (+3) worse" in text
    assert "only in A" in text and "only in B" in text


def test_a_recording_that_fails_in_b_only_is_worse() -> None:
    a = document(entry("/r/a", "1111"))
    b = document(
        {"path": "/r/a", "name": "a", "error": "frame 3: bad PNG", "kind": "dataset error"}
    )
    result = compare(a, b)
    (rec,) = result["recordings"]
    assert rec["status"] == "failed" and rec["verdict"] == "worse"
    assert rec["error_b"] == "frame 3: bad PNG" and result["worse"] >= 1
    total = {r["metric"]: r for r in result["total"]}
    assert total["recordings"]["a"] == 0  # replayed in both: none


@pytest.mark.parametrize(
    ("text", "named"),
    [
        ("{not json", "not JSON"),
        (json.dumps({"format": "companion-dataset"}), "not a replay file"),
        (json.dumps({"format": "companion-replay", "recordings": [1]}), "recordings"),
        (
            json.dumps({"format": "companion-replay", "recordings": [{"path": "x"}]}),
            r"recordings\[0\].metrics",
        ),
    ],
)
def test_a_file_that_is_not_a_replay_is_refused_naming_it(
    tmp_path: Path, text: str, named: str
) -> None:
    path = tmp_path / "x.json"
    path.write_text(text)
    with pytest.raises(ConfigError, match=named) as e:
        read_replay(path)
    assert str(path) in str(e.value)
    good = tmp_path / "good.json"
    good.write_text(json.dumps(document(entry("/r/a", "1"))))
    assert read_replay(good)["recordings"][0]["id"] == "1"
