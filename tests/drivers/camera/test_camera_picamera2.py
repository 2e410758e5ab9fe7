"""The Picamera2 source (drivers/camera/picamera2.py), tested at its seam: Picamera2 cannot
run here (no libcamera, no camera), so the adapter runs against a small object following
Picamera2's documented API and libcamera's pixel layout."""

from __future__ import annotations

import sys
import time

import numpy as np
import pytest

from companion.drivers.camera import (
    CameraError,
    CaptureRequest,
    check_camera_url,
    open_camera,
)
from companion.errors import ConfigError


class FakeRequest:
    def __init__(self, cam: FakePicamera2, k: int) -> None:
        self.cam, self.k, self.released = cam, k, False

    def make_array(self, name: str) -> np.ndarray:
        assert name == "main" and not self.released
        w, h = self.cam.configured["main"]["size"]
        scene = self.cam.scene_bgr[:h, :w]
        fmt = self.cam.configured["main"]["format"]
        # libcamera: RGB888 is stored B, G, R; BGR888 is stored R, G, B
        return scene.copy() if fmt == "RGB888" else scene[..., ::-1].copy()

    def get_metadata(self) -> dict:
        return {
            "SensorTimestamp": self.cam.t0_ns + self.k * 33_333_000,
            "ExposureTime": self.cam.exposure_us,
            "FrameDuration": self.cam.frame_duration_us,
        }

    def release(self) -> None:
        self.released = True


class FakePicamera2:
    """Picamera2's documented calls: create_video_configuration, configure,
    camera_configuration, start, capture_request, stop, close."""

    def __init__(self, num: int = 0) -> None:
        self.num = num
        self.scene_bgr = np.random.default_rng(5).integers(0, 256, (480, 640, 3), np.uint8)
        self.aligned = False
        self.exposure_us = 4000
        self.frame_duration_us = 33_333
        self.requests: list[FakeRequest] = []
        self.calls: list[str] = []
        # each frame's first row finished its exposure 20 ms before it is captured
        self.t0_ns = time.monotonic_ns() - 20_000_000

    def create_video_configuration(self, main=None, controls=None, queue=True, **_):
        self.calls.append("create")
        return {"main": dict(main or {}), "controls": dict(controls or {}), "queue": queue}

    def configure(self, config) -> None:
        self.calls.append("configure")
        self.configured = config
        w, h = config["main"].get("size", (640, 480))
        if self.aligned:  # what Picamera2's align_stream(optimal=False) does: even sizes
            w, h = w - w % 2, h - h % 2
        self.configured["main"]["size"] = (w, h)

    def camera_configuration(self) -> dict:
        return self.configured

    def start(self) -> None:
        self.calls.append("start")

    def capture_request(self) -> FakeRequest:
        k = len(self.requests)
        self.requests.append(FakeRequest(self, k))
        self.t0_ns = time.monotonic_ns() - 20_000_000 - k * 33_333_000
        return self.requests[-1]

    def stop(self) -> None:
        self.calls.append("stop")

    def close(self) -> None:
        self.calls.append("close")


def picamera2_source(cam: FakePicamera2, request: CaptureRequest | None):
    from companion.drivers.camera.picamera2 import Picamera2Source

    return Picamera2Source(cam.num, request=request, factory=lambda num: cam)


def test_picamera2_configuration_pixels_and_time(monkeypatch) -> None:
    from companion.drivers.camera.picamera2 import sensor_stamp_us, video_configuration_args

    args = video_configuration_args(CaptureRequest(640, 480, 25.0, "", 3000.0))
    assert args == {
        "main": {"format": "RGB888", "size": (640, 480)},
        "controls": {"FrameDurationLimits": (40000, 40000), "ExposureTime": 3000},
        "queue": False,
    }
    cam = FakePicamera2()
    src = picamera2_source(cam, CaptureRequest(640, 480, 30.0))
    got = []
    for f in src.frames():
        got.append((f, time.monotonic_ns() // 1000))
        if len(got) == 8:
            src.close()
    assert cam.calls[:3] == ["create", "configure", "start"] and cam.calls[-2:] == ["stop", "close"]
    assert all(r.released for r in cam.requests)  # every buffer went back to libcamera
    assert src.stamps == "sensor timestamp"
    for f, arrived in got:
        np.testing.assert_array_equal(f.image_bgr, cam.scene_bgr)  # RGB888 bytes are BGR
        # mid-exposure: half the 4 ms exposure before the end stamped 20 ms before capture
        assert 0 <= arrived - f.time_us - (20_000 + 2_000) < 50_000
    # the stamp: the end of the first row's exposure less half of it, on our clock
    md = {"SensorTimestamp": 10_000_000_000, "ExposureTime": 4000}
    assert sensor_stamp_us(md, 10_010_000) == 9_998_000
    assert sensor_stamp_us(md, 9_998_000 - 1) is None  # after the frame arrived: not ours
    assert sensor_stamp_us(md, 11_000_000) is None  # 1 s old: not ours
    assert sensor_stamp_us({}, 11_000_000) is None


def test_picamera2_refuses_what_libcamera_changed() -> None:
    # an odd size, which Picamera2 rounds down to even numbers
    cam = FakePicamera2()
    cam.aligned = True
    src = picamera2_source(cam, CaptureRequest(101, 81, 30.0))
    with pytest.raises(CameraError, match=r"camera.width/camera.height: asked 101x81.*100x80"):
        next(iter(src.frames()))
    assert cam.calls[-2:] == ["stop", "close"] and "start" not in cam.calls
    # a sensor that cannot run at 90 Hz at this size: refused once the controls settled
    cam = FakePicamera2()
    cam.frame_duration_us = 16_667
    src = picamera2_source(cam, CaptureRequest(640, 480, 90.0))
    n = 0
    with pytest.raises(CameraError, match=r"camera.rate_hz: asked 90 Hz.*60 Hz"):
        for _ in src.frames():
            n += 1
    assert n == 5 and cam.calls[-2:] == ["stop", "close"]
    # a fixed exposure the sensor does not keep
    cam = FakePicamera2()
    cam.exposure_us = 9000
    src = picamera2_source(cam, CaptureRequest(640, 480, 30.0, "", 3000.0))
    with pytest.raises(CameraError, match=r"camera.exposure_us: asked 3000 us.*9000 us"):
        list(src.frames())


def test_picamera2_that_cannot_be_imported_is_a_config_error(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "picamera2", None)  # import picamera2 -> ImportError
    assert check_camera_url("picamera2:0") is None
    with pytest.raises(ConfigError, match=r"service\.camera_url: picamera2: .*libcamera"):
        open_camera("picamera2:0")
    with pytest.raises(ConfigError, match=r"service\.camera_url: expected picamera2:N"):
        open_camera("picamera2:front")
