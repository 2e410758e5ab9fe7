"""The figures and plots of a ``companion sitl px4`` flight (sitl/loops/px4_flight.py).

Sources: ``truth.csv`` (the bridge: SIH's true state, our clock), the ground station's
LOCAL_POSITION_NED (PX4's own estimate, stamped on arrival), PX4's .ulg log (EKF2's
``estimator_status_flags.cs_ev_pos``, ``estimator_aid_src_ev_pos`` innovations and test
ratios, ``vehicle_visual_odometry`` = our estimate as PX4 received it, ``vehicle_land_detected``,
``vehicle_status.failsafe``), PX4's console, the service's exit report and the bridge's stats.

Definitions (docs/RESULTS.md, "PX4 in the loop"):
- PX4's local frame is our vision frame once EKF2 reset to it (origin where our VO initialised,
  in the air): its position is compared with the truth after one constant translation (the
  median difference over the compared span), no rotation and no scale; when EKF2 resets its
  position (our reset_counter changed), each stretch between resets gets its own translation.
- compared span: from 2 s after the first EV position fusion (EKF2's reset to our frame) to
  the touchdown (the truth back at the home level, or PX4's land detector if earlier; before
  the fusion PX4 has no horizontal position at all: Altitude mode, px4_flight.py).
- PX4's estimate: ``vehicle_local_position`` from the log at its ``timestamp_sample``, PX4's
  clock mapped to ours by a line through the smallest LOCAL_POSITION_NED arrival delays (SIH's
  clock drifts against ours); without a log, LOCAL_POSITION_NED stamped on arrival. Its error
  is taken against SIH's ``vehicle_local_position_groundtruth`` at the same PX4 timestamps
  (``truth_source``; no clock mapping in the figure), else against truth.csv at the mapped
  times (beside it as ``*_bridge_clock`` when both exist).
- ``heading_offset_deg``: SIH's true yaw minus PX4's (``vehicle_attitude`` against
  ``vehicle_attitude_groundtruth``, both PX4's clock), the median over the 10 s before the
  compared span (on the ground: PX4's compass heading, which our VO's frame took at its start);
  ``horizontal_error_m_p95_px4_axes``: the horizontal p95 with PX4's estimate turned by it (in
  PX4's own axes, as the ArduPilot loop reports EKF3's), beside the north-aligned figure.
- ``ev_pos_fused_pct``: the share of the airborne time after the first fusion during which
  EKF2's ``cs_ev_pos`` was set; ``airborne_before_fusion_s`` is the climb before it.
"""

from __future__ import annotations

import glob
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from companion.sitl.loops.gps_missions import is_gps_mission
from companion.sitl.loops.gps_results import add_service_frame, summarise_px4
from companion.sitl.loops.loop_results import (
    camera_and_latency,
    clock_line,
    path_and_landing,
    percentile,
    plot_side,
    plot_top,
    read_json,
    read_truth,
    segment_errors,
    touchdown,
    truth_at,
)
from companion.sitl.loops.ulog import read_topics

SETTLE_NS = 2e9  # compared from this long after the first EV fusion
TOPICS = {
    "estimator_status_flags",
    "estimator_aid_src_ev_pos",
    "vehicle_visual_odometry",
    "vehicle_land_detected",
    "vehicle_status",
    "vehicle_local_position",
    "vehicle_attitude",
    "vehicle_attitude_groundtruth",
    "vehicle_local_position_groundtruth",
    "vehicle_gps_position",
}


