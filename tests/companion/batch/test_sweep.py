"""Sweeps (companion/batch/sweep.py) and the task specs under them (spec.py): the grid's
product, the names, the metrics read back, the order of the table; the config a task runs
with, written as TOML and read back the same."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import pytest

from companion.batch import sweep
from companion.batch.runner import config_text
from companion.batch.spec import Task, nested, parse_value, to_toml
from companion.config import Config, from_dict
from companion.errors import ConfigError


def test_the_grid_is_the_product_of_its_axes_in_order() -> None:
    a = sweep.parse_grid("vo.max_features=150,200,300")
    b = sweep.parse_grid("scale.method = M-MSC,M-MSCwK")
    assert a == sweep.Grid("vo.max_features", (150, 200, 300))
    assert b.key == "scale.method" and b.values == ("M-MSC", "M-MSCwK")
    pts = sweep.points([a, b])
    assert len(pts) == 6
    assert pts[0] == (("vo.max_features", 150), ("scale.method", "M-MSC"))
    assert pts[1] == (("vo.max_features", 150), ("scale.method", "M-MSCwK"))
    assert sweep.point_label(pts[5]) == "vo.max_features=300,scale.method=M-MSCwK"
    for bad in ("max_features=1", "vo.max_features", "vo.max_features="):
        with pytest.raises(ConfigError, match="--grid"):
            sweep.parse_grid(bad)
    with pytest.raises(ConfigError, match="twice"):
        sweep.points([a, a])


def test_one_task_per_point_and_input(tmp_path: Path) -> None:
    ds = tmp_path / "clip"
    ds.mkdir()
    grids = [sweep.parse_grid("vo.max_features=150,200")]
    tasks = sweep.sweep_tasks(grids, [ds], ["hills-lawnmower-2"], 10.0)
    assert [t.name for t in tasks] == [
        "clip/vo.max_features=150",
        "clip/vo.max_features=200",
        "hills-lawnmower-2/vo.max_features=150",
        "hills-lawnmower-2/vo.max_features=200",
    ]
    assert {t.kind for t in tasks} == {"sweep"}
    assert tasks[0].inputs == (str(ds.resolve()),) and tasks[0].argv[1] == str(ds.resolve())
    flight = ("--terrain", "hills", "--trajectory", "lawnmower", "--seconds", "10")
    assert tasks[3].argv[1:9] == (*flight, "--seed", "2")
    assert tasks[3].overrides == (("vo.max_features", 200),)
    with pytest.raises(ConfigError, match="TERRAIN-TRAJECTORY-SEED"):
        sweep.sweep_tasks(grids, [], ["hills-1"], 10.0)
    with pytest.raises(ConfigError, match="--datasets or --flights"):
        sweep.sweep_tasks(grids, [], [], 10.0)


def test_metrics_are_read_for_the_published_method(tmp_path: Path) -> None:
    flight = tmp_path / "flight"
    flight.mkdir()
    rows = [
        {"method": "MSC", "ate_m": 9.0, "ate_pct": 9.0, "scale_mse": 1.0},
        {"method": "M-MSCwK", "ate_m": 0.04, "ate_pct": 0.03, "scale_mse": math.nan},
    ]
    (flight / "scale_metrics.json").write_text(json.dumps(rows))  # NaN, as eval writes it
    m = sweep.metrics_of(flight)
    assert m["metric_ate_m"] == 0.04 and m["metric_ate_pct"] == 0.03
    assert m["scale_mse"] is None and m["sim3_scale"] is None
    assert sweep.metrics_of(flight, "MSC")["metric_ate_m"] == 9.0
    real = tmp_path / "real"
    real.mkdir()
    doc = {"methods": [{"method": "M-MSCwK", "ate_se3_m": 0.05, "sim3_scale": 1.02}]}
    (real / "scale_metrics.json").write_text(json.dumps(doc))
    m = sweep.metrics_of(real)
    assert m["metric_ate_m"] == 0.05 and m["sim3_scale"] == 1.02
    assert m["scale_error_pct"] is None  # a no-world dataset has no true scale


def test_the_table_is_sorted_by_the_metric_with_failures_last() -> None:
    grids = [sweep.Grid("vo.max_features", (150, 200, 300))]
    rows = [
        sweep.SweepRow("a", (("vo.max_features", 150),), {"metric_ate_m": 0.3}),
        sweep.SweepRow("a", (("vo.max_features", 200),), {}, "exit 2: bad dataset"),
        sweep.SweepRow("a", (("vo.max_features", 300),), {"metric_ate_m": 0.1}),
    ]
    lines = sweep.table(rows, grids, "metric_ate_m").splitlines()
    assert lines[0].startswith("| rank | input | vo.max_features | **metric_ate_m** |")
    assert lines[2].startswith("| 1 | a | 300 | 0.1 |")
    assert lines[3].startswith("| 2 | a | 150 | 0.3 |")
    assert lines[4].startswith("| 3 | a | 200 | failed: exit 2: bad dataset |")


def test_a_tasks_config_is_its_file_with_the_overrides_as_valid_toml(tmp_path: Path) -> None:
    assert parse_value("150") == 150 and parse_value("0.5") == 0.5
    assert parse_value("true") is True and parse_value("magnetometer") == "magnetometer"
    data = {
        "vo": {"max_features": 150, "klt_fb_max_px": 1.5},
        "scale": {"method": "M-MSC"},
        "rangefinders": [{"id": 1, "mount": {"x_m": 0.1}}, {"id": 2, "name": 'a "b"'}],
        "x": {"y": {"z": [1, 2]}},
    }
    assert tomllib.loads(to_toml(data)) == data
    base = tmp_path / "base.toml"
    base.write_text('[vo]\nmax_features = 300\nheading_source = "autopilot"\n')
    task = Task("sequence", "t", ("eval",), (), str(base), (("vo.max_features", 150),))
    text = config_text(task)
    assert text is not None
    merged = tomllib.loads(text)
    assert merged["vo"] == {"max_features": 150, "heading_source": "autopilot"}
    assert from_dict(Config, merged).vo.max_features == 150
    assert config_text(Task("sequence", "t", ("eval",))) is None
    with pytest.raises(ConfigError, match=r"section\.key"):
        nested([("vo.", 1)])
