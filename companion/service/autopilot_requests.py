"""What the service asks of the autopilot: its message rates, and ArduPilot's EKF origin.

Inputs: the autopilot's identity and last HEARTBEAT (``ServiceStats``, kept by the autopilot
session), COMMAND_ACK (``MessageRates.on_command_ack``) and GLOBAL_POSITION_INT (fed to
``EkfOrigin.keeper``), our clock sync's resets. Outputs: SET_MESSAGE_INTERVAL and
SET_GPS_GLOBAL_ORIGIN on the link, the rates acknowledged and refused (``ServiceStats``),
warnings (an autopilot lost and back, a rate refused, an origin missing).
"""

from __future__ import annotations

from typing import Any

from companion.drivers import ardupilot, messages
from companion.drivers.timesync import ClockSync, RequesterModel
from companion.service.runtime import AutopilotKind, Runtime

AUTOPILOT_SILENT_NS = 3_000_000_000  # no HEARTBEAT this long: it may be rebooting
ORIGIN_UNHELD_SAY_NS = 20_000_000_000  # no EKF origin this long (not set by us): said once
MSG_ID_GPS_RAW_INT, MSG_ID_GPS_GLOBAL_ORIGIN, MSG_ID_PARAM_VALUE = 24, 49, 22
MSG_ID_LOCAL_POSITION_NED = 32
GPS_RATE_HZ, GPS_ORIGIN_RATE_HZ = 5.0, 1.0  # [gps] align: GPS_RAW_INT, GPS_GLOBAL_ORIGIN
LOCAL_POSITION_RATE_HZ = 20.0  # [gps] px4_loss_carry: EKF2's lag behind us before a loss
GPS_INPUTS = frozenset(
    {MSG_ID_GPS_RAW_INT, MSG_ID_GPS_GLOBAL_ORIGIN, MSG_ID_PARAM_VALUE, MSG_ID_LOCAL_POSITION_NED}
)


class MessageRates:
    """The message rates we need, asked one at a time until acknowledged or refused."""

    def __init__(self, rt: Runtime, link: Any, sync: ClockSync, px4_stamps: RequesterModel) -> None:
        self.rt = rt
        self.link = link
        self.sync = sync
        self.px4_stamps = px4_stamps
        self.pending: int | None = None  # the message id of the request in flight
        self._autopilot_lost = False
        self._sync_resets = 0

    def on_command_ack(self, command: int, result: int) -> None:
        """The autopilot's COMMAND_ACK addressed to us: the request in flight acknowledged
        (ACCEPTED) or refused (anything but IN_PROGRESS); other commands' are ignored."""
        if (
            command != messages.MAV_CMD_SET_MESSAGE_INTERVAL
            or result == messages.MAV_RESULT_IN_PROGRESS
            or self.pending is None
        ):
            return
        if result == messages.MAV_RESULT_ACCEPTED:
            self.rt.stats.rates_acknowledged.add(self.pending)
        else:  # refused: asked again only once the autopilot is back (it rebooted)
            self._refused(self.pending, int(result))
        self.pending = None

    def _refused(self, msg_id: int, result: int) -> None:
        """The autopilot refused a message rate: said once, left at the autopilot's own."""
        if msg_id not in self.rt.stats.rates_refused:
            self.rt.stats.rates_refused.add(msg_id)
            self.rt.warn(
                f"autopilot refused our rate for {messages.message_name(msg_id)} ({msg_id}): "
                f"COMMAND_ACK {messages.result_name(result)}; left at its own rate"
            )

    def restore(self) -> None:
        """On the way out: every rate the autopilot acknowledged back to its own default, so
        that a stopped companion leaves no 50 Hz TIMESYNC, ATTITUDE or IMU stream on the
        link (a telemetry radio's or a serial port's bandwidth). Not waited for: a restarted
        service asks again."""
        sysid = self.rt.stats.autopilot_system_id
        for msg_id in sorted(self.rt.stats.rates_acknowledged):
            self.link.send(messages.set_message_interval(self.link.mav, sysid, msg_id, None))

    def wanted(self) -> dict[int, float]:
        """Message id -> rate [Hz] to ask of the autopilot we have heard, in asking order."""
        o, vo = self.rt.config.service, self.rt.config.vo
        kind = self.rt.stats.autopilot_kind
        wanted: dict[int, float] = {}
        if kind is AutopilotKind.PX4 and o.px4_timesync_rate_hz > 0:
            # PX4 converts our stamps after ~500 TIMESYNC answers: 50 s at its own 10 Hz
            wanted[messages.MSG_ID_TIMESYNC] = o.px4_timesync_rate_hz
        wanted[messages.MSG_ID_DISTANCE_SENSOR] = o.distance_sensor_rate_hz
        wanted[messages.MSG_ID_ATTITUDE] = o.attitude_rate_hz
        imu_wanted = vo.imu_gravity_window_s > 0 or vo.heading_source == "magnetometer"
        if kind is AutopilotKind.PX4 and o.imu_rate_hz > 0 and imu_wanted:
            wanted[messages.MSG_ID_SCALED_IMU] = o.imu_rate_hz
        if kind is AutopilotKind.ARDUPILOT:  # whether it holds our EKF origin
            wanted[ardupilot.MSG_ID_GLOBAL_POSITION_INT] = ardupilot.POSITION_RATE_HZ
        g = self.rt.config.gps
        if g.align:  # the fixes and the origin they are about
            wanted[MSG_ID_GPS_RAW_INT] = GPS_RATE_HZ
            wanted[MSG_ID_GPS_GLOBAL_ORIGIN] = GPS_ORIGIN_RATE_HZ
        if g.align and g.px4_loss_carry and kind is AutopilotKind.PX4:
            wanted[MSG_ID_LOCAL_POSITION_NED] = LOCAL_POSITION_RATE_HZ
        return wanted

    async def loop(self) -> None:
        """Ask for the message rates (PX4: TIMESYNC first, the longest wait, then
        DISTANCE_SENSOR, ATTITUDE, SCALED_IMU), one request in flight at a time (PX4's
        COMMAND_ACK does not say which message it was for), each until acknowledged or refused
        (a refused one is not asked again, so it blocks none of the others); all again after 3 s
        of autopilot silence or a jump of its clock (it may have rebooted)."""
        s = self.rt.stats
        while not self.rt.stopping:
            wanted = self.wanted()
            hb = s.autopilot_heartbeat_ns
            silent = bool(hb) and self.rt.clock() - hb > AUTOPILOT_SILENT_NS
            if silent:  # it may reboot: its time sync starts again
                self.px4_stamps.reset()
            if silent and not self._autopilot_lost:
                self.rt.warn("autopilot: no heartbeat for 3 s (link lost?)")
            elif self._autopilot_lost and not silent:
                self.rt.warn("autopilot: heartbeat back; asking for the message rates again")
            self._autopilot_lost = silent
            if silent or self.sync.resets != self._sync_resets:  # gone, or its clock jumped
                self._sync_resets = self.sync.resets
                s.rates_acknowledged.clear()
                s.rates_refused.clear()
            done = s.rates_acknowledged | s.rates_refused
            missing = [m for m in wanted if m not in done]
            if hb and missing:
                self.pending = missing[0]
                self.link.send(
                    messages.set_message_interval(
                        self.link.mav, s.autopilot_system_id, missing[0], wanted[missing[0]]
                    )
                )
                await self.rt.sleep(0.3)
            else:
                await self.rt.sleep(1.0)


