"""Faults the SITL autopilot can inject during a flight, and what it measures around them.

A fault is ``KIND@START+DURATION`` in flight seconds (``camera_freeze@10+1``); ``companion sitl
run --fault`` takes any number of them and the tests use :class:`Fault` directly.

Camera faults (in the camera process): ``camera_freeze`` repeats the last good image with new
time stamps (a stuck capture pipeline), ``camera_black`` / ``camera_saturated`` send all-0 /
all-255 images, ``camera_unplug`` closes the stream and refuses connections (a USB camera
that drops off the bus and comes back). Link faults (in the autopilot): ``link_silence``
sends and hears nothing (a cable out), ``link_port_change`` moves the autopilot to another UDP
port at START (a restarted router), ``autopilot_reboot`` is silent for DURATION, then its boot
clock restarts at zero, its time sync and message rates return to their defaults. GPS
(``AutopilotOptions.gps``): ``gps_loss`` is a receiver without a fix for DURATION
(sitl/stub/gps.py), ``gps_loss@12+10``.

:func:`fault_metrics` says, per fault, what the autopilot saw: poses from frames taken during
it, how long after the last good frame poses kept coming, when they resumed, the
reset_counter before and after, rate requests and time-sync error after it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.errors import ConfigError

KINDS = {
    "camera_freeze": "the camera repeats its last image with new time stamps",
    "camera_black": "all-black images",
    "camera_saturated": "all-white images",
    "camera_unplug": "the camera stream closes and refuses connections",
    "link_silence": "the autopilot neither sends nor hears anything",
    "link_port_change": "the autopilot moves to another UDP port (at START)",
    "autopilot_reboot": "silent for DURATION, then its clock restarts at 0",
    "gps_loss": "the GPS receiver has no fix (GPS_RAW_INT fix type 1, no position)",
}
CAMERA_KINDS = frozenset(k for k in KINDS if k.startswith("camera_"))


@dataclass(frozen=True, slots=True)
class Fault:
    """One fault: ``kind`` during [start_s, start_s + duration_s) of flight time."""

    kind: str
    start_s: float
    duration_s: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ConfigError(f"fault: unknown kind {self.kind!r} (one of {', '.join(KINDS)})")
        if self.start_s < 0 or self.duration_s < 0:
            raise ConfigError(f"fault: negative time in {self}")

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s

    def active(self, t_s: float) -> bool:
        return self.start_s <= t_s < self.end_s

    @staticmethod
    def parse(text: str) -> Fault:
        """``KIND@START+DURATION`` (seconds; ``+DURATION`` may be left out: 0)."""
        kind, _, when = text.partition("@")
        start, _, duration = when.partition("+")
        try:
            return Fault(kind, float(start), float(duration or 0.0))
        except ValueError:
            raise ConfigError(f"fault: expected KIND@START+DURATION, got {text!r}") from None


def active(faults: Sequence[Fault], t_s: float) -> set[str]:
    """The kinds active at flight time t_s."""
    return {f.kind for f in faults if f.active(t_s)}


def fault_metrics(
    fault: Fault,
    rx_s: np.ndarray,
    t_pose_s: np.ndarray,
    reset_counter: np.ndarray,
    sync_error_us: np.ndarray,
    rate_requests_s: Sequence[float],
    frame_rate_hz: float,
    readout_ms: float,
    time_scale: float = 1.0,
    next_start_s: float = float("inf"),
) -> dict[str, Any]:
    """What the autopilot saw around ``fault``. Arrays: one entry per received pose, in
    reception order: reception and pose (exposure) times in flight seconds, reset_counter,
    time-sync conversion error [us]. Poses are put before/during/after the fault by their
    frame index, as the camera decides which frames are faulty (``seq / rate`` in the
    window); the settled time-sync window ends at the next fault's start. ``time_scale``:
    flight seconds per wall-clock second (sitl/stub/autopilot.py); the durations the service is
    judged by (``stop_after_last_good_frame_ms``, ``resume_s``) are wall-clock, the windows
    flight time."""
    start, end = fault.start_s, fault.end_s
    out: dict[str, Any] = {"kind": fault.kind, "start_s": start, "end_s": end}
    t_frame = np.round(t_pose_s * frame_rate_hz) / frame_rate_hz  # the frame's nominal time
    during = (t_frame >= start) & (t_frame < end)
    out["poses_from_fault_time"] = int(during.sum())
    before = t_frame < start
    out["reset_counter_before"] = int(reset_counter[before][-1]) if before.any() else None
    if fault.kind in CAMERA_KINDS:
        # the last good frame: the last exposure before the fault, released after readout
        last_exposure = (np.ceil(start * frame_rate_hz) - 1) / frame_rate_hz
        release = last_exposure + readout_ms * 1e-3 * time_scale
        late = (rx_s >= release) & (rx_s < end)
        out["stop_after_last_good_frame_ms"] = (
            float((rx_s[late].max() - release) * 1e3 / time_scale) if late.any() else 0.0
        )
    after = t_frame >= end
    if after.any():
        first = int(np.flatnonzero(after)[0])
        out["resume_s"] = float(rx_s[first] - end) / time_scale
        out["reset_counter_after"] = int(reset_counter[first])
    else:
        out["resume_s"] = None
        out["reset_counter_after"] = None
    settled = (t_pose_s >= end + 2.0) & (t_pose_s < min(end + 12.0, next_start_s))
    out["sync_error_ms_after"] = (
        float(np.abs(sync_error_us[settled]).max() * 1e-3) if settled.any() else None
    )
    out["rate_requests_after"] = sum(1 for t in rate_requests_s if end <= t < end + 10.0)
    return out
