"""GStreamer camera source (``gst:PIPELINE``) through GStreamer's own Python bindings (PyGObject,
Debian's python3-gi + gir1.2-gstreamer-1.0 + gir1.2-gst-plugins-base-1.0), not through
OpenCV: the pip OpenCV build has no GStreamer. The pipeline must end in an ``appsink``.

Pixels: the appsink is limited to the raw formats we convert (``SINK_FORMATS``) unless the
pipeline gives it caps itself, so a ``videoconvert`` before it (or ``nvvidconv`` on a Jetson)
negotiates one of them; each buffer is copied out once, rows cut to the width (GStreamer pads a
row to 4 bytes: a 3-byte-per-pixel row of odd width has a stride larger than 3 * width) and
turned into the (H, W, 3) BGR array of a CameraFrame.

Time: the pipeline runs on a GstSystemClock of type MONOTONIC, i.e. CLOCK_MONOTONIC, the clock of
``time.monotonic_ns()`` and so of our ``time_us``. A buffer's PTS is a running time on that
clock (after the segment: ``segment.to_running_time``); ``base_time + running time`` is then the
clock time the source stamped: for a live camera source (v4l2src, libcamerasrc,
nvarguscamerasrc) the capture time it stamps. That time is used when it is plausible (not after
the buffer reached us, at most 0.5 s before); otherwise (a non-live pipeline: a file decoded as
fast as possible, ``videotestsrc`` without ``is-live``) the time the buffer reached the appsink.
``stamps`` says which ("gst pts" or "arrival").

End of stream ends ``frames()``. Whether the service then stops or reopens the pipeline is
decided by its source elements' kind, not by whether the pipeline is live (an MJPEG IP camera
read by ``souphttpsrc`` is not live, yet it is a camera): the pipeline is ``finite`` (a
recording: the service stops at its end) only when every source reads a file (``filesrc``,
``multifilesrc``, a ``uri`` of ``file:``) or is a non-live generator (``videotestsrc``
without ``is-live``). A device (v4l2src, libcamerasrc, nvarguscamerasrc), a network source
(a URI handler of another protocol, or a Source/Network element: souphttpsrc, rtspsrc,
udpsrc, srtsrc), a live source and any element we cannot tell make it a camera: reopened with
backoff when it ends (see ``source_kind``). An error message on the bus raises CameraError
with the element's name and GStreamer's text, with credentials masked (companion.redact);
nothing here can crash the service.
"""

from __future__ import annotations

import importlib
import logging
import re
import time
from collections.abc import Iterator
from typing import Any

import cv2
import numpy as np

from companion.drivers.camera.source import (
    CameraError,
    CameraSource,
    CaptureRequest,
    plausible_stamp_us,
)
from companion.errors import ConfigError
from companion.redact import redact_text, url_secrets
from companion.types import U8, CameraFrame

log = logging.getLogger("companion.camera")

# raw formats the appsink accepts, and for each: bytes per pixel, and the byte index of B, G, R
FORMAT_LAYOUT: dict[str, tuple[int, tuple[int, int, int]]] = {
    "BGR": (3, (0, 1, 2)),
    "RGB": (3, (2, 1, 0)),
    "BGRx": (4, (0, 1, 2)),
    "BGRA": (4, (0, 1, 2)),
    "RGBx": (4, (2, 1, 0)),
    "RGBA": (4, (2, 1, 0)),
    "xRGB": (4, (3, 2, 1)),
    "ARGB": (4, (3, 2, 1)),
    "xBGR": (4, (1, 2, 3)),
    "ABGR": (4, (1, 2, 3)),
    "GRAY8": (1, (0, 0, 0)),
}
SINK_FORMATS = "{BGR, BGRx, BGRA, RGB, RGBx, RGBA, xRGB, ARGB, xBGR, ABGR, GRAY8}"
PULL_TIMEOUT_S = 0.1  # how often the reader looks at the bus and at close()
EOS_ERROR_WAIT_NS = 200_000_000  # after EOS, how long an error that caused it may take
# source elements that read files; URI protocols that are files
FILE_SOURCES = ("filesrc", "multifilesrc", "splitmuxsrc", "imagesequencesrc")
FILE_PROTOCOLS = ("file", "multifile", "splitmux", "imagesequence")
FINITE_KINDS = ("file", "generator")  # a pipeline of these sources only is a recording
INSTALL_HINT = (
    "GStreamer's Python bindings are needed: apt-get install python3-gi gir1.2-gstreamer-1.0 "
    "gir1.2-gst-plugins-base-1.0 gstreamer1.0-plugins-base gstreamer1.0-plugins-good, and a "
    "venv that sees them (make venv links gi into it: docs/install.md, Cameras)"
)


