"""A ground-station session with ArduPilot (pymavlink, blocking: callers run it in a thread).

Parameters: PARAM_REQUEST_LIST (missing indices asked again), PARAM_SET with the parameter's
own type and the value as a float (ArduPilot's convention: an integer travels as the float of
its value, never as its bytes), PARAM_REQUEST_READ to read one back. Watch: EKF_STATUS_REPORT,
GLOBAL_POSITION_INT, GPS_RAW_INT, STATUSTEXT (pre-arm reasons asked for with
MAV_CMD_RUN_PREARM_CHECKS), GPS_GLOBAL_ORIGIN, and the companion's own VISION_POSITION_ESTIMATE
/ ODOMETRY as ArduPilot forwards them to this link (its MAVLink routing sends broadcast messages
to every other link): their frame ids, quality and rate, as the autopilot received them.
"""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass, field
from typing import Any

from companion.autopilot.params import Param, Target
from companion.autopilot.reach import pymavlink_url
from companion.errors import AutopilotError, AutopilotUnreachableError

log = logging.getLogger("companion.autopilot")

INT_TYPES = frozenset({1, 2, 3, 4, 5, 6, 7, 8})  # MAV_PARAM_TYPE_UINT8 .. INT64
REAL32 = 9
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MSG_EKF_STATUS_REPORT, MSG_GLOBAL_POSITION_INT, MSG_GPS_RAW_INT = 193, 33, 24
MSG_GPS_GLOBAL_ORIGIN = 49
MAV_CMD_SET_MESSAGE_INTERVAL, MAV_CMD_REQUEST_MESSAGE, MAV_CMD_RUN_PREARM_CHECKS = 511, 512, 401


@dataclass
class CompanionSeen:
    """One of our messages as ArduPilot forwarded it (per message type)."""

    count: int = 0
    first_s: float | None = None
    last_s: float | None = None
    frame_id: int | None = None  # ODOMETRY
    child_frame_id: int | None = None  # ODOMETRY
    quality: int | None = None  # ODOMETRY
    component: int | None = None

    def rate_hz(self) -> float:
        if (
            self.count < 2
            or self.first_s is None
            or self.last_s is None
            or self.last_s <= self.first_s
        ):
            return 0.0
        return (self.count - 1) / (self.last_s - self.first_s)


@dataclass
class Watched:
    """What the watch saw."""

    ekf_flags: int | None = None  # the last EKF_STATUS_REPORT.flags
    position: tuple[int, int] | None = None  # the last GLOBAL_POSITION_INT lat/lon [degE7]
    origin: tuple[int, int, int] | None = None  # GPS_GLOBAL_ORIGIN lat/lon degE7, alt mm
    gps_seen: bool = False  # GPS_RAW_INT with fix_type >= 1
    statustexts: list[str] = field(default_factory=list)
    companion: dict[str, CompanionSeen] = field(default_factory=dict)  # by message type


