"""The figures both closed loops share (``companion sitl px4`` and ``companion sitl ardupilot``:
sitl/loops/px4_results.py, sitl/loops/ardupilot_results.py), from the truth the bridge logged
(``truth.csv``: t_ns, NED position [m], attitude wxyz, NED velocity [m/s]; our monotonic clock),
the ground station's telemetry, the service's exit report and the bridge's stats.

Times are [ns] of our monotonic clock, positions NED [m]; ``s`` is the summary being filled.
"""

from __future__ import annotations

import datetime
import json
from pathlib import Path
from typing import Any

import numpy as np


def percentile(a: np.ndarray, q: float) -> float | None:
    """The q-th percentile of ``a``; None when ``a`` is empty."""
    return float(np.percentile(a, q)) if len(a) else None


def clock_line(lp: np.ndarray) -> np.ndarray:
    """The autopilot's clock -> ours, (offset [ns], rate), from LOCAL_POSITION_NED rows
    (arrival [ns, ours], time_boot_ms, x, y, z): a line through the smallest arrival delay of
    every 2 s (arrival = autopilot time + delay >= 0); (0, 1) with 10 rows or fewer."""
    # a simulator's lockstep clock drifts against ours (SIH's by ~1 ms/s)
    clock = np.array([0.0, 1.0])
    if len(lp) > 10:
        bins = ((lp[:, 0] - lp[0, 0]) // 2e9).astype(int)
        pts = [
            lp[bins == b][np.argmin(lp[bins == b, 0] - lp[bins == b, 1] * 1e6)]
            for b in np.unique(bins)
        ]
        env = np.array(pts)
        if len(env) >= 3:
            clock = np.polyfit(env[:, 1] * 1e6, env[:, 0], 1)[::-1]
        else:
            clock = np.array([float(np.min(lp[:, 0] - lp[:, 1] * 1e6)), 1.0])
    return clock


def read_truth(s: dict[str, Any], out: Path, lp: np.ndarray, autopilot: str) -> np.ndarray | None:
    """The rows of OUT/truth.csv (N, 11); None, with ``landed`` False and ``error`` in ``s``,
    without the file or with fewer than 10 of the ``autopilot``'s positions ``lp`` (the flight
    did not run)."""
    truth_path = out / "truth.csv"
    if not truth_path.exists() or len(lp) < 10:
        s["landed"] = False
        s["error"] = f"no truth or no {autopilot} position: the flight did not run"
        return None
    return np.loadtxt(truth_path, delimiter=",", skiprows=1, ndmin=2)


def truth_at(t: np.ndarray, t_tr: np.ndarray, p_tr: np.ndarray) -> np.ndarray:
    """The truth's position (N, 3) at the times ``t`` (N,), linearly interpolated."""
    return np.column_stack([np.interp(t, t_tr, p_tr[:, i]) for i in range(3)])


def touchdown(t_tr: np.ndarray, p_tr: np.ndarray, after: Any, air_t1: Any, level_m: float) -> Any:
    """The first time after ``after`` at which the truth is back within ``level_m`` of the
    home level (up is -z), or ``air_t1`` (the autopilot's landing) if that is earlier."""
    down = np.flatnonzero((t_tr > after) & (p_tr[:, 2] >= -level_m))
    return min(air_t1, t_tr[down[0]]) if len(down) else air_t1


def segment_errors(
    s: dict[str, Any], est: np.ndarray, gt: np.ndarray, seg: np.ndarray
) -> np.ndarray:
    """The estimate ``est`` (N, 3) against the truth ``gt`` (N, 3), each stretch of equal
    ``seg`` (N,: between position resets) after its own translation (the median difference;
    stretches of fewer than 10 samples are left out, and so are samples with a NaN in either:
    one such sample made a whole stretch's median NaN): ``horizontal_error_m_p95``,
    ``vertical_error_m_p95`` and ``horizontal_error_m_max`` into ``s``. Beside them the same
    p95s after one translation for the whole flight (``*_one_translation``): a reset that
    restarts the autopilot's fusion leaves our frame where it was, and a stretch's own offset
    would take the drift before it out of the figure (docs/RESULTS.md, "2026-11-27 (d7a0c08)").
    Returns the longest stretch's translation (3,) (zeros if none)."""
    err = np.full_like(est, np.nan)
    offset = np.zeros(3)
    best = 0
    finite = np.all(np.isfinite(est), axis=1) & np.all(np.isfinite(gt), axis=1)
    for value in np.unique(seg):
        k = (seg == value) & finite
        if k.sum() >= 10:
            off = np.median(gt[k] - est[k], axis=0)
            err[k] = est[k] + off - gt[k]
            if k.sum() > best:
                best, offset = int(k.sum()), off
    used = np.all(np.isfinite(err), axis=1)
    err = err[used]
    h_err = np.linalg.norm(err[:, :2], axis=1)
    s["horizontal_error_m_p95"] = percentile(h_err, 95)
    s["vertical_error_m_p95"] = percentile(np.abs(err[:, 2]), 95)
    s["horizontal_error_m_max"] = float(h_err.max()) if len(h_err) else None
    one = est[used] + np.median(gt[used] - est[used], axis=0) - gt[used] if used.any() else err
    s["horizontal_error_m_p95_one_translation"] = percentile(np.linalg.norm(one[:, :2], axis=1), 95)
    s["vertical_error_m_p95_one_translation"] = percentile(np.abs(one[:, 2]), 95)
    return offset


def path_and_landing(
    s: dict[str, Any], flight: Any, ok: bool, tr: np.ndarray, air_t0: Any, air_t1: Any
) -> None:
    """The flown path, the error relative to it, where the vehicle came down and whether it
    landed, into ``s`` (``tr``: the rows of truth.csv)."""
    t_tr, p_tr = tr[:, 0], tr[:, 1:4]
    air = (t_tr >= air_t0) & (t_tr <= air_t1)
    path = (
        float(np.sum(np.linalg.norm(np.diff(p_tr[air], axis=0), axis=1))) if air.sum() > 1 else 0.0
    )
    s["path_m"] = path
    s["horizontal_error_pct_of_path"] = (
        100.0 * s["horizontal_error_m_p95"] / path if path and s["horizontal_error_m_p95"] else None
    )
    final = p_tr[-1]
    s["landing_error_m"] = float(np.linalg.norm(final[:2]))
    s["final_altitude_m"] = float(-final[2])
    phases = flight.tel.phases
    start_t = phases.get("mission " + flight.o.mission, phases.get("hover"))
    if start_t is not None:
        p_start = np.array([np.interp(start_t * 1e9, t_tr, p_tr[:, i]) for i in range(3)])
        s["landing_error_from_mission_start_m"] = float(np.linalg.norm(final[:2] - p_start[:2]))
    # on the ground and disarmed (SIH's vehicle may rest below its start altitude: see
    # px4_bridge.py), not moving
    s["landed"] = bool(ok and not flight.tel.armed and np.linalg.norm(tr[-1, 8:11]) < 0.1)


def camera_and_latency(s: dict[str, Any], out: Path) -> None:
    """Camera frames and latency (the service's exit report, the bridge's stats) into ``s``."""
    rep = read_json(out / "service-report.json")
    br = read_json(out / "bridge-stats.json")
    s["camera_frames_sent"] = br.get("frames_sent")
    s["camera_frames_dropped_by_bridge"] = br.get("frames_dropped")
    s["camera_frames_dropped_by_service"] = find_key(rep, "frames_dropped")
    s["camera_frames_dropped"] = (br.get("frames_dropped") or 0) + (
        find_key(rep, "frames_dropped") or 0
    )
    s["render_ms_p50"] = br.get("render_ms_p50")
    s["render_ms_p99"] = br.get("render_ms_p99")
    s["truth_rate_hz"] = br.get("truth_rate_hz")
    s["latency_ms_p50"] = find_key(rep, "latency_ms_p50")
    s["latency_ms_p99"] = find_key(rep, "latency_ms_p99")
    s["service_poses_sent"] = find_key(rep, "published")


def read_json(path: Path) -> dict[str, Any]:
    """A JSON object from ``path``; {} when missing, unreadable or not an object."""
    try:
        data = json.loads(path.read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def find_key(d: Any, key: str) -> Any:
    """The first value of ``key`` anywhere in a nested dict (the report's layout may change)."""
    if isinstance(d, dict):
        if key in d:
            return d[key]
        for v in d.values():
            got = find_key(v, key)
            if got is not None:
                return got
    return None


def plot_top(
    a: Any,
    p_tr: np.ndarray,
    p_est: np.ndarray,
    labels: tuple[str, str],
    title: str,
    ours: tuple[str, np.ndarray] | None = None,
) -> None:
    """Top view on the matplotlib axes ``a``: the truth (black), the autopilot's estimate
    (blue), and ``ours`` (label, positions; red dots) if given. ``labels``: truth, estimate."""
    a.plot(p_tr[:, 1], p_tr[:, 0], "k-", lw=1.6, label=labels[0])
    a.plot(p_est[:, 1], p_est[:, 0], "b-", lw=0.9, label=labels[1])
    if ours is not None:
        a.plot(ours[1][:, 1], ours[1][:, 0], "r.", ms=1, label=ours[0])
    a.set_xlabel("east [m]")
    a.set_ylabel("north [m]")
    a.axis("equal")
    a.legend(fontsize=8)
    a.set_title(title)


def plot_side(
    a: Any,
    t0: float,
    truth: tuple[np.ndarray, np.ndarray],
    est: tuple[str, np.ndarray, np.ndarray],
    axis_labels: tuple[str, str],
    ours: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """Height over time [s since ``t0``] on the matplotlib axes ``a``: the truth (times,
    positions; black), the estimate (label, times, positions; blue) and ``ours`` (times,
    positions; red dots) if given. ``axis_labels``: x, y."""
    a.plot((truth[0] - t0) * 1e-9, -truth[1][:, 2], "k-", lw=1.6, label="truth")
    a.plot((est[1] - t0) * 1e-9, -est[2][:, 2], "b-", lw=0.9, label=est[0])
    if ours is not None:
        a.plot((ours[0] - t0) * 1e-9, -ours[1][:, 2], "r.", ms=1, label="ours")
    a.set_xlabel(axis_labels[0])
    a.set_ylabel(axis_labels[1])
    a.legend(fontsize=8)
    a.set_title("side")


def service_log_lines(log: Path, needle: str) -> list[tuple[str, float]]:
    """The lines of the service's log holding ``needle``, each with its wall-clock stamp [s]
    (the log's "%Y-%m-%d %H:%M:%S,%f" prefix); none when the log is absent, a line without a
    readable stamp skipped."""
    if not log.is_file():
        return []
    out = []
    for line in log.read_text(errors="replace").splitlines():
        if needle not in line:
            continue
        try:
            wall = datetime.datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f").timestamp()
        except ValueError:
            continue
        out.append((line, wall))
    return out
