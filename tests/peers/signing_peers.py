"""Signing helpers for the MAVLink signing tests (tests/drivers/test_signing*.py): a key, its
file, a pymavlink autopilot that signs and requires signatures, a signing parser and signer."""

from __future__ import annotations

import socket
import time
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from companion.drivers.mavlink_parser import Parser
from companion.drivers.signing import Signing, wall_units

KEY = bytes(range(100, 132))


def write_key(path: Path, data: bytes, mode: int = 0o600) -> Path:
    path.write_bytes(data)
    path.chmod(mode)
    return path


class Peer:
    """A pymavlink autopilot on a UDP socket; signs with ``key`` and requires signatures."""

    def __init__(self, key: bytes | None, port: int) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.mav.robust_parsing = True
        if key is not None:
            s = self.mav.signing
            s.secret_key, s.link_id, s.sign_outgoing = key, 3, True
            s.timestamp = wall_units()
            s.allow_unsigned_callback = None  # every frame must be signed
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = port

    def send(self, msg: Any, mav: Any = None) -> None:
        self.sock.sendto(msg.pack(mav or self.mav), ("127.0.0.1", self.port))

    def receive(self, seconds: float) -> list[Any]:
        out: list[Any] = []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            out += self.mav.parse_buffer(data) or []
        return out


def parser_with_signing() -> tuple[Parser, Any]:
    """A parser that checks signatures with KEY, and its signing state."""
    sig = Signing(KEY, None, link_id=0)
    ours = mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
    parser = Parser()
    sig.apply(ours, parser.mav)
    parser.signing_state = ours.signing
    return parser, ours.signing


def signer(key: bytes, timestamp: int) -> Any:
    """A pymavlink MAVLink (system 1, component 1) signing with ``key`` from ``timestamp``."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    s = mav.signing
    s.secret_key, s.link_id, s.sign_outgoing, s.timestamp = key, 0, True, timestamp
    return mav
