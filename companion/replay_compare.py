"""``companion compare A.json B.json``: what changed between two replays (``companion
replay``'s files), per recording and in total, each metric with a verdict.

Recordings are matched by their id (``companion.replay.recording_id``: the SHA-256 of their
frame times, so a folder moved or copied still matches), else by the path given. Every
metric has a direction and a tolerance (:data:`METRICS`): within the tolerance the verdict is
``same``; beyond it ``better`` or ``worse`` by the direction, or ``changed`` for a metric with
none (the frames, the difference from what was published: a new setting is meant to change
the poses). The tolerance is the larger of an absolute one and a relative one (of A's value):
a replay is deterministic, so the poses, the resets and the ATE change only when the code or
the options do, and their tolerances are tiny; the time to the pose over the KLT floor of
``companion bench vo`` (within 10 %) has no direction, as its floor tracks the features the
options ask for (fewer features: a lower floor, a higher ratio, less CPU); the CPU per frame
is measured on a machine that also runs other work, so its median and 95th percentile within
10 % (its 99th percentile and maximum, a handful of frames, within 25 %) are ``same``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from companion.bounded import read_regular_file
from companion.errors import ConfigError
from companion.toml_files import decode_utf8

Direction = Literal["lower", "higher", "none"]
MAX_REPLAY_BYTES = 64 << 20  # a replay file holds a few kB per recording


@dataclass(frozen=True, slots=True)
class MetricRule:
    """How a metric is judged: which way is better ("none": no better or worse, only
    changed), and the tolerance below which a difference is ``same``: max(abs_tol,
    rel_tol * |A|)."""

    direction: Direction
    abs_tol: float = 0.0
    rel_tol: float = 0.0


_CPU = MetricRule("lower", 0.05, 0.10)
_CPU_TAIL = MetricRule("lower", 0.05, 0.25)
_EXACT = MetricRule("none")
_POSE_DIFF = MetricRule("none", 1e-12)

# the metrics of a recording in the order they are printed
METRICS: dict[str, MetricRule] = {
    "frames": _EXACT,
    "frames_replayed": _EXACT,
    "poses": MetricRule("higher"),
    "tracked_fraction": MetricRule("higher", 0.002),
    "vo_resets": MetricRule("lower"),
    "reset_counter_steps": MetricRule("lower"),
    "pipeline_errors": MetricRule("lower"),
    "cpu_ms_median": _CPU,
    "cpu_ms_p95": _CPU,
    "cpu_ms_p99": _CPU_TAIL,
    "cpu_ms_max": _CPU_TAIL,
    "cpu_ms_mean": _CPU,
    "frame_to_floor": MetricRule("none", 0.0, 0.10),  # its floor follows the feature count
    "published_matched": _EXACT,
    "published_missing": _EXACT,
    "position_diff_max_m": _POSE_DIFF,
    "position_diff_p95_m": _POSE_DIFF,
    "yaw_diff_max_deg": _POSE_DIFF,
    "angle_diff_max_deg": _POSE_DIFF,
    "identical": _EXACT,
    "ate_m": MetricRule("lower", 1e-4, 0.01),
    "ate_pct_path": MetricRule("lower", 1e-3, 0.01),
    "ate_to_best_constant": MetricRule("lower", 1e-4, 0.01),
}

# the totals over the recordings replayed in both files
TOTALS: dict[str, MetricRule] = {
    "recordings": _EXACT,
    "failed": MetricRule("lower"),
    "frames": _EXACT,
    "poses": MetricRule("higher"),
    "tracked_fraction": MetricRule("higher", 0.002),
    "vo_resets": MetricRule("lower"),
    "pipeline_errors": MetricRule("lower"),
    "cpu_ms_mean": _CPU,
    "identical": _EXACT,
    "ate_m_mean": MetricRule("lower", 1e-4, 0.01),
}


def verdict(rule: MetricRule, a: Any, b: Any) -> str:
    """``same``, ``better``, ``worse`` or ``changed`` for a metric going from ``a`` to ``b``;
    ``new`` / ``gone`` when only one side has a value (None: the recording could not say)."""
    if a is None and b is None:
        return "same"
    if a is None:
        return "new"
    if b is None:
        return "gone"
    if isinstance(a, bool) or isinstance(b, bool) or (rule.direction == "none" and a == b):
        return "same" if a == b else "changed"
    diff = float(b) - float(a)
    if abs(diff) <= max(rule.abs_tol, rule.rel_tol * abs(float(a))):
        return "same"
    if rule.direction == "none":
        return "changed"
    return "better" if (diff < 0) == (rule.direction == "lower") else "worse"


def _row(name: str, rule: MetricRule, a: Any, b: Any) -> dict[str, Any]:
    numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (a, b))
    diff = float(b) - float(a) if numeric else None
    return {
        "metric": name,
        "a": a,
        "b": b,
        "diff": diff if diff is None or math.isfinite(diff) else None,
        "verdict": verdict(rule, a, b),
    }


def read_replay(path: Path) -> dict[str, Any]:
    """A replay file (``companion replay --json``); ConfigError naming the file when it is
    not one (exit 2)."""
    raw = read_regular_file(Path(path), MAX_REPLAY_BYTES, ConfigError)
    try:
        doc = json.loads(decode_utf8(raw, str(path)))
    except ValueError as e:
        raise ConfigError(f"{path}: not JSON ({e})") from None
    if not isinstance(doc, dict) or doc.get("format") != "companion-replay":
        raise ConfigError(f"{path}: not a replay file (format != 'companion-replay')")
    recordings = doc.get("recordings")
    if not isinstance(recordings, list) or not all(
        isinstance(r, dict) and isinstance(r.get("path"), str) for r in recordings
    ):
        raise ConfigError(f"{path}: recordings: expected a list of objects with a path")
    for i, r in enumerate(recordings):
        if "error" not in r and not isinstance(r.get("metrics"), dict):
            raise ConfigError(f"{path}: recordings[{i}].metrics: expected an object")
    return doc


def _key(entry: dict[str, Any]) -> str:
    return f"id:{entry['id']}" if isinstance(entry.get("id"), str) else f"path:{entry['path']}"


def _match(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> list[tuple[Any, Any]]:
    """Pairs (A's entry or None, B's entry or None): by id, else by path, in A's order then
    B's remaining ones."""
    b_left = list(b)
    pairs: list[tuple[Any, Any]] = []
    for ea in a:
        mate = next((eb for eb in b_left if _key(eb) == _key(ea)), None)
        if mate is None:
            mate = next((eb for eb in b_left if eb["path"] == ea["path"]), None)
        if mate is not None:
            b_left.remove(mate)
        pairs.append((ea, mate))
    return pairs + [(None, eb) for eb in b_left]


