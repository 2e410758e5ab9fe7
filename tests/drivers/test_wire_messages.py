"""MAVLink on the wire: our messages' fields (drivers.messages), the parser, link URLs."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from peers.mavlink_peers import decode

from companion.config import DEFAULT_RANGEFINDERS
from companion.drivers import messages
from companion.drivers.mavlink import LinkUrl
from companion.drivers.mavlink_parser import LinkStats, Parser
from companion.errors import ConfigError
from companion.geometry import so3
from companion.types import PoseEstimate


def test_a_pose_is_carried_to_its_sending_along_its_velocity() -> None:
    pose = sample_pose()
    later = messages.pose_at(pose, pose.time_us + 100_000)
    assert later.time_us == pose.time_us + 100_000
    assert np.allclose(later.position_ned_m, pose.position_ned_m + 0.1 * pose.velocity_ned_m_s)
    assert np.array_equal(later.quat_wxyz_ned_frd, pose.quat_wxyz_ned_frd)
    assert np.array_equal(later.covariance_6x6, pose.covariance_6x6)
    unknown = PoseEstimate(
        pose.time_us,
        pose.position_ned_m,
        pose.quat_wxyz_ned_frd,
        np.full(3, np.nan),
        pose.covariance_6x6,
        3,
        87,
    )
    assert messages.pose_at(unknown, pose.time_us + 100_000) is unknown  # nothing to carry


def test_link_urls() -> None:
    assert LinkUrl.parse("udpin:127.0.0.1:14540") == LinkUrl("udpin", "127.0.0.1", 14540)
    assert LinkUrl.parse("/dev/ttyAMA0").kind == "serial"
    assert LinkUrl.parse("serial:/dev/ttyUSB0:57600") == LinkUrl("serial", "/dev/ttyUSB0", 57600)
    for bad in ("udp:1.2.3.4", "udpin:host:port", "tcp::14550x", ""):
        with pytest.raises(ConfigError, match=r"service\.mavlink_url"):
            LinkUrl.parse(bad)


def sample_pose() -> PoseEstimate:
    R = so3.rpy_to_matrix(0.05, -0.03, 1.2)
    cov = np.diag([0.01, 0.02, 0.03, 1e-4, 2e-4, 3e-3])
    cov[0, 1] = cov[1, 0] = 0.005
    return PoseEstimate(
        1_234_567_890,
        np.array([1.5, -2.25, -6.0]),
        so3.matrix_to_quat(R),
        np.array([0.5, 1.0, -0.1]),
        cov,
        3,
        87,
    )


def test_vision_position_estimate_fields_round_trip() -> None:
    from pymavlink.dialects.v20 import common as mavlink

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
    pose = sample_pose()
    buf = messages.vision_position_estimate(mav, pose).pack(mav)
    assert buf[0] == 0xFD  # MAVLink 2
    msg = decode(buf)
    assert msg.get_type() == "VISION_POSITION_ESTIMATE"
    assert msg.get_srcComponent() == 197
    assert msg.usec == pose.time_us
    np.testing.assert_allclose([msg.x, msg.y, msg.z], pose.position_ned_m, rtol=1e-7)
    rpy = so3.matrix_to_rpy(so3.quat_to_matrix(pose.quat_wxyz_ned_frd))
    np.testing.assert_allclose([msg.roll, msg.pitch, msg.yaw], rpy, atol=1e-6)
    cov = np.array(msg.covariance)
    assert cov[0] == pytest.approx(0.01) and cov[1] == pytest.approx(0.005)
    assert cov[6] == pytest.approx(0.02) and cov[20] == pytest.approx(3e-3)
    assert msg.reset_counter == 3


def test_odometry_fields_round_trip() -> None:
    from pymavlink.dialects.v20 import common as mavlink

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
    pose = sample_pose()
    msg = decode(messages.odometry(mav, pose, (0.1, -0.2, 0.3)).pack(mav))
    assert msg.frame_id == messages.MAV_FRAME_LOCAL_FRD
    assert msg.child_frame_id == messages.MAV_FRAME_BODY_FRD
    assert msg.estimator_type == messages.MAV_ESTIMATOR_TYPE_VISION
    np.testing.assert_allclose(msg.q, pose.quat_wxyz_ned_frd, atol=1e-7)
    R = so3.quat_to_matrix(pose.quat_wxyz_ned_frd)
    np.testing.assert_allclose([msg.vx, msg.vy, msg.vz], R.T @ pose.velocity_ned_m_s, atol=1e-6)
    np.testing.assert_allclose([msg.rollspeed, msg.pitchspeed, msg.yawspeed], [0.1, -0.2, 0.3])
    assert msg.quality == 87 and msg.reset_counter == 3
    unknown_velocity = PoseEstimate(**{**_fields(pose), "velocity_ned_m_s": np.full(3, np.nan)})
    assert messages.odometry(mav, unknown_velocity) is None


def _fields(pose: PoseEstimate) -> dict:
    return {k: getattr(pose, k) for k in pose.__slots__}


def test_non_finite_poses_are_not_sendable() -> None:
    pose = sample_pose()
    assert messages.is_finite_pose(pose)
    cov = pose.covariance_6x6.copy()
    cov[3, 3] = np.nan
    assert not messages.is_finite_pose(PoseEstimate(**{**_fields(pose), "covariance_6x6": cov}))
    pos = np.array([np.inf, 0.0, 0.0])
    assert not messages.is_finite_pose(PoseEstimate(**{**_fields(pose), "position_ned_m": pos}))


def test_distance_sensor_mapping() -> None:
    from pymavlink.dialects.v20 import common as mavlink

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    sensors = {r.sensor_id: r for r in DEFAULT_RANGEFINDERS}

    def ds(d_cm: int, sid: int = 1, orientation: int = 25, quality: int = 100):
        return decode(
            mav.distance_sensor_encode(
                10, 10, 4000, d_cm, 0, sid, orientation, 255, signal_quality=quality
            ).pack(mav)
        )

    s, why = messages.range_from_distance_sensor(ds(612), sensors, 42, 50)
    assert s is not None and s.distance_m == pytest.approx(6.12) and s.sensor_id == 1
    assert s.time_us == 42 and why == ""
    for bad, reason, t_us in (
        (ds(0), "no_reading", 42),
        (ds(65535), "no_reading", 42),
        (ds(5), "out_of_range", 42),
        (ds(4500), "out_of_range", 42),
        (ds(612, quality=1), "invalid", 42),
        (ds(612, sid=9), "unknown_id", 42),
        (ds(612, orientation=0), "not_downward", 42),
        (ds(612), "from_the_past", 50 - 600_000),
        (ds(612), "from_the_future", 50 + 60_000),
    ):
        assert messages.range_from_distance_sensor(bad, sensors, t_us, 50) == (None, reason)


def test_implausible_attitudes_are_refused() -> None:
    from pymavlink.dialects.v20 import common as mavlink

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)

    def att(*v: float):
        return decode(mav.attitude_encode(10, *v).pack(mav))

    assert messages.attitude_from_message(att(0.1, -0.2, 3.0, 0.0, 0.1, 0.2), 5) is not None
    for v in (
        (np.nan, 0, 0, 0, 0, 0),
        (0, 0, 0, np.inf, 0, 0),
        (4.0, 0, 0, 0, 0, 0),
        (0, 1.7, 0, 0, 0, 0),
        (0, 0, 1e30, 0, 0, 0),
        (0, 0, 0, 0, 0, 80.0),
    ):
        assert messages.attitude_from_message(att(*v), 5) is None


def test_centred_pose_velocity_is_exact_under_constant_acceleration() -> None:
    """ODOMETRY's centred pose: the mean time and position of the last N poses and their
    central velocity, which under constant acceleration is the true velocity at the mean
    time (the newest pose's 150 ms difference lags it by 75 ms)."""
    from companion.types import PoseEstimate

    a = np.array([2.0, -1.0, 0.5])
    v0 = np.array([1.0, 3.0, 0.0])

    def pose(t_us: int, reset: int = 4) -> PoseEstimate:
        t = t_us * 1e-6
        p = v0 * t + 0.5 * a * t**2
        return PoseEstimate(
            t_us, p, np.array([1.0, 0, 0, 0]), np.full(3, np.nan), np.eye(6), reset, 90
        )

    poses = [pose(1_000_000 + k * 33_333) for k in range(5)]
    c = messages.centred_pose(poses)
    assert c is not None and c.time_us == poses[2].time_us
    assert np.allclose(c.velocity_ned_m_s, v0 + a * c.time_us * 1e-6, atol=1e-9)
    # the position is the mean: under acceleration it sits a/2 * var(t) off the curve
    t_c = c.time_us * 1e-6
    var_t = np.var([q.time_us * 1e-6 for q in poses])
    curve = v0 * t_c + 0.5 * a * t_c**2
    assert np.allclose(c.position_ned_m, curve + 0.5 * a * var_t, atol=1e-9)
    assert c.reset_counter == 4 and c.quality_pct == 90
    assert messages.centred_pose(poses[:2]) is None
    assert messages.centred_pose([*poses[:4], pose(1_200_000, reset=5)]) is None
    # a pause in publishing (a slow moment): a window over it would be stamped half the pause
    # old (PX4 received 1.5 s old samples so, 2026-11-27); one skipped frame is no pause
    late = [poses[0], poses[1], pose(poses[1].time_us + 2_000_000)]
    assert messages.centred_pose(late) is not None  # without a bound: the old behaviour
    assert messages.centred_pose(late, max_gap_us=100_000) is None
    skipped = [poses[0], poses[1], poses[3]]
    c = messages.centred_pose(skipped, max_gap_us=100_000)
    assert c is not None and c.time_us == round(np.mean([q.time_us for q in skipped]))


def test_scaled_imu_gives_the_accelerometer_or_nothing() -> None:
    """SCALED_IMU's accelerometer (mG -> specific force, FRD [m/s^2]) for the VO's gravity,
    its gyroscope (mrad/s -> rad/s) and magnetometer (mgauss -> gauss; all zero: no compass)
    for our compass heading; beyond 16 g: none."""
    from pymavlink.dialects.v20 import common as mavlink

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)

    def imu(ax: int, ay: int, az: int, gyro=(0, 0, 0), mag=(0, 0, 0)):
        m = mav.scaled_imu_encode(123, ax, ay, az, *gyro, *mag)
        return decode(m.pack(mav))

    got = messages.imu_from_scaled(imu(10, -20, -1000), 42)
    assert got is not None and got.time_us == 42
    assert np.allclose(got.accel_frd_m_s2, [0.0980665, -0.196133, -9.80665])
    assert got.mag_frd_gauss is None and np.array_equal(got.gyro_frd_rad_s, np.zeros(3))
    got = messages.imu_from_scaled(imu(0, 0, -1000, (5, -7, 1200), (218, -13, 430)), 42)
    assert got is not None and got.gyro_frd_rad_s is not None and got.mag_frd_gauss is not None
    assert np.allclose(got.gyro_frd_rad_s, [0.005, -0.007, 1.2])
    assert np.allclose(got.mag_frd_gauss, [0.218, -0.013, 0.430])
    assert messages.imu_from_scaled(imu(0, 0, -17000), 42) is None  # 17 g


