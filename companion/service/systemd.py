"""systemd's sd_notify protocol, without libsystemd: datagrams on $NOTIFY_SOCKET.

READY=1 once the links are up, WATCHDOG=1 pings from the event loop itself every half
WatchdogSec (so none arrive when the loop is stuck and systemd restarts the service),
STOPPING=1 on the way out, STATUS= lines for `systemctl status`. Outside systemd (no
$NOTIFY_SOCKET) everything is a no-op. An abstract socket is written with a leading '@'.
"""

from __future__ import annotations

import os
import socket


class SdNotify:
    """The notification socket of the unit, if any."""

    def __init__(self, environ: dict[str, str] | None = None) -> None:
        env = dict(os.environ if environ is None else environ)
        path = env.get("NOTIFY_SOCKET", "")
        self.address = ("\0" + path[1:]) if path.startswith("@") else path
        self.watchdog_s: float | None = None
        usec = env.get("WATCHDOG_USEC")
        pid = env.get("WATCHDOG_PID")
        if usec and usec.isdigit() and (not pid or pid == str(os.getpid())):
            self.watchdog_s = int(usec) * 1e-6
        self.sent = 0

    @property
    def enabled(self) -> bool:
        return bool(self.address)

    def notify(self, *fields: str) -> bool:
        """Send "KEY=value" fields in one datagram; False outside systemd or on error."""
        if not self.address:
            return False
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
            try:
                s.sendto("\n".join(fields).encode(), self.address)
            except OSError:
                return False
        self.sent += 1
        return True

    def ready(self, status: str) -> bool:
        return self.notify("READY=1", f"STATUS={status}")

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def stopping(self) -> bool:
        return self.notify("STOPPING=1", "STATUS=stopping")