def _hold(t_src: np.ndarray, v_src: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Zero-order hold of a step signal at times t (before the first sample: the first)."""
    idx = np.clip(np.searchsorted(t_src, t, side="right") - 1, 0, len(t_src) - 1)
    return v_src[idx]


def summarise(flight: Any, ok: bool) -> dict[str, Any]:
    out: Path = flight.out
    tel = flight.tel
    service_report = read_json(out / "service-report.json")
    s: dict[str, Any] = {
        "mission": flight.o.mission,
        "seed": flight.o.seed,
        "completed": ok,
        "px4_version": tel.version or None,
        "armed_mode": getattr(flight, "armed_mode", None),
        "timesync_converged_at_arming": getattr(flight, "timesync_converged", None),
        "timesync_wait_s": getattr(flight, "timesync_wait_s", None),
        # how long EKF2 had fused our position on the ground when PX4 armed (ground start)
        "ev_fused_s_before_arming": _between(tel.phases, "ev fused", "armed"),
        # the message rates PX4 acknowledged to the service (its exit report): TIMESYNC (111)
        # among them once PX4 took our faster time sync (service.px4_timesync_rate_hz)
        "rates_acknowledged": service_report.get("rates_acknowledged"),
        "configure_exit": getattr(flight, "configure_exit", None),
        "notes": list(flight.notes),
    }
    ulog = _read_log(out, s["notes"])
    lp = np.array(tel.lpos, dtype=np.float64).reshape(-1, 5)
    clock = clock_line(lp)
    s["px4_clock_rate_vs_ours_ppm"] = float((clock[1] - 1.0) * 1e6)

    def ours(t_us: np.ndarray) -> np.ndarray:
        """PX4 time [us] -> our monotonic clock [ns]."""
        ns: np.ndarray = clock[0] + clock[1] * np.asarray(t_us, dtype=np.float64) * 1e3
        return ns

    s["failsafes"] = _failsafes(out, tel, ulog)
    # ---- truth
    tr = read_truth(s, out, lp, "PX4")
    if tr is None:
        return s
    t_tr, p_tr = tr[:, 0], tr[:, 1:4]
    air_t0, air_t1 = _airborne_span(tel.phases, lp, ulog, ours)
    s["airborne_s"] = float((air_t1 - air_t0) * 1e-9)
    t_first = _ev_fusion(s, tel, ulog, ours, air_t0, air_t1)
    t_lp, p_lp = _px4_estimate(s, out, lp, ulog, ours)
    # from 2 s after the first fusion (EKF2's reset to our frame and its transient) to the disarm
    t_cmp = (t_first + SETTLE_NS) if t_first is not None else air_t0
    s["compared_from_s_after_takeoff"] = float((t_cmp - air_t0) * 1e-9)
    s["vo_heading_deg"] = service_report.get("vo_heading_deg")
    # the compass's part in it (vo.heading_source = magnetometer): field samples averaged at
    # rest and their white-noise sigma; 0 / None when the heading is PX4's at our start
    s["mag_heading_samples"] = service_report.get("mag_heading_samples")
    s["mag_heading_sigma_deg"] = service_report.get("mag_heading_sigma_deg")
    frame_error_rad = _frame_heading_error(t_tr, tr[:, 4:8], air_t0, s["vo_heading_deg"])
    offset = _position_errors(s, t_tr, p_tr, t_lp, p_lp, ulog, ours, t_cmp, air_t1, frame_error_rad)
    path_and_landing(s, flight, ok, tr, air_t0, air_t1)
    camera_and_latency(s, out)
    _px4_vision_age(s, ulog)
    if is_gps_mission(flight.o.mission):
        armed_s = tel.phases.get("armed")
        t_armed_us = None if armed_s is None else (armed_s * 1e9 - clock[0]) / (clock[1] * 1e3)
        summarise_px4(s, ulog, t_armed_us)
        add_service_frame(s, out)
    try:
        _plot(out, s, t_tr, p_tr, t_lp, p_lp, offset, ulog, ours, t_cmp, air_t0, air_t1)
    except Exception as e:  # plots are a by-product: never lose the summary for them
        s["notes"].append(f"plot failed: {e!r}")
    return s


def _between(phases: dict[str, float], first: str, then: str) -> float | None:
    """Seconds from phase ``first`` to phase ``then``; None unless both were reached."""
    if first not in phases or then not in phases:
        return None
    return float(phases[then] - phases[first])


def _read_log(out: Path, notes: list[str]) -> dict[str, np.ndarray]:
    """PX4's last .ulg, copied to ``px4.ulg``: the topics of TOPICS (empty if none; a note
    if unreadable)."""
    ulg_files = sorted(glob.glob(str(out / "px4" / "log" / "*" / "*.ulg")))
    ulog: dict[str, np.ndarray] = {}
    if ulg_files:
        shutil.copy(ulg_files[-1], out / "px4.ulg")
        try:
            ulog = read_topics(out / "px4.ulg", TOPICS)
        except (ValueError, KeyError) as e:
            notes.append(f"px4.ulg unreadable: {e}")
    return ulog


def _failsafes(out: Path, tel: Any, ulog: dict[str, np.ndarray]) -> list[str]:
    """Failsafes seen on PX4's console, in STATUSTEXT and in vehicle_status."""
    fs: list[str] = []
    console = out / "px4-console.log"
    if console.exists():
        for line in console.read_text(errors="replace").splitlines():
            if re.search(r"failsafe", line, re.I):
                fs.append(line.strip())
    for t, _, text in tel.texts:
        if re.search(r"failsafe", text, re.I):
            fs.append(f"STATUSTEXT {t:.1f} s: {text}")
    if "vehicle_status" in ulog and np.any(ulog["vehicle_status"]["failsafe"]):
        fs.append("vehicle_status.failsafe set in px4.ulg")
    return fs


