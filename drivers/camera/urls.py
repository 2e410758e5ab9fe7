"""Camera URLs (config ``service.camera_url``): checked without opening (``check_camera_url``)
and turned into a source (``open_camera``)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

from companion.drivers.camera.folder import FolderSource
from companion.drivers.camera.sitl_stream import SitlStream
from companion.drivers.camera.source import CameraSource, CaptureRequest
from companion.drivers.camera.video_capture import VideoCaptureSource
from companion.errors import ConfigError
from companion.redact import redact_url

if TYPE_CHECKING:
    from companion.config import CameraConfig


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
        from companion.drivers.camera.gst import GstSource

        pipeline = url[len(GST_PREFIX) :] if url.startswith(GST_PREFIX) else url
        return GstSource(pipeline, key, request)
    if url.startswith(PICAMERA2_PREFIX):
        from companion.drivers.camera.picamera2 import Picamera2Source

        num = url[len(PICAMERA2_PREFIX) :] or "0"
        if not num.isdigit():
            raise ConfigError(f"{key}: expected picamera2:N (a camera number), got {url!r}")
        return Picamera2Source(int(num), key, request)
    if url.isdigit():
        return VideoCaptureSource(int(url), request, device=True)
    if not url:
        raise ConfigError(f"{key}: empty")
    return VideoCaptureSource(url, request, device=url.startswith("/dev/video"))
