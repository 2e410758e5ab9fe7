"""The SITL autopilot's camera: a child process that renders the flight (ahead of time, or all
of it before the flight) and serves frame k on a TCP loopback stream (format in
:mod:`companion.drivers.camera`) at its exposure time plus the readout; a frame not ready or not
taken in time is dropped and counted, as a camera would drop it. Camera faults (frozen, black,
saturated, unplugged: :mod:`companion.sitl.stub.faults`) are applied here.

Times: monotonic [ns] on the wall clock; flight time [s] for the fault windows
(``time_scale`` flight seconds per wall-clock second).
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from companion.config import Config, from_dict
from companion.drivers.camera import encode_frame
from companion.sitl.stub.faults import CAMERA_KINDS, Fault, active
from companion.types import CameraFrame


def camera_process(
    cfg_dict: dict[str, Any],
    port: int,
    flight_start_ns: int,
    readout_ms: float,
    counters: Any,
    prerender: bool = False,
    ready: Any = None,
    faults: tuple[Fault, ...] = (),
    loop: tuple[int, int] = (0, 0),
    time_scale: float = 1.0,
    end_s: float = 0.0,
) -> None:
    """Child process: render the flight (ahead of time, or all of it before the flight with
    ``prerender``) and stream each frame at exposure + readout; camera faults applied.
    ``time_scale``: flight seconds per wall-clock second (frame k is exposed k / (rate x
    time_scale) wall-clock seconds after the flight start).
    ``loop = (first, n)``, n > 0: frame k >= first + n shows frame first + (k - first) % n
    (only valid for a flight that is periodic there: it renders first + n frames at most).
    ``end_s`` > 0: the flight ends then [s of flight time], before the scenario's end (the
    frames after it are neither rendered nor sent)."""
    from companion.sitl.world.scenario import Scenario

    cfg = from_dict(Config, cfg_dict)
    scenario = Scenario(cfg)
    scenario.step(0)  # compile the kernels before the flight
    first, n_loop = loop
    n_frames = flight_frames(scenario.n_frames, cfg.camera.rate_hz, end_s)

    images: list[Any] = []
    if prerender:
        n_distinct = min(n_frames, first + n_loop) if n_loop > 0 else n_frames
        images = prerender_frames(scenario, n_distinct)
    if ready is not None:
        ready.set()
    while counters[2] == 0:  # the parent sets the flight start once everybody is ready
        time.sleep(0.01)
    flight_start_ns = int(counters[2])

    def render(seq: int) -> Any:
        """Frame seq's image (a looped flight shows frames first .. first + n - 1 again)."""
        src = seq if n_loop <= 0 or seq < first + n_loop else first + (seq - first) % n_loop
        return images[src] if prerender else scenario.step(src).frame.image_bgr

    _stream_frames(
        n_frames,
        cfg.camera.rate_hz,
        render,
        port,
        flight_start_ns,
        readout_ms,
        counters,
        faults,
        time_scale,
    )


def flight_frames(n_frames: int, rate_hz: float, end_s: float) -> int:
    """How many frames a flight sends: the scenario's ``n_frames`` (frame k exposed at
    k / ``rate_hz`` s), or, when it ends at ``end_s`` > 0 [s of flight time] before the
    scenario's end, the frames exposed up to that time (the one at ``end_s`` included)."""
    if end_s <= 0:
        return n_frames
    return min(n_frames, int(end_s * rate_hz + 1e-9) + 1)


