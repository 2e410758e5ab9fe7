"""The message rates the service asks of the autopilot over a real link (issue 16): one of
them refused, what was acknowledged given back when we stop, PX4's TIMESYNC rate left alone
and never asked of ArduPilot; and the link's smaller guards: frames nobody reads skipped by
their header, the reconnect backoff, the autopilot's own rangefinder kept apart from ours, a
busy listening port. A real Service on loopback, real pymavlink peers."""

from __future__ import annotations

import asyncio
import copy
import socket
import time
from typing import Any

from peers import free_port, service_config
from peers.mavlink_sender import Sender, kinds
from pymavlink.dialects.v20 import common as mavlink

from companion.drivers import messages
from companion.drivers.mavlink_parser import LinkStats, Parser, frame_spans
from companion.service.app import Service

MAV_AUTOPILOT_PX4, MAV_AUTOPILOT_ARDUPILOTMEGA = 12, 3


async def fake_autopilot(
    autopilot: Sender,
    seconds: float,
    refuse: frozenset[int],
    asked: list[int],
    kind: int = MAV_AUTOPILOT_PX4,
) -> None:
    """An autopilot (PX4 unless ``kind`` says otherwise) for ``seconds``: HEARTBEAT every
    0.1 s, each MAV_CMD_SET_MESSAGE_INTERVAL (its message id appended to ``asked``) answered at
    once with a COMMAND_ACK that, like PX4's, does not say which message it was for: FAILED
    for the ids in ``refuse``, else ACCEPTED."""
    end = time.monotonic() + seconds
    seen = 0
    while time.monotonic() < end:
        autopilot.send(autopilot.mav.heartbeat_encode(2, kind, 0, 0, 4))  # a QUADROTOR
        got = autopilot.drain()
        for m in got[seen:]:
            if m.get_type() == "COMMAND_LONG" and m.command == 511:
                asked.append(int(m.param1))
                result = 4 if int(m.param1) in refuse else 0  # MAV_RESULT_FAILED / ACCEPTED
                autopilot.send(autopilot.mav.command_ack_encode(511, result, 0, 0, 1, 197))
        seen = len(got)
        await asyncio.sleep(0.1)


def test_a_refused_rate_is_said_once_and_blocks_none_of_the_others(tmp_path) -> None:
    """The rates are asked one at a time until acknowledged, TIMESYNC first from PX4. One the
    autopilot refuses (COMMAND_ACK FAILED: PX4 for a message it cannot stream) is warned about
    once and not asked again, so the others after it are asked and acknowledged (before, the
    service asked a refused rate again every 0.3 s for ever and never the ones after it); once
    the autopilot was silent for 3 s (a reboot) everything is asked again."""
    port = free_port(socket.SOCK_DGRAM)
    cfg = service_config(tmp_path, mavlink_url=f"udpin:127.0.0.1:{port}")
    timesync = messages.MSG_ID_TIMESYNC
    others = [messages.MSG_ID_DISTANCE_SENSOR, messages.MSG_ID_ATTITUDE, messages.MSG_ID_SCALED_IMU]

    async def main() -> tuple[list[int], list[int], Any, dict[str, Any], list[str]]:
        async with Service(cfg) as service:
            autopilot = Sender(port)
            first: list[int] = []
            await fake_autopilot(autopilot, 3.0, frozenset({timesync}), first)
            stats = copy.deepcopy(service.stats)
            status = service.status()["autopilot"]
            await asyncio.sleep(3.5)  # silent: the service forgets what was acknowledged
            again: list[int] = []
            await fake_autopilot(autopilot, 2.5, frozenset(), again)
            autopilot.close()
            return first, again, stats, status, list(service.stats.warnings)

    first, again, stats, status, warnings = asyncio.run(main())
    assert list(dict.fromkeys(first)) == [timesync, *others], first  # in this order, all asked
    assert first.count(timesync) <= 2, first  # not again after the refusal (0.3 s apart)
    assert stats.rates_refused == {timesync} and stats.rates_acknowledged == set(others)
    assert status["rates_refused"] == [timesync]
    assert status["rates_acknowledged"] == sorted(others)
    refused = [w for w in warnings if "refused" in w]
    assert len(refused) == 1 and "TIMESYNC (111)" in refused[0], warnings
    assert "MAV_RESULT_FAILED" in refused[0]
    assert list(dict.fromkeys(again)) == [timesync, *others], again  # back: asked again


