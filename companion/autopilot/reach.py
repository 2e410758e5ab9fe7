"""How ``check`` and ``configure`` reach the autopilot, PX4 or ArduPilot.

The autopilot is reached on ``--url``, or on the service's own link (``service.mavlink_url``)
when the service is not running: a running service holds that port, and then the command asks
for another link instead of fighting over it. MAVSDK (PX4's session) and pymavlink
(ArduPilot's) spell the same link differently: :func:`mavsdk_url`, :func:`pymavlink_url`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from companion.autopilot.options import CheckOptions
from companion.autopilot.report import service_answers
from companion.config import Config
from companion.drivers.mavlink import LinkUrl
from companion.drivers.status import find_status_socket
from companion.errors import ConfigError


@dataclass(frozen=True, slots=True)
class LinkTarget:
    """Where check and configure talk to."""

    url: str  # MAVSDK URL of the autopilot (pymavlink_url spells it for pymavlink)
    service_link: LinkUrl  # the service's own link (service.mavlink_url)
    socket: Path  # the service's status socket


def mavsdk_url(url: str, key: str = "--url") -> str:
    """A MAVSDK connection URL from ours (pymavlink's spelling) or MAVSDK's own."""
    if "://" in url:
        return url
    u = LinkUrl.parse(url, key)
    if u.kind == "serial":
        return f"serial://{u.host}:{u.port}"
    if u.kind == "tcp":
        return f"tcpout://{u.host}:{u.port}"
    return f"{u.kind}://{u.host}:{u.port}"


def pymavlink_url(url: str) -> str:
    """pymavlink's spelling of a link URL (ours, or MAVSDK's udpin:// tcpout:// serial://)."""
    if "://" not in url:
        return url
    scheme, _, rest = url.partition("://")
    if scheme == "serial":
        dev, _, baud = rest.rpartition(":")
        return f"{dev},{baud}" if baud.isdigit() else rest
    return {
        "udpin": "udpin",
        "udpout": "udpout",
        "udp": "udpin",
        "tcpout": "tcp",
        "tcp": "tcp",
    }.get(scheme, scheme) + f":{rest}"


def resolve_link(cfg: Config, opts: CheckOptions) -> LinkTarget:
    """The autopilot URL; ConfigError when the only link is the one the running service
    holds."""
    service_url = cfg.service.mavlink_url
    link = LinkUrl.parse(service_url)
    socket = find_status_socket(opts.socket or cfg.service.status_socket)
    own = mavsdk_url(service_url, "service.mavlink_url")
    url = mavsdk_url(opts.url) if opts.url else own
    if url == own and service_answers(socket):
        raise ConfigError(
            f"--url: the running service holds {service_url} (its status is on {socket}); "
            "give check its own link to the autopilot: PX4 SITL's (and the stub's) ground-"
            "station port --url udpin://127.0.0.1:14550, a USB or telemetry port "
            "(--url serial:///dev/ttyACM0:115200), or stop the service to use its link"
        )
    return LinkTarget(url, link, socket)