def _airborne_span(
    phases: dict[str, float], lp: np.ndarray, ulog: dict[str, np.ndarray], ours: Any
) -> tuple[Any, Any]:
    """Take-off and touchdown [ns, our clock] from PX4's land detector, else the ground
    station's arm and disarm."""
    t_arm = phases.get("armed", 0.0) * 1e9
    t_disarm = phases.get("disarmed", lp[-1, 0] * 1e-9) * 1e9
    air_t0 = air_t1 = None
    if "vehicle_land_detected" in ulog:
        ld = ulog["vehicle_land_detected"]
        t_ld = ours(ld["timestamp"])
        landed = ld["landed"].astype(bool)
        up = np.flatnonzero(~landed & (t_ld >= t_arm - 1e9))
        if len(up):
            air_t0 = t_ld[up[0]]
            down = np.flatnonzero(landed & (t_ld > air_t0))
            air_t1 = t_ld[down[0]] if len(down) else t_disarm
    if air_t0 is None:
        air_t0, air_t1 = t_arm, t_disarm
    return air_t0, air_t1


def _ev_fusion(
    s: dict[str, Any],
    tel: Any,
    ulog: dict[str, np.ndarray],
    ours: Any,
    air_t0: Any,
    air_t1: Any,
) -> Any:
    """EKF2's EV position fusion over the airborne time (from the log, else the ground
    station's view) into ``s``; the time of the first fusion (None if never)."""
    fuse_src = "none"
    t_f = f = None
    if "estimator_status_flags" in ulog:
        ef = ulog["estimator_status_flags"]
        t_f, f = ours(ef["timestamp"]), ef["cs_ev_pos"].astype(bool)
        fuse_src = "px4.ulg estimator_status_flags.cs_ev_pos"
    elif tel.est:
        est = np.array(tel.est, dtype=np.float64)
        t_f, f = est[:, 0], (est[:, 1].astype(int) & 8) > 0
        fuse_src = "ESTIMATOR_STATUS flags POS_HORIZ_REL (GCS link)"
    s["ev_pos_fused_source"] = fuse_src
    t_first = None
    if t_f is not None and f is not None:
        grid = np.arange(air_t0, air_t1, 10e6)  # 10 ms steps over the airborne time
        fused = _hold(t_f, f, grid)
        if fused.any():
            k0 = int(np.argmax(fused))
            t_first = grid[k0]
            s["airborne_before_fusion_s"] = float((t_first - air_t0) * 1e-9)
            s["ev_pos_fused_pct"] = float(100.0 * fused[k0:].mean())
            s["ev_pos_fused_pct_whole_airborne"] = float(100.0 * fused.mean())
            s["ev_pos_unfused_max_s"] = _longest_false_s(fused[k0:], 10e-3)
        else:
            s["ev_pos_fused_pct"] = 0.0
    return t_first


def _longest_false_s(flags: np.ndarray, step_s: float) -> float:
    """The longest run of False in ``flags`` (N,) sampled every ``step_s`` [s], in seconds:
    how long EKF2 went without fusing our position at a stretch."""
    off = np.concatenate([[0], (~flags.astype(bool)).astype(np.int8), [0]])
    edges = np.flatnonzero(np.diff(off))
    runs = edges[1::2] - edges[::2]
    return float(runs.max() * step_s) if len(runs) else 0.0


