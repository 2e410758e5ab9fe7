"""Camera sources: cv2.VideoCapture (V4L2 device, GStreamer/FFmpeg URL, video file), image
folders (our dataset format and EuRoC) and the SITL loopback stream.

Every source is iterated in a worker thread (``read()`` blocks) and yields CameraFrame with
``time_us`` in the companion's monotonic clock at exposure:
- VideoCapture: with the V4L2 backend the buffer's timestamp (``CAP_PROP_POS_MSEC``; the
  kernel stamps buffers with CLOCK_MONOTONIC, uvcvideo at the start of the frame) when it is
  plausible (not in the future, at most 0.5 s before ``grab()`` returned), else the time
  ``grab()`` returned (FFmpeg/GStreamer: their position is stream time, not our clock);
  ``stamps`` says which one the last frame got;
- folders: the recorded times, shifted so that the first frame is "now" (replayed at the
  recorded rate, or as fast as possible with ``realtime=False``);
- the SITL stream: the time written by the simulator (same machine, same monotonic clock).

``url`` forms (config ``service.camera_url``): ``sitl://HOST:PORT``, ``folder:PATH[?fast]``,
``/dev/videoN`` or an integer, anything else goes to VideoCapture (a file, ``rtsp://...``,
a GStreamer pipeline ending in ``appsink``).

SITL stream format (TCP, the simulator is the server): each frame is a 32-byte little-endian
header ``struct '<4sIqHHIII'`` = magic ``b"CFRM"``, seq (uint32), time_us (int64, monotonic clock
of the machine at mid-exposure), width, height (uint16), pixel format (uint32, 0 = BGR8),
payload length (uint32), reserved (uint32), followed by the payload (height*width*3 bytes).
"""

from __future__ import annotations

import contextlib
import logging
import math
import socket
import struct
import time
from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from companion.errors import ConfigError, DatasetError
from companion.types import CameraFrame

FRAME_HEADER = struct.Struct("<4sIqHHIII")
FRAME_MAGIC = b"CFRM"
FORMAT_BGR8 = 0
MAX_SIDE_PX = 8192  # a header claiming more is corrupt (never allocate from garbage)
MAX_DRIVER_STAMP_AGE_US = 500_000  # a driver stamp older than this at grab() is not our clock

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


class CameraSource(ABC):
    """Base: ``frames()`` yields CameraFrame until the source ends or ``close()``.
    ``finite``: a recording that ends for good (a file, a folder), not a live device."""

    finite = False

    def __init__(self) -> None:
        self.closed = False
        self.stamps = "source"  # where the last frame's time_us came from

    @abstractmethod
    def frames(self) -> Iterator[CameraFrame]:
        """The frames, stamped in our monotonic clock at exposure (blocking; a worker thread)."""

    def close(self) -> None:
        self.closed = True


class SitlStream(CameraSource):
    """Frames from the SITL autopilot's loopback stream; reconnects while the stream is down."""

    def __init__(self, host: str, port: int, retry_s: float = 0.5) -> None:
        super().__init__()
        self.host, self.port, self.retry_s = host, port, retry_s
        self._sock: socket.socket | None = None
        self.bad_frames = 0

    def _recv_exact(self, sock: socket.socket, n: int) -> bytes | None:
        buf = bytearray(n)
        view = memoryview(buf)
        got = 0
        while got < n:
            k = sock.recv_into(view[got:], n - got)
            if k == 0:
                return None
            got += k
        return bytes(buf)

    def frames(self) -> Iterator[CameraFrame]:
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


class FolderSource(CameraSource):
    """A recorded dataset (ours or EuRoC) replayed at its rate (or as fast as possible)."""

    finite = True

    def __init__(self, path: Path, realtime: bool = True) -> None:
        super().__init__()
        from drivers.dataset import open_dataset

        self.dataset = open_dataset(path)
        self.realtime = realtime

    def frames(self) -> Iterator[CameraFrame]:
        t_start: int | None = None
        shift = 0
        for ev in self.dataset.events():
            if self.closed:
                return
            if not isinstance(ev, CameraFrame):
                continue
            now_us = time.monotonic_ns() // 1000
            if t_start is None:
                t_start, shift = ev.time_us, now_us - ev.time_us
            if self.realtime:
                wait = (ev.time_us + shift - now_us) * 1e-6
                if wait > 0:
                    time.sleep(wait)
            else:
                shift = now_us - ev.time_us  # as fast as possible: stamp with "now"
            yield CameraFrame(ev.time_us + shift, ev.seq, ev.image_bgr)


