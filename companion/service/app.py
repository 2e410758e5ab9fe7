"""The companion service: camera + DISTANCE_SENSOR + ATTITUDE in, VISION_POSITION_ESTIMATE /
ODOMETRY out (DESIGN.md section 6).

Structure: ``Service`` is an async context manager that enters its components (status socket,
serial rangefinders, the autopilot link, MQTT, one TaskGroup of named loops: heartbeat,
timesync, rates, camera, pipeline, health) through one AsyncExitStack, so a failure part-way
closes what was already open. The camera is read in its own thread into a short queue: the
pipeline takes the oldest frame not older than ``service.frame_wait_ms`` since its exposure
(so one slow keyframe costs latency, not a pose) and skips older ones for newer ones (so a board
too slow for the camera keeps a bounded latency); a skipped frame is counted as dropped. The
service does no maths: conversions to and from the wire are in ``drivers.messages``.

Threads, and the one rule for what crosses them:
- the event loop owns everything but the Pipeline: the link (TIMESYNC requests are answered
  inside the receive callback), ServiceStats, MQTT, the status socket;
- the worker thread (``asyncio.to_thread``; OpenCV and numpy release the GIL) owns the
  Pipeline. Ranges and attitudes are queued on the loop and handed over with the next frame,
  and after each frame the worker publishes ``pipeline_status``, a frozen snapshot
  (``Pipeline.status()``): the status, MQTT and the exit summary read only that;
- the camera reader thread writes the frame queue, the arrival times, its counters and the
  frame check only under ``_frames_lock`` (the loop reads them under it too), and reports a
  camera fault's start and end with ``call_soon_threadsafe``;
- serial readers (TFmini, a serial autopilot link) hand their samples and bytes to the loop
  with ``call_soon_threadsafe``.
So another thread either holds ``_frames_lock``, goes through ``call_soon_threadsafe``, or
replaces a frozen snapshot; nothing else is shared.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import json
import logging
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import Config
from companion.drivers import ardupilot, messages
from companion.drivers.backoff import Backoff
from companion.drivers.files import atomic_write
from companion.drivers.status import status_path
from companion.drivers.timesync import ClockSync, RequesterModel, reply_for
from companion.pipeline import Pipeline, PipelineStatus
from companion.redact import redact_text, redact_url, url_secrets
from companion.service import preflight, statustext
from companion.service.mqtt import MqttPublisher
from companion.service.recorder import Recorder
from companion.service.state import RESET_COUNTER_FILE, ResetCounter, state_dir
from companion.service.status import StatusServer
from companion.service.systemd import SdNotify
from companion.types import (
    AttitudeSample,
    CameraFrame,
    ImuSample,
    PoseEstimate,
    RangeSample,
    VoState,
)
from companion.vo.frame_check import FrameCheck, FrameProblem

log = logging.getLogger("companion.service")

MAX_CONSECUTIVE_PIPELINE_ERRORS = 30  # about a second of frames: then the service ends
RECENT_PROCESS = 20  # frames whose median processing time rules which queued one can be sent
FRAME_QUEUE_MAX = 8  # frames waiting for the pipeline at most (memory bound; frame_wait_ms rules)
CAMERA_SILENT_S = 1.0  # no frame for this long (or 10 frame periods, if longer): said, shown
AUTOPILOT_UNHEARD_S = 5.0  # no heartbeat this long after the start: said, with the link's error
HEALTH_PERIOD_S = 0.5
TIMESYNC_UNSETTLED_HZ = 10.0  # our TIMESYNC requests while the estimate is not settled


def now_ns() -> int:
    """Our clock: monotonic [ns] (the camera's and the time sync's)."""
    return time.monotonic_ns()


@dataclass
class ServiceStats:
    """Counters and recent timings (the status and the exit report read them)."""

    started_ns: int = field(default_factory=now_ns)
    frames_in: int = 0
    frames_dropped: int = 0
    frames_rejected: int = 0  # refused by the frame check (frozen, dark, saturated, ...)
    frames_processed: int = 0
    published: int = 0
    not_published: int = 0  # processed frames without a pose (not tracking / no scale)
    waited_for_attitude: int = 0  # frames held from the VO's start: no autopilot attitude yet
    stale: int = 0  # poses not sent because their frame was older than stale_frame_ms
    pipeline_errors: int = 0  # frames on which the pipeline raised (a bug: logged)
    ranges_in: int = 0
    ranges_rejected: int = 0
    ranges_rejected_by: dict[str, int] = field(default_factory=dict)  # reason -> count
    attitudes_in: int = 0
    attitudes_rejected: int = 0  # not finite or outside the Euler ranges
    imus_in: int = 0  # SCALED_IMU accelerometer samples taken (gravity for the VO)
    imus_rejected: int = 0  # not finite or beyond 16 g
    foreign_messages: int = 0  # from another system id than the configured autopilot's
    timesync_replies: int = 0
    stamped_at_send: int = 0  # poses sent as of their sending (PX4 stamping on arrival)
    last_reset_counter: int = 0
    autopilot_heartbeat_ns: int = 0
    autopilot_system_id: int = 0
    autopilot: str = ""  # who flies, from its HEARTBEAT: PX4, ArduPilot, ...
    autopilot_armed: bool = False  # its HEARTBEAT's MAV_MODE_FLAG_SAFETY_ARMED
    rates_acknowledged: set[int] = field(default_factory=set)
    # refused (COMMAND_ACK not ACCEPTED): not asked again until the autopilot comes back
    rates_refused: set[int] = field(default_factory=set)
    latency_ms: deque[float] = field(default_factory=lambda: deque(maxlen=20000))
    process_ms: deque[float] = field(default_factory=lambda: deque(maxlen=20000))
    # a frame's whole turn on the worker: the pipeline, the send and the keyframe work after it
    cycle_ms: deque[float] = field(default_factory=lambda: deque(maxlen=20000))
    publish_times_ns: deque[int] = field(default_factory=lambda: deque(maxlen=20000))
    warnings: deque[str] = field(default_factory=lambda: deque(maxlen=20))
    sent: deque[PoseEstimate] = field(default_factory=lambda: deque(maxlen=200))  # last poses
    statustexts: deque[tuple[int, str]] = field(default_factory=lambda: deque(maxlen=50))


class Service:
    """``async with Service(cfg) as s: await s.run(duration_s)``."""

    def __init__(self, config: Config) -> None:
        from companion.drivers.camera import open_camera
        from companion.drivers.mavlink import MavlinkLink

        self.config = config
        o = config.service
        # everything the config needs from the machine, before anything starts (exit 2)
        self.preflight_warnings = preflight.check(config)
        self._secrets = [*url_secrets(o.camera_url), *url_secrets(o.mavlink_url), o.mqtt.password]
        self.camera_url_shown = redact_url(o.camera_url)
        self.resets = ResetCounter(state_dir(o.state_dir) / RESET_COUNTER_FILE)
        self.pipeline = Pipeline(config)  # touched by the worker thread only
        # what the loop (status, MQTT, the exit summary) may read of it: a frozen snapshot the
        # worker replaces after each frame (a reference swap, atomic in CPython)
        self.pipeline_status = self.pipeline.status()
        self.sync = ClockSync()
        # PX4's own time sync as our answers drive it: whether it converts our stamps
        self.px4_stamps = RequesterModel(clock=self.sync)  # its round trips by our clock sync
        self.stats = ServiceStats()
        self.camera = open_camera(o.camera_url, camera=config.camera)  # size etc. checked
        from companion.drivers.signing import Signing

        self.link = MavlinkLink(
            o.mavlink_url,
            o.system_id,
            o.component_id,
            self._on_message,
            Signing.from_options(o.signing),  # a bad key file stops here (exit 2)
            o.mavlink_local_port,
            # the rest is skipped unparsed (floods, streams)
            wanted=messages.SERVICE_INPUTS | ardupilot.ARDUPILOT_INPUTS,
        )
        self.status_server = StatusServer(status_path(o.status_socket), self.status)
        self.mqtt: MqttPublisher | None = (
            MqttPublisher(o.mqtt, o.system_id) if o.mqtt.enabled else None
        )
        self.recorder = Recorder(config.record, config)  # its folder is made at start
        self._last_pose: PoseEstimate | None = None
        self.origin = ardupilot.OriginKeeper()  # ArduPilot: does its EKF hold our origin
        self.systemd = SdNotify()
        self.tfminis = [self._tfmini(rf) for rf in config.rangefinders if rf.serial]
        self._frame_times_ns: deque[int] = deque(maxlen=90)  # arrivals, for the camera fps
        # the sensors the autopilot reports (DISTANCE_SENSOR); one wired to the companion
        # (a TFmini on serial) is read here only, so the autopilot's own rangefinder with the
        # same id (PX4 SIH streams id 0) is not mixed into it
        self.sensors = {r.sensor_id: r for r in config.rangefinders if not r.serial}
        # frames waiting for the pipeline (bounded: the wait rule keeps it at a few)
        self._frames: deque[CameraFrame] = deque(maxlen=FRAME_QUEUE_MAX)
        self._frames_lock = threading.Lock()
        self._frame_ready = asyncio.Event()
        # bounded: if the pipeline stalls, the oldest samples go first
        self._ranges: deque[RangeSample] = deque(maxlen=4096)
        self._attitudes: deque[AttitudeSample] = deque(maxlen=4096)
        self._imus: deque[ImuSample] = deque(maxlen=4096)
        self._recent_poses: deque[PoseEstimate] = deque(maxlen=15)  # for centred ODOMETRY
        # centred ODOMETRY: no window over a gap longer than the age limit, and no stamp older
        # than the budget `px4 check` holds EKF2's horizon to (the config is frozen)
        self._centre_max_gap_us = 1e3 * config.service.stale_frame_ms
        self._oldest_stamp_us = 1e3 * config.oldest_stamp_ms()
        self._stop = asyncio.Event()
        self._tg: asyncio.TaskGroup | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._rate_pending: int | None = None
        self._timesync_sent: deque[int] = deque(maxlen=16)  # ts1 of our recent requests
        self._last_vo_state = VoState.INITIALIZING
        self._vo_start_logged = -1  # vo_resets of the last initialisation logged
        self._compass_logged = (False, False)  # (first fix logged, final one logged)
        self._first_frame_us: int | None = None  # for service.attitude_wait_s
        self.frame_check = FrameCheck(config.vo)  # on every delivered frame (reader thread)
        self._frame_problem: FrameProblem | None = None  # the camera fault in progress
        self._autopilot_lost = False
        self._sync_resets = 0
        self._attitude_rates = np.zeros(3)
        self._camera_silent = False
        self._stack: contextlib.AsyncExitStack | None = None
        self._switch_interval_s: float | None = None
        # STATUSTEXT to the ground station: events from snapshot transitions, rate-limited
        st = o.statustext
        self.statustext = statustext.Limiter(st.key_interval_s, st.burst, st.rate_hz, st.prefix)
        self._operator = statustext.INITIAL
        self._attitude_held = statustext.Held(statustext.ATTITUDE_HOLD_S)
        self._dpose_lock = statustext.RecentIncrease(statustext.DPOSE_LOCK_HOLD_S)
        self.dpose_status = (False, 0)  # (armed, poses used): the worker replaces it
        self._text_id = 0  # of the last chunked STATUSTEXT

    def _tfmini(self, rf: Any) -> Any:
        """A rangefinder wired to the companion (drivers.rangefinder)."""
        from companion.drivers.rangefinder import TfminiSerial

        device, baud = rf.serial, 115200
        head, _, tail = rf.serial.rpartition(":")
        if head and tail.isdigit():
            device, baud = head, int(tail)
        return TfminiSerial(device, rf.sensor_id, rf.min_m, rf.max_m, self._range_from_thread, baud)

    def _range_from_thread(self, sample: RangeSample) -> None:
        """A serial rangefinder's sample (its reader thread) -> the event loop's queue."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return

        def put() -> None:
            if sample.is_valid:
                self.stats.ranges_in += 1
                self._ranges.append(sample)
            else:
                self.stats.ranges_rejected += 1

        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(put)

    # ------------------------------------------------------------------ lifecycle
    async def __aenter__(self) -> Service:
        """Enter the components in order through one AsyncExitStack: a failure part-way
        (a second instance on the status socket, a port taken) closes what was entered."""
        self._loop = asyncio.get_running_loop()
        o = self.config.service
        async with contextlib.AsyncExitStack() as stack:
            # first: a second instance stops here (exit 2)
            await stack.enter_async_context(self.status_server)
            # let the event loop in often while the worker computes; restored on exit
            self._switch_interval_s = sys.getswitchinterval()
            stack.callback(sys.setswitchinterval, self._switch_interval_s)
            sys.setswitchinterval(0.0005)
            for drv in self.tfminis:
                drv.start()
                stack.callback(drv.close)
            await stack.enter_async_context(self.link)
            if self.mqtt is not None:
                await stack.enter_async_context(self.mqtt)
            loop = self._loop  # the recorder says why it stopped from its thread:
            stack.enter_context(
                self.recorder.running(lambda t: loop.call_soon_threadsafe(self._warn, t))
            )
            self._tg = await stack.enter_async_context(asyncio.TaskGroup())
            loops = {
                "heartbeat": self._heartbeat_loop(),
                "timesync": self._timesync_loop(),
                "rates": self._rates_loop(),
                "origin": self._origin_loop(),
                "camera": self._camera_loop(),
                "pipeline": self._pipeline_loop(),
                "health": self._health_loop(),
            }
            if o.statustext.enabled:
                loops["statustext"] = self._statustext_loop()
            if self.systemd.watchdog_s:
                loops["watchdog"] = self._watchdog_loop()
            if self.mqtt is not None:
                loops["mqtt-status"] = self._mqtt_status_loop()
                loops["mqtt-pose"] = self._mqtt_pose_loop()
            for name, coro in loops.items():
                self._tasks.append(self._tg.create_task(coro, name=name))
            self._stack = stack.pop_all()
        for text in self.preflight_warnings:
            self._warn(text)
        from companion import __version__

        for event in statustext.start_events(__version__, o.output, self.preflight_warnings):
            self.statustext.offer(event, now_ns() * 1e-9)  # sent once the link has a peer
        self.systemd.ready(f"link {o.mavlink_url}, camera {self.camera_url_shown}")
        return self

    async def __aexit__(self, *exc: Any) -> None:
        """Stop every loop; a loop's exception reaches the caller (as an ExceptionGroup)."""
        self.systemd.stopping()
        self._stop.set()
        self._frame_ready.set()
        self.camera.close()
        for task in self._tasks:
            task.cancel()
        if self._stack is not None:  # the link is still open: the last words on it
            self._restore_rates()
            if self.config.service.statustext.enabled:
                self._last_statustexts()
            stack, self._stack = self._stack, None
            await stack.__aexit__(*exc)

    async def run(self, duration_s: float | None = None) -> None:
        """Serve until ``stop()`` or for duration_s seconds."""
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._stop.wait(), duration_s)
        self._stop.set()

    def stop(self) -> None:
        self._stop.set()
        self._frame_ready.set()

    # ------------------------------------------------------------------ MAVLink in
    def _on_message(self, msg: Any, rx_ns: int) -> None:
        """Every received message, on the event loop, stamped at reception. Messages of other
        systems are counted and dropped first (a ground station's or another vehicle's
        TIMESYNC requests are not ours to answer)."""
        if msg.get_srcSystem() != self.config.service.system_id:
            self.stats.foreign_messages += 1  # another vehicle or a ground station: not ours
            return
        kind = msg.get_type()
        if kind == "TIMESYNC":
            reply = reply_for(msg.tc1, msg.ts1, now_ns())
            if reply is not None:  # a request: answer at once
                self.link.send(self.link.mav.timesync_encode(reply.tc1, reply.ts1))
                self.stats.timesync_replies += 1
                if msg.get_srcComponent() == messages.MAV_COMP_ID_AUTOPILOT1:
                    self._px4_answered(reply.ts1, reply.tc1)
            elif msg.ts1 in self._timesync_sent:  # an answer to one of our own requests
                self._timesync_sent.remove(msg.ts1)
                self.sync.on_reply(msg.tc1, msg.ts1, rx_ns)
            return
        if kind == "HEARTBEAT":
            if (
                msg.get_srcComponent() == messages.MAV_COMP_ID_AUTOPILOT1
                and msg.autopilot != messages.MAV_AUTOPILOT_INVALID
                and self.link.authentic(msg)  # signing: an unsigned one proves nothing
            ):
                self.stats.autopilot_heartbeat_ns = rx_ns
                self.stats.autopilot_system_id = msg.get_srcSystem()
                name = ardupilot.autopilot_name(msg.autopilot)
                if name != self.stats.autopilot:
                    log.info("autopilot: %s (HEARTBEAT.autopilot %d)", name, msg.autopilot)
                    self.stats.autopilot = name
                armed = int(msg.base_mode) & messages.MAV_MODE_FLAG_SAFETY_ARMED
                self.stats.autopilot_armed = bool(armed)
            return
        if kind == "COMMAND_ACK":
            if (
                # the autopilot's, addressed to us (or to all)
                msg.get_srcComponent() == messages.MAV_COMP_ID_AUTOPILOT1
                and getattr(msg, "target_system", 0) in (0, self.link.mav.srcSystem)
                and getattr(msg, "target_component", 0) in (0, self.link.mav.srcComponent)
                and msg.command == messages.MAV_CMD_SET_MESSAGE_INTERVAL
                and msg.result != messages.MAV_RESULT_IN_PROGRESS
                and self._rate_pending is not None
            ):
                if msg.result == messages.MAV_RESULT_ACCEPTED:
                    self.stats.rates_acknowledged.add(self._rate_pending)
                else:  # refused: asked again only once the autopilot is back (it rebooted)
                    self._rate_refused(self._rate_pending, int(msg.result))
                self._rate_pending = None
            return
        if kind == "DISTANCE_SENSOR":
            sample, why = messages.range_from_distance_sensor(
                msg, self.sensors, self._fc_to_us(msg), rx_ns // 1000
            )
            if sample is None:
                self.stats.ranges_rejected += 1
                self.stats.ranges_rejected_by[why] = self.stats.ranges_rejected_by.get(why, 0) + 1
            else:
                self.stats.ranges_in += 1
                self._ranges.append(sample)
            return
        if kind == "GLOBAL_POSITION_INT":
            if msg.get_srcComponent() == messages.MAV_COMP_ID_AUTOPILOT1:
                self.origin.position(int(msg.lat), int(msg.lon), rx_ns)
            return
        if kind == "ATTITUDE" and msg.get_srcComponent() == messages.MAV_COMP_ID_AUTOPILOT1:
            att = messages.attitude_from_message(msg, self._fc_to_us(msg))
            if att is None:
                self.stats.attitudes_rejected += 1
            else:
                self._attitude_rates = att.rates_rad_s
                self.stats.attitudes_in += 1
                self._attitudes.append(att)
            return
        if kind == "SCALED_IMU" and msg.get_srcComponent() == messages.MAV_COMP_ID_AUTOPILOT1:
            imu = messages.imu_from_scaled(msg, self._fc_to_us(msg))
            if imu is None:
                self.stats.imus_rejected += 1
            else:
                self.stats.imus_in += 1
                self._imus.append(imu)

    def _fc_to_us(self, msg: Any) -> int:
        """A message's time_boot_ms in our clock [us] (its reception time until synced)."""
        now = now_ns()
        if not self.sync.converged:
            return now // 1000
        return self.sync.remote_to_local_us(int(msg.time_boot_ms) * 1000, now)

    # ------------------------------------------------------------------ loops
    async def _heartbeat_loop(self) -> None:
        mav = self.link.mav
        while not self._stop.is_set():
            tracking = self._last_vo_state == VoState.TRACKING
            state = messages.MAV_STATE_ACTIVE if tracking else messages.MAV_STATE_STANDBY
            self.link.send(
                mav.heartbeat_encode(
                    messages.MAV_TYPE_ONBOARD_CONTROLLER,
                    messages.MAV_AUTOPILOT_INVALID,
                    0,
                    0,
                    state,
                )
            )
            await self._sleep(1.0)

    async def _timesync_loop(self) -> None:
        """Our TIMESYNC requests: service.timesync_rate_hz once the estimate is settled,
        TIMESYNC_UNSETTLED_HZ before (at the start, or confirming a jump of the autopilot's
        clock: its stamps are refused "from the past" until the estimate is new; 2.5 s of
        them at 2 Hz, 0.5 s at 10 Hz)."""
        rate_hz = self.config.service.timesync_rate_hz
        while not self._stop.is_set():
            ts1 = now_ns()
            self._timesync_sent.append(ts1)
            self.link.send(self.link.mav.timesync_encode(0, ts1))
            settled = self.sync.settled
            await self._sleep(1.0 / (rate_hz if settled else max(rate_hz, TIMESYNC_UNSETTLED_HZ)))

    def _rate_refused(self, msg_id: int, result: int) -> None:
        """The autopilot refused a message rate: said once, left at the autopilot's own."""
        if msg_id not in self.stats.rates_refused:
            self.stats.rates_refused.add(msg_id)
            self._warn(
                f"autopilot refused our rate for {messages.message_name(msg_id)} ({msg_id}): "
                f"COMMAND_ACK {messages.result_name(result)}; left at its own rate"
            )

    def _restore_rates(self) -> None:
        """On the way out: every rate the autopilot acknowledged back to its own default, so
        that a stopped companion leaves no 50 Hz TIMESYNC, ATTITUDE or IMU stream on the
        link (a telemetry radio's or a serial port's bandwidth). Not waited for: a restarted
        service asks again."""
        sysid = self.stats.autopilot_system_id
        for msg_id in sorted(self.stats.rates_acknowledged):
            self.link.send(messages.set_message_interval(self.link.mav, sysid, msg_id, None))

    async def _rates_loop(self) -> None:
        """Ask for the message rates (PX4: TIMESYNC first, the longest wait, then
        DISTANCE_SENSOR, ATTITUDE, SCALED_IMU), one request in flight at a time (PX4's
        COMMAND_ACK does not say which message it was for), each until acknowledged or refused
        (a refused one is not asked again, so it blocks none of the others); all again after 3 s
        of autopilot silence or a jump of its clock (it may have rebooted)."""
        o = self.config.service
        while not self._stop.is_set():
            wanted: dict[int, float] = {}
            if self.stats.autopilot == "PX4" and o.px4_timesync_rate_hz > 0:
                # PX4 converts our stamps after ~500 TIMESYNC answers: 50 s at its own 10 Hz
                wanted[messages.MSG_ID_TIMESYNC] = o.px4_timesync_rate_hz
            wanted[messages.MSG_ID_DISTANCE_SENSOR] = o.distance_sensor_rate_hz
            wanted[messages.MSG_ID_ATTITUDE] = o.attitude_rate_hz
            vo = self.config.vo
            imu_wanted = vo.imu_gravity_window_s > 0 or vo.heading_source == "magnetometer"
            if self.stats.autopilot == "PX4" and o.imu_rate_hz > 0 and imu_wanted:
                wanted[messages.MSG_ID_SCALED_IMU] = o.imu_rate_hz
            if self.stats.autopilot == "ArduPilot":  # whether it holds our EKF origin
                wanted[ardupilot.MSG_ID_GLOBAL_POSITION_INT] = ardupilot.POSITION_RATE_HZ
            hb = self.stats.autopilot_heartbeat_ns
            silent = bool(hb) and now_ns() - hb > 3_000_000_000
            if silent:  # it may reboot: its time sync starts again
                self.px4_stamps.reset()
            if silent and not self._autopilot_lost:
                self._warn("autopilot: no heartbeat for 3 s (link lost?)")
            elif self._autopilot_lost and not silent:
                self._warn("autopilot: heartbeat back; asking for the message rates again")
            self._autopilot_lost = silent
            if silent or self.sync.resets != self._sync_resets:  # gone, or its clock jumped
                self._sync_resets = self.sync.resets
                self.stats.rates_acknowledged.clear()
                self.stats.rates_refused.clear()
            done = self.stats.rates_acknowledged | self.stats.rates_refused
            missing = [m for m in wanted if m not in done]
            if hb and missing:
                self._rate_pending = missing[0]
                self.link.send(
                    messages.set_message_interval(
                        self.link.mav,
                        self.stats.autopilot_system_id,
                        missing[0],
                        wanted[missing[0]],
                    )
                )
                await self._sleep(0.3)
            else:
                await self._sleep(1.0)

    async def _origin_loop(self) -> None:
        """ArduPilot without GPS: SET_GPS_GLOBAL_ORIGIN every second until GLOBAL_POSITION_INT
        shows that EKF3 holds it (drivers/ardupilot.py: one sent before "EKF3 IMU0 initialised"
        is wiped); again after the autopilot fell silent (it may have rebooted). Not asked for
        ([service.ardupilot] set_origin false): said once if the EKF has none after 20 s."""
        a = self.config.service.ardupilot
        origin = ardupilot.Origin(a.origin_lat_deg, a.origin_lon_deg, a.origin_alt_m)
        first_heard: int | None = None
        said = False
        while not self._stop.is_set():
            now = now_ns()
            hb = self.stats.autopilot_heartbeat_ns
            if hb and now - hb > 3_000_000_000:
                self.origin.reset()
                first_heard = None
            elif hb and self.stats.autopilot == "ArduPilot":
                first_heard = first_heard or now
                if a.set_origin and self.origin.due(now):
                    self.link.send(
                        ardupilot.set_gps_global_origin(
                            self.link.mav, self.stats.autopilot_system_id, origin, now // 1000
                        )
                    )
                    self.origin.mark_sent(now)
                elif (
                    not a.set_origin
                    and not said
                    and not self.origin.held
                    and now - first_heard > 20_000_000_000
                ):
                    said = True
                    self._warn(
                        "ArduPilot has no EKF origin after 20 s (GLOBAL_POSITION_INT at 0, 0): "
                        "without GPS set [service.ardupilot] set_origin and the site's "
                        "origin_lat_deg / origin_lon_deg / origin_alt_m"
                    )
            await self._sleep(0.2)

    async def _camera_loop(self) -> None:
        """Read the camera in a daemon thread (a blocked driver call can never hold up the
        exit). A finite source (a file, a folder) that ends stops the service; a live one that
        ends or fails is reopened with capped, jittered backoff."""
        loop = asyncio.get_running_loop()
        backoff, reported = Backoff(0.5, 5.0), False
        while not self._stop.is_set():
            done: asyncio.Future[BaseException | None] = loop.create_future()
            frames_before = self.stats.frames_in

            def reader(done: asyncio.Future[BaseException | None] = done) -> None:
                error: BaseException | None = None
                seen_problem = self._frame_problem
                try:
                    for frame in self.camera.frames():
                        if self._stop.is_set():
                            break
                        # every delivered frame is checked (a few us), not only the ones the
                        # pipeline gets to: a frozen frame must be compared with the frame
                        # before it, not with the last one processed
                        with self._frames_lock:
                            problem = self.frame_check.check(frame)
                            if problem != seen_problem:  # the loop owns _frame_problem
                                loop.call_soon_threadsafe(self._camera_problem, problem)
                                seen_problem = problem
                            self.stats.frames_in += 1
                            self._frame_times_ns.append(now_ns())
                            if problem is not None:  # never reaches the pipeline: no pose
                                self.stats.frames_rejected += 1
                                continue
                            if len(self._frames) == self._frames.maxlen:
                                self.stats.frames_dropped += 1  # the oldest goes
                            self._frames.append(frame)
                        loop.call_soon_threadsafe(self._frame_ready.set)
                except Exception as e:  # a driver error: reported, the source is reopened
                    error = e

                def finish() -> None:
                    if not done.done():
                        done.set_result(error)

                with contextlib.suppress(RuntimeError):  # the loop may be closed at exit
                    loop.call_soon_threadsafe(finish)

            threading.Thread(target=reader, name="camera", daemon=True).start()
            error = await done
            if self._stop.is_set():
                return
            if error is None and self.camera.finite:
                self._warn("camera: the recording ended; stopping")
                self.stop()
                return
            if self.stats.frames_in > frames_before:  # it worked for a while: retry soon
                backoff.reset()
                reported = False
            if not reported:  # once per outage, not once per attempt
                why = f"failed: {error}" if error else "stream ended"
                self._warn(f"camera: {why}; reopening until it is back")
                reported = True
            await self._sleep(backoff.next_s())

    async def _watchdog_loop(self) -> None:
        """WATCHDOG=1 every half WatchdogSec, from the event loop: a stuck loop sends none."""
        assert self.systemd.watchdog_s is not None
        while not self._stop.is_set():
            self.systemd.watchdog()
            await self._sleep(self.systemd.watchdog_s / 2)

    async def _health_loop(self) -> None:
        """What an operator must hear about even when nothing raises: a camera that delivers
        nothing (a killed stream, a stalled driver, nobody listening), an autopilot never heard
        since the start (a wrong port or device), a serial rangefinder that cannot be opened."""
        started = now_ns()
        silent_after_s = max(CAMERA_SILENT_S, 10.0 / self.config.camera.rate_hz)
        unheard_said = False
        rf_said: dict[int, str] = {}
        while not self._stop.is_set():
            now = now_ns()
            with self._frames_lock:
                last = self._frame_times_ns[-1] if self._frame_times_ns else started
            silent_s = (now - last) * 1e-9
            if silent_s > silent_after_s and not self._camera_silent:
                self._camera_silent = True
                self._warn(
                    f"camera: no frames for {silent_s:.1f} s from {self.camera_url_shown}; "
                    "not publishing"
                )
            elif self._camera_silent and silent_s <= silent_after_s:
                self._camera_silent = False
                self._warn("camera: frames again")
            if (
                not unheard_said
                and not self.stats.autopilot_heartbeat_ns
                and (now - started) * 1e-9 > AUTOPILOT_UNHEARD_S
            ):
                unheard_said = True
                why = self.link.stats.last_error
                self._warn(
                    f"autopilot: no heartbeat on {self.config.service.mavlink_url} for "
                    f"{AUTOPILOT_UNHEARD_S:g} s" + (f" ({why})" if why else "")
                )
            for drv in self.tfminis:
                err = drv.last_error
                if err and rf_said.get(drv.sensor_id) != err:
                    self._warn(f"rangefinder {drv.sensor_id}: {err}")
                elif not err and drv.sensor_id in rf_said:
                    self._warn(f"rangefinder {drv.sensor_id}: {drv.device} open")
                if err:
                    rf_said[drv.sensor_id] = err
                else:
                    rf_said.pop(drv.sensor_id, None)
            await self._sleep(HEALTH_PERIOD_S)

    # ------------------------------------------------------------------ STATUSTEXT
    def _operator_state(self, now: int) -> statustext.OperatorState:
        """What the operator cares about now, from the service's own state (the loop's)."""
        s, p = self.stats, self.pipeline_status
        camera = "no frames" if self._camera_silent else None
        if camera is not None and self.camera.last_error_brief:  # a size refused, say which
            camera = f"no frames ({self.camera.last_error_brief})"
        if camera is None and self._frame_problem is not None:
            camera = self._frame_problem.value
        tracking = p.vo_state == VoState.TRACKING.name
        t_s = now * 1e-9
        dpose_armed, dpose_used = self.dpose_status
        hb = s.autopilot_heartbeat_ns
        return statustext.OperatorState(
            camera=camera,
            vo_state=p.vo_state,
            vo_resets=p.vo_resets,
            reset_counter=s.last_reset_counter if s.published else None,
            scale_ready=tracking and p.scale is not None,
            scale_sensors=p.sensors_used,
            attitude_ready=self._attitude_held.update(tracking and p.roll_deg is not None, t_s),
            autopilot_silent_s=(now - hb) * 1e-9 if hb else None,
            rangefinder_faults=frozenset(d.sensor_id for d in self.tfminis if d.last_error),
            dpose_armed=dpose_armed,
            dpose_locked=self._dpose_lock.update(dpose_used, t_s),
            armed=s.autopilot_armed,
            link_rival=self.link.rival_address(now),
        )

    async def _statustext_loop(self) -> None:
        """Every STATUSTEXT_PERIOD_S: the events between the last snapshot and this one go to
        the limiter; what it lets out is sent while the link has somebody to send to."""
        while not self._stop.is_set():
            now = now_ns()
            cur = self._operator_state(now)
            for event in statustext.transitions(self._operator, cur):
                self.statustext.offer(event, now * 1e-9)
            self._operator = cur
            if self.link.connected:
                for severity, text in self.statustext.take(now * 1e-9):
                    self._send_statustext(severity, text)
            await self._sleep(statustext.STATUSTEXT_PERIOD_S)

    def _send_statustext(self, severity: int, text: str) -> None:
        """One text on the link (in chunks sharing an id when it is longer than 50)."""
        self._text_id = self._text_id % 0xFFFF + 1
        for msg in messages.statustext(self.link.mav, severity, text, self._text_id):
            self.link.send(msg)
        self.stats.statustexts.append((int(severity), text))

    def _last_statustexts(self) -> None:
        """At exit: what is still pending, then why we stop (beyond the limits: bounded)."""
        failed = [
            t for t in self._tasks if t.done() and not t.cancelled() and t.exception() is not None
        ]
        error = None
        if failed:
            exc = failed[0].exception()
            error = f"{failed[0].get_name()} error ({type(exc).__name__})"
        now_s = now_ns() * 1e-9
        self.statustext.offer(statustext.stop_event(error, self.stats.autopilot_armed), now_s)
        for severity, text in self.statustext.drain(now_s):
            self._send_statustext(severity, text)

    def _warn(self, text: str) -> None:
        text = redact_text(text, self._secrets)  # a driver's error may quote the camera URL
        log.warning(text)
        self.stats.warnings.append(text)
        if self.mqtt is not None:
            self.mqtt.publish_event(text)

    async def _mqtt_status_loop(self) -> None:
        assert self.mqtt is not None
        while not self._stop.is_set():
            self.mqtt.publish_status(self.status())
            await self._sleep(1.0 / self.config.service.mqtt.status_hz)

    async def _mqtt_pose_loop(self) -> None:
        assert self.mqtt is not None
        sent_time = -1
        while not self._stop.is_set():
            pose = self._last_pose
            if pose is not None and pose.time_us != sent_time:
                sent_time = pose.time_us
                self.mqtt.publish_pose(
                    {
                        "time_us": pose.time_us,
                        "position_ned_m": pose.position_ned_m.tolist(),
                        "quat_wxyz": pose.quat_wxyz_ned_frd.tolist(),
                        "reset_counter": pose.reset_counter,
                        "quality_pct": pose.quality_pct,
                    }
                )
            await self._sleep(1.0 / self.config.service.mqtt.pose_hz)

    async def _pipeline_loop(self) -> None:
        failures = 0
        while not self._stop.is_set():
            frame = self._next_frame()
            if frame is None:
                await self._frame_ready.wait()
                self._frame_ready.clear()
                continue
            ranges, atts, imus = list(self._ranges), list(self._attitudes), list(self._imus)
            self._ranges.clear()
            self._attitudes.clear()
            self._imus.clear()
            t0 = time.perf_counter()
            try:
                pose = await asyncio.to_thread(self._process, frame, ranges, atts, imus)
            except Exception:
                # a bug on one frame must not take the autopilot's estimate down for good:
                # log it, count it, skip the frame; a persistent failure ends the service
                # (systemd restarts it)
                log.exception("pipeline failed on frame %d", frame.seq)
                self.stats.pipeline_errors += 1
                failures += 1
                if failures >= MAX_CONSECUTIVE_PIPELINE_ERRORS:
                    raise
                continue
            failures = 0
            self.stats.process_ms.append((time.perf_counter() - t0) * 1e3)
            self.stats.frames_processed += 1
            self._publish(frame, pose)
            await asyncio.to_thread(self._background)  # after the send
            self.stats.cycle_ms.append((time.perf_counter() - t0) * 1e3)

    def _next_frame(self) -> CameraFrame | None:
        """The oldest queued frame that can still be published: at most frame_wait_ms old
        (since exposure), and at most stale_frame_ms less the recent processing time (the
        median of the last RECENT_PROCESS frames), so that its pose is not too old to send
        once made; older ones are skipped (counted as dropped) while a newer frame exists.
        On a loaded machine (a climb's keyframes beside the simulator on 2 cores, session
        19) frames were processed only to be found stale: 1.3-1.7 s without a pose sent,
        and PX4 stopped fusing us; a frame skipped before the work leaves the time to the
        next one."""
        o = self.config.service
        limit_us = o.frame_wait_ms * 1e3
        recent = list(itertools.islice(reversed(self.stats.process_ms), RECENT_PROCESS))
        if len(recent) == RECENT_PROCESS:
            limit_us = min(limit_us, (o.stale_frame_ms - float(np.median(recent))) * 1e3)
        with self._frames_lock:
            now_us = now_ns() / 1e3
            while len(self._frames) > 1 and now_us - self._frames[0].time_us > limit_us:
                self._frames.popleft()
                self.stats.frames_dropped += 1
            return self._frames.popleft() if self._frames else None

    def _process(
        self,
        frame: CameraFrame,
        ranges: list[RangeSample],
        atts: list[AttitudeSample],
        imus: list[ImuSample] | None = None,
    ) -> PoseEstimate | None:
        """Worker thread: feed the queued samples, then the frame."""
        p = self.pipeline
        imus = imus or []
        for a in atts:
            p.feed_attitude(a)
        for m in imus:
            p.feed_imu(m)
        for r in ranges:
            p.feed_range(r)
        held = self._wait_for_attitude(frame)
        # recorded with whether it reached the VO: a replay then holds the same frames (the
        # wait depends on when the autopilot's HEARTBEAT came, which a replay does not have)
        self.recorder.frame(frame, ranges, atts, imus, held)  # a reference into its queue
        if held:
            return None
        pose = p.feed_frame(frame, checked=True)  # checked in the camera reader
        self.pipeline_status = p.status()  # a new frozen snapshot: the loop reads only this
        self.dpose_status = (p.dpose is not None and p.dpose.armed, p.dpose_used)
        return pose

    def _wait_for_attitude(self, frame: CameraFrame) -> bool:
        """Whether to hold this frame from a VO that has not started: the heading of the VO's
        frame is the autopilot's attitude at its start (else 0, the camera's first heading,
        and the autopilot's frame and ours are turned by its heading for the whole flight).
        ArduPilot streams ATTITUDE only once asked, some time after its first HEARTBEAT; after
        service.attitude_wait_s from the first frame held the VO starts without one (logged).
        Without an autopilot's HEARTBEAT (a replay, a bench test) nothing is held."""
        p = self.pipeline
        if (
            not self.stats.autopilot_heartbeat_ns  # no autopilot (yet): nothing to wait for
            or p.vo.state == VoState.TRACKING
            or p.attitude_at(frame.time_us) is not None
        ):
            return False
        if self._first_frame_us is None:
            self._first_frame_us = frame.time_us
        wait_us = self.config.service.attitude_wait_s * 1e6
        if wait_us <= 0 or frame.time_us - self._first_frame_us > wait_us:
            return False
        self.stats.waited_for_attitude += 1
        return True

    def _background(self) -> None:
        """Worker thread: the keyframe work the pose did not need, then a new snapshot."""
        if self.pipeline.background_work():
            self.pipeline_status = self.pipeline.status()

    def _log_vo_start(self, p: PipelineStatus) -> None:
        """Once per VO initialisation: which heading its frame has (the autopilot's, or none:
        then our north is the camera's first heading and the autopilot's frame is turned)."""
        if p.vo_resets == self._vo_start_logged:
            return
        self._vo_start_logged = p.vo_resets
        if p.vo_heading_deg is None:
            log.warning(
                "VO tracking (initialisation %d) without an autopilot attitude at hand: its "
                "heading 0 is the camera's first, not the autopilot's",
                p.vo_resets + 1,
            )
        else:
            log.info(
                "VO tracking (initialisation %d): its frame's heading %.2f deg (the autopilot's)",
                p.vo_resets + 1,
                p.vo_heading_deg,
            )

    def _log_compass_heading(self, p: PipelineStatus) -> None:
        """vo.heading_source = magnetometer: once when our compass first sets the frame's
        heading, and once when it stops refining it (the vehicle moved)."""
        if p.mag_heading_samples == 0 or p.vo_heading_deg is None:
            return
        ended = p.mag_heading_final
        if self._compass_logged == (True, ended):
            return
        self._compass_logged = (True, ended)
        log.info(
            "VO frame's heading %.2f deg from our compass (%d samples at rest, sigma %.2f deg)%s",
            p.vo_heading_deg,
            p.mag_heading_samples,
            p.mag_heading_sigma_deg or 0.0,
            ": final, the vehicle moved" if ended else "; refined until the vehicle moves",
        )

    def _camera_problem(self, problem: FrameProblem | None) -> None:
        """A camera fault starts or ends (on the event loop): said once, not per frame."""
        prev, self._frame_problem = self._frame_problem, problem
        if problem is not None:
            self._warn(f"camera: {problem.value} frames; not publishing")
        elif prev is not None:
            self._warn(f"camera: usable frames again (after {prev.value} ones)")

    def _publish(self, frame: CameraFrame, pose: PoseEstimate | None) -> None:
        self._last_vo_state = VoState[self.pipeline_status.vo_state]
        if self._last_vo_state == VoState.TRACKING:
            self._log_vo_start(self.pipeline_status)
            self._log_compass_heading(self.pipeline_status)
        if pose is None or not messages.is_finite_pose(pose):
            self.stats.not_published += 1
            return
        age_ms = (now_ns() / 1e3 - frame.time_us) / 1e3
        if age_ms > self.config.service.stale_frame_ms:  # too old to help the autopilot
            self.stats.stale += 1
            return
        # the counter on the wire never repeats the last one an earlier run sent
        pose = dataclasses.replace(pose, reset_counter=self.resets.wire(pose.reset_counter))
        o = self.config.service.output
        mav = self.link.mav
        sent = False
        # PX4 stamping on arrival: each message as of its sending, stamped then
        send_us = now_ns() // 1000 if self._stamp_at_send() else None
        if o in ("vision_position_estimate", "both"):
            vpe = pose if send_us is None else messages.pose_at(pose, send_us)
            sent |= self.link.send(messages.vision_position_estimate(mav, vpe))
        if o in ("odometry", "both"):
            rates = self._attitude_rates
            wire = pose
            n = self.config.service.odometry_centre_frames
            if n:
                self._recent_poses.append(pose)
                recent = list(self._recent_poses)[-n:]
                centred = (
                    messages.centred_pose(recent, self._centre_max_gap_us)
                    if len(recent) == n
                    else None
                )
                if centred is not None and now_ns() / 1e3 - centred.time_us > self._oldest_stamp_us:
                    # a window over a skipped frame is centred more than (N - 1) / 2 frames
                    # back: past the oldest stamp `px4 check` holds EKF2's horizon to, the
                    # newest pose goes out with the window's velocity (EKF2 drops samples
                    # older than its horizon: one went out 275 ms old against its 236,
                    # 2026-11-27, d7a0c08)
                    centred = dataclasses.replace(pose, velocity_ned_m_s=centred.velocity_ned_m_s)
                wire = (
                    centred
                    if centred is not None
                    else dataclasses.replace(pose, velocity_ned_m_s=np.full(3, np.nan))
                )
            if self.stats.autopilot == "ArduPilot":  # 0 would read "unknown" to AP_VisualOdom
                wire = dataclasses.replace(
                    pose, quality_pct=ardupilot.ardupilot_quality(pose.quality_pct)
                )
            if send_us is not None:
                wire = messages.pose_at(wire, send_us)
            so = self.config.service
            odo = messages.odometry(
                mav, wire, rates, so.odometry_velocity_sigma_m_s, frame=so.odometry_frame
            )
            if odo is not None:
                sent |= self.link.send(odo)
        if sent:
            t = now_ns()
            if self.stats.published and pose.reset_counter != self.stats.last_reset_counter:
                self._warn(f"VO re-initialised: reset_counter {pose.reset_counter}")
            self.stats.published += 1
            self.stats.stamped_at_send += send_us is not None
            self.stats.publish_times_ns.append(t)
            self.stats.latency_ms.append((t / 1e3 - frame.time_us) / 1e3)
            self.stats.last_reset_counter = pose.reset_counter
            self.stats.sent.append(pose)
            self.recorder.pose(pose)
            self._last_pose = pose

    def _px4_answered(self, ts1: int, tc1: int) -> None:
        """A TIMESYNC request of the autopilot answered: our model of PX4's time sync
        follows it; a reset (its clock jumped) is warned, the convergence logged."""
        model = self.px4_stamps
        before = (model.converts, model.resets)
        model.on_answer(ts1, tc1)
        if self.stats.autopilot != "PX4":
            return
        if model.resets != before[1]:
            self._warn(
                "autopilot clock jumped: PX4 stamps our poses on arrival until its time sync "
                "converges again (~500 answers)"
                + (
                    "; sending them as of their sending"
                    if self.config.service.px4_stamp_at_send
                    else ""
                )
            )
        elif model.converts and not before[0]:
            log.info("PX4 converts our stamps now (%d TIMESYNC answers)", model.sequence)

    def _stamp_at_send(self) -> bool:
        """Whether PX4 stamps our poses with their arrival now, by our model of its time
        sync (drivers/timesync.py, RequesterModel): then they go out as of their sending
        (``service.px4_stamp_at_send``; a pose so sent is right in either state of PX4, so
        the model errs toward it)."""
        return (
            self.config.service.px4_stamp_at_send
            and self.stats.autopilot == "PX4"
            and not self.px4_stamps.converts
        )

    async def _sleep(self, seconds: float) -> None:
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._stop.wait(), seconds)

    # ------------------------------------------------------------------ reporting
    def summary(self) -> dict[str, Any]:
        """Figures of the run so far (the exit report)."""
        s = self.stats
        lat = np.array(s.latency_ms)
        proc = np.array(s.process_ms)
        times = np.array(s.publish_times_ns) * 1e-9
        rate = float((len(times) - 1) / (times[-1] - times[0])) if len(times) > 1 else 0.0
        ps = self.pipeline_status
        return {
            "uptime_s": (now_ns() - s.started_ns) * 1e-9,
            "frames_in": s.frames_in,
            "frames_dropped": s.frames_dropped,
            "frames_rejected": s.frames_rejected,
            "frames_processed": s.frames_processed,
            "published": s.published,
            "not_published": s.not_published,
            "waited_for_attitude": s.waited_for_attitude,
            "publish_rate_hz": rate,
            "latency_ms_p50": float(np.percentile(lat, 50)) if len(lat) else None,
            "latency_ms_p99": float(np.percentile(lat, 99)) if len(lat) else None,
            "process_ms_p50": float(np.percentile(proc, 50)) if len(proc) else None,
            "process_ms_p99": float(np.percentile(proc, 99)) if len(proc) else None,
            # frames a second this machine let the pipeline turn over (1 / its mean turn):
            # the most it could publish here, whatever the camera's rate
            "pipeline_capacity_hz": (float(1e3 / np.mean(s.cycle_ms)) if len(s.cycle_ms) else None),
            "ranges_in": s.ranges_in,
            "ranges_rejected": s.ranges_rejected,
            "attitudes_in": s.attitudes_in,
            "imus_in": s.imus_in,
            "imu_gravity_frames": self.pipeline.gravity_used,
            "timesync_replies": s.timesync_replies,
            "timesync_converged": self.sync.converged,
            # PX4's side, modelled: whether it converts our stamps; poses sent as of sending
            "px4_converts_stamps": self.px4_stamps.converts,
            "px4_timesync_resets": self.px4_stamps.resets,
            # our answers PX4 discards for their round trip (late, forged), as modelled
            "px4_timesync_rtt_discarded": self.px4_stamps.rtt_discarded,
            "stamped_at_send": s.stamped_at_send,
            "rates_acknowledged": sorted(s.rates_acknowledged),
            "rates_refused": sorted(s.rates_refused),
            "autopilot_offset_ms": self.sync.offset_at(now_ns()) * 1e-6,
            "timesync_rtt_ms": self.sync.last_rtt_ns * 1e-6,
            "stale": s.stale,
            "pipeline_errors": s.pipeline_errors,
            "warnings": list(s.warnings),
            "vo_resets": ps.vo_resets,
            # our frame's heading [deg]: the autopilot's when the VO started (None: no attitude),
            # or our compass's (vo.heading_source = magnetometer) over the samples below
            "vo_heading_deg": ps.vo_heading_deg,
            "mag_heading_samples": ps.mag_heading_samples,
            "mag_heading_sigma_deg": ps.mag_heading_sigma_deg,
            "vo_gaps": ps.gaps,  # resets forced by > vo.max_gap_ms without frames
            "vo_held_for_attitude": ps.held_for_attitude,
            "vo_heading_restarts": ps.heading_restarts,
            "reset_counter": s.last_reset_counter,
            "scale": ps.scale,
            "link": vars(self.link.stats),
            "recorder": self.recorder.status(),
            "signing": self.link.signing.counters() if self.link.signing else None,
            "statustext": vars(self.statustext.stats),
            "mqtt": dataclasses.asdict(self.mqtt.stats) if self.mqtt else None,
            "status_socket": dataclasses.asdict(self.status_server.stats),
        }

    def status(self) -> dict[str, Any]:
        """What `companion status` shows (served as JSON on the status socket)."""
        now = now_ns()
        s, p, o = self.stats, self.pipeline_status, self.config.service
        pubs = [t for t in s.publish_times_ns if now - t < 5_000_000_000]
        lat = list(s.latency_ms)[-300:]
        return {
            "uptime_s": (now - s.started_ns) * 1e-9,
            "autopilot": self._autopilot_status(now),
            "camera": self._camera_status(now),
            "vo": {
                "state": "STALLED (no frames)" if self._camera_silent else p.vo_state,
                "features": p.features,
                "keyframes": p.keyframes,
                "resets": p.vo_resets,
                "heading_deg": p.vo_heading_deg,
                "heading_from_compass": p.mag_heading_samples > 0,
                # frames kept from a VO that was not tracking for want of an attitude, and
                # maps dropped for starting before the attitude stream: north is the autopilot's
                "held_for_attitude": p.held_for_attitude,
                "heading_restarts": p.heading_restarts,
            },
            "scale": {
                "method": p.method,
                "value": p.scale,
                "sigma": p.scale_sigma,
                "sensors_used": p.sensors_used,
                "match_rate": {str(k): v for k, v in p.match_rates},
                "ranges_in": s.ranges_in,
                "ranges_rejected": s.ranges_rejected + p.ranges_rejected,
                "rejected_by": dict(s.ranges_rejected_by),
            },
            "attitude": {
                "roll_deg": p.roll_deg,
                "pitch_deg": p.pitch_deg,
                "sigma_deg": p.tilt_sigma_deg,
                "compensation": self.config.attitude.compensate,
                "reasons": list(p.tilt_reasons),
            },
            "output": {
                "message": o.output,
                "rate_hz": len(pubs) / 5.0,
                "published": s.published,
                "reset_counter": s.last_reset_counter,
                "latency_ms_p50": float(np.percentile(lat, 50)) if lat else None,
            },
            "mqtt": {
                "enabled": self.mqtt is not None,
                "connected": self.mqtt.stats.connected if self.mqtt else False,
                "queued": self.mqtt.queued if self.mqtt else 0,
                "dropped": self.mqtt.stats.dropped if self.mqtt else 0,
                "published": self.mqtt.stats.published if self.mqtt else 0,
                "unasked": self.mqtt.stats.unasked if self.mqtt else 0,  # dropped, counted
            },
            "status_socket": dataclasses.asdict(self.status_server.stats),  # floods refused
            "recorder": self.recorder.status(),
            "warnings": list(s.warnings),
        }

    def _autopilot_status(self, now: int) -> dict[str, Any]:
        """The status's autopilot section: heartbeat, time sync, message counts, signing."""
        s, link = self.stats, self.link.stats
        return {
            "url": self.config.service.mavlink_url,
            "heartbeat_age_s": (now - s.autopilot_heartbeat_ns) * 1e-9
            if s.autopilot_heartbeat_ns
            else None,
            "system_id": s.autopilot_system_id or None,
            "type": s.autopilot or None,
            "ekf_origin": {
                "held": self.origin.held,
                "sent": self.origin.sent,
                "lost": self.origin.lost,
            }
            if s.autopilot == "ArduPilot"
            else None,
            "timesync_converged": self.sync.converged,
            "timesync_offset_ms": self.sync.offset_at(now) * 1e-6 if self.sync.converged else None,
            "timesync_rtt_ms": self.sync.last_rtt_ns * 1e-6,
            "px4_converts_stamps": self.px4_stamps.converts if s.autopilot == "PX4" else None,
            "px4_timesync_rtt_discarded": self.px4_stamps.rtt_discarded,
            "stamped_at_send": s.stamped_at_send,
            "rates_acknowledged": sorted(s.rates_acknowledged),
            "rates_refused": sorted(s.rates_refused),
            "rx_messages": link.rx_messages,
            "rx_bad": link.rx_bad,
            "handler_errors": link.handler_errors,
            "foreign_messages": s.foreign_messages + link.rx_foreign,
            "other_address": link.rx_other_address,
            "rx_overflow_bytes": link.rx_overflow_bytes,  # serial: faster than parsed, dropped
            # udpin: every source claiming the autopilot's system id (two: a spoofer, say)
            "claimants": self.link.claimants_status(now),
            "rivals_seen": link.rivals_seen,
            "attitudes_rejected": s.attitudes_rejected,
            "imus_rejected": s.imus_rejected,
            "signing": self.link.signing.counters() if self.link.signing else None,
        }

    def _camera_status(self, now: int) -> dict[str, Any]:
        """The status's camera section (read under the camera thread's lock)."""
        with self._frames_lock:
            frames = list(self._frame_times_ns)
            frames_in, dropped = self.stats.frames_in, self.stats.frames_dropped
            rejected = {k: v for k, v in self.frame_check.counts.items() if v}
        recent = [t for t in frames if now - t < 2_000_000_000]  # a dead camera shows 0 fps
        fps = (len(recent) - 1) / ((recent[-1] - recent[0]) * 1e-9) if len(recent) > 1 else 0.0
        problem = self._frame_problem.value if self._frame_problem else None
        if self._camera_silent:  # and why, when the driver said (a size refused, an error)
            why = self.camera.last_error
            problem = "no frames" + (f": {redact_text(why, self._secrets)}" if why else "")
        return {
            "url": self.camera_url_shown,
            "fps": fps,
            "frames": frames_in,
            "dropped": dropped,
            "stamps": self.camera.stamps,
            "last_frame_age_s": (now - frames[-1]) * 1e-9 if frames else None,
            "problem": problem,
            "rejected": rejected,
            "gaps": self.pipeline_status.gaps,
        }

    def write_report(self, path: Path) -> None:
        """The exit summary as JSON, written atomically (a full disk leaves no torn file and
        raises OSError for the caller to report)."""
        atomic_write(path, (json.dumps(self.summary(), indent=2) + "\n").encode(), 0o644)
