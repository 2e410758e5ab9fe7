"""The "Real sequences" table: one row per `companion eval DIR --methods all` of a dataset
without a simulated world (its ``scale_metrics.json`` document), the published method beside
the raw VO, a constant position and the best of the baselines.

Columns: frames; the share tracked after the VO's first pose and its resets; the raw VO's
Sim(3) ATE over its longest segment (% of that segment's path); the published method's metric
ATE after an SE(3) alignment (m, % of path, frames scored: from 5 s after the VO's first pose),
its ratio to the best constant position (the mean true position: 1 = no better than standing
still) and the scale a Sim(3) alignment would still apply (1 = metric); the best baseline
(B7/B8/B9) by metric ATE; and whether the published method beats every baseline.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from companion.evaluation.tables import markdown_table

BASELINES = ("B7 window-ML", "B8 per-frame", "B9 plane")
HEADER = [
    "sequence",
    "frames",
    "tracked after start",
    "resets",
    "raw VO Sim(3) ATE (longest segment)",
    "{m} metric ATE",
    "{m} / best constant",
    "{m} Sim(3) scale",
    "best baseline",
    "beats B7, B8, B9",
]


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f} %"


def real_row(name: str, doc: dict[str, Any], method: str = "M-MSCwK") -> list[str]:
    """The table row of sequence ``name`` from its no-world scale_metrics.json ``doc``."""
    vo = doc.get("vo") or {}
    methods = {m["method"]: m for m in doc.get("methods", [])}
    tracks = doc.get("tracks") or {}
    ours = methods.get(method)
    tracked = f"{100 * vo['tracking_ratio']:.1f} %" if vo.get("tracking_ratio") is not None else "-"
    raw = "-"
    if vo.get("ate_sim3_pct") is not None:
        raw = (
            f"{vo['ate_sim3_m']:.3f} m = {vo['ate_sim3_pct']:.2f} % of {vo['path_m']:.2f} m "
            f"({vo['segment_frames']} fr.)"
        )
    ate = ratio = scale = "no estimate"
    if ours is not None and ours.get("ate_se3_m") is not None:
        ate = f"{ours['ate_se3_m']:.3f} m = {_pct(ours['ate_se3_pct'])} ({ours['frames']} fr.)"
        scale = f"{ours['sim3_scale']:.3f}" if ours.get("sim3_scale") is not None else "-"
        t = tracks.get(method) or {}
        ratio = f"{t['ratio_to_mean']:.3f}" if t.get("ratio_to_mean") is not None else "-"
    scored = [
        methods[b] for b in BASELINES if b in methods and methods[b].get("ate_se3_m") is not None
    ]
    best = min(scored, key=lambda m: m["ate_se3_m"]) if scored else None
    best_text = "-" if best is None else f"{best['method']} {best['ate_se3_m']:.3f} m"
    beats = "-"
    if ours is not None and ours.get("ate_se3_m") is not None and scored:
        beats = "yes" if all(ours["ate_se3_m"] < m["ate_se3_m"] for m in scored) else "NO"
    frames = doc.get("frames") or {}
    n_frames = frames.get("frames", vo.get("frames", "-"))
    return [
        name,
        str(n_frames),
        tracked,
        str(vo.get("resets", "-")),
        raw,
        ate,
        ratio,
        scale,
        best_text,
        beats,
    ]


def real_sequences_table(
    docs: Sequence[tuple[str, dict[str, Any]]], method: str = "M-MSCwK"
) -> str:
    """Markdown table over (sequence name, scale_metrics.json document) pairs."""
    header = [h.format(m=method) for h in HEADER]
    return markdown_table(header, (real_row(n, d, method) for n, d in docs))
