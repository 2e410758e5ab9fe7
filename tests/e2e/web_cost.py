"""What the live page costs the pipeline's worker, in one SITL flight: the page on, with no
viewer and with one (an aiohttp WebSocket client that reads everything, as a browser would,
without a browser's own CPU on this machine), in alternating windows of WINDOW_S, so that
both see the same stretch of flight and the same load.

Prints, per state, the worker's per-frame time (``ServiceStats.process_ms``: the frame through
``PipelineWorker.process`` and back on the loop, which includes the view's handover) as
median, p90 and mean, the handover itself (``LatestView.offer``) per frame, and the page
thread's own CPU (downscale, JPEG, the laser matches) per image and per frame watched.

    PYTHONPATH=$PWD:$PWD/tests .venv/bin/python tests/e2e/web_cost.py [SECONDS]

Not a test (it asserts nothing; the figures go to docs/BENCHMARKS.md by hand).
"""

from __future__ import annotations

import asyncio
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

WINDOW_S = 4.0
TOKEN = "web-cost-token-0123456789"


def main(seconds: float = 44.0) -> None:
    import aiohttp
    from peers import free_port, sitl_flight

    from companion.service.app import Service
    from companion.sitl.stub.autopilot import SimAutopilot

    tmp = Path(tempfile.mkdtemp(prefix="web-cost-"))
    port = free_port()
    cfg, opts = sitl_flight(
        tmp, seconds, overrides={"web": {"enabled": True, "port": port, "token": TOKEN}}
    )
    offer_ns: list[int] = []
    render_cpu_s: list[float] = []  # the page thread's CPU per image rendered
    import companion.service.web as web_module

    render = web_module.render

    def timed_render(*args: Any) -> Any:
        t0 = time.thread_time()
        try:
            return render(*args)
        finally:
            render_cpu_s.append(time.thread_time() - t0)

    web_module.render = timed_render  # type: ignore[assignment]
    windows: list[tuple[bool, list[float], int]] = []

    async def measure(service: Service, stub_done: asyncio.Task[Any]) -> None:
        view = service.web_view
        assert view is not None
        offer = view.offer

        def timed(*args: Any) -> None:
            t0 = time.perf_counter_ns()
            offer(*args)
            if view.viewers:
                offer_ns.append(time.perf_counter_ns() - t0)

        view.offer = timed  # type: ignore[method-assign]
        while service.stats.published < 60 and not stub_done.done():
            await asyncio.sleep(0.2)
        async with aiohttp.ClientSession() as http:
            k = 0
            while not stub_done.done():
                watched = k % 2 == 1
                ws = reader = None
                if watched:
                    ws = await http.ws_connect(f"http://127.0.0.1:{port}/ws?token={TOKEN}")
                    reader = asyncio.create_task(_read(ws))
                sent0 = service.web.stats.images_sent if service.web else 0
                n0 = service.stats.frames_processed
                await asyncio.sleep(WINDOW_S)
                n1 = service.stats.frames_processed
                sent = (service.web.stats.images_sent if service.web else 0) - sent0
                times = list(service.stats.process_ms)[-(n1 - n0) :] if n1 > n0 else []
                windows.append((watched, times, sent))
                if ws is not None and reader is not None:
                    await ws.close()
                    reader.cancel()
                k += 1

    async def fly() -> None:
        stub = SimAutopilot(cfg, opts)
        stub_task = asyncio.create_task(stub.run(tmp / "autopilot"))
        async with Service(cfg) as service:
            stub_task.add_done_callback(lambda _: service.stop())
            measuring = asyncio.create_task(measure(service, stub_task))
            await service.run()
            await measuring
        await stub_task

    asyncio.run(fly())
    for watched in (False, True):
        times = [t for w, ts, _ in windows[:-1] if w == watched for t in ts]  # last: cut short
        images = sum(n for w, _, n in windows[:-1] if w == watched)
        if not times:
            continue
        q = statistics.quantiles(times, n=10)
        print(
            f"{'1 viewer ' if watched else 'no viewer'}: {len(times)} frames, worker per frame "
            f"p50 {statistics.median(times):.2f} ms, p90 {q[8]:.2f} ms, mean "
            f"{statistics.fmean(times):.2f} ms; {images} images sent"
        )
    watched_frames = sum(len(ts) for w, ts, _ in windows if w)
    if render_cpu_s and watched_frames:
        print(
            f"the page's thread: {len(render_cpu_s)} images rendered, CPU p50 "
            f"{statistics.median(render_cpu_s) * 1e3:.2f} ms an image, "
            f"{sum(render_cpu_s) * 1e3 / watched_frames:.3f} ms per frame watched"
        )
    if offer_ns:
        us = [n / 1e3 for n in offer_ns]
        print(
            f"handover (LatestView.offer) with a viewer: p50 {statistics.median(us):.1f} us, "
            f"max {max(us):.1f} us over {len(us)} frames"
        )


async def _read(ws: Any) -> None:
    async for _ in ws:
        pass


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else 44.0)