class ArduPilotLink:
    """``with ArduPilotLink(url, timeout_s) as ap:`` a connected ArduPilot."""

    def __init__(self, url: str, timeout_s: float = 10.0) -> None:
        self.url = pymavlink_url(url)
        self.timeout_s = timeout_s
        self.conn: Any = None
        self.system_id = 0
        self.autopilot = ""
        self.base_mode = 0
        self.param_values: dict[str, tuple[float, int]] = {}
        self._param_index: dict[int, str] = {}
        self._param_count = 0

    def __enter__(self) -> ArduPilotLink:
        os.environ["MAVLINK20"] = "1"  # ODOMETRY (id 331) needs MAVLink 2
        from pymavlink import mavutil

        try:  # ardupilotmega: EKF_STATUS_REPORT is ArduPilot's own message
            self.conn = mavutil.mavlink_connection(
                self.url,
                source_system=255,
                source_component=190,
                autoreconnect=True,
                dialect="ardupilotmega",
            )
        except Exception as e:
            raise AutopilotUnreachableError(f"cannot open {self.url}: {e}") from None
        end = time.monotonic() + self.timeout_s
        while time.monotonic() < end:
            self.conn.mav.heartbeat_send(6, 8, 0, 0, 0)
            m = self.conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
            if m is not None and m.get_srcComponent() == 1 and m.autopilot != 8:
                self.system_id = m.get_srcSystem()
                self.base_mode = int(m.base_mode)
                self.autopilot = (
                    "ArduPilot"
                    if m.autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA
                    else f"MAV_AUTOPILOT {m.autopilot}"
                )
                return self
        self.close()
        raise AutopilotUnreachableError(
            f"no autopilot heartbeat on {self.url} within {self.timeout_s:g} s "
            "(wrong port or baud rate, or the autopilot is off)"
        )

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self.conn is not None:
            try:
                self.conn.close()
            finally:
                self.conn = None

    # ---------------------------------------------------------------- receiving
    def _pump(self, seconds: float, on: Any = None) -> None:
        end = time.monotonic() + seconds
        last_hb = 0.0
        while True:
            now = time.monotonic()
            if now - last_hb > 1.0:
                self.conn.mav.heartbeat_send(6, 8, 0, 0, 0)
                last_hb = now
            left = end - now
            if left <= 0:
                return
            m = self.conn.recv_match(blocking=True, timeout=min(left, 0.1))
            while m is not None:
                self._on(m)
                if on is not None:
                    on(m)
                m = self.conn.recv_match(blocking=False)

    def _on(self, m: Any) -> None:
        kind = m.get_type()
        if kind == "PARAM_VALUE" and m.get_srcSystem() == self.system_id:
            self.param_values[str(m.param_id)] = (float(m.param_value), int(m.param_type))
            self._param_index[int(m.param_index)] = str(m.param_id)
            self._param_count = int(m.param_count)
        elif (
            kind == "HEARTBEAT"
            and m.get_srcSystem() == self.system_id
            and m.get_srcComponent() == 1
        ):
            self.base_mode = int(m.base_mode)

    # ---------------------------------------------------------------- parameters
    def params(self) -> dict[str, Param]:
        """Every parameter (PARAM_REQUEST_LIST; the missing ones by index)."""
        self._param_index, self._param_count = {}, 0
        self.conn.mav.param_request_list_send(self.system_id, 1)
        deadline = time.monotonic() + max(30.0, self.timeout_s)
        quiet_since = time.monotonic()
        seen = 0
        while time.monotonic() < deadline:
            self._pump(0.3)
            n = len(self._param_index)
            if n != seen:
                seen, quiet_since = n, time.monotonic()
            if self._param_count and n >= self._param_count:
                break
            if time.monotonic() - quiet_since > 1.0:
                missing = [i for i in range(self._param_count) if i not in self._param_index]
                if not self._param_count:
                    self.conn.mav.param_request_list_send(self.system_id, 1)
                for i in missing[:50]:
                    self.conn.mav.param_request_read_send(self.system_id, 1, b"", i)
                quiet_since = time.monotonic()
        if not self.param_values:
            raise AutopilotError(f"cannot read the parameter list from {self.url}")
        return {
            name: Param(
                name, int(round(v)) if t in INT_TYPES and math.isfinite(v) else v, t in INT_TYPES
            )
            for name, (v, t) in self.param_values.items()
        }

    def read(self, name: str) -> float:
        """One parameter, read again (PARAM_REQUEST_READ)."""
        for _ in range(5):
            self.param_values.pop(name, None)
            self.conn.mav.param_request_read_send(self.system_id, 1, name.encode(), -1)
            end = time.monotonic() + 1.0
            while time.monotonic() < end and name not in self.param_values:
                self._pump(0.05)
            if name in self.param_values:
                return self.param_values[name][0]
        raise AutopilotError(f"cannot read {name}")

    def write(self, target: Target) -> None:
        """PARAM_SET (the value as a float, the parameter's type)."""
        kind = self.param_values.get(target.name, (0.0, REAL32 if not target.is_int else 6))[1]
        self.conn.mav.param_set_send(
            self.system_id, 1, target.name.encode(), float(target.value), kind
        )
        self._pump(0.2)

    def armed(self) -> bool:
        self._pump(0.2)
        return bool(self.base_mode & 128)

    # ---------------------------------------------------------------- watching
    def watch(self, seconds: float) -> Watched:
        """Listen ``seconds`` (see the module docstring)."""
        seen = Watched()
        for msg_id, hz in (
            (MSG_EKF_STATUS_REPORT, 4.0),
            (MSG_GLOBAL_POSITION_INT, 4.0),
            (MSG_GPS_RAW_INT, 2.0),
        ):
            self.conn.mav.command_long_send(
                self.system_id, 1, MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, 1e6 / hz, 0, 0, 0, 0, 0
            )
        self.conn.mav.command_long_send(
            self.system_id, 1, MAV_CMD_REQUEST_MESSAGE, 0, MSG_GPS_GLOBAL_ORIGIN, 0, 0, 0, 0, 0, 0
        )
        start = time.monotonic()
        prearm_asked = [False]

        def on(m: Any) -> None:
            kind = m.get_type()
            if m.get_srcSystem() != self.system_id:
                return
            t = time.monotonic() - start
            comp = m.get_srcComponent()
            if comp != 1 and kind in ("ODOMETRY", "VISION_POSITION_ESTIMATE"):
                c = seen.companion.setdefault(kind, CompanionSeen())
                c.count += 1
                c.first_s = t if c.first_s is None else c.first_s
                c.last_s = t
                c.component = comp
                if kind == "ODOMETRY":
                    c.frame_id, c.child_frame_id = int(m.frame_id), int(m.child_frame_id)
                    c.quality = int(m.quality)
                return
            if comp != 1:
                return
            if kind == "EKF_STATUS_REPORT":
                seen.ekf_flags = int(m.flags)
            elif kind == "GLOBAL_POSITION_INT":
                seen.position = (int(m.lat), int(m.lon))
            elif kind == "GPS_GLOBAL_ORIGIN":
                seen.origin = (int(m.latitude), int(m.longitude), int(m.altitude))
            elif kind == "GPS_RAW_INT" and int(m.fix_type) >= 1:
                seen.gps_seen = True
            elif kind == "STATUSTEXT":
                seen.statustexts.append(str(m.text))

        while time.monotonic() - start < seconds:
            if not prearm_asked[0] and time.monotonic() - start > min(1.0, seconds / 2):
                prearm_asked[0] = True  # ArduPilot answers with "PreArm: ..." texts
                self.conn.mav.command_long_send(
                    self.system_id, 1, MAV_CMD_RUN_PREARM_CHECKS, 0, 0, 0, 0, 0, 0, 0, 0
                )
            self._pump(min(0.2, seconds - (time.monotonic() - start)), on)
        return seen
