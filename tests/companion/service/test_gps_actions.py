"""The autopilot's side of a GPS handover (companion/service/gps_actions.py) against a fake
link: whom [gps] handover tells, what it sends (PX4's INT32 byte-wise, ArduPilot's source set),
which answers count, the retries. The actions inside a whole loss and return are in
test_gps_frame.py."""

from __future__ import annotations

import pytest
from peers.mavlink_peers import EncodingLink as FakeLink

from companion.config import load_config
from companion.service.gps_actions import (
    MAX_TRIES,
    GpsActions,
    bytewise_int32,
    int32_bytewise,
)
from companion.service.runtime import AutopilotKind, Runtime


def actions(handover: str) -> tuple[GpsActions, FakeLink, list[int]]:
    rt = Runtime(load_config(None, {"gps": {"align": True, "handover": handover}}))
    now = [0]
    rt.clock = lambda: now[0]
    link = FakeLink()
    return GpsActions(rt, link), link, now


def test_auto_tells_the_autopilot_its_heartbeat_names() -> None:
    a, link, _ = actions("auto")
    assert a.target() is None
    a.on_loss()
    assert link.sent == []  # nobody heard yet: nothing told
    a.rt.stats.autopilot_kind = AutopilotKind.ARDUPILOT
    a.on_loss()
    cmd = link.sent[-1]
    assert cmd.get_type() == "COMMAND_LONG" and cmd.command == 42007 and cmd.param1 == 2.0
    a.on_command_ack(42007, 5)  # IN_PROGRESS: not an answer
    assert a.current is not None and a.current.result == "pending"
    a.on_command_ack(42007, 4)
    assert a.status()[-1]["result"] == "refused (MAV_RESULT_FAILED)"
    a.on_return()
    assert link.sent[-1].param1 == 1.0
    a.on_command_ack(42007, 0)
    assert a.status()[-1]["result"] == "acknowledged"


@pytest.mark.parametrize("value", [0, 7, 1, -1, 2**31 - 1])
def test_px4_int32_travels_byte_wise(value: int) -> None:
    assert bytewise_int32(int32_bytewise(value)) == value


def test_px4_takes_only_its_own_echo_and_is_retried_until_then() -> None:
    a, link, now = actions("px4")
    a.on_loss()
    m = link.sent[-1]
    assert m.get_type() == "PARAM_SET" and m.param_id == "EKF2_GPS_CTRL" and m.param_type == 6
    assert bytewise_int32(m.param_value) == 0
    a.on_param_value("EKF2_GPS_CTRL", int32_bytewise(7))  # another value: not ours
    a.on_param_value("EKF2_EV_CTRL", int32_bytewise(0))  # another parameter
    a.on_command_ack(42007, 0)  # ArduPilot's answer: not PX4's
    assert a.status()[-1]["result"] == "pending"
    for k in range(1, 4):
        now[0] = int(k * 1.05e9)
        a.tick()
    assert len(link.sent) == 4 and a.status()[-1]["tries"] == 4
    a.on_param_value("EKF2_GPS_CTRL", int32_bytewise(0))
    assert a.status()[-1]["result"] == "acknowledged"
    now[0] = int(10e9)
    a.tick()
    assert len(link.sent) == 4  # answered: not sent again


def test_a_newer_action_replaces_an_unanswered_one() -> None:
    a, link, now = actions("px4")
    a.on_loss()
    a.on_return()
    assert [s["result"] for s in a.status()] == ["replaced", "pending"]
    for k in range(1, 3 * MAX_TRIES):
        now[0] = int(k * 1.05e9)
        a.tick()
    assert a.status()[-1] == {"what": "EKF2_GPS_CTRL 7", "tries": MAX_TRIES, "result": "no answer"}
    assert len(link.sent) == 1 + MAX_TRIES


def test_none_tells_nobody() -> None:
    a, link, _ = actions("none")
    a.rt.stats.autopilot_kind = AutopilotKind.PX4
    a.on_loss()
    a.on_return()
    assert link.sent == [] and a.status() == []
