"""The summary of an ArduPilot flight (sitl/ardupilot_flight.py): the PX4 loop's figures where
they apply (sitl/px4_results.py, whose path, landing, camera and latency parts are reused).

- EKF3's estimate: LOCAL_POSITION_NED (its time_boot_ms moved into our clock through the
  smallest arrival delay, px4_results._clock_line) against the truth the bridge logged, from
  2 s after take-off to the touchdown: as in the PX4 loop each stretch between position resets
  (our reset_counter changes, from the service's log) after its own translation (the median
  difference: EKF3's frame is ours, whose origin is where our VO started), and
  ``horizontal_error_m_p95_one_frame`` after one translation for the whole flight; both in
  EKF3's own axes (turned by ``heading_offset_deg``, the true minus EKF3's yaw at arming: EKF3's
  heading comes from ours, ours from the autopilot's when our VO started), and
  ``horizontal_error_m_p95_north`` in north-aligned axes;
- fused: the share of the airborne time in which EKF_STATUS_REPORT said EKF3 has a relative
  horizontal position and is not in constant-position mode;
- failsafes: STATUSTEXTs that name one (ArduPilot says "EKF failsafe", "Failsafe", "Lost ...").
"""

from __future__ import annotations

import datetime
import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from sitl.px4_results import _camera_and_latency, _clock_line, _p, _path_and_landing

SETTLE_NS = 2e9
FAILSAFE = re.compile(r"fail.?safe|ekf.*(variance|failure)|lost (gps|rc|radio)", re.I)
EKF_POS_HORIZ_REL, EKF_CONST_POS_MODE = 0x08, 0x80


def _service_resets_ns(out: Path, wall_minus_mono_s: float | None) -> np.ndarray:
    """The times [ns, our monotonic clock] of the service's "VO re-initialised" lines (its log
    stamps wall-clock time: moved by the flight's wall-minus-monotonic offset), sorted."""
    log = out / "service.log"
    if wall_minus_mono_s is None or not log.exists():
        return np.zeros(0)
    times = []
    for line in log.read_text(errors="replace").splitlines():
        if "VO re-initialised" in line:
            try:
                wall = datetime.datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f").timestamp()
            except ValueError:
                continue
            times.append((wall - wall_minus_mono_s) * 1e9)
    return np.array(sorted(times))


def _heading_offset(tr: np.ndarray, yaw: np.ndarray, phases: dict[str, float]) -> float:
    """True yaw minus EKF3's (ATTITUDE) at arming [rad], wrapped; 0 without both."""
    t_arm = phases.get("armed")
    if t_arm is None or len(yaw) == 0 or len(tr) == 0:
        return 0.0
    t = t_arm * 1e9
    k = int(np.clip(np.searchsorted(tr[:, 0], t), 0, len(tr) - 1))
    qw, qx, qy, qz = tr[k, 4:8]
    true_yaw = np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
    j = int(np.clip(np.searchsorted(yaw[:, 0], t), 0, len(yaw) - 1))
    d = true_yaw - yaw[j, 1]
    return float(np.arctan2(np.sin(d), np.cos(d)))


