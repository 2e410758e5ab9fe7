"""The PX4 services of the SITL autopilot beyond its sensor streams: parameters, the emulated
EV fusion, the MAVLink shell, and a second MAVLink endpoint for a ground station.

The second endpoint plays PX4 SITL's GCS instance (``mavlink start -u 18570 -o 14550``): it
listens on ``gcs_listen_port`` and streams to ``gcs_port`` on 127.0.0.1 (or to the last sender
of a HEARTBEAT: a ground station on an ephemeral port); answers go to whoever asked, so that a
one-shot script does not steal the streams. A ground-station tool (QGroundControl, MAVSDK:
``companion px4 check`` / ``configure``) talks to the autopilot there while the companion
service holds the onboard port; on a real board a telemetry radio or the USB port plays that
role. On it: HEARTBEAT 1 Hz (armed flag), ESTIMATOR_STATUS 1 Hz, LOCAL_POSITION_NED 10 Hz (only
while the local position is valid, as PX4 sends it), STATUSTEXT, the parameter protocol, the
shell, TIMESYNC answers, AUTOPILOT_VERSION on request (PARAM_ENCODE_BYTEWISE among its
capabilities) and a COMMAND_ACK for every command (UNSUPPORTED for what the stub does not do).
The onboard link gets the parameter protocol and the shell too; TIMESYNC replies from the
companion feed the emulated ``timesync_status``. Like PX4 SITL (POSIX), the stub sends to the
companion's fixed port from the start; PX4 on a flight controller (NuttX) instead waits for a
first packet to learn its UDP partner (and broadcasts before that only outside Onboard mode,
with MAV_n_BROADCAST = 1), which ``companion px4 check`` reports for a service on another host.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Coroutine
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from companion.drivers.mavlink_parser import LinkStats, Parser
from companion.drivers.timesync import ClockSync
from companion.sitl.stub.ekf_fusion import EvFusion
from companion.sitl.stub.faults import active
from companion.sitl.stub.options import AutopilotOptions
from companion.sitl.stub.px4_params import ParamServer, ParamStore, px4_parameters
from companion.sitl.stub.px4_shell import SERIAL_CONTROL_DEV_SHELL, NshShell, serial_control_replies

if TYPE_CHECKING:
    from companion.config import Config
    from companion.sitl.world.trajectory import Trajectory

log = logging.getLogger("sitl.px4")

MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_REQUEST_MESSAGE = 512
MSG_AUTOPILOT_VERSION = 148
MAV_RESULT_ACCEPTED, MAV_RESULT_UNSUPPORTED = 0, 3
MAV_SEVERITY_CRITICAL = 2
GCS_STREAMS_HZ = {0: 1.0, 230: 1.0, 32: 10.0}  # HEARTBEAT, ESTIMATOR_STATUS, LOCAL_POSITION_NED
EKF_PERIOD_S = 0.01  # EKF2_PREDICT_US


class ServedAutopilot(Protocol):
    """What the PX4 services use of the autopilot they serve
    (:class:`companion.sitl.stub.autopilot.SimAutopilot`): its configuration and options, its
    onboard MAVLink encoder and time sync, the flight's trajectory (the truth), its clocks
    (boot clock [ns], monotonic [ns], flight time [s]) and its onboard link's send."""

    cfg: Config
    opts: AutopilotOptions
    mav: mavlink.MAVLink
    sync: ClockSync
    trajectory: Trajectory

    def clock_ns(self, mono_ns: int) -> int: ...

    def mono_of_clock_ns(self, clock_ns: float) -> float: ...

    def t_sim_of_mono(self, mono_ns: float) -> float: ...

    def send(self, msg: Any) -> None: ...


