"""GStreamer camera sources (drivers/camera/gst.py), run for real with videotestsrc and a
small MJPEG server: frames in BGR stamped on our clock, every raw format, errors and
end-of-stream, pipelines that cannot work, frames of another size than the intrinsics (and
the service that survives such a camera), a recording told from a camera."""

from __future__ import annotations

import asyncio
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from peers.cameras import camera

from companion.drivers.camera import (
    CameraError,
    check_camera_url,
    open_camera,
)
from companion.errors import ConfigError
from companion.types import CameraFrame

ROOT = Path(__file__).resolve().parents[3]


def gst_available() -> str | None:
    """Why GStreamer cannot be used here (None: it can). Asked in a child process: at
    collection time the check would otherwise initialise GStreamer (its threads, its plugin
    scanner) inside the pytest process that every later test shares."""
    probe = subprocess.run(
        [sys.executable, "-c", "from companion.drivers.camera.gst import load_gst; load_gst()"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    if probe.returncode != 0:
        why = (probe.stderr.strip().splitlines() or ["no output"])[-1]
        return (
            f"GStreamer's Python bindings do not load ({why}): apt-get install python3-gi "
            "gir1.2-gstreamer-1.0 gir1.2-gst-plugins-base-1.0 gstreamer1.0-plugins-base "
            "gstreamer1.0-plugins-good, then `make venv` (links gi into .venv)"
        )
    return None


GST_MISSING = gst_available()
needs_gst = pytest.mark.skipif(GST_MISSING is not None, reason=str(GST_MISSING))


def live_pipeline(width: int, height: int, n: int, pattern: str = "red", fmt: str = "BGR") -> str:
    return (
        f"gst:videotestsrc is-live=true num-buffers={n} pattern={pattern} ! "
        f"video/x-raw,width={width},height={height},framerate=30/1 ! videoconvert ! "
        f"video/x-raw,format={fmt} ! appsink"
    )


# --------------------------------------------------------------------------- GStreamer


@needs_gst
def test_gst_live_videotestsrc_frames_are_bgr_and_stamped_on_our_clock() -> None:
    """A live pipeline: 66 px rows of BGR are padded to 200 bytes by GStreamer (stride),
    the red pattern comes out as BGR (0, 0, 255), and each frame carries its PTS mapped to
    our monotonic clock: 1/30 s apart exactly, never after the frame reached us."""
    src = open_camera(live_pipeline(66, 48, 12), camera=camera(66, 48))
    frames, arrivals = [], []
    for f in src.frames():
        arrivals.append(time.monotonic_ns() // 1000)
        frames.append(f)
    assert len(frames) == 12 and src.stamps == "gst pts" and src.live and not src.finite
    assert [f.seq for f in frames] == list(range(12))
    for f, arrived in zip(frames, arrivals, strict=True):
        assert f.image_bgr.shape == (48, 66, 3) and f.image_bgr.dtype == np.uint8
        assert f.image_bgr.flags.c_contiguous
        b, g, r = (float(f.image_bgr[..., k].mean()) for k in range(3))
        assert r > 240 and b < 15 and g < 15, (b, g, r)
        assert arrived - 500_000 <= f.time_us <= arrived
    dt_us = np.diff([f.time_us for f in frames])
    assert np.all(dt_us > 0)
    np.testing.assert_allclose(dt_us, 1e6 / 30, atol=1.0)  # the buffers' PTS, not arrival


@needs_gst
@pytest.mark.parametrize("fmt", ["RGB", "BGRx", "RGBA", "xRGB", "ABGR", "GRAY8"])
def test_gst_each_raw_format_gives_the_same_bgr_image(fmt: str) -> None:
    """A non-live pipeline (deterministic SMPTE bars, 66 px wide: padded rows) through each
    format the appsink takes equals the same pipeline in BGR (grey: its B = G = R, linear in
    the BGR image's luma); a non-live pipeline is finite and loses no frame."""

    def grab(f: str) -> list[CameraFrame]:
        url = (
            "gst:videotestsrc num-buffers=4 pattern=smpte ! video/x-raw,width=66,height=48 ! "
            f"videoconvert ! video/x-raw,format={f} ! appsink"
        )
        src = open_camera(url)
        out = list(src.frames())
        assert src.finite and src.stamps == "arrival"
        return out

    ref, got = grab("BGR"), grab(fmt)
    assert len(ref) == len(got) == 4
    for a, b in zip(ref, got, strict=True):
        assert b.image_bgr.shape == (48, 66, 3)
        if fmt == "GRAY8":
            assert np.array_equal(b.image_bgr[..., 0], b.image_bgr[..., 2])
            luma = cv2.cvtColor(a.image_bgr, cv2.COLOR_BGR2GRAY).astype(int)
            # GStreamer's GRAY8 is video-range luma (16-235): linear in the BGR image's luma
            # over the seven bars (the top 2/3; the strips below have sub-pixel details)
            bars = slice(0, 30)
            grey = b.image_bgr[bars, :, 0].ravel()
            assert np.corrcoef(grey, luma[bars].ravel())[0, 1] > 0.99
        else:
            assert np.abs(a.image_bgr.astype(int) - b.image_bgr.astype(int)).max() <= 2


def test_frame_to_bgr_undoes_every_layout_and_row_padding() -> None:
    """The pure conversion: a random BGR image packed into each layout, rows padded to a
    larger stride, comes back exactly; a short buffer or an unknown format is a CameraError."""
    from companion.drivers.camera.gst import FORMAT_LAYOUT, frame_to_bgr

    rng = np.random.default_rng(1)
    h, w = 7, 5
    img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    for fmt, (bpp, (b, g, r)) in FORMAT_LAYOUT.items():
        stride = w * bpp + 3
        raw = np.full((h, stride), 77, np.uint8)
        px = raw[:, : w * bpp].reshape(h, w, bpp)
        if bpp == 1:
            px[..., 0] = img[..., 1]
            want = np.repeat(img[..., 1:2], 3, axis=2)
        else:
            px[..., b], px[..., g], px[..., r] = img[..., 0], img[..., 1], img[..., 2]
            want = img
        np.testing.assert_array_equal(frame_to_bgr(raw.tobytes(), fmt, w, h, stride), want)
        with pytest.raises(CameraError, match="bytes"):
            frame_to_bgr(raw.tobytes()[:-stride], fmt, w, h, stride)
    with pytest.raises(CameraError, match="videoconvert"):
        frame_to_bgr(b"\0" * 1000, "I420", 10, 10, 10)


@needs_gst
def test_gst_runtime_errors_and_eos_end_the_stream_cleanly() -> None:
    """EOS ends frames() with no error; a device that is not there and a format that cannot
    be negotiated raise CameraError with GStreamer's reason (the service reports and
    reopens); last_error keeps it for the status."""
    src = open_camera(live_pipeline(64, 48, 3))
    assert len(list(src.frames())) == 3 and src.last_error is None
    src = open_camera("gst:v4l2src device=/dev/video-none ! videoconvert ! appsink")
    with pytest.raises(CameraError, match="video-none") as e:
        list(src.frames())
    assert src.last_error == str(e.value)
    src = open_camera(
        "gst:videotestsrc ! video/x-raw,width=64,height=48 ! videoconvert ! "
        "video/x-raw,format=I420 ! appsink"
    )
    with pytest.raises(CameraError, match=r"not-negotiated.*videoconvert"):
        list(src.frames())
    # the same source again after an error: it starts afresh (the service's reopen)
    src = open_camera(live_pipeline(64, 48, 2))
    assert len(list(src.frames())) == 2 and len(list(src.frames())) == 2


@needs_gst
def test_gst_pipelines_that_cannot_work_are_config_errors_naming_the_key() -> None:
    for url, why in (
        ("gst:nosuchsrc ! appsink", "no element"),
        ("gst:videotestsrc bogus=1 ! appsink", "no property"),
        ("gst:videotestsrc ! fakesink", "appsink"),
        ("gst:videotestsrc ! ! appsink", ""),
        ("videotestsrc ! nosuchconvert ! appsink", "no element"),  # bare pipeline: gst too
    ):
        assert check_camera_url(url) is None  # the text alone is fine; parsing decides
        with pytest.raises(ConfigError, match=rf"service\.camera_url: gst: .*{why}"):
            open_camera(url)


@needs_gst
def test_gst_frames_of_another_size_than_the_intrinsics_are_refused() -> None:
    src = open_camera(live_pipeline(320, 240, 3), camera=camera(640, 480))
    with pytest.raises(CameraError) as e:
        list(src.frames())
    text = str(e.value)
    assert "camera.width/camera.height" in text and "320x240" in text and "640x480" in text


@needs_gst
def test_gst_under_refused_writable_executable_memory(tmp_path) -> None:
    """The unit has MemoryDenyWriteExecute=yes; videoconvert's ORC code generator must still
    work without writable+executable memory. The kernel's own equivalent (prctl PR_SET_MDWE,
    Linux >= 6.3) is set in a child process, which then runs a BGR pipeline."""
    code = textwrap.dedent(
        """
        import ctypes, sys
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(65, 1, 0, 0, 0) != 0:  # PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN
            print("NO-MDWE", ctypes.get_errno()); sys.exit(0)
        import mmap
        try:
            mmap.mmap(-1, 4096, prot=mmap.PROT_READ | mmap.PROT_WRITE | mmap.PROT_EXEC)
            print("W+X allowed"); sys.exit(1)
        except OSError:
            pass
        from companion.drivers.camera import open_camera
        url = ("gst:videotestsrc num-buffers=5 pattern=smpte ! video/x-raw,format=I420,"
               "width=320,height=240 ! videoconvert ! video/x-raw,format=BGR ! appsink")
        frames = list(open_camera(url).frames())
        print("FRAMES", len(frames), frames[0].image_bgr.shape)
        """
    )
    r = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120
    )
    if r.stdout.startswith("NO-MDWE"):
        pytest.skip(f"this kernel has no PR_SET_MDWE (Linux >= 6.3): {r.stdout.strip()}")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "FRAMES 5 (240, 320, 3)" in r.stdout, r.stdout + r.stderr


def serve_mjpeg_parts(parts_per_connection: int) -> tuple[int, Callable[[], None]]:
    """A tiny MJPEG camera over HTTP on 127.0.0.1 that sends ``parts_per_connection`` 64x48
    JPEG parts on each connection, then closes it (an IP camera that ends its stream);
    returns its port and a function that stops it."""
    import http.server

    rng = np.random.default_rng(4)
    jpg = cv2.imencode(".jpg", rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))[1].tobytes()

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=f")
            self.end_headers()
            head = b"--f\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n"
            for _ in range(parts_per_connection):
                self.wfile.write(head % len(jpg) + jpg + b"\r\n")
                time.sleep(1 / 30)
            self.close_connection = True

        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, daemon=True).start()

    def stop() -> None:
        server.shutdown()
        server.server_close()

    return server.server_address[1], stop


