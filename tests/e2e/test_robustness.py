"""Bad input against the service: 100,000 random and mutated MAVLink packets on its port, bad
distance readings, an autopilot serial port that vanishes and returns, a bad config."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import os
import socket
import struct
import subprocess
import sys
import threading
import time
import tty
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from peers import free_port, service_config
from pymavlink.dialects.v20 import common as mavlink

from companion.config import load_config
from companion.drivers.mavlink import MavlinkLink
from companion.drivers.status import read_status
from companion.offline import feed_step
from companion.pipeline import Pipeline
from companion.service.app import Service
from companion.sitl.world.scenario import Scenario
from companion.types import RangeSample


def _absurd_float(rng: np.random.Generator) -> float:
    return float(rng.choice([np.nan, np.inf, -np.inf, 1e38, -1e38, 0.0, rng.normal(0, 1e3)]))


def _random_message(mav: Any, rng: np.random.Generator) -> Any:
    """A well-formed message of a type the service handles (or ignores), absurd fields."""
    f = lambda: _absurd_float(rng)  # noqa: E731
    u = lambda bits: int(rng.integers(0, 2**bits))  # noqa: E731
    kind = int(rng.integers(0, 8))
    if kind == 0:
        return mav.heartbeat_encode(u(8), u(8), u(8), u(32), u(8))
    if kind == 1:
        return mav.timesync_encode(u(63) - 2**62, u(63) - 2**62)
    if kind == 2:
        return mav.attitude_encode(u(32), f(), f(), f(), f(), f(), f())
    if kind == 3:
        return mav.distance_sensor_encode(
            u(32), u(16), u(16), u(16), u(8), u(8), u(8), u(8), f(), f(), [f()] * 4, u(8)
        )
    if kind == 4:
        return mav.command_ack_encode(u(16), u(8), u(8), u(32) - 2**31, u(8), u(8))
    if kind == 5:
        return mav.command_long_encode(u(8), u(8), u(16), u(8), f(), f(), f(), f(), f(), f(), f())
    if kind == 6:
        return mav.param_value_encode(b"EKF2_EV_CTRL", f(), u(8), u(16), u(16))
    return mav.odometry_encode(
        u(32), u(8), u(8), f(), f(), f(), [f()] * 4, f(), f(), f(), f(), f(), f(),
        [f()] * 21, [f()] * 21, u(8), u(8), u(8) - 128,
    )  # fmt: skip


def fuzz_packets(n: int, seed: int) -> list[bytes]:
    """n datagrams: valid frames with absurd fields, flipped bytes, truncated frames, wrong
    length bytes, wrong CRCs, unknown message ids with a valid CRC, random bytes, and
    several frames glued into one datagram."""
    rng = np.random.default_rng(seed)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    out: list[bytes] = []
    for _ in range(n):
        mav.srcSystem = 1 if rng.uniform() < 0.8 else int(rng.integers(0, 256))
        buf = bytearray(_random_message(mav, rng).pack(mav))
        r = rng.uniform()
        if r < 0.25:
            pass  # well formed, absurd values
        elif r < 0.45:
            for i in rng.integers(0, len(buf), int(rng.integers(1, 4))):
                buf[i] ^= int(rng.integers(1, 256))
        elif r < 0.6:
            buf = buf[: int(rng.integers(1, len(buf)))]
        elif r < 0.7:
            buf[1] = int(rng.integers(0, 256))  # payload length
        elif r < 0.8:
            buf[-1] ^= 0x5A  # CRC
        elif r < 0.9:  # an id nobody knows, with a CRC computed without a CRC extra
            buf[7:10] = struct.pack("<I", int(rng.integers(20000, 2**24)))[:3]
            crc = mavlink.x25crc(bytes(buf[1:-2]))
            buf[-2:] = struct.pack("<H", crc.crc)
        elif r < 0.95:
            buf = bytearray(rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8))
        else:
            more = [_random_message(mav, rng).pack(mav) for _ in range(int(rng.integers(1, 4)))]
            buf += b"".join(more)
        out.append(bytes(buf))
    return out


@pytest.mark.timeout(300)
def test_100k_random_and_mutated_packets_on_its_port(tmp_path) -> None:
    packets = fuzz_packets(100_000, seed=11)
    port = free_port(socket.SOCK_DGRAM)
    # no camera (the camera loop keeps trying)
    cfg = service_config(tmp_path, mavlink_url=f"udpin:127.0.0.1:{port}")
    loop_errors: list[Any] = []

    async def main() -> tuple[dict, dict | None, bool, int]:
        asyncio.get_running_loop().set_exception_handler(lambda _l, ctx: loop_errors.append(ctx))
        async with Service(cfg) as service:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind(("127.0.0.1", 0))
            sent = 0
            for k in range(0, len(packets), 100):
                for p in packets[k : k + 100]:
                    sock.sendto(p, ("127.0.0.1", port))
                    sent += len(p)
                # paced by what the service has read (a loaded CI machine must not turn this
                # into a test of the kernel's socket buffer): wait for the burst, up to 2 s
                deadline = time.monotonic() + 2.0
                while service.link.stats.rx_bytes < sent and time.monotonic() < deadline:
                    await asyncio.sleep(0.001)
            await asyncio.sleep(0.5)
            status = await asyncio.to_thread(read_status, tmp_path / "status.sock")
            # still answering: a real TIMESYNC request after the storm
            mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
            sock.settimeout(0.1)
            answered = False
            sock.sendto(mav.timesync_encode(0, 424242).pack(mav), ("127.0.0.1", port))
            t0 = time.monotonic()  # still answering, however loaded the machine (not its speed)
            while time.monotonic() - t0 < 10 and not answered:
                with contextlib.suppress(TimeoutError):
                    data = await asyncio.to_thread(sock.recv, 4096)
                    answered = any(
                        m.get_type() == "TIMESYNC" and m.ts1 == 424242
                        for m in mav.parse_buffer(data) or []
                    )
            tasks_alive = [t.get_name() for t in service.tasks if not t.done()]
            tasks_dead = [t.get_name() for t in service.tasks if t.done()]
            queued_attitudes = list(service.session.attitudes)
            queued_ranges = list(service.session.ranges)
            summary = service.summary()
            sock.close()
        # whatever got through is plausible (the pipeline has no camera, so the queues hold
        # every accepted sample)
        for a in queued_attitudes:
            assert np.all(np.isfinite(a.quat_wxyz)) and np.all(np.abs(a.rates_rad_s) <= 50)
        assert all(r.is_valid for r in queued_ranges)
        return summary, status, (answered, tasks_alive, tasks_dead), sent

    summary, status, (answered, tasks_alive, tasks_dead), sent = asyncio.run(main())
    link = summary["link"]
    print(link, summary["ranges_rejected"], summary["attitudes_in"])
    assert answered, "no TIMESYNC answer within 10 s of the storm's end"
    assert tasks_alive and not tasks_dead, tasks_dead
    assert not loop_errors, loop_errors
    assert link["handler_errors"] == 0
    assert link["rx_bytes"] >= 0.99 * sent  # the storm was read, not lost in the socket
    assert link["rx_bad"] > 20_000 and link["rx_messages"] > 20_000
    assert status is not None and status["autopilot"]["rx_bad"] > 0
    assert status["autopilot"]["foreign_messages"] > 1000
    assert status["autopilot"]["attitudes_rejected"] > 100
    assert summary["ranges_rejected"] > 100


def test_bad_ranges_are_counted_and_do_not_move_the_scale() -> None:
    """Two pipelines fed the same flight; one also gets every kind of bad reading before each
    frame (NaN, infinite, negative, zero, below min, above max, invalid quality, unknown
    sensor, repeated and older time stamps). The scale must be identical to the bit."""
    cfg = load_config(
        overrides={"sitl": {"terrain": "hills", "trajectory": "lawnmower", "seconds": 8.0}}
    )
    clean, dirty = Pipeline(cfg), Pipeline(cfg)
    injected = 0
    for step in Scenario(cfg).steps():
        feed_step(clean, step)
        feed_step(dirty, step)
        a, b = clean.estimates[clean.method_name], dirty.estimates[dirty.method_name]
        assert (a is None) == (b is None)
        if a is not None and b is not None:
            assert a.scale == b.scale and a.sigma == b.sigma
        # after this frame's readings, before the next frame's: every kind of bad one
        t = step.frame.time_us
        for rf in cfg.rangefinders:
            lo, hi = rf.min_m, rf.max_m
            for d, q, sid, tt in (
                (np.nan, 100, rf.sensor_id, t),
                (np.inf, 100, rf.sensor_id, t),
                (-1.0, 100, rf.sensor_id, t),
                (0.0, 100, rf.sensor_id, t),
                (lo * 0.5, 100, rf.sensor_id, t),
                (hi * 2.0, 100, rf.sensor_id, t),
                (5.0, 1, rf.sensor_id, t),
                (5.0, 100, 200 + rf.sensor_id, t),
                (5.0, 100, rf.sensor_id, t - 10_000_000),  # older than the last one
            ):
                if tt < t and rf.sensor_id not in dirty.ranges.sensors():
                    continue  # nothing to be older than yet (the service refuses it by age)
                dirty.feed_range(RangeSample(tt, sid, d, lo, hi, q))
                injected += 1
        for r in step.ranges:  # the same readings again: refused
            if r.sample is not None:
                dirty.feed_range(r.sample)
                injected += 1
    assert clean.estimates[clean.method_name] is not None
    assert dirty.ranges.rejected - clean.ranges.rejected == injected


def test_the_autopilot_serial_port_vanishes_and_returns(tmp_path) -> None:
    """A USB serial adapter: its device path disappears (the pty closes, the symlink goes) and
    comes back as a new device under the same name; the link reopens it by itself."""
    dev = tmp_path / "ttyACM0"

    def plug() -> int:
        master, slave = os.openpty()
        tty.setraw(slave)
        if dev.is_symlink():
            dev.unlink()
        dev.symlink_to(os.ttyname(slave))
        os.close(slave)  # only the link holds the device open
        return master

    got: list[str] = []
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    hb = mav.heartbeat_encode(2, 12, 0, 0, 4).pack(mav)

    async def main() -> int:
        link = MavlinkLink(f"serial:{dev}:921600", 1, 197, lambda m, t: got.append(m.get_type()))
        master = plug()
        async with link:
            for _ in range(30):
                os.write(master, hb)
                await asyncio.sleep(0.05)
            before = len(got)
            os.close(master)  # unplugged
            dev.unlink()
            await asyncio.sleep(1.0)
            master = plug()  # back, a new device node behind the same name
            deadline = time.monotonic() + 10
            while len(got) < before + 10 and time.monotonic() < deadline:
                os.write(master, hb)
                await asyncio.sleep(0.05)
            os.close(master)
            assert before >= 20
            return link.stats.reconnects

    reconnects = asyncio.run(main())
    assert got.count("HEARTBEAT") >= 30 and reconnects >= 1


def test_a_bad_config_exits_2_naming_the_key_and_starts_nothing(tmp_path) -> None:
    sock = tmp_path / "status.sock"
    bad = tmp_path / "bad.toml"
    bad.write_text(f'[service]\nmavlink_url = "udp://nowhere"\nstatus_socket = "{sock}"\n')
    r = subprocess.run(
        [sys.executable, "-m", "companion.cli", "run", "--config", str(bad)],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert r.returncode == 2
    errors = [line for line in r.stderr.splitlines() if "service.mavlink_url" in line]
    assert len(errors) == 1 and "Traceback" not in r.stderr
    assert not sock.exists()


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


def test_reset_counter_after_a_kill_never_repeats_the_last_one_sent(tmp_path) -> None:
    """SIGKILL between two poses, then a restart: the first counter sent differs from the
    last one of the killed run (EKF2 would fuse the new origin as a jump otherwise)."""
    from companion.service.state import ResetCounter

    path = tmp_path / "state" / "reset_counter"
    script = (
        "import sys, time\n"
        "from pathlib import Path\n"
        "from companion.service.state import ResetCounter\n"
        f"rc = ResetCounter(Path({str(path)!r}))\n"
        "for k in range(int(sys.argv[1]) + 1):\n"
        "    sent = rc.wire(k)\n"
        "print(sent, flush=True)\n"
        "time.sleep(60)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    last_sent = []
    for resets in (21, 0, 0, 3):  # a run that re-initialised 21 times, then crashes at 0
        proc = subprocess.Popen(
            [sys.executable, "-c", script, str(resets)], stdout=subprocess.PIPE, env=env
        )
        assert proc.stdout is not None
        last_sent.append(int(proc.stdout.readline()))
        proc.kill()  # SIGKILL: no clean-up of any kind
        proc.wait()
    assert last_sent[0] == 21
    assert all(a != b for a, b in itertools.pairwise(last_sent)), last_sent
    assert ResetCounter(path).wire(0) == (last_sent[-1] + 1) % 256


def test_credentials_in_the_camera_url_are_never_shown(tmp_path, caplog) -> None:
    from peers import MOSQUITTO, Broker

    from companion.config import describe

    if not os.path.exists(MOSQUITTO):
        pytest.fail("mosquitto is not installed (make test installs it with apt-get)")
    broker = Broker(tmp_path)
    broker.start()
    url = f"rtsp://pilot:hunter2secret@127.0.0.1:{free_port()}/live"
    cfg = service_config(
        tmp_path, camera_url=url, mqtt={"enabled": True, "port": broker.port, "keepalive_s": 2}
    )
    import aiomqtt

    async def main() -> tuple[list[bytes], dict | None, dict]:
        got: list[bytes] = []

        async def listen() -> None:
            async with aiomqtt.Client("127.0.0.1", broker.port) as sub:
                await sub.subscribe("companion/#")
                async for msg in sub.messages:
                    got.append(bytes(msg.payload))  # type: ignore[arg-type]

        listener = asyncio.create_task(listen())
        async with Service(cfg) as service:
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not any(
                "cannot open" in w for w in service.stats.warnings
            ):
                await asyncio.sleep(0.1)
            await asyncio.sleep(1.5)  # a status or two on MQTT
            status = await asyncio.to_thread(read_status, tmp_path / "status.sock")
            summary = service.summary()
        listener.cancel()
        return got, status, summary

    try:
        with caplog.at_level("DEBUG"):
            got, status, summary = asyncio.run(main())
    finally:
        broker.stop()
    shown = "\n".join(
        [*(g.decode() for g in got), json.dumps(status), json.dumps(summary, default=str)]
        + [r.getMessage() for r in caplog.records]
        + describe(cfg)
    )
    assert "cannot open" in shown  # the driver's error quoting the URL did reach everything...
    assert "rtsp://pilot:***@127.0.0.1" in shown
    assert "hunter2secret" not in shown  # ...with the password masked everywhere
    assert len(got) >= 2


def test_redaction_knows_gstreamer_credentials_and_passwords_with_at() -> None:
    from companion.redact import redact_text, redact_url, url_secrets

    pipeline = (
        "gst:rtspsrc location=rtsp://pilot:p@ss@w0rd@cam.local/live user-id=gstuser "
        'user-pw="hunter2 secret" proxy-id=proxyman proxy-pw=pr0xy@pw ! decodebin ! '
        "videoconvert ! appsink srtsrc passphrase=longpassphrase"
    )
    shown = redact_url(pipeline)
    for secret in ("p@ss@w0rd", "ss@w0rd", "w0rd", "gstuser", "hunter2", "proxyman", "pr0xy"):
        assert secret not in shown, (secret, shown)
    assert "longpassphrase" not in shown
    assert "rtsp://pilot:***@cam.local/live" in shown and "user-pw=*** proxy-id=***" in shown
    assert "! decodebin ! videoconvert ! appsink" in shown  # the rest as it was
    secrets = url_secrets(pipeline)
    assert {"p@ss@w0rd", "hunter2 secret", "pr0xy@pw", "longpassphrase"} <= set(secrets)
    error = "camera gst: rtspsrc0: Unauthorized (hunter2 secret; p%40ss@w0rd)"
    assert "hunter2" not in redact_text(error, secrets)  # a secret quoted anywhere
    # a one-letter password: masked in its URL, never searched for in every warning
    text = "camera: pipeline stopped; reopening (appsink), autopilot happy"
    assert redact_text(text, url_secrets("rtsp://u:p@cam/x")) == text
    assert redact_url("rtsp://u:p@cam/x") == "rtsp://u:***@cam/x"
    assert redact_text(text, ["p", "pp", "ing"]) == text


def test_gst_credentials_are_never_shown(tmp_path, caplog) -> None:
    """A gst: camera with credentials in its location (a password with '@') and in
    souphttpsrc's properties, against a camera that is not there: GStreamer's error quotes
    the location; neither the log, the warnings, the status nor the summary shows them, and
    a warning with many 'p' is left as it is."""
    pytest.importorskip("gi")
    from companion.config import describe

    url = (
        f"gst:souphttpsrc location=http://pilot:p@ssw0rd@127.0.0.1:{free_port()}/cam.mjpg "
        "user-id=gstpilot user-pw=hunter2@s3kr1t proxy-id=proxyman proxy-pw=pr0xy@pw "
        "! multipartdemux ! jpegdec ! videoconvert ! appsink"
    )
    cfg = service_config(tmp_path, camera_url=url)
    plain = "camera: pipeline stopped; reopening (appsink), autopilot happy"

    async def main() -> tuple[dict, dict, list[str]]:
        async with Service(cfg) as service:
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not any(
                "reopening until" in w for w in service.stats.warnings
            ):
                await asyncio.sleep(0.1)
            service.runtime.warn(plain)
            status = await asyncio.to_thread(read_status, tmp_path / "status.sock")
            return status or {}, service.summary(), list(service.stats.warnings)

    with caplog.at_level("DEBUG"):
        status, summary, warnings = asyncio.run(main())
    shown = "\n".join(
        [json.dumps(status), json.dumps(summary, default=str), *warnings]
        + [r.getMessage() for r in caplog.records]
        + describe(cfg)
    )
    assert any("reopening until" in w for w in warnings), warnings
    assert "http://pilot:***@127.0.0.1" in shown and "user-pw=***" in shown
    for secret in ("ssw0rd", "gstpilot", "hunter2", "s3kr1t", "proxyman", "pr0xy"):
        assert secret not in shown, secret
    assert warnings[-1] == plain


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


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_poses_keep_flowing_through_a_5000_packet_per_second_flood(tmp_path) -> None:
    """A SITL flight in slow motion (16 s of flight in 32 s: the camera at 15 frames/s);
    from 6.5 to 15.5 s of flight (18 s) another process floods the service's port with 5,000
    datagrams/s (garbage, another system's frames, spoofed autopilot frames) from its own
    address. Before the fix the output stopped for ~45 s. Asserted at any load: the rate in
    the flood is >= 80 % of the rate before it (and >= half of what the pipeline could do, up
    to the camera's), no VO reset, and the flood was read (dropped by address, not lost in
    the socket buffer). The figure at 30 Hz on a quiet machine is in docs/BENCHMARKS.md.

    Slow motion, because the 80 % is about the service, not the machine: in real time on a
    2-core host that turns a frame over in 45 ms with the SITL autopilot in its process
    (2026-11-27), the pipeline had no time to spare before the flood, and the CPU the flood
    takes (its sender and the reading of 5,000 datagrams/s) came straight off the output
    rate (22.8 poses/s before, 14.5 in it). At half the camera rate the pipeline has the
    slack a vehicle's companion has; a service that stalls in the flood still fails."""
    from peers import sitl_flight

    from companion.sitl.stub.autopilot import SimAutopilot

    seconds, flood_s, scale = 16.0, (6.5, 15.5), 0.5
    cfg, opts = sitl_flight(tmp_path, seconds, small=True, time_scale=scale)  # 320x240
    port = int(cfg.service.mavlink_url.rsplit(":", 1)[1])

    async def fly() -> tuple[SimAutopilot, dict, dict, dict]:
        stub = SimAutopilot(cfg, opts)
        stub_task = asyncio.create_task(stub.run(tmp_path / "autopilot"))
        async with Service(cfg) as service:
            stub_task.add_done_callback(lambda _: service.stop())

            async def attack() -> dict:
                while stub.t_sim_of_mono(time.monotonic_ns()) < flood_s[0]:
                    await asyncio.sleep(0.05)
                proc = await asyncio.create_subprocess_exec(
                    sys.executable,
                    "-m",
                    "companion.sitl.stub.flood",
                    "--port",
                    str(port),
                    "--rate",
                    "5000",
                    "--seconds",
                    str((flood_s[1] - flood_s[0]) / scale),  # wall-clock
                    stdout=asyncio.subprocess.PIPE,
                    cwd=Path(__file__).resolve().parents[2],
                )
                out, _ = await proc.communicate()
                return dict(json.loads(out))

            attacker = asyncio.create_task(attack())
            await service.run()
            sent = await attacker
            summary = service.summary()
            link = vars(service.link.stats)
        report = await stub_task
        return stub, report, summary, {"flood": sent, "link": link}

    stub, report, summary, extra = asyncio.run(fly())
    rec = [r for r in stub.stats.received if r.kind == report["message"]]
    t_pose = np.array([r.t_sim_s for r in rec])

    def rate(lo: float, hi: float) -> float:
        return float(((t_pose >= lo) & (t_pose < hi)).sum() / (hi - lo))

    # poses per second of flight (twice those per wall-clock second)
    before, during = rate(3.0, flood_s[0]), rate(flood_s[0] + 0.5, flood_s[1] - 0.5)
    print(f"poses/s before {before:.1f}, in the flood {during:.1f}", extra, summary)
    assert extra["flood"]["rate"] >= 2500, extra["flood"]  # the attacker really flooded
    assert extra["link"]["rx_other_address"] >= 0.5 * extra["flood"]["sent"]
    # at least half of what the machine let the pipeline do, up to the camera's rate (a slow
    # host turned a frame over in 60-80 ms on 2026-11-27)
    keep_up = min(cfg.camera.rate_hz, summary["pipeline_capacity_hz"] / scale)
    assert during >= 0.8 * before and during >= 0.5 * keep_up, (before, during, keep_up)
    assert report["resets"] <= summary["vo_gaps"]
    assert summary["pipeline_errors"] == 0 and summary["link"]["handler_errors"] == 0


@pytest.fixture
def full_disk(tmp_path):
    """A 64 kB tmpfs filled to the last byte (mounting needs root: make test runs as root)."""
    mnt = tmp_path / "full"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)])
    if r.returncode != 0:
        pytest.skip("cannot mount a tmpfs to fill (needs root): the full-disk case is not run")
    try:
        (mnt / "report.json").write_text('{"old": true}\n')  # a report of an earlier run
        with open(mnt / "filler", "wb", buffering=0) as fh, contextlib.suppress(OSError):
            while True:
                fh.write(b"\0" * 4096)
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)])


