"""Camera sources: GStreamer pipelines (``gst:``), Raspberry Pi CSI cameras (``picamera2:``),
V4L2 / UVC devices and other cv2.VideoCapture inputs (video files, network streams), image
folders (our dataset format and EuRoC) and the SITL loopback stream.

Every source is iterated in a worker thread (``read()`` blocks) and yields CameraFrame with
``time_us`` in the companion's monotonic clock at exposure and a (H, W, 3) BGR image:
- GStreamer (drivers/camera_gst.py): the buffer's PTS on the pipeline clock, which we set to a
  CLOCK_MONOTONIC system clock (see that module);
- picamera2 (drivers/camera_picamera2.py): libcamera's SensorTimestamp + half the exposure;
- VideoCapture: with the V4L2 backend the buffer's timestamp (``CAP_PROP_POS_MSEC``; the
  kernel stamps buffers with CLOCK_MONOTONIC, uvcvideo at the start of the frame) when it is
  plausible (not in the future, at most 0.5 s before ``grab()`` returned), else the time
  ``grab()`` returned (FFmpeg: its position is stream time, not our clock);
- folders: the recorded times, shifted so that the first frame is "now" (replayed at the
  recorded rate, or as fast as possible with ``realtime=False``);
- the SITL stream: the time written by the simulator (same machine, same monotonic clock).
``stamps`` says where the last frame's time came from.

``url`` forms (config ``service.camera_url``): ``sitl://HOST:PORT``, ``folder:PATH[?fast]``,
``gst:PIPELINE`` (ending in ``appsink``; a bare pipeline with ``!`` is taken as ``gst:`` too),
``picamera2:[N]`` (camera N, default 0), ``/dev/videoN`` or an integer (V4L2), anything else
goes to VideoCapture (a file, ``rtsp://...``, ``http://...``).

What was asked of the camera (``CaptureRequest``, from the ``[camera]`` table: width, height,
rate_hz, fourcc, exposure_us) is applied where the source can apply it (V4L2 devices, picamera2)
and read back: a device that sets something else is refused with CameraError naming the key. On
every source, a frame whose size is not the calibrated ``camera.width`` x ``camera.height`` is
refused the same way (intrinsics of another size would give a wrong metric pose, silently).

SITL stream format (TCP, the simulator is the server): each frame is a 32-byte little-endian
header ``struct '<4sIqHHIII'`` = magic ``b"CFRM"``, seq (uint32), time_us (int64, monotonic clock
of the machine at mid-exposure), width, height (uint16), pixel format (uint32, 0 = BGR8),
payload length (uint32), reserved (uint32), followed by the payload (height*width*3 bytes).
"""

from __future__ import annotations

import contextlib
import logging
import math
import re
import socket
import struct
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.errors import CompanionError, ConfigError
from companion.redact import redact_url
from companion.types import CameraFrame

if TYPE_CHECKING:
    from companion.config import CameraConfig

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


class CameraError(CompanionError):
    """A camera that cannot deliver what the config asks (a size, a rate, a pixel format), or a
    driver error (a GStreamer element, libcamera). The message names the config key;
    ``brief`` says it in a few words for a ground station (STATUSTEXT: 50 characters)."""

    def __init__(self, message: str, brief: str = "") -> None:
        super().__init__(message)
        self.brief = brief


@dataclass(frozen=True, slots=True)
class CaptureRequest:
    """What the ``[camera]`` table asks of a camera: the calibrated image size [px], the frame
    rate [Hz], a V4L2 pixel format (4 characters, "" = the driver's) and a fixed exposure
    time [us] (0 = automatic)."""

    width: int
    height: int
    rate_hz: float
    fourcc: str = ""
    exposure_us: float = 0.0

    @classmethod
    def from_config(cls, camera: CameraConfig) -> CaptureRequest:
        """The request of a ``[camera]`` table."""
        return cls(camera.width, camera.height, camera.rate_hz, camera.fourcc, camera.exposure_us)


def check_frame_size(img: np.ndarray, request: CaptureRequest | None) -> None:
    """CameraError naming camera.width / camera.height when ``img`` (H, W[, C]) is not the
    calibrated size (None: nothing to check against)."""
    if request is None:
        return
    h, w = img.shape[:2]
    if (w, h) != (request.width, request.height):
        raise CameraError(
            f"camera.width/camera.height: the camera delivers {w}x{h} frames, the intrinsics "
            f"are calibrated for {request.width}x{request.height}; set the camera to that size "
            "or calibrate it at this one (frames refused)",
            brief=f"{w}x{h}, calibrated {request.width}x{request.height}",
        )