def test_the_rates_the_autopilot_acknowledged_go_back_to_its_defaults_when_we_stop(
    tmp_path,
) -> None:
    """A stopped service leaves no stream at our rates: for every rate the autopilot
    acknowledged, MAV_CMD_SET_MESSAGE_INTERVAL with interval 0 (MAVLink's default rate), sent
    on the way out; none for a refused one (it was never changed), none while running."""
    port = free_port(socket.SOCK_DGRAM)
    cfg = service_config(tmp_path, mavlink_url=f"udpin:127.0.0.1:{port}")
    timesync = messages.MSG_ID_TIMESYNC
    autopilot = Sender(port)

    async def main() -> tuple[set[int], int]:
        async with Service(cfg) as service:
            await fake_autopilot(autopilot, 3.0, frozenset({timesync}), [])
            acknowledged = set(service.stats.rates_acknowledged)
            n_before = len(autopilot.drain())
        return acknowledged, n_before

    acknowledged, n_before = asyncio.run(main())
    time.sleep(0.2)
    got = autopilot.drain()
    autopilot.close()
    assert acknowledged == {
        messages.MSG_ID_DISTANCE_SENSOR,
        messages.MSG_ID_ATTITUDE,
        messages.MSG_ID_SCALED_IMU,
    }

    def defaults(msgs: list[Any]) -> list[int]:
        return [
            int(m.param1) for m in kinds(msgs, "COMMAND_LONG") if m.command == 511 and m.param2 == 0
        ]

    assert defaults(got[:n_before]) == []  # never while running
    assert sorted(defaults(got[n_before:])) == sorted(acknowledged), got[n_before:]


def test_px4s_timesync_rate_is_left_alone_at_0_and_never_asked_of_ardupilot(tmp_path) -> None:
    """service.px4_timesync_rate_hz 0 leaves PX4's own TIMESYNC rate; ArduPilot (whose
    TIMESYNC is no stream) is never asked for it."""
    port = free_port(socket.SOCK_DGRAM)
    cfg = service_config(tmp_path, mavlink_url=f"udpin:127.0.0.1:{port}", px4_timesync_rate_hz=0.0)

    async def main() -> list[int]:
        async with Service(cfg) as service:
            autopilot = Sender(port)
            asked: list[int] = []
            await fake_autopilot(autopilot, 2.0, frozenset(), asked)
            assert service.stats.rates_refused == set()
            autopilot.close()
            return asked

    asked = asyncio.run(main())
    assert messages.MSG_ID_TIMESYNC not in asked and messages.MSG_ID_ATTITUDE in asked, asked
    port = free_port(socket.SOCK_DGRAM)
    cfg = service_config(tmp_path, mavlink_url=f"udpin:127.0.0.1:{port}")

    async def ardupilot_main() -> list[int]:
        async with Service(cfg):
            autopilot = Sender(port)
            asked: list[int] = []
            await fake_autopilot(
                autopilot, 2.0, frozenset(), asked, kind=MAV_AUTOPILOT_ARDUPILOTMEGA
            )
            autopilot.close()
            return asked

    asked = asyncio.run(ardupilot_main())
    assert messages.MSG_ID_TIMESYNC not in asked and messages.MSG_ID_ATTITUDE in asked, asked


def test_frames_nobody_reads_are_skipped_by_their_header() -> None:
    ap = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    other = mavlink.MAVLink(None, srcSystem=42, srcComponent=1)
    hb = ap.heartbeat_encode(2, 12, 0, 0, 4).pack(ap)
    imu = ap.highres_imu_encode(1, *([0.0] * 13), 0).pack(ap)  # PX4 streams it at 50 Hz
    foreign_att = other.attitude_encode(1, 0.1, 0.1, 0, 0, 0, 0).pack(other)
    spans = frame_spans(hb + imu + foreign_att)
    assert spans is not None and [s[3] for s in spans] == [0, 105, 30]
    assert frame_spans(hb[:-1]) is None and frame_spans(b"\x00" + hb) is None

    parser = Parser(None, messages.SERVICE_INPUTS, 1)
    stats = LinkStats()
    calls = 0
    real = parser.mav.parse_char

    def counting(data: bytes) -> Any:
        nonlocal calls
        calls += 1 if data else 0
        return real(data)

    parser.mav.parse_char = counting  # type: ignore[method-assign]
    got = parser.feed(hb + imu + foreign_att, stats, datagram=True)
    assert [m.get_type() for m in got] == ["HEARTBEAT"]
    assert stats.rx_skipped == 1 and stats.rx_foreign == 1 and stats.rx_bad == 0
    for _ in range(1000):  # a flood of frames nobody reads: pymavlink never sees them
        assert parser.feed(imu, stats, datagram=True) == []
        assert parser.feed(foreign_att, stats, datagram=True) == []
    assert calls == 1 and stats.rx_skipped == 1001 and stats.rx_foreign == 1001
    # garbage still goes to pymavlink's robust parser (counted as bad, never raised)
    assert parser.feed(b"\x55" * 40 + hb[:5], stats, datagram=True) == []
    assert stats.rx_bad >= 1


