"""``companion px4 check | configure`` against the SITL autopilot, through MAVSDK, on 127.0.0.1.

The stub (``sitl/stub/autopilot.py`` with ``sitl/stub/px4_*.py`` and ``ekf_fusion.py``) serves PX4's
parameter protocol, its MAVLink shell and an emulated EKF2 vision fusion on a ground-station
endpoint; check and configure reach it with MAVSDK exactly as they reach a real PX4. A fake
companion (our MAVLink link and message encoders, answering TIMESYNC as the service does)
sends ODOMETRY / VISION_POSITION_ESTIMATE with one thing right or wrong at a time. No mocks.
"""

from __future__ import annotations

import asyncio
import socket
import time
from pathlib import Path
from typing import Any

import pytest
import tomli_w
from peers.px4_stub import Sender, companion, set_params, sitl, until
from pymavlink.dialects.v20 import common as mavlink

from companion import cli
from companion.autopilot.params import Row, Status
from companion.autopilot.px4.check import run_check
from companion.autopilot.px4.configure import run_configure
from companion.autopilot.px4.encoding import float32_bits_as_int32, int32_bits_as_float32
from companion.autopilot.px4.link import Px4Link
from companion.autopilot.px4.link_context import LinkContext
from companion.autopilot.report import CheckReport
from companion.config import Config
from companion.drivers import messages
from companion.drivers.mavlink import MavlinkLink
from companion.errors import AutopilotError
from companion.sitl.stub.autopilot import SimAutopilot
from companion.sitl.stub.px4_params import MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32

CONFIGURED = {  # what configure writes on the stub's PX4 v1.14 defaults (ODOMETRY output)
    "EKF2_EV_CTRL": 7,  # position, height, velocity; no yaw: the stub has a magnetometer
    "EKF2_HGT_REF": 3,
}


def row(report: CheckReport[LinkContext], name: str) -> Row:
    return next(r for r in report.rows if r.name == name)


def param_set(port: int, name: str, wire_value: float, param_type: int) -> None:
    """PARAM_SET from another tool (pymavlink, as a script would send it) to the stub."""
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    msg = mav.param_set_encode(1, 1, name.encode(), wire_value, param_type)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(msg.pack(mav), ("127.0.0.1", port))


# ---------------------------------------------------------------------------------------------
# parameters
# ---------------------------------------------------------------------------------------------


@pytest.mark.timeout(60)
def test_parameters_through_mavsdk_and_float_encoded_ints(tmp_path: Path) -> None:
    async def scenario() -> None:
        async with sitl(tmp_path) as s:
            store = s.stub.px4.params
            from companion.autopilot.px4.link_context import LinkContext
            from companion.autopilot.px4.rules import evaluate

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
    keys = {"mavlink_url": svc.mavlink_url, "output": svc.output}
    path = tmp / "companion.toml"
    path.write_text(tomli_w.dumps({"service": {**keys, "status_socket": svc.status_socket}}))
    return path


@pytest.mark.timeout(60)
def test_configure_refuses_while_armed(tmp_path: Path) -> None:
    async def scenario() -> int:
        async with sitl(tmp_path, armed=True) as s:
            with pytest.raises(AutopilotError, match="armed"):
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

    async def scenario() -> tuple[CheckReport[LinkContext], SimAutopilot]:
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
