"""STATUSTEXT on the wire (issue 20): the service against a pymavlink autopilot, the SITL stub
with a camera fault (forwarded to its ground-station port), and the real PX4 SITL forwarding
our texts from its onboard link to its ground-station link."""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import socket
import time
from typing import Any

import pytest
from peers import free_port, service_config, sitl_flight
from peers.mavlink_peers import join_chunks
from pymavlink.dialects.v20 import common as mavlink

from companion.config import load_config
from companion.service.app import Service
from companion.service.statustext import Event, Severity

PREFIX = "CMP: "


def texts(events: list[Event]) -> list[tuple[str, Severity, str]]:
    return [(e.key, e.severity, e.text) for e in events]


class Autopilot:
    """A pymavlink autopilot on its own UDP port (PX4-like HEARTBEAT, armed or not) that
    collects what the service sends it."""

    def __init__(self, port: int, armed: bool) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.rx = mavlink.MAVLink(None)
        self.rx.robust_parsing = True
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.port = port
        self.armed = armed
        self.got: list[Any] = []

    def heartbeat(self) -> None:
        mode = mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0
        beat = self.mav.heartbeat_encode(2, mavlink.MAV_AUTOPILOT_PX4, mode, 0, 4)
        self.sock.sendto(beat.pack(self.mav), ("127.0.0.1", self.port))

    def statustexts(self) -> list[tuple[int, str]]:
        while True:
            try:
                data = self.sock.recv(65536)
            except BlockingIOError:
                break
            self.got += [
                m for m in self.rx.parse_buffer(data) or [] if m.get_type() == "STATUSTEXT"
            ]
        return join_chunks(self.got)


@pytest.mark.timeout(60)
def test_the_service_tells_a_pymavlink_autopilot_config_camera_link_and_stop(tmp_path) -> None:
    """Against a real UDP peer: the start and a long config warning (chunked), the camera that
    never delivers (CRITICAL: the autopilot says armed), the autopilot silent for 4.5 s and
    back, and the stop, each with its severity and prefix."""
    port = free_port(socket.SOCK_DGRAM)
    cfg = service_config(tmp_path, mavlink_url=f"udpin:127.0.0.1:{port}", camera_url="/dev/video99")

    async def main() -> tuple[list[tuple[int, str]], dict[str, Any]]:
        autopilot = Autopilot(port, armed=True)
        async with Service(cfg) as service:

            async def beat(seconds: float) -> None:
                end = time.monotonic() + seconds
                while time.monotonic() < end:
                    autopilot.heartbeat()
                    await asyncio.sleep(0.5)

            await beat(3.0)
            await asyncio.sleep(4.5)  # silent: "no autopilot heartbeat" (sent: UDP is one-way)
            await beat(3.5)
        await asyncio.sleep(0.2)
        return autopilot.statustexts(), service.summary()

    got, summary = asyncio.run(main())
    print(got)
    assert all(text.startswith(PREFIX) for _, text in got), got
    seen = {text.removeprefix(PREFIX).split(" [")[0]: sev for sev, text in got}
    assert seen["started v0.1.0, VPE"] == Severity.NOTICE, got
    warning = "config: service.camera_url: /dev/video99 does not exist (yet): waiting for it"
    assert seen[warning] == Severity.WARNING, got  # 81 characters: two chunks, joined
    assert seen["camera lost: no frames"] == Severity.CRITICAL, got  # armed: in flight
    assert seen["no autopilot heartbeat for 3 s"] == Severity.WARNING, got
    back = [t for t in seen if t.startswith("autopilot link back after")]
    assert back and seen[back[0]] == Severity.NOTICE, got
    assert float(back[0].split()[-2]) >= 4.0, got
    assert got[-1] == (Severity.WARNING, "CMP: stopping"), got  # armed: a warning
    assert summary["statustext"]["messages"] >= len(got)


