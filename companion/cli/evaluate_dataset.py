"""``companion eval DIR`` on datasets that are not a simulated flight: the config a dataset runs
with (its own calibration and declared sensors, nothing invented), the replay check of a
flight recording (``companion run --record``), and the scale methods side by side on a dataset
without a simulated world (``--methods all``). Nothing here reaches the simulator: a dataset
that declares no world is evaluated without one (tests/companion/evaluation/test_evaluation.py
checks that ``sitl`` is never imported).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from companion.cli.common import EXIT_OK, out_dir, progress
from companion.config import Config, load_config
from companion.drivers.dataset import Dataset, PublishedPose, dataset_steps, write_tum
from companion.errors import CompanionError
from companion.evaluation.tables import markdown_table
from companion.geometry import so3
from companion.types import PoseEstimate
from companion.vo.focal_check import focal_summary

NO_RANGES = "the dataset has no distance sensors (ranges.csv): no metric scale"


def dataset_config(ds: Dataset, config_path: Path | None) -> Config:
    """The config a dataset runs with: a dataset of ours brings its own (its calibration, the
    sensors it declares, and a recording's algorithm options); another (EuRoC) takes the
    algorithm options of ``--config`` (or the built-in one) with no distance sensors, since
    it declares none. The camera model and T_body_cam always come from ``ds``."""
    if ds.config is not None:
        return ds.config
    cfg = load_config(config_path)
    return dataclasses.replace(
        cfg, rangefinders=(), attitude=dataclasses.replace(cfg.attitude, sensor_ids=())
    )


def report_skipped(ds: Dataset, out: Path) -> None:
    """The rows the reader left out (a word or NaN in a number, a zero quaternion, a short
    row): one warning per file on stderr and their counts in ``out/skipped_rows.json``
    (nothing when none was)."""
    if not ds.skipped:
        return
    for line in ds.skipped_text():
        print(f"companion: warning: {line}", file=sys.stderr)
    counts = {name: {"skipped": c.skipped, "first": c.first} for name, c in ds.skipped.items()}
    (out / "skipped_rows.json").write_text(json.dumps(counts, indent=2) + "\n")


def _max_diff(a: np.ndarray, b: np.ndarray) -> float:
    """Largest |a - b|; NaN against NaN (unknown on both sides) agrees, NaN against a number
    does not (inf)."""
    both = np.isnan(a) & np.isnan(b)
    d = np.where(both, 0.0, np.abs(a - b))
    return float(np.nan_to_num(d, nan=np.inf).max())


def _quat_angle_rad(q_a: np.ndarray, q_b: np.ndarray) -> float:
    """The rotation angle between two unit quaternions (wxyz; q and -q are the same)."""
    return float(2.0 * np.arccos(min(1.0, abs(float(np.dot(q_a, q_b))))))


def replay_check(
    published: Sequence[PublishedPose], poses: Sequence[PoseEstimate]
) -> dict[str, Any]:
    """The replayed poses against the ones the service sent, matched by frame time: how many
    match, and the largest position [m], orientation [rad] and velocity [m/s] differences.
    (reset_counter is not compared: the service sends a counter that continues across its
    restarts, the replay starts at 0.)"""
    by_time = {p.time_us: p for p in poses}
    pos, ang, vel = [0.0], [0.0], [0.0]
    missing = 0
    for sent in published:
        mine = by_time.get(sent.time_us)
        if mine is None:
            missing += 1
            continue
        pos.append(_max_diff(mine.position_ned_m, sent.position_ned_m))
        ang.append(_quat_angle_rad(mine.quat_wxyz_ned_frd, sent.quat_wxyz))
        vel.append(_max_diff(mine.velocity_ned_m_s, sent.velocity_ned_m_s))
    return {
        "published": len(published),
        "replayed": len(poses),
        "matched": len(published) - missing,
        "missing": missing,
        "max_position_diff_m": max(pos),
        "max_angle_diff_rad": max(ang),
        "max_velocity_diff_m_s": max(vel),
    }


def write_replay(ds: Dataset, poses: Sequence[PoseEstimate], out: Path) -> str | None:
    """A recording's replay against its published.csv: replay.json; returns the line to
    print (None when the dataset has no published poses)."""
    if not ds.published:
        return None
    check = replay_check(ds.published, poses)
    (out / "replay.json").write_text(json.dumps(check, indent=2) + "\n")
    return (
        f"replay vs the flight: {check['matched']} of {check['published']} published poses "
        f"replayed, max |dposition| {check['max_position_diff_m']:.3g} m, max angle "
        f"{check['max_angle_diff_rad']:.3g} rad"
        + (
            " (the recording did not close: read to its last complete frame)"
            if not ds.complete
            else ""
        )
    )


# ------------------------------------------------------------------------------ no world
def eval_scale_no_world(args: argparse.Namespace, ds: Dataset, config_path: Path | None) -> int:
    """Every scale method on a dataset without a simulated world: metric (SE3) and Sim(3) ATE
    against its ground truth side by side; the figures that need a true scale unavailable."""
    from companion.evaluation.methods import MethodAccuracy, trajectory_accuracy
    from companion.evaluation.vo import vo_metrics
    from companion.offline import run_scale

    cfg = dataset_config(ds, config_path)
    study = 6 if args.sensor_study else 0
    if study and len(cfg.rangefinders) < study:
        raise CompanionError("--sensor-study needs a recording with six distance sensors")
    name = ds.path.name
    out = out_dir(args, Path("out") / "eval" / name)
    report_skipped(ds, out)
    with progress(len(ds), f"eval {name}", not args.no_progress) as ticks:
        run = run_scale(
            cfg,
            dataset_steps(ds),
            None,
            ticks,
            sensor_study=study,
            camera=ds.camera,
            T_body_cam=ds.T_body_cam,
        )
    t = np.array(run.time_us) * 1e-6
    tracking = np.array(run.tracking, dtype=bool)
    gt = np.array(run.gt_position).reshape(-1, 3)
    missing = NO_RANGES if not ds.ranges else ""
    rows: list[MethodAccuracy] = []
    if tracking.any():
        init = float(t[np.argmax(tracking)])
        R = so3.rot_z(run.yaw_vo_rad)
        rows = [
            trajectory_accuracy(
                n, t, np.array(run.position[n]).reshape(-1, 3), gt, R, init, missing=missing
            )
            for n in run.methods
        ]
    vo = None
    if tracking.any() and ds.has_ground_truth:
        vo = vo_metrics(
            run.time_us,
            tracking,
            run.segment,
            run.resets,
            np.array(run.vo_position).reshape(-1, 3),
            np.array(run.gt_cam_position).reshape(-1, 3),
        )
    table = _write_no_world(rows, vo, run, ds, out)
    print(table)
    print(f"VO resets: {run.resets}")
    print(focal_summary(run.lens_focal, run.lens_warning))
    print(f"tables and TUM trajectories in {out}")
    return EXIT_OK


def _fmt(v: float | None, unit: str, digits: int) -> str:
    return "unavailable" if v is None else f"{v:.{digits}f}{unit}"


def _write_no_world(rows: list[Any], vo: Any, run: Any, ds: Dataset, out: Path) -> str:
    """scale_metrics.json, report.md and the TUM trajectories of a no-world evaluation."""
    doc = {
        "dataset": str(ds.path),
        "world": None,
        "ground_truth": ds.has_ground_truth,
        "distance_sensors": [r.sensor_id for r in ds.rangefinders],
        "methods": [dataclasses.asdict(r) for r in rows],
        "vo": None if vo is None else {k: getattr(vo, k) for k in vo.__slots__},
    }
    (out / "scale_metrics.json").write_text(json.dumps(doc, indent=2) + "\n")
    header = ["method", "frames", "metric ATE (SE3)", "ATE % path", "Sim(3) ATE"]
    header += ["Sim(3) scale", "final error", "scale MSE"]
    metrics = markdown_table(
        header,
        (
            [
                r.method,
                str(r.frames),
                _fmt(r.ate_se3_m, " m", 3),
                _fmt(r.ate_se3_pct, " %", 2),
                _fmt(r.ate_sim3_m, " m", 3),
                _fmt(r.sim3_scale, "", 4),
                _fmt(r.final_error_m, " m", 2),
                _fmt(r.scale_mse, "", 2),
            ]
            for r in rows
        ),
    )
    reasons = sorted({why for r in rows for why in r.unavailable.values()})
    notes = [f"- unavailable: {why}" for why in reasons]
    if vo is not None:
        notes.append(
            f"- raw VO (unscaled), longest segment ({vo.segment_frames} frames): Sim(3) ATE "
            f"{vo.ate_sim3_m:.3f} m ({vo.ate_sim3_pct:.2f} % of {vo.path_m:.1f} m)"
        )
    if not rows:
        notes.append("- the VO never tracked: no method has an estimate")
    table = "\n".join([metrics, "", *notes])
    (out / "report.md").write_text(f"# Metric scale on {ds.path.name} (no world)\n\n{table}\n")
    from companion.evaluation.trajectory import poses_from_positions

    t = np.array(run.time_us) * 1e-6
    if ds.has_ground_truth:
        gt = np.array(run.gt_position).reshape(-1, 3)
        write_tum(out / "groundtruth.tum", t, poses_from_positions(gt))
    for n in run.methods:
        p = np.array(run.position[n]).reshape(-1, 3)
        ok = np.all(np.isfinite(p), axis=1)
        name = n.replace(" ", "_").replace("=", "")
        write_tum(out / f"{name}.tum", t[ok], poses_from_positions(p[ok]))
    return table