class Px4Services:
    """Everything above, attached to one autopilot (``stub.px4`` of a :class:`ServedAutopilot`)."""

    def __init__(self, stub: ServedAutopilot) -> None:
        self.stub = stub
        o = stub.opts
        self.armed = o.armed
        self.params = ParamStore(px4_parameters(o.listen_port, o.companion_port))
        self.param_server = ParamServer(self.params, stub.mav)
        self.ekf = EvFusion(
            self.params,
            lambda: stub.sync,
            has_mag=o.has_mag,
            truth=self._truth,
            statustext=self.statustext,
        )
        self.gcs_mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.gcs_parser = Parser()
        self.gcs_stats = LinkStats()
        self.gcs_heartbeats = 0
        self.gcs_rates_hz = dict(GCS_STREAMS_HZ)
        self._gcs_transport: asyncio.DatagramTransport | None = None
        self._gcs_addr = (o.host, o.gcs_port)  # streams go here (a GCS's heartbeats move it)
        self._reply_to: tuple[str, int] | None = None  # the sender of the message in hand
        self.shells = {
            "onboard": NshShell(self.ekf.topics, self.now_us, lambda t: self._shell_out(t, False)),
            "gcs": NshShell(self.ekf.topics, self.now_us, lambda t: self._shell_out(t, True)),
        }

    # ---------------------------------------------------------------- clocks, truth
    def now_us(self) -> int:
        """The autopilot's boot clock [us] now."""
        return self.stub.clock_ns(time.monotonic_ns()) // 1000

    def _truth(self, now_us: int) -> tuple[Any, Any]:
        """Local position and velocity NED at autopilot time now_us (the flight's truth; held
        at its ends before and after the flight)."""
        stub = self.stub
        t = stub.t_sim_of_mono(stub.mono_of_clock_ns(now_us * 1000.0))
        t = float(np.clip(t, 0.0, stub.cfg.sitl.seconds))
        s = stub.trajectory.sample(np.array([t]))
        return s.position_m[0], s.velocity_m_s[0]

    def base_mode(self) -> int:
        """HEARTBEAT.base_mode (MAV_MODE_FLAG_SAFETY_ARMED while armed)."""
        return MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0

    # ---------------------------------------------------------------- both links
    def handle(self, msg: Any, gcs: bool, rx_ns: int) -> bool:
        """Messages every link serves; True when consumed (the caller does nothing more)."""
        kind = msg.get_type()
        reply = self._reply_gcs if gcs else self.stub.send
        if self.param_server.handle(msg, reply):
            return True
        if kind == "SERIAL_CONTROL":
            if int(msg.device) == SERIAL_CONTROL_DEV_SHELL:
                data = bytes(msg.data[: int(msg.count)])
                self.shells["gcs" if gcs else "onboard"].feed(data)
            return True
        if kind == "TIMESYNC" and int(msg.tc1) != 0 and not gcs:
            here = self.stub.clock_ns(rx_ns)
            self.ekf.on_timesync_reply(int(msg.tc1), int(msg.ts1), here)
            return False  # the stub's own time sync takes it too
        return False

    def on_vision(self, msg: Any, kind: str, rx_ns: int) -> None:
        """VISION_POSITION_ESTIMATE / ODOMETRY from the companion, received at rx_ns."""
        self.ekf.on_message(msg, kind, self.stub.clock_ns(rx_ns))

    def _shell_out(self, text: str, gcs: bool) -> None:
        for m in serial_control_replies(self.gcs_mav if gcs else self.stub.mav, text):
            (self._reply_gcs if gcs else self.stub.send)(m)

    def statustext(self, text: str) -> None:
        """A critical message to the ground station (PX4's mavlink_log_critical)."""
        self.send_gcs(self.gcs_mav.statustext_encode(MAV_SEVERITY_CRITICAL, text.encode()[:50]))

    # ---------------------------------------------------------------- the GCS endpoint
    async def open_gcs(self) -> None:
        """Bind the GCS endpoint (nothing when gcs_listen_port is 0)."""
        o = self.stub.opts
        if not o.gcs_listen_port:
            return
        services = self

        class Proto(asyncio.DatagramProtocol):
            def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
                services._on_gcs_datagram(data, addr)

        loop = asyncio.get_running_loop()
        try:
            self._gcs_transport, _ = await loop.create_datagram_endpoint(
                Proto, local_addr=(o.host, o.gcs_listen_port)
            )
        except OSError as e:  # another stub has it (tests in parallel): run without
            log.warning("SITL ground-station port %d unavailable (%s): none", o.gcs_listen_port, e)

    @property
    def gcs_open(self) -> bool:
        """The ground-station endpoint is bound."""
        return self._gcs_transport is not None

    def close(self) -> None:
        """Unbind the ground-station endpoint."""
        if self._gcs_transport is not None:
            self._gcs_transport.close()
            self._gcs_transport = None

    def rebooting(self) -> bool:
        """An injected autopilot reboot is on: the ground-station link is silent too."""
        stub = self.stub
        return "autopilot_reboot" in active(
            stub.opts.faults, stub.t_sim_of_mono(time.monotonic_ns())
        )

    def _reply_gcs(self, msg: Any) -> None:
        """An answer goes to whoever asked (a one-shot script too), a stream to the GCS."""
        self.send_gcs(msg, self._reply_to)

    def send_gcs(self, msg: Any, addr: tuple[str, int] | None = None) -> None:
        """A message on the ground-station endpoint (to its stream address by default)."""
        if self._gcs_transport is None or self.rebooting():
            return
        try:
            self._gcs_transport.sendto(msg.pack(self.gcs_mav), addr or self._gcs_addr)
            self.gcs_stats.tx_messages += 1
        except OSError:
            self.gcs_stats.tx_dropped += 1

    def forward_gcs(self, msg: Any) -> None:
        """A message from the companion, as received (its own system and component ids), to
        the ground station: PX4 forwards a link's messages to its other links (``-f``)."""
        if self._gcs_transport is None or self.rebooting():
            return
        try:
            self._gcs_transport.sendto(bytes(msg.get_msgbuf()), self._gcs_addr)
            self.gcs_stats.tx_messages += 1
        except OSError:
            self.gcs_stats.tx_dropped += 1

    def _on_gcs_datagram(self, data: bytes, addr: tuple[str, int]) -> None:
        rx_ns = time.monotonic_ns()
        if self.rebooting():
            return
        self._reply_to = addr
        try:
            for msg in self.gcs_parser.feed(data, self.gcs_stats):
                if msg.get_type() == "HEARTBEAT":
                    self._gcs_addr = addr  # a ground station announced itself: stream to it
                with contextlib.suppress(Exception):  # a bad message must not stop the stub
                    self._on_gcs_message(msg, rx_ns)
        finally:
            self._reply_to = None

    def _on_gcs_message(self, msg: Any, rx_ns: int) -> None:
        if self.handle(msg, True, rx_ns):
            return
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            self.gcs_heartbeats += 1
        elif kind == "TIMESYNC" and int(msg.tc1) == 0:
            now = self.stub.clock_ns(time.monotonic_ns())
            self._reply_gcs(self.gcs_mav.timesync_encode(now, int(msg.ts1)))
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            if int(msg.target_system) not in (0, 1):
                return
            self._reply_gcs(self.gcs_mav.command_ack_encode(int(msg.command), self._command(msg)))

    def _command(self, msg: Any) -> int:
        """Execute a command from the GCS link; its MAV_RESULT."""
        command = int(msg.command)
        if command == MAV_CMD_REQUEST_MESSAGE and int(msg.param1) == MSG_AUTOPILOT_VERSION:
            caps = (
                mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
                | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
            )
            version = (1 << 24) | (15 << 16) | (0 << 8) | 255  # 1.15.0 release
            self._reply_gcs(
                self.gcs_mav.autopilot_version_encode(
                    caps, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 1
                )
            )
            return MAV_RESULT_ACCEPTED
        if command == MAV_CMD_SET_MESSAGE_INTERVAL and int(msg.param1) in self.gcs_rates_hz:
            interval_us = float(msg.param2)
            if interval_us > 0:
                self.gcs_rates_hz[int(msg.param1)] = 1e6 / interval_us
            return MAV_RESULT_ACCEPTED
        return MAV_RESULT_UNSUPPORTED

    # ---------------------------------------------------------------- loops
    def loops(self) -> dict[str, Coroutine[Any, Any, None]]:
        """The coroutines the stub runs in its task group."""
        return {
            "px4-ekf2": self._ekf_loop(),
            "px4-gcs-heartbeat": self._stream(0, self._gcs_heartbeat),
            "px4-gcs-estimator-status": self._stream(230, self._gcs_estimator_status),
            "px4-gcs-local-position": self._stream(32, self._gcs_local_position),
        }

    async def _ekf_loop(self) -> None:
        next_t = time.monotonic()
        while True:
            self.ekf.step(self.now_us())
            next_t += EKF_PERIOD_S
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))

    async def _stream(self, msg_id: int, fn: Any) -> None:
        while True:
            if self._gcs_transport is not None:
                fn()
            await asyncio.sleep(1.0 / self.gcs_rates_hz[msg_id])

    def _gcs_heartbeat(self) -> None:
        self.send_gcs(self.gcs_mav.heartbeat_encode(2, 12, self.base_mode(), 0, 4))

    def _gcs_estimator_status(self) -> None:
        now = self.now_us()
        self.send_gcs(
            self.gcs_mav.estimator_status_encode(
                now, self.ekf.estimator_status_flags(now), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.1, 0.1
            )
        )

    def _gcs_local_position(self) -> None:
        lpos = self.ekf.topics["vehicle_local_position"].fields
        if lpos is None or not (lpos["xy_valid"] and lpos["v_xy_valid"]):
            return  # PX4's LOCAL_POSITION_NED stream sends nothing without a valid position
        self.send_gcs(
            self.gcs_mav.local_position_ned_encode(
                int(lpos["timestamp"]) // 1000,
                lpos["x"],
                lpos["y"],
                lpos["z"],
                lpos["vx"],
                lpos["vy"],
                lpos["vz"],
            )
        )
