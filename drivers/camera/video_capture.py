"""cv2.VideoCapture sources: V4L2 / UVC devices (the request applied and read back), network
streams and video files; a V4L2 buffer's own time stamp when it is plausible."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from companion.drivers.camera.source import (
    CameraError,
    CameraSource,
    CaptureRequest,
    plausible_stamp_us,
)
from companion.redact import redact_url
from companion.types import CameraFrame

if TYPE_CHECKING:
    pass


log = logging.getLogger("companion.camera")

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
