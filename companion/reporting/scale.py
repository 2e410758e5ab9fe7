"""The VO and metric-scale reports: tables (Markdown, CSV, JSON), trajectories (TUM) and PNG
plots of `companion eval` runs, and the summary over many run folders. Writes files; no
algorithms."""

from __future__ import annotations

import csv
import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from companion.drivers.dataset import write_tum
from companion.evaluation.scale import ScaleMetrics
from companion.evaluation.tables import markdown_table
from companion.evaluation.trajectory import poses_from_positions, umeyama
from companion.evaluation.vo import VoMetrics
from companion.geometry import so3
from companion.offline import ScaleRun
from companion.reporting import figures

COLOURS = {
    "MSC": "tab:blue",
    "MSCwK": "tab:green",
    "M-MSC": "tab:red",
    "M-MSCwK": "tab:brown",
    "B7 window-ML": "tab:gray",
    "B8 per-frame": "tab:orange",
    "B9 plane": "tab:purple",
}
METRIC_COLUMNS = [
    "method",
    "frames",
    "scale_mse",
    "scale_mean_abs_rel_pct",
    "ate_m",
    "ate_pct",
    "final_error_m",
    "path_m",
]


def write_tables(metrics: list[ScaleMetrics], out: Path, title: str) -> str:
    """metrics.csv, metrics.json and report.md in ``out``; returns the Markdown table."""
    rows = [asdict(m) for m in metrics]
    with (out / "scale_metrics.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=METRIC_COLUMNS)
        w.writeheader()
        w.writerows(rows)
    (out / "scale_metrics.json").write_text(json.dumps(rows, indent=2) + "\n")
    header = ["method", "scale MSE", "mean abs rel. scale error", "metric ATE (SE3)"]
    header += ["ATE % path", "final error"]
    table = markdown_table(
        header,
        (
            [
                m.method,
                f"{m.scale_mse:.2e}",
                f"{m.scale_mean_abs_rel_pct:.2f} %",
                f"{m.ate_m:.3f} m",
                f"{m.ate_pct:.2f} %",
                f"{m.final_error_m:.2f} m",
            ]
            for m in metrics
        ),
    )
    (out / "report.md").write_text(f"# {title}\n\n{table}\n")
    return table


def write_trajectories(run: ScaleRun, out: Path) -> None:
    """The true and every method's body positions as TUM files (identity rotations), each
    method's at the frames where it has an estimate."""
    t = np.array(run.time_us) * 1e-6
    write_tum(out / "groundtruth.tum", t, poses_from_positions(np.array(run.gt_position)))
    for n in run.methods:
        p = np.array(run.position[n])
        ok = np.all(np.isfinite(p), axis=1)
        write_tum(
            out / f"{n.replace(' ', '_').replace('=', '')}.tum", t[ok], poses_from_positions(p[ok])
        )


def write_vo_report(m: VoMetrics, out: Path, name: str) -> str:
    """metrics.json and report.md of a VO run in ``out``; returns the Markdown table."""
    metrics = {k: getattr(m, k) for k in m.__slots__}
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    rows = [
        f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {v} |"
        for k, v in metrics.items()
    ]
    table = "\n".join(["| metric | value |", "|---|---|", *rows])
    (out / "report.md").write_text(f"# VO on {name}\n\n{table}\n")
    return table


def write_plots(run: ScaleRun, world: Any, out: Path, main: str = "M-MSCwK") -> list[Path]:
    """scale.png, scale_error.png, trajectory.png, point_cloud.png (and sensors.png when the
    run has the number-of-sensors study); returns the paths."""
    plt = figures.pyplot()
    paths = _scale_plots(plt, run, out)
    paths.append(_trajectory_plot(plt, run, out, main))
    cloud = _point_cloud_plot(plt, run, world, out, main)
    study = _sensors_plot(plt, run, out)
    return paths + [p for p in (cloud, study) if p is not None]


def _scale_plots(plt: Any, run: ScaleRun, out: Path) -> list[Path]:
    """scale.png (every method's scale and the truth) and scale_error.png (relative error)."""
    t = np.array(run.time_us) * 1e-6
    gt_s = np.array(run.gt_scale)
    base = [n for n in run.methods if not n.startswith("M-MSC k=")]
    fig, ax = plt.subplots(figsize=(9, 4.5))
    ax.plot(t, gt_s, "k", lw=2, label="ground truth")
    for n in base:
        ax.plot(t, run.scale[n], lw=1, label=n, color=COLOURS.get(n))
    finite = gt_s[np.isfinite(gt_s)]
    if len(finite):
        mid = float(np.median(finite))
        ax.set_ylim(0.8 * mid, 1.2 * mid)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("scale [m per VO unit]")
    ax.legend(fontsize=8, ncol=3)
    ax.grid(alpha=0.3)
    paths = [figures.save(plt, fig, out / "scale.png")]

    fig, ax = plt.subplots(figsize=(9, 4.5))
    for n in base:
        err = 100 * (np.array(run.scale[n]) - gt_s) / gt_s
        ax.plot(t, err, lw=1, label=n, color=COLOURS.get(n))
    ax.set_ylim(-5, 5)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("relative scale error [%]")
    ax.legend(fontsize=8, ncol=3)
    ax.grid(alpha=0.3)
    paths.append(figures.save(plt, fig, out / "scale_error.png"))
    return paths


def _trajectory_plot(plt: Any, run: ScaleRun, out: Path, main: str) -> Path:
    """trajectory.png: top view and height of the truth, the raw VO and two methods."""
    t = np.array(run.time_us) * 1e-6
    gt_p = np.array(run.gt_position)
    fig, (top, side) = plt.subplots(1, 2, figsize=(12, 5))
    top.plot(gt_p[:, 1], gt_p[:, 0], "k", lw=2, label="ground truth")
    side.plot(t, -gt_p[:, 2], "k", lw=2, label="ground truth")
    vo = np.array(run.vo_position)
    gt_c = np.array(run.gt_cam_position)
    ok = np.all(np.isfinite(vo), axis=1)
    if ok.sum() > 3:
        a = umeyama(vo[ok], gt_c[ok], with_scale=True)
        v = a.apply(vo[ok])
        top.plot(v[:, 1], v[:, 0], color="tab:cyan", lw=1, label="raw VO (Sim3-aligned)")
        side.plot(t[ok], -v[:, 2], color="tab:cyan", lw=1, label="raw VO (Sim3-aligned)")
    for n in ("MSCwK", main):
        p = np.array(run.position[n])
        ok = np.all(np.isfinite(p), axis=1)
        if ok.sum() > 3:
            a = umeyama(p[ok], gt_p[ok], with_scale=False)
            q = a.apply(p[ok])
            top.plot(q[:, 1], q[:, 0], lw=1, color=COLOURS.get(n), label=f"{n} (SE3-aligned)")
            side.plot(t[ok], -q[:, 2], lw=1, color=COLOURS.get(n), label=f"{n} (SE3-aligned)")
    top.set_xlabel("east [m]")
    top.set_ylabel("north [m]")
    top.set_aspect("equal")
    side.set_xlabel("time [s]")
    side.set_ylabel("height [m]")
    for a_ in (top, side):
        a_.grid(alpha=0.3)
        a_.legend(fontsize=8)
    return figures.save(plt, fig, out / "trajectory.png")


def _point_cloud_plot(plt: Any, run: ScaleRun, world: Any, out: Path, main: str) -> Path | None:
    """point_cloud.png: the map of one frame, scaled by the method's scale at that frame and
    placed around the true camera position of that frame with the VO frame's orientation
    (gravity-aligned, yaw = heading at init): the shape and scale of the local
    reconstruction, without the trajectory's drift. None if the run kept no map."""
    if not len(run.points_vo) or main not in run.position:
        return None
    p = np.array(run.position[main])
    vo = np.array(run.vo_position)
    ok = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(vo), axis=1)
    if run.points_frame < 0 or not ok[run.points_frame]:
        return None
    k = run.points_frame
    scale = float(np.array(run.scale[main])[k])
    R = so3.rot_z(run.yaw_vo_rad)
    pts = np.array(run.gt_cam_position)[k] + scale * (run.points_vo - vo[k]) @ R.T
    h_true = world.surface_height(pts[:, 0], pts[:, 1])
    err = -pts[:, 2] - h_true
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 5))
    pad = 4.0
    xs = np.linspace(pts[:, 0].min() - pad, pts[:, 0].max() + pad, 120)
    ys = np.linspace(pts[:, 1].min() - pad, pts[:, 1].max() + pad, 120)
    X, Y = np.meshgrid(xs, ys)
    H = world.surface_height(X.ravel(), Y.ravel()).reshape(X.shape)
    cf = ax1.contourf(Y, X, H, 20, cmap="terrain")
    fig.colorbar(cf, ax=ax1, label="true terrain height [m]")
    ax1.scatter(
        pts[:, 1],
        pts[:, 0],
        c=-pts[:, 2],
        cmap="terrain",
        edgecolors="k",
        linewidths=0.3,
        s=14,
        vmin=H.min(),
        vmax=H.max(),
    )
    ax1.set_xlabel("east [m]")
    ax1.set_ylabel("north [m]")
    ax1.set_title(f"scaled VO points ({main}) over the true terrain")
    ax2.hist(100 * err, bins=40, color="tab:red")
    ax2.set_xlabel("point height - true terrain height [cm]")
    ax2.set_ylabel("points")
    ax2.set_title(f"median |error| {100 * np.median(np.abs(err)):.1f} cm")
    return figures.save(plt, fig, out / "point_cloud.png")


