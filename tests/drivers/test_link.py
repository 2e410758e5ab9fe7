"""The autopilot link against senders that are not the autopilot (issue 16): a spoofer on
another UDP address, TIMESYNC requests of other systems, a forged COMMAND_ACK, and the cheap
first look that skips what nobody reads; the message rates asked of the autopilot, one of them
refused. A real Service on loopback, real pymavlink peers."""

from __future__ import annotations

import asyncio
import copy
import socket
import time
from typing import Any

from peers import free_port, service_config
from pymavlink.dialects.v20 import common as mavlink

from companion.drivers import messages
from companion.drivers.mavlink import PEER_SILENCE_S
from companion.drivers.mavlink_parser import LinkStats, Parser, frame_spans
from companion.service.app import Service


class Sender:
    """A pymavlink sender on its own UDP port, as system ``sysid`` component ``compid``."""

    def __init__(self, port: int, sysid: int = 1, compid: int = 1) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.mav.robust_parsing = True
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.port = port
        self.got: list[Any] = []

    def send(self, msg: Any) -> None:
        self.sock.sendto(msg.pack(self.mav), ("127.0.0.1", self.port))

    def heartbeat(self) -> None:
        self.send(self.mav.heartbeat_encode(2, 12, 0, 0, 4))  # QUADROTOR, PX4

    def drain(self) -> list[Any]:
        while True:
            try:
                data = self.sock.recv(65536)
            except BlockingIOError:
                return self.got
            self.got += self.mav.parse_buffer(data) or []

    def close(self) -> None:
        self.sock.close()


def kinds(msgs: list[Any], kind: str) -> list[Any]:
    return [m for m in msgs if m.get_type() == kind]


def test_a_spoofer_on_another_address_gets_nothing_and_changes_nothing(tmp_path) -> None:
    port = free_port(socket.SOCK_DGRAM)
    cfg = service_config(tmp_path, mavlink_url=f"udpin:127.0.0.1:{port}")

    async def main() -> dict[str, Any]:
        async with Service(cfg) as service:
            autopilot, spoofer = Sender(port), Sender(port)
            gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
            autopilot.heartbeat()
            await asyncio.sleep(0.2)
            for k in range(30):  # the spoofer talks while the autopilot does
                autopilot.heartbeat()
                autopilot.send(autopilot.mav.timesync_encode(0, 10_000 + k))
                spoofer.heartbeat()
                spoofer.send(spoofer.mav.timesync_encode(0, 20_000 + k))
                spoofer.send(spoofer.mav.attitude_encode(k, 0.1, 0.1, 0.0, 0.0, 0.0, 0.0))
                spoofer.send(
                    spoofer.mav.command_ack_encode(
                        messages.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 0, 0, 1, 197
                    )
                )
                # a ground station's request forwarded on the autopilot's own address
                request = gcs.timesync_encode(0, 30_000 + k).pack(gcs)
                autopilot.sock.sendto(request, ("127.0.0.1", port))
                await asyncio.sleep(0.02)
            await asyncio.sleep(1.2)  # a heartbeat and some time-sync requests of ours
            out = {
                "autopilot": autopilot.drain(),
                "spoofer": spoofer.drain(),
                "stats": service.stats,
                "link": service.link.stats,
                "peer": service.link._peer,
                "autopilot_port": autopilot.sock.getsockname(),
            }
            autopilot.close()
            spoofer.close()
            return out

    r = asyncio.run(main())
    assert r["spoofer"] == []  # no heartbeat, no TIMESYNC reply, nothing
    assert r["peer"] == r["autopilot_port"]
    replies = {m.ts1 for m in kinds(r["autopilot"], "TIMESYNC") if m.tc1 != 0}
    assert {10_000 + k for k in range(30)} <= replies  # every request of the autopilot...
    assert not replies & {30_000 + k for k in range(30)}  # ...none of the ground station's
    assert kinds(r["autopilot"], "HEARTBEAT")
    assert r["stats"].attitudes_in == 0  # the spoofed ATTITUDE never reached the pipeline
    assert r["stats"].rates_acknowledged == set()  # nor did the forged COMMAND_ACK
    assert r["link"].rx_other_address >= 4 * 30
    assert r["stats"].timesync_replies == 30


