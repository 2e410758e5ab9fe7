"""PX4's parameter rules as EKF2 and PX4's MAVLink read them (pure): the EKF2_EV_CTRL bits,
the noise floors, the delays, GNSS and the height reference, the companion's MAVLink instance
(serial and UDP), and the INT32 / REAL32 byte-wise encodings a wrong tool leaves behind."""

from __future__ import annotations

from typing import Any

from companion.autopilot.params import Param, Row, Status
from companion.autopilot.px4.encoding import (
    float32_bits_as_int32,
    float_encoded_int,
    int32_bits_as_float32,
    int_encoded_float,
)
from companion.autopilot.px4.link_context import LinkContext
from companion.autopilot.px4.rules import evaluate
from companion.config import load_config


def test_float_and_int_encodings_are_inverse_and_detected() -> None:

    for v in (0, 1, 3, 15, 921600, -1, 2**31 - 1):
        assert float32_bits_as_int32(int32_bits_as_float32(v)) == v
    assert float_encoded_int(1077936128, 0, 15) == 3.0  # the EKF2_EV_CTRL trap
    assert float_encoded_int(0x49610000, 0, 3_000_000) == 921600.0  # SER_TELn_BAUD
    assert float_encoded_int(3, 0, 15) is None  # a fine value
    assert float_encoded_int(99, 0, 15) is None  # out of range, but not a float's bytes
    assert int_encoded_float(int32_bits_as_float32(5)) == 5
    assert int_encoded_float(0.1) is None and int_encoded_float(0.0) is None


def _rows(params: dict[str, int | float], ctx: Any) -> dict[str, Row]:

    typed = {k: Param(k, v, isinstance(v, int)) for k, v in params.items()}
    return {r.name: r for r in evaluate(typed, ctx)}


