"""Parameter sweeps: a grid of config values (``--grid vo.max_features=150,200,300``) times
datasets or simulated flights, one task per point and input, and the table of a metric.

The metrics are read from what ``companion eval --methods all`` writes (scale_metrics.json:
a list of methods for a flight or a recorded simulated flight, a document for a dataset
without a world), for the published method (``scale.method``, M-MSCwK by default).
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.batch.spec import Override, Task, flight, parse_value, sequence
from companion.errors import BatchError, ConfigError

PUBLISHED = "M-MSCwK"  # the config's default scale.method
# metric -> (key in a simulated flight's row, key in a no-world method row); None: not there
METRICS: dict[str, tuple[str | None, str | None]] = {
    "metric_ate_m": ("ate_m", "ate_se3_m"),
    "metric_ate_pct": ("ate_pct", "ate_se3_pct"),
    "final_error_m": ("final_error_m", "final_error_m"),
    "scale_mse": ("scale_mse", "scale_mse"),
    "scale_error_pct": ("scale_mean_abs_rel_pct", None),
    "sim3_scale": (None, "sim3_scale"),
}


@dataclass(frozen=True)
class Grid:
    """One ``--grid`` axis: a dotted config key and its values."""

    key: str
    values: tuple[Any, ...]


def parse_grid(text: str) -> Grid:
    """``section.key=v1,v2,...`` -> Grid (ConfigError naming the flag otherwise)."""
    key, eq, values = text.partition("=")
    key = key.strip()
    if not eq or "." not in key or not values.strip():
        raise ConfigError(f"--grid {text}: expected section.key=value1,value2,...")
    return Grid(key, tuple(parse_value(v.strip()) for v in values.split(",")))


def points(grids: Sequence[Grid]) -> list[tuple[Override, ...]]:
    """The grid's product, in the order given (the first axis varies slowest)."""
    keys = [g.key for g in grids]
    if len(set(keys)) != len(keys):
        raise ConfigError(f"--grid: a key given twice ({', '.join(keys)})")
    return [
        tuple(zip(keys, combo, strict=True))
        for combo in itertools.product(*(g.values for g in grids))
    ]


def point_label(point: tuple[Override, ...]) -> str:
    """``vo.max_features=150,scale.method=M-MSC``: a point's folder name."""
    return ",".join(f"{k}={v}" for k, v in point) or "defaults"


def flight_base(spec: str, seconds: float) -> Task:
    """A simulated flight named TERRAIN-TRAJECTORY-SEED (``hills-lawnmower-1``), every scale
    method."""
    parts = spec.split("-")
    if len(parts) != 3 or not parts[2].isdigit():
        raise ConfigError(f"--flights {spec}: expected TERRAIN-TRAJECTORY-SEED (hills-lawnmower-1)")
    return flight(spec, parts[0], parts[1], int(parts[2]), seconds, ("--methods", "all"))


def sweep_tasks(
    grids: Sequence[Grid],
    datasets: Sequence[Path],
    flights: Sequence[str],
    seconds: float,
    config: str | None = None,
) -> list[Task]:
    """One task per grid point and dataset or flight, named ``INPUT/POINT``."""
    bases = [sequence(d.name, d.resolve(), config=config) for d in datasets]
    bases += [flight_base(f, seconds) for f in flights]
    if not bases:
        raise ConfigError("companion sweep: give --datasets or --flights")
    names = [b.name for b in bases]
    if len(set(names)) != len(names):
        raise ConfigError(f"companion sweep: two inputs with one name ({', '.join(names)})")
    return [b.with_overrides(p, f"{b.name}/{point_label(p)}") for b in bases for p in points(grids)]


def metrics_of(folder: Path, method: str = PUBLISHED) -> dict[str, float | None]:
    """Every metric of METRICS for ``method`` from a result folder (None where absent)."""
    path = folder / "scale_metrics.json"
    if not path.is_file():
        raise BatchError(
            f"{folder}: no scale_metrics.json (was it `companion eval --methods all`?)"
        )
    doc = json.loads(path.read_text())
    if isinstance(doc, list):  # a simulated world: one row per method
        row = next((r for r in doc if r.get("method") == method), None)
        col = 0
    else:  # no world: the methods' accuracy rows
        row = next((r for r in doc.get("methods", []) if r.get("method") == method), None)
        col = 1
    out: dict[str, float | None] = {}
    for name, keys in METRICS.items():
        key = keys[col]
        value = None if row is None or key is None else row.get(key)
        if isinstance(value, int | float) and math.isfinite(value):
            out[name] = float(value)
        else:
            out[name] = None
    return out


@dataclass(frozen=True)
class SweepRow:
    """One point on one input, with its metrics (``error``: why it has none)."""

    input: str
    point: tuple[Override, ...]
    metrics: dict[str, float | None]
    error: str = ""


def sort_rows(rows: list[SweepRow], metric: str) -> list[SweepRow]:
    """By ``metric``, lowest first; rows without it (failed, unavailable) last."""
    return sorted(rows, key=lambda r: (r.metrics.get(metric) is None, r.metrics.get(metric) or 0))


def table(rows: Sequence[SweepRow], grids: Sequence[Grid], metric: str) -> str:
    """The sweep as a Markdown table, sorted by ``metric``."""
    others = [m for m in METRICS if m != metric]
    head = ["rank", "input", *(g.key for g in grids), f"**{metric}**", *others]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for i, r in enumerate(sort_rows(list(rows), metric), 1):
        values = dict(r.point)
        cells = [str(i), r.input, *(str(values[g.key]) for g in grids)]
        if r.error:
            cells += [f"failed: {r.error}"] + [""] * len(others)
        else:
            cells += [_fmt(r.metrics.get(metric)), *(_fmt(r.metrics.get(m)) for m in others)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.4g}"
