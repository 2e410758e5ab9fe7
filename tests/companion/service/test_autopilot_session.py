"""The autopilot session (companion.service.autopilot_session): messages in as the link hands
them over, PX4's time sync as our answers drive it."""

from __future__ import annotations

from peers.mavlink_peers import PeerClock, decode

from companion.service.runtime import AutopilotKind


def test_a_stall_of_the_service_raises_no_false_clock_jump_and_a_real_jump_is_seen(
    tmp_path, monkeypatch
) -> None:
    """The event loop blocked 0.2 s (or 0.25, 0.5, 1 s): PX4's requests queued meanwhile are
    answered at once when it runs again, up to a second late. PX4 discards those answers for
    their round trip; before, the model took the ones over 100 ms off as outliers and, six in
    a row, warned "autopilot clock jumped" (a stall of ~0.2 s, and once an unattacked
    flight). Fed as the service feeds it (`AutopilotSession.on_message`, PX4's requests and
    the answers to our own), no warning and no reset; a real jump of PX4's clock (187 ms, a
    stalled SIH) is still warned, within 0.5 s of our first answer showing it."""
    from peers import service_config
    from pymavlink.dialects.v20 import common as mavlink

    from companion.service import app

    clock = {"ns": 0}
    service = app.Service(service_config(tmp_path))
    service.runtime.clock = lambda: clock["ns"]
    service.stats.autopilot_kind = AutopilotKind.PX4
    monkeypatch.setattr(service.link, "send", lambda m: True)
    px4 = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    peer = PeerClock(offset_ns=2_000_000_000, drift_ppm=30.0)
    stalls = {20.0: 0.2, 23.0: 0.25, 26.0: 0.5, 29.0: 1.0}  # start [s] -> length [s]
    jump_s = 33.0

    def handled_at(sent_ns: int) -> int:
        """When the service handles a message that arrived at sent_ns + 0.3 ms."""
        for start, length in stalls.items():
            if start * 1e9 <= sent_ns < (start + length) * 1e9:
                return int((start + length) * 1e9)  # the loop runs again
        return sent_ns + 300_000

    def px4_clock(t_ns: int) -> int:
        return peer(t_ns) - (187_000_000 if t_ns >= jump_s * 1e9 else 0)

    events = []  # (handled at, order, message)
    for k in range(int(37.0 * 50)):
        sent = 10**9 + k * 20_000_000
        request = mavlink.MAVLink_timesync_message(0, px4_clock(sent))
        events.append((handled_at(sent), k, decode(request.pack(px4))))
    for k in range(int(37.0 * 10)):  # ours at 10 Hz; none while the loop is blocked
        sent = 10**9 + k * 100_000_000 + 3_000_000
        if handled_at(sent) != sent + 300_000:
            continue
        events.append((sent, -2, sent))  # sent: the service waits for its answer
        answer = mavlink.MAVLink_timesync_message(px4_clock(sent + 250_000), sent)
        events.append((sent + 500_000, -1, decode(answer.pack(px4))))
    jumped_at_ns, before_stalls = None, False
    for at, kind, msg in sorted(events, key=lambda e: (e[0], e[1])):
        clock["ns"] = at
        if kind == -2:
            service.session.timesync_sent.append(msg)
            continue
        if not before_stalls and at >= 20e9:  # PX4 converts by then, as modelled
            assert service.px4_stamps.converts and service.sync.converged
            before_stalls = True
        service.session.on_message(msg, at)
        if jumped_at_ns is None and service.px4_stamps.resets:
            jumped_at_ns = at
        if at < jump_s * 1e9:
            assert not any("clock jumped" in w for w in service.stats.warnings), at * 1e-9
    assert service.px4_stamps.rtt_discarded >= 10 + 12 + 25 + 50  # the stalls' late answers
    assert jumped_at_ns is not None and service.px4_stamps.resets == 1
    assert before_stalls and service.sync.resets == 1  # ours followed the jump too
    first_answer_after_jump_ns = 10**9 + 3_000_000 + 100_000_000 * 320  # 33.003 s
    assert 0 <= jumped_at_ns - first_answer_after_jump_ns < 500_000_000, jumped_at_ns
    assert sum("clock jumped" in w for w in service.stats.warnings) == 1
    report = service.summary()
    assert report["px4_timesync_resets"] == 1


