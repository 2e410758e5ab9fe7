"""The ArduPilot dialect's pure parts (drivers/ardupilot.py): when the origin is (re)sent and
held, the quality mapping, the SET_GPS_GLOBAL_ORIGIN wire round trip; the checker's URL
spelling. The real ArduCopter is in tests/e2e/test_ardupilot_service.py and
test_ardupilot_check.py."""

from __future__ import annotations

from pymavlink.dialects.v20 import common as mavlink

from companion.autopilot.reach import pymavlink_url
from companion.drivers.ardupilot import (
    ORIGIN_HOLD_S,
    ORIGIN_RESEND_S,
    Origin,
    OriginKeeper,
    ardupilot_quality,
    autopilot_name,
    set_gps_global_origin,
)

S = 1_000_000_000  # ns


def test_origin_is_resent_each_second_until_a_position_holds_for_two_seconds() -> None:
    k = OriginKeeper()
    assert k.due(0)
    k.mark_sent(0)
    assert not k.due(int(0.5 * S)) and k.due(int(ORIGIN_RESEND_S * S))
    # EKF3 took an origin sent before its initialisation: a position, then 0 again (wiped)
    k.position(-353632610, 1491652300, 1 * S)
    k.position(0, 0, int(1.5 * S))
    assert not k.held and k.due(2 * S)
    k.mark_sent(2 * S)
    for t in range(3, 3 + int(ORIGIN_HOLD_S) + 1):
        k.position(-353632610, 1491652300, t * S)
    assert k.held and not k.due(10 * S)
    assert k.sent == 2
    # the autopilot rebooted: its position is 0, 0 again
    k.position(0, 0, 11 * S)
    assert not k.held and k.lost == 1 and k.due(11 * S)
    k.reset()
    assert k.due(11 * S)


def test_quality_never_reads_unknown_or_failed_to_ardupilot() -> None:
    assert [ardupilot_quality(q) for q in (0, 0.4, 1, 57.6, 100, 130)] == [1, 1, 1, 58, 100, 100]


def test_autopilot_names() -> None:
    assert autopilot_name(mavlink.MAV_AUTOPILOT_PX4) == "PX4"
    assert autopilot_name(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA) == "ArduPilot"
    assert autopilot_name(99) == "MAV_AUTOPILOT 99"


def test_set_gps_global_origin_round_trip() -> None:
    tx = mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
    msg = set_gps_global_origin(tx, 1, Origin(-35.363261, 149.16523, 584.0), 123456)
    rx = mavlink.MAVLink(None)
    got = rx.parse_char(msg.pack(tx))
    assert got.get_type() == "SET_GPS_GLOBAL_ORIGIN"
    assert (got.latitude, got.longitude, got.altitude) == (-353632610, 1491652300, 584000)
    assert got.time_usec == 123456 and got.target_system == 1


def test_checker_speaks_pymavlink_urls() -> None:
    assert pymavlink_url("tcp:127.0.0.1:5762") == "tcp:127.0.0.1:5762"
    assert pymavlink_url("udpin://0.0.0.0:14550") == "udpin:0.0.0.0:14550"
    assert pymavlink_url("tcpout://127.0.0.1:5763") == "tcp:127.0.0.1:5763"
    assert pymavlink_url("serial:///dev/ttyACM0:115200") == "/dev/ttyACM0,115200"
