"""Raspberry Pi CSI cameras through libcamera's Picamera2 (``picamera2:[N]``, camera N).

Picamera2 (the ``pi`` extra; it needs Raspberry Pi OS's libcamera bindings, docs/install.md)
is used through its documented API only: ``Picamera2(N)``, ``create_video_configuration``,
``configure``, ``camera_configuration``, ``start``, ``capture_request`` -> ``make_array``,
``get_metadata``, ``release``, ``stop``, ``close``. The adapter's decisions are pure functions
(below) so they are tested without a camera:

- Pixels: main stream ``RGB888``, which libcamera lays out as B, G, R bytes (Picamera2's own
  PIL conversion maps ``RGB888`` to mode ``BGR``): the (H, W, 3) array is OpenCV BGR as is.
  ``BGR888`` would be R, G, B.
- Size and rate: ``main.size`` = (camera.width, camera.height); ``FrameDurationLimits`` =
  (1e6 / rate_hz, 1e6 / rate_hz) us; a fixed ``ExposureTime`` when camera.exposure_us > 0 (the
  Pi's AGC then varies the gain only). After ``configure`` the configuration is read back and
  a size or format libcamera changed is refused (CameraError naming the key); after
  ``SETTLE_FRAMES`` frames each frame's ``FrameDuration`` and (if fixed) ``ExposureTime``
  metadata must match the request.
- Time: ``SensorTimestamp`` [ns]. libcamera's control reference calls it the start of the
  first row's exposure on CLOCK_BOOTTIME; the kernel's V4L2 buffers it comes from are stamped on
  CLOCK_MONOTONIC at the start of frame (readout), and Picamera2 itself (0.3.38,
  ``wait_for_timestamp_``) takes ``SensorTimestamp - ExposureTime`` as the start of exposure
  and compares it with ``time.monotonic_ns()``. We follow the implementation Picamera2 relies
  on: mid-exposure = SensorTimestamp - ExposureTime / 2, on CLOCK_MONOTONIC (our clock), kept
  if plausible (drivers.camera.source.plausible_stamp_us), else the arrival time. (Read as the
  documentation says, the stamp would be one exposure time later: 1-10 ms.) The
  rolling-shutter readout (the last row is read a frame-readout time after the first) is not
  modelled.
"""

from __future__ import annotations

import importlib
import logging
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from companion.drivers.camera.source import (
    CameraError,
    CameraSource,
    CaptureRequest,
    plausible_stamp_us,
)
from companion.errors import ConfigError
from companion.types import U8, CameraFrame

log = logging.getLogger("companion.camera")

MAIN_FORMAT = "RGB888"  # B, G, R bytes in memory: OpenCV's BGR
SETTLE_FRAMES = 5  # controls reach the sensor a few frames after start
RATE_TOLERANCE = 0.02
EXPOSURE_TOLERANCE = 0.05
EXPOSURE_FLOOR_US = 100.0  # exposure is quantised to sensor lines (tens of us)
INSTALL_HINT = (
    "on Raspberry Pi OS: apt-get install python3-libcamera python3-kms++ libcap-dev, the venv "
    "linked to them (systemd/venv-system-modules.sh VENV gi libcamera pykms) and the `pi` "
    "extra (pip install 'companion[pi]'); docs/install.md, Raspberry Pi"
)


def video_configuration_args(request: CaptureRequest | None) -> dict[str, Any]:
    """Keyword arguments of ``Picamera2.create_video_configuration`` for a request (None: the
    camera's default size, our pixel format). ``queue=False``: a capture is always a frame
    exposed after the call, never one held back from before."""
    main: dict[str, Any] = {"format": MAIN_FORMAT}
    controls: dict[str, Any] = {}
    if request is not None:
        main["size"] = (request.width, request.height)
        period_us = round(1e6 / request.rate_hz)
        controls["FrameDurationLimits"] = (period_us, period_us)
        if request.exposure_us > 0:
            controls["ExposureTime"] = round(request.exposure_us)
    return {"main": main, "controls": controls, "queue": False}


def configuration_problems(request: CaptureRequest | None, config: dict[str, Any]) -> list[str]:
    """What libcamera changed in the main stream (``camera_configuration()`` after
    ``configure``), one text per config key."""
    main = config.get("main") or {}
    problems = []
    fmt = main.get("format")
    if fmt != MAIN_FORMAT:
        problems.append(f"picamera2: main stream format {fmt!r}, not {MAIN_FORMAT!r}")
    if request is not None:
        size = tuple(main.get("size") or ())
        if size != (request.width, request.height):
            problems.append(
                f"camera.width/camera.height: asked {request.width}x{request.height}, libcamera "
                f"configured {'x'.join(str(v) for v in size) or 'no size'} (Picamera2 rounds "
                "a size down to even numbers and libcamera may adjust it to what the ISP can "
                "output: 640x480, 1280x720 and other multiples of 16 are safe)"
            )
    return problems


