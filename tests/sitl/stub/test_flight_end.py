"""The SITL autopilot's flight window (sitl/stub/autopilot.py, sitl/stub/camera.py): a flight
ended before its scenario's end (AutopilotOptions.end_s) stops its camera and its clock
there with the scenario's trajectory unchanged, and the end-of-flight hook
(AutopilotOptions.flight_done, which gives a test run's machine back) is awaited once, after
the flight and its linger, before the report."""

from __future__ import annotations

import asyncio
import socket
import time

import numpy as np
from peers import free_port

from companion.config import load_config
from companion.sitl.stub.autopilot import SimAutopilot
from companion.sitl.stub.camera import flight_frames
from companion.sitl.stub.options import AutopilotOptions
from companion.sitl.world.trajectory import Trajectory


def test_a_flight_ended_early_sends_the_frames_up_to_its_end() -> None:
    assert flight_frames(1200, 30.0, 0.0) == 1200  # the scenario's whole flight
    assert flight_frames(1200, 30.0, 34.0) == 1021  # frames 0 .. 1020, the last at 34.000 s
    assert flight_frames(1200, 30.0, 33.99) == 1020
    assert flight_frames(1200, 30.0, 50.0) == 1200  # never past the scenario's end
    assert flight_frames(300, 15.0, 1.0 / 15.0) == 2


def test_a_flight_ended_early_ends_there_then_says_so_once() -> None:
    cfg = load_config(None, {"sitl": {"terrain": "flat", "trajectory": "circle", "seconds": 20.0}})
    ends: list[float] = []

    async def done() -> None:
        ends.append(stub.t_sim_of_mono(time.monotonic_ns()))

    opts = AutopilotOptions(
        listen_port=free_port(socket.SOCK_DGRAM),
        companion_port=free_port(socket.SOCK_DGRAM),
        gcs_listen_port=0,
        camera=False,  # MAVLink only: no render process
        warmup_s=0.0,
        linger_s=0.2,
        end_s=0.5,
        flight_done=done,
    )
    stub = SimAutopilot(cfg, opts)
    assert stub.end_s == 0.5
    asyncio.run(stub.run())
    # once, after the end and the linger, long before the scenario's 20 s
    assert len(ends) == 1 and 0.5 + 0.2 <= ends[0] < 20.0, ends
    # the trajectory is the scenario's own (its circle paced for 20 s), not one of 0.5 s
    whole = Trajectory("circle", stub.world, 20.0, cfg.sitl.altitude_m, cfg.sitl.speed_m_s)
    t = np.linspace(0.0, 20.0, 41)
    np.testing.assert_array_equal(stub.trajectory.sample(t).position_m, whole.sample(t).position_m)
