"""The GPS missions' figures (sitl/loops/gps_missions.py): the autopilot's position jumps at the
GPS changes, and its error while the GPS was denied.

- ``max_jump_m``: the largest step of the autopilot's own local position within JUMP_WINDOW_S
  after a GPS change, truth-subtracted: with e(t) = estimate(t) - truth(t), the largest
  |e(t) - e(t_c)| for t in (t_c, t_c + 1 s], e(t_c) interpolated at the change t_c. The truth's
  own motion cancels; what is left is what the estimate did that the vehicle did not (a reset,
  a pull). Each change is reported (``gps_events``): the receiver losing and regaining its fix
  and the autopilot starting and stopping to use it, each with its 3-D, horizontal and vertical
  step.
- ``horizontal_error_m_p95_denied``: the 95th percentile of |e| horizontally from the loss to
  the return, raw: the autopilot's frame is the GPS's (its origin and north), so no alignment
  is taken off; ``horizontal_error_m_p95_before_denial`` is the same over the 30 s before.
- ``gps_lost_s`` / ``gps_back_s``: when the receiver's fix was lost / came back, seconds after
  the arming; ``gps_denied_s`` between.

Times in one clock (s), positions NED [m] (the autopilot's local frame and the simulator's truth
about the same home).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from companion.drivers.ardupilot import ekf_navigates
from companion.sitl.loops.loop_results import service_log_lines

JUMP_WINDOW_S = 1.0
BEFORE_DENIAL_S = 30.0


def _interp(t: np.ndarray, p: np.ndarray, at: np.ndarray) -> np.ndarray:
    return np.column_stack([np.interp(at, t, p[:, k]) for k in range(p.shape[1])])


def errors(t_est: np.ndarray, p_est: np.ndarray, t_gt: np.ndarray, p_gt: np.ndarray) -> Any:
    """(t (M,), e (M, 3)): the estimate minus the truth at the estimate's times inside the
    truth's span."""
    keep = (t_est >= t_gt[0]) & (t_est <= t_gt[-1])
    t = t_est[keep]
    return t, p_est[keep] - _interp(t_gt, p_gt, t)


def jump_at(t: np.ndarray, e: np.ndarray, t_change: float) -> dict[str, float] | None:
    """The largest truth-subtracted step within JUMP_WINDOW_S after ``t_change``: 3-D,
    horizontal and vertical [m] (each its own maximum); None without samples around it."""
    if len(t) < 2 or t_change < t[0] or t_change > t[-1]:
        return None
    e0 = _interp(t, e, np.array([t_change]))[0]
    win = (t > t_change) & (t <= t_change + JUMP_WINDOW_S)
    if not np.any(win):
        return None
    d = e[win] - e0
    return {
        "jump_m": float(np.max(np.linalg.norm(d, axis=1))),
        "horizontal_m": float(np.max(np.hypot(d[:, 0], d[:, 1]))),
        "vertical_m": float(np.max(np.abs(d[:, 2]))),
    }


def transitions(t: np.ndarray, flag: np.ndarray) -> list[tuple[float, bool]]:
    """(time, new value) at each change of a boolean signal."""
    f = np.asarray(flag, dtype=bool)
    idx = np.flatnonzero(f[1:] != f[:-1]) + 1
    return [(float(t[i]), bool(f[i])) for i in idx]


