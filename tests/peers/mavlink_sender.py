"""A pymavlink sender standing for an autopilot (or a spoofer) on its own UDP port, for the
link tests (tests/drivers/test_link*.py)."""

from __future__ import annotations

import socket
from typing import Any

from pymavlink.dialects.v20 import common as mavlink


class Sender:
    """A pymavlink sender on its own UDP port, as system ``sysid`` component ``compid``."""

    def __init__(self, port: int, sysid: int = 1, compid: int = 1) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.mav.robust_parsing = True
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.port = port
        self.got: list[Any] = []

    def send(self, msg: Any) -> None:
        self.sock.sendto(msg.pack(self.mav), ("127.0.0.1", self.port))

    def heartbeat(self) -> None:
        self.send(self.mav.heartbeat_encode(2, 12, 0, 0, 4))  # QUADROTOR, PX4

    def drain(self) -> list[Any]:
        while True:
            try:
                data = self.sock.recv(65536)
            except BlockingIOError:
                return self.got
            self.got += self.mav.parse_buffer(data) or []

    def close(self) -> None:
        self.sock.close()


def kinds(msgs: list[Any], kind: str) -> list[Any]:
    return [m for m in msgs if m.get_type() == kind]