def _sensors_plot(plt: Any, run: ScaleRun, out: Path) -> Path | None:
    """sensors.png: M-MSC's scale error against the number of sensors (the sensor study)."""
    study = sorted(
        (n for n in run.methods if n.startswith("M-MSC k=")), key=lambda n: int(n.split("=")[1])
    )
    if not study:
        return None
    metrics = {m.method: m for m in run.metrics()}
    ks = [int(n.split("=")[1]) for n in study]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(ks, [metrics[n].scale_mean_abs_rel_pct for n in study], "o-", color="tab:red")
    ax.set_xlabel("number of distance sensors")
    ax.set_ylabel("mean abs. relative scale error [%]")
    ax.set_title("M-MSC: scale error vs number of sensors")
    ax.grid(alpha=0.3)
    return figures.save(plt, fig, out / "sensors.png")


def summary(dirs: list[Path]) -> str:
    """Markdown tables over several `eval --methods all` folders named TERRAIN-TRAJECTORY-SEED:
    per terrain and trajectory, every method averaged over the seeds, and whether each thesis
    method beats each baseline (lower scale MSE and lower metric ATE); folders of datasets
    without a simulated world (real sequences, any name) make one "Real sequences" table
    (companion/evaluation/real_table.py)."""
    groups: dict[tuple[str, str], list[list[dict[str, Any]]]] = {}
    real: list[tuple[str, dict[str, Any]]] = []  # datasets without a world: real sequences
    for d in sorted(dirs):
        f = d / "scale_metrics.json"
        if not f.exists():
            continue
        doc = json.loads(f.read_text())
        parts = d.name.split("-")
        if isinstance(doc, dict):
            real.append((d.name, doc))
        elif len(parts) == 3:
            groups.setdefault((parts[0], parts[1]), []).append(doc)
    out: list[str] = []
    if real:
        from companion.evaluation.real_table import real_sequences_table

        out.append(real_sequences_table(real) + "\n")
    thesis = ["MSC", "MSCwK", "M-MSC", "M-MSCwK"]
    baselines = ["B7 window-ML", "B8 per-frame", "B9 plane"]
    for (terrain, traj), runs in sorted(groups.items()):
        methods = [r["method"] for r in runs[0]]
        out.append(f"### {terrain} / {traj} ({len(runs)} seeds)\n")
        out.append(
            "| method | scale MSE | mean abs rel. scale error | metric ATE | ATE % path "
            "| final error |"
        )
        out.append("|---|---|---|---|---|---|")
        avg: dict[str, dict[str, float]] = {}
        for m in methods:
            rows = [next(r for r in run if r["method"] == m) for run in runs]
            avg[m] = {
                k: float(np.mean([r[k] for r in rows]))
                for k in (
                    "scale_mse",
                    "scale_mean_abs_rel_pct",
                    "ate_m",
                    "ate_pct",
                    "final_error_m",
                )
            }
            a = avg[m]
            out.append(
                f"| {m} | {a['scale_mse']:.2e} | {a['scale_mean_abs_rel_pct']:.2f} % | "
                f"{a['ate_m']:.3f} m | {a['ate_pct']:.2f} % | {a['final_error_m']:.2f} m |"
            )
        beats = []
        for t in thesis:
            for b in baselines:
                if t in avg and b in avg:
                    ok = (
                        avg[t]["scale_mse"] < avg[b]["scale_mse"]
                        and avg[t]["ate_m"] < avg[b]["ate_m"]
                    )
                    beats.append(f"{t} vs {b}: {'yes' if ok else 'NO'}")
        out.append(
            "\nBeats (lower scale MSE and lower ATE, seed average): " + "; ".join(beats) + "\n"
        )
    return "\n".join(out)
