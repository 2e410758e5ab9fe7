"""One row per simulated flight over its seeds, from `companion eval --methods all` folders
named NAME-SEED: the simulator's effects one at a time (docs/RESULTS.md, "A simulator as hard
as reality"), or any other set of flights compared on the published method.

A row: the published method's (M-MSCwK) metric ATE as % of the path per seed and their mean,
the VO's resets per seed (eval.json ``vo_resets``; "?" for a folder written before it was
kept), the baselines' mean ATE % of the path, and whether the mean beats each baseline's; a
seed whose VO never gave a pose shows "no pose" and is left out of the means. The detailed
table (``rows_table(..., detail=True)``) adds the tracking, the share of the frames from the
published method's first pose on that have one (its TUM trajectory against groundtruth.tum's
frames), and the published scale's mean error [%].
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from companion.drivers.dataset import read_tum

PUBLISHED = "M-MSCwK"
BASELINES = ("B7 window-ML", "B8 per-frame", "B9 plane")


@dataclass
class FlightRow:
    """One flight over its seeds: ``ate_pct`` [% of path] and ``resets`` by seed (None: not
    recorded), ``baseline_pct``: each baseline's ATE [% of path] by seed."""

    name: str
    seeds: list[int] = field(default_factory=list)
    ate_pct: list[float] = field(default_factory=list)
    resets: list[int | None] = field(default_factory=list)
    baseline_pct: dict[str, list[float]] = field(default_factory=dict)
    tracked: list[float] = field(default_factory=list)  # frames posed from the first pose, 0..1
    scale_err_pct: list[float] = field(default_factory=list)  # published scale's mean error

    @property
    def mean_pct(self) -> float:
        """The mean over the seeds with an estimate (NaN: none has one)."""
        return _mean(self.ate_pct)

    def beats(self, baseline: str) -> bool:
        """Whether the published method's mean ATE is below the baseline's mean."""
        return self.mean_pct < _mean(self.baseline_pct[baseline])


def _mean(values: list[float]) -> float:
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def _pct(value: float) -> str:
    """A percentage of the path, or "no pose" for a flight the VO never tracked."""
    return f"{value:.3f}" if np.isfinite(value) else "no pose"


def name_and_seed(folder: Path) -> tuple[str, int] | None:
    """(NAME, SEED) of a folder named NAME-SEED (SEED an integer), else None."""
    name, _, seed = folder.name.rpartition("-")
    return (name, int(seed)) if name and seed.isdigit() else None


def tracked_share(folder: Path) -> float:
    """The share of the frames from the published method's first pose on that have one: its
    TUM trajectory (one line per pose) against groundtruth.tum (one line per frame); NaN
    without the files, 0 without a pose."""
    pub, truth = folder / f"{PUBLISHED}.tum", folder / "groundtruth.tum"
    if not (pub.exists() and truth.exists()):
        return float("nan")
    poses, frames = read_tum(pub)[0], read_tum(truth)[0]
    if len(poses) == 0:
        return 0.0
    after = int(np.sum(frames >= poses[0] - 1e-6))
    return min(len(poses) / after, 1.0) if after else float("nan")


def read_rows(dirs: list[Path]) -> list[FlightRow]:
    """The rows of the NAME-SEED folders among ``dirs`` that hold a simulated flight's
    scale_metrics.json (a list of methods), in the order of their names' first appearance,
    seeds ascending."""
    rows: dict[str, FlightRow] = {}
    found = []
    for d in dirs:
        key = name_and_seed(d)
        f = d / "scale_metrics.json"
        if key is None or not f.exists():
            continue
        doc = json.loads(f.read_text())
        if not isinstance(doc, list):
            continue  # a real sequence's: no world, another table
        found.append((key, d, {r["method"]: r for r in doc}))
    for (name, seed), d, methods in sorted(found, key=lambda x: x[0][1]):
        row = rows.setdefault(name, FlightRow(name))
        row.seeds.append(seed)
        pub = methods.get(PUBLISHED, {})
        row.ate_pct.append(float(pub.get("ate_pct", "nan")))
        row.scale_err_pct.append(float(pub.get("scale_mean_abs_rel_pct", "nan")))
        honest = d / "eval.json"
        doc = json.loads(honest.read_text()) if honest.exists() else {}
        resets = doc.get("vo_resets")
        row.resets.append(None if resets is None else int(resets))
        row.tracked.append(tracked_share(d))
        for b in BASELINES:
            pct = float(methods[b]["ate_pct"]) if b in methods else float("nan")
            row.baseline_pct.setdefault(b, []).append(pct)
    order = [name_and_seed(d) for d in dirs]
    names = list(dict.fromkeys(k[0] for k in order if k is not None and k[0] in rows))
    return [rows[n] for n in names]


def rows_table(
    rows: list[FlightRow], labels: dict[str, str] | None = None, detail: bool = False
) -> str:
    """Markdown: one line per row, ``labels`` naming a row instead of its folder name;
    ``detail``: with the tracking (the lowest seed's) and the scale's error."""
    labels = labels or {}
    head = (
        f"| flight | seeds | {PUBLISHED} metric ATE, % of path, by seed | mean | VO resets "
        "| B7 / B8 / B9 mean ATE % | better than B7, B8, B9 |"
    )
    if detail:
        head += " tracked after the first pose, lowest seed | scale error, mean |"
    out = [head, "|---" * (9 if detail else 7) + "|"]
    for r in rows:
        per_seed = " / ".join(_pct(v) for v in r.ate_pct)
        resets = " / ".join("?" if n is None else str(n) for n in r.resets)
        base = " / ".join(_pct(_mean(r.baseline_pct[b])) for b in BASELINES)
        beats = ", ".join("yes" if r.beats(b) else "NO" for b in BASELINES)
        seeds = ", ".join(str(s) for s in r.seeds)
        label = labels.get(r.name, r.name)
        line = (
            f"| {label} | {seeds} | {per_seed} | {r.mean_pct:.3f} % | {resets} | {base} | {beats} |"
        )
        if detail:
            tracked = [v for v in r.tracked if np.isfinite(v)]
            line += f" {100 * min(tracked):.1f} % |" if tracked else " ? |"
            line += f" {_mean(r.scale_err_pct):.2f} % |"
        out.append(line)
    return "\n".join(out)
