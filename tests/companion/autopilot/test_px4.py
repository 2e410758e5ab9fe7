"""``companion px4 check | configure`` against the SITL autopilot, through MAVSDK, on 127.0.0.1.

The stub (``sitl/stub/autopilot.py`` with ``sitl/stub/px4_*.py`` and ``ekf_fusion.py``) serves PX4's
parameter protocol, its MAVLink shell and an emulated EKF2 vision fusion on a ground-station
endpoint; check and configure reach it with MAVSDK exactly as they reach a real PX4. A fake
companion (our MAVLink link and message encoders, answering TIMESYNC as the service does)
sends ODOMETRY / VISION_POSITION_ESTIMATE with one thing right or wrong at a time. No mocks.
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
import pytest
from peers import free_port
from pymavlink.dialects.v20 import common as mavlink

from companion import cli
from companion.config import Config, load_config
from companion.drivers import messages
from companion.drivers.mavlink import MavlinkLink
from companion.drivers.timesync import reply_for
from companion.errors import Px4Error
from companion.geometry import so3
from companion.px4.check import CheckReport, run_check
from companion.px4.configure import run_configure
from companion.px4.encoding import float32_bits_as_int32, int32_bits_as_float32
from companion.px4.link import Px4Link
from companion.px4.options import Px4Options
from companion.px4.rules import Row, Status
from companion.sitl.stub.autopilot import SimAutopilot
from companion.sitl.stub.options import AutopilotOptions
from companion.sitl.stub.px4_params import MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32
from companion.types import PoseEstimate

WATCH_S = 2.0
CONFIGURED = {  # what configure writes on the stub's PX4 v1.14 defaults (ODOMETRY output)
    "EKF2_EV_CTRL": 7,  # position, height, velocity; no yaw: the stub has a magnetometer
    "EKF2_HGT_REF": 3,
}


@dataclass
class Sitl:
    """A running stub and the config of a companion wired to it."""

    stub: SimAutopilot
    cfg: Config
    gcs_url: str  # MAVSDK's ground-station link

    def options(self, **kw: Any) -> Px4Options:
        base: dict[str, Any] = {"url": self.gcs_url, "timeout_s": 8.0, "watch_s": WATCH_S}
        base.update(kw)
        return Px4Options(**base)


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


def row(report: CheckReport, name: str) -> Row:
    return next(r for r in report.rows if r.name == name)


def set_params(stub: SimAutopilot, values: dict[str, int | float]) -> None:
    """The autopilot's own configuration before a test (as if set from its console)."""
    for name, value in values.items():
        stub.px4.params.set(name, value)


def param_set(port: int, name: str, wire_value: float, param_type: int) -> None:
    """PARAM_SET from another tool (pymavlink, as a script would send it) to the stub."""
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    msg = mav.param_set_encode(1, 1, name.encode(), wire_value, param_type)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(msg.pack(mav), ("127.0.0.1", port))


