"""Everything a config needs from the machine, checked before the service starts anything,
and by ``companion config`` the same way (a file validated there starts here).

Errors raise ConfigError naming the key (exit 2): a link or camera URL that cannot work, a
signing key or timestamp file that would stop the output, a TLS CA file that is missing, a
status socket path that is not ours to use, a state folder that is not a folder. What may
still work later (a USB device not plugged in yet) is returned as warnings.
"""

from __future__ import annotations

import ssl
from pathlib import Path

from companion.config import Config
from companion.drivers.camera import check_camera_url, open_camera
from companion.drivers.mavlink import LinkUrl
from companion.drivers.signing import Signing, TimestampStore, default_timestamp_file
from companion.drivers.status import status_path
from companion.errors import ConfigError
from companion.service.state import state_dir
from companion.service.status import check_socket_path


def check(cfg: Config) -> list[str]:
    """Raise ConfigError naming the first key that cannot work; return warnings."""
    o = cfg.service
    warnings: list[str] = []
    link = LinkUrl.parse(o.mavlink_url)
    if link.kind == "serial" and not Path(link.host).exists():
        warnings.append(f"service.mavlink_url: {link.host} does not exist (yet): waiting for it")
    why = check_camera_url(o.camera_url)
    if why:
        warnings.append(why)
    open_camera(o.camera_url).close()  # the sitl:// and folder: forms in full (nothing opened)
    if o.signing.key_file:
        Signing.from_options(o.signing)  # the key (its file's mode and length)
        TimestampStore(default_timestamp_file(o.signing)).read()  # a value that can work
    m = o.mqtt
    if m.enabled and m.tls:
        try:
            ssl.create_default_context(cafile=m.ca_file or None)
        except (OSError, ssl.SSLError) as e:
            what = m.ca_file or "the system's CA certificates"
            raise ConfigError(f"service.mqtt.ca_file: cannot load {what}: {e}") from None
    elif m.enabled and m.ca_file:
        warnings.append("service.mqtt.ca_file: set but tls = false: not used")
    check_socket_path(status_path(o.status_socket))
    folder = state_dir(o.state_dir)
    if folder.exists() and not folder.is_dir():
        raise ConfigError(f"service.state_dir: {folder} exists and is not a folder")
    for i, rf in enumerate(cfg.rangefinders):
        head, _, tail = rf.serial.rpartition(":")
        device = head if head and tail.isdigit() else rf.serial
        if rf.serial and not Path(device).exists():
            warnings.append(f"rangefinders[{i}].serial: {device} does not exist (yet)")
    return warnings
