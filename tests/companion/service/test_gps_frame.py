"""The service's GPS frame ([gps] align) fed a synthetic flight: our track in our own frame,
GPS fixes and the autopilot's heading in its frame (turned by 37 deg, moved by (5, -3, 0.4) m),
as the autopilot session and the publisher feed it.

What is asserted: the states go own -> aligning -> aligned -> held -> slewing -> aligned; the
output is the autopilot's frame within 0.45 m once aligned (the fixes' 0.3 m of noise per axis,
correlated over 1 s, averaged over 8-20 s windows: 0.19 m on average, 0.35 m at most with this
seed); between two outputs it never moves
more than 0.1 m/s x dt beyond our own motion (but at the first alignment, applied at once on
the ground with a new reset counter); a reset of our own frame during the denial leaves the
output continuous; the handover's PARAM_SET goes out at the loss and after the slew, retried
until PX4 echoes it; malformed fixes are counted and dropped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pytest
from peers.mavlink_peers import EncodingLink as FakeLink
from pymavlink.dialects.v20 import common as mavlink

from companion.config import load_config
from companion.geometry import so3
from companion.service.gps_actions import bytewise_int32
from companion.service.gps_frame import GpsFrame
from companion.service.runtime import Runtime
from companion.sitl.stub import gps as stub_gps
from companion.types import PoseEstimate

YAW = math.radians(37.0)
OFFSET = np.array([5.0, -3.0, 0.4])
RATE_HZ = 30.0


def vehicle(t_s: float) -> tuple[np.ndarray, float]:
    """Our frame's truth: a 12 m circle at 1 m/s, 5 m up; the heading along the track."""
    w = 1.0 / 12.0
    p = np.array([12.0 * math.cos(w * t_s), 12.0 * math.sin(w * t_s), -5.0])
    return p, math.atan2(math.cos(w * t_s), -math.sin(w * t_s))


def pose_at(t_us: int, p: np.ndarray, yaw: float, reset: int) -> PoseEstimate:
    q = so3.matrix_to_quat(so3.rot_z(yaw))
    cov = np.diag([0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-3])
    return PoseEstimate(t_us, p, q, np.zeros(3), cov, reset, 80)


@dataclass
class Flight:
    states: list[str] = field(default_factory=list)
    t_s: list[float] = field(default_factory=list)
    ours: list[np.ndarray] = field(default_factory=list)  # what we fed (our frame)
    out: list[np.ndarray] = field(default_factory=list)  # what went out
    ref: list[np.ndarray] = field(default_factory=list)  # the truth in the autopilot's frame
    resets: list[int] = field(default_factory=list)
    jumped: list[int] = field(default_factory=list)  # the poses that were the first of a jump
    sets: list[tuple[float, int]] = field(default_factory=list)  # (t [s], EKF2_GPS_CTRL) sent
    ap: list[np.ndarray] = field(default_factory=list)  # the autopilot's estimate (ap_lag_s)


