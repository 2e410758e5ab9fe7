"""Options of the service (composed into the config as [service])."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from companion.options import opt

OutputName = Literal["vision_position_estimate", "odometry", "both"]


@dataclass(frozen=True, slots=True)
class ServiceOptions:
    """Links, rates and what is sent to the autopilot."""

    mavlink_url: str = opt(
        "udpin:127.0.0.1:14540", "autopilot link: udpin/udpout/tcp:HOST:PORT or serial:DEV:BAUD"
    )
    system_id: int = opt(1, "MAVLink system id (the autopilot's)", ge=1, le=255)
    component_id: int = opt(197, "our component id (197 = VISUAL_INERTIAL_ODOMETRY)", ge=1, le=255)
    camera_url: str = opt("sitl://127.0.0.1:5600", "camera: sitl://, folder:PATH, /dev/videoN, URL")
    output: OutputName = opt(
        "vision_position_estimate", "vision_position_estimate, odometry or both"
    )
    distance_sensor_rate_hz: float = opt(
        50.0, "DISTANCE_SENSOR rate asked from the autopilot [Hz]", gt=0, le=1000
    )
    attitude_rate_hz: float = opt(
        50.0, "ATTITUDE rate asked from the autopilot [Hz]", gt=0, le=1000
    )
    timesync_rate_hz: float = opt(2.0, "our own TIMESYNC requests [Hz]", gt=0, le=50)
    stale_frame_ms: float = opt(
        100.0, "stop publishing when the last good frame is older than this [ms]", gt=0
    )
    report_path: str = opt("", "write a JSON summary here on exit (empty = none)")
    status_socket: str = opt(
        "",
        "Unix socket of `companion status` (empty: $RUNTIME_DIRECTORY/status.sock under systemd, "
        "else $XDG_RUNTIME_DIR/companion.sock, else /tmp/companion-UID.sock)",
    )
