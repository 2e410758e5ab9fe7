"""The live page (companion/service/web.py, web_view.py, web_access.py): its options, who may
read it, what it costs the worker while nobody watches, the drawing data of a frame, and the
server against a real aiohttp client (token, read-only, frames skipped for a slow viewer, a
port in use)."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import socket
from typing import Any

import cv2
import numpy as np
import pytest
from peers import free_port, service_config

from companion.config import load_config
from companion.errors import ConfigError
from companion.scale.methods import ScaleInput
from companion.service.web_access import authorised, same_origin
from companion.service.web_view import LatestView, Track, WebView, render
from companion.service_options import is_loopback, web_flag
from companion.types import CameraFrame, VoFeatures, VoOutput, VoState

TOKEN = "0123456789abcdef-web"


# ------------------------------------------------------------------------------- options
def test_the_page_is_off_and_on_loopback_by_default() -> None:
    o = load_config().web
    assert (o.enabled, o.host, o.token) == (False, "127.0.0.1", "")
    assert o.image_hz <= 10
    assert all(map(is_loopback, ["127.0.0.1", "127.3.4.5", "::1", "[::1]", "localhost"]))
    assert not any(map(is_loopback, ["0.0.0.0", "::", "192.168.4.1", "drone.local", ""]))


@pytest.mark.parametrize(
    ("web", "message"),
    [
        ({"enabled": True, "host": "0.0.0.0"}, "web.token: required when host is not loopback"),
        ({"enabled": True, "host": "192.168.8.1"}, "web.token: required"),
        ({"token": "short"}, "web.token: at least 16 printable ASCII"),
        ({"token": "sixteen chars but spaces"}, "web.token: at least 16"),
        ({"image_hz": 25}, "web.image_hz: must be <= 10"),
        ({"image_width": 40}, "web.image_width: 0 (the camera's) or >= 80"),
        ({"port": 0}, "web.port: must be >= 1"),
        ({"host": ""}, "web.host: an address or a host name"),
    ],
)
def test_a_bad_web_option_names_its_key(web: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_config(None, {"web": web})


def test_a_non_loopback_host_with_a_token_loads_and_the_token_is_never_shown() -> None:
    from companion.config import describe

    cfg = load_config(None, {"web": {"enabled": True, "host": "0.0.0.0", "token": TOKEN}})
    assert cfg.web.token == TOKEN
    assert not any(TOKEN in line for line in describe(cfg))


def test_the_web_flag() -> None:
    assert web_flag("8081") == {"enabled": True, "port": 8081}
    assert web_flag("0.0.0.0:9000") == {"enabled": True, "port": 9000, "host": "0.0.0.0"}
    assert web_flag("[::1]:9000")["host"] == "::1"
    for bad in ("", "x", "host:", ":80", "1:99999", "a:0"):
        with pytest.raises(ConfigError, match="--web"):
            web_flag(bad)


def test_companion_run_web_on_wifi_without_a_token_exits_2_naming_the_key(capsys) -> None:
    from companion.cli import main

    assert main(["run", "--web", "0.0.0.0:8088", "--duration", "0"]) == 2
    assert "web.token" in capsys.readouterr().err


# ------------------------------------------------------------------------------- access
def test_the_token_is_asked_on_every_request() -> None:
    host = "192.168.8.1:8080"
    assert authorised(TOKEN, host, {"token": TOKEN}, {})
    assert authorised(TOKEN, host, {}, {"X-Companion-Token": TOKEN})
    assert authorised(TOKEN, host, {}, {"Authorization": f"Bearer {TOKEN}"})
    assert not authorised(TOKEN, host, {}, {})
    assert not authorised(TOKEN, host, {"token": TOKEN[:-1]}, {})
    assert not authorised(TOKEN, host, {"token": TOKEN + "x"}, {})
    assert not authorised(TOKEN, host, {}, {"Authorization": TOKEN})  # not "Bearer ..."
    # no token configured (loopback only): a loopback Host, not a rebinding site's name
    assert authorised("", "127.0.0.1:8080", {}, {})
    assert authorised("", "localhost:8080", {}, {})
    assert authorised("", "[::1]:8080", {}, {})
    assert not authorised("", "evil.example:8080", {}, {})
    assert not authorised("", "192.168.8.1:8080", {}, {})
    assert same_origin(None, "127.0.0.1:8080")
    assert same_origin("http://127.0.0.1:8080", "127.0.0.1:8080")
    assert not same_origin("http://evil.example", "127.0.0.1:8080")


# ------------------------------------------------------------------------------- the worker
def test_the_worker_makes_no_view_while_nobody_watches(tmp_path) -> None:
    """With the page on but no viewer, the worker hands over nothing (offered stays 0, no
    frame is kept); with one, every processed frame is offered and only the newest is held."""
    from companion.service.app import Service

    service = Service(service_config(tmp_path, {"web": {"enabled": True}}))
    view = service.web_view
    assert view is not None and service.worker.view is view
    rng = np.random.default_rng(1)
    frames = [
        CameraFrame(5_000_000_000 + k * 33_333, k, rng.integers(0, 255, (48, 64, 3), np.uint8))
        for k in range(12)
    ]
    for f in frames[:6]:
        service.worker.process(f, [], [], [])
    assert (view.offered, view.latest) == (0, None)
    view.viewers = 1
    for f in frames[6:]:
        service.worker.process(f, [], [], [])
    assert view.offered == 6
    assert view.latest is not None and view.latest.frame is frames[-1]  # a reference
    assert view.take(6) is None and view.take(5) is view.latest
    view.viewers = 0
    service.worker.process(frames[0], [], [], [])
    assert view.offered == 6
    # a frame held for the autopilot's attitude: drawn without an earlier frame's features
    view.viewers = 1
    service.stats.autopilot_heartbeat_ns = 1  # an autopilot, no ATTITUDE yet: held
    service.worker.pipeline.vo.lose()
    service.worker.process(frames[0], [], [], [])
    assert view.latest.frame is frames[0] and view.latest.vo is None
    assert service.worker.pipeline.vo_output is not None  # the earlier frame's, not drawn


def test_a_track_keeps_a_point_per_5_cm_or_second_and_gives_each_viewer_what_it_lacks() -> None:
    t = Track(max_points=10)
    step_m = 1 / 64  # exact in binary: 4 steps (6.25 cm) make a point, 3 (4.7 cm) do not
    for k in range(100):  # at 100 Hz
        t.add(k * 0.01, k * step_m, 0.0)
    assert t.total == 25 and len(t.points) == 10
    start, pts = t.since(0)  # the first 15 were dropped: all that is kept
    assert (start, len(pts)) == (15, 10) and pts[-1] == (round(96 * step_m, 3), 0.0)
    assert t.since(23) == (23, list(t.points)[-2:])
    assert t.since(25) == (25, [])
    t.add(5.0, 96 * step_m, 0.0)  # hovering: one a second still
    t.add(5.5, 96 * step_m, 0.0)
    assert t.total == 26
    t.add(7.0, float("nan"), 0.0)
    assert t.total == 26


# ------------------------------------------------------------------------------- drawing
def _view(number: int = 1, size: tuple[int, int] = (640, 480)) -> tuple[WebView, Any, Any]:
    """A tracked frame: 3 features (two with map points at 5 and 10 VO units ahead), one laser
    hitting the image centre, the scale 2 m per VO unit."""
    from companion.pipeline import Pipeline

    cfg = load_config()
    pipe = Pipeline(cfg)
    cam = pipe.camera
    cx, cy = cam.cx, cam.cy
    feats = VoFeatures(
        np.array([[cx + 2.0, cy + 1.0], [100.0, 80.0], [300.0, 200.0]]),
        np.array([7, 8, -1]),
        np.array([[0.004, 0.002, 5.0], [-2.0, -1.5, 10.0], [np.nan] * 3]),
        np.array([0.01, 0.02, np.nan]),
    )
    out = VoOutput(1000, VoState.TRACKING, False, np.eye(4), feats)
    laser = (10.0, np.array([0.0, 0.0, 10.0]), 0.02)
    inp = ScaleInput(1000, out, np.eye(4), {3: laser}, 0)
    status = dataclasses.replace(pipe.status(), vo_state="TRACKING", scale=2.0, scale_sigma=0.01)
    image = np.random.default_rng(0).integers(0, 255, (size[1], size[0], 3), np.uint8)
    frame = CameraFrame(1000, 42, image)
    return WebView(frame, out, inp, status, None, number), cam, cfg.scale


def test_a_frame_is_drawn_with_its_features_depths_laser_dots_and_matches() -> None:
    view, cam, scale_opts = _view()
    r = render(view, cam, scale_opts, 320, 70)
    img = cv2.imdecode(np.frombuffer(r.jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (240, 320, 3)  # downscaled for a phone
    o = json.loads(r.overlay_json)
    for key in ("features", "lasers", "vo_state", "scale", "scale_sigma", "quality_pct", "seq"):
        assert key in o
    assert (o["width"], o["height"], o["seq"], o["vo_state"]) == (320, 240, 42, "TRACKING")
    k = 320 / cam.width
    (u0, v0, d0, p0), (_, _, d1, _), (_, _, d2, p2) = o["features"]
    assert (u0, v0) == (round((cam.cx + 2) * k, 1), round((cam.cy + 1) * k, 1))
    assert (d0, d1, d2, p0, p2) == (10.0, 20.0, None, 1, 0)  # metres: 2 x VO depth
    (dot,) = o["lasers"]
    assert dot["id"] == 3 and dot["range_m"] == 10.0
    assert abs(dot["u"] - cam.cx * k) < 0.1 and abs(dot["v"] - cam.cy * k) < 0.1
    assert dot["match"] == [u0, v0]  # the map point the MSC match takes: feature 0's


def test_no_match_is_drawn_where_the_scale_would_take_none() -> None:
    view, cam, scale_opts = _view()
    far = dataclasses.replace(view.scale_input, lasers={3: (10.0, np.array([3.0, 3.0, 10]), 0.02)})
    o = json.loads(
        render(dataclasses.replace(view, scale_input=far), cam, scale_opts, 0, 70).overlay_json
    )
    assert o["width"] == cam.width and o["lasers"][0]["match"] is None


# ------------------------------------------------------------------------------- the server
class Page:
    """A WebServer on a free loopback port with a fake status, for an aiohttp client."""

    def __init__(self, tmp_path, **web: Any) -> None:
        from companion.service.runtime import Runtime

        self.port = free_port()
        o = {"enabled": True, "port": self.port, "token": TOKEN, "image_hz": 10, **web}
        self.cfg = service_config(tmp_path, {"web": o})
        self.rt = Runtime(self.cfg)
        self.view = LatestView()
        self.base = f"http://127.0.0.1:{self.port}"

    def server(self) -> Any:
        from companion.pipeline import Pipeline
        from companion.service.web import WebServer

        camera = Pipeline(self.cfg).camera
        return WebServer(
            self.rt, self.cfg.web, self.view, camera, self.cfg.scale, lambda: {"uptime_s": 1.0}
        )


def test_the_page_asks_for_its_token_and_is_read_only(tmp_path) -> None:
    import aiohttp

    page = Page(tmp_path)

    async def main() -> dict[str, Any]:
        got: dict[str, Any] = {}
        async with page.server() as web, aiohttp.ClientSession() as http:
            for name, url, headers in (
                ("none", "/", {}),
                ("wrong", f"/?token={TOKEN[:-1]}x", {}),
                ("query", f"/?token={TOKEN}", {}),
                ("header", "/", {"X-Companion-Token": TOKEN}),
                ("ws-none", "/ws", {}),
                ("missing", f"/nothing?token={TOKEN}", {}),
            ):
                async with http.get(page.base + url, headers=headers) as r:
                    got[name] = (r.status, await r.text(), dict(r.headers))
            async with http.post(f"{page.base}/?token={TOKEN}", data=b"x") as r:
                got["post"] = r.status
            got["stats"] = web.status()
        return got

    got = asyncio.run(main())
    assert got["none"][0] == 401 and got["wrong"][0] == 401 and got["ws-none"][0] == 401
    status, html, headers = got["query"]
    assert status == 200 and '<canvas id="camera"' in html and "new WebSocket" in html
    assert "http" not in html.split("<script>")[1].replace("https:", "")  # no CDN, no address
    assert headers["Referrer-Policy"] == "no-referrer"
    assert got["header"][0] == 200
    assert got["missing"][0] == 404 and got["post"] == 405
    s = got["stats"]
    assert s["url"] == f"http://127.0.0.1:{page.port}/" and TOKEN not in json.dumps(s)
    assert s["pages"] == 2 and s["refused"] == 4 and s["listening"]


def test_a_slow_viewer_gets_the_newest_frames_not_a_queue(tmp_path) -> None:
    """A viewer that stops reading for 2 s while frames keep coming (1.5 MB each, so that the
    sockets' buffers fill within a few): the server keeps one packet, the frames rendered
    meanwhile are skipped for it (counted), and once it reads again it gets the newest ones,
    not every frame in order; a second viewer that reads meanwhile gets them at the full rate."""
    import aiohttp

    page = Page(tmp_path, image_width=0, jpeg_quality=95)
    view, _, _ = _view(size=(1600, 1200))

    async def main() -> dict[str, Any]:
        async with page.server() as web, aiohttp.ClientSession() as http:
            url = f"{page.base}/ws?token={TOKEN}"
            producer = asyncio.create_task(web.loop())  # the service's "web" loop
            async with http.ws_connect(url) as slow, http.ws_connect(url) as fast:
                assert page.view.viewers == 2

                async def feed(seconds: float) -> None:
                    for _ in range(int(seconds / 0.05)):
                        number = page.view.offered + 1
                        page.view.offer(view.frame, view.vo, view.scale_input, view.status, None)
                        assert page.view.latest is not None and page.view.latest.number == number
                        await asyncio.sleep(0.05)

                async def read(ws: Any, seconds: float) -> list[int]:
                    numbers: list[int] = []
                    end = asyncio.get_running_loop().time() + seconds
                    while (left := end - asyncio.get_running_loop().time()) > 0:
                        try:
                            msg = await ws.receive(timeout=left)
                        except TimeoutError:
                            break
                        if msg.type == aiohttp.WSMsgType.TEXT and '"frame"' in msg.data[:20]:
                            numbers.append(json.loads(msg.data)["number"])
                    return numbers

                fast_reader = asyncio.create_task(read(fast, 4.5))
                await feed(2.0)  # the slow viewer reads nothing meanwhile
                feeding = asyncio.create_task(feed(2.0))
                slow_numbers = await read(slow, 2.5)
                await feeding
                fast_numbers = await fast_reader
                page.rt.stop()
                await producer
                return {
                    "slow": slow_numbers,
                    "fast": fast_numbers,
                    "stats": web.status(),
                }

    r = asyncio.run(main())
    assert page.view.viewers == 0 and page.view.latest is None  # let go when they left
    s = r["stats"]
    assert s["images_skipped"] > 0
    # the fast viewer: about every rendered frame (5 Hz on a loaded machine at least)
    assert len(r["fast"]) >= 10 and r["fast"] == sorted(r["fast"])
    # the slow one: what its sockets held, then the newest, never each frame rendered
    # (seen: [2, 4, 6, 8, 40, 42, ...] against the fast one's [2, 4, 6, ..., 80])
    assert len(r["slow"]) < s["images_rendered"] and r["slow"] == sorted(r["slow"])
    assert np.diff(r["slow"]).max() >= 10, r["slow"]  # half a second of frames and more skipped


def test_a_port_in_use_leaves_the_service_running_and_says_why(tmp_path) -> None:
    from companion.service.app import Service

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        cfg = service_config(tmp_path, {"web": {"enabled": True, "port": port}})

        async def main() -> dict[str, Any]:
            async with Service(cfg) as service:
                await asyncio.sleep(0.3)
                assert not any(t.done() for t in service.tasks)  # every loop runs on
                return service.status()

        st = asyncio.run(main())
    web = st["web"]
    assert web["enabled"] and not web["listening"] and web["viewers"] == 0
    assert f"cannot listen on 127.0.0.1:{port}" in web["problem"]
    assert any("web: cannot listen" in w and "the live page is off" in w for w in st["warnings"])
    # `companion status` takes the section and shows why the page is off
    from companion.cli.service import format_status
    from companion.drivers.status import validate_status

    validate_status(json.loads(json.dumps(st, default=str)))
    (line,) = [x for x in format_status(st).splitlines() if x.startswith("web ")]
    assert f"OFF: cannot listen on 127.0.0.1:{port}" in line


def test_a_failure_in_the_page_is_counted_and_said_and_the_page_runs_on(
    tmp_path, monkeypatch, caplog
) -> None:
    """The producer's render raises (a bug): counted, logged once, the status still goes out,
    the next views are drawn again; a viewer that drops its connection leaves no trace."""
    import aiohttp

    import companion.service.web as web_module

    page = Page(tmp_path)
    view, _, _ = _view()
    real = web_module.render
    calls = {"n": 0}

    def flaky(*args: Any) -> Any:
        calls["n"] += 1
        if calls["n"] <= 3:
            raise ValueError("a bug in the drawing")
        return real(*args)

    monkeypatch.setattr(web_module, "render", flaky)

    async def main() -> tuple[list[str], dict[str, Any], bool]:
        async with page.server() as web, aiohttp.ClientSession() as http:
            producer = asyncio.create_task(web.loop())
            kinds: list[str] = []
            async with http.ws_connect(f"{page.base}/ws?token={TOKEN}") as ws:
                for _ in range(12):
                    page.view.offer(view.frame, view.vo, view.scale_input, view.status, None)
                    await asyncio.sleep(0.1)
                while True:
                    try:
                        msg = await ws.receive(timeout=0.5)
                    except TimeoutError:
                        break
                    if msg.type == aiohttp.WSMsgType.TEXT:
                        kinds.append(json.loads(msg.data)["type"])
                    elif msg.type == aiohttp.WSMsgType.BINARY:
                        kinds.append("jpeg")
            await asyncio.sleep(0.2)  # the server sees the viewer gone
            alive = not producer.done()
            page.rt.stop()
            await producer
            return kinds, web.status(), alive

    kinds, st, alive = asyncio.run(main())
    assert alive and st["errors"] == 3 and "ValueError: a bug in the drawing" in st["problem"]
    assert "status" in kinds and kinds.count("frame") == kinds.count("jpeg") >= 3
    assert len([r for r in caplog.records if "producer failed" in r.getMessage()]) == 1
    assert st["viewers"] == 0 and page.view.latest is None


def test_the_autopilots_own_position_feeds_the_page_not_the_session(tmp_path) -> None:
    """LOCAL_POSITION_NED is parsed only with the page on, from the autopilot's system only."""
    from pymavlink.dialects.v20 import common as mavlink

    from companion.service.app import Service

    service = Service(service_config(tmp_path, {"web": {"enabled": True}}))
    assert service.web is not None

    def message(system_id: int, north_m: float) -> Any:
        mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=1)
        buf = mavlink.MAVLink_local_position_ned_message(1000, north_m, 2.0, -5.0, 0, 0, 0)
        return mav.parse_char(buf.pack(mav))

    service._on_message(message(1, 1.0), 0)
    service._on_message(message(1, 3.0), 0)
    service._on_message(message(7, 9.0), 0)  # another vehicle's
    assert list(service.web.autopilot.points) == [(1.0, 2.0), (3.0, 2.0)]
    assert service.stats.foreign_messages == 0  # not the session's to count
    (tmp_path / "off").mkdir()
    off = Service(service_config(tmp_path / "off", {}))
    assert off.web is None and 32 not in off.link._parser.wanted
    assert 32 in service.link._parser.wanted


def test_the_service_stops_promptly_with_a_viewer_connected(tmp_path) -> None:
    """The server closes while a viewer is connected and reading: its socket is closed, the
    server's exit takes well under the viewer heartbeat's 10 s, nothing is left counted."""
    import aiohttp

    page = Page(tmp_path)

    async def main() -> tuple[float, Any, int]:
        async with aiohttp.ClientSession() as http:
            web = page.server()
            await web.__aenter__()
            producer = asyncio.create_task(web.loop())
            ws = await http.ws_connect(f"{page.base}/ws?token={TOKEN}")
            first = await ws.receive(timeout=5.0)  # the status
            assert json.loads(first.data)["type"] == "status"
            t0 = asyncio.get_running_loop().time()
            page.rt.stop()
            await producer
            await web.__aexit__(None, None, None)
            took_s = asyncio.get_running_loop().time() - t0
            last = await ws.receive(timeout=5.0)
            return took_s, last.type, page.view.viewers

    took_s, last, viewers = asyncio.run(main())
    assert took_s < 5.0 and viewers == 0
    assert last in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.CLOSING)