def summarise(flight: Any, ok: bool) -> dict[str, Any]:
    tel = flight.tel
    out = flight.out
    s: dict[str, Any] = {
        "autopilot": "ArduPilot",
        "mission": flight.o.mission,
        "seed": flight.o.seed,
        "heading": flight.o.heading,
        "completed": ok,
        "ardupilot_version": tel.version or None,
        "armed_mode": "GUIDED",
        "configure_exit": flight.configure_exit,
        "notes": list(flight.notes),
    }
    s["failsafes"] = [t for _, _, t in tel.texts if FAILSAFE.search(t)]
    lp = np.array(tel.lpos, dtype=np.float64).reshape(-1, 5)
    truth_path = out / "truth.csv"
    if not truth_path.exists() or len(lp) < 10:
        s["landed"] = False
        s["error"] = "no truth or no ArduPilot position: the flight did not run"
        return s
    tr = np.loadtxt(truth_path, delimiter=",", skiprows=1, ndmin=2)
    t_tr, p_tr = tr[:, 0], tr[:, 1:4]
    clock = _clock_line(lp)
    t_lp = clock[0] + clock[1] * lp[:, 1] * 1e6
    p_lp = lp[:, 2:5]
    ph = tel.phases
    air_t0 = ph.get("take-off", ph.get("armed", 0.0)) * 1e9
    air_t1 = ph.get("disarmed", t_lp[-1] * 1e-9) * 1e9
    s["airborne_s"] = float((air_t1 - air_t0) * 1e-9)
    ekf = np.array(tel.ekf, dtype=np.float64).reshape(-1, 2)
    air = (ekf[:, 0] >= air_t0) & (ekf[:, 0] <= air_t1)
    if air.any():
        flags = ekf[air, 1].astype(np.int64)
        fused = (flags & EKF_POS_HORIZ_REL != 0) & (flags & EKF_CONST_POS_MODE == 0)
        s["ev_pos_fused_pct"] = float(100.0 * fused.mean())
    t_cmp = air_t0 + SETTLE_NS
    # the touchdown: back on the ground (the truth's home level) after the landing began
    t_land = ph.get("landing", air_t1 * 1e-9) * 1e9
    down = np.flatnonzero((t_tr > t_land) & (p_tr[:, 2] >= -0.05))
    t_touch = min(air_t1, t_tr[down[0]]) if len(down) else air_t1
    s["compared_s"] = float((t_touch - t_cmp) * 1e-9)
    span = (t_lp >= t_cmp) & (t_lp <= t_touch) & (t_lp >= t_tr[0]) & (t_lp <= t_tr[-1])
    if span.sum() >= 10:
        gt = np.column_stack([np.interp(t_lp[span], t_tr, p_tr[:, i]) for i in range(3)])
        est = p_lp[span]
        # in north-aligned axes, one translation for the whole flight
        offset = np.median(gt - est, axis=0)
        h_north = np.linalg.norm((est + offset - gt)[:, :2], axis=1)
        s["horizontal_error_m_p95_north"] = _p(h_north, 95)
        # EKF3's heading reference is ours, and ours is the autopilot's heading when our VO
        # started (EK3_SRC1_YAW = 6: before our data EKF3 has no heading of its own): its local
        # frame is turned from north by the heading error of that moment. Compared in EKF3's
        # own axes: turned by the difference between the true and EKF3's yaw at arming.
        dpsi = _heading_offset(tr, np.array(tel.yaw, dtype=np.float64).reshape(-1, 2), ph)
        s["heading_offset_deg"] = float(np.degrees(dpsi))
        c, sn = np.cos(dpsi), np.sin(dpsi)
        est = est @ np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]]).T
        offset = np.median(gt - est, axis=0)
        h_one = np.linalg.norm((est + offset - gt)[:, :2], axis=1)
        s["horizontal_error_m_p95_one_frame"] = _p(h_one, 95)
        # as the PX4 loop: each stretch between position resets after its own translation
        # (EKF3 resets its position to ours when our reset_counter changes; ArduPilot's
        # telemetry has no reset counter, so the service's own reset times are used)
        resets = _service_resets_ns(out, getattr(flight, "wall_minus_mono_s", None))
        s["position_resets_in_flight"] = int(np.sum((resets > t_cmp) & (resets < t_touch)))
        seg = np.searchsorted(resets, t_lp[span])
        err = np.full_like(est, np.nan)
        for value in np.unique(seg):
            k = seg == value
            if k.sum() >= 10:
                err[k] = est[k] + np.median(gt[k] - est[k], axis=0) - gt[k]
        err = err[np.all(np.isfinite(err), axis=1)]
        h_err = np.linalg.norm(err[:, :2], axis=1)
        s["horizontal_error_m_p95"] = _p(h_err, 95)
        s["vertical_error_m_p95"] = _p(np.abs(err[:, 2]), 95)
        s["horizontal_error_m_max"] = float(h_err.max()) if len(h_err) else None
        s["frame_offset_m"] = [float(v) for v in offset]
        try:
            _plot(out, s, t_tr, p_tr, t_lp[span], est + offset, t_cmp)
        except Exception as e:  # a by-product: never lose the summary for it
            s["notes"].append(f"plot failed: {e!r}")
    else:
        s["horizontal_error_m_p95"] = s["vertical_error_m_p95"] = None
    s["ardupilot_clock_rate_vs_ours_ppm"] = float((clock[1] - 1.0) * 1e6)
    _path_and_landing(s, flight, ok, tr, air_t0, air_t1)
    _camera_and_latency(s, out, {})
    rep = out / "service-report.json"
    if rep.exists():
        data = json.loads(rep.read_text())
        s["vo_resets"] = data.get("vo_resets")
    return s


def _plot(
    out: Path,
    s: dict[str, Any],
    t_tr: np.ndarray,
    p_tr: np.ndarray,
    t_est: np.ndarray,
    p_est: np.ndarray,
    t0: float,
) -> None:
    """flight.png: top and side views of the truth and EKF3's position (in EKF3's axes, one
    translation), and the horizontal error over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(16, 5))
    a = ax[0]
    a.plot(p_tr[:, 1], p_tr[:, 0], "k-", lw=1.6, label="truth (ArduPilot SITL)")
    a.plot(p_est[:, 1], p_est[:, 0], "b-", lw=0.9, label="ArduPilot EKF3 (its axes)")
    a.set_xlabel("east [m]")
    a.set_ylabel("north [m]")
    a.axis("equal")
    a.legend(fontsize=8)
    a.set_title(f"{s['mission']} seed {s['seed']}: top")
    a = ax[1]
    a.plot((t_tr - t0) * 1e-9, -p_tr[:, 2], "k-", lw=1.6, label="truth")
    a.plot((t_est - t0) * 1e-9, -p_est[:, 2], "b-", lw=0.9, label="EKF3")
    a.set_xlabel("time [s]")
    a.set_ylabel("height [m]")
    a.legend(fontsize=8)
    a.set_title("side")
    a = ax[2]
    gt = np.column_stack([np.interp(t_est, t_tr, p_tr[:, i]) for i in range(3)])
    a.plot((t_est - t0) * 1e-9, np.linalg.norm((p_est - gt)[:, :2], axis=1), "b-", lw=0.9)
    a.set_xlabel("time [s]")
    a.set_ylabel("horizontal error [m]")
    a.set_title(
        f"EKF3 - truth: p95 {s.get('horizontal_error_m_p95_one_frame') or float('nan'):.3f} m"
    )
    fig.tight_layout()
    fig.savefig(out / "flight.png", dpi=90)
    plt.close(fig)
