"""``companion px4 check | configure`` against the SITL autopilot, through MAVSDK, on 127.0.0.1.

The stub (``sitl/autopilot.py`` with ``sitl/px4_*.py`` and ``sitl/ekf_fusion.py``) serves PX4's
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
from companion.errors import Px4Error
from companion.geometry import so3
from companion.px4.check import CheckReport, run_check
from companion.px4.configure import run_configure
from companion.px4.encoding import float32_bits_as_int32, int32_bits_as_float32
from companion.px4.link import Px4Link
from companion.px4.options import Px4Options
from companion.px4.rules import Row, Status
from companion.service.timesync import reply_for
from companion.types import PoseEstimate
from drivers import messages
from drivers.mavlink import MavlinkLink
from sitl.autopilot import AutopilotOptions, SimAutopilot
from sitl.px4_params import MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32

WATCH_S = 2.0
CONFIGURED = {  # what configure writes on the stub's PX4 defaults (ODOMETRY output)
    "EKF2_EV_CTRL": 15,
    "EKF2_HGT_REF": 3,
    "EKF2_GPS_CTRL": 0,
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
            # the whole list, with PX4's types, through MAVSDK's param plugin
            async with Px4Link(s.gcs_url, 8.0) as px4:
                params = await px4.params()
                assert len(params) == len(store) >= 90
                for name, p in params.items():
                    assert p.is_int == (store.type_of(name) == MAV_PARAM_TYPE_INT32), name
                    assert p.value == pytest.approx(store.get(name), rel=1e-6), name

            # PX4's defaults: EKF2 is not told to use vision at all
            fresh = await run_check(s.cfg, s.options(watch_s=0))
            assert row(fresh, "EKF2_EV_CTRL").status is Status.FAIL
            assert "ignores our horizontal position" in row(fresh, "EKF2_EV_CTRL").why
            assert fresh.problems >= 1

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
            assert ev.targets and ev.targets[0].is_int and ev.targets[0].value == 15
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
    assert "EKF2_EV_CTRL   INT32   1077936128 -> 15" in out
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
            assert s.stub.px4.params.get("EKF2_EV_CTRL") == 0  # untouched
            assert s.stub.px4.params.sets_accepted == 0
            return code

    assert asyncio.run(scenario()) == 1


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
    if case == "vpe_without_north_heading":
        assert row(report, "EKF2_MAG_TYPE").status is Status.FAIL


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


PX4_LISTENER = (
    "listener vehicle_visual_odometry\r\n\n"
    "TOPIC: vehicle_visual_odometry\n"
    " vehicle_odometry\n"
    "    timestamp: 71100704 (0.004519 seconds ago)\n"
    "    timestamp_sample: 71090001 (0.015222 seconds ago)\n"
    "    position: [1.2000, -0.4000, nan]\n"
    "    pose_frame: 2\n"
    "    quality: 80\n"
    "    cs_ev_pos: True\n"
    " \x1b[Knsh> "
)


def test_px4_shell_output_is_parsed_as_px4_prints_it() -> None:
    from companion.px4.shell import parse_listener, parse_uorb_top

    f = parse_listener(PX4_LISTENER)
    assert f is not None
    assert f["timestamp"] == 71100704 and f["timestamp_age_s"] == pytest.approx(0.004519)
    assert f["timestamp"] - f["timestamp_sample"] == 10703
    assert f["position"][:2] == [1.2, -0.4] and np.isnan(f["position"][2])
    assert f["pose_frame"] == 2 and f["quality"] == 80 and f["cs_ev_pos"] is True
    assert parse_listener("listener timesync_status\nnever published\nnsh> ") is None
    top = (
        "update: 1s, topics: 2, total publications: 31, 3.4 kB/s\n"
        "TOPIC NAME                          INST #SUB RATE #Q SIZE\n"
        "vehicle_visual_odometry                0    2   29  1  112\n"
        "vehicle_mocap_odometry                 0    1    0  1  112\nnsh> "
    )
    assert parse_uorb_top(top) == {"vehicle_visual_odometry": 29.0, "vehicle_mocap_odometry": 0.0}


def test_serial_link_rules_name_mode_and_baud() -> None:
    from companion.px4.rules import LinkContext, Param, evaluate

    params = {
        "MAV_0_CONFIG": Param("MAV_0_CONFIG", 101, True),
        "MAV_1_CONFIG": Param("MAV_1_CONFIG", 102, True),
        "MAV_1_MODE": Param("MAV_1_MODE", 0, True),
        "MAV_2_CONFIG": Param("MAV_2_CONFIG", 0, True),
        "SER_TEL2_BAUD": Param("SER_TEL2_BAUD", 57600, True),
    }
    ctx = LinkContext("odometry", "TELEM2", "serial", 921600)
    rows = {r.name: r for r in evaluate(params, ctx)}
    assert rows["MAV_1_CONFIG"].status is Status.OK
    mode = rows["MAV_1_MODE"]
    assert mode.status is Status.FAIL and mode.targets[0].value == 2 and mode.targets[0].reboot
    baud = rows["SER_TEL2_BAUD"]
    assert baud.status is Status.FAIL and baud.targets[0].value == 921600
    assert rows["MAV_0_CONFIG"].status is Status.INFO  # the ground station's link, not ours
    # nothing on TELEM3: configure would enable the free instance 2 there
    rows3 = {
        r.name: r for r in evaluate(params, LinkContext("odometry", "TELEM3", "serial", 921600))
    }
    assert rows3["MAV_2_CONFIG"].status is Status.FAIL
    assert rows3["MAV_2_CONFIG"].targets[0].value == 103


def test_without_a_shell_fusion_is_inferred_only_without_gnss() -> None:
    from companion.px4.fusion import Observations, diagnose
    from companion.px4.rules import LinkContext, Param

    params = {
        "EKF2_EV_CTRL": Param("EKF2_EV_CTRL", 11, True),
        "EKF2_GPS_CTRL": Param("EKF2_GPS_CTRL", 7, True),
    }
    ctx = LinkContext()
    seen = Observations(watch_s=2.0, estimator_flags=0x12F, local_positions=20, gps_seen=False)
    assert diagnose(seen, params, ctx).fused is True
    with_gps = Observations(watch_s=2.0, estimator_flags=0x12F, local_positions=20, gps_seen=True)
    assert diagnose(with_gps, params, ctx).fused is None  # GNSS may be what makes it valid
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
