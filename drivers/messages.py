"""MAVLink wire data <-> the frozen types of companion.types (docs/service.md).

In: DISTANCE_SENSOR (cm, orientation 25 = downward, id = instance, signal_quality 0 unknown /
1 invalid / 2..100) mapped to a configured sensor by its id; ATTITUDE (rad, time_boot_ms).
Out: VISION_POSITION_ESTIMATE (NED, roll/pitch/yaw, 21-element upper-triangular covariance,
reset_counter) and ODOMETRY (frame LOCAL_FRD, child BODY_FRD, estimator VISION, velocity in the
body frame, quality). Nothing non-finite leaves: callers check :func:`is_finite_pose`.
STATUSTEXT (severity, 50 characters; a longer text in chunks sharing an id) for the operator.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from companion.config import RangefinderConfig
from companion.geometry import so3
from companion.types import AttitudeSample, ImuSample, PoseEstimate, RangeSample, SignalQuality

MSG_ID_ATTITUDE = mavlink.MAVLINK_MSG_ID_ATTITUDE
MSG_ID_SCALED_IMU = mavlink.MAVLINK_MSG_ID_SCALED_IMU
MSG_ID_DISTANCE_SENSOR = mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR
MSG_ID_TIMESYNC = mavlink.MAVLINK_MSG_ID_TIMESYNC  # 111: PX4 sends its requests as a stream
MAV_CMD_SET_MESSAGE_INTERVAL = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
# names for the numbers the service puts on the wire or compares with
MAV_COMP_ID_AUTOPILOT1 = mavlink.MAV_COMP_ID_AUTOPILOT1  # 1: the autopilot's own component
MAV_AUTOPILOT_INVALID = mavlink.MAV_AUTOPILOT_INVALID  # 8: not an autopilot (a GCS, us)
MAV_TYPE_ONBOARD_CONTROLLER = mavlink.MAV_TYPE_ONBOARD_CONTROLLER  # 18: our HEARTBEAT's type
MAV_STATE_STANDBY = mavlink.MAV_STATE_STANDBY  # 3: not tracking
MAV_STATE_ACTIVE = mavlink.MAV_STATE_ACTIVE  # 4: tracking, poses going out
MAV_RESULT_ACCEPTED = mavlink.MAV_RESULT_ACCEPTED  # 0
MAV_RESULT_IN_PROGRESS = mavlink.MAV_RESULT_IN_PROGRESS  # 5: not an answer yet
MAV_MODE_FLAG_SAFETY_ARMED = mavlink.MAV_MODE_FLAG_SAFETY_ARMED  # 128: HEARTBEAT.base_mode
STATUSTEXT_CHARS = 50  # text bytes in one STATUSTEXT
STATUSTEXT_MAX_CHUNKS = 4  # a longer text is cut to 4 chunks (200 characters)

# what the service reads from the autopilot (the link skips every other frame unparsed)
SERVICE_INPUTS = frozenset(
    {
        mavlink.MAVLINK_MSG_ID_HEARTBEAT,
        MSG_ID_TIMESYNC,
        mavlink.MAVLINK_MSG_ID_COMMAND_ACK,
        MSG_ID_DISTANCE_SENSOR,
        MSG_ID_ATTITUDE,
        MSG_ID_SCALED_IMU,
    }
)
STANDARD_GRAVITY_M_S2 = 9.80665  # PX4's and ArduPilot's 1 g in SCALED_IMU's mG
MAX_SPECIFIC_FORCE_M_S2 = 160.0  # 16 g: beyond any multirotor's accelerometer range
MAV_SENSOR_ROTATION_PITCH_270 = mavlink.MAV_SENSOR_ROTATION_PITCH_270  # downward
MAV_FRAME_LOCAL_FRD = mavlink.MAV_FRAME_LOCAL_FRD
MAV_FRAME_BODY_FRD = mavlink.MAV_FRAME_BODY_FRD
MAV_FRAME_LOCAL_NED = mavlink.MAV_FRAME_LOCAL_NED
MAV_ESTIMATOR_TYPE_VISION = mavlink.MAV_ESTIMATOR_TYPE_VISION


RANGE_MAX_AGE_US = 500_000  # a reading older than this at reception is refused
RANGE_MAX_AHEAD_US = 50_000  # one stamped this far after its reception is refused (clock)


def range_from_distance_sensor(
    msg: Any, sensors: Mapping[int, RangefinderConfig], time_us: int, rx_us: int
) -> tuple[RangeSample | None, str]:
    """A RangeSample from DISTANCE_SENSOR, or None and why not (the caller counts the reason):
    ``unknown_id`` / ``not_downward`` (not one of our sensors), ``no_reading`` (0 or 65535),
    ``out_of_range`` (outside the tighter of the message's and the configured limits),
    ``invalid`` (signal_quality 1), ``from_the_past`` / ``from_the_future`` (its time in our
    clock, ``time_us``, against its reception ``rx_us``: a stale reading or a clock that
    jumped). The covariance byte is not used (the configured noise model is)."""
    rf = sensors.get(int(msg.id))
    if rf is None:
        return None, "unknown_id"
    if int(msg.orientation) != MAV_SENSOR_ROTATION_PITCH_270:
        return None, "not_downward"
    d_cm, lo_cm, hi_cm = int(msg.current_distance), int(msg.min_distance), int(msg.max_distance)
    if d_cm <= 0 or d_cm >= 65535:
        return None, "no_reading"
    if time_us < rx_us - RANGE_MAX_AGE_US:
        return None, "from_the_past"
    if time_us > rx_us + RANGE_MAX_AHEAD_US:
        return None, "from_the_future"
    lo = max(rf.min_m, lo_cm * 0.01) if lo_cm > 0 else rf.min_m
    hi = min(rf.max_m, hi_cm * 0.01) if 0 < hi_cm < 65535 else rf.max_m
    quality = int(getattr(msg, "signal_quality", 0))
    sample = RangeSample(time_us, rf.sensor_id, d_cm * 0.01, lo, hi, quality)
    if quality == SignalQuality.INVALID:
        return None, "invalid"
    if not sample.is_valid:
        return None, "out_of_range"
    return sample, ""


def attitude_from_message(msg: Any, time_us: int) -> AttitudeSample | None:
    """An AttitudeSample from ATTITUDE (ZYX roll/pitch/yaw [rad]); None unless finite and
    inside the Euler ranges (|roll|, |yaw| <= pi, |pitch| <= pi/2) with rates below 50 rad/s."""
    rpy = np.array([msg.roll, msg.pitch, msg.yaw], dtype=np.float64)
    rates = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=np.float64)
    if not (np.all(np.isfinite(rpy)) and np.all(np.isfinite(rates))):
        return None
    limits = np.array([np.pi, np.pi / 2, np.pi]) + 1e-6
    if np.any(np.abs(rpy) > limits) or np.any(np.abs(rates) > 50.0):
        return None
    q = so3.matrix_to_quat(so3.rpy_to_matrix(*rpy))
    return AttitudeSample(time_us, q, rates)


def imu_from_scaled(msg: Any, time_us: int) -> ImuSample | None:
    """An ImuSample (accelerometer, body FRD [m/s^2]; gyroscope and magnetometer when usable)
    from SCALED_IMU (mG, mrad/s, mgauss); None unless the three accelerations are finite and
    below 16 g. SCALED_IMU, not HIGHRES_IMU: PX4 subtracts
    EKF2's accelerometer bias estimate from HIGHRES_IMU, and without GNSS that estimate wanders
    (0.1-0.3 m/s^2 on SIH: 1-2 deg of tilt in our gravity); SCALED_IMU is the calibrated
    sensor alone (docs/decisions.md, "Gravity from the accelerometer")."""
    f = np.array([msg.xacc, msg.yacc, msg.zacc], dtype=np.float64) * (STANDARD_GRAVITY_M_S2 / 1e3)
    if not np.all(np.isfinite(f)) or float(np.linalg.norm(f)) > MAX_SPECIFIC_FORCE_M_S2:
        return None
    # gyroscope (mrad/s) and magnetometer (mgauss; PX4 sends its first sensor_mag, corrected
    # for the board's rotation only; all zero when there is none): None when not usable
    w = np.array([msg.xgyro, msg.ygyro, msg.zgyro], dtype=np.float64) * 1e-3
    m = np.array([msg.xmag, msg.ymag, msg.zmag], dtype=np.float64) * 1e-3
    gyro = w if np.all(np.isfinite(w)) else None
    mag = m if np.all(np.isfinite(m)) and np.any(m) else None
    return ImuSample(time_us, f, gyro, mag)


def set_message_interval(mav: Any, target_system: int, msg_id: int, rate_hz: float | None) -> Any:
    """COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL asking for msg_id at rate_hz; None: back to
    the autopilot's default rate (interval 0, MAVLink's "default rate": PX4 SITL measured so,
    ArduPilot's documentation says the same)."""
    interval_us = 0.0 if rate_hz is None else 1e6 / rate_hz
    return mav.command_long_encode(
        target_system, 1, MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, interval_us, 0, 0, 0, 0, 0
    )


def message_name(msg_id: int) -> str:
    """A message id's name in the common dialect (TIMESYNC), or the number itself."""
    known = mavlink.mavlink_map.get(msg_id)
    return str(known.msgname) if known is not None else str(msg_id)


def result_name(result: int) -> str:
    """A COMMAND_ACK result's name (MAV_RESULT_FAILED), or the number itself."""
    entry = mavlink.enums["MAV_RESULT"].get(result)
    return str(entry.name) if entry is not None else str(result)


def is_finite_pose(pose: PoseEstimate) -> bool:
    """Whether every field that is sent is finite (position, attitude, covariance)."""
    return bool(
        np.all(np.isfinite(pose.position_ned_m))
        and np.all(np.isfinite(pose.quat_wxyz_ned_frd))
        and np.all(np.isfinite(pose.covariance_6x6))
    )


def upper_triangle(cov: Any) -> list[float]:
    """The 21 row-major upper-triangular elements of a (6, 6) covariance (MAVLink order)."""
    c = np.asarray(cov, dtype=np.float64)
    return [float(c[i, j]) for i in range(6) for j in range(i, 6)]


def vision_position_estimate(mav: Any, pose: PoseEstimate) -> Any:
    """VISION_POSITION_ESTIMATE of a pose (usec = capture time in our clock)."""
    roll, pitch, yaw = so3.matrix_to_rpy(so3.quat_to_matrix(pose.quat_wxyz_ned_frd))
    x, y, z = (float(v) for v in pose.position_ned_m)
    return mav.vision_position_estimate_encode(
        pose.time_us,
        x,
        y,
        z,
        roll,
        pitch,
        yaw,
        upper_triangle(pose.covariance_6x6),
        pose.reset_counter & 0xFF,
    )


def pose_at(pose: PoseEstimate, time_us: int) -> PoseEstimate:
    """The pose carried to ``time_us`` [us, our clock] along its own velocity (NED, m/s):
    position + velocity * dt, attitude, covariance and the rest as they are; the pose itself
    when its velocity is unknown (NaN). For an autopilot that stamps a sample with its arrival
    (PX4 before its time sync converges): sent as of its sending, the pose and its stamp agree
    whether the autopilot converts our stamp or takes the arrival (drivers/timesync.py,
    RequesterModel)."""
    v = np.asarray(pose.velocity_ned_m_s, dtype=np.float64)
    if not np.all(np.isfinite(v)):
        return pose
    dt_s = (time_us - pose.time_us) * 1e-6
    return dataclasses.replace(
        pose, time_us=int(time_us), position_ned_m=np.asarray(pose.position_ned_m) + v * dt_s
    )


def centred_pose(
    poses: Sequence[PoseEstimate], max_gap_us: float = float("inf")
) -> PoseEstimate | None:
    """The pose at the centre of the last ``len(poses)`` published ones (time order, N >= 3):
    time and position their means (a straight-line fit's value at the mean time), velocity
    [m/s] the fit's slope: a central difference, right under constant acceleration, where the
    velocity over the last poses stamped at the newest one lags by half its span in every
    turn. Attitude, covariance and quality are the middle pose's. None when the poses are
    fewer than three, of different VO maps (reset counters), not finite, or when two
    neighbours are more than ``max_gap_us`` [us] apart: after a pause in publishing (a slow
    moment of the machine), a window reaching back over it would stamp the message half the
    pause old, older than EKF2's delayed horizon keeps (PX4 received 1.5 s old samples so).

    What it is for: ODOMETRY with velocity for EKF2 (EKF2_EV_CTRL bit 2), stamped (N-1)/2
    frames back; EKF2 fuses each sample at its own time in its delayed horizon, so the older
    stamp costs no lag, where a velocity stamped late would pull EKF2 behind in every turn."""
    if len(poses) < 3 or len({p.reset_counter for p in poses}) != 1:
        return None
    t = np.array([p.time_us for p in poses], dtype=np.float64)
    p = np.array([q.position_ned_m for q in poses], dtype=np.float64)
    gaps = np.diff(t)
    if not (np.all(np.isfinite(p)) and np.all(gaps > 0) and np.all(gaps <= max_gap_us)):
        return None
    tc = (t - t.mean()) * 1e-6
    velocity = (tc @ (p - p.mean(axis=0))) / float(tc @ tc)
    mid = poses[len(poses) // 2]
    return PoseEstimate(
        int(round(t.mean())),
        p.mean(axis=0),
        mid.quat_wxyz_ned_frd,
        np.asarray(velocity, dtype=np.float64),
        mid.covariance_6x6,
        mid.reset_counter,
        mid.quality_pct,
    )


def odometry(
    mav: Any,
    pose: PoseEstimate,
    rates_rad_s: Any = (0.0, 0.0, 0.0),
    velocity_sigma_m_s: float = 0.1,
    frame: str = "local_frd",
) -> Any | None:
    """ODOMETRY (``frame`` local_frd: LOCAL_FRD, local_ned: LOCAL_NED; velocity in BODY_FRD;
    VISION) of a pose with the body rates (the autopilot's latest, FRD [rad/s]); None until
    the velocity is known or if the rates are not finite."""
    w = np.asarray(rates_rad_s, dtype=np.float64)
    if not (np.all(np.isfinite(pose.velocity_ned_m_s)) and np.all(np.isfinite(w))):
        return None
    R = so3.quat_to_matrix(pose.quat_wxyz_ned_frd)
    v_body = R.T @ pose.velocity_ned_m_s
    vel_cov = np.eye(6) * velocity_sigma_m_s**2
    x, y, z = (float(v) for v in pose.position_ned_m)
    return mav.odometry_encode(
        pose.time_us,
        MAV_FRAME_LOCAL_NED if frame == "local_ned" else MAV_FRAME_LOCAL_FRD,
        MAV_FRAME_BODY_FRD,
        x,
        y,
        z,
        [float(v) for v in pose.quat_wxyz_ned_frd],
        float(v_body[0]),
        float(v_body[1]),
        float(v_body[2]),
        float(w[0]),
        float(w[1]),
        float(w[2]),
        upper_triangle(pose.covariance_6x6),
        upper_triangle(vel_cov),
        pose.reset_counter & 0xFF,
        MAV_ESTIMATOR_TYPE_VISION,
        int(pose.quality_pct),
    )


def statustext_chunk_count(text: str) -> int:
    """How many STATUSTEXT messages :func:`statustext` makes of ``text``."""
    n = len(text.encode("ascii", "replace"))
    if n <= STATUSTEXT_CHARS:
        return 1
    return min(n // STATUSTEXT_CHARS + 1, STATUSTEXT_MAX_CHUNKS)


def statustext(mav: Any, severity: int, text: str, text_id: int) -> list[Any]:
    """STATUSTEXT message(s) of ``text`` (ASCII; any other character as '?'). Up to 50
    characters: one message with id 0 ("the only chunk"). Longer: chunks of 50 sharing
    ``text_id`` (1..65535) with chunk_seq 0, 1, ...; the last chunk is shorter than 50 (a
    NUL ends it, which tells the receiver the text is complete: a text of exactly 100
    characters gets an empty third chunk), at most STATUSTEXT_MAX_CHUNKS chunks (the rest is
    cut, ending in "...")."""
    raw = text.encode("ascii", "replace")
    if len(raw) <= STATUSTEXT_CHARS:
        return [mav.statustext_encode(severity, raw, 0, 0)]
    if not 1 <= text_id <= 0xFFFF:
        raise ValueError(f"text_id must be 1..65535, got {text_id}")
    room = STATUSTEXT_MAX_CHUNKS * STATUSTEXT_CHARS - 1  # the last chunk keeps its NUL
    if len(raw) > room:
        raw = raw[: room - 3] + b"..."
    chunks = [raw[i : i + STATUSTEXT_CHARS] for i in range(0, len(raw), STATUSTEXT_CHARS)]
    if len(chunks[-1]) == STATUSTEXT_CHARS:
        chunks.append(b"")
    return [mav.statustext_encode(severity, c, text_id, seq) for seq, c in enumerate(chunks)]