def plausible_stamp_us(t_us: int, arrival_us: int) -> int | None:
    """A driver's frame time [us] if it can be our monotonic clock at exposure: not after the
    frame arrived and at most MAX_DRIVER_STAMP_AGE_US before (a stream-time or realtime stamp is
    off by the uptime or by years); else None (the caller uses the arrival time)."""
    return t_us if arrival_us - MAX_DRIVER_STAMP_AGE_US <= t_us <= arrival_us else None


class CameraSource(ABC):
    """Base: ``frames()`` yields CameraFrame until the source ends or ``close()``; it may be
    called again after it ended (the service reopens a camera). ``finite``: a recording that
    ends for good, decided by the source's kind: a ``folder:``, a video file (a path or
    ``file://``), a ``gst:`` pipeline whose sources all read files or generate frames; never
    a device, a network URL, the SITL stream, picamera2, or a pipeline with a live, network
    or unknown source (drivers/camera_gst.py): those are cameras, reopened with backoff.
    ``request``: what the config asks (None: take what comes, e.g. for a check that opens
    nothing). ``last_error``: the driver error that ended the last ``frames()``, None once a
    frame came again."""

    finite = False

    def __init__(self, request: CaptureRequest | None = None) -> None:
        self.closed = False
        self.stamps = "source"  # where the last frame's time_us came from
        self.request = request
        self.last_error: str | None = None
        self.last_error_brief: str | None = None  # CameraError.brief of last_error, if any

    def frames(self) -> Iterator[CameraFrame]:
        """The frames, stamped in our monotonic clock at exposure (blocking; a worker thread);
        CameraError for a frame that is not the calibrated size, or a driver error."""
        try:
            for frame in self._read():
                check_frame_size(frame.image_bgr, self.request)
                self.last_error = self.last_error_brief = None
                yield frame
        except Exception as e:
            self.last_error = str(e)
            self.last_error_brief = e.brief or None if isinstance(e, CameraError) else None
            raise

    @abstractmethod
    def _read(self) -> Iterator[CameraFrame]:
        """The source's own frames (``frames()`` adds the checks)."""

    def close(self) -> None:
        self.closed = True


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


MAX_REPLAY_GAP_S = 1.0  # FolderSource: a longer gap between two frames is replayed as this


class FolderSource(CameraSource):
    """A recorded dataset (ours or EuRoC) replayed at its rate (or as fast as possible), read
    under drivers/safe_files.py's discipline (nothing outside the folder, regular files only,
    each image's size checked before it is decoded); a gap in its time stamps is replayed as
    MAX_REPLAY_GAP_S at most."""

    finite = True

    def __init__(
        self, path: Path, realtime: bool = True, request: CaptureRequest | None = None
    ) -> None:
        super().__init__(request)
        from companion.drivers.dataset import open_dataset

        self.dataset = open_dataset(path)
        self.realtime = realtime

    def _read(self) -> Iterator[CameraFrame]:
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
                if wait > MAX_REPLAY_GAP_S:  # a gap in the recording (or a hostile time
                    # stamp, 2**62 us ahead): replayed as a short pause, not slept through
                    shift -= int((wait - MAX_REPLAY_GAP_S) * 1e6)
                    wait = MAX_REPLAY_GAP_S
                if wait > 0:
                    time.sleep(wait)
            else:
                shift = now_us - ev.time_us  # as fast as possible: stamp with "now"
            yield CameraFrame(ev.time_us + shift, ev.seq, ev.image_bgr)


# V4L2 controls as OpenCV's V4L2 backend passes them through (raw driver values)
V4L2_EXPOSURE_MANUAL = 1  # CAP_PROP_AUTO_EXPOSURE: V4L2_EXPOSURE_MANUAL (3 = aperture priority)
V4L2_EXPOSURE_UNIT_US = 100.0  # CAP_PROP_EXPOSURE: V4L2 exposure_time_absolute, 100 us units
RATE_TOLERANCE = 0.02  # a read-back frame rate within 2 % is the one asked (30 vs 30.0003)
EXPOSURE_TOLERANCE = 0.05  # sensors quantise the exposure to line times (a few %)


def fourcc_text(code: float) -> str:
    """The 4 characters of a FOURCC as CAP_PROP_FOURCC returns it (a float of the int code)."""
    n = int(code) if math.isfinite(code) and code > 0 else 0
    return "".join(chr((n >> (8 * i)) & 0xFF) for i in range(4)).rstrip("\x00")


def fourcc_code(text: str) -> int:
    """The int code of a 4-character FOURCC ("MJPG")."""
    return sum(ord(c) << (8 * i) for i, c in enumerate(text))


