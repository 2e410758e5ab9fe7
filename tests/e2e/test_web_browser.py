"""The live page in a real browser: headless Chromium (Debian's, driven over its DevTools
protocol: tests/peers/chromium.py) opens the page of a service flying the SITL autopilot,
with a token as on a vehicle's Wi-Fi. The page loads, its camera image and pose counter move
between two screenshots, and the health line of a camera fault injected mid-flight (2 s of
black frames) appears in its DOM.

``COMPANION_WEB_DOCS_PNG=docs/web-live-page.png`` also writes the last screenshot there, and
the page on a phone's screen beside it as ``web-live-page-phone.png`` (the
docs' picture of the page: docs/service.md, "The live page")."""

from __future__ import annotations

import asyncio
import os
import shutil
from pathlib import Path
from typing import Any

import pytest
from peers import free_port, sitl_flight
from peers.chromium import CHROMIUM, chromium

from companion.service.app import Service

TOKEN = "browser-test-token-0123456789"
FAULT_AT_S, FAULT_S = 11.0, 2.0


@pytest.mark.slow
@pytest.mark.timeout(240)
@pytest.mark.skipif(
    shutil.which("chromium") is None and not Path(CHROMIUM).exists(),
    reason="no Chromium (Debian's chromium package: `make sysdeps` installs it)",
)
def test_the_live_page_in_chromium_during_a_sitl_flight(tmp_path) -> None:
    from companion.sitl.stub.autopilot import SimAutopilot
    from companion.sitl.stub.faults import Fault

    port = free_port()
    docs_png = os.environ.get("COMPANION_WEB_DOCS_PNG")
    cfg, opts = sitl_flight(
        tmp_path,
        20.0,
        small=not docs_png,  # the docs' picture at the SITL's own 640 x 480
        overrides={"web": {"enabled": True, "port": port, "host": "127.0.0.1", "token": TOKEN}},
        faults=(Fault("camera_black", FAULT_AT_S, FAULT_S),),
    )
    url = f"http://127.0.0.1:{port}/?token={TOKEN}"
    shots = tmp_path / "screenshots"
    shots.mkdir()

    async def browse(service: Service, stub_done: asyncio.Task[Any]) -> dict[str, Any]:
        seen: dict[str, Any] = {}
        async with chromium(tmp_path / "profile") as page:
            # the whole page in one picture
            await page.call(
                "Emulation.setDeviceMetricsOverride",
                width=1280,
                height=1060,
                deviceScaleFactor=1,
                mobile=False,
            )
            while service.stats.published < 30 and not stub_done.done():
                await asyncio.sleep(0.2)
            await page.call("Page.navigate", url=url)
            js = "document.getElementById('{}').textContent"
            for k in (1, 2):
                await asyncio.sleep(2.5)
                seen[f"shot{k}"] = await page.screenshot(shots / f"page-{k}.png")
                seen[f"camera{k}"] = await page.evaluate(
                    "document.getElementById('camera').toDataURL()"
                )
                seen[f"seq{k}"] = await page.evaluate(js.format("frame-seq"))
                seen[f"published{k}"] = await page.evaluate(js.format("published"))
                seen[f"features{k}"] = await page.evaluate("overlay && overlay.features.length")
            seen["conn"] = await page.evaluate(js.format("conn"))
            seen["health"] = ""
            while not stub_done.done() and "camera lost: dark" not in seen["health"]:
                await asyncio.sleep(0.5)
                seen["health"] = await page.evaluate(js.format("health"))
            await asyncio.sleep(3.0)  # the camera back, the track on: the docs' picture
            seen["last"] = await page.screenshot(shots / "page-3.png")
            seen["health_last"] = await page.evaluate(js.format("health"))
            seen["track_points"] = await page.evaluate("tracks.ours.length")
            seen["viewers"] = service.status()["web"]["viewers"]
            # a phone held upright: the page fits its width (nothing to scroll sideways)
            await page.call(
                "Emulation.setDeviceMetricsOverride",
                width=390,
                height=844,
                deviceScaleFactor=2,
                mobile=True,
            )
            await asyncio.sleep(1.5)
            seen["phone"] = await page.screenshot(shots / "phone.png")
            seen["phone_width"] = await page.evaluate("document.documentElement.scrollWidth")
            seen["phone_camera"] = await page.evaluate(
                "document.getElementById('camera').getBoundingClientRect().width"
            )
        return seen

    async def fly() -> tuple[dict[str, Any], dict[str, Any]]:
        stub = SimAutopilot(cfg, opts)
        stub_task = asyncio.create_task(stub.run(tmp_path / "autopilot"))
        async with Service(cfg) as service:
            stub_task.add_done_callback(lambda _: service.stop())
            browser = asyncio.create_task(browse(service, stub_task))
            await service.run()
            seen = await browser
            status = service.status()
        await stub_task
        return seen, status

    seen, status = asyncio.run(fly())
    # the page loaded and stayed live; two screenshots: the image and the pose count moved
    assert seen["conn"] == "live"
    assert seen["shot1"] != seen["shot2"]
    assert seen["camera1"] != seen["camera2"]
    assert int(seen["seq2"]) > int(seen["seq1"]) > 0
    assert int(seen["published2"]) > int(seen["published1"]) > 0
    assert seen["features1"] > 20 and seen["features2"] > 20
    # the camera fault's health line, as sent to the ground station, in the page's DOM
    assert "camera lost: dark" in seen["health"], seen["health"]
    assert "camera ok" in seen["health_last"]
    assert seen["track_points"] > 10 and seen["viewers"] == 1
    web = status["web"]
    assert web["listening"] and web["images_sent"] > 20 and web["errors"] == 0
    assert web["refused"] == 0
    assert seen["phone_width"] <= 390 and 300 <= seen["phone_camera"] <= 390
    if docs_png:
        Path(docs_png).write_bytes(seen["last"])
        phone = Path(docs_png)
        phone.with_name(f"{phone.stem}-phone.png").write_bytes(seen["phone"])
