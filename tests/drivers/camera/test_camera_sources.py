"""Camera sources (drivers.camera): the SITL stream's framing, URLs, a folder replayed at its
rate, V4L2 buffer stamps."""

from __future__ import annotations

import socket
import threading

import numpy as np
import pytest

from companion.drivers.camera import SitlStream, VideoCaptureSource, encode_frame, open_camera
from companion.errors import ConfigError
from companion.types import CameraFrame


def test_sitl_stream_round_trip() -> None:
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    port = server.getsockname()[1]
    rng = np.random.default_rng(2)
    sent = [
        CameraFrame(1000 * k, k, rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
        for k in range(5)
    ]

    def serve() -> None:
        conn, _ = server.accept()
        with conn:
            for f in sent:
                conn.sendall(encode_frame(f))

    thread = threading.Thread(target=serve)
    thread.start()
    src = open_camera(f"sitl://127.0.0.1:{port}")
    assert isinstance(src, SitlStream)
    got = []
    for f in src.frames():
        got.append(f)
        if len(got) == len(sent):
            src.close()
    thread.join()
    server.close()
    for a, b in zip(sent, got, strict=True):
        assert (a.time_us, a.seq) == (b.time_us, b.seq)
        np.testing.assert_array_equal(a.image_bgr, b.image_bgr)


def test_camera_urls_are_checked(tmp_path) -> None:
    with pytest.raises(ConfigError, match=r"service\.camera_url"):
        open_camera("sitl://nohost")
    with pytest.raises(ConfigError, match=r"service\.camera_url"):
        open_camera(f"folder:{tmp_path / 'missing'}")
    assert isinstance(open_camera("0"), VideoCaptureSource)


def test_folder_source_replays_at_the_recorded_rate(tmp_path) -> None:
    import time

    from companion.config import load_config
    from companion.sitl.world.dataset import record

    cfg = load_config(overrides={"sitl": {"terrain": "flat", "seconds": 0.5}})
    path = record(cfg, tmp_path / "ds", image_format="png", progress=False)
    t0 = time.monotonic()
    frames = list(open_camera(f"folder:{path}").frames())
    elapsed = time.monotonic() - t0
    assert len(frames) == 15
    dt_us = np.diff([f.time_us for f in frames])
    np.testing.assert_allclose(dt_us, 1e6 / 30, atol=2)  # recorded spacing kept
    assert elapsed >= 14 / 30 - 0.01  # not faster than recorded
    fast = list(open_camera(f"folder:{path}?fast").frames())
    assert [f.seq for f in fast] == [f.seq for f in frames]
    np.testing.assert_array_equal(fast[3].image_bgr, frames[3].image_bgr)


class _FakeCapture:
    """cv2.VideoCapture of a device that cannot exist here: a backend name and a
    CAP_PROP_POS_MSEC that is either the V4L2 buffer stamp or a stream position."""

    def __init__(self, backend: str, stamp_ms) -> None:
        self.backend, self.stamp_ms, self.n = backend, stamp_ms, 0

    def set(self, *_a) -> bool:
        return True

    def isOpened(self) -> bool:
        return True

    def getBackendName(self) -> str:
        return self.backend

    def grab(self) -> bool:
        self.n += 1
        return self.n <= 3

    def get(self, prop: int) -> float:
        import cv2

        assert prop == cv2.CAP_PROP_POS_MSEC
        return self.stamp_ms(self.n)

    def retrieve(self):
        return True, np.zeros((4, 6), np.uint8)

    def release(self) -> None:
        pass


def test_v4l2_buffer_stamps_are_used_when_they_are_our_clock(monkeypatch) -> None:
    import time

    import cv2

    from companion.drivers.camera import MAX_DRIVER_STAMP_AGE_US, driver_stamp_us

    now_us = 5_000_000_000
    assert driver_stamp_us(now_us / 1e3 - 20.0, now_us) == now_us - 20_000
    assert driver_stamp_us(0.0, now_us) is None  # before the first buffer
    assert driver_stamp_us(float("nan"), now_us) is None
    assert driver_stamp_us(now_us / 1e3 + 5.0, now_us) is None  # from the future
    assert driver_stamp_us((now_us - MAX_DRIVER_STAMP_AGE_US) / 1e3 - 1, now_us) is None
    assert driver_stamp_us(1.7e12, now_us) is None  # a realtime-clock stamp

    def frames(backend: str, stamp_ms) -> tuple[list[CameraFrame], list[int], str]:
        cap = _FakeCapture(backend, stamp_ms)
        monkeypatch.setattr(cv2, "VideoCapture", lambda _spec: cap)
        src = VideoCaptureSource(0)
        grabbed = []
        out = []
        for f in src.frames():
            out.append(f)
            grabbed.append(time.monotonic_ns() // 1000)
        return out, grabbed, src.stamps

    # V4L2: the buffer was stamped 30 ms before grab() returned -> that stamp
    exposure_us: list[int] = []

    def v4l2_stamp(_n: int) -> float:
        exposure_us.append(time.monotonic_ns() // 1000 - 30_000)
        return exposure_us[-1] / 1e3

    got, _, stamps = frames("V4L2", v4l2_stamp)
    assert stamps == "v4l2 buffer" and len(got) == 3
    assert [f.time_us for f in got] == exposure_us
    assert [f.image_bgr.shape for f in got] == [(4, 6, 3)] * 3  # grey converted to BGR
    # FFmpeg: POS_MSEC is the stream position -> the grab time, even if it looks plausible
    got, after, stamps = frames("FFMPEG", lambda n: time.monotonic_ns() / 1e6 - 10.0)
    assert stamps == "grab"
    assert all(0 <= a - f.time_us < 50_000 for f, a in zip(got, after, strict=True))
    # V4L2 with a realtime-clock stamp (an old kernel or driver) -> the grab time
    got, _, stamps = frames("V4L2", lambda n: time.time() * 1e3)
    assert stamps == "grab"