def test_the_autopilot_moves_port_only_with_its_own_heartbeat_after_silence(tmp_path) -> None:
    port = free_port(socket.SOCK_DGRAM)
    cfg = service_config(tmp_path, mavlink_url=f"udpin:127.0.0.1:{port}")

    async def main() -> list[Any]:
        async with Service(cfg) as service:
            link = service.link
            old = Sender(port)
            old.heartbeat()
            await asyncio.sleep(0.2)
            first = link._peer
            new = Sender(port)
            new.heartbeat()  # while the old address is fresh: ignored
            await asyncio.sleep(0.2)
            kept = link._peer
            await asyncio.sleep(PEER_SILENCE_S + 0.3)  # the autopilot rebooted, say
            new.send(new.mav.attitude_encode(1, 0.1, 0.1, 0, 0, 0, 0))  # not a heartbeat
            gcs = mavlink.MAVLink(None, srcSystem=1, srcComponent=190)
            new.sock.sendto(gcs.heartbeat_encode(6, 8, 0, 0, 4).pack(gcs), ("127.0.0.1", port))
            await asyncio.sleep(0.2)
            still = link._peer
            new.heartbeat()  # the autopilot's own
            await asyncio.sleep(0.2)
            moved = link._peer
            result = [first, kept, still, moved, old.sock.getsockname(), new.sock.getsockname()]
            result.append(link.stats.peer_changes)
            old.close()
            new.close()
            return result

    first, kept, still, moved, old_addr, new_addr, changes = asyncio.run(main())
    assert first == kept == still == old_addr
    assert moved == new_addr and changes == 1