def _totals(entries: list[dict[str, Any]]) -> dict[str, Any]:
    """Sums over the replayed entries (a frame-weighted tracked fraction and CPU mean; the
    mean ATE over those with ground truth)."""
    ok = [e["metrics"] for e in entries if "error" not in e]
    frames = sum(int(m.get("frames") or 0) for m in ok)
    cpu = [(m["cpu_ms_mean"], m.get("frames_replayed") or 0) for m in ok if m.get("cpu_ms_mean")]
    cpu_frames = sum(n for _, n in cpu)
    ates = [m["ate_m"] for m in ok if m.get("ate_m") is not None]
    flags = [m["identical"] for m in ok if m.get("identical") is not None]
    return {
        "recordings": len(entries),
        "failed": len(entries) - len(ok),
        "frames": frames,
        "poses": sum(int(m.get("poses") or 0) for m in ok),
        "tracked_fraction": sum((m.get("tracked_fraction") or 0.0) * m["frames"] for m in ok)
        / frames
        if frames
        else None,
        "vo_resets": sum(int(m.get("vo_resets") or 0) for m in ok),
        "pipeline_errors": sum(int(m.get("pipeline_errors") or 0) for m in ok),
        "cpu_ms_mean": sum(c * n for c, n in cpu) / cpu_frames if cpu_frames else None,
        "identical": all(flags) if flags else None,
        "ate_m_mean": sum(ates) / len(ates) if ates else None,
    }


