"""The autopilot's side of a GPS handover ([gps] handover): what it is told at a GPS loss and
after the return (docs/gps.md: what the probes of both SITLs showed).

- PX4: PARAM_SET EKF2_GPS_CTRL 0 at the loss (EKF2 stops fusing GNSS at once: a 0.095 m step
  against 0.29 m at its own 7 s time-out; 0.3 s after the loss when EKF2's lag is carried into
  our output: ``gps_frame``), back to ``gps.px4_gps_ctrl`` after the slew onto GPS ended.
  Acknowledged by PARAM_VALUE echoing the value (PX4 answers nothing to a refused one: the
  retries run out). The INT32 travels byte-wise, as PX4 copies it.
- ArduPilot: MAV_CMD_SET_EKF_SOURCE_SET (42007) param1 = 2 (ExternalNav) at the loss, 1 after
  the slew; acknowledged by COMMAND_ACK ACCEPTED, refused by any other result but IN_PROGRESS.

One action at a time: a newer one replaces one still unanswered. Each is sent again every
``RETRY_S`` until answered, ``MAX_TRIES`` times at most; every send, answer and give-up is
logged, the latest ``KEPT`` actions are in the status. Inputs: the GPS frame's loss / return
(``on_loss``, ``on_return``), PARAM_VALUE and COMMAND_ACK from the autopilot session.
"""

from __future__ import annotations

import logging
import struct
from collections import deque
from dataclasses import dataclass
from typing import Any, Literal

from companion.drivers import messages
from companion.service.runtime import AutopilotKind, Runtime

log = logging.getLogger("companion.service")

PX4_GPS_PARAM = "EKF2_GPS_CTRL"
MAV_PARAM_TYPE_INT32 = 6
MAV_CMD_SET_EKF_SOURCE_SET = 42007
EKF_SOURCE_GPS, EKF_SOURCE_EXTNAV = 1, 2  # ArduPilot's source sets as configure sets them
RETRY_S = 1.0
MAX_TRIES = 5
KEPT = 8
Target = Literal["px4", "ardupilot"]


def int32_bytewise(value: int) -> float:
    """An INT32 parameter as PX4 takes it: its bit pattern in the float field."""
    return float(struct.unpack("<f", struct.pack("<i", int(value)))[0])


def bytewise_int32(wire: float) -> int:
    """The INT32 in a PARAM_VALUE's float field (PX4: byte-wise)."""
    return int(struct.unpack("<i", struct.pack("<f", float(wire)))[0])


@dataclass
class Action:
    """One action: ``what`` in words; ``value`` (EKF2_GPS_CTRL or the source set);
    ``result``: pending, acknowledged, refused (with the result's name), no answer."""

    target: Target
    what: str
    value: int
    tries: int = 0
    sent_ns: int = 0
    result: str = "pending"
    due_ns: int = 0  # not sent before this (our clock [ns]): 0, at once