def _px4_estimate(
    s: dict[str, Any], out: Path, lp: np.ndarray, ulog: dict[str, np.ndarray], ours: Any
) -> tuple[np.ndarray, np.ndarray]:
    """PX4's position estimate (times [ns, our clock], NED positions): from the log at the
    time it refers to, else LOCAL_POSITION_NED on arrival; the latter saved as CSV."""
    t_lp, p_lp = lp[:, 0], lp[:, 2:5]
    s["px4_position_source"] = "LOCAL_POSITION_NED on the GCS link, stamped on arrival"
    if "vehicle_local_position" in ulog:  # the estimate at the time it refers to
        vlp = ulog["vehicle_local_position"]
        t_lp = ours(vlp["timestamp_sample"])
        p_lp = np.column_stack([vlp["x"], vlp["y"], vlp["z"]]).astype(np.float64)
        s["px4_position_source"] = "px4.ulg vehicle_local_position at timestamp_sample"
    np.savetxt(
        out / "px4_local_position.csv",
        lp,
        delimiter=",",
        fmt="%.6f",
        header="t_ns,time_boot_ms,x_m,y_m,z_m",
        comments="",
    )
    return t_lp, p_lp


def _position_errors(
    s: dict[str, Any],
    t_tr: np.ndarray,
    p_tr: np.ndarray,
    t_lp: np.ndarray,
    p_lp: np.ndarray,
    ulog: dict[str, np.ndarray],
    ours: Any,
    t_cmp: Any,
    air_t1: Any,
    frame_error_rad: float | None = None,
) -> np.ndarray:
    """PX4's estimate against the truth over the compared span, each stretch between EKF2
    position resets after its own translation, into ``s`` (also turned into PX4's axes and,
    given ``frame_error_rad`` (_frame_heading_error), into our frame's); the longest
    stretch's translation (3,)."""
    # to the touchdown: the truth at the home level, or PX4's land detector if earlier (SIH's
    # vehicle may sink below its start altitude before PX4 sees the landing: px4_bridge.py)
    t_touch = touchdown(t_tr, p_tr, t_cmp, air_t1, 0.02)
    s["compared_s"] = float((t_touch - t_cmp) * 1e-9)
    span = (t_lp >= t_cmp) & (t_lp <= t_touch)
    span &= (t_lp >= t_tr[0]) & (t_lp <= t_tr[-1])
    gt = truth_at(t_lp[span], t_tr, p_tr)
    est_p = p_lp[span]
    gt_px4 = _px4_clock_truth(ulog, span)
    # PX4 resets its position to ours when our reset_counter changes (a VO re-initialisation):
    # each stretch between EKF2 position resets is compared after its own translation
    seg = np.zeros(len(est_p), dtype=np.int64)
    if "vehicle_local_position" in ulog:
        vlp = ulog["vehicle_local_position"]
        rc = vlp["xy_reset_counter"].astype(np.int64) * 256 + vlp["z_reset_counter"]
        seg = _hold(ours(vlp["timestamp"]), rc, t_lp[span])
    s["px4_position_resets"] = int(len(np.unique(seg)) - 1)
    if gt_px4 is not None:
        # the same figures against truth.csv through the clock line, for comparison
        bridge: dict[str, Any] = {}
        segment_errors(bridge, est_p, gt, seg)
        s["horizontal_error_m_p95_bridge_clock"] = bridge["horizontal_error_m_p95"]
        s["vertical_error_m_p95_bridge_clock"] = bridge["vertical_error_m_p95"]
        gt = gt_px4
        s["truth_source"] = "px4.ulg vehicle_local_position_groundtruth (PX4's clock)"
    else:
        s["truth_source"] = "truth.csv (the bridge's clock; PX4's time mapped by a line)"
    offset = segment_errors(s, est_p, gt, seg)
    s["frame_offset_m"] = [float(v) for v in offset]
    dpsi = _heading_offset(ulog, ours, t_cmp)
    if dpsi is not None:
        s["heading_offset_deg"] = float(np.degrees(dpsi))
        s["horizontal_error_m_p95_px4_axes"] = _turned_p95(est_p, gt, seg, dpsi)
    if frame_error_rad is not None:
        s["frame_heading_error_deg"] = float(np.degrees(frame_error_rad))
        s["horizontal_error_m_p95_frame_axes"] = _turned_p95(est_p, gt, seg, -frame_error_rad)
    return offset


