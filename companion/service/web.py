"""The live page: one HTML page and one WebSocket, served on the service's event loop (aiohttp),
read-only (GET only; nothing a viewer sends is read but the WebSocket's own frames).

Inputs: ``LatestView`` (the worker's 1-slot handover, web_view.py), the service's status
(the provider ``companion status`` reads), the STATUSTEXT lines sent and the warnings
(``ServiceStats``), the poses sent and the autopilot's LOCAL_POSITION_NED (``on_pose``,
``on_local_position``: two top-down tracks). Outputs, on ``/ws`` to each viewer: ``frame``
(the overlay as JSON text, then the JPEG as a binary message) at ``web.image_hz`` at most,
``status`` once a second, ``track`` (the points a viewer has not seen).

Cost: with no viewer, nothing runs (the producer waits; the worker checks one int). With
viewers, one producer renders the latest view on the page's own thread (a 1-thread executor:
never the worker's, never the event loop) and every viewer sends the newest packet when its
previous send is done: a slow viewer skips frames (counted), nothing queues for it, and a
send stuck for SEND_TIMEOUT_S closes it.

Access: web_access.py (the token on every request, a loopback Host without one, the
WebSocket's Origin); the access log is off (a URL's token is never logged). A port in use, a
bad request, a viewer gone mid-send or a bug in the page's code are said (warnings, the
status's ``web`` section) and the service runs on.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from functools import partial
from importlib import resources
from typing import Any

from aiohttp import WSMsgType, web

from companion.geometry.camera import CameraModel
from companion.scale.options import ScaleOptions
from companion.service.runtime import Runtime
from companion.service.status import jsonable
from companion.service.web_access import PAGE_HEADERS, authorised, same_origin
from companion.service.web_view import LatestView, Rendered, Track, render
from companion.service_options import WebOptions
from companion.types import PoseEstimate

log = logging.getLogger("companion.web")

MAX_VIEWERS = 4  # WebSockets at once; more get 503 (each costs a send per image)
SEND_TIMEOUT_S = 10.0  # a viewer whose send is stuck this long is closed
STATUS_PERIOD_S = 1.0
HEALTH_LINES = 12  # the last STATUSTEXT lines sent with each status


@dataclass
class WebStats:
    """What the page did (counts since the start; the status's ``web`` section)."""

    listening: bool = False
    problem: str | None = None  # why the page is off (a port in use), or its last error
    pages: int = 0  # pages served
    refused: int = 0  # requests without the token, from a foreign Host or Origin, or too many
    viewers_total: int = 0  # WebSockets opened
    images_rendered: int = 0
    images_sent: int = 0  # to all viewers together
    images_skipped: int = 0  # newer ones came while a viewer was still sending
    errors: int = 0  # the producer's failures (logged once per kind)


@dataclass(frozen=True, slots=True)
class Packet:
    """What the producer made last: the image and its overlay, the status message."""

    version: int
    image: Rendered | None
    image_index: int  # images rendered so far (the one here is the image_index-th)
    status_json: str
    status_version: int


class WebServer:
    """``async with WebServer(...)``: listens (or says why not); ``loop()`` is the producer."""

    def __init__(
        self,
        rt: Runtime,
        options: WebOptions,
        view: LatestView,
        camera: CameraModel,
        scale_opts: ScaleOptions,
        status: Callable[[], dict[str, Any]],
    ) -> None:
        self.rt, self.o, self.view = rt, options, view
        self.camera, self.scale_opts, self.status_provider = camera, scale_opts, status
        self.stats = WebStats()
        self.ours, self.autopilot = Track(), Track()
        self.page = resources.files("companion.service").joinpath("web_page.html").read_bytes()
        self._packet = Packet(0, None, 0, "{}", 0)
        self._changed = asyncio.Condition()
        self._watched = asyncio.Event()
        self._sockets: set[web.WebSocketResponse] = set()
        self._runner: web.AppRunner | None = None
        self._executor: ThreadPoolExecutor | None = None
        self._errors_said: set[str] = set()

    @property
    def url(self) -> str:
        """The page's address (without the token)."""
        host = f"[{self.o.host}]" if ":" in self.o.host else self.o.host
        return f"http://{host}:{self.o.port}/"

    # ------------------------------------------------------------------ lifecycle
    async def __aenter__(self) -> WebServer:
        app = web.Application(middlewares=[self._guard], client_max_size=4096)
        app.router.add_get("/", self._page)
        app.router.add_get("/ws", self._socket, allow_head=False)
        runner = web.AppRunner(app, access_log=None, handle_signals=False, shutdown_timeout=2.0)
        await runner.setup()
        try:
            await web.TCPSite(runner, self.o.host, self.o.port, reuse_address=True).start()
        except OSError as e:  # a port in use, an address not ours: the service runs on
            await runner.cleanup()
            self.stats.problem = f"cannot listen on {self.o.host}:{self.o.port}: {e.strerror or e}"
            self.rt.warn(f"web: {self.stats.problem}; the live page is off")
            return self
        self._runner = runner
        self._executor = ThreadPoolExecutor(1, thread_name_prefix="companion-web")
        self.stats.listening = True
        log.info("live page on %s%s", self.url, " (token required)" if self.o.token else "")
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.stats.listening = False
        for ws in list(self._sockets):
            with contextlib.suppress(Exception):
                await asyncio.wait_for(ws.close(), 1.0)
        await self._notify()  # the viewers' loops see their sockets closed
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
        self.view.viewers = 0
        self.view.clear()

    def status(self) -> dict[str, Any]:
        """The status's ``web`` section."""
        return {
            "enabled": True,
            "url": self.url,
            "token_required": bool(self.o.token),
            "viewers": self.view.viewers,
            "views_offered": self.view.offered,
            **asdict(self.stats),
        }

    # ------------------------------------------------------------------ tracks (event loop)
    def on_pose(self, pose: PoseEstimate) -> None:
        """A pose sent to the autopilot: our track."""
        p = pose.position_ned_m
        self.ours.add(pose.time_us * 1e-6, float(p[0]), float(p[1]))

    def on_local_position(self, msg: Any) -> None:
        """LOCAL_POSITION_NED from the autopilot: its own estimate's track."""
        self.autopilot.add(self.rt.clock() * 1e-9, float(msg.x), float(msg.y))

    # ------------------------------------------------------------------ the producer
    async def loop(self) -> None:
        """While somebody watches: the latest view rendered at ``web.image_hz`` at most on
        the page's thread, the status once a second; each new packet wakes the viewers.
        Never raises (a failure is counted, said once per kind, and tried again)."""
        loop = asyncio.get_running_loop()
        period_s = 1.0 / self.o.image_hz
        status_due = 0.0
        while not self.rt.stopping:
            if not self.stats.listening or not self.view.wanted():
                self._watched.clear()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._watched.wait(), 1.0)
                continue
            t0 = loop.time()
            try:
                image = await self._render(self._packet.image)
                status_json, status_version = self._packet.status_json, self._packet.status_version
                if t0 >= status_due:
                    status_due = t0 + STATUS_PERIOD_S
                    status_json, status_version = self._status_json(), status_version + 1
                last = self._packet
                if image is not last.image or status_version != last.status_version:
                    index = last.image_index + (image is not last.image)
                    self._packet = Packet(
                        last.version + 1, image, index, status_json, status_version
                    )
                    await self._notify()
            except Exception as e:  # the page's bug never stops the service
                self._failed(e)
            await self.rt.sleep(max(0.0, period_s - (loop.time() - t0)))

    async def _render(self, last: Rendered | None) -> Rendered | None:
        """The latest view rendered (off the loop), or ``last`` when there is no newer one."""
        view = self.view.take(last.number if last is not None else 0)
        if view is None or self._executor is None:
            return last
        o = self.o
        rendered = await asyncio.get_running_loop().run_in_executor(
            self._executor,
            render,
            view,
            self.camera,
            self.scale_opts,
            o.image_width,
            o.jpeg_quality,
        )
        self.stats.images_rendered += 1
        return rendered

    def _status_json(self) -> str:
        s = self.rt.stats
        message = {
            "type": "status",
            "status": self.status_provider(),
            "health": [[sev, text] for sev, text in list(s.statustexts)[-HEALTH_LINES:]],
            "warnings": list(s.warnings),
        }
        return json.dumps(message, default=jsonable)

    def _failed(self, e: BaseException) -> None:
        self.stats.errors += 1
        self.stats.problem = f"{type(e).__name__}: {e}"[:200]
        if type(e).__name__ not in self._errors_said:
            self._errors_said.add(type(e).__name__)
            log.exception("web: the live page's producer failed (the service runs on)")

    # ------------------------------------------------------------------ requests
    @web.middleware
    async def _guard(self, request: web.Request, handler: Any) -> web.StreamResponse:
        """Every request: GET (and HEAD) only, the token, a loopback Host without a token."""
        if request.method not in ("GET", "HEAD"):
            self.stats.refused += 1
            raise web.HTTPMethodNotAllowed(request.method, ["GET"])
        if not authorised(self.o.token, request.host, request.query, request.headers):
            self.stats.refused += 1
            raise web.HTTPUnauthorized(text="companion: the live page needs its token\n")
        response: web.StreamResponse = await handler(request)
        return response

    async def _page(self, request: web.Request) -> web.Response:
        self.stats.pages += 1
        return web.Response(
            body=self.page, content_type="text/html", charset="utf-8", headers=PAGE_HEADERS
        )

    async def _socket(self, request: web.Request) -> web.StreamResponse:
        """One viewer: the newest packet whenever its last send is done."""
        if not same_origin(request.headers.get("Origin"), request.host):
            self.stats.refused += 1
            raise web.HTTPForbidden(text="companion: a WebSocket from another page\n")
        if len(self._sockets) >= MAX_VIEWERS or not self.stats.listening:
            self.stats.refused += 1
            raise web.HTTPServiceUnavailable(text=f"companion: {MAX_VIEWERS} viewers already\n")
        ws = web.WebSocketResponse(heartbeat=10.0, max_msg_size=1024, compress=False)
        await ws.prepare(request)
        self._sockets.add(ws)
        self.stats.viewers_total += 1
        self.view.viewers = len(self._sockets)
        self._watched.set()
        reader = asyncio.create_task(_drain(ws))
        reader.add_done_callback(lambda _: asyncio.ensure_future(self._notify()))
        try:
            await self._serve(ws, reader)
        except (ConnectionError, TimeoutError, RuntimeError):
            pass  # the viewer went (or stuck): nothing to say
        finally:
            reader.cancel()
            self._sockets.discard(ws)
            self.view.viewers = len(self._sockets)
            if not self._sockets:
                self.view.clear()
            await ws.close()
        return ws

    async def _notify(self) -> None:
        """Wake every viewer's loop (a new packet, a viewer gone, the service stopping)."""
        async with self._changed:
            self._changed.notify_all()

    def _ready(self, version: int, reader: asyncio.Task[None]) -> bool:
        """Whether a viewer's loop has work: a packet newer than ``version``, or an end."""
        return self._packet.version > version or reader.done() or self.rt.stopping

    async def _serve(self, ws: web.WebSocketResponse, reader: asyncio.Task[None]) -> None:
        version = image_index = status_version = 0
        seen = {"ours": 0, "autopilot": 0}
        while not ws.closed and not reader.done() and not self.rt.stopping:
            async with self._changed:
                await self._changed.wait_for(partial(self._ready, version, reader))
            p = self._packet
            version = p.version
            async with asyncio.timeout(SEND_TIMEOUT_S):
                if p.status_version != status_version:
                    status_version = p.status_version
                    await ws.send_str(p.status_json)
                    for name, track in (("ours", self.ours), ("autopilot", self.autopilot)):
                        start, points = track.since(seen[name])
                        seen[name] = start + len(points)
                        if points:
                            await ws.send_str(_track_json(name, start, points))
                if p.image is not None and p.image_index > image_index:
                    if image_index:  # rendered while this viewer was still sending: skipped
                        self.stats.images_skipped += p.image_index - image_index - 1
                    image_index = p.image_index
                    await ws.send_str(p.image.overlay_json)
                    await ws.send_bytes(p.image.jpeg)
                    self.stats.images_sent += 1


async def _drain(ws: web.WebSocketResponse) -> None:
    """Read what a viewer sends (its close, pongs) and drop it; ends when it goes."""
    async for msg in ws:
        if msg.type in (WSMsgType.CLOSE, WSMsgType.ERROR):
            break


def _track_json(name: str, start: int, points: list[tuple[float, float]]) -> str:
    return json.dumps({"type": "track", "which": name, "from": start, "points": points})