def test_garbage_is_counted_not_raised() -> None:
    from pymavlink.dialects.v20 import common as mavlink

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    good = mav.heartbeat_encode(2, 12, 0, 0, 4).pack(mav)
    parser, stats = Parser(), LinkStats()
    rng = np.random.default_rng(0)
    got = 0
    for _ in range(300):
        junk = bytes(rng.integers(0, 256, int(rng.integers(1, 60)), dtype=np.uint8))
        got += len(parser.feed(junk, stats))
        got += len(parser.feed(good, stats))
    assert got >= 150  # most good frames survive the garbage between them
    assert stats.rx_bad > 0


def test_a_corrupted_length_byte_costs_one_frame_on_a_stream() -> None:
    """pymavlink waits for as many bytes as a corrupted length byte promises, swallowing the
    good frames behind it; our parser searches the failed frame again from its second byte."""
    from pymavlink.dialects.v20 import common as mavlink

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frames = [mav.attitude_encode(k, 0.1, 0.2, 0.3, 0, 0, 0).pack(mav) for k in range(400)]
    rng = np.random.default_rng(5)
    bad = set(rng.choice(np.arange(1, 399), 40, replace=False).tolist())
    stream = bytearray()
    for k, f in enumerate(frames):
        b = bytearray(f)
        if k in bad:
            b[1] = 255  # a length byte hit by noise: promises 255 payload bytes
        stream += b
    stream += bytes(300)  # the line goes on (a frame promising more is only judged then)
    parser, stats = Parser(), LinkStats()
    got = []
    for i in range(0, len(stream), 64):  # serial reads of 64 bytes
        got += parser.feed(bytes(stream[i : i + 64]), stats)
    times = [m.time_boot_ms for m in got]
    assert times == sorted(set(range(400)) - bad)  # every good frame once, nothing invented
    assert stats.rx_bad >= len(bad)


def test_udpout_sends_from_the_fixed_local_port() -> None:
    """PX4 answers the first sender's address until it reboots: after a restart of the
    service, the autopilot's stream must still reach us, so udpout can use a fixed port."""
    import asyncio

    from peers import free_port

    from companion.drivers.mavlink import MavlinkLink

    autopilot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    autopilot.bind(("127.0.0.1", 0))
    autopilot.settimeout(2.0)
    local = free_port(socket.SOCK_DGRAM)
    url = f"udpout:127.0.0.1:{autopilot.getsockname()[1]}"

    async def once() -> tuple[str, int]:
        async with MavlinkLink(url, 1, 197, lambda m, t: None, local_port=local) as link:
            link.send(link.mav.heartbeat_encode(18, 8, 0, 0, 4))
            _, addr = await asyncio.to_thread(autopilot.recvfrom, 4096)
        return addr

    first, second = asyncio.run(once()), asyncio.run(once())  # a restart in between
    autopilot.close()
    assert first[1] == second[1] == local