def _px4_clock_truth(ulog: dict[str, np.ndarray], span: np.ndarray) -> np.ndarray | None:
    """SIH's true position (N, 3), NED [m], at the ``span`` (mask over vehicle_local_position)
    samples' own times, both in PX4's clock (``vehicle_local_position_groundtruth``); None
    without either topic. No clock mapping: the line through the arrival delays that maps PX4's
    time to ours (clock_line) was off by up to 35 ms in parts of a flight (SIH's lockstep pace
    varies), and at 3 m/s that alone put 0.1 m into the horizontal figure (docs/RESULTS.md,
    "2026-11-28 (e28df69)")."""
    vlp = ulog.get("vehicle_local_position")
    g = ulog.get("vehicle_local_position_groundtruth")
    if vlp is None or g is None or len(g) < 2 or len(vlp) != len(span):
        return None
    names = g.dtype.names or ()
    t_g = (g["timestamp_sample"] if "timestamp_sample" in names else g["timestamp"]).astype(
        np.float64
    )
    order = np.argsort(t_g, kind="stable")
    t = vlp["timestamp_sample"][span].astype(np.float64)
    return np.column_stack(
        [np.interp(t, t_g[order], g[k][order].astype(np.float64)) for k in "xyz"]
    )


def _yaw_rad(q_wxyz: np.ndarray) -> np.ndarray:
    """Yaw [rad] of quaternions (N, 4) wxyz (body FRD -> NED)."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.asarray(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def _turned_p95(est: np.ndarray, gt: np.ndarray, seg: np.ndarray, angle_rad: float) -> Any:
    """Horizontal p95 [m] of ``est`` (N, 3) turned by ``angle_rad`` about the vertical (NED:
    positive turns north towards east) against ``gt``, per stretch (segment_errors)."""
    c, sn = np.cos(angle_rad), np.sin(angle_rad)
    turned = est @ np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]]).T
    own: dict[str, Any] = {}
    segment_errors(own, turned, gt, seg)
    return own["horizontal_error_m_p95"]


def _frame_heading_error(
    t_tr: np.ndarray, q_tr: np.ndarray, before: Any, vo_heading_deg: float | None
) -> float | None:
    """Our frame's heading error [rad]: the heading of the service's VO frame
    (``vo_heading_deg``, its exit report: our compass's at rest with vo.heading_source =
    magnetometer, else the autopilot's at the VO's start) minus SIH's true yaw on the ground
    (the median before ``before``, our clock [ns]; the vehicle rests until it arms). Every
    position we send is turned by it about home, and no estimator of ours sees it
    (docs/RESULTS.md, "2026-11-27 (e751c17)" and "2026-11-27 (d7a0c08)"). None without
    either."""
    rest = t_tr < before
    if vo_heading_deg is None or rest.sum() < 10:
        return None
    d = np.radians(vo_heading_deg) - float(np.median(_yaw_rad(q_tr[rest])))
    return float(np.arctan2(np.sin(d), np.cos(d)))


def _heading_offset(ulog: dict[str, np.ndarray], ours: Any, t_cmp: Any) -> float | None:
    """SIH's true yaw minus PX4's [rad], the median over the 10 s before ``t_cmp`` (our clock
    [ns]); None without both topics there."""
    if "vehicle_attitude" not in ulog or "vehicle_attitude_groundtruth" not in ulog:
        return None
    va, vg = ulog["vehicle_attitude"], ulog["vehicle_attitude_groundtruth"]
    t_a = ours(va["timestamp_sample"])
    near = (t_a < t_cmp) & (t_a > t_cmp - 10e9)
    if near.sum() < 10:
        return None

    t_g = ours(vg["timestamp"])
    y_true = np.interp(t_a[near], t_g, np.unwrap(_yaw_rad(vg["q"])))
    d = y_true - _yaw_rad(va["q"][near])
    return float(np.median(np.arctan2(np.sin(d), np.cos(d))))


def _px4_vision_age(s: dict[str, Any], ulog: dict[str, np.ndarray]) -> None:
    """PX4's receipt of our estimate (``vehicle_visual_odometry``: its age, count and rate)
    into ``s``."""
    if "vehicle_visual_odometry" in ulog:
        vo = ulog["vehicle_visual_odometry"]
        lat = _vision_age_ms(vo)
        s["px4_vision_age_ms_p50"] = percentile(lat, 50)
        s["px4_vision_age_ms_p99"] = percentile(lat, 99)
        s["px4_vision_messages"] = int(len(vo))
        dur = (vo["timestamp"][-1] - vo["timestamp"][0]) * 1e-6 if len(vo) > 1 else 0
        s["px4_vision_rate_hz"] = float((len(vo) - 1) / dur) if dur else None


def _vision_age_ms(vo: np.ndarray) -> np.ndarray:
    """PX4's receipt minus our exposure stamp [ms] of each ``vehicle_visual_odometry``."""
    return np.asarray((vo["timestamp"].astype(np.float64) - vo["timestamp_sample"]) * 1e-3)


