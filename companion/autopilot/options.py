"""Options of ``companion autopilot check | configure`` and of its PX4 alias ``companion px4``
(the command-line flags are built from the fields)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from companion.options import opt

FcPort = Literal["auto", "TELEM1", "TELEM2", "TELEM3", "TELEM4", "ETHERNET"]


@dataclass(frozen=True, slots=True)
class CheckOptions:
    """How to reach the autopilot and how long to watch it."""

    url: str = opt(
        "",
        "autopilot link for MAVSDK (udpin://HOST:PORT, serial:///dev/ttyACM0:115200, or "
        "pymavlink's udpin:HOST:PORT); empty: the service's service.mavlink_url",
    )
    fc_port: FcPort = opt(
        "auto",
        "the autopilot port the companion is wired to: TELEM1-4 or ETHERNET (auto: TELEM2 for "
        "a serial service link, ETHERNET for UDP/TCP)",
    )
    timeout_s: float = opt(10.0, "wait this long for the autopilot's heartbeat [s]", gt=0)
    watch_s: float = opt(
        5.0, "check: watch the autopilot this long for fusion [s] (0: parameters only)", ge=0
    )
    socket: str = opt("", "the service's status socket (empty: from service.status_socket)")
    shell: bool = opt(True, "ask PX4's MAVLink shell for EKF2's own fusion flags")
    yes: bool = opt(False, "configure: write without asking")
    no_gnss: bool = opt(
        False, "configure: also turn GNSS fusion off (EKF2_GPS_CTRL = 0) where none is fitted"
    )
    with_gps: bool = opt(
        False,
        "GPS and our vision together: judge / write the parameters for a handover at GPS loss "
        "and return (PX4: EKF2_GPS_CTRL, EKF2_EV_CTRL without yaw, EKF2_HGT_REF; ArduPilot: "
        "EKF3 source set 1 GPS, set 2 ExtNav, VISO_TYPE 3; docs/gps.md)",
    )
