"""The autopilot session: every MAVLink message in, our HEARTBEAT and TIMESYNC out.

Inputs: the link's received messages (``on_message``, on the event loop, stamped at reception
[ns]), a serial rangefinder's samples (``range_from_thread``, from its reader thread).
Outputs: the samples for the pipeline (``take_samples``: ranges, attitudes, IMU, in our clock
[us]), the autopilot's identity in ``ServiceStats`` (kind, system id, armed, last HEARTBEAT),
our clock sync (``sync``) and the model of PX4's (``px4_stamps``, ``stamp_at_send``), the
latest body rates [rad/s] (``attitude_rates``, for ODOMETRY). Message rates and the EKF origin
are asked for by ``autopilot_requests``; incoming COMMAND_ACK and GLOBAL_POSITION_INT go there.
With [gps] align: GPS_RAW_INT, GPS_GLOBAL_ORIGIN and the ATTITUDE yaw to the GPS frame
(``gps_frame``), PARAM_VALUE and COMMAND_ACK to its handover actions.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from companion.drivers import ardupilot, messages
from companion.drivers.timesync import ClockSync, RequesterModel, reply_for
from companion.service.autopilot_requests import EkfOrigin, MessageRates
from companion.service.gps_frame import GpsFrame
from companion.service.runtime import AutopilotKind, Runtime
from companion.types import F64, AttitudeSample, ImuSample, RangeSample

log = logging.getLogger("companion.service")

TIMESYNC_UNSETTLED_HZ = 10.0  # our TIMESYNC requests while the estimate is not settled
SAMPLE_QUEUE_MAX = 4096  # samples waiting for the next frame (if the pipeline stalls)

SampleT = TypeVar("SampleT", AttitudeSample, ImuSample)
Samples = tuple[list[RangeSample], list[AttitudeSample], list[ImuSample]]


def _sample_queue() -> deque[Any]:
    """Bounded: if the pipeline stalls, the oldest samples go first."""
    return deque(maxlen=SAMPLE_QUEUE_MAX)


@dataclass(eq=False, repr=False)
class AutopilotSession:
    """The link's messages handled by kind (a dispatch table), our HEARTBEAT and TIMESYNC."""

    rt: Runtime
    link: Any
    # the sensors the autopilot reports (DISTANCE_SENSOR) by id; one wired to the
    # companion (a TFmini on serial) is read here only, so the autopilot's own
    # rangefinder with the same id (PX4 SIH streams id 0) is not mixed into it
    sensors: dict[int, Any]
    sync: ClockSync  # our estimate of the autopilot's clock
    px4_stamps: RequesterModel  # PX4's own time sync as our answers drive it
    rates: MessageRates
    origin: EkfOrigin
    gps: GpsFrame | None = None  # [gps] align: the GPS frame fed here
    # ts1 of our recent requests
    timesync_sent: deque[int] = field(init=False, default_factory=lambda: deque(maxlen=16))
    # the latest ATTITUDE's body rates [rad/s]
    attitude_rates: F64 = field(init=False, default_factory=lambda: np.zeros(3))
    ranges: deque[RangeSample] = field(init=False, default_factory=_sample_queue)
    attitudes: deque[AttitudeSample] = field(init=False, default_factory=_sample_queue)
    imus: deque[ImuSample] = field(init=False, default_factory=_sample_queue)
    loop: asyncio.AbstractEventLoop | None = field(init=False, default=None)  # set on entry
    _handlers: dict[str, Callable[[Any, int], None]] = field(init=False)

    def __post_init__(self) -> None:
        self._handlers = {
            "TIMESYNC": self._on_timesync,
            "HEARTBEAT": self._on_heartbeat,
            "COMMAND_ACK": self._on_command_ack,
            "DISTANCE_SENSOR": self._on_distance_sensor,
            "GLOBAL_POSITION_INT": self._on_global_position,
            "ATTITUDE": self._on_attitude,
            "SCALED_IMU": self._on_scaled_imu,
        }
        if self.gps is not None:
            self._handlers["GPS_RAW_INT"] = self._on_gps_raw
            self._handlers["GPS_GLOBAL_ORIGIN"] = self._on_gps_origin
            self._handlers["PARAM_VALUE"] = self._on_param_value
            self._handlers["LOCAL_POSITION_NED"] = self._on_local_position

    # ------------------------------------------------------------------ messages in
    def on_message(self, msg: Any, rx_ns: int) -> None:
        """Every received message, on the event loop, stamped at reception. Messages of other
        systems are counted and dropped first (a ground station's or another vehicle's
        TIMESYNC requests are not ours to answer)."""
        if msg.get_srcSystem() != self.rt.config.service.system_id:
            self.rt.stats.foreign_messages += 1  # another vehicle or a ground station
            return
        handler = self._handlers.get(msg.get_type())
        if handler is not None:
            handler(msg, rx_ns)

    @staticmethod
    def _from_autopilot(msg: Any) -> bool:
        return bool(msg.get_srcComponent() == messages.MAV_COMP_ID_AUTOPILOT1)

    def _on_timesync(self, msg: Any, rx_ns: int) -> None:
        reply = reply_for(msg.tc1, msg.ts1, self.rt.clock())
        if reply is not None:  # a request: answer at once
            self.link.send(self.link.mav.timesync_encode(reply.tc1, reply.ts1))
            self.rt.stats.timesync_replies += 1
            if self._from_autopilot(msg):
                self._px4_answered(reply.ts1, reply.tc1)
        elif msg.ts1 in self.timesync_sent:  # an answer to one of our own requests
            self.timesync_sent.remove(msg.ts1)
            self.sync.on_reply(msg.tc1, msg.ts1, rx_ns)

    def _on_heartbeat(self, msg: Any, rx_ns: int) -> None:
        if (
            self._from_autopilot(msg)
            and msg.autopilot != messages.MAV_AUTOPILOT_INVALID
            and self.link.authentic(msg)  # signing: an unsigned one proves nothing
        ):
            s = self.rt.stats
            s.autopilot_heartbeat_ns = rx_ns
            s.autopilot_system_id = msg.get_srcSystem()
            name = ardupilot.autopilot_name(msg.autopilot)
            if name != s.autopilot:
                log.info("autopilot: %s (HEARTBEAT.autopilot %d)", name, msg.autopilot)
                s.autopilot = name
                s.autopilot_kind = AutopilotKind.from_heartbeat(msg.autopilot)
            armed = int(msg.base_mode) & messages.MAV_MODE_FLAG_SAFETY_ARMED
            s.autopilot_armed = bool(armed)

    def _on_command_ack(self, msg: Any, rx_ns: int) -> None:
        if (
            # the autopilot's, addressed to us (or to all)
            self._from_autopilot(msg)
            and getattr(msg, "target_system", 0) in (0, self.link.mav.srcSystem)
            and getattr(msg, "target_component", 0) in (0, self.link.mav.srcComponent)
        ):
            self.rates.on_command_ack(msg.command, msg.result)
            if self.gps is not None:
                self.gps.actions.on_command_ack(int(msg.command), int(msg.result))

    def _on_distance_sensor(self, msg: Any, rx_ns: int) -> None:
        s = self.rt.stats
        sample, why = messages.range_from_distance_sensor(
            msg, self.sensors, self.fc_to_us(msg), rx_ns // 1000
        )
        if sample is None:
            s.ranges_rejected += 1
            s.ranges_rejected_by[why] = s.ranges_rejected_by.get(why, 0) + 1
        else:
            s.ranges_in += 1
            self.ranges.append(sample)

    def _on_global_position(self, msg: Any, rx_ns: int) -> None:
        if self._from_autopilot(msg):
            self.origin.keeper.position(int(msg.lat), int(msg.lon), rx_ns)

    def _on_attitude(self, msg: Any, rx_ns: int) -> None:
        att = self._sample(msg, messages.attitude_from_message, self.attitudes, "attitudes")
        if att is not None:
            self.attitude_rates = att.rates_rad_s
            if self.gps is not None:
                self.gps.on_attitude(att.time_us, float(msg.yaw))

    def _on_gps_raw(self, msg: Any, rx_ns: int) -> None:
        if self.gps is not None and self._from_autopilot(msg):
            self.gps.on_gps_raw(msg, rx_ns // 1000)

    def _on_gps_origin(self, msg: Any, rx_ns: int) -> None:
        if self.gps is not None and self._from_autopilot(msg):
            self.gps.on_origin(int(msg.latitude), int(msg.longitude), int(msg.altitude))

    def _on_local_position(self, msg: Any, rx_ns: int) -> None:
        if self.gps is not None and self._from_autopilot(msg):
            self.gps.lag.on_local_position(self.fc_to_us(msg), np.array([msg.x, msg.y, msg.z]))

    def _on_param_value(self, msg: Any, rx_ns: int) -> None:
        if self.gps is not None and self._from_autopilot(msg):
            name = str(msg.param_id).split("\x00")[0]
            self.gps.actions.on_param_value(name, float(msg.param_value))

    def _on_scaled_imu(self, msg: Any, rx_ns: int) -> None:
        self._sample(msg, messages.imu_from_scaled, self.imus, "imus")

    def _sample(
        self,
        msg: Any,
        convert: Callable[[Any, int], SampleT | None],
        queue: deque[SampleT],
        counter: str,
    ) -> SampleT | None:
        """The autopilot's timed sample (ATTITUDE, SCALED_IMU) in our clock: queued and
        counted in ``ServiceStats.<counter>_in``, or refused (None) and counted in
        ``<counter>_rejected``; another component's is ignored."""
        if not self._from_autopilot(msg):
            return None
        sample = convert(msg, self.fc_to_us(msg))
        name = f"{counter}_in" if sample is not None else f"{counter}_rejected"
        setattr(self.rt.stats, name, getattr(self.rt.stats, name) + 1)
        if sample is not None:
            queue.append(sample)
        return sample

    def fc_to_us(self, msg: Any) -> int:
        """A message's time_boot_ms in our clock [us] (its reception time until synced)."""
        now = self.rt.clock()
        if not self.sync.converged:
            return now // 1000
        return self.sync.remote_to_local_us(int(msg.time_boot_ms) * 1000, now)

    def range_from_thread(self, sample: RangeSample) -> None:
        """A serial rangefinder's sample (its reader thread) -> the event loop's queue."""
        loop = self.loop
        if loop is None or loop.is_closed():
            return

        def put() -> None:
            if sample.is_valid:
                self.rt.stats.ranges_in += 1
                self.ranges.append(sample)
            else:
                self.rt.stats.ranges_rejected += 1

        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(put)

    def take_samples(self) -> Samples:
        """The samples queued since the last frame (ranges, attitudes, IMU), queues emptied."""
        taken = (list(self.ranges), list(self.attitudes), list(self.imus))
        self.ranges.clear()
        self.attitudes.clear()
        self.imus.clear()
        return taken

    # ------------------------------------------------------------------ PX4's time sync
    def _px4_answered(self, ts1: int, tc1: int) -> None:
        """A TIMESYNC request of the autopilot answered: our model of PX4's time sync
        follows it; a reset (its clock jumped) is warned, the convergence logged."""
        model = self.px4_stamps
        before = (model.converts, model.resets)
        model.on_answer(ts1, tc1)
        if self.rt.stats.autopilot_kind is not AutopilotKind.PX4:
            return
        if model.resets != before[1]:
            self.rt.warn(
                "autopilot clock jumped: PX4 stamps our poses on arrival until its time sync "
                "converges again (~500 answers)"
                + (
                    "; sending them as of their sending"
                    if self.rt.config.service.px4_stamp_at_send
                    else ""
                )
            )
        elif model.converts and not before[0]:
            log.info("PX4 converts our stamps now (%d TIMESYNC answers)", model.sequence)

    def stamp_at_send(self) -> bool:
        """Whether PX4 stamps our poses with their arrival now, by our model of its time
        sync (drivers/timesync.py, RequesterModel): then they go out as of their sending
        (``service.px4_stamp_at_send``; a pose so sent is right in either state of PX4, so
        the model errs toward it)."""
        return (
            self.rt.config.service.px4_stamp_at_send
            and self.rt.stats.autopilot_kind is AutopilotKind.PX4
            and not self.px4_stamps.converts
        )

    # ------------------------------------------------------------------ loops
    async def heartbeat_loop(self, tracking: Callable[[], bool]) -> None:
        """Our HEARTBEAT at 1 Hz: ACTIVE while the VO tracks (``tracking()``), else STANDBY."""
        mav = self.link.mav
        while not self.rt.stopping:
            state = messages.MAV_STATE_ACTIVE if tracking() else messages.MAV_STATE_STANDBY
            self.link.send(
                mav.heartbeat_encode(
                    messages.MAV_TYPE_ONBOARD_CONTROLLER,
                    messages.MAV_AUTOPILOT_INVALID,
                    0,
                    0,
                    state,
                )
            )
            await self.rt.sleep(1.0)

    async def timesync_loop(self) -> None:
        """Our TIMESYNC requests: service.timesync_rate_hz once the estimate is settled,
        TIMESYNC_UNSETTLED_HZ before (at the start, or confirming a jump of the autopilot's
        clock: its stamps are refused "from the past" until the estimate is new; 2.5 s of
        them at 2 Hz, 0.5 s at 10 Hz)."""
        rate_hz = self.rt.config.service.timesync_rate_hz
        while not self.rt.stopping:
            ts1 = self.rt.clock()
            self.timesync_sent.append(ts1)
            self.link.send(self.link.mav.timesync_encode(0, ts1))
            settled = self.sync.settled
            await self.rt.sleep(1.0 / (rate_hz if settled else max(rate_hz, TIMESYNC_UNSETTLED_HZ)))