@needs_gst
def test_gst_a_network_camera_that_ends_its_stream_is_a_camera_not_a_recording() -> None:
    """souphttpsrc is not a live source, yet an MJPEG IP camera is a camera: its end of
    stream must not read as the end of a recording (the service would stop); frames() opens
    it again. Finiteness goes by the sources' kind, known before anything starts."""
    port, stop = serve_mjpeg_parts(6)
    try:
        src = open_camera(
            f"gst:souphttpsrc location=http://127.0.0.1:{port}/cam.mjpg ! multipartdemux ! "
            "jpegdec ! videoconvert ! appsink",
            camera=camera(64, 48),
        )
        assert not src.finite
        first, again = list(src.frames()), list(src.frames())  # ended, then reopened
        assert len(first) >= 3 and len(again) >= 3 and not src.live
        assert not src.finite and src.sources == [("souphttpsrc0", "network")]
    finally:
        stop()
    for pipeline, finite in (
        ("filesrc location=clip.avi ! decodebin", True),
        ("multifilesrc location=img%04d.jpg ! jpegdec", True),
        ("uridecodebin uri=file:///clip.mp4", True),
        ("videotestsrc num-buffers=5", True),  # not live: a generator that ends
        ("videotestsrc is-live=true", False),
        ("v4l2src device=/dev/video0", False),
        ("uridecodebin uri=rtsp://cam/live", False),
        ("rtspsrc location=rtsp://cam/live ! decodebin", False),
        ("udpsrc port=5600 ! application/x-rtp ! rtpjpegdepay ! jpegdec", False),
    ):
        assert open_camera(f"gst:{pipeline} ! videoconvert ! appsink").finite == finite, pipeline