async def until(cond: Any, timeout_s: float = 3.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not cond():
            await asyncio.sleep(0.02)


# ---------------------------------------------------------------------------------------------
# parameters
# ---------------------------------------------------------------------------------------------


@pytest.mark.timeout(60)
def test_parameters_through_mavsdk_and_float_encoded_ints(tmp_path: Path) -> None:
    async def scenario() -> None:
        async with sitl(tmp_path) as s:
            store = s.stub.px4.params
            from companion.px4.rules import LinkContext, evaluate

            # the whole list, with PX4's types, through MAVSDK's param plugin
            async with Px4Link(s.gcs_url, 8.0) as px4:
                params = await px4.params()
                assert len(params) == len(store) >= 90
                for name, p in params.items():
                    assert p.is_int == (store.type_of(name) == MAV_PARAM_TYPE_INT32), name
                    assert p.value == pytest.approx(store.get(name), rel=1e-6), name

            # PX4 v1.14's default (the stub's) EKF2_EV_CTRL = 15 fuses our ODOMETRY yaw, which
            # never aligns EKF2's heading (the real PX4 refuses to arm): 7 is written instead
            v114 = {r.name: r for r in evaluate(params, LinkContext("odometry"))}
            ev = v114["EKF2_EV_CTRL"]
            assert ev.status is Status.FAIL and "never aligns" in ev.why
            assert ev.targets[0].value == 7
            # PX4 v1.16's default, 0: EKF2 is not told to use vision at all
            set_params(s.stub, {"EKF2_EV_CTRL": 0})
            fresh = await run_check(s.cfg, s.options(watch_s=0))
            assert row(fresh, "EKF2_EV_CTRL").status is Status.FAIL
            assert "ignores our horizontal position" in row(fresh, "EKF2_EV_CTRL").why
            assert fresh.problems >= 1
            # not watched: the GNSS height reference is a warning worded so, not a failure
            hgt = row(fresh, "EKF2_HGT_REF")
            assert hgt.status is Status.WARN and "not watched" in hgt.why

            # a script writes EKF2_EV_CTRL = 3 the C-cast way (the float 3.0, typed INT32):
            # PX4 keeps the float's bytes as an integer
            param_set(s.stub.opts.gcs_listen_port, "EKF2_EV_CTRL", 3.0, MAV_PARAM_TYPE_INT32)
            await until(lambda: store.get("EKF2_EV_CTRL") != 0)
            assert store.get("EKF2_EV_CTRL") == 1077936128 == float32_bits_as_int32(3.0)
            # a float typed as REAL32 into an INT32 is refused (current PX4: the types must match)
            param_set(s.stub.opts.gcs_listen_port, "EKF2_EV_QMIN", 20.0, MAV_PARAM_TYPE_REAL32)
            # an integer's bytes typed REAL32 into a float parameter: 5 -> 7e-45
            param_set(
                s.stub.opts.gcs_listen_port,
                "EKF2_EV_DELAY",
                int32_bits_as_float32(5),
                MAV_PARAM_TYPE_REAL32,
            )
            await until(lambda: store.get("EKF2_EV_DELAY") != 0.0)
            assert store.get("EKF2_EV_QMIN") == 0

            report = await run_check(s.cfg, s.options(watch_s=0))
            ev = row(report, "EKF2_EV_CTRL")
            assert ev.value == "1077936128" and ev.status is Status.FAIL
            assert "float-encoded" in ev.why and "float 3" in ev.why
            assert ev.targets and ev.targets[0].is_int and ev.targets[0].value == 7
            delay = row(report, "EKF2_EV_DELAY")
            assert delay.status is Status.FAIL and "int-encoded" in delay.why
            # configure restores what the tool meant (5 ms is acceptable), as a REAL32
            assert delay.targets[0].value == 5.0 and not delay.targets[0].is_int
            assert row(report, "EKF2_EV_QMIN").status is Status.OK

    asyncio.run(scenario())


@pytest.mark.timeout(60)
def test_configure_fixes_a_float_encoded_ev_ctrl_with_typed_writes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    async def scenario() -> None:
        async with sitl(tmp_path) as s:
            store = s.stub.px4.params
            param_set(s.stub.opts.gcs_listen_port, "EKF2_EV_CTRL", 3.0, MAV_PARAM_TYPE_INT32)
            await until(lambda: store.get("EKF2_EV_CTRL") == 1077936128)
            argv = ["--config", str(write_toml(tmp_path, s.cfg)), "--url", s.gcs_url]
            check_argv = ["px4", "check", *argv, "--watch-s", "0"]
            assert await asyncio.to_thread(cli.main, check_argv) == 1

            asked: list[str] = []
            declined = await run_configure(
                s.cfg, s.options(), confirm=lambda q: asked.append(q) or False, show=print
            )
            assert asked and not declined.written
            assert store.get("EKF2_EV_CTRL") == 1077936128  # nothing written without a yes

            report = await run_configure(s.cfg, s.options(yes=True), show=print)
            assert report.written and report.problems == 0
            changed = {c.target.name: c for c in report.changes}
            assert set(changed) == set(CONFIGURED)
            for name, value in CONFIGURED.items():
                c = changed[name]
                assert c.ok and c.after == value and c.target.is_int
                assert store.get(name) == value and isinstance(store.get(name), int)
            assert changed["EKF2_EV_CTRL"].before == 1077936128
            assert changed["EKF2_HGT_REF"].target.reboot
            assert not changed["EKF2_EV_CTRL"].target.reboot

            assert await asyncio.to_thread(cli.main, check_argv) == 0

    asyncio.run(scenario())
    out = capsys.readouterr().out
    assert "EKF2_EV_CTRL  INT32   1077936128 -> 7" in out
    assert "result: OK" in out


def write_toml(tmp: Path, cfg: Config) -> Path:
    """The [service] part of cfg as a TOML file for the CLI."""
    svc = cfg.service
    path = tmp / "companion.toml"
    path.write_text(
        "[service]\n"
        f'mavlink_url = "{svc.mavlink_url}"\n'
        f'output = "{svc.output}"\n'
        f'status_socket = "{svc.status_socket}"\n'
    )
    return path


@pytest.mark.timeout(60)
def test_configure_refuses_while_armed(tmp_path: Path) -> None:
    async def scenario() -> int:
        async with sitl(tmp_path, armed=True) as s:
            with pytest.raises(Px4Error, match="armed"):
                await run_configure(s.cfg, s.options(yes=True), show=print)
            argv = ["px4", "configure", "--config", str(write_toml(tmp_path, s.cfg))]
            code = await asyncio.to_thread(cli.main, [*argv, "--url", s.gcs_url, "--yes"])
            assert s.stub.px4.params.get("EKF2_EV_CTRL") == 15  # untouched (v1.14 default)
            assert s.stub.px4.params.sets_accepted == 0
            return code

    assert asyncio.run(scenario()) == 1


@pytest.mark.timeout(60)
def test_configure_reports_a_write_the_autopilot_did_not_keep(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The autopilot keeps EKF2_HGT_REF inside 0..2 (as a module constraining a parameter after
    the write would): the value read back from it differs, configure says so and exits 1."""

    async def scenario() -> int:
        async with sitl(tmp_path) as s:
            store = s.stub.px4.params
            store.clamp["EKF2_HGT_REF"] = (0, 2)
            argv = ["px4", "configure", "--config", str(write_toml(tmp_path, s.cfg))]
            code = await asyncio.to_thread(cli.main, [*argv, "--url", s.gcs_url, "--yes"])
            assert store.get("EKF2_HGT_REF") == 2 and store.sets_accepted >= 1
            return code

    assert asyncio.run(scenario()) == 1
    out = capsys.readouterr().out
    assert "EKF2_HGT_REF  INT32   1 -> 3" in out
    assert "EKF2_HGT_REF: 2 (INT32) MISMATCH: wrote 3" in out
    assert "result: 1 problem(s)" in out


# ---------------------------------------------------------------------------------------------
# fusion
# ---------------------------------------------------------------------------------------------

FUSION_CASES = {
    # name: (service.output, sender, extra autopilot params, fused, most likely reason)
    "odometry_frd_30hz": ("odometry", Sender(), {}, True, None),
    "vpe_with_magnetometer": ("vision_position_estimate", Sender(kind="vpe"), {}, True, None),
    "rate_too_low": ("odometry", Sender(rate_hz=3.0), {}, False, "rate too low"),
    "wrong_frame": (
        "odometry",
        Sender(frame_id=messages.MAV_FRAME_BODY_FRD),
        {},
        False,
        "wrong frame",
    ),
    "mocap_estimator_type": (
        "odometry",
        Sender(estimator_type=mavlink.MAV_ESTIMATOR_TYPE_MOCAP),
        {},
        False,
        "wrong estimator_type",
    ),
    "stale_timestamps": (
        "odometry",
        Sender(stamp_offset_us=-600_000),
        {},
        False,
        "stale timestamps",
    ),
    # ahead of PX4's clock: EKF2 holds them until its delayed horizon gets there (a warning)
    "future_timestamps_fused_late": ("odometry", Sender(stamp_offset_us=150_000), {}, True, None),
    "vpe_without_north_heading": (
        "vision_position_estimate",
        Sender(kind="vpe"),
        {"EKF2_MAG_TYPE": 5, "EKF2_EV_CTRL": 3},
        False,
        "no north-aligned heading",
    ),
}


@pytest.mark.timeout(60)
@pytest.mark.parametrize("case", list(FUSION_CASES))
def test_fusion_reported_only_when_our_output_meets_the_rules(tmp_path: Path, case: str) -> None:
    output, sender, extra, fused, reason = FUSION_CASES[case]

    async def scenario() -> tuple[CheckReport, SimAutopilot]:
        async with sitl(tmp_path, output=output) as s:
            set_params(s.stub, {**CONFIGURED, **extra})
            async with companion(s.stub.opts.companion_port, sender):
                await until(lambda: s.stub.sync.converged, 5.0)  # PX4 converts our stamps
                await asyncio.sleep(1.0)  # fusion starts, or stops after 400 ms, and settles
                return await run_check(s.cfg, s.options()), s.stub

    report, stub = asyncio.run(scenario())
    v = report.verdict
    assert v is not None
    text = "\n".join([v.headline, *v.reasons, *v.warnings, *v.evidence])
    assert v.fused is fused, text
    assert stub.px4.ekf.flags["ev_pos"] is fused, text  # the stub's own state agrees
    if fused:
        assert report.problems == 0, text
        assert not v.reasons
        assert "LOCAL_POSITION_NED" in text and " 0 LOCAL_POSITION_NED" not in text
    else:
        assert report.problems >= 1
        assert v.reasons and reason in v.reasons[0], text
    if case == "future_timestamps_fused_late":
        assert any("fused late by" in w for w in v.warnings), text
    if case == "vpe_without_north_heading":
        ev = row(report, "EKF2_EV_CTRL")
        assert ev.status is Status.FAIL and ev.targets[0].value == 11, ev


@pytest.mark.timeout(60)
def test_the_stubs_timesync_is_a_stream_whose_rate_is_set_as_px4s(tmp_path: Path) -> None:
    """PX4 sends its TIMESYNC requests as a stream (10 Hz on an onboard link) and answers
    MAV_CMD_SET_MESSAGE_INTERVAL for it as for any stream (MavlinkReceiver::set_message_interval):
    ACCEPTED, the interval [us] setting the rate, 0 its default, < 0 stopping it; FAILED for
    HEARTBEAT or a message it does not stream. The stub does the same, so the service's ask
    (service.px4_timesync_rate_hz, 50 Hz) gives it ~500 answers in ~10 s, not ~50 s, as PX4."""
    requests: list[int] = []  # reception times [ns] of the stub's TIMESYNC requests
    acks: list[int] = []
    link: MavlinkLink

    def on_message(msg: Any, rx_ns: int) -> None:
        if msg.get_type() == "TIMESYNC" and msg.tc1 == 0:
            requests.append(rx_ns)
            link.send(link.mav.timesync_encode(time.monotonic_ns(), msg.ts1))
        elif msg.get_type() == "COMMAND_ACK" and msg.command == 511:
            acks.append(int(msg.result))

    async def rate_over(seconds: float) -> float:
        await asyncio.sleep(0.3)  # the new rate acts from the next request
        start = len(requests)
        await asyncio.sleep(seconds)
        return (len(requests) - start) / seconds

    async def ask(msg_id: int, interval_us: float) -> int:
        n = len(acks)
        link.send(link.mav.command_long_encode(1, 1, 511, 0, msg_id, interval_us, 0, 0, 0, 0, 0))
        await until(lambda: len(acks) > n)
        return acks[n]

    async def scenario() -> dict[str, Any]:
        nonlocal link
        got: dict[str, Any] = {}
        async with sitl(tmp_path) as s:
            link = MavlinkLink(f"udpin:127.0.0.1:{s.stub.opts.companion_port}", 1, 197, on_message)
            async with link:
                got["default_hz"] = await rate_over(1.5)
                got["ack_50"] = await ask(messages.MSG_ID_TIMESYNC, 20_000)
                got["fast_hz"] = await rate_over(1.5)
                got["ack_stop"] = await ask(messages.MSG_ID_TIMESYNC, -1)
                got["stopped_hz"] = await rate_over(1.0)
                got["ack_default"] = await ask(messages.MSG_ID_TIMESYNC, 0)
                got["back_hz"] = await rate_over(1.5)
                got["ack_heartbeat"] = await ask(0, 20_000)
                got["ack_unstreamed"] = await ask(messages.MSG_ID_SCALED_IMU, 20_000)
                got["rates_hz"] = dict(s.stub.rates_hz)
                got["answers"] = s.stub.sync.samples
        return got

    got = asyncio.run(scenario())
    accepted, failed = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_FAILED
    assert got["ack_50"] == got["ack_stop"] == got["ack_default"] == accepted, got
    assert got["ack_heartbeat"] == got["ack_unstreamed"] == failed, got
    # the request rates (an asyncio timer: a loaded machine may lag, never run ahead)
    assert 7.0 <= got["default_hz"] <= 11.0, got
    assert 35.0 <= got["fast_hz"] <= 52.0, got
    assert got["stopped_hz"] == 0.0, got
    assert 7.0 <= got["back_hz"] <= 11.0, got
    assert got["rates_hz"][messages.MSG_ID_TIMESYNC] == 10.0
    assert got["answers"] >= 60, got  # each answer fed the stub's time sync


# ---------------------------------------------------------------------------------------------
# the pure parts: encoding, PX4 shell output, rules, diagnosis
# ---------------------------------------------------------------------------------------------


def test_float_and_int_encodings_are_inverse_and_detected() -> None:
    from companion.px4.encoding import float_encoded_int, int_encoded_float

    for v in (0, 1, 3, 15, 921600, -1, 2**31 - 1):
        assert float32_bits_as_int32(int32_bits_as_float32(v)) == v
    assert float_encoded_int(1077936128, 0, 15) == 3.0  # the EKF2_EV_CTRL trap
    assert float_encoded_int(0x49610000, 0, 3_000_000) == 921600.0  # SER_TELn_BAUD
    assert float_encoded_int(3, 0, 15) is None  # a fine value
    assert float_encoded_int(99, 0, 15) is None  # out of range, but not a float's bytes
    assert int_encoded_float(int32_bits_as_float32(5)) == 5
    assert int_encoded_float(0.1) is None and int_encoded_float(0.0) is None


# ``listener`` output as PX4 prints it (uORB's orb_print_message_internal): the timestamp with
# "(x seconds ago)", timestamp_sample with "(N us before timestamp)", a device_id with its
# decoded type, a quaternion followed by its Euler angles, a flags field with its bits
PX4_LISTENER = (
    "listener vehicle_visual_odometry\r\n\n"
    "TOPIC: vehicle_visual_odometry\n"
    " vehicle_visual_odometry\n"
    "    timestamp: 71100704 (0.004519 seconds ago)\n"
    "    timestamp_sample: 71090001 (10703 us before timestamp)\n"
    "    device_id: 8682243 (Type: 0x84, UAVCAN:0 (0x7B))\n"
    "    position: [1.20000, -0.40000, nan]\n"
    "    q: [0.70697, 0.00669, -0.00373, 0.70720] (Roll: 0.2 deg, Pitch: -0.8 deg, Yaw: 90.0 deg)\n"
    "    pose_frame: 2\n"
    "    quality: 80\n"
    "    reset_counter: 0\n"
    " \x1b[Knsh> "
)
PX4_FLAGS = (
    "listener estimator_status_flags\n\n"
    "TOPIC: estimator_status_flags 2 instances\n\n"
    "Instance 0:\n"
    " estimator_status_flags\n"
    "    timestamp: 191878100 (0.000580 seconds ago)\n"
    "    control_status_changes: 12\n"
    "    filter_fault_flags: 0\n"
    "    innovation_fault_flags: 6 (0b110)\n"
    "    cs_tilt_align: True\n"
    "    cs_yaw_align: True\n"
    "    cs_ev_pos: True\n\n"
    "Instance 1:\n"
    " estimator_status_flags\n"
    "    timestamp: 191878000 (0.000680 seconds ago)\n"
    "    cs_ev_pos: False\n"
    "nsh> "
)


def test_px4_shell_output_is_parsed_as_px4_prints_it() -> None:
    from companion.drivers.px4_shell_text import number, parse_listener, parse_uorb_top
    from companion.px4.fusion import sample_age_ms

    f = parse_listener(PX4_LISTENER)
    assert f is not None
    assert f["timestamp"] == 71100704 and f["timestamp_age_s"] == pytest.approx(0.004519)
    assert f["timestamp_sample"] == 71090001
    assert f["timestamp_sample_before_timestamp_us"] == 10703
    assert sample_age_ms(f) == pytest.approx(10.703)
    assert f["device_id"] == 8682243  # the leading integer of "N (Type: ...)"
    assert f["q"] == pytest.approx([0.70697, 0.00669, -0.00373, 0.70720])
    assert f["position"][:2] == [1.2, -0.4] and np.isnan(f["position"][2])
    assert f["pose_frame"] == 2 and f["quality"] == 80
    flags = parse_listener(PX4_FLAGS)
    assert flags is not None and flags["_instances"] == 2
    assert flags["cs_ev_pos"] is True and flags["innovation_fault_flags"] == 6  # instance 0
    # a sample stamped ahead of PX4's clock: PX4 prints a negative difference
    ahead = parse_listener(
        "TOPIC: vehicle_visual_odometry\n vehicle_visual_odometry\n"
        "    timestamp: 5000000 (0.010000 seconds ago)\n"
        "    timestamp_sample: 5150000 (-150000 us before timestamp)\nnsh> "
    )
    assert sample_age_ms(ahead) == pytest.approx(-150.0)
    # what it cannot read stays text, and counts as unknown
    odd = parse_listener(
        "TOPIC: vehicle_visual_odometry\n vehicle_visual_odometry\n"
        "    timestamp: soon (later)\n    timestamp_sample: 12 (mystery)\n"
        '    name: "a (b)"\nnsh> '
    )
    assert odd is not None and odd["name"] == "a (b)"
    assert number(odd, "timestamp") is None and sample_age_ms(odd) is None
    assert parse_listener("listener timesync_status\nnever published\nnsh> ") is None
    assert parse_listener("listener timesync_status\nnsh> ") is None  # no instance at all
    top = (
        "update: 1s, topics: 2, total publications: 31, 3.4 kB/s\n"
        "TOPIC NAME                          INST #SUB RATE #Q SIZE\n"
        "vehicle_visual_odometry                0    2   29  1  112\n"
        "vehicle_mocap_odometry                 0    1    0  1  112\nnsh> "
    )
    assert parse_uorb_top(top) == {"vehicle_visual_odometry": 29.0, "vehicle_mocap_odometry": 0.0}


def test_the_stub_prints_listener_output_in_px4s_format() -> None:
    from companion.drivers.px4_shell_text import parse_listener
    from companion.px4.fusion import sample_age_ms
    from companion.sitl.stub.ekf_fusion import Topic
    from companion.sitl.stub.px4_shell import format_listener

    t = Topic("vehicle_visual_odometry", "vehicle_odometry")
    q = (0.70710678, 0.0, 0.0, 0.70710678)
    t.publish({"timestamp": 2_000_000, "timestamp_sample": 1_990_000, "q": q}, 2_000_000)
    text = format_listener(t, t.name, 2_004_519)
    assert "    timestamp: 2000000 (0.004519 seconds ago)\n" in text
    assert "    timestamp_sample: 1990000 (10000 us before timestamp)\n" in text
    assert "(Roll: 0.0 deg, Pitch: 0.0 deg, Yaw: 90.0 deg)" in text
    assert text.startswith("\nTOPIC: vehicle_visual_odometry\n vehicle_visual_odometry\n")
    f = parse_listener(text)
    assert f is not None and sample_age_ms(f) == pytest.approx(10.0)


def _rows(params: dict[str, int | float], ctx: Any) -> dict[str, Row]:
    from companion.px4.rules import Param, evaluate

    typed = {k: Param(k, v, isinstance(v, int)) for k, v in params.items()}
    return {r.name: r for r in evaluate(typed, ctx)}


def test_ev_ctrl_bits_as_ekf2_reads_them() -> None:
    from companion.px4.rules import LinkContext

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
    from companion.px4.rules import LinkContext

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
    from companion.px4.rules import LinkContext

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
    from companion.px4.rules import LinkContext

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
    from companion.px4.rules import LinkContext

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


def _shell(**kw: Any) -> Any:
    from companion.px4.fusion import ShellView

    visual = {
        "timestamp": 10_000_000,
        "timestamp_age_s": 0.01,
        "timestamp_sample": 9_990_000,
        "pose_frame": 2,
        "position": [1.0, 2.0, -3.0],
        "quality": 80,
    }
    flags = {"timestamp_age_s": 0.01, "cs_ev_pos": True, "cs_yaw_align": True}
    timesync = {"timestamp_age_s": 0.05, "round_trip_time": 900}
    base: dict[str, Any] = {
        "visual": visual,
        "flags": flags,
        "timesync": timesync,
        "rates_hz": {"vehicle_visual_odometry": 30.0},
    }
    for k, v in kw.items():
        merge = isinstance(v, dict) and k in ("visual", "flags", "timesync")
        base[k] = {**base[k], **v} if merge else v
    return ShellView(**base)


def test_diagnosis_from_px4s_shell() -> None:
    from companion.px4.fusion import Observations, diagnose
    from companion.px4.rules import LinkContext, Param

    params = {"EKF2_EV_CTRL": Param("EKF2_EV_CTRL", 7, True)}
    ctx = LinkContext("odometry")

    def verdict(**kw: Any) -> Any:
        return diagnose(
            Observations(watch_s=2.0, local_positions=20, shell=_shell(**kw)), params, ctx
        )

    fused = verdict()
    assert fused.fused is True and not fused.reasons
    # stamps 150 ms ahead: held until the delayed horizon reaches them, fused late; a warning
    late = verdict(visual={"timestamp_sample": 10_150_000})
    assert late.fused is True and not late.reasons
    assert any("fused late by 150 ms" in w for w in late.warnings)
    # 900 ms ahead: the 20-sample buffer (667 ms at 30 Hz) overwrites them first
    lost = verdict(visual={"timestamp_sample": 10_900_000}, flags={"cs_ev_pos": False})
    assert lost.fused is False and "lost" in lost.reasons[0]
    # a fused verdict never comes with a "most likely" reason: the slow rate is a warning
    slow = verdict(rates_hz={"vehicle_visual_odometry": 4.0})
    assert slow.fused is True and not slow.reasons and any("rate" in w for w in slow.warnings)
    # the shell answered but the flags did not come through: unknown, not "off"
    assert verdict(flags=None).fused is None
    assert verdict(flags={"cs_ev_pos": "?"}).fused is None
    # fusion active, but EKF2 rejects our samples at the gate
    aid = {"timestamp_age_s": 0.02, "fused": False, "innovation_rejected": True}
    rejected = verdict(aid_pos=aid)
    assert rejected.fused is False and "rejected at EKF2_EVP_GATE" in rejected.reasons[0]
    assert verdict(aid_pos={**aid, "fused": True, "innovation_rejected": False}).fused is True
    # EKF2 marks a sample below EKF2_EV_QMIN rejected too: named as such, not as the gate
    strict = {**params, "EKF2_EV_QMIN": Param("EKF2_EV_QMIN", 90, True)}
    obs = Observations(watch_s=2.0, local_positions=20, shell=_shell(aid_pos=aid))
    low = diagnose(obs, strict, ctx)
    assert low.fused is False and "EKF2_EV_QMIN" in low.reasons[0] and len(low.reasons) == 1
    # non-numeric fields are unknown, never a crash
    odd = verdict(visual={"timestamp": "x", "quality": "y"}, timesync={"round_trip_time": "z"})
    assert odd.fused is True and any("timestamp_sample" in w for w in odd.warnings)


def test_without_a_shell_fusion_is_inferred_only_when_nothing_else_can_aid() -> None:
    from companion.px4.fusion import Observations, diagnose
    from companion.px4.rules import LinkContext, Param

    params = {
        "EKF2_EV_CTRL": Param("EKF2_EV_CTRL", 11, True),
        "EKF2_GPS_CTRL": Param("EKF2_GPS_CTRL", 7, True),
        "EKF2_OF_CTRL": Param("EKF2_OF_CTRL", 0, True),
        "EKF2_NOAID_TOUT": Param("EKF2_NOAID_TOUT", 5_000_000, True),
    }
    ctx = LinkContext()
    publishing = {"output": {"message": "ODOMETRY", "rate_hz": 30.0, "published": 900}}
    all_along: dict[str, Any] = {
        "watch_s": 5.0,
        "estimator_flags": 0x12F,
        "local_positions": 50,
        "lpos_first_s": 0.1,
        "lpos_last_s": 4.95,
        "lpos_max_gap_s": 0.2,
        "service": publishing,
    }
    v = diagnose(Observations(**all_along), params, ctx)
    assert v.fused is True and "inferred" in v.headline
    cannot_tell: list[dict[str, Any]] = [
        {"gps_seen": True},  # GNSS may be what makes it valid
        {"service": None},  # nothing says we publish
        {"service": {"output": {"rate_hz": 0.0, "published": 0}}},  # we do not publish
        {"lpos_last_s": 2.0},  # the position stopped being valid during the watch
        {"watch_s": 2.0, "lpos_last_s": 1.95},  # shorter than EKF2_NOAID_TOUT: dead reckoning
    ]
    for change in cannot_tell:
        assert diagnose(Observations(**{**all_along, **change}), params, ctx).fused is None
    optical_flow = {**params, "EKF2_OF_CTRL": Param("EKF2_OF_CTRL", 1, True)}
    assert diagnose(Observations(**all_along), optical_flow, ctx).fused is None
    nothing = Observations(watch_s=2.0, estimator_flags=0x0A5, local_positions=0)
    v = diagnose(nothing, params, ctx)
    assert v.fused is False and "service is not running" in v.reasons[0]


def test_check_will_not_share_the_running_services_link(tmp_path: Path) -> None:
    """The service holds its MAVLink port: check asks for another link (exit 2), not a fight."""
    from companion.errors import ConfigError
    from companion.px4.check import resolve
    from companion.service.status import StatusServer

    sock = tmp_path / "status.sock"
    cfg = load_config(
        overrides={"service": {"mavlink_url": "udpin:127.0.0.1:14540", "status_socket": str(sock)}}
    )

    async def scenario() -> None:
        stopped = await asyncio.to_thread(resolve, cfg, Px4Options())
        assert stopped.url == "udpin://127.0.0.1:14540"
        async with StatusServer(sock, lambda: {"output": {"rate_hz": 30.0}}):
            with pytest.raises(ConfigError, match="running service holds"):
                await asyncio.to_thread(resolve, cfg, Px4Options())
            with pytest.raises(ConfigError):
                await asyncio.to_thread(resolve, cfg, Px4Options(url="udpin:127.0.0.1:14540"))
            gcs = await asyncio.to_thread(resolve, cfg, Px4Options(url="udpin:127.0.0.1:14550"))
            assert gcs.url == "udpin://127.0.0.1:14550" and gcs.ctx.fc_port == "ETHERNET"

    asyncio.run(scenario())


def test_delay_max_reaches_back_as_far_as_our_oldest_stamps() -> None:
    """EKF2_DELAY_MAX against how old our stamps can leave (service.stale_frame_ms plus the
    ODOMETRY centring), EKF2's horizon trailing by ~45 ms (the real PX4 measured 156 / 236 ms
    with 200 / 300): the default service (100 ms, no centring) is served by PX4's default 200;
    the PX4 loop's (200 ms and 3 poses centred at 20 Hz: 250 ms) needs 300, which configure
    writes (applied at a reboot). A parameter list without it gets no row."""
    from companion.config import load_config
    from companion.px4.rules import LinkContext

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
