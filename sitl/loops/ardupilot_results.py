"""The summary of an ArduPilot flight (sitl/loops/ardupilot_flight.py): the PX4 loop's figures where
they apply (sitl/loops/loop_results.py: the path, landing, camera and latency parts both share).

- EKF3's estimate: LOCAL_POSITION_NED (its time_boot_ms moved into our clock through the
  smallest arrival delay, loop_results.clock_line) against the truth the bridge logged, from
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

import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from companion.drivers.ardupilot import ekf_navigates
from companion.sitl.loops import gps_missions, gps_results, loop_results

SETTLE_NS = 2e9
FAILSAFE = re.compile(r"fail.?safe|ekf.*(variance|failure)|lost (gps|rc|radio)", re.I)


def _service_resets_ns(out: Path, wall_minus_mono_s: float | None) -> np.ndarray:
    """The times [ns, our monotonic clock] of the service's "VO re-initialised" lines (its log
    stamps wall-clock time: moved by the flight's wall-minus-monotonic offset), sorted."""
    if wall_minus_mono_s is None:
        return np.zeros(0)
    lines = loop_results.service_log_lines(out / "service.log", "VO re-initialised")
    return np.array(sorted((wall - wall_minus_mono_s) * 1e9 for _, wall in lines))


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


def _ekf_fused(s: dict[str, Any], ekf_rows: list[Any], air_t0: float, air_t1: float) -> None:
    """``ev_pos_fused_pct``: the share of the EKF_STATUS_REPORTs (t [ns], flags) between
    ``air_t0`` and ``air_t1`` that say EKF3 has a relative horizontal position and is not in
    constant-position mode (none airborne: no key)."""
    ekf = np.array(ekf_rows, dtype=np.float64).reshape(-1, 2)
    air = (ekf[:, 0] >= air_t0) & (ekf[:, 0] <= air_t1)
    if air.any():
        flags = ekf[air, 1].astype(np.int64)
        fused = ekf_navigates(flags)
        s["ev_pos_fused_pct"] = float(100.0 * fused.mean())


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
    tr = loop_results.read_truth(s, out, lp, "ArduPilot")
    if tr is None:
        return s
    t_tr, p_tr = tr[:, 0], tr[:, 1:4]
    clock = loop_results.clock_line(lp)
    t_lp = clock[0] + clock[1] * lp[:, 1] * 1e6
    p_lp = lp[:, 2:5]
    ph = tel.phases
    air_t0 = ph.get("take-off", ph.get("armed", 0.0)) * 1e9
    air_t1 = ph.get("disarmed", t_lp[-1] * 1e-9) * 1e9
    s["airborne_s"] = float((air_t1 - air_t0) * 1e-9)
    _ekf_fused(s, tel.ekf, air_t0, air_t1)
    t_cmp = air_t0 + SETTLE_NS
    # the touchdown: back on the ground (the truth's home level) after the landing began
    t_land = ph.get("landing", air_t1 * 1e-9) * 1e9
    t_touch = loop_results.touchdown(t_tr, p_tr, t_land, air_t1, 0.05)
    s["compared_s"] = float((t_touch - t_cmp) * 1e-9)
    span = (t_lp >= t_cmp) & (t_lp <= t_touch) & (t_lp >= t_tr[0]) & (t_lp <= t_tr[-1])
    if span.sum() >= 10:
        gt = loop_results.truth_at(t_lp[span], t_tr, p_tr)
        est = p_lp[span]
        # in north-aligned axes, one translation for the whole flight
        offset = np.median(gt - est, axis=0)
        h_north = np.linalg.norm((est + offset - gt)[:, :2], axis=1)
        s["horizontal_error_m_p95_north"] = loop_results.percentile(h_north, 95)
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
        s["horizontal_error_m_p95_one_frame"] = loop_results.percentile(h_one, 95)
        # as the PX4 loop: each stretch between position resets after its own translation
        # (EKF3 resets its position to ours when our reset_counter changes; ArduPilot's
        # telemetry has no reset counter, so the service's own reset times are used)
        resets = _service_resets_ns(out, getattr(flight, "wall_minus_mono_s", None))
        s["position_resets_in_flight"] = int(np.sum((resets > t_cmp) & (resets < t_touch)))
        loop_results.segment_errors(s, est, gt, np.searchsorted(resets, t_lp[span]))
        s["frame_offset_m"] = [float(v) for v in offset]
        try:
            _plot(out, s, t_tr, p_tr, t_lp[span], est + offset, t_cmp)
        except Exception as e:  # a by-product: never lose the summary for it
            s["notes"].append(f"plot failed: {e!r}")
    else:
        s["horizontal_error_m_p95"] = s["vertical_error_m_p95"] = None
    s["ardupilot_clock_rate_vs_ours_ppm"] = float((clock[1] - 1.0) * 1e6)
    loop_results.path_and_landing(s, flight, ok, tr, air_t0, air_t1)
    loop_results.camera_and_latency(s, out)
    if gps_missions.is_gps_mission(flight.o.mission):
        gps_results.summarise_ardupilot(s, flight, t_lp, p_lp, t_tr, p_tr)
        gps_results.add_service_frame(s, out)
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
    title = f"{s['mission']} seed {s['seed']}: top"
    labels = ("truth (ArduPilot SITL)", "ArduPilot EKF3 (its axes)")
    loop_results.plot_top(ax[0], p_tr, p_est, labels, title)
    loop_results.plot_side(
        ax[1], t0, (t_tr, p_tr), ("EKF3", t_est, p_est), ("time [s]", "height [m]")
    )
    a = ax[2]
    gt = loop_results.truth_at(t_est, t_tr, p_tr)
    a.plot((t_est - t0) * 1e-9, np.linalg.norm((p_est - gt)[:, :2], axis=1), "b-", lw=0.9)
    a.set_xlabel("time [s]")
    a.set_ylabel("horizontal error [m]")
    a.set_title(
        f"EKF3 - truth: p95 {s.get('horizontal_error_m_p95_one_frame') or float('nan'):.3f} m"
    )
    fig.tight_layout()
    fig.savefig(out / "flight.png", dpi=90)
    plt.close(fig)