class VideoCaptureSource(CameraSource):
    """cv2.VideoCapture: a V4L2 device, a GStreamer/FFmpeg URL or a video file."""

    def __init__(self, spec: str | int) -> None:
        super().__init__()
        self.spec = spec
        self.finite = isinstance(spec, str) and Path(spec).is_file()  # a video file ends

    def frames(self) -> Iterator[CameraFrame]:
        import cv2

        cap = cv2.VideoCapture(self.spec)
        # a stalled network stream must not block forever (FFmpeg/GStreamer backends)
        cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, 2000)
        if not cap.isOpened():
            raise DatasetError(f"camera {self.spec!r}: cannot open")
        v4l2 = cap.getBackendName() == "V4L2"
        seq = 0
        try:
            while not self.closed:
                if not cap.grab():
                    return
                # grab() returns after exposure + readout + transfer: the V4L2 buffer's own
                # stamp is closer to the exposure when the backend gives one
                grab_us = time.monotonic_ns() // 1000
                driver_us = None
                if v4l2:
                    driver_us = driver_stamp_us(cap.get(cv2.CAP_PROP_POS_MSEC), grab_us)
                stamps = "grab" if driver_us is None else "v4l2 buffer"
                if stamps != self.stamps:
                    log.info("camera %r: frames stamped at %s", self.spec, stamps)
                    self.stamps = stamps
                t_us = grab_us if driver_us is None else driver_us
                ok, img = cap.retrieve()
                if not ok or img is None:
                    return
                if img.ndim == 2:
                    img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
                yield CameraFrame(t_us, seq, img)
                seq += 1
        finally:
            cap.release()


def driver_stamp_us(driver_ms: float, grab_us: int) -> int | None:
    """A frame's driver timestamp in our monotonic clock [us], or None when it cannot be.

    driver_ms: ``CAP_PROP_POS_MSEC`` read after ``grab()`` (V4L2: the buffer's timestamp,
    CLOCK_MONOTONIC; 0 before the first buffer); grab_us: our monotonic clock when ``grab()``
    returned. Plausible = not after grab_us and at most MAX_DRIVER_STAMP_AGE_US before it (a
    realtime-clock or stream-time stamp is off by years or by the uptime).
    """
    if not math.isfinite(driver_ms) or driver_ms <= 0:
        return None
    t_us = round(driver_ms * 1000.0)
    return t_us if grab_us - MAX_DRIVER_STAMP_AGE_US <= t_us <= grab_us else None


NETWORK_SCHEMES = ("rtsp", "rtsps", "rtmp", "http", "https", "udp", "tcp", "rtp", "srt", "file")


def check_camera_url(url: str, key: str = "service.camera_url") -> str | None:
    """Check a camera URL without opening it: ConfigError naming ``key`` when it cannot work;
    a warning text when it may work later (a device that is not plugged in yet), else None."""
    if not url:
        raise ConfigError(f"{key}: empty")
    if url.startswith(("sitl://", "folder:")) or url.isdigit():
        return None  # open_camera() checks these forms fully
    scheme, sep, _ = url.partition("://")
    if sep:
        if scheme.lower() not in NETWORK_SCHEMES:
            raise ConfigError(
                f"{key}: unknown URL scheme {scheme!r} (known: sitl, folder:, "
                f"{', '.join(NETWORK_SCHEMES)}, a /dev/video device or a GStreamer pipeline)"
            )
        return None
    if "!" in url:  # a GStreamer pipeline (it must end in appsink)
        if "appsink" not in url:
            raise ConfigError(f"{key}: a GStreamer pipeline must end in appsink: {url!r}")
        return None
    path = Path(url)
    if url.startswith("/dev/"):
        return None if path.exists() else f"{key}: {url} does not exist (yet): waiting for it"
    if not path.is_file():
        raise ConfigError(
            f"{key}: {url!r} is neither a file, a device, a URL (scheme://...) nor a "
            "GStreamer pipeline"
        )
    return None


def open_camera(url: str, key: str = "service.camera_url") -> CameraSource:
    """The source for a config URL (see the module docstring); ConfigError naming ``key``."""
    if url.startswith("sitl://"):
        host, _, port = url[len("sitl://") :].rpartition(":")
        if not host or not port.isdigit():
            raise ConfigError(f"{key}: expected sitl://HOST:PORT, got {url!r}")
        return SitlStream(host, int(port))
    if url.startswith("folder:"):
        path, _, flag = url[len("folder:") :].partition("?")
        if not Path(path).is_dir():
            raise ConfigError(f"{key}: no such folder {path!r}")
        return FolderSource(Path(path), realtime=flag != "fast")
    if url.isdigit():
        return VideoCaptureSource(int(url))
    if not url:
        raise ConfigError(f"{key}: empty")
    return VideoCaptureSource(url)