def px4_stream(autopilot: Sender, k: int) -> None:
    """One round of an autopilot's stream to its companion link (8 kinds, as PX4's onboard
    mode sends ~25): attitude, position, IMU, altitude, HUD, a rangefinder, a TIMESYNC
    request; its HEARTBEAT once a second (every tenth round, at 10 rounds a second)."""
    m = autopilot.mav
    if k % 10 == 0:
        autopilot.heartbeat()
    autopilot.send(m.attitude_encode(k, 0.01, 0.02, 0.3, 0.0, 0.0, 0.0))
    autopilot.send(m.attitude_quaternion_encode(k, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    autopilot.send(m.local_position_ned_encode(k, 1.0, 2.0, -3.0, 0.0, 0.0, 0.0))
    autopilot.send(m.highres_imu_encode(k, *([0.0] * 13), 0))
    autopilot.send(m.altitude_encode(k, 0.0, 0.0, 0.0, 0.0, 3.0, 3.0))
    autopilot.send(m.vfr_hud_encode(0.0, 0.0, 17, 0, 3.0, 0.0))
    autopilot.send(m.distance_sensor_encode(k, 10, 4000, 300, 0, 0, 25, 0))
    autopilot.send(m.timesync_encode(0, 50_000 + k))


def test_a_spoofer_that_spoke_first_is_named_and_loses_the_link_to_the_autopilot(
    tmp_path, caplog
) -> None:
    """A spoofer on its own UDP address that speaks before the autopilot took the link for
    the whole flight (0 poses reached the autopilot; nothing said). The autopilot's stream
    (many kinds of message as the autopilot) beats a source that only claims its id: within
    2 s of the autopilot's first HEARTBEAT the link sends to the autopilot, and the status
    and the log name the spoofer's address. Once the autopilot's stream holds the link, a
    claimant that imitates it later does not take it."""
    import logging

    port = free_port(socket.SOCK_DGRAM)
    cfg = service_config(tmp_path, mavlink_url=f"udpin:127.0.0.1:{port}")

    async def main() -> dict[str, Any]:
        async with Service(cfg) as service:
            spoofer, autopilot = Sender(port), Sender(port)
            spoofer_at = f"127.0.0.1:{spoofer.sock.getsockname()[1]}"

            def spoof(k: int) -> None:  # a HEARTBEAT, forged ATTITUDE and TIMESYNC
                spoofer.heartbeat()
                spoofer.send(spoofer.mav.attitude_encode(k, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0))
                spoofer.send(spoofer.mav.timesync_encode(0, 20_000 + k))

            for k in range(10):  # it speaks first, for a second
                spoof(k)
                await asyncio.sleep(0.1)
            taken = service.link._peer == spoofer.sock.getsockname()
            first_heartbeat = time.monotonic()
            named_after_s = None
            for k in range(40):  # then the autopilot; the spoofer goes on
                px4_stream(autopilot, k)
                spoof(10 + k)
                await asyncio.sleep(0.1)
                claimants = service.status()["autopilot"]["claimants"]
                rivals = [c["address"] for c in claimants if not c["autopilot"]]
                logged = any(spoofer_at in r.getMessage() for r in caplog.records)
                if named_after_s is None and rivals == [spoofer_at] and logged:
                    named_after_s = time.monotonic() - first_heartbeat
            for k in range(15):  # now it imitates the whole stream: too late, still named
                px4_stream(autopilot, 40 + k)
                px4_stream(spoofer, 40 + k)
                await asyncio.sleep(0.1)
            spoofer.drain()
            n_spoofer = len(spoofer.got)
            autopilot.drain()
            n_autopilot = len(autopilot.got)
            await asyncio.sleep(1.2)  # a heartbeat and time-sync requests of ours: to whom
            out = {
                "taken": taken,
                "named_after_s": named_after_s,
                "peer": service.link._peer,
                "autopilot_port": autopilot.sock.getsockname(),
                "to_spoofer_after": len(spoofer.drain()) - n_spoofer,
                "to_autopilot_after": len(autopilot.drain()) - n_autopilot,
                "status": service.status()["autopilot"],
                "link": copy.copy(service.link.stats),
                "rival": service.link.rival_address(time.monotonic_ns()),
                "spoofer_at": spoofer_at,
            }
            spoofer.close()
            autopilot.close()
            return out

    with caplog.at_level(logging.WARNING, logger="companion.mavlink"):
        r = asyncio.run(main())
    print(f"spoofer named {r['named_after_s']} s after the autopilot's first HEARTBEAT")
    assert r["taken"]  # speaking first took the link, as it does on a fresh link
    assert r["named_after_s"] is not None and r["named_after_s"] <= 2.0, r["named_after_s"]
    assert r["peer"] == r["autopilot_port"]
    assert r["to_spoofer_after"] == 0 and r["to_autopilot_after"] >= 2
    assert r["link"].peer_changes == 1 and r["link"].rivals_seen >= 1
    assert r["rival"] == r["spoofer_at"]  # what the operator is to be told
    assert [c["kinds"] >= 8 for c in r["status"]["claimants"]] == [True, True]
    ours = [c for c in r["status"]["claimants"] if c["autopilot"]]
    assert len(ours) == 1 and ours[0]["kinds"] >= 8, r["status"]["claimants"]


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
    from companion.config import load_config

    port = free_port(socket.SOCK_DGRAM)
    cfg = load_config(
        None,
        {
            "service": {
                "mavlink_url": f"udpin:127.0.0.1:{port}",
                "camera_url": f"sitl://127.0.0.1:{free_port()}",
                "status_socket": str(tmp_path / "s.sock"),
                "state_dir": str(tmp_path / "state"),
            },
            "rangefinders": [
                {"sensor_id": 0, "serial": str(tmp_path / "ttyTF0")},
                {"sensor_id": 1},
            ],
        },
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


def test_on_a_signed_link_an_unsigned_claimant_is_named_and_never_followed(
    tmp_path, caplog
) -> None:
    """Signing decides who the autopilot is: an unsigned source streaming as the autopilot
    (a full stream, more than the signed autopilot sends) never takes the link, and is
    named in the log and among the claimants, where before it was dropped unsaid."""
    import logging

    from companion.drivers.mavlink import MavlinkLink
    from companion.drivers.signing import Signing, TimestampStore, wall_units

    key = bytes(range(7, 39))
    port = free_port(socket.SOCK_DGRAM)
    signing = Signing(key, TimestampStore(tmp_path / "ts"), link_id=0)

    async def main() -> dict[str, Any]:
        link = MavlinkLink(f"udpin:127.0.0.1:{port}", 1, 197, lambda m, t: None, signing)
        async with link:
            autopilot, spoofer = Sender(port), Sender(port)
            s = autopilot.mav.signing
            s.secret_key, s.link_id, s.sign_outgoing = key, 3, True
            s.timestamp = wall_units()
            for k in range(25):  # the signed autopilot: a HEARTBEAT a second, an ATTITUDE
                if k % 10 == 0:
                    autopilot.heartbeat()
                autopilot.send(autopilot.mav.attitude_encode(k, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
                if k >= 5:
                    px4_stream(spoofer, k)
                await asyncio.sleep(0.1)
            out = {
                "peer": link._peer,
                "autopilot": autopilot.sock.getsockname(),
                "spoofer": f"127.0.0.1:{spoofer.sock.getsockname()[1]}",
                "claimants": link.claimants_status(time.monotonic_ns()),
                "stats": copy.copy(link.stats),
            }
            autopilot.close()
            spoofer.close()
            return out

    with caplog.at_level(logging.WARNING, logger="companion.mavlink"):
        r = asyncio.run(main())
    assert r["peer"] == r["autopilot"] and r["stats"].peer_changes == 0
    assert r["stats"].rivals_seen == 1
    rivals = [c for c in r["claimants"] if not c["autopilot"]]
    assert [c["address"] for c in rivals] == [r["spoofer"]] and rivals[0]["kinds"] >= 8
    said = [rec.getMessage() for rec in caplog.records if r["spoofer"] in rec.getMessage()]
    assert len(said) == 1 and "not signed" in said[0], said
