"""Cameras that fail under the running service: a network camera (MJPEG over HTTP, a GStreamer
stream) that closes and comes back, a SITL camera that cannot serve, a camera that dies: each
said and shown, frames resume, the service keeps running."""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from typing import Any

import cv2
import numpy as np
import pytest
from peers import free_port, service_config

from companion.config import load_config
from companion.drivers.status import read_status
from companion.service.app import Service


class MjpegCamera:
    """A network camera: an MJPEG stream over HTTP (what IP cameras and mjpg-streamer serve),
    read by the service through cv2.VideoCapture (FFmpeg). ``stop()`` unplugs it (the stream
    and the server go), ``start()`` brings it back on the same port."""

    def __init__(self) -> None:
        self.port = free_port()
        self.server: Any = None
        self.running = threading.Event()

    def start(self) -> None:
        import http.server
        import socketserver

        cam = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=f")
                self.end_headers()
                rng = np.random.default_rng(0)
                while cam.running.is_set():
                    img = cv2.GaussianBlur(
                        rng.integers(0, 255, (480, 640, 3), dtype=np.uint8), (5, 5), 0
                    )
                    jpg = cv2.imencode(".jpg", img)[1].tobytes()
                    head = b"--f\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n"
                    try:
                        self.wfile.write(head % len(jpg) + jpg + b"\r\n")
                    except OSError:
                        return
                    time.sleep(1 / 15)

            def log_message(self, *args: Any) -> None:
                pass

        class Server(socketserver.ThreadingMixIn, http.server.HTTPServer):
            allow_reuse_address = True
            daemon_threads = True

        self.running.set()
        self.server = Server(("127.0.0.1", self.port), Handler)
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def stop(self) -> None:
        self.running.clear()
        self.server.shutdown()
        self.server.server_close()


async def wait_frames(service: Service, n: int, timeout_s: float) -> bool:
    """Whether the service's camera delivers ``n`` more frames within ``timeout_s``."""
    target = service.stats.frames_in + n
    end = time.monotonic() + timeout_s
    while service.stats.frames_in < target and time.monotonic() < end:
        await asyncio.sleep(0.05)
    return service.stats.frames_in >= target