class EkfOrigin:
    """ArduPilot without GPS: our EKF origin sent until its EKF holds it."""

    def __init__(self, rt: Runtime, link: Any) -> None:
        self.rt = rt
        self.link = link
        self.keeper = ardupilot.OriginKeeper()  # does its EKF hold our origin

    async def loop(self) -> None:
        """SET_GPS_GLOBAL_ORIGIN every second until GLOBAL_POSITION_INT shows that EKF3 holds
        it (drivers/ardupilot.py: one sent before "EKF3 IMU0 initialised" is wiped); again
        after the autopilot fell silent (it may have rebooted). Not asked for
        ([service.ardupilot] set_origin false): said once if the EKF has none after 20 s."""
        a = self.rt.config.service.ardupilot
        origin = ardupilot.Origin(a.origin_lat_deg, a.origin_lon_deg, a.origin_alt_m)
        s, keeper = self.rt.stats, self.keeper
        first_heard: int | None = None
        said = False
        while not self.rt.stopping:
            now = self.rt.clock()
            hb = s.autopilot_heartbeat_ns
            if hb and now - hb > AUTOPILOT_SILENT_NS:
                keeper.reset()
                first_heard = None
            elif hb and s.autopilot_kind is AutopilotKind.ARDUPILOT:
                first_heard = first_heard or now
                if a.set_origin and keeper.due(now):
                    self.link.send(
                        ardupilot.set_gps_global_origin(
                            self.link.mav, s.autopilot_system_id, origin, now // 1000
                        )
                    )
                    keeper.mark_sent(now)
                elif (
                    not a.set_origin
                    and not said
                    and not keeper.held
                    and now - first_heard > ORIGIN_UNHELD_SAY_NS
                ):
                    said = True
                    self.rt.warn(
                        "ArduPilot has no EKF origin after 20 s (GLOBAL_POSITION_INT at 0, 0): "
                        "without GPS set [service.ardupilot] set_origin and the site's "
                        "origin_lat_deg / origin_lon_deg / origin_alt_m"
                    )
            await self.rt.sleep(0.2)
