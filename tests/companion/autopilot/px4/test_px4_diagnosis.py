"""PX4's fusion diagnosis (pure): PX4's shell output parsed as PX4 prints it, the verdict from
EKF2's own topics and, without a shell, only when nothing else can aid; and check's refusal to
share the running service's link."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.autopilot.options import CheckOptions
from companion.config import load_config

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
    from companion.autopilot.px4.ekf2_observations import sample_age_ms
    from companion.drivers.px4_shell_text import number, parse_listener, parse_uorb_top

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
    from companion.autopilot.px4.ekf2_observations import sample_age_ms
    from companion.drivers.px4_shell_text import parse_listener
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


def _shell(**kw: Any) -> Any:
    from companion.autopilot.px4.ekf2_observations import ShellView

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
    from companion.autopilot.params import Param
    from companion.autopilot.px4.ekf2_diagnosis import diagnose
    from companion.autopilot.px4.ekf2_observations import Observations
    from companion.autopilot.px4.link_context import LinkContext

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
    from companion.autopilot.params import Param
    from companion.autopilot.px4.ekf2_diagnosis import diagnose
    from companion.autopilot.px4.ekf2_observations import Observations
    from companion.autopilot.px4.link_context import LinkContext

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
    from companion.autopilot.px4.check import resolve
    from companion.errors import ConfigError
    from companion.service.status import StatusServer

    sock = tmp_path / "status.sock"
    cfg = load_config(
        overrides={"service": {"mavlink_url": "udpin:127.0.0.1:14540", "status_socket": str(sock)}}
    )

    async def scenario() -> None:
        stopped = await asyncio.to_thread(resolve, cfg, CheckOptions())
        assert stopped.url == "udpin://127.0.0.1:14540"
        async with StatusServer(sock, lambda: {"output": {"rate_hz": 30.0}}):
            with pytest.raises(ConfigError, match="running service holds"):
                await asyncio.to_thread(resolve, cfg, CheckOptions())
            with pytest.raises(ConfigError):
                await asyncio.to_thread(resolve, cfg, CheckOptions(url="udpin:127.0.0.1:14540"))
            gcs = await asyncio.to_thread(resolve, cfg, CheckOptions(url="udpin:127.0.0.1:14550"))
            assert gcs.url == "udpin://127.0.0.1:14550" and gcs.ctx.fc_port == "ETHERNET"

    asyncio.run(scenario())
