"""Tables (Markdown, CSV) and PNG plots of evaluation runs. Writes files; no algorithms."""

from __future__ import annotations

import csv
import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.drivers.dataset import write_tum
from companion.evaluation.attitude import rmse_summary, wrap_rad
from companion.evaluation.dpose import BandErrors, RandomPoseStudy, dpose_metrics, pose_errors
from companion.evaluation.scale import ScaleMetrics
from companion.evaluation.tables import markdown_table
from companion.evaluation.trajectory import poses_from_positions, umeyama
from companion.evaluation.vo import VoMetrics
from companion.geometry import so3
from companion.offline import AttitudeRun, DposeRun, ScaleRun

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


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt: Any, fig: Any, path: Path) -> Path:
    """Write a figure as PNG and free it."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_plots(run: ScaleRun, world: Any, out: Path, main: str = "M-MSCwK") -> list[Path]:
    """scale.png, scale_error.png, trajectory.png, point_cloud.png (and sensors.png when the
    run has the number-of-sensors study); returns the paths."""
    plt = _plt()
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
    paths = [_save(plt, fig, out / "scale.png")]

    fig, ax = plt.subplots(figsize=(9, 4.5))
    for n in base:
        err = 100 * (np.array(run.scale[n]) - gt_s) / gt_s
        ax.plot(t, err, lw=1, label=n, color=COLOURS.get(n))
    ax.set_ylim(-5, 5)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("relative scale error [%]")
    ax.legend(fontsize=8, ncol=3)
    ax.grid(alpha=0.3)
    paths.append(_save(plt, fig, out / "scale_error.png"))
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
    return _save(plt, fig, out / "trajectory.png")


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
    return _save(plt, fig, out / "point_cloud.png")


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
    return _save(plt, fig, out / "sensors.png")


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


ATTITUDE_LABELS = {
    "vo": "VO rotation alone",
    "ground": "ranges, uncompensated",
    "gravity": "ranges, compensated",
    "fused": "fused (published)",
    "fused_ranges": "fused, range tilts only",
}


def attitude_metrics(run: AttitudeRun, settle_s: float = 5.0) -> list[dict[str, Any]]:
    """One row per estimate: its name and label, then :func:`rmse_summary`."""
    t = (np.array(run.time_us) - run.time_us[0]) * 1e-6
    truth = run.array("truth")
    return [
        {"estimate": name, "label": label, **rmse_summary(t, run.array(name), truth, settle_s)}
        for name, label in ATTITUDE_LABELS.items()
    ]


def write_attitude(run: AttitudeRun, out: Path, title: str) -> str:
    """attitude_metrics.json / .csv, attitude.md and attitude.png in ``out``; returns the table."""
    rows = attitude_metrics(run)
    (out / "attitude_metrics.json").write_text(json.dumps(rows, indent=2) + "\n")
    with (out / "attitude_metrics.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    long = "first_min_rmse_deg" in rows[0]
    head = "| estimate | roll RMSE | pitch RMSE | available |"
    lines = [head + (" first minute | last minute |" if long else ""), "|---|---|---|---|"]
    lines[1] += "---|---|" if long else ""
    for r in rows:
        line = (
            f"| {r['label']} | {r['roll_rmse_deg']:.3f} deg | {r['pitch_rmse_deg']:.3f} deg | "
            f"{100 * r['available']:.1f} % |"
        )
        if long:
            line += f" {r['first_min_rmse_deg']:.3f} deg | {r['last_min_rmse_deg']:.3f} deg |"
        lines.append(line)
    refusals = sorted(run.reasons.items(), key=lambda kv: -kv[1])[:8]
    table = "\n".join(lines)
    why = "\n".join(f"- {n} frames: {reason}" for reason, n in refusals)
    (out / "attitude.md").write_text(f"# {title}\n\n{table}\n\nMost frequent reasons:\n{why}\n")
    _attitude_plot(run, out / "attitude.png", title)
    return table


def _attitude_plot(run: AttitudeRun, path: Path, title: str) -> Path:
    plt = _plt()
    t = (np.array(run.time_us) - run.time_us[0]) * 1e-6
    truth = np.degrees(run.array("truth"))
    fig, axes = plt.subplots(4, 1, figsize=(10, 11), sharex=True)
    colours = {
        "vo": "tab:blue",
        "ground": "tab:gray",
        "gravity": "tab:orange",
        "fused_ranges": "tab:green",
        "fused": "tab:red",
    }
    for j, angle in enumerate(("roll", "pitch")):
        ax = axes[j]
        ax.plot(t, truth[:, j], "k-", lw=1.2, label="truth")
        ax.plot(t, np.degrees(run.array("fused"))[:, j], color="tab:red", lw=0.8, label="fused")
        ax.set_ylabel(f"{angle} [deg]")
        ax.legend(loc="upper right", fontsize=8)
        ax = axes[2 + j]
        for name, colour in colours.items():
            e = np.degrees(wrap_rad(run.array(name)[:, j] - run.array("truth")[:, j]))
            raw = name in ("ground", "gravity")  # per-sample range tilts: noisy, drawn light
            ax.plot(
                t,
                e,
                color=colour,
                lw=0.4 if raw else 1.0,
                alpha=0.45 if raw else 1.0,
                label=ATTITUDE_LABELS[name],
            )
        ax.set_ylim(-4, 4)
        ax.set_ylabel(f"{angle} error [deg]")
        ax.legend(loc="upper right", fontsize=8, ncol=2)
    axes[-1].set_xlabel("time [s]")
    axes[0].set_title(title)
    return _save(plt, fig, path)


def write_attitude_study(
    study: dict[str, list[tuple[float, dict[str, float]]]], out: Path, title: str
) -> tuple[str, Path]:
    """Plot and table of the studies: {"spacing": [(L_m, {series: rmse_deg, "bound":
    bound_deg}), ...], "sigma": [(sigma_m, {...}), ...]}."""
    plt = _plt()
    fig, axes = plt.subplots(1, len(study), figsize=(6 * len(study), 4.2))
    axes = np.atleast_1d(axes)
    lines = []
    for ax, (kind, points) in zip(axes, study.items(), strict=True):
        x = np.array([p[0] for p in points])
        x_show = x * 100 if kind == "sigma" else x
        names = list(points[0][1])
        lines.append(f"| {kind} | " + " | ".join(names) + " |")
        lines.append("|---" * (len(names) + 1) + "|")
        for xv, vals in points:
            shown = f"{xv * 100:.1f} cm" if kind == "sigma" else f"{xv:.1f} m"
            lines.append(f"| {shown} | " + " | ".join(f"{vals[n]:.3f}" for n in names) + " |")
        lines.append("")
        for n in names:
            y = np.array([p[1][n] for p in points])
            style = "k--" if n == "bound" else "o-"
            label = "bound sigma*sqrt(2)/L" if n == "bound" else ATTITUDE_LABELS.get(n, n)
            ax.plot(x_show, y, style, label=label, ms=3)
        ax.set_yscale("log")
        ax.set_xlabel("range noise sigma [cm]" if kind == "sigma" else "sensor spacing L [m]")
        ax.set_ylabel("RMSE over roll and pitch [deg]")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_title(title)
    return "\n".join(lines), _save(plt, fig, out / "attitude_study.png")


DPOSE_LABELS = {"dpose": "d-Pose", "vo": "VO (M-MSCwK)"}


def format_random_study(
    n: int, distractors: int, st: RandomPoseStudy, bands: dict[str, BandErrors]
) -> str:
    """One line on a d-Pose random-pose study (``companion eval --dpose --random N``)."""
    a, b = bands["2-6 m"], bands["6-8 m"]
    return (
        f"{n} random poses, {distractors} distractor dots: {st.visible} with "
        f"all marks in view, {st.correct} correct vertex maps, {st.wrong} wrong, "
        f"pose rate {100 * st.pose_rate:.2f} %, refused {dict(st.refused)}; "
        f"2-6 m: translation RMSE {100 * a.t_rmse_m:.2f} cm, "
        f"orientation RMSE {a.r_rmse_deg:.3f} deg; "
        f"6-8 m: {100 * b.t_rmse_m:.2f} cm, {b.r_rmse_deg:.3f} deg"
    )


def write_dpose(run: DposeRun, out: Path, title: str) -> str:
    """dpose_metrics.json, dpose.md and dpose.png in ``out``; returns the Markdown table."""
    truth = np.array(run.truth)
    estimates = {DPOSE_LABELS[n]: np.array(getattr(run, n)) for n in ("dpose", "vo")}
    rows = dpose_metrics(truth, np.array(run.height_m), estimates)
    (out / "dpose_metrics.json").write_text(json.dumps(rows, indent=2) + "\n")
    header = ["estimate", "heights", "frames", "available", "translation MSE"]
    header += ["translation RMSE", "orientation MSE", "orientation RMSE"]
    table = markdown_table(
        header,
        (
            [
                str(r["estimate"]),
                str(r["heights"]),
                str(r["frames"]),
                f"{100 * r['available']:.1f} %",
                f"{r['t_mse_m2']:.2e} m²",
                f"{r['t_rmse_m']:.3f} m",
                f"{r['r_mse_deg2']:.3f} deg²",
                f"{r['r_rmse_deg']:.3f} deg",
            ]
            for r in rows
        ),
    )
    why = "\n".join(
        f"- {n} frames: {k}" for k, n in sorted(run.reasons.items(), key=lambda x: -x[1])
    )
    (out / "dpose.md").write_text(f"# {title}\n\n{table}\n\nNo pose because:\n{why}\n")
    plt = _plt()
    t = (np.array(run.time_us) - run.time_us[0]) * 1e-6
    fig, axes = plt.subplots(3, 1, figsize=(10, 9), sharex=True)
    axes[0].plot(t, run.height_m, "k-")
    axes[0].set_ylabel("height above the marks [m]")
    for name, colour in (("vo", "tab:blue"), ("dpose", "tab:red")):
        label = DPOSE_LABELS[name]
        t_err, r_err = pose_errors(estimates[label], truth)
        axes[1].plot(t, t_err * 100, color=colour, lw=0.8, label=label)
        axes[2].plot(t, r_err, color=colour, lw=0.8, label=label)
    axes[1].set_ylabel("translation error [cm]")
    axes[2].set_ylabel("orientation error [deg]")
    axes[2].set_xlabel("time since arming [s]")
    axes[1].legend()
    axes[0].set_title(title)
    _save(plt, fig, out / "dpose.png")
    return table


def write_dpose_return(
    time_s: NDArray[np.float64],
    err_published_m: NDArray[np.float64],
    err_vo_m: NDArray[np.float64],
    in_view: NDArray[np.bool_],
    path: Path,
) -> Path:
    """The return over the pad: the published position's error and the VO's own (both from
    the arming pose) over time, the frames where d-Pose corrected it shaded."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 4.5))
    ax.plot(time_s, 100 * err_vo_m, color="0.5", lw=1, label="VO alone")
    ax.plot(time_s, 100 * err_published_m, color="C3", lw=1.2, label="published (with d-Pose)")
    top = float(max(np.nanmax(100 * err_vo_m), 1.0))
    ax.fill_between(time_s, 0, top, where=in_view, color="C2", alpha=0.15, label="marks in view")
    ax.axhline(2.0, color="k", ls=":", lw=0.8, label="2 cm")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error from the arming pose [cm]")
    ax.legend(loc="upper left")
    ax.grid(alpha=0.3)
    return _save(plt, fig, path)
