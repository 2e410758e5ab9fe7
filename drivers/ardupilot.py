"""The autopilot's dialect: which one speaks (HEARTBEAT.autopilot) and what ArduPilot needs on
top of the messages PX4 and ArduPilot share (docs/service.md; docs/decisions.md,
"ArduPilot's dialect").

Both take VISION_POSITION_ESTIMATE and ODOMETRY (frame_id LOCAL_FRD, child_frame_id BODY_FRD,
velocity in the body frame); ArduPilot on top needs:

- an EKF origin when it has no GPS: SET_GPS_GLOBAL_ORIGIN (lat/lon degE7, alt mm AMSL). EKF3
  wipes an origin that arrives before "EKF3 IMU0 initialised", so it is resent every second
  until GLOBAL_POSITION_INT reports a position (a non-zero lat/lon) for ``ORIGIN_HOLD_S``
  without a break (:class:`OriginKeeper`);
- ODOMETRY.quality as AP_VisualOdom reads it: -1 failed, 0 unknown (accepted whatever
  VISO_QUAL_MIN says), 1..100 worst..best; a published pose is therefore never sent as 0
  (:func:`ardupilot_quality`). VISION_POSITION_ESTIMATE has no quality: ArduPilot takes it as 0
  (unknown), so VISO_QUAL_MIN > 0 drops it;
- no TIMESYNC conversion of our ``time_usec``: ArduPilot maps it into its own clock with its
  jitter correction (the smallest arrival-minus-stamp difference seen is taken as zero lag)
  and EKF3 moves it back by VISO_DELAY_MS. Our stamps need only be monotonic.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

MAV_AUTOPILOT_PX4 = mavlink.MAV_AUTOPILOT_PX4  # 12
MAV_AUTOPILOT_ARDUPILOTMEGA = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA  # 3
MSG_ID_GLOBAL_POSITION_INT = mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT  # 33
POSITION_RATE_HZ = 2.0  # GLOBAL_POSITION_INT asked of ArduPilot (its SITL streams none by default)
# what the service reads from ArduPilot beyond what it reads from any autopilot
ARDUPILOT_INPUTS = frozenset({MSG_ID_GLOBAL_POSITION_INT})
ORIGIN_RESEND_S = 1.0  # SET_GPS_GLOBAL_ORIGIN again this often until the EKF holds it
ORIGIN_HOLD_S = 2.0  # GLOBAL_POSITION_INT with a position this long without a break: held

# EKF_STATUS_REPORT.flags: a relative horizontal position, and constant-position mode (no aiding)
EKF_POS_HORIZ_REL, EKF_CONST_POS_MODE = 0x08, 0x80


def ekf_navigates(flags: Any) -> Any:
    """Whether EKF3 has a horizontal position (relative, not constant-position mode) by its
    EKF_STATUS_REPORT ``flags``: an int, or an integer array (elementwise)."""
    return (flags & EKF_POS_HORIZ_REL != 0) & (flags & EKF_CONST_POS_MODE == 0)


AUTOPILOT_NAMES = {
    MAV_AUTOPILOT_PX4: "PX4",
    MAV_AUTOPILOT_ARDUPILOTMEGA: "ArduPilot",
    mavlink.MAV_AUTOPILOT_GENERIC: "generic",
}


def autopilot_name(autopilot: int) -> str:
    """HEARTBEAT.autopilot in words: PX4, ArduPilot, or MAV_AUTOPILOT n."""
    return AUTOPILOT_NAMES.get(int(autopilot), f"MAV_AUTOPILOT {int(autopilot)}")


def ardupilot_quality(quality_pct: float) -> int:
    """ODOMETRY.quality for ArduPilot: 1..100 (0 would read as "unknown" and pass any
    VISO_QUAL_MIN; a pose we publish is never "failed")."""
    return int(min(100, max(1, round(quality_pct))))


@dataclass(frozen=True, slots=True)
class Origin:
    """The EKF origin (WGS-84): latitude and longitude [deg], altitude [m AMSL]."""

    lat_deg: float
    lon_deg: float
    alt_m: float

    def wire_units(self) -> tuple[int, int, int]:
        """(latitude, longitude) [degE7] and altitude [mm], as MAVLink carries them."""
        return (
            int(round(self.lat_deg * 1e7)),
            int(round(self.lon_deg * 1e7)),
            int(round(self.alt_m * 1000.0)),
        )


def set_gps_global_origin(mav: Any, target_system: int, origin: Origin, time_us: int) -> Any:
    """SET_GPS_GLOBAL_ORIGIN (lat/lon degE7, alt mm, time_usec ours)."""
    lat_e7, lon_e7, alt_mm = origin.wire_units()
    # time_usec is an extension field: keyword only in pymavlink
    return mav.set_gps_global_origin_encode(
        target_system, lat_e7, lon_e7, alt_mm, time_usec=int(time_us)
    )


class OriginKeeper:
    """When to (re)send the origin and whether the EKF holds it (pure; times in ns of any one
    monotonic clock).

    ``due(now)``: send now (unheld, and ``ORIGIN_RESEND_S`` since the last send). ``position``
    feeds every GLOBAL_POSITION_INT: a position (lat or lon non-zero) held for ``ORIGIN_HOLD_S``
    without a zero in between means the EKF keeps the origin; a zero afterwards (the autopilot
    rebooted, its EKF restarted) makes it unheld again. ``reset()`` after the autopilot fell
    silent."""

    def __init__(self) -> None:
        self.held = False
        self.sent = 0  # SET_GPS_GLOBAL_ORIGIN messages sent
        self.lost = 0  # times a held origin was lost again
        self._last_sent_ns: int | None = None
        self._position_since_ns: int | None = None

    def due(self, now_ns: int) -> bool:
        """Whether to send the origin now."""
        if self.held:
            return False
        last = self._last_sent_ns
        return last is None or now_ns - last >= int(ORIGIN_RESEND_S * 1e9)

    def mark_sent(self, now_ns: int) -> None:
        self.sent += 1
        self._last_sent_ns = now_ns

    def position(self, lat_e7: int, lon_e7: int, now_ns: int) -> None:
        """A GLOBAL_POSITION_INT (lat/lon degE7) seen at ``now_ns``."""
        if lat_e7 == 0 and lon_e7 == 0:
            if self.held:
                self.lost += 1
            self.held = False
            self._position_since_ns = None
            return
        if self._position_since_ns is None:
            self._position_since_ns = now_ns
        if now_ns - self._position_since_ns >= int(ORIGIN_HOLD_S * 1e9):
            self.held = True

    def reset(self) -> None:
        self.held = False
        self._position_since_ns = None
        self._last_sent_ns = None