def test_an_exit_report_on_a_full_disk_is_a_warning_and_leaves_no_torn_file(
    tmp_path, full_disk
) -> None:
    conf = tmp_path / "c.toml"
    conf.write_text(
        "[service]\n"
        f'mavlink_url = "udpin:127.0.0.1:{free_port(socket.SOCK_DGRAM)}"\n'
        f'camera_url = "sitl://127.0.0.1:{free_port()}"\n'
        f'status_socket = "{tmp_path / "s.sock"}"\n'
        f'state_dir = "{tmp_path / "state"}"\n'
    )
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "companion.cli",
            "run",
            "--config",
            str(conf),
            "--duration",
            "1",
            "--report",
            str(full_disk / "report.json"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert r.returncode == 0, r.stderr
    assert "exit report not written" in r.stderr and "Traceback" not in r.stderr
    assert (full_disk / "report.json").read_text() == '{"old": true}\n'  # untouched
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler", "report.json"]


def test_a_used_record_dir_on_a_full_disk_is_a_warning_never_an_exit(tmp_path, full_disk) -> None:
    """record.dir without {start}, holding an earlier run, on a full disk (a reboot of a
    drone whose recordings filled its card): the service runs, says why it does not
    record, and exits 0 at the end of its run (it used to exit 2 at each start: a restart
    loop with no output at all)."""
    rec = full_disk / "rec"
    rec.mkdir()
    (rec / "meta.toml").touch()  # an earlier run's (an inode: no byte of data needed)
    conf = tmp_path / "c.toml"
    conf.write_text(
        "[service]\n"
        f'mavlink_url = "udpin:127.0.0.1:{free_port(socket.SOCK_DGRAM)}"\n'
        f'camera_url = "sitl://127.0.0.1:{free_port()}"\n'
        f'status_socket = "{tmp_path / "s.sock"}"\n'
        f'state_dir = "{tmp_path / "state"}"\n'
        f'[record]\ndir = "{rec}"\n'
    )
    r = subprocess.run(
        [sys.executable, "-m", "companion.cli", "run", "--config", str(conf), "--duration", "2"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert r.returncode == 0, r.stderr
    said = [line for line in r.stderr.splitlines() if "recorder:" in line]
    assert said and "Traceback" not in r.stderr
    assert any("cannot record into" in line for line in said), said
    assert sorted(p.name for p in rec.iterdir()) == ["meta.toml"]  # the earlier run: as it was


def test_a_fifo_planted_at_a_state_or_key_file_is_refused_at_once(tmp_path) -> None:
    """The service reads its reset counter, signing timestamp and key at start-up; a FIFO put
    at one of those paths after `companion config` checked them (or by a hostile local user)
    blocked the read for good (an open for reading waits for a writer). Each is now refused
    at once: the reset counter takes its base from the clock, the timestamp and the key are a
    config error naming the key."""
    import threading

    from companion.drivers.signing import TimestampStore, load_key
    from companion.errors import ConfigError
    from companion.service.state import ResetCounter

    outcomes: dict[str, str] = {}

    def attempt(name: str, call: Any) -> threading.Thread:
        def run() -> None:
            try:
                call()
                outcomes[name] = "read"
            except ConfigError as e:
                outcomes[name] = f"refused: {e}"

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        return thread

    fifos = {name: tmp_path / name for name in ("reset_counter", "timestamp", "key")}
    for path in fifos.values():
        os.mkfifo(path, 0o600)
    threads = {
        "reset_counter": attempt("reset_counter", lambda: ResetCounter(fifos["reset_counter"])),
        "timestamp": attempt("timestamp", lambda: TimestampStore(fifos["timestamp"]).read()),
        "key": attempt("key", lambda: load_key(fifos["key"])),
    }
    try:
        for name, thread in threads.items():
            thread.join(5.0)
            assert not thread.is_alive(), f"{name}: blocked on the FIFO"
    finally:  # a blocked reader (the old code) is let go: a writer opens and closes
        for name, thread in threads.items():
            if thread.is_alive():
                with contextlib.suppress(OSError):
                    os.close(os.open(fifos[name], os.O_WRONLY | os.O_NONBLOCK))
    assert outcomes["reset_counter"] == "read", outcomes  # base from the clock, warned
    assert outcomes["timestamp"].startswith("refused") and "FIFO" in outcomes["timestamp"]
    assert outcomes["key"].startswith("refused") and "regular file" in outcomes["key"]
