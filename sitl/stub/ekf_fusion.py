"""An emulation of how PX4 takes in external vision and when EKF2 fuses it (SITL autopilot).

Two stages, as in PX4 (docs/service.md; PX4's ``mavlink_receiver.cpp`` and EKF2's
``ev_control.cpp`` / ``ev_pos_control.cpp`` / ``RingBuffer``):

1. Reception (``mavlink_receiver``). VISION_POSITION_ESTIMATE becomes a vehicle_odometry with
   ``pose_frame = NED`` and ``quality = 0`` (the message has none). ODOMETRY: ``frame_id``
   LOCAL_NED / LOCAL_ENU -> NED, LOCAL_FRD / LOCAL_FLU -> FRD, anything else leaves the position
   NaN and the frame UNKNOWN; the velocity frame from ``child_frame_id``; ``estimator_type``
   VISION, VIO, NAIVE or UNKNOWN -> topic ``vehicle_visual_odometry`` (what EKF2 reads), MOCAP ->
   ``vehicle_mocap_odometry`` (EKF2 does not read it), others are dropped with a critical
   message. ``timestamp_sample`` = ``time_usec`` moved into the autopilot's clock by its time
   sync once that has converged, else the reception time (PX4's ``Timesync::sync_stamp``).
2. EKF2, run every ``EKF2_PREDICT_US``. A sample enters the EV buffer at
   ``timestamp_sample - EKF2_EV_DELAY`` (only if newer than the newest there; the ring buffer
   holds ``min(round(1.5 D / P), max(2, ceil(D / P)))`` samples, D = EKF2_DELAY_MAX, P =
   EKF2_PREDICT_US, as EstimatorInterface::initialise_interface sizes it, and overwrites the
   oldest). The filter works on a delayed horizon ``now - EKF2_DELAY_MAX`` and takes the newest
   sample with ``time <= horizon < time + 100 ms`` (older ones are discarded: a sample that
   arrives more than ``EKF2_DELAY_MAX + 100 ms`` after its time stamp is never used; one stamped
   in the future waits until the horizon reaches it, fused late, unless newer samples overwrite
   it first). Fusion of each part starts only when the sample quality
   is at least ``EKF2_EV_QMIN`` (if > 0), consecutive samples are less than 200 ms apart
   (EV_MAX_INTERVAL: >= 5 Hz) and the newest arrived less than 200 ms ago; it stops when no
   sample reached the horizon for 400 ms ("vision data stopped"). Per part:
   horizontal position needs ``EKF2_EV_CTRL`` bit 0 and a finite position, in an NED frame only
   once the heading is north-aligned (a magnetometer, or EV yaw in NED), in an FRD frame at any
   heading; height bit 1; velocity bit 2 and a known velocity frame; yaw bit 3. EV yaw replaces
   the magnetometer's heading; in NED it aligns EKF2's heading, in FRD it never does (the
   heading stays unaligned and PX4 refuses to arm), as the real PX4 SITL (main, 2026-03) shows.
   PX4's time sync converts our stamps only after ``timesync_window`` answers (PX4: ~500,
   ~10 s at the 50 Hz the service asks for, ~50 s at PX4's own 10 Hz; 0 here by default so
   that fast tests need not wait), arrival time before that.

What is not emulated: innovations and their gates (``EKF2_EVP_GATE``: every sample that reaches
the filter is accepted), the estimator states themselves (the local position published is the
simulator's truth), GNSS (so GNSS and vision fighting is a case for the real PX4 only), optical
flow and in-flight resets. Runtime parameter changes act at
once (PX4 applies EKF2_HGT_REF / EKF2_DELAY_MAX at the next boot).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from companion.drivers.timesync import ClockSync
from companion.sitl.stub.px4_params import ParamStore

EV_MAX_INTERVAL_US = 200_000  # EKF2 common.h: >= 5 Hz to start
BUFFER_MATCH_US = 100_000  # RingBuffer::pop_first_older_than: time <= horizon < time + 100 ms

MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_NED = 8
MAV_FRAME_BODY_OFFSET_NED = 9
MAV_FRAME_BODY_FRD = 12
MAV_FRAME_LOCAL_ENU = 16
MAV_FRAME_LOCAL_FRD = 20
MAV_FRAME_LOCAL_FLU = 21

MAV_ESTIMATOR_TYPE_UNKNOWN = 0
MAV_ESTIMATOR_TYPE_NAIVE = 1
MAV_ESTIMATOR_TYPE_VISION = 2
MAV_ESTIMATOR_TYPE_VIO = 3
MAV_ESTIMATOR_TYPE_MOCAP = 6

POSE_FRAME_UNKNOWN, POSE_FRAME_NED, POSE_FRAME_FRD = 0, 1, 2
VELOCITY_FRAME_UNKNOWN, VELOCITY_FRAME_NED, VELOCITY_FRAME_FRD, VELOCITY_FRAME_BODY_FRD = 0, 1, 2, 3

EV_CTRL_HPOS, EV_CTRL_VPOS, EV_CTRL_VEL, EV_CTRL_YAW = 1, 2, 4, 8

# MAVLink ESTIMATOR_STATUS_FLAGS
ESTIMATOR_ATTITUDE = 1
ESTIMATOR_VELOCITY_HORIZ = 2
ESTIMATOR_VELOCITY_VERT = 4
ESTIMATOR_POS_HORIZ_REL = 8
ESTIMATOR_POS_VERT_ABS = 32
ESTIMATOR_POS_VERT_AGL = 64
ESTIMATOR_CONST_POS_MODE = 128
ESTIMATOR_PRED_POS_HORIZ_REL = 256

LOCAL_POSITION_PERIOD_US = 100_000  # vehicle_local_position at 10 Hz (the stream rate)
NAN3 = (math.nan, math.nan, math.nan)


def _local_frame(
    frame_id: int, xyz: tuple[float, float, float]
) -> tuple[str, tuple[float, float, float]] | None:
    """A vector in one of the MAVLink local frames as PX4's receiver takes it: ("ned", xyz)
    for LOCAL_NED and LOCAL_ENU (axes swapped), ("frd", xyz) for LOCAL_FRD and LOCAL_FLU
    (y and z negated); None for any other frame."""
    x, y, z = xyz
    if frame_id == MAV_FRAME_LOCAL_NED:
        return "ned", xyz
    if frame_id == MAV_FRAME_LOCAL_ENU:
        return "ned", (y, x, -z)
    if frame_id == MAV_FRAME_LOCAL_FRD:
        return "frd", xyz
    if frame_id == MAV_FRAME_LOCAL_FLU:
        return "frd", (x, -y, -z)
    return None


def _finite(values: tuple[float, ...]) -> bool:
    return all(math.isfinite(v) for v in values)


@dataclass
class Topic:
    """One uORB topic: its message struct name, last fields and publication times [us]."""

    name: str
    struct: str
    fields: dict[str, Any] | None = None
    published_us: deque[int] = field(default_factory=lambda: deque(maxlen=400))

    def publish(self, fields: dict[str, Any], now_us: int) -> None:
        """A new message at now_us [us]."""
        self.fields = fields
        self.published_us.append(now_us)

    def rate_hz(self, now_us: int, window_us: int = 1_000_000) -> float:
        """Publications per second over the last window (uorb top's RATE column)."""
        return sum(1 for t in self.published_us if now_us - t <= window_us) * 1e6 / window_us


@dataclass
class EvSample:
    """A vehicle_odometry as EKF2 buffers it (time_us = timestamp_sample - EKF2_EV_DELAY)."""

    time_us: int
    pose_frame: int
    position: tuple[float, float, float]
    q: tuple[float, float, float, float]
    velocity_frame: int
    velocity: tuple[float, float, float]
    reset_counter: int
    quality: int


class EvFusion:
    """PX4's vision input and EKF2's EV fusion state, driven by ``on_message`` (reception) and
    ``step`` (one filter update); clocks in the autopilot's boot time [us]."""

    def __init__(
        self,
        params: ParamStore,
        sync_of: Callable[[], ClockSync],
        has_mag: bool = True,
        truth: Callable[[int], tuple[Any, Any]] | None = None,
        statustext: Callable[[str], None] | None = None,
    ) -> None:
        self.params = params
        self.sync_of = sync_of  # the autopilot's current time sync (a reboot makes a new one)
        self.has_mag = has_mag
        self.truth = truth
        self.statustext = statustext
        self.topics = {
            name: Topic(name, struct)
            for name, struct in (
                ("vehicle_visual_odometry", "vehicle_odometry"),
                ("vehicle_mocap_odometry", "vehicle_odometry"),
                ("estimator_status_flags", "estimator_status_flags"),
                ("estimator_aid_src_ev_pos", "estimator_aid_source2d"),
                ("timesync_status", "timesync_status"),
                ("vehicle_local_position", "vehicle_local_position"),
            )
        }
        self.buffer: deque[EvSample] = deque(maxlen=self._buffer_length())
        self.prev: EvSample | None = None  # the last sample that reached the filter (quality ok)
        self.last_push_us = 0
        self.flags = {
            "tilt_align": True,
            "yaw_align": False,
            "ev_pos": False,
            "ev_hgt": False,
            "ev_vel": False,
            "ev_yaw": False,
        }
        self.ev_yaw_frame = POSE_FRAME_UNKNOWN  # the frame of the last sample with our yaw
        # PX4's time sync converts our stamps only after this many TIMESYNC answers (PX4:
        # ~500: ~10 s at the service's 50 Hz, ~50 s at PX4's own 10 Hz); 0: as soon as the
        # stub's own filter has converged (fast tests)
        self.timesync_window = 0
        self.last_aiding_us = 0  # last horizontal aiding (EV position or velocity)
        self.control_status_changes = 0
        self.fusion_starts = 0
        self.fusion_stops = 0
        self.dropped_unsupported = 0
        self._lpos_us = 0  # last vehicle_local_position

    # ---------------------------------------------------------------- parameters
    def _p(self, name: str) -> float:
        return float(self.params.get(name))

    def _buffer_length(self) -> int:
        """EKF2's observation buffer length (EstimatorInterface::initialise_interface)."""
        delay_ms = max(self._p("EKF2_DELAY_MAX"), self._p("EKF2_EV_DELAY"))
        period_ms = max(0.1, self._p("EKF2_PREDICT_US") / 1000.0)
        return min(round(1.5 * delay_ms / period_ms), max(2, math.ceil(delay_ms / period_ms)))

    @property
    def ev_ctrl(self) -> int:
        """EKF2_EV_CTRL as EKF2 reads it (its raw bits)."""
        return int(self.params.get("EKF2_EV_CTRL"))

    def mag_heading(self) -> bool:
        """A magnetometer gives EKF2 a north-aligned heading (fitted, declared, not disabled).
        SYS_HAS_MAG is a count in newer PX4 (0 none, 1, 2 ... magnetometers), 0 / 1 before."""
        return (
            self.has_mag
            and int(self.params.get("SYS_HAS_MAG")) >= 1
            and int(self.params.get("EKF2_MAG_TYPE")) != 5  # 5 = None
        )

    # ---------------------------------------------------------------- reception
    def sync_stamp_us(self, time_usec: int, here_ns: int) -> int:
        """PX4's Timesync::sync_stamp: the remote time in our clock once converged, else now."""
        sync = self.sync_of()
        if sync.converged and sync.samples >= self.timesync_window:
            return sync.remote_to_local_us(int(time_usec), here_ns)
        return here_ns // 1000

    def on_message(self, msg: Any, kind: str, here_ns: int) -> None:
        """VISION_POSITION_ESTIMATE or ODOMETRY received at our clock ``here_ns``."""
        now_us = here_ns // 1000
        if kind == "VISION_POSITION_ESTIMATE":
            position = (float(msg.x), float(msg.y), float(msg.z))
            q = _quat_from_euler(float(msg.roll), float(msg.pitch), float(msg.yaw))
            odom: dict[str, Any] = {
                "timestamp": now_us,
                "timestamp_sample": self.sync_stamp_us(int(msg.usec), here_ns),
                "pose_frame": POSE_FRAME_NED,
                "position": position,
                "q": q,
                "velocity_frame": VELOCITY_FRAME_UNKNOWN,
                "velocity": NAN3,
                "reset_counter": int(msg.reset_counter),
                "quality": 0,
            }
            self._publish_ev("vehicle_visual_odometry", odom, now_us)
            return
        odom = self._odometry_fields(msg, here_ns)
        est = int(msg.estimator_type)
        if est in (
            MAV_ESTIMATOR_TYPE_UNKNOWN,
            MAV_ESTIMATOR_TYPE_NAIVE,
            MAV_ESTIMATOR_TYPE_VISION,
            MAV_ESTIMATOR_TYPE_VIO,
        ):
            self._publish_ev("vehicle_visual_odometry", odom, now_us)
        elif est == MAV_ESTIMATOR_TYPE_MOCAP:
            self.topics["vehicle_mocap_odometry"].publish(odom, now_us)
        else:
            self.dropped_unsupported += 1
            if self.statustext is not None and self.dropped_unsupported % 100 == 1:
                self.statustext(f"ODOMETRY: estimator_type {est} unsupported")

    def _odometry_fields(self, msg: Any, here_ns: int) -> dict[str, Any]:
        p = (float(msg.x), float(msg.y), float(msg.z))
        pose_frame, position = POSE_FRAME_UNKNOWN, NAN3
        if _finite(p) and (local := _local_frame(int(msg.frame_id), p)) is not None:
            kind, position = local
            pose_frame = POSE_FRAME_NED if kind == "ned" else POSE_FRAME_FRD
        q = tuple(float(v) for v in msg.q)
        v = (float(msg.vx), float(msg.vy), float(msg.vz))
        vel_frame, velocity = VELOCITY_FRAME_UNKNOWN, NAN3
        if _finite(v):
            child = int(msg.child_frame_id)
            if (local := _local_frame(child, v)) is not None:
                kind, velocity = local
                vel_frame = VELOCITY_FRAME_NED if kind == "ned" else VELOCITY_FRAME_FRD
            elif child in (MAV_FRAME_BODY_NED, MAV_FRAME_BODY_OFFSET_NED, MAV_FRAME_BODY_FRD):
                vel_frame, velocity = VELOCITY_FRAME_BODY_FRD, v
        return {
            "timestamp": here_ns // 1000,
            "timestamp_sample": self.sync_stamp_us(int(msg.time_usec), here_ns),
            "pose_frame": pose_frame,
            "position": position,
            "q": q if _finite(q) else (math.nan,) * 4,
            "velocity_frame": vel_frame,
            "velocity": velocity,
            "reset_counter": int(msg.reset_counter),
            "quality": int(msg.quality),
        }

    def _publish_ev(self, topic: str, odom: dict[str, Any], now_us: int) -> None:
        """vehicle_visual_odometry -> EKF2's EV buffer (Ekf::setExtVisionData)."""
        self.topics[topic].publish(odom, now_us)
        time_us = int(odom["timestamp_sample"] - self._p("EKF2_EV_DELAY") * 1000)
        if self.buffer.maxlen != self._buffer_length():
            self.buffer = deque(self.buffer, maxlen=self._buffer_length())
        if self.buffer and time_us <= self.buffer[-1].time_us:
            return  # not newer than the newest buffered sample: EKF2 drops it
        self.buffer.append(
            EvSample(
                time_us,
                int(odom["pose_frame"]),
                odom["position"],
                odom["q"],
                int(odom["velocity_frame"]),
                odom["velocity"],
                int(odom["reset_counter"]),
                int(odom["quality"]),
            )
        )
        self.last_push_us = now_us

    def on_timesync_reply(self, tc1_ns: int, ts1_ns: int, here_ns: int) -> None:
        """A TIMESYNC answer from the companion (PX4 publishes timesync_status for each)."""
        sync = self.sync_of()
        self.topics["timesync_status"].publish(
            {
                "timestamp": here_ns // 1000,
                "source_protocol": 0,  # MAVLink
                "remote_timestamp": tc1_ns // 1000,
                "observed_offset": ((ts1_ns + here_ns) // 2 - tc1_ns) // 1000,
                "estimated_offset": int(sync.offset_at(here_ns) // 1000) if sync.converged else 0,
                "round_trip_time": (here_ns - ts1_ns) // 1000,
            },
            here_ns // 1000,
        )

    # ---------------------------------------------------------------- the filter
    def _pop_first_older_than(self, horizon_us: int) -> EvSample | None:
        """RingBuffer::pop_first_older_than: the newest sample with time <= horizon < time +
        100 ms; it and everything older leave the buffer."""
        for i in range(len(self.buffer) - 1, -1, -1):
            s = self.buffer[i]
            if s.time_us <= horizon_us < s.time_us + BUFFER_MATCH_US:
                for _ in range(i + 1):
                    self.buffer.popleft()
                return s
        return None

    def _set(self, flag: str, on: bool) -> None:
        if self.flags[flag] != on:
            self.flags[flag] = on
            self.control_status_changes += 1
            if flag in ("ev_pos", "ev_hgt", "ev_vel", "ev_yaw"):
                if on:
                    self.fusion_starts += 1
                else:
                    self.fusion_stops += 1

    def step(self, now_us: int) -> None:
        """One EKF2 update at the autopilot time ``now_us``."""
        horizon = now_us - int(self._p("EKF2_DELAY_MAX") * 1000)
        # the heading: the magnetometer's unless our yaw replaced it; our yaw aligns it only
        # in NED (ODOMETRY in LOCAL_FRD with EV yaw: never aligned, as PX4 SITL showed)
        ev_yaw_ned = self.flags["ev_yaw"] and self.ev_yaw_frame == POSE_FRAME_NED
        self._set("yaw_align", (self.mag_heading() and not self.flags["ev_yaw"]) or ev_yaw_ned)
        sample = self._pop_first_older_than(horizon)
        any_active = any(self.flags[f] for f in ("ev_pos", "ev_hgt", "ev_vel", "ev_yaw"))
        if sample is not None:
            self._fuse(sample, now_us)
        elif (
            any_active
            and self.prev is not None
            and horizon - self.prev.time_us > 2 * EV_MAX_INTERVAL_US
        ):
            for f in ("ev_pos", "ev_hgt", "ev_vel", "ev_yaw"):
                self._set(f, False)  # "vision data stopped"
        if self.flags["ev_pos"] or self.flags["ev_vel"]:
            self.last_aiding_us = now_us
        self._publish_status(now_us)

    def _fuse(self, s: EvSample, now_us: int) -> None:
        qmin = int(self.params.get("EKF2_EV_QMIN"))
        ctrl = self.ev_ctrl
        quality_ok = qmin <= 0 or s.quality >= qmin
        prev = self.prev
        newest = self.buffer[-1] if self.buffer else s
        starting = (
            quality_ok
            and prev is not None
            and s.time_us - prev.time_us < EV_MAX_INTERVAL_US
            and (qmin <= 0 or prev.quality >= qmin)
            and (qmin <= 0 or newest.quality >= qmin)
            and now_us - self.last_push_us < EV_MAX_INTERVAL_US
        )
        # yaw (ev_yaw_control): EV heading replaces the magnetometer; in NED it also aligns
        yaw_ok = bool(ctrl & EV_CTRL_YAW) and _finite(s.q) and s.pose_frame != POSE_FRAME_UNKNOWN
        self._part("ev_yaw", yaw_ok, starting)
        self.ev_yaw_frame = s.pose_frame
        if self.flags["ev_yaw"]:  # the EV heading becomes the EKF's: aligned only in NED
            self._set("yaw_align", s.pose_frame == POSE_FRAME_NED)
        # horizontal position (ev_pos_control)
        pos_ok = bool(ctrl & EV_CTRL_HPOS) and _finite(s.position[:2])
        if s.pose_frame == POSE_FRAME_NED:
            pos_ok = pos_ok and self.flags["yaw_align"]
        elif s.pose_frame != POSE_FRAME_FRD:
            pos_ok = False
        self._part("ev_pos", pos_ok, starting)
        # height (ev_height_control)
        hgt_ok = (
            bool(ctrl & EV_CTRL_VPOS)
            and math.isfinite(s.position[2])
            and s.pose_frame != POSE_FRAME_UNKNOWN
        )
        self._part("ev_hgt", hgt_ok, starting)
        # velocity (ev_vel_control)
        vel_ok = (
            bool(ctrl & EV_CTRL_VEL)
            and _finite(s.velocity)
            and s.velocity_frame != VELOCITY_FRAME_UNKNOWN
        )
        self._part("ev_vel", vel_ok, starting)
        if quality_ok:
            self.prev = s
        fused = self.flags["ev_pos"] and quality_ok
        self.topics["estimator_aid_src_ev_pos"].publish(
            {
                "timestamp": now_us,
                "timestamp_sample": s.time_us,
                "observation": s.position[:2],
                "innovation_rejected": self.flags["ev_pos"] and not quality_ok,
                "fused": fused,
            },
            now_us,
        )

    def _part(self, flag: str, continuing: bool, starting: bool) -> None:
        if self.flags[flag]:
            if not continuing:
                self._set(flag, False)
        elif continuing and starting:
            self._set(flag, True)

    # ---------------------------------------------------------------- outputs
    def local_position_valid(self, now_us: int) -> bool:
        """xy_valid (and v_xy_valid): horizontal aiding now, or dead reckoning for less than
        EKF2_NOAID_TOUT since it stopped."""
        if self.last_aiding_us == 0:
            return False
        return now_us - self.last_aiding_us < int(self.params.get("EKF2_NOAID_TOUT"))

    def range_height(self) -> bool:
        """The rangefinder is a height source (EKF2_RNG_CTRL enabled)."""
        return int(self.params.get("EKF2_RNG_CTRL")) == 2

    def estimator_status_flags(self, now_us: int) -> int:
        """MAVLink ESTIMATOR_STATUS.flags (ESTIMATOR_STATUS_FLAGS) as PX4's solution status."""
        flags = ESTIMATOR_ATTITUDE | ESTIMATOR_VELOCITY_VERT | ESTIMATOR_POS_VERT_ABS
        if self.local_position_valid(now_us):
            flags |= ESTIMATOR_VELOCITY_HORIZ | ESTIMATOR_POS_HORIZ_REL
            flags |= ESTIMATOR_PRED_POS_HORIZ_REL
        else:
            flags |= ESTIMATOR_CONST_POS_MODE
        if self.range_height():
            flags |= ESTIMATOR_POS_VERT_AGL
        return flags

    def _publish_status(self, now_us: int) -> None:
        f = self.flags
        mag = self.mag_heading() and not f["ev_yaw"]
        baro = int(self.params.get("EKF2_BARO_CTRL")) == 1
        valid = self.local_position_valid(now_us)
        self.topics["estimator_status_flags"].publish(
            {
                "timestamp": now_us,
                "control_status_changes": self.control_status_changes,
                "cs_tilt_align": f["tilt_align"],
                "cs_yaw_align": f["yaw_align"],
                "cs_gnss_pos": False,
                "cs_opt_flow": False,
                "cs_mag_hdg": False,
                "cs_mag_3d": mag,
                "cs_baro_hgt": baro,
                "cs_rng_hgt": self.range_height(),
                "cs_gps_hgt": False,
                "cs_ev_pos": f["ev_pos"],
                "cs_ev_yaw": f["ev_yaw"],
                "cs_ev_hgt": f["ev_hgt"],
                "cs_ev_vel": f["ev_vel"],
                "cs_inertial_dead_reckoning": valid and not (f["ev_pos"] or f["ev_vel"]),
                "cs_mag": mag,
            },
            now_us,
        )
        if self.truth is not None and now_us - self._lpos_us >= LOCAL_POSITION_PERIOD_US:
            self._lpos_us = now_us
            pos, vel = self.truth(now_us)
            self.topics["vehicle_local_position"].publish(
                {
                    "timestamp": now_us,
                    "xy_valid": valid,
                    "z_valid": True,
                    "v_xy_valid": valid,
                    "v_z_valid": True,
                    "x": float(pos[0]),
                    "y": float(pos[1]),
                    "z": float(pos[2]),
                    "vx": float(vel[0]),
                    "vy": float(vel[1]),
                    "vz": float(vel[2]),
                    "dead_reckoning": valid and not (f["ev_pos"] or f["ev_vel"]),
                },
                now_us,
            )


def _quat_from_euler(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """Hamilton w, x, y, z of ZYX Euler angles [rad] (matrix::Quatf(Eulerf(...)))."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )
