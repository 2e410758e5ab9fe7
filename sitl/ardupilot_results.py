"""The summary of an ArduPilot flight (sitl/ardupilot_flight.py): the PX4 loop's figures where
they apply (sitl/px4_results.py, whose path, landing, camera and latency parts are reused).

- EKF3's estimate: LOCAL_POSITION_NED (its time_boot_ms moved into our clock through the
  smallest arrival delay, px4_results._clock_line) against the truth the bridge logged, after
  one constant translation (the median difference: EKF3's frame is ours, whose origin is where
  our VO started), from 2 s after take-off to the touchdown;
- fused: the share of the airborne time in which EKF_STATUS_REPORT said EKF3 has a relative
  horizontal position and is not in constant-position mode;
- failsafes: STATUSTEXTs that name one (ArduPilot says "EKF failsafe", "Failsafe", "Lost ...").
"""

from __future__ import annotations

import json
import re
from typing import Any

import numpy as np

from sitl.px4_results import _camera_and_latency, _clock_line, _p, _path_and_landing

SETTLE_NS = 2e9
FAILSAFE = re.compile(r"fail.?safe|ekf.*(variance|failure)|lost (gps|rc|radio)", re.I)
EKF_POS_HORIZ_REL, EKF_CONST_POS_MODE = 0x08, 0x80


def summarise(flight: Any, ok: bool) -> dict[str, Any]:
    tel = flight.tel
    out = flight.out
    s: dict[str, Any] = {
        "autopilot": "ArduPilot",
        "mission": flight.o.mission,
        "seed": flight.o.seed,
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
        offset = np.median(gt - p_lp[span], axis=0)
        err = p_lp[span] + offset - gt
        h_err = np.linalg.norm(err[:, :2], axis=1)
        s["horizontal_error_m_p95"] = _p(h_err, 95)
        s["vertical_error_m_p95"] = _p(np.abs(err[:, 2]), 95)
        s["horizontal_error_m_max"] = float(h_err.max())
        s["frame_offset_m"] = [float(v) for v in offset]
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