def prerender_frames(scenario: Any, n_frames: int, workers: int = 0) -> list[Any]:
    """Images (BGR uint8, H x W x 3) of frames 0 .. n_frames - 1 of ``scenario`` (a
    :class:`companion.sitl.world.scenario.Scenario` that has rendered once: kernels compiled,
    textures built), rendered by ``workers`` threads (0: one per core this process may use, at
    most 4).

    The render kernels run without the GIL and frame k's image depends on k alone (its noise
    is seeded by k, the laser marks by its time), so each thread renders every workers-th
    frame with a Scenario of its own (its own buffers) over the same world, and the images are
    bit for bit those one thread renders (tests/sitl/world/test_render.py)."""
    from companion.sitl.world.scenario import Scenario, render_threads

    if workers <= 0:
        workers = render_threads()
    workers = min(workers, max(1, n_frames))
    images: list[Any] = [None] * n_frames
    scenarios = [scenario] + [
        Scenario(scenario.cfg, world=scenario.world) for _ in range(workers - 1)
    ]

    def render_every(i: int) -> None:
        for k in range(i, n_frames, workers):
            images[k] = scenarios[i].step(k).frame.image_bgr

    if workers == 1:
        render_every(0)
        return images
    with ThreadPoolExecutor(workers, thread_name_prefix="prerender") as pool:
        for done in [pool.submit(render_every, i) for i in range(workers)]:
            done.result()
    return images


def _stream_frames(
    n_frames: int,
    rate_hz: float,
    render: Callable[[int], Any],
    port: int,
    flight_start_ns: int,
    readout_ms: float,
    counters: Any,
    faults: tuple[Fault, ...],
    time_scale: float = 1.0,
) -> None:
    """Serve frame seq at its exposure + readout to one client; a frame not ready or not
    taken in time is dropped (counters[1]), a sent one counted (counters[0]). Frames are
    ``1 / (rate_hz x time_scale)`` wall-clock seconds apart (the fault windows: flight time)."""
    link = _CameraLink(port)
    period_ns = int(1e9 / (rate_hz * time_scale))
    last_good: Any = None
    for seq in range(n_frames):
        expose_ns = flight_start_ns + seq * period_ns
        release_ns = expose_ns + int(readout_ms * 1e6)
        now_faults = active(faults, seq / rate_hz) & CAMERA_KINDS
        if "camera_unplug" in now_faults:  # gone from the bus: no stream, no connections
            link.close()
            counters[1] += 1
            continue
        server = link.listen()
        if time.monotonic_ns() > release_ns + period_ns:
            counters[1] += 1  # behind: this frame is lost, as a camera would lose it
            continue
        image, last_good = _faulted(render(seq), now_faults, last_good)
        payload = encode_frame(CameraFrame(expose_ns // 1000, seq, image))
        link.accept(server, release_ns + period_ns)
        wait = (release_ns - time.monotonic_ns()) * 1e-9
        if wait > 0:
            time.sleep(wait)
        if link.client is None:
            counters[1] += 1
            continue
        if link.send(payload):
            counters[0] += 1
    link.close()


def _faulted(image: Any, now_faults: set[str], last_good: Any) -> tuple[Any, Any]:
    """The image a faulty camera shows (frozen, black or saturated), and the last good one."""
    if "camera_freeze" in now_faults and last_good is not None:
        return last_good, last_good
    if "camera_black" in now_faults:
        return np.zeros_like(image), last_good
    if "camera_saturated" in now_faults:
        return np.full_like(image, 255), last_good
    return image, image


class _CameraLink:
    """The camera's TCP end on 127.0.0.1: a listening socket and at most one client, both
    closed while the camera is unplugged."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.server: socket.socket | None = None
        self.client: socket.socket | None = None
        self.listen()

    def listen(self) -> socket.socket:
        """The listening socket, opened again after an unplug."""
        if self.server is None:
            self.server = socket.create_server(("127.0.0.1", self.port), reuse_port=False)
            self.server.settimeout(0.2)
        return self.server

    def accept(self, server: socket.socket, deadline_ns: int) -> None:
        """Wait for a client, if there is none, until ``deadline_ns`` (monotonic)."""
        while self.client is None:
            try:
                self.client, _ = server.accept()
                self.client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except TimeoutError:
                if time.monotonic_ns() > deadline_ns:
                    break

    def send(self, payload: bytes) -> bool:
        """Send to the client; on an error it is closed (a new one may connect)."""
        assert self.client is not None
        try:
            self.client.sendall(payload)
            return True
        except OSError:
            self.client.close()
            self.client = None
            return False

    def close(self) -> None:
        """Close the client, then the listening socket."""
        for sock in (self.client, self.server):
            if sock is not None:
                sock.close()
        self.client = self.server = None