def test_ev_ctrl_bits_as_ekf2_reads_them() -> None:

    ctx = LinkContext("odometry")
    base: dict[str, int | float] = {"EKF2_HGT_REF": 0, "SYS_HAS_MAG": 1, "EKF2_MAG_TYPE": 0}
    velocity_only = _rows({**base, "EKF2_EV_CTRL": 4}, ctx)["EKF2_EV_CTRL"]
    assert velocity_only.status is Status.FAIL and "horizontal position" in velocity_only.why
    assert velocity_only.targets[0].value == 7
    position_only = _rows({**base, "EKF2_EV_CTRL": 1}, ctx)["EKF2_EV_CTRL"]
    assert position_only.status is Status.WARN and position_only.targets[0].value == 7
    assert _rows({**base, "EKF2_EV_CTRL": 7}, ctx)["EKF2_EV_CTRL"].status is Status.OK
    # yaw, as the real PX4 showed it (docs/decisions.md): ODOMETRY (LOCAL_FRD) with bit 3
    # never aligns EKF2's heading, with a magnetometer or without: FAIL, 7 written instead
    with_yaw = _rows({**base, "EKF2_EV_CTRL": 15}, ctx)["EKF2_EV_CTRL"]
    assert with_yaw.status is Status.FAIL and with_yaw.targets[0].value == 7
    two_mags = _rows({**base, "SYS_HAS_MAG": 2, "EKF2_EV_CTRL": 7}, ctx)
    assert two_mags["EKF2_EV_CTRL"].status is Status.OK  # 2 is two magnetometers, not "none"
    assert two_mags["EKF2_MAG_TYPE"].status is Status.OK
    # ODOMETRY without a magnetometer: no heading alignment at all; the output is wrong
    no_mag = _rows({**base, "SYS_HAS_MAG": 0, "EKF2_EV_CTRL": 7}, ctx)
    assert no_mag["EKF2_EV_CTRL"].status is Status.OK
    assert no_mag["service.output"].status is Status.FAIL
    assert "vision_position_estimate" in no_mag["service.output"].need
    assert no_mag["EKF2_MAG_TYPE"].status is Status.FAIL
    # VISION_POSITION_ESTIMATE (NED): bit 3 needed without a magnetometer, either way with one
    vpe = LinkContext("vision_position_estimate")
    vpe_no_mag = _rows({**base, "EKF2_MAG_TYPE": 5, "EKF2_EV_CTRL": 3}, vpe)["EKF2_EV_CTRL"]
    assert vpe_no_mag.status is Status.FAIL and vpe_no_mag.targets[0].value == 11
    assert "never fused" in vpe_no_mag.why
    assert _rows({**base, "EKF2_MAG_TYPE": 5, "EKF2_EV_CTRL": 11}, vpe)["EKF2_EV_CTRL"].status is (
        Status.OK
    )
    for mask in (3, 11):
        assert _rows({**base, "EKF2_EV_CTRL": mask}, vpe)["EKF2_EV_CTRL"].status is Status.OK
    # ODOMETRY in LOCAL_NED (the PX4 loop's): NED like VISION_POSITION_ESTIMATE, so the yaw
    # bit is allowed (needed without a magnetometer), velocity wanted, quality present
    ned = LinkContext("odometry", odometry_frame="local_ned")
    for mask in (7, 15):
        assert _rows({**base, "EKF2_EV_CTRL": mask}, ned)["EKF2_EV_CTRL"].status is Status.OK
    ned_pos = _rows({**base, "EKF2_EV_CTRL": 11}, ned)["EKF2_EV_CTRL"]
    assert ned_pos.status is Status.WARN and ned_pos.targets[0].value == 15
    ned_no_mag = _rows({**base, "EKF2_MAG_TYPE": 5, "EKF2_EV_CTRL": 7}, ned)
    assert ned_no_mag["EKF2_EV_CTRL"].status is Status.FAIL
    assert ned_no_mag["EKF2_EV_CTRL"].targets[0].value == 15
    assert "service.output" not in ned_no_mag  # NED needs no magnetometer to arm: our yaw
    qmin = _rows({**base, "EKF2_EV_CTRL": 15, "EKF2_EV_QMIN": 10}, ned)["EKF2_EV_QMIN"]
    assert qmin.status is Status.OK  # ODOMETRY carries a quality
    # EKF2_HGT_REF = vision needs bit 1
    hgt = _rows({**base, "EKF2_HGT_REF": 3, "EKF2_EV_CTRL": 1}, ctx)
    assert hgt["EKF2_EV_CTRL"].status is Status.FAIL and "height" in hgt["EKF2_EV_CTRL"].why
    assert "flat ground" in hgt["EKF2_HGT_REF"].why  # PX4's caveat on vision/range height


def test_the_velocity_floor_is_judged_against_the_velocity_sigma_we_send() -> None:
    """EKF2_EVV_NOISE floors our velocity variance: above the sigma the service sends
    (service.odometry_velocity_sigma_m_s) EKF2 ignores how well we measured it; without a
    velocity in our message the floor does not matter."""

    ours = LinkContext("odometry", odometry_frame="local_ned", velocity_sigma_m_s=0.05)
    high = _rows({"EKF2_EVV_NOISE": 0.1}, ours)["EKF2_EVV_NOISE"]
    assert high.status is Status.WARN and high.targets[0].value == 0.05
    assert "0.05" in high.why
    assert _rows({"EKF2_EVV_NOISE": 0.05}, ours)["EKF2_EVV_NOISE"].status is Status.OK
    low = _rows({"EKF2_EVV_NOISE": 0.001}, ours)["EKF2_EVV_NOISE"]
    assert low.status is Status.FAIL and low.targets[0].value == 0.05
    default = _rows({"EKF2_EVV_NOISE": 0.1}, LinkContext("odometry"))["EKF2_EVV_NOISE"]
    assert default.status is Status.OK  # PX4's default floor is our default sigma
    vpe = _rows({"EKF2_EVV_NOISE": 1.0}, LinkContext("vision_position_estimate"))
    assert vpe["EKF2_EVV_NOISE"].status is Status.OK  # no velocity sent


