"""What ``check`` sees of EKF2 while it watches PX4 (pure): the MAVLink streams, PX4's own
topics through its shell, and the readings the diagnosis shares (a topic's freshness, a
sample's age, EKF2's observation buffer, the time sync)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from companion.autopilot.params import Param
from companion.drivers.px4_shell_text import Fields, number

MIN_RATE_HZ = 5.0  # EKF2's EV_MAX_INTERVAL = 200 ms
GOOD_RATE_HZ = 20.0  # PX4's docs ask for 30-50 Hz
FRESH_S = 1.0  # a topic older than this is not being published any more
FUTURE_TOLERANCE_MS = 20.0  # stamps this far ahead of PX4's clock are jitter, not an error
LPOS_EDGE_S = 2.0  # LOCAL_POSITION_NED comes at >= 1 Hz (PX4's Normal mode): gaps above this
POS_HORIZ_REL = 8  # ESTIMATOR_STATUS_FLAGS
POSE_FRAMES = {0: "UNKNOWN", 1: "NED", 2: "FRD"}
GNSS_DISAGREE_M = 2.0  # GNSS position innovation beyond this, with vision fused: they disagree
EKF2_BUFFER_MATCH_MS = 100.0  # RingBuffer::pop_first_older_than: time <= horizon < time + 100


@dataclass(frozen=True, slots=True)
class ShellView:
    """What PX4's shell showed; a topic is None when never published (or not parsed)."""

    visual: Fields | None = None  # listener vehicle_visual_odometry
    mocap: Fields | None = None  # listener vehicle_mocap_odometry
    flags: Fields | None = None  # listener estimator_status_flags
    aid_pos: Fields | None = None  # listener estimator_aid_src_ev_pos
    timesync: Fields | None = None  # listener timesync_status
    aid_gnss: Fields | None = None  # listener estimator_aid_src_gnss_pos
    rates_hz: Mapping[str, float] | None = None  # uorb top -1


@dataclass(frozen=True, slots=True)
class Observations:
    """Everything check saw while watching."""

    watch_s: float = 0.0  # how long it watched [s]
    estimator_flags: int | None = None  # the last ESTIMATOR_STATUS.flags
    local_positions: int = 0  # LOCAL_POSITION_NED messages received
    lpos_first_s: float | None = None  # the first one, after the watch started [s]
    lpos_last_s: float | None = None  # the last one, after the watch started [s]
    lpos_max_gap_s: float | None = None  # the longest gap between two of them [s]
    gps_seen: bool = False  # a GPS_RAW_INT with a receiver (fix_type >= 1)
    statustexts: tuple[str, ...] = ()  # STATUSTEXT texts
    shell: ShellView | None = None  # None: no shell answer
    service: Mapping[str, Any] | None = None  # the service's status (None: not running)


def dig(d: Mapping[str, Any] | None, *keys: str) -> Any:
    """``d[k1][k2]...`` of the service's status, or None where a level is missing."""
    for k in keys:
        if not isinstance(d, Mapping) or k not in d:
            return None
        d = d[k]
    return d


def raw_int(params: Mapping[str, Param], name: str) -> int | None:
    """An INT32 parameter as EKF2 reads it (a float-encoded one not decoded), or None."""
    p = params.get(name)
    return int(p.value) if p is not None and p.is_int else None


def raw_float(params: Mapping[str, Param], name: str, default: float) -> float:
    """A parameter as a float, or ``default`` when the autopilot has none."""
    p = params.get(name)
    return float(p.value) if p is not None else default


def frame_name(frame: Any) -> str:
    """vehicle_visual_odometry's pose_frame in words (``?`` when not a number)."""
    if isinstance(frame, int) and not isinstance(frame, bool):
        return POSE_FRAMES.get(frame, str(frame))
    return "?"


def fmt(v: float | None, spec: str, unknown: str = "?") -> str:
    """``v`` formatted by ``spec``, or ``unknown`` when missing or not finite."""
    return format(v, spec) if v is not None and math.isfinite(v) else unknown


def fresh(fields: Fields | None) -> bool:
    """The topic was published within FRESH_S."""
    age = number(fields, "timestamp_age_s")
    return age is not None and age < FRESH_S


def sample_age_ms(v: Fields | None) -> float | None:
    """How old our sample was when PX4 received it (``timestamp - timestamp_sample``, after
    PX4's time-sync conversion) [ms]; negative: stamped in PX4's future; None: unknown."""
    t, s = number(v, "timestamp"), number(v, "timestamp_sample")
    if t is not None and s is not None and t > 0 and s > 0:
        return (t - s) / 1000.0
    before = number(v, "timestamp_sample_before_timestamp_us")
    return before / 1000.0 if before is not None else None


def ev_buffer_length(params: Mapping[str, Param]) -> int:
    """EKF2's observation buffer length (EstimatorInterface::initialise_interface):
    min(round(1.5 * delay / period), max(2, ceil(delay / period))), delay the larger of
    EKF2_DELAY_MAX and EKF2_EV_DELAY [ms], period EKF2_PREDICT_US."""
    delay_max = raw_float(params, "EKF2_DELAY_MAX", 200.0)
    delay_ms = max(delay_max, raw_float(params, "EKF2_EV_DELAY", 0.0))
    period_ms = max(0.1, raw_float(params, "EKF2_PREDICT_US", 10000.0) / 1000.0)
    return min(round(1.5 * delay_ms / period_ms), max(2, math.ceil(delay_ms / period_ms)))


def timesync_converged(sh: ShellView) -> bool | None:
    """Whether PX4's time sync converts our stamps: once its filter converged (~500 TIMESYNC
    answers: ~10 s at the 50 Hz the service asks for, ~50 s at PX4's own 10 Hz) it moves our
    time_usec into its clock; before that it stamps each sample with its arrival time, so
    ``timestamp_sample`` equals ``timestamp`` exactly (a converted stamp has microseconds of
    its own). None: no fresh sample or no TIMESYNC."""
    v = sh.visual
    if not fresh(v) or not fresh(sh.timesync):
        return None
    t, ts = number(v, "timestamp"), number(v, "timestamp_sample")
    before = number(v, "timestamp_sample_before_timestamp_us")
    if t is not None and ts is not None and t > 0 and ts > 0:
        return t != ts
    return before != 0 if before is not None else None


def no_vision_reasons(obs: Observations, svc: Mapping[str, Any] | None, reasons: list[str]) -> None:
    """Nothing of ours reaches EKF2's vision topic: why, most likely first."""
    unsupported = [t for t in obs.statustexts if "estimator_type" in t]
    if unsupported:
        reasons.append(
            f"PX4 drops our ODOMETRY ('{unsupported[-1]}'): estimator_type must be "
            "MAV_ESTIMATOR_TYPE_VISION (2)"
        )
    if svc is None:
        reasons.append(
            "no vision message reaches the autopilot, and the service is not running here "
            "(start `companion run`, or give --socket)"
        )
        return
    published = dig(svc, "output", "published") or 0
    rate = dig(svc, "output", "rate_hz") or 0.0
    if not published or rate <= 0.0:
        reasons.append(
            f"the service runs but publishes nothing (VO {dig(svc, 'vo', 'state')}): it sends "
            "only while the VO tracks and the metric scale is initialised"
        )
    else:
        reasons.append(
            f"the service sends {dig(svc, 'output', 'message')} at {rate:.1f} Hz, but none "
            "reaches EKF2: check the link (MAV_n_CONFIG, baud rate, signing, UDP partner) and "
            "that the service talks to this autopilot"
        )