@pytest.mark.timeout(120)
def test_a_service_that_fails_says_why_it_stopped(tmp_path, monkeypatch) -> None:
    """A pipeline that raises on every frame ends the service after 30 frames; its last word,
    sent on the way out, names the loop and the exception (CRITICAL: armed)."""
    from companion.pipeline import Pipeline
    from companion.sitl.world.dataset import record

    ds = record(
        load_config(overrides={"sitl": {"terrain": "flat", "seconds": 2.0}}),
        tmp_path / "ds",
        image_format="png",
        progress=False,
    )

    def broken(self: Pipeline, frame: Any, checked: bool = False) -> None:
        raise RuntimeError("a bug")

    monkeypatch.setattr(Pipeline, "feed_frame", broken)
    port = free_port(socket.SOCK_DGRAM)
    # this autopilot sends no ATTITUDE: the VO would hold the 2 s of frames for it
    cfg = service_config(
        tmp_path,
        mavlink_url=f"udpin:127.0.0.1:{port}",
        camera_url=f"folder:{ds}",
        attitude_wait_s=0.0,
    )

    async def main() -> list[tuple[int, str]]:
        autopilot = Autopilot(port, armed=True)
        autopilot.heartbeat()
        with pytest.raises(ExceptionGroup) as failed:
            async with Service(cfg) as service:
                while not service.stopped:
                    autopilot.heartbeat()
                    await asyncio.sleep(0.3)
        assert failed.group_contains(RuntimeError, match="a bug")
        await asyncio.sleep(0.2)
        return autopilot.statustexts()

    got = asyncio.run(main())
    print(got)
    assert got[-1] == (Severity.CRITICAL, "CMP: stopped on pipeline error (RuntimeError)"), got


# ---------------------------------------------------------------------------------------------
# the SITL stub: a camera fault in an armed flight
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_sitl_stub_receives_and_forwards_camera_and_vo_statustexts(tmp_path) -> None:
    """The SITL flight (hills), the stub armed, the camera stream unplugged for 3 s at 10 s:
    the stub receives VO tracking and the scale ready, then the camera lost (CRITICAL) and
    back, the VO lost and tracking again, the pose reset; its ground-station endpoint
    forwards them as received (our system and component ids), as PX4 does with -f."""
    from companion.sitl.stub.autopilot import SimAutopilot
    from companion.sitl.stub.faults import Fault

    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", 0))
    gcs.setblocking(False)
    cfg, opts = sitl_flight(
        tmp_path,
        20.0,
        small=True,  # the 320x240 camera: the messages are the service's
        faults=(Fault("camera_unplug", 10.0, 3.0),),
        armed=True,
    )
    opts = dataclasses.replace(  # type: ignore[type-var]
        opts, gcs_listen_port=free_port(socket.SOCK_DGRAM), gcs_port=gcs.getsockname()[1]
    )

    rx = mavlink.MAVLink(None)
    rx.robust_parsing = True
    fwd: list[Any] = []

    def ground_station() -> None:  # what reached its port so far (drained: it gets streams)
        while True:
            try:
                data = gcs.recv(65536)
            except BlockingIOError:
                return
            fwd.extend(m for m in rx.parse_buffer(data) or [] if m.get_type() == "STATUSTEXT")

    async def fly() -> tuple[SimAutopilot, Service]:
        stub = SimAutopilot(cfg, opts)
        stub_task = asyncio.create_task(stub.run(tmp_path / "autopilot"))
        async with Service(cfg) as service:
            stub_task.add_done_callback(lambda _: service.stop())

            async def listen() -> None:
                while True:
                    ground_station()
                    await asyncio.sleep(0.1)

            listener = asyncio.create_task(listen())
            await service.run()
        await stub_task
        listener.cancel()
        ground_station()
        return stub, service

    stub, service = asyncio.run(fly())
    got = [(sev, text) for _, sev, text, _, _ in stub.stats.statustexts]
    print(got)
    bodies = [text.removeprefix(PREFIX).split(" [")[0] for _, text in got]
    sev = {b: s for b, (s, _) in zip(bodies, got, strict=True)}

    def first(prefix: str, after: int = -1) -> int:
        return next(i for i, b in enumerate(bodies) if b.startswith(prefix) and i > after)

    assert all(text.startswith(PREFIX) for _, text in got)
    assert sev["started v0.1.0, VPE"] == Severity.NOTICE
    assert sev["VO tracking"] == Severity.INFO
    assert sev["camera lost: no frames"] == Severity.CRITICAL  # armed
    assert sev["camera ok"] == Severity.INFO
    # (the camera may also be "lost" before the stub serves it and after the flight ends)
    tracking = first("VO tracking")
    assert first("scale ready") > tracking
    lost = first("camera lost: no frames", after=first("scale ready"))
    # each subject in its own order (subjects wait for their own interval, so the order
    # across subjects may differ by up to key_interval_s)
    first("camera ok", after=lost)
    assert first("VO lost", after=lost) < first("VO tracking again", after=lost), bodies
    first("pose reset: counter 1", after=lost)
    # no flood: the bucket's bound over the whole run, and no text twice in a row
    duration_s = service.summary()["uptime_s"]
    assert len(got) <= 5 + duration_s
    assert all(a != b for a, b in itertools.pairwise(got))
    # the ground-station endpoint forwarded them as received
    gcs.close()
    assert {(m.get_srcSystem(), m.get_srcComponent()) for m in fwd} == {(1, 197)}
    assert [(int(m.severity), str(m.text)) for m in fwd] == got