def metadata_problems(request: CaptureRequest, metadata: dict[str, Any]) -> list[str]:
    """A settled frame's metadata against the request: FrameDuration [us] vs camera.rate_hz,
    ExposureTime [us] vs a fixed camera.exposure_us. Missing fields are not held against it."""
    problems = []
    period_us = 1e6 / request.rate_hz
    duration = metadata.get("FrameDuration")
    if duration is not None and abs(duration - period_us) > RATE_TOLERANCE * period_us:
        problems.append(
            f"camera.rate_hz: asked {request.rate_hz:g} Hz, the sensor runs at "
            f"{1e6 / duration:.4g} Hz (FrameDuration {duration} us; a sensor mode this fast at "
            "this size may not exist)"
        )
    exposure = metadata.get("ExposureTime")
    if request.exposure_us > 0 and exposure is not None:
        tol = max(EXPOSURE_FLOOR_US, EXPOSURE_TOLERANCE * request.exposure_us)
        if abs(exposure - request.exposure_us) > tol:
            problems.append(
                f"camera.exposure_us: asked {request.exposure_us:g} us, the sensor exposes "
                f"{exposure} us (at most the frame period)"
            )
    return problems


def sensor_stamp_us(metadata: dict[str, Any], arrival_us: int) -> int | None:
    """Mid-exposure time in our monotonic clock [us] from a frame's metadata, or None (no
    SensorTimestamp, or not plausible: see the module docstring).

    metadata: SensorTimestamp [ns, CLOCK_MONOTONIC, end of the first row's exposure],
    ExposureTime [us]; arrival_us: our clock when the request came back.
    """
    end_ns = metadata.get("SensorTimestamp")
    if not isinstance(end_ns, int) or end_ns <= 0:
        return None
    exposure_us = metadata.get("ExposureTime") or 0
    mid_ns = end_ns - round(exposure_us * 500)
    return plausible_stamp_us(mid_ns // 1000, arrival_us)


class Picamera2Source(CameraSource):
    """Frames from camera ``camera_num`` through Picamera2 (see the module docstring).

    ``factory``: what makes the camera object from its number (default ``picamera2.Picamera2``;
    the module must import when the source is made: ConfigError naming ``key`` otherwise).
    """

    def __init__(
        self,
        camera_num: int,
        key: str = "service.camera_url",
        request: CaptureRequest | None = None,
        factory: Callable[[int], Any] | None = None,
    ) -> None:
        super().__init__(request)
        self.camera_num = camera_num
        if factory is None:
            try:
                factory = importlib.import_module("picamera2").Picamera2
            except Exception as e:  # ImportError, or libcamera's own import failing
                raise ConfigError(
                    f"{key}: picamera2: cannot import picamera2 ({e}); {INSTALL_HINT}"
                ) from None
        self.factory = factory
        if request is not None and request.fourcc:
            log.info("camera.fourcc is for V4L2 devices; picamera2 uses %s", MAIN_FORMAT)

    def _open(self) -> Any:
        """The configured, started camera; CameraError for what it cannot do."""
        try:
            cam = self.factory(self.camera_num)
        except Exception as e:  # no camera N, the camera in use by another process
            raise CameraError(f"camera picamera2:{self.camera_num}: cannot open: {e}") from None
        try:
            cam.configure(cam.create_video_configuration(**video_configuration_args(self.request)))
            problems = configuration_problems(self.request, cam.camera_configuration())
            if problems:
                raise CameraError(f"camera picamera2:{self.camera_num}: " + "; ".join(problems))
            cam.start()
        except Exception as e:
            _close(cam)
            if isinstance(e, CameraError):
                raise
            raise CameraError(f"camera picamera2:{self.camera_num}: {e}") from None
        return cam

    def _read(self) -> Iterator[CameraFrame]:
        cam = self._open()
        seq = 0
        try:
            while not self.closed:
                request = cam.capture_request()
                try:
                    img: U8 = np.ascontiguousarray(request.make_array("main"))
                    metadata = dict(request.get_metadata())
                finally:
                    request.release()  # the buffer goes back to libcamera: we hold a copy
                arrival_us = time.monotonic_ns() // 1000
                if img.ndim != 3 or img.shape[2] != 3:
                    raise CameraError(
                        f"camera picamera2:{self.camera_num}: main stream array of shape "
                        f"{img.shape}, expected (H, W, 3)"
                    )
                if self.request is not None and seq >= SETTLE_FRAMES:
                    problems = metadata_problems(self.request, metadata)
                    if problems:
                        raise CameraError(
                            f"camera picamera2:{self.camera_num}: " + "; ".join(problems)
                        )
                t_us = sensor_stamp_us(metadata, arrival_us)
                stamps = "arrival" if t_us is None else "sensor timestamp"
                if stamps != self.stamps:
                    log.info("camera picamera2:%d: frames stamped at %s", self.camera_num, stamps)
                    self.stamps = stamps
                yield CameraFrame(arrival_us if t_us is None else t_us, seq, img)
                seq += 1
        finally:
            _close(cam)


def _close(cam: Any) -> None:
    """Stop and close, whatever state the camera is in (errors here are only logged)."""
    for name in ("stop", "close"):
        try:
            getattr(cam, name)()
        except Exception as e:
            log.debug("picamera2 %s: %s", name, e)
