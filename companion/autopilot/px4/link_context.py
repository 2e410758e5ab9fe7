"""What PX4's rules need to know about our side: the output, the link and its timing."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class LinkContext:
    """What the rules need to know about our side."""

    output: str = "vision_position_estimate"  # service.output
    fc_port: str = "ETHERNET"  # the autopilot port the companion is wired to
    link_kind: str = "udpin"  # the service's link: udpin, udpout, tcp or serial
    link_port: int = 14540  # its UDP/TCP port, or the serial baud rate
    gps_seen: bool | None = None  # a GNSS receiver reported while watching (None: not watched)
    link_host: str = "127.0.0.1"  # its host (UDP/TCP: where it listens or sends to)
    no_gnss: bool = False  # configure --no-gnss: also turn GNSS fusion off (EKF2_GPS_CTRL = 0)
    odometry_frame: str = "local_frd"  # service.odometry_frame
    # the oldest our samples' stamps can be when they leave: service.stale_frame_ms plus the
    # ODOMETRY centring's (service.odometry_centre_frames - 1) / 2 frames [ms]
    oldest_stamp_ms: float = 100.0
    velocity_sigma_m_s: float = 0.1  # service.odometry_velocity_sigma_m_s
    with_gps: bool = False  # --with-gps: GPS and our vision together (docs/gps.md)