def test_rules_for_delay_gnss_output_and_height_reference() -> None:

    params: dict[str, int | float] = {
        "EKF2_EV_DELAY": 50.0,
        "EKF2_GPS_CTRL": 7,
        "EKF2_HGT_REF": 1,
        "MAV_2_CONFIG": 1000,
        "MAV_2_MODE": 2,
    }
    rows = _rows(params, LinkContext("both", gps_seen=False))
    assert rows["EKF2_EV_DELAY"].status is Status.WARN  # not FAIL: only with TIMESYNC working
    assert "TIMESYNC" in rows["EKF2_EV_DELAY"].need
    gps = rows["EKF2_GPS_CTRL"]
    assert gps.status is Status.INFO and not gps.targets and "--no-gnss" in gps.why
    assert "falls back" in rows["EKF2_HGT_REF"].why and rows["EKF2_HGT_REF"].status is Status.WARN
    assert rows["service.output"].status is Status.WARN  # both messages on one topic
    asked = _rows(params, LinkContext("odometry", gps_seen=False, no_gnss=True))
    assert asked["EKF2_GPS_CTRL"].targets[0].value == 0
    # a link mode without TIMESYNC: PX4 stamps at arrival, the delay is then right
    normal = _rows({**params, "MAV_2_MODE": 0}, LinkContext("odometry"))
    assert normal["EKF2_EV_DELAY"].status is Status.INFO
    assert normal["MAV_2_MODE"].status is Status.WARN and "latency" in normal["MAV_2_MODE"].why


def test_serial_link_rules_name_mode_and_baud() -> None:

    params: dict[str, int | float] = {
        "MAV_0_CONFIG": 101,
        "MAV_1_CONFIG": 102,
        "MAV_1_MODE": 0,
        "MAV_2_CONFIG": 0,
        "SER_TEL2_BAUD": 57600,
    }
    ctx = LinkContext("odometry", "TELEM2", "serial", 921600)
    rows = _rows(params, ctx)
    assert rows["MAV_1_CONFIG"].status is Status.OK
    mode = rows["MAV_1_MODE"]  # Normal: no TIMESYNC, fused but stamped at arrival
    assert mode.status is Status.WARN and mode.targets[0].value == 2 and mode.targets[0].reboot
    baud = rows["SER_TEL2_BAUD"]
    assert baud.status is Status.FAIL and baud.targets[0].value == 921600
    assert rows["MAV_0_CONFIG"].status is Status.INFO  # the ground station's link, not ours
    for ok_mode in (8, 11):  # External Vision, Onboard Low Bandwidth: both time-sync
        assert _rows({**params, "MAV_1_MODE": ok_mode}, ctx)["MAV_1_MODE"].status is Status.OK
    auto = _rows({**params, "SER_TEL2_BAUD": 0}, ctx)["SER_TEL2_BAUD"]
    assert auto.status is Status.WARN and "Auto" in auto.value  # 0 is Auto, not slow
    # nothing on TELEM3: configure would enable the free instance 2 there
    rows3 = _rows(params, LinkContext("odometry", "TELEM3", "serial", 921600))
    assert rows3["MAV_2_CONFIG"].status is Status.FAIL
    assert rows3["MAV_2_CONFIG"].targets[0].value == 103
    # PX4 after 1.16: SER_<port>_PROT and MAV_ETH_EN instead of MAV_n_CONFIG
    newer: dict[str, int | float] = {
        "SER_TEL1_PROT": 1,
        "SER_TEL2_PROT": 0,
        "MAV_ETH_EN": 0,
        "MAV_1_MODE": 2,
        "MAV_1_REMOTE_PRT": 14540,
    }
    eth = _rows(newer, LinkContext("odometry", "ETHERNET", "udpin", 14540))
    assert eth["MAV_ETH_EN"].status is Status.FAIL and eth["MAV_ETH_EN"].targets[0].value == 1
    assert eth["MAV_1_MODE"].status is Status.OK  # Ethernet is the instance after TEL1
    tel2 = _rows(newer, LinkContext("odometry", "TELEM2", "serial", 921600))
    assert tel2["SER_TEL2_PROT"].status is Status.FAIL and "instance 1" in tel2["SER_TEL2_PROT"].why


