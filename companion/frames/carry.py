"""How far the autopilot's own estimate lies from our output just before a GPS loss (pure).

Why (docs/decisions.md, "The missions on the real autopilots"): while EKF2 fuses GNSS it lags
the vehicle by ~0.11 s x its speed (SIH's fixes on time, EKF2_GPS_DELAY 0); our output lags by
0.00-0.02 s. When GNSS fusion stops, EKF2 resets its horizontal position onto our output, so its
position steps by the whole difference: 0.26-0.43 m in three real-PX4 flights at the leg's
speed. Carrying that difference over into our output at the loss (and taking it out at the
handover's slew rate afterwards, :meth:`companion.frames.handover.Handover.carry`) makes the
reset land where EKF2 already was. The difference is measured only before the loss and then
frozen: following the autopilot's estimate while it fuses ours is a loop (tried: 2.4 m).

Inputs: the autopilot's local position samples (LOCAL_POSITION_NED, stamped on our clock:
``ap_time_us`` (M,), ``ap_position_ned_m`` (M, 3) [m]) and our output in the same frame
(``out_time_us`` (N,), ``out_position_ned_m`` (N, 3) [m], increasing times). Output: the mean
horizontal difference (autopilot minus ours) over the autopilot's samples in the last
``window_us`` before ``until_us``, each against our output linearly interpolated to its stamp;
z is 0 (EKF2's horizontal reset; its height keeps its own reference).
"""

from __future__ import annotations

import numpy as np

from companion.types import F64

MIN_SAMPLES = 3  # fewer of the autopilot's samples in the window: no offset


def autopilot_offset(
    ap_time_us: np.ndarray,
    ap_position_ned_m: np.ndarray,
    out_time_us: np.ndarray,
    out_position_ned_m: np.ndarray,
    until_us: int,
    window_us: int,
) -> F64 | None:
    """(3,) [m]: mean(autopilot - ours) horizontally, z = 0 (module docstring); None when fewer
    than MIN_SAMPLES of the autopilot's samples fall in the window inside our output's span, or
    any of them is not finite."""
    t_ap = np.asarray(ap_time_us, dtype=np.float64)
    p_ap = np.asarray(ap_position_ned_m, dtype=np.float64).reshape(-1, 3)
    t_out = np.asarray(out_time_us, dtype=np.float64)
    p_out = np.asarray(out_position_ned_m, dtype=np.float64).reshape(-1, 3)
    if len(t_out) < 2 or len(t_ap) == 0:
        return None
    keep = (
        (t_ap > until_us - window_us)
        & (t_ap <= until_us)
        & (t_ap >= t_out[0])
        & (t_ap <= t_out[-1])
    )
    if int(np.count_nonzero(keep)) < MIN_SAMPLES:
        return None
    t = t_ap[keep]
    ours = np.column_stack([np.interp(t, t_out, p_out[:, k]) for k in range(2)])
    d = p_ap[keep, :2] - ours
    if not np.all(np.isfinite(d)):
        return None
    mean = d.mean(axis=0)
    return np.array([mean[0], mean[1], 0.0])