def uvc_settings(request: CaptureRequest) -> list[tuple[str, int, float]]:
    """(config key, cv2 property id, value) to set on a V4L2 device, in the order that works:
    the pixel format first (it decides which sizes and rates exist), then the size, the rate,
    and a fixed exposure when asked (exposure_us = 0 leaves the driver's automatic exposure)."""
    import cv2

    out: list[tuple[str, int, float]] = []
    if request.fourcc:
        out.append(("camera.fourcc", cv2.CAP_PROP_FOURCC, float(fourcc_code(request.fourcc))))
    out += [
        ("camera.width", cv2.CAP_PROP_FRAME_WIDTH, float(request.width)),
        ("camera.height", cv2.CAP_PROP_FRAME_HEIGHT, float(request.height)),
        ("camera.rate_hz", cv2.CAP_PROP_FPS, float(request.rate_hz)),
    ]
    if request.exposure_us > 0:
        out += [
            ("camera.exposure_us", cv2.CAP_PROP_AUTO_EXPOSURE, float(V4L2_EXPOSURE_MANUAL)),
            (
                "camera.exposure_us",
                cv2.CAP_PROP_EXPOSURE,
                request.exposure_us / V4L2_EXPOSURE_UNIT_US,
            ),
        ]
    return out


def uvc_readback_problems(request: CaptureRequest, get: Callable[[int], float]) -> list[str]:
    """What a V4L2 device set differently from the request, one text per config key (empty:
    all as asked). ``get``: ``cv2.VideoCapture.get`` after the settings were applied (the
    backend reads them back from the driver: VIDIOC_G_FMT, G_PARM, G_CTRL). A rate the driver
    cannot report (0 or less) is not held against it."""
    import cv2

    problems = []
    if request.fourcc:
        got = fourcc_text(get(cv2.CAP_PROP_FOURCC))
        if got != request.fourcc:
            problems.append(f"camera.fourcc: asked {request.fourcc!r}, the driver set {got!r}")
    w, h = get(cv2.CAP_PROP_FRAME_WIDTH), get(cv2.CAP_PROP_FRAME_HEIGHT)
    if (round(w), round(h)) != (request.width, request.height):
        problems.append(
            f"camera.width/camera.height: asked {request.width}x{request.height}, the driver "
            f"set {w:g}x{h:g} (the sizes it has: v4l2-ctl --list-formats-ext)"
        )
    fps = get(cv2.CAP_PROP_FPS)
    if fps > 0 and abs(fps - request.rate_hz) > RATE_TOLERANCE * request.rate_hz:
        problems.append(f"camera.rate_hz: asked {request.rate_hz:g} Hz, the driver set {fps:g} Hz")
    if request.exposure_us > 0:
        mode = get(cv2.CAP_PROP_AUTO_EXPOSURE)
        got_us = get(cv2.CAP_PROP_EXPOSURE) * V4L2_EXPOSURE_UNIT_US
        if round(mode) != V4L2_EXPOSURE_MANUAL:
            problems.append(
                f"camera.exposure_us: the driver kept automatic exposure (mode {mode:g}, "
                f"manual is {V4L2_EXPOSURE_MANUAL})"
            )
        elif abs(got_us - request.exposure_us) > max(
            V4L2_EXPOSURE_UNIT_US, EXPOSURE_TOLERANCE * request.exposure_us
        ):
            problems.append(
                f"camera.exposure_us: asked {request.exposure_us:g} us, the driver set "
                f"{got_us:g} us"
            )
    return problems


class VideoCaptureSource(CameraSource):
    """cv2.VideoCapture: a V4L2 device (``device``: settings applied and read back), a
    network stream or a video file."""

    def __init__(
        self, spec: str | int, request: CaptureRequest | None = None, device: bool = False
    ) -> None:
        super().__init__(request)
        self.spec = spec
        self.shown = redact_url(spec) if isinstance(spec, str) else spec  # for log and errors
        self.device = device
        self.finite = is_video_file(spec)  # a recording ends for good; a camera is reopened

    def _open(self) -> Any:
        """The opened capture, with the request applied and checked on a V4L2 device."""
        import cv2

        cap = (
            cv2.VideoCapture(self.spec, cv2.CAP_V4L2)
            if self.device
            else cv2.VideoCapture(self.spec)
        )
        # a stalled network stream must not block forever (FFmpeg backend)
        cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, 2000)
        if not cap.isOpened():
            raise CameraError(f"camera {self.shown!r}: cannot open")
        if self.device and self.request is not None:
            for _key, prop, value in uvc_settings(self.request):
                cap.set(prop, value)  # False is common for a value the driver rounds: read back
            problems = uvc_readback_problems(self.request, cap.get)
            if problems:
                cap.release()
                raise CameraError(f"camera {self.shown!r}: " + "; ".join(problems))
        return cap

    def _read(self) -> Iterator[CameraFrame]:
        import cv2

        cap = self._open()
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
                    log.info("camera %r: frames stamped at %s", self.shown, stamps)
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


