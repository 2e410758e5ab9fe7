"""The camera source contract: ``CameraSource`` (frames stamped in our monotonic clock at
exposure, checked against the calibrated size), ``CaptureRequest`` (what the ``[camera]``
table asks), ``CameraError`` and the plausibility rule for a driver's own time stamps."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from companion.errors import CompanionError
from companion.types import CameraFrame

if TYPE_CHECKING:
    from companion.config import CameraConfig


MAX_DRIVER_STAMP_AGE_US = 500_000  # a driver stamp older than this at grab() is not our clock


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
    or unknown source (drivers/camera/gst.py): those are cameras, reopened with backoff.
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
