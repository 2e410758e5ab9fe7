"""``companion eval --phases``: what the autopilot would receive over a simulated flight,
by flight phase (issue 18: from the ground up). Run from ``companion.offline.run_published``,
metrics from ``companion.evaluation.phases``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.cli import sim
from companion.cli.common import EXIT_OK, load, out_dir, progress, run_name
from companion.errors import CompanionError

if TYPE_CHECKING:
    from companion.offline import PublishedRun
from companion.evaluation.phases import (
    MIN_PATH_FOR_PCT_M,
    by_phase,
    flight_ate,
    phase_labels,
    published_errors,
    relative_errors,
)
from companion.evaluation.trajectory import path_length


def eval_phases(args: argparse.Namespace) -> int:
    """First published pose, VO resets, whole-flight metric ATE and the error per phase."""
    from companion.offline import run_published

    cfg = load(args)
    name = run_name(cfg.sitl)
    out = out_dir(args, Path("out") / "eval" / f"{name}-phases")
    sc = sim.scenario(cfg)
    with progress(sc.n_frames, f"phases {name}", not args.no_progress) as ticks:
        run = run_published(cfg, sc.steps(), sc.world, ticks)
    if len(run.time_s) < 10:
        raise CompanionError(f"fewer than 10 poses published over {name}")
    t, est, gt = run.array("time_s"), run.array("position"), run.array("truth")
    err = published_errors(est, gt)
    phases = by_phase(err, phase_labels(t, run.array("height_m")))
    ate_m, ate_pct = flight_ate(est, gt)
    path_m = path_length(gt)
    summary: dict[str, Any] = {
        "flight": name,
        "first_pose_s": float(t[0]),
        "vo_resets": run.vo_resets,
        "reset_counters": sorted(set(run.reset_counter)),
        "published": len(t),
        "frames": run.frames,
        "ate_m": ate_m,
        "ate_pct_of_path": ate_pct if np.isfinite(ate_pct) else None,  # JSON has no NaN
        "path_m": path_m,
        "end_error_m": float(err[-1]),
        "phases": {
            p.phase: {"frames": p.frames, "rmse_m": p.rmse_m, "max_m": p.max_m} for p in phases
        },
    }
    if run.dpose_armed_s is not None:
        summary["dpose"] = _dpose_summary(run, out)
    (out / "phases.json").write_text(json.dumps(summary, indent=2) + "\n")
    rows = [
        f"| {p.phase} | {p.frames} | {100 * p.rmse_m:.1f} | {100 * p.max_m:.1f} |"
        for p in phases
        if p.frames
    ]
    pct = (
        f"{ate_pct:.3f} % of the path"
        if np.isfinite(ate_pct)
        else f"no % of a {path_m:.2f} m path (under {MIN_PATH_FOR_PCT_M:g} m)"
    )
    print(
        f"{name}: first pose {t[0]:.2f} s, VO resets {run.vo_resets}, metric ATE "
        f"{ate_m:.3f} m = {pct}, end error {100 * err[-1]:.1f} cm"
    )
    print("\n".join(["| phase | poses | RMSE [cm] | max [cm] |", "|---|---|---|---|", *rows]))
    if "dpose" in summary:
        d = summary["dpose"]
        print(
            f"d-Pose armed at {d['armed_s']:.2f} s, used on {d['poses_in_view']} poses back over "
            f"the marks: error from the arming pose RMS {100 * d['published_rmse_m']:.2f} cm, "
            f"max {100 * d['published_max_m']:.2f} cm (the VO alone: RMS "
            f"{100 * d['vo_rmse_m']:.2f} cm); plot {d['plot']}"
        )
    print(f"phases.json in {out}")
    return EXIT_OK


def _dpose_summary(run: PublishedRun, out: Path) -> dict[str, Any]:
    """Back over the marks: the published position and the VO's own, both from the arming
    pose (the marks' reference), against the truth; and the plot of both over time."""
    from companion.reporting import write_dpose_return

    t, gt = run.array("time_s"), run.array("truth")
    assert run.dpose_armed_s is not None
    i = int(np.searchsorted(t, run.dpose_armed_s))
    back = np.array(run.dpose_used) & (t > t[i] + 1.0)
    e_pub = relative_errors(run.array("position"), gt, i)
    e_own = relative_errors(run.array("vo_own"), gt, i)
    plot = write_dpose_return(t, e_pub, e_own, back, out / "dpose_return.png")
    return {
        "armed_s": float(t[i]),
        "poses_in_view": int(back.sum()),
        "published_rmse_m": float(np.sqrt(np.mean(e_pub[back] ** 2))) if back.any() else None,
        "published_max_m": float(e_pub[back].max()) if back.any() else None,
        "vo_rmse_m": float(np.sqrt(np.mean(e_own[back] ** 2))) if back.any() else None,
        "plot": str(plot),
    }