def is_video_file(spec: str | int) -> bool:
    """Whether a VideoCapture spec is a recording (a video file, a ``file://`` URL), which
    ends for good, rather than a camera (a device, a network stream), which is reopened."""
    if not isinstance(spec, str):
        return False  # a device number
    scheme, sep, _rest = spec.partition("://")
    if sep:
        return scheme.lower() == "file"
    return not spec.startswith("/dev/") and Path(spec).is_file()


def driver_stamp_us(driver_ms: float, grab_us: int) -> int | None:
    """A frame's driver timestamp in our monotonic clock [us], or None when it cannot be.

    driver_ms: ``CAP_PROP_POS_MSEC`` read after ``grab()`` (V4L2: the buffer's timestamp,
    CLOCK_MONOTONIC; 0 before the first buffer); grab_us: our monotonic clock when ``grab()``
    returned. Plausible = not after grab_us and at most MAX_DRIVER_STAMP_AGE_US before it (a
    realtime-clock or stream-time stamp is off by years or by the uptime).
    """
    if not math.isfinite(driver_ms) or driver_ms <= 0:
        return None
    return plausible_stamp_us(round(driver_ms * 1000.0), grab_us)


NETWORK_SCHEMES = ("rtsp", "rtsps", "rtmp", "http", "https", "udp", "tcp", "rtp", "srt", "file")
GST_PREFIX = "gst:"
PICAMERA2_PREFIX = "picamera2:"
_URL = re.compile(r"[A-Za-z][A-Za-z0-9+.\-]*://")


def is_gst_pipeline(url: str) -> bool:
    """``gst:PIPELINE``, or a bare pipeline (elements joined by ``!``, not a scheme://URL)."""
    return url.startswith(GST_PREFIX) or ("!" in url and _URL.match(url) is None)


def check_camera_url(url: str, key: str = "service.camera_url") -> str | None:
    """Check a camera URL without opening it: ConfigError naming ``key`` when it cannot work;
    a warning text when it may work later (a device that is not plugged in yet), else None."""
    if not url:
        raise ConfigError(f"{key}: empty")
    if url.startswith(("sitl://", "folder:", GST_PREFIX, PICAMERA2_PREFIX)) or url.isdigit():
        return None  # open_camera() checks these forms fully
    if is_gst_pipeline(url):
        return None  # open_camera() parses it
    scheme, sep, _ = url.partition("://")
    if sep:
        if scheme.lower() not in NETWORK_SCHEMES:
            raise ConfigError(
                f"{key}: unknown URL scheme {scheme!r} (known: sitl, folder:, gst:, picamera2:, "
                f"{', '.join(NETWORK_SCHEMES)}, a /dev/video device or a GStreamer pipeline)"
            )
        return None
    path = Path(url)
    if url.startswith("/dev/"):
        return None if path.exists() else f"{key}: {url} does not exist (yet): waiting for it"
    if not path.is_file():
        raise ConfigError(
            f"{key}: {redact_url(url)!r} is neither a file, a device, a URL (scheme://...) nor a "
            "GStreamer pipeline"
        )
    return None


def open_camera(
    url: str, key: str = "service.camera_url", camera: CameraConfig | None = None
) -> CameraSource:
    """The source for a config URL (see the module docstring); ConfigError naming ``key``.
    ``camera``: the ``[camera]`` table, whose size, rate, FOURCC and exposure are asked of the
    camera and checked (None: nothing asked or checked; nothing is opened either way)."""
    request = CaptureRequest.from_config(camera) if camera is not None else None
    if url.startswith("sitl://"):
        host, _, port = url[len("sitl://") :].rpartition(":")
        if not host or not port.isdigit():
            raise ConfigError(f"{key}: expected sitl://HOST:PORT, got {url!r}")
        return SitlStream(host, int(port), request=request)
    if url.startswith("folder:"):
        path, _, flag = url[len("folder:") :].partition("?")
        if not Path(path).is_dir():
            raise ConfigError(f"{key}: no such folder {path!r}")
        return FolderSource(Path(path), realtime=flag != "fast", request=request)
    if is_gst_pipeline(url):
        from companion.drivers.camera_gst import GstSource

        pipeline = url[len(GST_PREFIX) :] if url.startswith(GST_PREFIX) else url
        return GstSource(pipeline, key, request)
    if url.startswith(PICAMERA2_PREFIX):
        from companion.drivers.camera_picamera2 import Picamera2Source

        num = url[len(PICAMERA2_PREFIX) :] or "0"
        if not num.isdigit():
            raise ConfigError(f"{key}: expected picamera2:N (a camera number), got {url!r}")
        return Picamera2Source(int(num), key, request)
    if url.isdigit():
        return VideoCaptureSource(int(url), request, device=True)
    if not url:
        raise ConfigError(f"{key}: empty")
    return VideoCaptureSource(url, request, device=url.startswith("/dev/video"))
