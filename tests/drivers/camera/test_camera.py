"""Camera sources (drivers/camera/): each path that can exist on this machine is run for real
(a video file, an image folder, the SITL stream) and refuses frames of another size than the
intrinsics; the V4L2 read-back, which needs hardware, is tested at its seam with the property
values OpenCV returns. GStreamer: test_camera_gst.py; Picamera2: test_camera_picamera2.py."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from peers.cameras import camera

from companion.config import load_config
from companion.drivers.camera import (
    CameraError,
    CaptureRequest,
    VideoCaptureSource,
    check_camera_url,
    encode_frame,
    fourcc_code,
    fourcc_text,
    open_camera,
    uvc_readback_problems,
)
from companion.types import CameraFrame

ROOT = Path(__file__).resolve().parents[3]


def test_only_a_video_file_is_a_finite_video_capture(tmp_path) -> None:
    clip = tmp_path / "clip.avi"
    clip.write_bytes(b"")
    for spec, finite in (
        (str(clip), True),
        (f"file://{clip}", True),
        ("http://127.0.0.1:8080/video.mjpg", False),
        ("rtsp://cam/live", False),
        ("/dev/video0", False),
        (0, False),
    ):
        assert VideoCaptureSource(spec).finite == finite, spec


# --------------------------------------------------------------------------- files, folders


def test_a_video_file_is_read_to_its_end_and_checked_against_the_intrinsics(tmp_path) -> None:
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (160, 120))
    assert writer.isOpened()
    rng = np.random.default_rng(2)
    for k in range(10):
        img = cv2.GaussianBlur(rng.integers(0, 256, (120, 160, 3), dtype=np.uint8), (5, 5), 0)
        cv2.putText(img, str(k), (40, 80), cv2.FONT_HERSHEY_SIMPLEX, 2, (255, 255, 255), 3)
        writer.write(img)
    writer.release()
    assert check_camera_url(str(path)) is None
    src = open_camera(str(path), camera=camera(160, 120))
    assert isinstance(src, VideoCaptureSource) and src.finite and not src.device
    frames = list(src.frames())
    assert len(frames) == 10
    assert all(f.image_bgr.shape == (120, 160, 3) for f in frames)
    assert np.all(np.diff([f.time_us for f in frames]) > 0)
    with pytest.raises(CameraError, match=r"160x120 frames.*640x480"):
        list(open_camera(str(path), camera=camera(640, 480)).frames())


def test_an_image_folder_replays_and_is_checked_against_the_intrinsics(tmp_path) -> None:
    from companion.drivers.dataset import DatasetWriter

    cfg = load_config(None, {"camera": {"width": 96, "height": 64}})
    writer = DatasetWriter(tmp_path / "ds", cfg)
    rng = np.random.default_rng(3)
    sent = []
    for k in range(6):
        img = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
        frame = CameraFrame(1_000_000 + k * 33_333, k, img)
        writer.write_frame(frame, writer.encode(img), [], [])
        sent.append(frame)
    writer.close()
    src = open_camera(f"folder:{tmp_path / 'ds'}?fast", camera=cfg.camera)
    got = list(src.frames())
    assert src.finite and [f.seq for f in got] == list(range(6))
    for a, b in zip(sent, got, strict=True):
        np.testing.assert_array_equal(a.image_bgr, b.image_bgr)  # PNG: lossless
    with pytest.raises(CameraError, match=r"96x64 frames.*640x480"):
        list(open_camera(f"folder:{tmp_path / 'ds'}?fast", camera=camera()).frames())


def test_the_sitl_stream_is_checked_against_the_intrinsics() -> None:
    """The SITL stream delivers what it was sent; a size the intrinsics do not have is
    refused at the first frame (a simulator configured apart from the service)."""

    def serve(frames: list[CameraFrame]) -> tuple[socket.socket, threading.Thread]:
        server = socket.create_server(("127.0.0.1", 0))

        def run() -> None:
            conn, _ = server.accept()
            # a refused stream is closed at its first frame: the rest may meet a closed socket
            # (BrokenPipe / reset on a loaded machine, where the refusal comes before them)
            with conn, contextlib.suppress(BrokenPipeError, ConnectionResetError):
                for f in frames:
                    conn.sendall(encode_frame(f))
                time.sleep(0.5)

        t = threading.Thread(target=run, daemon=True)
        t.start()
        return server, t

    rng = np.random.default_rng(4)
    sent = [
        CameraFrame(10_000 + k, k, rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
        for k in range(3)
    ]
    server, t = serve(sent)
    src = open_camera(f"sitl://127.0.0.1:{server.getsockname()[1]}", camera=camera(64, 48))
    got = []
    for f in src.frames():
        got.append(f)
        if len(got) == 3:
            src.close()
    t.join()
    server.close()
    assert [(f.time_us, f.seq) for f in got] == [(f.time_us, f.seq) for f in sent]
    server, t = serve(sent)
    src = open_camera(f"sitl://127.0.0.1:{server.getsockname()[1]}", camera=camera(640, 480))
    with pytest.raises(CameraError, match=r"64x48 frames.*640x480") as e:
        next(iter(src.frames()))
    assert e.value.brief == "64x48, calibrated 640x480" == src.last_error_brief
    src.close()
    t.join()
    server.close()


# --------------------------------------------------------------------------- V4L2 (UVC)
# No /dev/video device exists here: the read-back is tested with the property values OpenCV's
# V4L2 backend returns after the settings (CAP_PROP_* as floats), and the source with a
# stand-in for cv2.VideoCapture of a device that set something else.


def props(**values: float):
    """cv2.VideoCapture.get of a device that reports these values."""
    ids = {
        "fourcc": cv2.CAP_PROP_FOURCC,
        "width": cv2.CAP_PROP_FRAME_WIDTH,
        "height": cv2.CAP_PROP_FRAME_HEIGHT,
        "fps": cv2.CAP_PROP_FPS,
        "auto": cv2.CAP_PROP_AUTO_EXPOSURE,
        "exposure": cv2.CAP_PROP_EXPOSURE,
    }
    table = {ids[k]: float(v) for k, v in values.items()}
    return lambda prop: table.get(prop, 0.0)


def test_fourcc_round_trip() -> None:
    for text in ("MJPG", "YUYV", "H264", "GREY"):
        assert fourcc_code(text) == cv2.VideoWriter_fourcc(*text)
        assert fourcc_text(float(fourcc_code(text))) == text
    assert fourcc_text(0.0) == "" and fourcc_text(float("nan")) == ""


def test_uvc_read_back_names_each_setting_the_driver_changed() -> None:
    req = CaptureRequest(640, 480, 30.0, "MJPG", 5000.0)
    mjpg = float(fourcc_code("MJPG"))
    same = props(fourcc=mjpg, width=640, height=480, fps=30.0003, auto=1, exposure=50)
    assert uvc_readback_problems(req, same) == []
    # the driver's choice: 1280x720 YUYV at 10 Hz, automatic exposure
    other = props(fourcc=fourcc_code("YUYV"), width=1280, height=720, fps=10, auto=3, exposure=50)
    problems = uvc_readback_problems(req, other)
    assert len(problems) == 4
    assert problems[0].startswith("camera.fourcc:") and "'YUYV'" in problems[0]
    assert problems[1].startswith("camera.width/camera.height:") and "1280x720" in problems[1]
    assert problems[2].startswith("camera.rate_hz:") and "10 Hz" in problems[2]
    assert problems[3].startswith("camera.exposure_us:") and "automatic" in problems[3]
    # manual exposure, but another time than asked (one V4L2 unit = 100 us is tolerated)
    off = props(fourcc=mjpg, width=640, height=480, fps=30, auto=1, exposure=80)
    assert uvc_readback_problems(req, off) == [
        "camera.exposure_us: asked 5000 us, the driver set 8000 us"
    ]
    near = props(fourcc=mjpg, width=640, height=480, fps=30, auto=1, exposure=51)
    assert uvc_readback_problems(req, near) == []
    # a driver that cannot report its rate (0) is not held against it; no fourcc, no
    # exposure asked: only the size and rate are compared
    plain = CaptureRequest(640, 480, 30.0)
    assert uvc_readback_problems(plain, props(width=640, height=480, fps=0)) == []


class _DeviceCapture:
    """Stands in for cv2.VideoCapture(device, CAP_V4L2) (no camera here): takes every set()
    and reports ``reported`` back, as a driver that picks its own mode does."""

    def __init__(self, reported, api: int) -> None:
        self.reported, self.api = reported, api
        self.sets: list[tuple[int, float]] = []
        self.released = False

    def set(self, prop: int, value: float) -> bool:
        self.sets.append((prop, value))
        return True

    def isOpened(self) -> bool:
        return True

    def get(self, prop: int) -> float:
        return self.reported(prop)

    def release(self) -> None:
        self.released = True


def test_a_v4l2_device_that_sets_another_mode_is_refused_before_any_frame(monkeypatch) -> None:
    made: list[_DeviceCapture] = []

    def capture(spec, api=None):
        assert spec == "/dev/video0" and api == cv2.CAP_V4L2
        made.append(_DeviceCapture(props(width=1280, height=720, fps=30), api))
        return made[-1]

    monkeypatch.setattr(cv2, "VideoCapture", capture)
    src = open_camera("/dev/video0", camera=camera(640, 480, fourcc="MJPG"))
    assert isinstance(src, VideoCaptureSource) and src.device
    with pytest.raises(CameraError) as e:
        next(iter(src.frames()))
    assert "camera.width/camera.height: asked 640x480, the driver set 1280x720" in str(e.value)
    assert "camera.fourcc" in str(e.value)
    cap = made[0]
    assert cap.released
    order = [p for p, _ in cap.sets if p != cv2.CAP_PROP_READ_TIMEOUT_MSEC]
    assert order == [
        cv2.CAP_PROP_FOURCC,
        cv2.CAP_PROP_FRAME_WIDTH,
        cv2.CAP_PROP_FRAME_HEIGHT,
        cv2.CAP_PROP_FPS,
    ]  # the pixel format first: it decides which sizes and rates exist


def test_venv_system_modules_links_only_what_fits_this_python(tmp_path) -> None:
    """systemd/venv-system-modules.sh: a pure-Python module is linked and importable; one
    built for another Python version is skipped with the reason; nothing else of the system's
    dist-packages becomes visible."""
    dist = tmp_path / "dist-packages"
    (dist / "purepkg").mkdir(parents=True)
    (dist / "purepkg" / "__init__.py").write_text("VALUE = 42\n")
    (dist / "oldabi").mkdir()
    (dist / "oldabi" / "__init__.py").write_text("")
    (dist / "oldabi" / "_c.cpython-39-x86_64-linux-gnu.so").write_bytes(b"")
    (dist / "other").mkdir()
    (dist / "other" / "__init__.py").write_text("")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    script = ROOT / "systemd" / "venv-system-modules.sh"
    env = {**os.environ, "SYSTEM_DIST_PACKAGES": str(dist)}
    r = subprocess.run(
        ["bash", str(script), str(venv), "purepkg", "oldabi", "missing"],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "purepkg: importable" in r.stdout
    assert "oldabi:" in r.stdout and "another Python" in r.stdout
    assert "missing: not in" in r.stdout
    py = str(venv / "bin" / "python")
    out = subprocess.run(
        [py, "-c", "import purepkg; print(purepkg.VALUE)"], capture_output=True, text=True
    )
    assert out.stdout.strip() == "42"
    for name in ("oldabi", "other"):
        out = subprocess.run([py, "-c", f"import {name}"], capture_output=True, text=True)
        assert out.returncode != 0, name