class GpsActions:
    """The actions at a loss and after the return, retried until answered."""

    def __init__(self, rt: Runtime, link: Any) -> None:
        self.rt = rt
        self.link = link
        self.current: Action | None = None
        self.recent: deque[Action] = deque(maxlen=KEPT)

    def target(self) -> Target | None:
        """Whom to tell: [gps] handover, or (auto) the autopilot its HEARTBEAT names."""
        mode = self.rt.config.gps.handover
        if mode == "px4" or mode == "ardupilot":
            return mode
        if mode == "auto":
            kind = self.rt.stats.autopilot_kind
            if kind is AutopilotKind.PX4:
                return "px4"
            if kind is AutopilotKind.ARDUPILOT:
                return "ardupilot"
        return None

    def on_loss(self, delay_s: float = 0.0) -> None:
        """Our GPS verdict turned bad: the autopilot stops using its GPS, ``delay_s`` from now
        (PX4 with the lag carried over: the carried poses must reach EKF2's buffer first)."""
        self._start(lost=True, delay_s=delay_s)

    def on_return(self) -> None:
        """The slew onto the returned GPS ended: the autopilot uses its GPS again."""
        self._start(lost=False)

    def _start(self, lost: bool, delay_s: float = 0.0) -> None:
        target = self.target()
        if target is None:
            return
        if target == "px4":
            value = 0 if lost else self.rt.config.gps.px4_gps_ctrl
            action = Action(target, f"{PX4_GPS_PARAM} {value}", value)
        else:
            value = EKF_SOURCE_EXTNAV if lost else EKF_SOURCE_GPS
            action = Action(target, f"EKF source set {value}", value)
        if self.current is not None and self.current.result == "pending":
            self.current.result = "replaced"
        self.current = action
        self.recent.append(action)
        if delay_s > 0.0:
            action.due_ns = self.rt.clock() + int(delay_s * 1e9)
            log.info("GPS handover: %s in %.2f s", action.what, delay_s)
            return
        self._send(action)

    def _send(self, a: Action) -> None:
        sysid = self.rt.stats.autopilot_system_id or self.rt.config.service.system_id
        mav = self.link.mav
        if a.target == "px4":
            msg = mav.param_set_encode(
                sysid, 1, PX4_GPS_PARAM.encode(), int32_bytewise(a.value), MAV_PARAM_TYPE_INT32
            )
        else:
            msg = mav.command_long_encode(
                sysid, 1, MAV_CMD_SET_EKF_SOURCE_SET, a.tries, float(a.value), 0, 0, 0, 0, 0, 0
            )
        a.tries += 1
        a.sent_ns = self.rt.clock()
        self.link.send(msg)
        log.info("GPS handover: %s sent (try %d)", a.what, a.tries)

    def tick(self) -> None:
        """A delayed action once due; the pending action again after RETRY_S, until MAX_TRIES."""
        a = self.current
        if a is None or a.result != "pending":
            return
        now = self.rt.clock()
        if a.tries == 0:
            if now >= a.due_ns:
                self._send(a)
            return
        if now - a.sent_ns < RETRY_S * 1e9:
            return
        if a.tries >= MAX_TRIES:
            a.result = "no answer"
            self.rt.warn(f"GPS handover: {a.what} unanswered after {a.tries} tries")
            return
        self._send(a)

    def on_param_value(self, name: str, value: float) -> None:
        """PARAM_VALUE from the autopilot: our EKF2_GPS_CTRL echoed."""
        a = self.current
        if a is None or a.target != "px4" or a.result != "pending" or name != PX4_GPS_PARAM:
            return
        if bytewise_int32(value) == a.value:
            self._answered(a, "acknowledged")

    def on_command_ack(self, command: int, result: int) -> None:
        """COMMAND_ACK addressed to us: MAV_CMD_SET_EKF_SOURCE_SET's."""
        a = self.current
        if (
            a is None
            or a.target != "ardupilot"
            or a.result != "pending"
            or command != MAV_CMD_SET_EKF_SOURCE_SET
            or result == messages.MAV_RESULT_IN_PROGRESS
        ):
            return
        if result == messages.MAV_RESULT_ACCEPTED:
            self._answered(a, "acknowledged")
        else:
            self._answered(a, f"refused ({messages.result_name(result)})")

    def _answered(self, a: Action, result: str) -> None:
        a.result = result
        if result == "acknowledged":
            log.info("GPS handover: %s acknowledged", a.what)
        else:
            self.rt.warn(f"GPS handover: {a.what} {result}")

    def status(self) -> list[dict[str, Any]]:
        """The latest actions, oldest first."""
        return [{"what": a.what, "tries": a.tries, "result": a.result} for a in self.recent]

    async def loop(self) -> None:
        """The retries, every 0.2 s."""
        while not self.rt.stopping:
            self.tick()
            await self.rt.sleep(0.2)