def fly(
    seconds: float = 70.0,
    loss: tuple[float, float] = (30.0, 45.0),
    reset_at_s: float | None = None,
    echo: bool = True,
    gps: dict | None = None,
    ap_lag_s: float | None = None,
) -> tuple[GpsFrame, FakeLink, Flight]:
    """``ap_lag_s``: the autopilot's own estimate (LOCAL_POSITION_NED at 30 Hz) is the truth in
    its frame this late, as EKF2's was while it fused GNSS."""
    cfg = load_config(None, {"gps": {"align": True, "handover": "px4", **(gps or {})}})
    ardupilot = cfg.gps.handover == "ardupilot"
    rt = Runtime(cfg)
    now_ns = [0]
    rt.clock = lambda: now_ns[0]
    link = FakeLink()
    frame = GpsFrame(rt, link)
    rng = np.random.default_rng(7)
    noise = stub_gps.GpsNoise(0.3, 1.0, 3)
    lat0, lon0, alt0 = stub_gps.GPS_ORIGIN
    frame.on_origin(int(lat0 * 1e7), int(lon0 * 1e7), int(alt0 * 1e3))
    flight = Flight()
    drift = np.zeros(3)
    reset, jump = 0, np.zeros(3)
    n = int(seconds * RATE_HZ)
    for k in range(n):
        t = k / RATE_HZ
        t_us = int(t * 1e6)
        now_ns[0] = t_us * 1000
        truth, heading = vehicle(t)
        ref_truth = so3.rot_z(YAW) @ truth + OFFSET
        if k % 6 == 0:  # 5 Hz fixes, 3 Hz... the autopilot's heading with each
            lost = loss[0] <= t < loss[1]
            msg = stub_gps.gps_raw_int(link.mav, t_us, ref_truth, lost, noise.at(t))
            frame.on_gps_raw(msg, t_us)
            frame.on_attitude(t_us, heading + YAW + rng.normal(0, math.radians(1)))
        if loss[0] <= t < loss[1]:
            drift += np.array([0.02, -0.01, 0.0]) / RATE_HZ  # our VO drifts meanwhile
        if reset_at_s is not None and reset == 0 and t >= reset_at_s:
            reset, jump = 1, np.array([-7.0, 4.0, 0.0])  # a new frame: another origin
        ours = truth + drift + jump + rng.normal(0, 0.01, 3)
        if ap_lag_s is not None:
            ap = so3.rot_z(YAW) @ vehicle(t - ap_lag_s)[0] + OFFSET
            frame.lag.on_local_position(t_us, ap)
            flight.ap.append(ap)
        pose = frame.align(pose_at(t_us, ours, heading, reset))
        if echo:
            for m in link.sent:
                if m.get_type() == "PARAM_SET" and not getattr(m, "_echoed", False):
                    m._echoed = True
                    flight.sets.append((t, bytewise_int32(m.param_value)))
                    frame.actions.on_param_value("EKF2_GPS_CTRL", m.param_value)
                if m.get_type() == "COMMAND_LONG" and not getattr(m, "_echoed", False):
                    m._echoed = True
                    frame.actions.on_command_ack(int(m.command), 0)  # ACCEPTED
        frame.actions.tick()
        flight.states.append(frame.out.state)
        flight.t_s.append(t)
        flight.ours.append(ours)
        flight.out.append(pose.position_ned_m)
        flight.ref.append(ref_truth)
        flight.resets.append(pose.reset_counter)
        if frame.jumped:
            flight.jumped.append(k)
    assert ardupilot == (frame.actions.target() == "ardupilot")
    return frame, link, flight


def runs(states: list[str]) -> list[str]:
    return [s for i, s in enumerate(states) if i == 0 or states[i - 1] != s]


def test_a_loss_and_return_go_aligned_held_slewing_aligned_without_a_step() -> None:
    frame, link, f = fly(gps={"align_height": True})
    assert runs(f.states) == ["own", "aligning", "aligned", "held", "slewing", "aligned"], runs(
        f.states
    )
    out, ours, ref = np.array(f.out), np.array(f.ours), np.array(f.ref)
    t, resets = np.array(f.t_s), np.array(f.resets)
    states = np.array(f.states)
    aligned = states == "aligned"
    err = np.linalg.norm(out - ref, axis=1)
    first = int(np.argmax(aligned))
    before_loss = aligned & (t < 30.0)
    assert err[before_loss].max() < 0.45, err[before_loss].max()
    assert frame.status()["yaw_deg"] == pytest.approx(37.0, abs=1.5)
    # held: the drift of our track (0.02, -0.01 m/s) is all the error adds
    held = states == "held"
    assert err[held].max() < 0.45 + 15 * 0.023, err[held].max()
    assert err[-30:].max() < 0.45, err[-30:].max()  # slewed back onto the GPS
    # the first alignment is a jump with a new reset counter; nothing else jumps
    assert resets[first] == resets[first - 1] + 1 and resets[-1] == resets[first]
    assert f.jumped == [first]  # told to the publisher (its warning names the jump)
    step = np.linalg.norm(np.diff(out, axis=0), axis=1)
    own = np.linalg.norm(np.diff(ours, axis=0), axis=1)
    bound = 0.1 / RATE_HZ + own + 1e-9
    same = np.diff(resets) == 0
    assert np.all(step[same] <= bound[same]), (step - bound)[same].max()
    # the handover: 0 at the loss, 7 after the slew, each echoed
    sets = [bytewise_int32(m.param_value) for m in link.sent if m.get_type() == "PARAM_SET"]
    assert sets == [0, 7]
    assert [a["result"] for a in frame.status()["handover"]] == ["acknowledged"] * 2