def load_gst() -> tuple[Any, Any]:
    """(Gst, GstVideo) from PyGObject, initialised; ImportError/ValueError when the bindings
    or the typelibs are missing."""
    gi = importlib.import_module("gi")
    gi.require_version("Gst", "1.0")
    gi.require_version("GstVideo", "1.0")
    gi.require_version("GstApp", "1.0")  # appsink's try_pull_sample as a method
    gst = importlib.import_module("gi.repository.Gst")
    gst_video = importlib.import_module("gi.repository.GstVideo")
    importlib.import_module("gi.repository.GstApp")
    if not gst.is_initialized():
        gst.init(None)
    return gst, gst_video


def frame_to_bgr(data: bytes, fmt: str, width: int, height: int, stride: int) -> U8:
    """One raw video frame (the bytes of a GstBuffer) as a (height, width, 3) uint8 BGR array.

    fmt: a GStreamer format name in FORMAT_LAYOUT; stride: bytes per row (>= width * bytes per
    pixel). CameraError when the format is not one we convert or the buffer is too short.
    """
    if fmt not in FORMAT_LAYOUT:
        raise CameraError(
            f"camera gst: appsink negotiated {fmt!r}; put a videoconvert before the appsink or "
            f"ask for one of {SINK_FORMATS}"
        )
    bpp, (b, g, r) = FORMAT_LAYOUT[fmt]
    need = (height - 1) * stride + width * bpp
    if width <= 0 or height <= 0 or stride < width * bpp or len(data) < need:
        raise CameraError(
            f"camera gst: a {width}x{height} {fmt} buffer of {len(data)} bytes (stride {stride})"
        )
    flat = np.frombuffer(data, np.uint8, count=need)
    rows = np.lib.stride_tricks.as_strided(
        flat, shape=(height, width, bpp), strides=(stride, bpp, 1), writeable=False
    )
    if (b, g, r) == (0, 1, 2) and bpp == 3:
        return np.ascontiguousarray(rows)  # a view when the rows are not padded
    # OpenCV's conversions take padded rows as they are (4-6x faster than numpy indexing)
    code = _CV_CONVERSIONS.get((bpp, (b, g, r)))
    if code is not None:
        out: U8 = cv2.cvtColor(rows, code)
        return out
    return np.ascontiguousarray(rows[:, :, [b, g, r]])  # xRGB / xBGR: the padding byte first


_CV_CONVERSIONS = {
    (1, (0, 0, 0)): cv2.COLOR_GRAY2BGR,
    (3, (2, 1, 0)): cv2.COLOR_RGB2BGR,
    (4, (0, 1, 2)): cv2.COLOR_BGRA2BGR,
    (4, (2, 1, 0)): cv2.COLOR_RGBA2BGR,
}


def _appsink_text(pipeline: str) -> str:
    """The pipeline text of the last appsink (to see which properties the user set)."""
    parts = [p for p in pipeline.split("!") if re.search(r"\bappsink\b", p)]
    return parts[-1] if parts else ""