def test_backoff_doubles_jitters_caps_and_resets() -> None:
    import random

    import pytest

    from companion.drivers.backoff import Backoff

    b = Backoff(0.5, 4.0, random.Random(7))
    waits = [b.next_s() for _ in range(8)]
    nominal = [0.5, 1.0, 2.0, 4.0, 4.0, 4.0, 4.0, 4.0]
    assert all(0.5 * n <= w < 1.5 * n for w, n in zip(waits, nominal, strict=True))
    assert len({round(w / n, 6) for w, n in zip(waits, nominal, strict=True)}) == 8  # jittered
    b.reset()
    assert 0.25 <= b.next_s() < 0.75
    with pytest.raises(ValueError):
        Backoff(2.0, 1.0)


def test_the_autopilots_rangefinder_is_not_mixed_into_a_tfmini_with_its_id(tmp_path) -> None:
    """PX4 SIH streams its own downward rangefinder as DISTANCE_SENSOR id 0; a sensor 0 wired
    to the companion (a TFmini on serial) must not take those readings as its own."""
    port = free_port(socket.SOCK_DGRAM)
    rangefinders = [{"sensor_id": 0, "serial": str(tmp_path / "ttyTF0")}, {"sensor_id": 1}]
    cfg = service_config(
        tmp_path, tables={"rangefinders": rangefinders}, mavlink_url=f"udpin:127.0.0.1:{port}"
    )

    async def main() -> tuple[int, dict[str, int]]:
        async with Service(cfg) as service:
            ap = Sender(port)
            ap.heartbeat()
            await asyncio.sleep(0.1)
            for k in range(10):
                for sid in (0, 1):
                    ap.send(ap.mav.distance_sensor_encode(k, 10, 4000, 300, 0, sid, 25, 0))
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.3)
            ap.close()
            return service.stats.ranges_in, dict(service.stats.ranges_rejected_by)

    taken, refused = asyncio.run(main())
    assert taken == 10 and refused.get("unknown_id") == 10, (taken, refused)


def test_a_busy_listening_port_is_a_config_error_naming_the_key(tmp_path) -> None:
    """Another program (or a second companion) on our udpin port: a one-line error naming
    service.mavlink_url from the service, exit 2 from `companion run`, no traceback."""
    import subprocess
    import sys

    import pytest

    from companion.errors import ConfigError

    taken = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    taken.bind(("127.0.0.1", 0))
    port = taken.getsockname()[1]
    try:
        cfg = service_config(tmp_path, mavlink_url=f"udpin:127.0.0.1:{port}")

        async def main() -> None:
            async with Service(cfg):
                pass

        with pytest.raises(ConfigError, match=r"service\.mavlink_url: cannot listen"):
            asyncio.run(main())
        toml = tmp_path / "busy.toml"
        toml.write_text(
            f'[service]\nmavlink_url = "udpin:127.0.0.1:{port}"\n'
            f'camera_url = "sitl://127.0.0.1:{free_port()}"\n'
            f'status_socket = "{tmp_path / "s.sock"}"\nstate_dir = "{tmp_path / "state"}"\n'
        )
        run = subprocess.run(
            [sys.executable, "-m", "companion.cli", "run", "--config", str(toml)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert run.returncode == 2, run.stderr[-2000:]
        assert "service.mavlink_url" in run.stderr and "Traceback" not in run.stderr
    finally:
        taken.close()
