"""The SITL autopilot's PX4 stub for ``companion px4 check | configure`` tests, and a fake
companion on its link.

``sitl(tmp_path)`` runs the stub (``sitl/autopilot.py`` with ``sitl/px4_*.py`` and
``sitl/ekf_fusion.py``) on free loopback ports, without a camera, with the config of a companion
wired to it; ``companion(port, Sender(...))`` is our MAVLink link on its companion port,
answering TIMESYNC at once (as the service does) and streaming ODOMETRY /
VISION_POSITION_ESTIMATE with one thing right or wrong at a time. Shared by
tests/companion/autopilot/px4/test_px4_stub.py and tests/e2e/test_px4_real.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.autopilot.options import CheckOptions
from companion.config import Config, load_config
from companion.drivers import messages
from companion.drivers.mavlink import MavlinkLink
from companion.drivers.timesync import reply_for
from companion.geometry import so3
from companion.sitl.stub.autopilot import SimAutopilot
from companion.sitl.stub.options import AutopilotOptions
from companion.types import PoseEstimate

from . import free_port

WATCH_S = 2.0


@dataclass
class Sitl:
    """A running stub and the config of a companion wired to it."""

    stub: SimAutopilot
    cfg: Config
    gcs_url: str  # MAVSDK's ground-station link

    def options(self, **kw: Any) -> CheckOptions:
        base: dict[str, Any] = {"url": self.gcs_url, "timeout_s": 8.0, "watch_s": WATCH_S}
        base.update(kw)
        return CheckOptions(**base)


@contextlib.asynccontextmanager
async def sitl(tmp_path: Path, output: str = "odometry", **opts: Any) -> AsyncIterator[Sitl]:
    """The stub on free ports (no camera), running until the block ends."""
    udp = socket.SOCK_DGRAM
    o = AutopilotOptions(
        listen_port=free_port(udp),
        companion_port=free_port(udp),
        gcs_listen_port=free_port(udp),
        gcs_port=free_port(udp),
        camera=False,
        warmup_s=0.2,
        **opts,
    )
    cfg = load_config(
        overrides={
            "sitl": {"seconds": 120.0, "world_size_m": 40.0},
            "service": {
                "mavlink_url": f"udpin:127.0.0.1:{o.companion_port}",
                "output": output,
                "status_socket": str(tmp_path / "no-service.sock"),
            },
        }
    )
    stub = SimAutopilot(cfg, o)
    task = asyncio.create_task(stub.run(None), name="sitl-stub")
    try:
        await until(lambda: stub.px4.gcs_open and stub._transport is not None)
        yield Sitl(stub, cfg, f"udpin://127.0.0.1:{o.gcs_port}")
    finally:
        task.cancel()
        with contextlib.suppress(BaseException):
            await task


@dataclass
class Sender:
    """What the fake companion sends (one field wrong at a time)."""

    kind: str = "odometry"  # or "vpe"
    rate_hz: float = 30.0
    frame_id: int = messages.MAV_FRAME_LOCAL_FRD
    estimator_type: int = messages.MAV_ESTIMATOR_TYPE_VISION
    stamp_offset_us: int = 0  # added to the capture time (negative: old stamps)
    quality_pct: int = 80


@contextlib.asynccontextmanager
async def companion(port: int, s: Sender) -> AsyncIterator[MavlinkLink]:
    """Our link on the stub's companion port: answers TIMESYNC at once (as the service does)
    and streams poses stamped in our monotonic clock."""
    link: MavlinkLink

    def on_message(msg: Any, _rx_ns: int) -> None:
        if msg.get_type() == "TIMESYNC":
            reply = reply_for(msg.tc1, msg.ts1, time.monotonic_ns())
            if reply is not None:
                link.send(link.mav.timesync_encode(reply.tc1, reply.ts1))

    link = MavlinkLink(f"udpin:127.0.0.1:{port}", 1, 197, on_message)

    async def stream() -> None:
        k = 0
        while True:
            now_us = time.monotonic_ns() // 1000
            pose = PoseEstimate(
                time_us=now_us + s.stamp_offset_us,
                position_ned_m=np.array([0.02 * k, 0.01 * k, -5.0]),
                quat_wxyz_ned_frd=so3.matrix_to_quat(so3.rpy_to_matrix(0.01, -0.02, 0.7)),
                velocity_ned_m_s=np.array([0.6, 0.3, 0.0]),
                covariance_6x6=np.diag([0.01, 0.01, 0.02, 0.001, 0.001, 0.004]),
                reset_counter=0,
                quality_pct=s.quality_pct,
            )
            if s.kind == "vpe":
                msg = messages.vision_position_estimate(link.mav, pose)
            else:
                msg = messages.odometry(link.mav, pose, (0.0, 0.0, 0.1))
                msg.frame_id = s.frame_id
                msg.estimator_type = s.estimator_type
            link.send(msg)
            link.send(link.mav.heartbeat_encode(18, 8, 0, 0, 4))
            k += 1
            await asyncio.sleep(1.0 / s.rate_hz)

    async with link:
        async with asyncio.timeout(10.0):
            while not link.connected:
                await asyncio.sleep(0.02)
        task = asyncio.create_task(stream())
        try:
            yield link
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


def set_params(stub: SimAutopilot, values: dict[str, int | float]) -> None:
    """The autopilot's own configuration before a test (as if set from its console)."""
    for name, value in values.items():
        stub.px4.params.set(name, value)


async def until(cond: Any, timeout_s: float = 3.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not cond():
            await asyncio.sleep(0.02)
