"""A status socket with a sample reply, for the tests of the server (test_status.py), the
client (test_status_client.py) and the CLI (test_cli.py)."""

from __future__ import annotations

import asyncio
import threading
from typing import Any

from companion.service.status import StatusServer

SAMPLE: dict[str, Any] = {
    "uptime_s": 12.5,
    "autopilot": {
        "url": "udpin:127.0.0.1:14540",
        "heartbeat_age_s": 0.4,
        "system_id": 1,
        "timesync_converged": True,
        "timesync_offset_ms": 10608.123,
        "timesync_rtt_ms": 0.21,
        "px4_converts_stamps": False,
        "stamped_at_send": 12,
        "rates_acknowledged": [26, 30, 111, 132],  # PX4: SCALED_IMU, ATTITUDE, TIMESYNC, ...
        "rates_refused": [],
        "rx_messages": 1000,
        "rx_bad": 2,
    },
    "camera": {
        "url": "sitl://127.0.0.1:5600",
        "fps": 29.9,
        "frames": 370,
        "dropped": 1,
        "last_frame_age_s": 0.02,
    },
    "vo": {
        "state": "TRACKING",
        "features": 180,
        "keyframes": 9,
        "resets": 0,
        "frames_retimed": 412,
        "stamp_jitter_ms": 15.7,
        "focal_ratio": 0.914,
        "focal_pairs": 134,
        "k1_delta": -0.004,
        "lens_warning": "camera focal length looks 8.5 % too large",
    },
    "scale": {
        "method": "M-MSCwK",
        "value": 5.93,
        "sigma": 0.004,
        "sensors_used": 4,
        "ranges_in": 2400,
        "ranges_rejected": 0,
    },
    "attitude": {
        "roll_deg": 1.2,
        "pitch_deg": -0.4,
        "sigma_deg": 0.05,
        "compensation": True,
        "reasons": ["sensor 2: hit 0.31 m off the surface around it (edge?)"],
    },
    "output": {
        "message": "vision_position_estimate",
        "rate_hz": 30.0,
        "published": 300,
        "reset_counter": 0,
        "latency_ms_p50": 12.1,
    },
    "mqtt": {"enabled": False},
    "warnings": ["camera: stream ended; reopening"],
}


def serve_in_thread(path, provider):
    """Run a StatusServer on its own event loop in a thread; returns (stop, thread)."""
    ready = threading.Event()
    stop: dict = {}

    def run() -> None:
        async def main_() -> None:
            stop["event"] = asyncio.Event()
            stop["loop"] = asyncio.get_running_loop()
            async with StatusServer(path, provider) as srv:
                stop["server"] = srv
                ready.set()
                await stop["event"].wait()

        asyncio.run(main_())

    t = threading.Thread(target=run)
    t.start()
    assert ready.wait(5)
    return stop, t


def halt(stop, t) -> None:
    stop["loop"].call_soon_threadsafe(stop["event"].set)
    t.join(5)