def test_the_heartbeat_says_who_flies_and_other_systems_are_dropped(tmp_path) -> None:
    """HEARTBEAT.autopilot sets the kind the service branches on (PX4, ArduPilot, other) and
    the name it shows; a message of another system id is counted and changes nothing."""
    from peers import service_config
    from pymavlink.dialects.v20 import common as mavlink

    from companion.service.app import Service

    service = Service(service_config(tmp_path))
    session, stats = service.session, service.stats
    assert stats.autopilot_kind is AutopilotKind.NONE

    def heartbeat(system_id: int, autopilot: int) -> None:
        peer = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=1)
        msg = peer.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, autopilot, 0, 0, 0)
        session.on_message(decode(msg.pack(peer)), 5_000)

    for autopilot, kind, name in (
        (mavlink.MAV_AUTOPILOT_PX4, AutopilotKind.PX4, "PX4"),
        (mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, AutopilotKind.ARDUPILOT, "ArduPilot"),
        (mavlink.MAV_AUTOPILOT_GENERIC, AutopilotKind.OTHER, "generic"),
    ):
        heartbeat(1, autopilot)
        assert (stats.autopilot_kind, stats.autopilot) == (kind, name)
    assert stats.autopilot_heartbeat_ns == 5_000 and stats.foreign_messages == 0
    heartbeat(2, mavlink.MAV_AUTOPILOT_PX4)  # another vehicle's
    assert stats.autopilot_kind is AutopilotKind.OTHER and stats.foreign_messages == 1
    heartbeat(1, mavlink.MAV_AUTOPILOT_INVALID)  # a ground station's or a companion's
    assert stats.autopilot_kind is AutopilotKind.OTHER


def test_gps_is_asked_for_and_read_only_with_gps_align(tmp_path) -> None:
    """[gps] align off: GPS_RAW_INT is neither asked for nor parsed, nothing of the GPS frame
    exists. On: asked for at 5 Hz (and its origin at 1 Hz), fed to the GPS frame; a fix out of
    range is counted and dropped, another component's ignored, a NaN attitude gives no yaw;
    the autopilot's yaw and its PARAM_VALUE reach the frame and its actions."""
    import struct

    from peers import service_config
    from pymavlink.dialects.v20 import common as mavlink

    from companion.service.app import Service
    from companion.service.autopilot_requests import MSG_ID_GPS_RAW_INT

    (tmp_path / "off").mkdir()
    (tmp_path / "on").mkdir()
    off = Service(service_config(tmp_path / "off"))
    off.stats.autopilot_kind = AutopilotKind.PX4
    assert off.gps is None and off.publisher.gps is None
    assert MSG_ID_GPS_RAW_INT not in off.rates.wanted()
    assert "GPS_RAW_INT" not in off.session._handlers

    service = Service(service_config(tmp_path / "on", {"gps": {"align": True, "handover": "px4"}}))
    service.stats.autopilot_kind = AutopilotKind.PX4
    assert service.rates.wanted()[MSG_ID_GPS_RAW_INT] == 5.0
    gps = service.gps
    assert gps is not None and service.publisher.gps is gps
    px4 = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    other = mavlink.MAVLink(None, srcSystem=1, srcComponent=154)  # a camera's component

    def feed(peer: object, msg: object, rx_ns: int = 1_000_000) -> None:
        service.session.on_message(decode(msg.pack(peer)), rx_ns)

    feed(px4, px4.gps_global_origin_encode(473977420, 85455940, 488000, 0))
    feed(px4, px4.gps_raw_int_encode(0, 3, 473977420, 85455940, 488000, 90, 0, 0, 0, 12))
    feed(px4, px4.gps_raw_int_encode(0, 3, 950000000, 85455940, 488000, 90, 0, 0, 0, 12))
    feed(other, other.gps_raw_int_encode(0, 3, 473977420, 85455940, 488000, 90, 0, 0, 0, 12))
    feed(px4, px4.attitude_encode(10, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0))
    st = gps.status()["gps"]
    assert (st["fixes"], st["dropped"], st["origin"]) == (1, 1, True)
    assert len(gps.pending) == 1 and len(gps.yaws) == 1 and gps.yaws[0][1] == 0.5
    with_nan = mavlink.MAVLink_attitude_message(10, float("nan"), 0.0, 0.0, 0.0, 0.0, 0.0)
    feed(px4, with_nan)  # refused by the attitude check: no yaw fed
    assert len(gps.yaws) == 1
    service.gps.actions.on_loss()
    value = struct.unpack("<f", struct.pack("<i", 0))[0]
    feed(px4, px4.param_value_encode(b"EKF2_GPS_CTRL", value, 6, 900, 12))
    assert gps.status()["handover"] == [
        {"what": "EKF2_GPS_CTRL 0", "tries": 1, "result": "acknowledged"}
    ]