def _plot(
    out: Path,
    s: dict[str, Any],
    t_tr: np.ndarray,
    p_tr: np.ndarray,
    t_lp: np.ndarray,
    p_lp: np.ndarray,
    offset: np.ndarray,
    ulog: dict[str, np.ndarray],
    ours: Any,
    t_first: float | None,
    air_t0: float,
    air_t1: float,
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t00 = air_t0
    fig, ax = plt.subplots(2, 2, figsize=(13, 9))
    sel = t_lp >= (t_first if t_first is not None else air_t0)
    # the truth, PX4's estimate and ours (as PX4 received it), in the truth's frame
    p_est = p_lp[sel] + offset
    top_ours = side_ours = None
    if "vehicle_visual_odometry" in ulog:
        vo = ulog["vehicle_visual_odometry"]
        top_ours = ("ours (as PX4 received it)", vo["position"] + offset)
        side_ours = (ours(vo["timestamp"]), vo["position"] + offset)
    title = f"{s['mission']}: top (PX4 frame shifted by one translation)"
    plot_top(ax[0, 0], p_tr, p_est, ("truth (SIH)", "PX4 EKF2"), title, top_ours)
    axis_labels = ("time since take-off [s]", "height above home [m]")
    est = ("PX4 EKF2", t_lp[sel], p_est)
    plot_side(ax[0, 1], t00, (t_tr, p_tr), est, axis_labels, side_ours)
    _plot_fusion(ax[1, 0], ulog, ours, t00, air_t1)
    _plot_latency(ax[1, 1], s, ulog, ours, t00)
    fig.tight_layout()
    fig.savefig(out / "flight.png", dpi=100)
    plt.close(fig)


def _plot_fusion(a: Any, ulog: dict[str, np.ndarray], ours: Any, t00: float, air_t1: float) -> None:
    """EKF2's EV position innovations, test ratio and fusion flag over time."""
    if "estimator_aid_src_ev_pos" in ulog:
        ev = ulog["estimator_aid_src_ev_pos"]
        te = (ours(ev["timestamp"]) - t00) * 1e-9
        a.plot(te, ev["innovation"][:, 0], "r-", lw=0.6, label="EV innovation north [m]")
        a.plot(te, ev["innovation"][:, 1], "g-", lw=0.6, label="EV innovation east [m]")
        a.plot(te, ev["test_ratio"][:, 0], "m:", lw=0.6, label="test ratio north")
    if "estimator_status_flags" in ulog:
        ef = ulog["estimator_status_flags"]
        a.step(
            (ours(ef["timestamp"]) - t00) * 1e-9,
            ef["cs_ev_pos"].astype(float) * 0.5,
            "k-",
            where="post",
            lw=1.0,
            label="cs_ev_pos (0.5 = fused)",
        )
    a.axvspan(0, (air_t1 - t00) * 1e-9, color="0.9", zorder=0)
    a.set_xlabel("time since take-off [s] (grey: airborne)")
    a.legend(fontsize=7)
    a.set_title("EKF2: EV position fusion")


def _plot_latency(
    a: Any, s: dict[str, Any], ulog: dict[str, np.ndarray], ours: Any, t00: float
) -> None:
    """The age of our estimate at PX4's receipt over time; the service's latency in the
    title."""
    if "vehicle_visual_odometry" in ulog:
        vo = ulog["vehicle_visual_odometry"]
        lat = _vision_age_ms(vo)
        a.plot((ours(vo["timestamp"]) - t00) * 1e-9, lat, "b.", ms=1)
        a.set_ylabel("PX4 receipt - our exposure stamp [ms]")
    a.set_xlabel("time since take-off [s]")
    a.set_title(
        f"latency: service exposure->send p50 {s.get('latency_ms_p50') or float('nan'):.1f} ms, "
        f"p99 {s.get('latency_ms_p99') or float('nan'):.1f} ms"
    )