# ---------------------------------------------------------------------------------------------
# the real PX4 SITL: our STATUSTEXT on its ground-station port
# ---------------------------------------------------------------------------------------------


@pytest.mark.timeout(120)
def test_real_px4_forwards_our_statustext_to_its_ground_station_port(tmp_path) -> None:
    """PX4 SITL's GCS and onboard links are started with -f (forwarding: its
    etc/init.d-posix/px4-rc.mavlink), so a STATUSTEXT the service sends on the onboard link
    reaches a ground station on PX4's GCS link with our system and component ids."""
    from peers import px4 as px4_peer

    if not px4_peer.available():
        pytest.skip(px4_peer.SKIP_REASON)
    px4 = px4_peer.Px4Sitl(px4_peer.free_instance(), tmp_path / "px4")
    px4.start()
    try:
        gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        gcs.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        gcs.bind(("127.0.0.1", px4.gcs_client_port))  # PX4's partner (announced at start)
        gcs.settimeout(0.2)
        cfg = service_config(
            tmp_path,
            mavlink_url=f"udpin:127.0.0.1:{px4.companion_port}",
            camera_url=f"sitl://127.0.0.1:{free_port()}",  # nobody there: "camera lost"
            system_id=px4.instance + 1,  # PX4 SITL's MAV_SYS_ID (its rcS)
        )
        rx = mavlink.MAVLink(None)
        rx.robust_parsing = True
        seen: list[Any] = []

        def listen(until: Any, deadline_s: float) -> None:
            end = time.monotonic() + deadline_s
            while time.monotonic() < end and not until():
                try:
                    data = gcs.recv(65536)
                except (TimeoutError, OSError):
                    continue
                seen.extend(m for m in rx.parse_buffer(data) or [] if m.get_type() == "STATUSTEXT")

        def ours() -> list[str]:
            return [
                str(m.text)
                for m in seen
                if (m.get_srcSystem(), m.get_srcComponent()) == (px4.instance + 1, 197)
            ]

        async def run() -> None:
            async with Service(cfg) as service:
                # Both, not the first of them: under load PX4's onboard link may speak
                # only after our camera has already been declared lost.
                await asyncio.to_thread(
                    listen,
                    lambda: (
                        "CMP: camera lost: no frames" in ours()
                        and service.stats.autopilot_system_id != 0
                    ),
                    45.0,
                )
                assert service.stats.autopilot_system_id == px4.instance + 1  # PX4 heard

        asyncio.run(run())
        listen(lambda: "CMP: stopping" in ours(), 5.0)
        gcs.close()
    finally:
        px4.stop()
    print([(m.get_srcSystem(), m.get_srcComponent(), int(m.severity), str(m.text)) for m in seen])
    texts_px4 = ours()
    assert "CMP: started v0.1.0, VPE" in texts_px4, [str(m.text) for m in seen]
    assert "CMP: camera lost: no frames" in texts_px4, [str(m.text) for m in seen]
    assert "CMP: stopping" in texts_px4, [str(m.text) for m in seen]