def summarise_gps(
    s: dict[str, Any],
    t_est: np.ndarray,
    p_est: np.ndarray,
    t_gt: np.ndarray,
    p_gt: np.ndarray,
    events: list[tuple[str, float]],
    t_armed: float | None,
    denied: tuple[float | None, float | None],
    ev_used: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """The GPS figures into ``s`` (this module's docstring). ``events``: (name, time) of each GPS
    change; ``denied``: (loss, return) times (None: not in this mission: gps-appears has no
    loss); ``ev_used``: (times, flag) of the autopilot fusing our position."""
    t, e = errors(t_est, p_est, t_gt, p_gt)
    jumps: list[dict[str, Any]] = []
    sizes: list[float] = []
    for name, tc in sorted(events, key=lambda x: x[1]):
        j = jump_at(t, e, tc)
        since = None if t_armed is None else tc - t_armed
        jumps.append({"event": name, "t_after_arming_s": since, **(j or {"jump_m": None})})
        if j is not None:
            sizes.append(j["jump_m"])
    s["gps_events"] = jumps
    s["max_jump_m"] = max(sizes) if sizes else None
    t_lost, t_back = denied
    s["gps_lost_s"] = None if t_lost is None or t_armed is None else t_lost - t_armed
    s["gps_back_s"] = None if t_back is None or t_armed is None else t_back - t_armed
    if t_lost is None or t_back is None:
        s["gps_denied_s"] = None
        s["horizontal_error_m_p95_denied"] = None
        return
    s["gps_denied_s"] = t_back - t_lost
    h = np.hypot(e[:, 0], e[:, 1])
    during = (t >= t_lost) & (t <= t_back)
    before = (t >= t_lost - BEFORE_DENIAL_S) & (t < t_lost)
    s["horizontal_error_m_p95_denied"] = (
        float(np.percentile(h[during], 95)) if np.any(during) else None
    )
    s["horizontal_error_m_max_denied"] = float(np.max(h[during])) if np.any(during) else None
    s["horizontal_error_m_p95_before_denial"] = (
        float(np.percentile(h[before], 95)) if np.any(before) else None
    )
    if ev_used is not None and len(ev_used[0]):
        tf, flag = ev_used  # logged at its changes: held between samples, on a 10 ms grid
        grid = np.arange(t_lost, t_back, 0.01)
        idx = np.searchsorted(tf, grid, side="right") - 1
        held = np.where(idx >= 0, flag[np.clip(idx, 0, len(flag) - 1)], False)
        s["ev_used_fraction_denied"] = float(np.mean(held)) if len(grid) else None
        s["ev_unused_s_denied"] = float(np.sum(~held) * 0.01)


def summarise_px4(s: dict[str, Any], ulog: dict[str, np.ndarray], t_armed_us: float | None) -> None:
    """The GPS figures of a PX4 flight from its log, all in PX4's clock: the estimate
    (``vehicle_local_position`` at ``timestamp_sample``), SIH's truth
    (``vehicle_local_position_groundtruth``), the receiver's fix (``vehicle_gps_position``,
    fix type >= 3), EKF2's use of it and of ours (``estimator_status_flags`` cs_gnss_pos,
    cs_ev_pos); changes before the arming are the boot's, not the mission's."""
    need = ("vehicle_local_position", "vehicle_local_position_groundtruth", "vehicle_gps_position")
    missing = [k for k in need if k not in ulog]
    if missing:
        s["notes"].append(f"GPS figures: px4.ulg lacks {', '.join(missing)}")
        return
    vlp, g = ulog["vehicle_local_position"], ulog["vehicle_local_position_groundtruth"]
    names = g.dtype.names or ()
    t_g = (g["timestamp_sample"] if "timestamp_sample" in names else g["timestamp"]) * 1e-6
    order = np.argsort(t_g, kind="stable")
    p_g = np.column_stack([g[k][order] for k in "xyz"]).astype(np.float64)
    t_v = vlp["timestamp_sample"].astype(np.float64) * 1e-6
    p_v = np.column_stack([vlp[k] for k in "xyz"]).astype(np.float64)
    t0 = -np.inf if t_armed_us is None else t_armed_us * 1e-6
    gps = ulog["vehicle_gps_position"]
    fix = transitions(gps["timestamp"] * 1e-6, gps["fix_type"] >= 3)
    events = [("fix back" if on else "fix lost", t) for t, on in fix if t > t0]
    ev_used = None
    if "estimator_status_flags" in ulog:
        f = ulog["estimator_status_flags"]
        t_f = f["timestamp"] * 1e-6
        for t, on in transitions(t_f, f["cs_gnss_pos"]):
            if t > t0:
                events.append(("EKF2 started GNSS" if on else "EKF2 stopped GNSS", t))
        ev_used = (t_f, f["cs_ev_pos"].astype(bool))
    lost = next((t for name, t in events if name == "fix lost"), None)
    backs = [t for name, t in events if name == "fix back" and (lost is None or t > lost)]
    back = backs[0] if backs else None
    t_armed = None if t_armed_us is None else t_armed_us * 1e-6
    summarise_gps(s, t_v, p_v, t_g[order], p_g, events, t_armed, (lost, back), ev_used)
    if lost is not None and back is not None:  # EKF2's own resets while denied (ours refused)
        rc = vlp["xy_reset_counter"].astype(np.int64)
        step = np.flatnonzero(np.diff(rc)) + 1
        inside = [i for i in step if lost + JUMP_WINDOW_S < t_v[i] <= back]
        s["px4_xy_resets_denied"] = len(inside)
        s["px4_xy_reset_max_m_denied"] = (
            float(max(np.hypot(*vlp["delta_xy"][i][:2]) for i in inside)) if inside else 0.0
        )
    if back is not None and ev_used is not None:
        started = [t for name, t in events if name == "EKF2 started GNSS" and t >= back]
        s["gnss_fused_again_after_s"] = (started[0] - back) if started else None


# EKF3's own words at a change of what it uses (STATUSTEXT)
ARDUPILOT_GPS_TEXTS = ("source set", "is using gps", "is using external nav", "stopped aiding")


def summarise_ardupilot(
    s: dict[str, Any],
    flight: Any,
    t_est_ns: np.ndarray,
    p_est: np.ndarray,
    t_tr_ns: np.ndarray,
    p_tr: np.ndarray,
) -> None:
    """The GPS figures of an ArduPilot flight in our clock: EKF3's position
    (LOCAL_POSITION_NED, its boot time mapped by the clock line), the bridge's truth, the
    receiver switched off / on (the phases "gps lost" / "gps back") and EKF3's STATUSTEXT at a
    source change (ARDUPILOT_GPS_TEXTS) as the changes."""
    ph = flight.tel.phases
    t0_gcs = getattr(flight.gcs, "t0", None)
    events = [(name, ph[name]) for name in ("gps lost", "gps back") if name in ph]
    t_armed = ph.get("armed")
    if t0_gcs is not None:
        for t, _, text in flight.tel.texts:
            after_arming = t_armed is not None and t + t0_gcs > t_armed
            if after_arming and any(k in text.lower() for k in ARDUPILOT_GPS_TEXTS):
                events.append((f"EKF3: {text}", t + t0_gcs))
    wall_minus_mono = getattr(flight, "wall_minus_mono_s", None)
    for what, t_wall in service_actions(flight.out / "service.log"):
        if wall_minus_mono is not None and (t_armed is None or t_wall - wall_minus_mono > t_armed):
            events.append((f"service: {what}", t_wall - wall_minus_mono))
    denied = (ph.get("gps lost"), ph.get("gps back"))
    ekf = np.array(flight.tel.ekf, dtype=np.float64).reshape(-1, 2)
    # EKF3 navigating (a relative horizontal position, not constant-position mode): while set
    # 2 is active that position is ours
    ok = ekf_navigates(ekf[:, 1].astype(np.int64))
    summarise_gps(
        s,
        t_est_ns * 1e-9,
        p_est,
        t_tr_ns * 1e-9,
        p_tr,
        events,
        t_armed,
        denied,
        (ekf[:, 0] * 1e-9, ok),
    )


_ACTION = re.compile(r"GPS handover: (.+) acknowledged")


def service_actions(log: Path) -> list[tuple[str, float]]:
    """The service's acknowledged handover actions (EKF2_GPS_CTRL, the EKF source set) from its
    log: (what, wall-clock time [s])."""
    found = [(_ACTION.search(line), wall) for line, wall in service_log_lines(log, "GPS handover")]
    return [(m.group(1), wall) for m, wall in found if m is not None]


def add_service_frame(s: dict[str, Any], out: Path) -> None:
    """The service's GPS frame at its exit (its report): state, the alignment it applied (yaw
    [deg], translation NED [m]: how far our own frame lay from the GPS frame) and the agreement
    [m] of its last fit; EKF2's lag carried into our output at the last loss [m]; its handover
    actions."""
    path = out / "service-report.json"
    try:
        frame = json.loads(path.read_text()).get("frame")
    except (OSError, ValueError):
        frame = None
    if not isinstance(frame, dict):
        s["service_frame"] = None
        return
    keys = (
        "state",
        "yaw_deg",
        "translation_ned_m",
        "agreement_m",
        "reanchors",
        "carried_m",
        "handover",
    )
    s["service_frame"] = {k: frame.get(k) for k in keys}