def test_a_reset_of_our_frame_while_held_keeps_the_output_continuous() -> None:
    frame, _, f = fly(reset_at_s=36.0, gps={"align_height": True})
    assert frame.reanchors == 1
    out, ours, ref = np.array(f.out), np.array(f.ours), np.array(f.ref)
    t = np.array(f.t_s)
    k = int(np.argmax(t >= 36.0))
    assert f.states[k] == "held"
    # across the reset the output moves as the vehicle does (1 m/s), not by the 8 m jump
    assert np.linalg.norm(out[k] - out[k - 1]) < 1.0 / RATE_HZ + 0.05
    assert np.linalg.norm(ours[k] - ours[k - 1]) > 7.0
    held = np.array(f.states) == "held"
    err = np.linalg.norm(out - ref, axis=1)
    assert err[held].max() < 0.45 + 15 * 0.023 + 0.05, err[held].max()
    assert runs(f.states)[-1] == "aligned" and err[-30:].max() < 0.45


def test_without_align_height_the_height_stays_ours() -> None:
    frame, _, f = fly(seconds=25.0)
    assert runs(f.states)[-1] == "aligned"
    out, ours, ref = np.array(f.out), np.array(f.ours), np.array(f.ref)
    assert frame.handover.applied.translation_ned_m[2] == 0.0
    assert np.array_equal(out[:, 2], ours[:, 2])  # the yaw turns about z: z untouched
    horizontal = np.linalg.norm(out[-30:, :2] - ref[-30:, :2], axis=1)
    assert horizontal.max() < 0.45, horizontal.max()


@pytest.mark.parametrize("handover", ["ardupilot", "px4"])
def test_gps_that_appears_mid_flight_hands_ardupilot_from_ours_to_gps(handover: str) -> None:
    """Indoors (no fix for the first 25 s), then GPS: ArduPilot (set 1 = GPS) is told once to
    use ours (set 2) 5 s after our first pose, and set 1 once the GPS frame is found; PX4 is
    told nothing (it fuses GNSS beside ours once there is one)."""
    frame, link, flight = fly(seconds=50.0, loss=(0.0, 25.0), gps={"handover": handover})
    assert runs(flight.states)[:3] == ["own", "aligning", "aligned"]
    sets = [int(m.param1) for m in link.sent if m.get_type() == "COMMAND_LONG"]
    params = [m for m in link.sent if m.get_type() == "PARAM_SET"]
    if handover == "ardupilot":
        assert sets == [2, 1]
        assert [a["result"] for a in frame.status()["handover"]] == ["acknowledged"] * 2
        assert frame.told_no_gps
    else:
        assert sets == [] and params == []
        assert not frame.told_no_gps


def test_an_unanswered_action_is_retried_and_given_up() -> None:
    frame, link, _ = fly(seconds=40.0, echo=False)
    sets = [bytewise_int32(m.param_value) for m in link.sent if m.get_type() == "PARAM_SET"]
    assert sets == [0] * 5  # MAX_TRIES, a second apart
    status = frame.status()["handover"]
    assert status == [{"what": "EKF2_GPS_CTRL 0", "tries": 5, "result": "no answer"}]
    assert any("unanswered" in w for w in frame.rt.stats.warnings)


def test_malformed_fixes_and_origins_are_counted_and_dropped() -> None:
    cfg = load_config(None, {"gps": {"align": True}})
    rt = Runtime(cfg)
    frame = GpsFrame(rt, FakeLink())
    mav = mavlink.MAVLink(None)
    bad = [
        mav.gps_raw_int_encode(0, 3, 91 * 10**7, 0, 0, 90, 0, 0, 0, 12),  # latitude > 90
        mav.gps_raw_int_encode(0, 30, 0, 0, 0, 90, 0, 0, 0, 12),  # fix type 30
        mav.gps_raw_int_encode(0, 3, 0, 181 * 10**7, 0, 90, 0, 0, 0, 12),  # longitude
    ]
    for i, m in enumerate(bad):
        frame.on_gps_raw(m, i)

    class Nan:
        fix_type, lat, lon, alt, eph, satellites_visible = 3, float("nan"), 0, 0, 90, 12

    frame.on_gps_raw(Nan(), 5)
    frame.on_origin(95 * 10**7, 0, 0)
    frame.lag.on_local_position(6, np.array([1.0, np.inf, 0.0]))  # the autopilot's estimate too
    frame.lag.on_local_position(7, np.array([1.0, 2.0]))
    s = frame.status()
    assert s["gps"]["dropped"] == 5 and s["gps"]["fixes"] == 0 and not s["gps"]["origin"]
    assert s["autopilot_positions_dropped"] == 2 and not frame.lag.ap_positions
    assert s["state"] == "own" and not s["gps"]["good"]