def test_a_network_camera_disappears_and_returns(tmp_path) -> None:
    cam = MjpegCamera()
    cam.start()
    cfg = service_config(tmp_path, camera_url=f"http://127.0.0.1:{cam.port}/stream.mjpg")

    async def main() -> dict[str, Any]:
        async with Service(cfg) as service:
            assert await wait_frames(service, 30, 10.0)
            t_first = service.intake.frame_times_ns[-1] // 1000
            cam.stop()  # unplugged
            await asyncio.sleep(0.5)
            frames_gone = service.stats.frames_in
            await asyncio.sleep(2.5)
            down = service.status()
            assert service.stats.frames_in == frames_gone  # nothing while it is away
            cam.start()  # back
            back = await wait_frames(service, 30, 10.0)
            return {
                "back": back,
                "down": down,
                "warnings": list(service.stats.warnings),
                "t_first": t_first,
            }

    try:
        r = asyncio.run(main())
    finally:
        cam.stop()
    assert r["back"], "no frames within 10 s of the camera's return"
    assert r["down"]["camera"]["last_frame_age_s"] > 2.0
    reports = [w for w in r["warnings"] if "reopening" in w]
    assert len(reports) == 1  # once per outage, not per attempt
    silent = [w for w in r["warnings"] if "camera: no frames for" in w]
    assert len(silent) == 1 and "frames again" in r["warnings"][-1]  # said, then cleared
    assert abs(r["t_first"] - time.monotonic_ns() // 1000) < 60e6  # our monotonic clock


def test_a_gst_network_camera_that_closes_its_stream_is_reopened(tmp_path) -> None:
    """An MJPEG IP camera through GStreamer (souphttpsrc: not a live source) closes its
    stream: the service does not take it for the end of a recording and stop (the unit is
    restarted on failure only: the output would be gone until somebody acts); it reopens the
    camera with backoff, and frames resume when the camera is back."""
    pytest.importorskip("gi")
    cam = MjpegCamera()
    cam.start()
    url = (
        f"gst:souphttpsrc location=http://127.0.0.1:{cam.port}/stream.mjpg ! multipartdemux "
        "! jpegdec ! videoconvert ! appsink"
    )
    cfg = service_config(tmp_path, camera_url=url)

    async def main() -> dict[str, Any]:
        async with Service(cfg) as service:
            first = await wait_frames(service, 20, 20.0)
            cam.stop()  # the camera closes the stream (a reboot, a network drop)
            await asyncio.sleep(2.0)
            stopped = service.stopped
            cam.start()
            back = await wait_frames(service, 20, 20.0)
            return {
                "first": first,
                "stopped": stopped,
                "back": back,
                "finite": service.camera.finite,
                "warnings": list(service.stats.warnings),
            }

    try:
        r = asyncio.run(main())
    finally:
        cam.stop()
    assert r["first"], "no frames from the camera at the start"
    assert not r["stopped"] and not r["finite"], r["warnings"]
    assert not any("recording ended" in w for w in r["warnings"]), r["warnings"]
    assert sum("reopening" in w for w in r["warnings"]) == 1, r["warnings"]
    assert r["back"], "no frames within 20 s of the camera's return"


def test_the_sitl_autopilot_stops_when_its_camera_cannot_serve() -> None:
    """The camera port taken (a leftover run): the SITL must fail, not fly while somebody
    else's stream is measured as its own."""
    from companion.errors import SitlError
    from companion.sitl.stub.autopilot import SimAutopilot
    from companion.sitl.stub.options import AutopilotOptions

    with socket.create_server(("127.0.0.1", 0)) as blocker:
        opts = AutopilotOptions(
            listen_port=free_port(socket.SOCK_DGRAM),
            companion_port=free_port(socket.SOCK_DGRAM),
            camera_port=blocker.getsockname()[1],
            gcs_listen_port=0,
        )
        stub = SimAutopilot(load_config("config/sitl.toml", {"sitl": {"seconds": 5.0}}), opts)
        with pytest.raises(SitlError, match="camera process failed"):
            asyncio.run(asyncio.wait_for(stub.run(), 60))


# ------------------------------------------------------------------ issue 16, round 2


def test_a_camera_that_dies_is_said_and_shown(tmp_path) -> None:
    """Frames, then the camera process is gone: a warning within seconds, fps 0 and the
    problem in the status; a serial autopilot port and a TFmini port that do not exist are
    said too (they used to be retried in silence)."""
    from companion.drivers.camera import encode_frame
    from companion.types import CameraFrame

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    port = srv.getsockname()[1]

    def camera() -> None:
        conn, _ = srv.accept()
        rng = np.random.default_rng(0)
        for seq in range(60):  # 2 s at 30 fps, then killed (new pixels: not a frozen camera)
            img = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)  # the intrinsics' size
            conn.sendall(encode_frame(CameraFrame(time.monotonic_ns() // 1000, seq, img)))
            time.sleep(1 / 30)
        conn.close()
        srv.close()

    threading.Thread(target=camera, daemon=True).start()
    cfg = load_config(
        None,
        {
            "service": {
                "mavlink_url": f"serial:{tmp_path / 'ttyNOPE'}:921600",
                "camera_url": f"sitl://127.0.0.1:{port}",
                "status_socket": str(tmp_path / "status.sock"),
                "state_dir": str(tmp_path / "state"),
            },
            "rangefinders": [{"sensor_id": 9, "serial": str(tmp_path / "ttyTF")}],
        },
    )

    async def main() -> tuple[dict | None, dict | None, list[str]]:
        async with Service(cfg) as service:
            while service.stats.frames_in < 30:
                await asyncio.sleep(0.05)
            alive = await asyncio.to_thread(read_status, tmp_path / "status.sock")
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and not (
                service.intake.silent
                and service.stats.warnings
                and any("autopilot: no heartbeat" in w for w in service.stats.warnings)
            ):
                await asyncio.sleep(0.1)
            dead = await asyncio.to_thread(read_status, tmp_path / "status.sock")
            return alive, dead, list(service.stats.warnings)

    alive, dead, warnings = asyncio.run(main())
    assert alive is not None and dead is not None
    assert alive["camera"]["fps"] > 5 and alive["camera"]["problem"] is None
    assert dead["camera"]["fps"] == 0.0 and dead["camera"]["problem"] == "no frames"
    assert dead["vo"]["state"].startswith("STALLED")
    text = "\n".join(warnings)
    assert "camera: no frames for" in text
    assert "autopilot: no heartbeat" in text and "ttyNOPE" in text
    assert "rangefinder 9: cannot open" in text and "ttyTF" in text
