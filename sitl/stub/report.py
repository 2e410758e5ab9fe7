"""What the SITL autopilot received from the companion, and its report of a flight.

Every VISION_POSITION_ESTIMATE / ODOMETRY is kept as a :class:`Received` with the truth at its
time (flight time through the autopilot's time sync). The report: camera frames sent and
dropped, the link and time-sync figures, latency (wall-clock ms), the ATE of each segment
between reset_counter changes (SE(3)-aligned, as EKF2 re-anchors the vision frame), heading
errors, the scale error (Sim(3) on the main segment) and each injected fault's metrics.
Positions NED [m], angles [rad] (errors in [deg]), times as named.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.drivers.mavlink_parser import LinkStats
from companion.evaluation.trajectory import path_length, umeyama
from companion.sitl.stub.faults import fault_metrics
from companion.sitl.stub.options import AutopilotOptions


@dataclass
class Received:
    """One pose message from the companion, with its truth."""

    rx_ns: int  # reception, our monotonic clock
    kind: str
    time_usec: int  # as sent (companion clock)
    t_sim_s: float  # the same instant in flight time, through our time sync
    position: tuple[float, float, float]
    rpy: tuple[float, float, float]
    reset_counter: int
    true_position: tuple[float, float, float]
    true_rpy: tuple[float, float, float]
    sync_error_us: float  # time sync's conversion minus the exact one


@dataclass
class AutopilotStats:
    received: list[Received] = field(default_factory=list)
    timesync_rtt_ns: list[int] = field(default_factory=list)
    timesync_answers: int = 0
    heartbeats_from_companion: int = 0
    rates_set: dict[int, float] = field(default_factory=dict)
    rate_requests_s: list[float] = field(default_factory=list)  # flight times of requests
    reboots: int = 0
    link: LinkStats = field(default_factory=LinkStats)
    # STATUSTEXT from the companion: (rx_ns, severity, text, id, chunk_seq)
    statustexts: list[tuple[int, int, str, int, int]] = field(default_factory=list)


def flight_report(
    stats: AutopilotStats,
    opts: AutopilotOptions,
    camera_rate_hz: float,
    t_sim_of_mono: Callable[[float], float],
    signing: dict[str, int] | None,
    frames_sent: int = 0,
    frames_dropped: int = 0,
) -> dict[str, Any]:
    """Rates, latency, time-sync and accuracy figures of what was received (``stats``), with
    the flight's options, its camera rate [Hz], its clock (``t_sim_of_mono``: flight time [s]
    of a monotonic instant [ns]) and the signing counters (None: unsigned)."""
    rec = main_received(stats.received)
    out: dict[str, Any] = {
        "camera_frames_sent": frames_sent,
        "camera_frames_dropped": frames_dropped,
        "messages_received": len(stats.received),
        "timesync_answers": stats.timesync_answers,
        "rates_set_hz": {str(k): v for k, v in stats.rates_set.items()},
        "link": vars(stats.link),
        "signing": signing,
    }
    rtt = np.array(stats.timesync_rtt_ns) * 1e-6
    if len(rtt):
        out["timesync_rtt_ms_p50"] = float(np.percentile(rtt, 50))
        out["timesync_rtt_ms_p99"] = float(np.percentile(rtt, 99))
        # the slowest round trip the filter took: one sample's offset is off by at most
        # half of it (an asymmetric path), so the estimate is never further off than that
        out["timesync_rtt_ms_max"] = float(np.max(rtt))
    if len(rec) < 10:
        out["error"] = "fewer than 10 pose messages received"
        return out
    rx = np.array([r.rx_ns for r in rec]) * 1e-9
    t_sim = np.array([r.t_sim_s for r in rec])
    est = np.array([r.position for r in rec])
    gt = np.array([r.true_position for r in rec])
    rx_sim = np.array([t_sim_of_mono(r.rx_ns) for r in rec])
    latency_ms = (rx_sim - t_sim) * 1e3 / opts.time_scale  # wall-clock ms
    # as EKF2 does on a reset_counter change (it re-anchors the vision frame), each segment
    # between resets is aligned on its own (SE(3), no scale); segments of < 10 poses are
    # left out of the ATE
    resets = np.array([r.reset_counter for r in rec])
    err = np.full(len(rec), np.nan)
    for value in np.unique(resets):
        seg = resets == value
        if seg.sum() >= 10:
            a = umeyama(est[seg], gt[seg], with_scale=False)
            err[seg] = np.linalg.norm(a.apply(est[seg]) - gt[seg], axis=1)
    out["faults"] = [
        fault_metrics(
            f,
            rx_sim,
            t_sim,
            resets,
            np.array([r.sync_error_us for r in rec]),
            stats.rate_requests_s,
            camera_rate_hz,
            opts.readout_ms,
            opts.time_scale,
            min(
                (g.start_s for g in opts.faults if g.start_s >= f.end_s and g != f),
                default=float("inf"),
            ),
        )
        for f in opts.faults
    ]
    out["reboots"] = stats.reboots
    # the heading we sent against the truth, each segment on its own: the ATE aligns each
    # segment's rotation away, so a map whose north was the camera's (180 deg off after a
    # stall) kept a small ATE; EKF2 fuses the yaw as sent
    yaw_err = np.degrees(
        np.abs(
            np.remainder(np.array([r.rpy[2] - r.true_rpy[2] for r in rec]) + np.pi, 2 * np.pi)
            - np.pi
        )
    )
    out["heading_error_deg_max_by_segment"] = {
        str(v): float(yaw_err[resets == v].max()) for v in np.unique(resets)
    }
    # and as each map started (the median of its first 10 poses): its north's error
    out["heading_error_deg_start_by_segment"] = {
        str(v): float(np.median(yaw_err[resets == v][:10])) for v in np.unique(resets)
    }
    out["heading_error_deg_p50"] = float(np.percentile(yaw_err, 50))
    main_seg = resets == np.bincount(resets - resets.min()).argmax() + resets.min()
    sim3 = umeyama(est[main_seg], gt[main_seg], with_scale=True)
    err = err[np.isfinite(err)]
    length = path_length(gt)
    sync_err = np.abs([r.sync_error_us for r in rec])
    out.update(
        {
            "message": main_kind(stats.received),
            "received": len(rec),
            "received_rate_hz": float((len(rx) - 1) / (rx[-1] - rx[0])),
            "first_pose_s": float(t_sim[0]),
            "latency_ms_p50": float(np.percentile(latency_ms, 50)),
            "latency_ms_p99": float(np.percentile(latency_ms, 99)),
            "timesync_error_ms_max": float(sync_err.max() * 1e-3),
            "timesync_error_ms_p99": float(np.percentile(sync_err, 99) * 1e-3),
            "ate_m": float(np.sqrt(np.mean(err**2))),
            "path_m": length,
            "ate_pct": float(100 * np.sqrt(np.mean(err**2)) / length) if length else None,
            "scale_error_pct": float(100 * (1.0 / sim3.scale - 1.0)),
            "resets": len({r.reset_counter for r in rec}) - 1,
            "ate_segments": int(len(np.unique(resets))),
        }
    )
    return out


def main_received(received: list[Received]) -> list[Received]:
    """The received poses of the main kind (the kind is looked up once, not per pose)."""
    kind = main_kind(received)
    return [r for r in received if r.kind == kind]


def main_kind(received: list[Received]) -> str:
    """VISION_POSITION_ESTIMATE if the companion sent any, else ODOMETRY."""
    kinds = [r.kind for r in received]
    if "VISION_POSITION_ESTIMATE" in kinds:
        return "VISION_POSITION_ESTIMATE"
    return "ODOMETRY"


def write_report(out: Path, report: dict[str, Any], received: list[Received]) -> None:
    """``report.json``, ``received.csv`` (every pose received, with its truth) and, with 10
    poses of the main kind or more, ``autopilot.png`` in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    with (out / "received.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(
            [
                "rx_ns",
                "kind",
                "time_usec",
                "t_sim_s",
                "x",
                "y",
                "z",
                "roll",
                "pitch",
                "yaw",
                "reset_counter",
                "x_true",
                "y_true",
                "z_true",
                "roll_true",
                "pitch_true",
                "yaw_true",
                "sync_error_us",
            ]
        )
        for r in received:
            w.writerow(
                [
                    r.rx_ns,
                    r.kind,
                    r.time_usec,
                    f"{r.t_sim_s:.6f}",
                    *r.position,
                    *r.rpy,
                    r.reset_counter,
                    *r.true_position,
                    *r.true_rpy,
                    f"{r.sync_error_us:.1f}",
                ]
            )
    rec = main_received(received)
    if len(rec) >= 10:
        _plot(rec, out / "autopilot.png")


def _plot(rec: list[Received], path: Path) -> None:
    """Truth and the received path (SE(3)-aligned) from above; the position error in time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    est = np.array([r.position for r in rec])
    gt = np.array([r.true_position for r in rec])
    t = np.array([r.t_sim_s for r in rec])
    aligned = umeyama(est, gt, with_scale=False).apply(est)
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    axes[0].plot(gt[:, 1], gt[:, 0], "k-", lw=1.5, label="truth")
    axes[0].plot(aligned[:, 1], aligned[:, 0], "r-", lw=0.8, label="received (SE3-aligned)")
    axes[0].set_xlabel("east [m]")
    axes[0].set_ylabel("north [m]")
    axes[0].axis("equal")
    axes[0].legend()
    axes[1].plot(t, np.linalg.norm(aligned - gt, axis=1), "r-", lw=0.8)
    axes[1].set_xlabel("flight time [s]")
    axes[1].set_ylabel("position error [m]")
    axes[0].set_title("What the autopilot received")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
