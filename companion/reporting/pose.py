"""The roll/pitch and d-Pose reports: tables (Markdown, CSV, JSON) and PNG plots of
`companion eval --attitude` and `--dpose` runs, their studies, and d-Pose back over the pad.
Writes files; no algorithms."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.evaluation.attitude import rmse_summary, wrap_rad
from companion.evaluation.dpose import BandErrors, RandomPoseStudy, dpose_metrics, pose_errors
from companion.evaluation.tables import markdown_table
from companion.offline import AttitudeRun, DposeRun
from companion.reporting import figures

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
    plt = figures.pyplot()
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
    return figures.save(plt, fig, path)


def write_attitude_study(
    study: dict[str, list[tuple[float, dict[str, float]]]], out: Path, title: str
) -> tuple[str, Path]:
    """Plot and table of the studies: {"spacing": [(L_m, {series: rmse_deg, "bound":
    bound_deg}), ...], "sigma": [(sigma_m, {...}), ...]}."""
    plt = figures.pyplot()
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
    return "\n".join(lines), figures.save(plt, fig, out / "attitude_study.png")


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
    plt = figures.pyplot()
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
    figures.save(plt, fig, out / "dpose.png")
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
    plt = figures.pyplot()
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
    return figures.save(plt, fig, path)