# --------------------------------------------------------------------------- the service


@needs_gst
def test_the_service_survives_a_camera_of_the_wrong_size_and_says_why(tmp_path) -> None:
    """A 320x240 camera under 640x480 intrinsics: no frame reaches the pipeline, one warning
    names the keys, the status shows the problem, and the service keeps running."""
    from peers import service_config

    from companion.service.app import Service

    url = (
        "gst:videotestsrc is-live=true pattern=ball ! video/x-raw,width=320,height=240,"
        "framerate=30/1 ! videoconvert ! video/x-raw,format=BGR ! appsink"
    )
    cfg = service_config(tmp_path, camera_url=url)

    async def run() -> tuple[dict, list[str], int, object]:
        async with Service(cfg) as service:
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not service.intake.silent:
                await asyncio.sleep(0.1)
            await asyncio.sleep(0.5)
            operator = service.operator.state(time.monotonic_ns())
            return service.status(), list(service.stats.warnings), service.stats.frames_in, operator

    status, warnings, frames_in, operator = asyncio.run(run())
    assert frames_in == 0
    # the ground station's STATUSTEXT says which size, in a few words (not only "no frames")
    assert getattr(operator, "camera", None) == "no frames (320x240, calibrated 640x480)", operator
    problem = status["camera"]["problem"]
    assert problem.startswith("no frames: camera.width/camera.height") and "320x240" in problem
    refused = [w for w in warnings if "camera: failed: camera.width/camera.height" in w]
    assert len(refused) == 1, warnings  # once per outage, not once per reopening
