"""A minimal ground station for the closed loops: pumped from the flight's thread, it sends a
heartbeat a second, the loop's periodic messages (setpoints: SET_POSITION_TARGET_LOCAL_NED) and
commands, and records the telemetry both autopilots send (:class:`LoopTelemetry`).

Positions NED [m] in the autopilot's local frame; arrival times [ns] of our monotonic clock.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# SET_POSITION_TARGET_LOCAL_NED type_mask: position + velocity; no acceleration, no yaw, no
# yaw rate
POS_VEL_TYPE_MASK = 0b0000_1101_1100_0000


@dataclass
class LoopTelemetry:
    """What the ground station saw of either autopilot (arrival times: our monotonic clock
    [ns]); each loop's Telemetry adds its own."""

    lpos: list[tuple[int, int, float, float, float]] = field(default_factory=list)
    texts: list[tuple[float, int, str]] = field(default_factory=list)
    landed_state: int = 0
    armed: bool = False
    custom_mode: int = 0
    heartbeat_ns: int = 0
    version: str = ""
    phases: dict[str, float] = field(default_factory=dict)  # name -> monotonic [s]


class GcsBase:
    """A minimal ground station (pymavlink connection ``conn`` to system ``sysid``, component
    1), pumped from the flight's thread: a heartbeat a second, the subclass's periodic sends
    (:meth:`_send`), and the telemetry of :class:`LoopTelemetry` (the subclass's messages:
    :meth:`_on_other`)."""

    def __init__(self, conn: Any, sysid: int, tel: LoopTelemetry) -> None:
        self.conn = conn
        self.mav = conn.mav
        self.sysid = sysid
        self.tel = tel
        self.setpoint: tuple[np.ndarray, np.ndarray] | None = None  # NED position, velocity
        self._last_hb = 0.0
        self.t0 = time.monotonic()

    def pump(self, seconds: float) -> None:
        """Send and receive for ``seconds`` (at least one round)."""
        end = time.monotonic() + seconds
        while True:
            now = time.monotonic()
            if now - self._last_hb > 1.0:
                self.mav.heartbeat_send(6, 8, 0, 0, 0)  # GCS, INVALID autopilot
                self._last_hb = now
            self._send(now)
            if now >= end:
                return
            m = self.conn.recv_match(blocking=True, timeout=min(0.01, max(end - now, 0.001)))
            while m is not None:
                self._on(m)
                m = self.conn.recv_match(blocking=False)

    def _send(self, now: float) -> None:
        """The subclass's periodic messages (sticks, setpoints), at monotonic time ``now``."""

    def send_setpoint(self) -> None:
        """SET_POSITION_TARGET_LOCAL_NED of :attr:`setpoint` (position + velocity, from the
        EKF origin); nothing without one."""
        if self.setpoint is None:
            return
        p, v = self.setpoint
        self.mav.set_position_target_local_ned_send(
            0,
            self.sysid,
            1,
            1,  # MAV_FRAME_LOCAL_NED
            POS_VEL_TYPE_MASK,
            *(float(x) for x in p),
            *(float(x) for x in v),
            0,
            0,
            0,
            0,
            0,
        )

    def _on(self, m: Any) -> None:
        if m.get_srcSystem() != self.sysid or m.get_srcComponent() != 1:
            return
        kind = m.get_type()
        t = time.monotonic_ns()
        if kind == "LOCAL_POSITION_NED":
            self.tel.lpos.append((t, int(m.time_boot_ms), m.x, m.y, m.z))
        elif kind == "HEARTBEAT":
            self.tel.armed = bool(m.base_mode & 128)
            self.tel.custom_mode = int(m.custom_mode)
            self.tel.heartbeat_ns = t
        elif kind == "EXTENDED_SYS_STATE":
            self.tel.landed_state = int(m.landed_state)
        elif kind == "STATUSTEXT":
            self.tel.texts.append((time.monotonic() - self.t0, int(m.severity), str(m.text)))
        else:
            self._on_other(kind, m, t)

    def _on_other(self, kind: str, m: Any, t: int) -> None:
        """A message of another ``kind`` from the autopilot, arrived at ``t`` [ns]."""

    def command(self, cmd: int, *params: float) -> None:
        p = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
        self.mav.command_long_send(self.sysid, 1, cmd, 0, *p)

    def ask_streams(self, rates_hz: tuple[tuple[int, float], ...]) -> None:
        """MAV_CMD_SET_MESSAGE_INTERVAL for each (message id, rate [Hz]), then
        MAV_CMD_REQUEST_MESSAGE AUTOPILOT_VERSION."""
        for msg_id, hz in rates_hz:
            self.command(511, msg_id, 1e6 / hz)
            self.pump(0.1)
        self.command(512, 148)

    def position(self) -> np.ndarray | None:
        """The autopilot's latest LOCAL_POSITION_NED (3,), None before the first."""
        return np.array(self.tel.lpos[-1][2:5]) if self.tel.lpos else None
