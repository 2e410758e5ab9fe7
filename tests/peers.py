"""Real peers the tests start on 127.0.0.1: free ports and a Mosquitto broker."""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from pathlib import Path

MOSQUITTO = shutil.which("mosquitto") or "/usr/sbin/mosquitto"


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port nobody listens on right now (TCP by default, or SOCK_DGRAM)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Broker:
    """A Mosquitto process on 127.0.0.1:port (start/stop at will; same port)."""

    def __init__(self, tmp: Path) -> None:
        self.port = free_port()
        self.conf = tmp / "mosquitto.conf"
        self.conf.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\n")
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [MOSQUITTO, "-c", str(self.conf)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", self.port)) == 0:
                    return
            time.sleep(0.05)
        raise RuntimeError("mosquitto did not start")

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(5)
            self.proc = None


def sitl_flight(
    tmp_path: Path,
    seconds: float,
    service: dict | None = None,
    config: str = "config/sitl.toml",
    **autopilot: object,
) -> tuple[object, object]:
    """A config (config/sitl.toml, ``seconds`` of flight) and SITL autopilot options that put
    the autopilot, the service and the camera on free loopback ports, with a prerendered
    camera (the two cores are then the service's and the autopilot's, not the renderer's)
    and the status socket in ``tmp_path``. ``service``: more [service] keys;
    ``config``: the scenario's config file; ``autopilot``: more AutopilotOptions fields."""
    from companion.config import load_config
    from sitl.autopilot import AutopilotOptions

    udp_stub, udp_us, tcp_cam = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM), 0
    tcp_cam = free_port()
    opts = AutopilotOptions(
        listen_port=udp_stub,
        companion_port=udp_us,
        camera_port=tcp_cam,
        gcs_listen_port=0,
        warmup_s=4.0,
        prerender=True,
        **autopilot,  # type: ignore[arg-type]
    )
    svc = {
        "mavlink_url": f"udpin:127.0.0.1:{udp_us}",
        "camera_url": f"sitl://127.0.0.1:{tcp_cam}",
        "status_socket": str(tmp_path / "status.sock"),
        "state_dir": str(tmp_path / "state"),
        **(service or {}),
    }
    cfg = load_config(config, {"sitl": {"seconds": seconds}, "service": svc})
    return cfg, opts


def service_config(tmp_path: Path, **service: object) -> object:
    """The built-in config with a service that has no peers unless told: the autopilot link on
    a free loopback UDP port, a camera URL where nothing listens (the camera loop keeps
    retrying), the status socket in ``tmp_path``; ``service``: [service] keys to override."""
    from companion.config import load_config

    svc = {
        "mavlink_url": f"udpin:127.0.0.1:{free_port(socket.SOCK_DGRAM)}",
        "camera_url": f"sitl://127.0.0.1:{free_port()}",
        "status_socket": str(tmp_path / "status.sock"),
        "state_dir": str(tmp_path / "state"),
        **service,
    }
    return load_config(None, {"service": svc})
