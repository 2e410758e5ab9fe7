"""The SITL loopback stream: the simulator's frames over TCP (the simulator is the server).

Each frame is a 32-byte little-endian header ``struct '<4sIqHHIII'`` = magic ``b"CFRM"``, seq
(uint32), time_us (int64, monotonic clock of the machine at mid-exposure), width, height
(uint16), pixel format (uint32, 0 = BGR8), payload length (uint32), reserved (uint32), followed
by the payload (height*width*3 bytes)."""

from __future__ import annotations

import contextlib
import logging
import socket
import struct
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING

import numpy as np

from companion.drivers.camera.source import CameraSource, CaptureRequest
from companion.types import CameraFrame

if TYPE_CHECKING:
    pass


FRAME_HEADER = struct.Struct("<4sIqHHIII")
FRAME_MAGIC = b"CFRM"
FORMAT_BGR8 = 0
MAX_SIDE_PX = 8192  # a header claiming more is corrupt (never allocate from garbage)

log = logging.getLogger("companion.camera")


def encode_frame(frame: CameraFrame) -> bytes:
    """Header + payload of one frame on the SITL stream."""
    img = np.ascontiguousarray(frame.image_bgr)
    h, w = img.shape[:2]
    payload = img.tobytes()
    header = FRAME_HEADER.pack(
        FRAME_MAGIC, frame.seq & 0xFFFFFFFF, frame.time_us, w, h, FORMAT_BGR8, len(payload), 0
    )
    return header + payload


class SitlStream(CameraSource):
    """Frames from the SITL autopilot's loopback stream; reconnects while the stream is down."""

    def __init__(
        self, host: str, port: int, retry_s: float = 0.5, request: CaptureRequest | None = None
    ) -> None:
        super().__init__(request)
        self.host, self.port, self.retry_s = host, port, retry_s
        self._sock: socket.socket | None = None
        self.bad_frames = 0

    def _recv_exact(self, sock: socket.socket, n: int) -> bytearray | None:
        """``n`` bytes from ``sock`` (None at its end), read into one buffer that the frame's
        array then wraps: a 320x240 frame is not copied again."""
        buf = bytearray(n)
        view = memoryview(buf)
        got = 0
        while got < n:
            k = sock.recv_into(view[got:], n - got)
            if k == 0:
                return None
            got += k
        return buf

    def _read(self) -> Iterator[CameraFrame]:
        while not self.closed:
            try:
                sock = socket.create_connection((self.host, self.port), timeout=2.0)
            except OSError:
                time.sleep(self.retry_s)
                continue
            self._sock = sock
            try:
                while not self.closed:
                    head = self._recv_exact(sock, FRAME_HEADER.size)
                    if head is None:
                        break
                    magic, seq, time_us, w, h, fmt, n, _ = FRAME_HEADER.unpack(head)
                    ok_size = 16 <= w <= MAX_SIDE_PX and 16 <= h <= MAX_SIDE_PX
                    if magic != FRAME_MAGIC or fmt != FORMAT_BGR8 or not ok_size or n != w * h * 3:
                        self.bad_frames += 1
                        break  # lost framing: reconnect
                    payload = self._recv_exact(sock, n)
                    if payload is None:
                        break
                    img = np.frombuffer(payload, np.uint8).reshape(h, w, 3)
                    yield CameraFrame(int(time_us), int(seq), img)
            except OSError:
                pass
            finally:
                sock.close()
                self._sock = None

    def close(self) -> None:
        super().close()
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.shutdown(socket.SHUT_RDWR)
