"""Interoperability with MAVSDK (MAVSDK-Python 4, the ctypes binding of the C++ core).

MAVSDK is an independent MAVLink implementation, so it checks both ends of our wire format
against somebody else's decoder, over real UDP on loopback, without mocks:

- the SITL autopilot stub (:mod:`sitl.stub.autopilot`) looks like a PX4 autopilot with downward
  distance sensors to a MAVSDK client in the companion's place;
- what our encoders (:mod:`drivers.messages`) send through :class:`drivers.mavlink.MavlinkLink`
  is decoded by MAVSDK into the same values: ODOMETRY by its telemetry plugin, ODOMETRY and
  VISION_POSITION_ESTIMATE field by field by its ``mavlink_direct`` plugin (libmav and
  MAVSDK's own message definitions).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import socket
import time
from collections.abc import AsyncGenerator
from typing import Any, TypeVar

import numpy as np
import pytest
from mavsdk.asyncio import Autopilot, ComponentType, Configuration, Mavsdk, Vehicle
from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

from companion.config import load_config
from companion.drivers import messages
from companion.drivers.mavlink import MavlinkLink
from companion.geometry import so3
from companion.sitl.stub.autopilot import SimAutopilot
from companion.sitl.stub.options import AutopilotOptions
from companion.types import PoseEstimate

T = TypeVar("T")

# float32 on the wire: relative rounding error <= 2**-24
F32 = {"rtol": 1e-6, "atol": 1e-9}


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def take(stream: AsyncGenerator[T, None], n: int, timeout_s: float) -> list[T]:
    """The first n items of a MAVSDK subscription; closes it (which unsubscribes) in any case.

    Raises TimeoutError when fewer than n arrive within timeout_s."""
    out: list[T] = []
    async with contextlib.aclosing(stream):
        async with asyncio.timeout(timeout_s):
            async for item in stream:
                out.append(item)
                if len(out) >= n:
                    break
    return out


def wrap_deg(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


# ---------------------------------------------------------------------------------------------
# 1. The SITL stub, seen by MAVSDK in the companion's place
# ---------------------------------------------------------------------------------------------


@pytest.mark.timeout(120)
def test_mavsdk_sees_sitl_stub_as_px4_with_downward_distance_sensors() -> None:
    cfg = load_config(overrides={"sitl": {"seconds": 8.0}})
    opts = AutopilotOptions(
        listen_port=free_port(socket.SOCK_DGRAM),
        companion_port=free_port(socket.SOCK_DGRAM),
        camera_port=free_port(socket.SOCK_STREAM),
        warmup_s=1.0,
    )

    async def scenario() -> dict[str, Any]:
        stub = SimAutopilot(cfg, opts)
        stub_task = asyncio.create_task(stub.run(None), name="sitl-stub")
        try:
            conf = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
            async with Mavsdk(conf) as drone:
                # The stub sends to companion_port: MAVSDK listens there (as the service does)
                # and answers to the address the stub's packets come from (its listen_port).
                await drone.add_any_connection(f"udpin://127.0.0.1:{opts.companion_port}")
                system = await drone.first_autopilot(timeout_s=10.0)
                assert system is not None, "MAVSDK discovered no autopilot"
                assert await system.get_system_id() == 1
                assert await system.has_autopilot()
                assert await system.is_connected()
                assert 1 in await system.component_ids()
                assert await system.autopilot_type() == Autopilot.PX4
                assert await system.vehicle_type() == Vehicle.MULTICOPTER

                telemetry = TelemetryAsync(system)
                # The flight (and the distance sensors' stream) starts warmup_s after the
                # stub's camera process is up: on a loaded machine (two runs of the suite at
                # once, 2026-11-27) that took longer than the 10 s given to the readings, so
                # the 10 s count from the flight's start
                async with asyncio.timeout(45.0):
                    while stub.flight_start_ns > time.monotonic_ns() + 10**14:
                        await asyncio.sleep(0.05)
                distances = await take(telemetry.subscribe_distance_sensor(), 20, 10.0)
                eulers = await take(telemetry.subscribe_attitude_euler(), 10, 5.0)
                rates = await take(telemetry.subscribe_attitude_angular_velocity_body(), 5, 5.0)
            # MAVSDK is gone: let the stub finish its (short) flight and write its report.
            report = await asyncio.wait_for(stub_task, timeout=30.0)
        finally:
            if not stub_task.done():
                stub_task.cancel()
                with contextlib.suppress(BaseException):
                    await stub_task

        min_m = min(rf.min_m for rf in cfg.rangefinders)
        max_m = max(rf.max_m for rf in cfg.rangefinders)
        for d in distances:
            # MAV_SENSOR_ROTATION_PITCH_270 (25), as MAVSDK's Euler angles: pitch 270 deg = down
            assert (d.orientation.roll_deg, d.orientation.pitch_deg, d.orientation.yaw_deg) == (
                0.0,
                270.0,
                0.0,
            ), d
            assert d.minimum_distance_m == pytest.approx(min_m, rel=1e-6)
            assert d.maximum_distance_m == pytest.approx(max_m, rel=1e-6)
            # hills, flown ~6 m above ground: cm on the wire, metres out of MAVSDK
            assert 3.0 <= d.current_distance_m <= 10.0, d
        assert len({round(d.current_distance_m, 2) for d in distances}) > 1  # live, not frozen

        # ATTITUDE: MAVSDK's Euler angles [deg] at its timestamp (the stub's time_boot_ms) are
        # the stub's true attitude at that instant, plus its 0.1 deg noise.
        for e in eulers:
            t_sim = stub.t_sim_of_mono(stub.mono_of_clock_ns(e.timestamp_us * 1000.0))
            assert -0.01 <= t_sim <= cfg.sitl.seconds + 0.01, (e, t_sim)
            R = stub.trajectory.sample(np.array([t_sim])).R_world_body[0]
            truth = np.degrees(so3.matrix_to_rpy(R))
            got = (e.roll_deg, e.pitch_deg, e.yaw_deg)
            for g, want in zip(got, truth, strict=True):
                assert abs(wrap_deg(g - want)) < 1.0, (e, truth)
        for w in rates:
            body = (w.roll_rad_s, w.pitch_rad_s, w.yaw_rad_s)
            assert all(math.isfinite(v) and abs(v) < 3.0 for v in body), w

        return {"heartbeats": stub.stats.heartbeats_from_companion, "link": report["link"]}

    result = asyncio.run(scenario())
    # The other way round: MAVSDK's own HEARTBEATs (it announces itself as a companion) reached
    # the stub's port, and all MAVSDK sent decoded cleanly in the stub's (pymavlink's) parser.
    assert result["heartbeats"] >= 1, result
    assert result["link"]["rx_messages"] >= result["heartbeats"], result
    assert result["link"]["rx_bad"] == 0, result


# ---------------------------------------------------------------------------------------------
# 2. Our output, decoded by MAVSDK
# ---------------------------------------------------------------------------------------------


def known_pose() -> tuple[PoseEstimate, tuple[float, float, float]]:
    """A pose with distinct, non-trivial values in every field, and body rates."""
    q = so3.matrix_to_quat(so3.rpy_to_matrix(0.1, -0.05, 1.2))
    cov = np.diag([0.01, 0.02, 0.03, 0.001, 0.002, 0.004])
    cov[0, 1] = cov[1, 0] = 0.005
    cov[2, 5] = cov[5, 2] = -0.0007
    pose = PoseEstimate(
        time_us=1_234_567_890_123,
        position_ned_m=np.array([12.5, -3.25, -6.0]),
        quat_wxyz_ned_frd=q,
        velocity_ned_m_s=np.array([1.0, 0.5, -0.2]),
        covariance_6x6=cov,
        reset_counter=3,
        quality_pct=87,
    )
    return pose, (0.01, -0.02, 0.3)


@pytest.mark.timeout(60)
def test_mavsdk_decodes_our_odometry_and_vision_position_estimate() -> None:
    pose, rates = known_pose()
    R = so3.quat_to_matrix(pose.quat_wxyz_ned_frd)
    v_body = R.T @ pose.velocity_ned_m_s
    pose_cov = messages.upper_triangle(pose.covariance_6x6)
    vel_cov = messages.upper_triangle(np.eye(6) * 0.1**2)  # odometry()'s default sigma 0.1 m/s
    roll, pitch, yaw = so3.matrix_to_rpy(R)
    port = free_port(socket.SOCK_DGRAM)
    received: list[str] = []

    async def scenario() -> tuple[Any, dict[str, Any], dict[str, Any]]:
        # Our side as the service's udpout form (a udpin link only ever answers the
        # autopilot, system 1; MAVSDK here is a ground station): MAVSDK listens, we speak
        # first, and it answers with its heartbeats from the port we send to.
        async with MavlinkLink(
            f"udpout:127.0.0.1:{port}", 1, 197, lambda msg, _t: received.append(msg.get_type())
        ) as link:
            conf = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
            async with Mavsdk(conf) as gcs:
                await gcs.add_any_connection(f"udpin://127.0.0.1:{port}")
                async with asyncio.timeout(10.0):
                    while "HEARTBEAT" not in received:
                        assert link.send(link.mav.heartbeat_encode(18, 8, 0, 0, 4))
                        await asyncio.sleep(0.1)

                odom = messages.odometry(link.mav, pose, rates)
                vpe = messages.vision_position_estimate(link.mav, pose)
                assert odom is not None

                async def keep_sending() -> None:
                    while True:
                        assert link.send(odom)
                        assert link.send(vpe)
                        await asyncio.sleep(0.05)

                sender = asyncio.create_task(keep_sending())
                try:
                    # No HEARTBEAT from an autopilot is needed: MAVSDK creates system 1 from
                    # any message of it (here ODOMETRY from component 197) and its plugins
                    # take that system's messages.
                    async with asyncio.timeout(10.0):
                        while not (systems := await gcs.get_systems()):
                            await asyncio.sleep(0.02)
                    system = systems[0]
                    assert await system.get_system_id() == 1
                    assert 197 in await system.component_ids()
                    telemetry = TelemetryAsync(system)
                    direct = MavlinkDirectAsync(system)
                    async with asyncio.TaskGroup() as tg:
                        odometry = tg.create_task(take(telemetry.subscribe_odometry(), 1, 10.0))
                        raw_odom = tg.create_task(
                            take(direct.subscribe_message("ODOMETRY"), 1, 10.0)
                        )
                        raw_vpe = tg.create_task(
                            take(direct.subscribe_message("VISION_POSITION_ESTIMATE"), 1, 10.0)
                        )
                finally:
                    sender.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await sender
        odo_msg, odo_raw, vpe_raw = odometry.result()[0], raw_odom.result()[0], raw_vpe.result()[0]
        for raw in (odo_raw, vpe_raw):
            assert (raw.system_id, raw.component_id) == (1, 197)
        return odo_msg, json.loads(odo_raw.fields_json), json.loads(vpe_raw.fields_json)

    odo, raw, vis = asyncio.run(scenario())

    # --- ODOMETRY through MAVSDK's telemetry plugin
    assert odo.time_usec == pose.time_us
    # MAVSDK 4.1's Odometry.MavFrame only knows UNDEF, BODY_NED, VISION_NED and ESTIM_NED, so
    # the frames we send (MAVLink's current LOCAL_FRD 20 / BODY_FRD 12) come out as UNDEF (0);
    # a MAVSDK that knows them would pass them through. The raw ids are checked below.
    assert int(odo.frame_id) in (0, messages.MAV_FRAME_LOCAL_FRD)
    assert int(odo.child_frame_id) in (0, messages.MAV_FRAME_BODY_FRD)
    p = odo.position_body
    np.testing.assert_allclose([p.x_m, p.y_m, p.z_m], pose.position_ned_m, **F32)
    q = odo.q
    np.testing.assert_allclose([q.w, q.x, q.y, q.z], pose.quat_wxyz_ned_frd, **F32)
    v = odo.velocity_body
    np.testing.assert_allclose([v.x_m_s, v.y_m_s, v.z_m_s], v_body, **F32)
    w = odo.angular_velocity_body
    np.testing.assert_allclose([w.roll_rad_s, w.pitch_rad_s, w.yaw_rad_s], rates, **F32)
    np.testing.assert_allclose(odo.pose_covariance.covariance_matrix, pose_cov, **F32)
    np.testing.assert_allclose(odo.velocity_covariance.covariance_matrix, vel_cov, **F32)

    # --- ODOMETRY, every field, as decoded by MAVSDK's message definitions (mavlink_direct)
    assert raw["message_name"] == "ODOMETRY"
    assert raw["time_usec"] == pose.time_us
    assert raw["frame_id"] == messages.MAV_FRAME_LOCAL_FRD == 20
    assert raw["child_frame_id"] == messages.MAV_FRAME_BODY_FRD == 12
    assert raw["estimator_type"] == messages.MAV_ESTIMATOR_TYPE_VISION
    assert raw["reset_counter"] == pose.reset_counter
    assert raw["quality"] == pose.quality_pct
    np.testing.assert_allclose([raw["x"], raw["y"], raw["z"]], pose.position_ned_m, **F32)
    np.testing.assert_allclose(raw["q"], pose.quat_wxyz_ned_frd, **F32)
    np.testing.assert_allclose([raw["vx"], raw["vy"], raw["vz"]], v_body, **F32)
    body_rates = [raw["rollspeed"], raw["pitchspeed"], raw["yawspeed"]]
    np.testing.assert_allclose(body_rates, rates, **F32)
    np.testing.assert_allclose(raw["pose_covariance"], pose_cov, **F32)
    np.testing.assert_allclose(raw["velocity_covariance"], vel_cov, **F32)

    # --- VISION_POSITION_ESTIMATE (mavlink_direct; the telemetry plugin has no such stream)
    assert vis["message_name"] == "VISION_POSITION_ESTIMATE"
    assert vis["usec"] == pose.time_us
    assert vis["reset_counter"] == pose.reset_counter
    np.testing.assert_allclose([vis["x"], vis["y"], vis["z"]], pose.position_ned_m, **F32)
    np.testing.assert_allclose([vis["roll"], vis["pitch"], vis["yaw"]], [roll, pitch, yaw], **F32)
    np.testing.assert_allclose(vis["covariance"], pose_cov, **F32)