def compare(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """Two replay documents compared: per recording (matched by id, else path) its rows
    ``{metric, a, b, diff, verdict}`` (or, for one that failed or is in one file only, what
    happened), the totals over the recordings replayed in both, and the count of each
    verdict."""
    recordings: list[dict[str, Any]] = []
    both_a: list[dict[str, Any]] = []
    both_b: list[dict[str, Any]] = []
    for ea, eb in _match(a["recordings"], b["recordings"]):
        entry = ea if ea is not None else eb
        out: dict[str, Any] = {"name": entry.get("name", entry["path"]), "key": _key(entry)}
        out["path_a"], out["path_b"] = (e["path"] if e else None for e in (ea, eb))
        if ea is None or eb is None:
            out["status"] = "only in A" if eb is None else "only in B"
        elif "error" in ea or "error" in eb:
            out["status"] = "failed"
            out["error_a"], out["error_b"] = ea.get("error"), eb.get("error")
            verdict_word = "same" if ("error" in ea) == ("error" in eb) else None
            if verdict_word is None:
                verdict_word = "worse" if "error" in eb else "better"
            out["verdict"] = verdict_word
        else:
            out["status"] = "both"
            ma, mb = ea["metrics"], eb["metrics"]
            names = [n for n in METRICS if n in ma or n in mb]
            out["rows"] = [_row(n, METRICS[n], ma.get(n), mb.get(n)) for n in names]
            both_a.append(ea)
            both_b.append(eb)
        recordings.append(out)
    ta, tb = _totals(both_a), _totals(both_b)
    total_rows = [_row(n, rule, ta[n], tb[n]) for n, rule in TOTALS.items()]
    verdicts = [r["verdict"] for rec in recordings for r in rec.get("rows", [])]
    verdicts += [rec["verdict"] for rec in recordings if "verdict" in rec]
    return {
        "a": _header(a),
        "b": _header(b),
        "recordings": recordings,
        "total": total_rows,
        "counts": {w: verdicts.count(w) for w in sorted(set(verdicts))},
        "worse": verdicts.count("worse") + sum(r["verdict"] == "worse" for r in total_rows),
    }


def _header(doc: dict[str, Any]) -> dict[str, Any]:
    over = doc.get("override")
    return {
        "created": doc.get("created"),
        "software": doc.get("software"),
        "override_sha256": over.get("sha256") if isinstance(over, dict) else None,
    }


def _value(v: Any) -> str:
    if isinstance(v, bool) or v is None or isinstance(v, int):
        return str(v).lower() if isinstance(v, bool) else str(v)
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def _line(row: dict[str, Any]) -> str:
    diff = "" if row["diff"] is None else f" ({row['diff']:+.3g})"
    return f"  {row['metric']}: {_value(row['a'])} -> {_value(row['b'])}{diff} {row['verdict']}"


def compare_text(result: dict[str, Any], show_same: bool = False) -> list[str]:
    """The comparison as lines: the two runs, then per recording the metrics that changed
    (all with ``show_same``) or that all are the same, then the totals."""
    lines = []
    for side in ("a", "b"):
        h = result[side]
        sw = h.get("software") or {}
        lines.append(
            f"{side.upper()}: {h.get('created')}, companion {sw.get('version')} "
            f"commit {str(sw.get('commit'))[:12]}{' (modified)' if sw.get('dirty') else ''}, "
            f"override {str(h.get('override_sha256'))[:12] if h.get('override_sha256') else 'none'}"
        )
    for rec in result["recordings"]:
        if rec["status"] != "both":
            detail = ""
            if rec["status"] == "failed":
                detail = (
                    f": A {rec['error_a'] or 'ok'}; B {rec['error_b'] or 'ok'} {rec['verdict']}"
                )
            lines.append(f"{rec['name']} ({rec['key']}): {rec['status']}{detail}")
            continue
        shown = [r for r in rec["rows"] if show_same or r["verdict"] != "same"]
        same = len(rec["rows"]) - len(shown)
        head = f"{rec['name']} ({rec['key']}):"
        lines.append(head + (f" all {same} metrics the same" if not shown else ""))
        lines += [_line(r) for r in shown]
        if shown and same:
            lines.append(f"  ({same} other metrics the same)")
    lines.append("total (the recordings replayed in both):")
    lines += [_line(r) for r in result["total"]]
    counts = ", ".join(f"{n} {w}" for w, n in result["counts"].items()) or "nothing compared"
    lines.append(f"verdicts: {counts}")
    return lines