def test_a_silent_receiver_is_a_loss_the_status_names() -> None:
    rt = Runtime(load_config(None, {"gps": {"align": True, "good_after_s": 1.0}}))
    frame = GpsFrame(rt, FakeLink())
    lat0, lon0, alt0 = stub_gps.GPS_ORIGIN
    frame.on_origin(int(lat0 * 1e7), int(lon0 * 1e7), int(alt0 * 1e3))
    for k in range(int(12.0 * RATE_HZ)):
        t_us = int(k / RATE_HZ * 1e6)
        p, yaw = vehicle(k / RATE_HZ)
        if k % 6 == 0 and k < 3 * RATE_HZ:  # fixes for 3 s, then none at all
            msg = stub_gps.gps_raw_int(frame.actions.link.mav, t_us, p, False, np.zeros(3))
            frame.on_gps_raw(msg, t_us)
        frame.align(pose_at(t_us, p, yaw, 0))
        if k == int(2.5 * RATE_HZ):
            assert frame.status()["gps"]["good"]
    gps = frame.status()["gps"]
    assert not gps["good"] and gps["reasons"][0].startswith("no GPS sample for 9.")
    assert frame.status()["state"] == "own"  # lost before an alignment


def test_the_origin_is_asked_for_until_it_arrives() -> None:
    """PX4 sends GPS_GLOBAL_ORIGIN only when its origin changes (one set at boot, before our
    rate request, never comes): MAV_CMD_REQUEST_MESSAGE 49 every 2 s until one arrives."""
    link = FakeLink()
    frame = GpsFrame(Runtime(load_config(None, {"gps": {"align": True}})), link)
    for k in range(int(7.0 * 5)):  # fixes at 5 Hz for 7 s, the origin at 5 s
        t_us = int(k / 5 * 1e6)
        if k == 25:
            lat0, lon0, alt0 = stub_gps.GPS_ORIGIN
            frame.on_origin(int(lat0 * 1e7), int(lon0 * 1e7), int(alt0 * 1e3))
        msg = stub_gps.gps_raw_int(link.mav, t_us, np.zeros(3), False, np.zeros(3))
        frame.on_gps_raw(msg, t_us)
    asks = [m for m in link.sent if m.get_type() == "COMMAND_LONG"]
    assert [(int(m.command), int(m.param1)) for m in asks] == [(512, 49)] * 3  # 0, 2, 4 s
    assert frame.status()["gps"]["origin_requests"] == 3 and frame.status()["gps"]["origin"]


@pytest.mark.parametrize("carry", [True, False])
def test_ekf2s_lag_is_carried_into_the_output_before_ekf2_stops_gnss(carry: bool) -> None:
    """EKF2 0.3 s behind (0.3 m at 1 m/s): at the loss the output lands on the autopilot's own
    estimate (EKF2, reset onto it 0.3 s later, stays where it was), EKF2_GPS_CTRL 0 waits
    0.3 s for those poses, and the lag goes out at the slew rate. Without the carry: the
    parameter at once, the output unmoved (EKF2 steps by its whole lag)."""
    frame, _, f = fly(ap_lag_s=0.3, gps={"px4_loss_carry": carry})
    assert runs(f.states) == ["own", "aligning", "aligned", "held", "slewing", "aligned"]
    out, ours, ap, t = np.array(f.out), np.array(f.ours), np.array(f.ap), np.array(f.t_s)
    k = f.states.index("held")
    lag = np.linalg.norm(ap[k - 1, :2] - out[k - 1, :2])
    assert 0.1 < lag < 0.8, lag  # the lag and the alignment's own error
    step = np.linalg.norm(out[k, :2] - out[k - 1, :2])
    own = np.linalg.norm(ours[k, :2] - ours[k - 1, :2])
    sets = [(when, value) for when, value in f.sets]
    assert [v for _, v in sets] == [0, 7]
    if carry:
        assert frame.lag.carried_m == pytest.approx(lag, abs=0.05)
        assert np.linalg.norm(ap[k, :2] - out[k, :2]) < 0.05  # EKF2's reset lands where it is
        assert sets[0][0] - t[k] == pytest.approx(0.3, abs=1.5 / RATE_HZ)
        assert frame.status()["carried_m"] == frame.lag.carried_m
    else:
        assert frame.lag.carried_m is None and step <= own + 0.1 / RATE_HZ + 1e-9
        assert sets[0][0] == t[k]
    # after the loss's step the output moves at most the slew rate beyond our own motion
    d_out = np.linalg.norm(np.diff(out[k:], axis=0), axis=1)
    d_ours = np.linalg.norm(np.diff(ours[k:], axis=0), axis=1)
    assert np.all(d_out <= d_ours + 0.1 / RATE_HZ + 1e-9)