class GstSource(CameraSource):
    """Frames from a GStreamer pipeline ending in an appsink (see the module docstring).

    The pipeline is parsed when the source is made (a syntax error, an element or a plugin
    that is not installed, a property that does not exist, no appsink: ConfigError naming
    ``key``), and again each time ``frames()`` starts it. Nothing is opened before ``frames()``.
    """

    def __init__(
        self, pipeline: str, key: str = "service.camera_url", request: CaptureRequest | None = None
    ) -> None:
        super().__init__(request)
        self.pipeline_text = pipeline.strip()
        self.key = key
        try:
            self._gst, self._gst_video = load_gst()
        except (ImportError, ValueError) as e:
            raise ConfigError(f"{key}: gst: cannot load GStreamer ({e}). {INSTALL_HINT}") from None
        if request is not None and request.fourcc:
            log.info("camera.fourcc is for V4L2 devices; a gst: pipeline sets its own caps")
        pipe = self._parse()  # checked now, started later
        self.sources = self._source_kinds(pipe)  # (element name, kind) of each source
        self.finite = all(kind in FINITE_KINDS for _name, kind in self.sources)
        pipe.set_state(self._gst.State.NULL)
        self.live: bool | None = None  # known once started
        self._set_drop = False
        self.negotiated = ""  # "WIDTHxHEIGHT FORMAT" of the last caps seen

    def _parse(self) -> Any:
        Gst = self._gst
        try:
            pipe = Gst.parse_launch(self.pipeline_text)
        except Exception as e:  # GLib.Error: syntax, no such element / property
            why = self._redacted(str(getattr(e, "message", e)))  # may quote a value
            raise ConfigError(f"{self.key}: gst: {why}") from None
        if not isinstance(pipe, Gst.Pipeline):  # a single element: wrap it
            raise ConfigError(f"{self.key}: gst: a pipeline ending in appsink is needed")
        if self._appsink(pipe) is None:
            raise ConfigError(f"{self.key}: gst: the pipeline must end in an appsink")
        return pipe

    def _redacted(self, text: str) -> str:
        """``text`` (GStreamer's, which may quote a location or a property) with the
        pipeline's credentials masked."""
        return redact_text(text, url_secrets(self.pipeline_text))

    def _appsink(self, pipe: Any) -> Any:
        """The pipeline's (last) appsink, or None. Gst.Iterator is walked by hand: without
        gst-python's overrides it is not a Python iterable."""
        Gst = self._gst
        found = None
        it = pipe.iterate_sinks()
        while True:
            res, element = it.next()
            if res == Gst.IteratorResult.OK:
                if _factory(element) == "appsink":
                    found = element
            elif res == Gst.IteratorResult.RESYNC:
                it.resync()
                found = None
            else:  # DONE or ERROR
                return found

    def _source_kinds(self, pipe: Any) -> list[tuple[str, str]]:
        """(name, kind) of each of the pipeline's source elements (see ``source_kind``)."""
        Gst = self._gst
        out = []
        it = pipe.iterate_sources()
        while True:
            res, element = it.next()
            if res == Gst.IteratorResult.OK:
                out.append((str(element.get_name()), source_kind(Gst, element)))
            elif res == Gst.IteratorResult.RESYNC:
                it.resync()
                out = []
            else:  # DONE or ERROR
                return out

    def _sink(self, pipe: Any) -> Any:
        """The appsink, set up for a reader that wants the newest frame without waiting."""
        Gst = self._gst
        sink = self._appsink(pipe)
        user = _appsink_text(self.pipeline_text)
        if sink.get_property("caps") is None:
            sink.set_property("caps", Gst.Caps.from_string(f"video/x-raw,format={SINK_FORMATS}"))
        if "sync" not in user:
            sink.set_property("sync", False)  # a live source: no extra wait for the clock
        self._set_drop = "max-buffers" not in user and "drop" not in user
        if self._set_drop:
            sink.set_property("max-buffers", 2)  # a slow reader: the newest, not a backlog
        sink.set_property("emit-signals", False)
        return sink

    def _bus_error(self, msg: Any) -> CameraError:
        err, debug = msg.parse_error()
        src = msg.src.get_name() if msg.src is not None else "pipeline"
        detail = (debug or "").strip().splitlines()
        more = f" ({detail[-1]})" if detail else ""
        if "not-negotiated" in (debug or ""):
            more += f"; the appsink takes {SINK_FORMATS}: put a videoconvert before it"
        return CameraError(self._redacted(f"camera gst: {src}: {err.message}{more}"))

    def _start(self, pipe: Any, sink: Any) -> None:
        """PAUSED then PLAYING on our monotonic clock; CameraError from the bus on failure. A
        live source's old frames are dropped for new ones; a non-live one (a file) waits for
        the reader, so that none is lost."""
        Gst = self._gst
        clock = Gst.SystemClock.obtain()
        if clock.props.clock_type != Gst.ClockType.MONOTONIC:  # someone changed the default
            clock = Gst.SystemClock()
            clock.props.clock_type = Gst.ClockType.MONOTONIC
        pipe.use_clock(clock)
        bus = pipe.get_bus()
        ret = pipe.set_state(Gst.State.PAUSED)
        if ret != Gst.StateChangeReturn.FAILURE:
            self.live = ret == Gst.StateChangeReturn.NO_PREROLL
            if self._set_drop:
                sink.set_property("drop", self.live)
            ret = pipe.set_state(Gst.State.PLAYING)
        if ret == Gst.StateChangeReturn.FAILURE:
            msg = bus.timed_pop_filtered(Gst.SECOND, Gst.MessageType.ERROR)
            if msg is not None:
                raise self._bus_error(msg)
            shown = self._redacted(repr(self.pipeline_text))
            raise CameraError(f"camera gst: the pipeline does not start: {shown}")

    def _read(self) -> Iterator[CameraFrame]:
        Gst = self._gst
        pipe = self._parse()
        sink = self._sink(pipe)
        bus = pipe.get_bus()
        seq = 0
        try:
            self._start(pipe, sink)
            while not self.closed:
                msg = bus.pop_filtered(Gst.MessageType.ERROR | Gst.MessageType.EOS)
                if msg is not None and msg.type == Gst.MessageType.ERROR:
                    raise self._bus_error(msg)
                if msg is not None:  # EOS
                    log.info("camera gst: end of stream")
                    return
                sample = sink.try_pull_sample(int(PULL_TIMEOUT_S * Gst.SECOND))
                if sample is None:
                    if sink.is_eos():  # a source that fails posts its error, then sends EOS:
                        # the error may reach the bus after the EOS reached the appsink
                        late = bus.timed_pop_filtered(EOS_ERROR_WAIT_NS, Gst.MessageType.ERROR)
                        if late is not None:
                            raise self._bus_error(late)
                        log.info("camera gst: end of stream")
                        return
                    continue
                frame = self._frame(sample, pipe.get_base_time(), seq)
                if frame is not None:
                    yield frame
                    seq += 1
        finally:
            pipe.set_state(Gst.State.NULL)

    def _frame(self, sample: Any, base_time_ns: int, seq: int) -> CameraFrame | None:
        """A pulled sample as a CameraFrame stamped in our clock (see the module docstring)."""
        Gst = self._gst
        arrival_us = time.monotonic_ns() // 1000
        buf, caps = sample.get_buffer(), sample.get_caps()
        if buf is None or caps is None:
            return None
        info = self._gst_video.VideoInfo.new_from_caps(caps)
        fmt, w, h = info.finfo.name, info.width, info.height
        if self.negotiated != f"{w}x{h} {fmt}":
            self.negotiated = f"{w}x{h} {fmt}"
            log.info("camera gst: %s frames", self.negotiated)
        img = frame_to_bgr(buf.extract_dup(0, buf.get_size()), fmt, w, h, info.stride[0])
        t_us: int | None = None
        if buf.pts != Gst.CLOCK_TIME_NONE:
            running_ns = sample.get_segment().to_running_time(Gst.Format.TIME, buf.pts)
            if running_ns != Gst.CLOCK_TIME_NONE and running_ns >= 0:
                t_us = plausible_stamp_us((base_time_ns + running_ns) // 1000, arrival_us)
        stamps = "arrival" if t_us is None else "gst pts"
        if stamps != self.stamps:
            log.info("camera gst: frames stamped at %s", stamps)
            self.stamps = stamps
        return CameraFrame(arrival_us if t_us is None else t_us, seq, img)


def source_kind(Gst: Any, element: Any) -> str:
    """What a source element reads: "file" or "generator" (a recording: it ends for good),
    "network", "live" (a device, a live source) or "unknown" (all three a camera: reopened
    when it ends).

    In this order: a ``uri`` property (uridecodebin, urisourcebin, playbin) decides by its
    scheme; a Source/Network element is "network"; a live GstBaseSrc (v4l2src, libcamera's,
    ``is-live=true``) is "live"; a URI handler of a protocol that is not a file (rtmpsrc,
    appsrc) is "unknown"; a non-live GstBaseSrc is "file" when it reads files (FILE_SOURCES,
    Source/File), else "generator" (videotestsrc); anything else (a bin) is "unknown".
    """
    factory = element.get_factory()
    klass = str(factory.get_metadata("klass") or "") if factory is not None else ""
    if element.find_property("uri") is not None:
        uri = str(element.get_property("uri") or "")
        return "file" if uri.startswith("file:") else "network"
    if "Network" in klass:
        return "network"
    live = getattr(element, "is_live", None)  # GstBaseSrc's field; None: not a GstBaseSrc
    if not isinstance(live, bool):
        return "unknown"
    if live:
        return "live"
    protocols: list[str] = []
    if factory is not None and factory.get_uri_type() == Gst.URIType.SRC:
        protocols = list(factory.get_uri_protocols() or [])
    if any(p not in FILE_PROTOCOLS for p in protocols):
        return "unknown"
    return "file" if _factory(element) in FILE_SOURCES or "File" in klass else "generator"


def _factory(element: Any) -> str:
    f = element.get_factory()
    return str(f.get_name()) if f is not None else ""