def test_udp_partner_rules_on_ethernet() -> None:
    """PX4 on a flight controller answers only the first sender, and broadcasts only outside
    Onboard mode with MAV_n_BROADCAST = 1: a listening service on another host never hears it."""

    params: dict[str, int | float] = {
        "MAV_2_CONFIG": 1000,
        "MAV_2_MODE": 2,
        "MAV_2_BROADCAST": 0,
        "MAV_2_UDP_PRT": 14580,
        "MAV_2_REMOTE_PRT": 14540,
    }
    sitl = _rows(params, LinkContext("odometry", link_kind="udpin", link_host="127.0.0.1"))
    assert sitl["MAV_2_BROADCAST"].status is Status.OK  # PX4 SITL sends to 127.0.0.1 at once
    board = LinkContext("odometry", link_kind="udpin", link_host="0.0.0.0")
    deadlock = _rows(params, board)["MAV_2_BROADCAST"]
    assert deadlock.status is Status.FAIL and "udpout:<autopilot IP>:14580" in deadlock.why
    assert not deadlock.targets  # broadcasting changes nothing in Onboard mode
    ev_mode = _rows({**params, "MAV_2_MODE": 8}, board)["MAV_2_BROADCAST"]
    assert ev_mode.status is Status.FAIL and ev_mode.targets[0].value == 1
    broadcast = _rows({**params, "MAV_2_MODE": 8, "MAV_2_BROADCAST": 1}, board)
    assert broadcast["MAV_2_BROADCAST"].status is Status.OK
    out = LinkContext("odometry", link_kind="udpout", link_port=14580, link_host="10.41.10.2")
    sends_first = _rows(params, out)
    assert sends_first["MAV_2_UDP_PRT"].status is Status.OK
    assert sends_first["MAV_2_BROADCAST"].status is Status.WARN  # the partner's port sticks


def test_delay_max_reaches_back_as_far_as_our_oldest_stamps() -> None:
    """EKF2_DELAY_MAX against how old our stamps can leave (service.stale_frame_ms plus the
    ODOMETRY centring), EKF2's horizon trailing by ~45 ms (the real PX4 measured 156 / 236 ms
    with 200 / 300): the default service (100 ms, no centring) is served by PX4's default 200;
    the PX4 loop's (200 ms and 3 poses centred at 20 Hz: 250 ms) needs 300, which configure
    writes (applied at a reboot). A parameter list without it gets no row."""

    assert load_config().oldest_stamp_ms() == 100.0
    assert load_config("config/px4_sitl.toml").oldest_stamp_ms() == 250.0
    base: dict[str, int | float] = {
        "EKF2_HGT_REF": 3,
        "SYS_HAS_MAG": 1,
        "EKF2_MAG_TYPE": 0,
        "EKF2_EV_CTRL": 15,
    }
    loop = LinkContext("odometry", odometry_frame="local_ned", oldest_stamp_ms=250.0)
    short = _rows({**base, "EKF2_DELAY_MAX": 200.0}, loop)["EKF2_DELAY_MAX"]
    assert short.status is Status.WARN and "fused late" in short.why
    assert [(t.value, t.reboot) for t in short.targets] == [(300.0, True)]
    assert _rows({**base, "EKF2_DELAY_MAX": 300.0}, loop)["EKF2_DELAY_MAX"].status is Status.OK
    default = LinkContext("odometry")
    assert _rows({**base, "EKF2_DELAY_MAX": 200.0}, default)["EKF2_DELAY_MAX"].status is Status.OK
    assert "EKF2_DELAY_MAX" not in _rows(base, loop)
