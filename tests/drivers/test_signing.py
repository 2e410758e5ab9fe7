"""MAVLink 2 signing: the key file's checks, the persisted timestamp, and a live link against a
pymavlink peer that requires signing (the right key, then a wrong one)."""

from __future__ import annotations

import asyncio
import socket
import time
from pathlib import Path
from typing import Any

import pytest
from peers import free_port
from peers.signing_peers import KEY, Peer, write_key
from pymavlink.dialects.v20 import common as mavlink

from companion.config import load_config
from companion.drivers.mavlink import MavlinkLink
from companion.drivers.signing import (
    RESERVE_UNITS,
    UNITS_PER_S,
    Signing,
    TimestampStore,
    load_key,
    wall_units,
)
from companion.errors import ConfigError


def test_the_key_file_must_be_private_and_32_bytes(tmp_path) -> None:
    assert load_key(write_key(tmp_path / "raw", KEY)) == KEY
    assert load_key(write_key(tmp_path / "hex", KEY.hex().encode() + b"\n")) == KEY
    assert load_key(write_key(tmp_path / "ro", KEY, 0o400)) == KEY
    with pytest.raises(ConfigError, match=r"service.signing.key_file: .* mode 0640"):
        load_key(write_key(tmp_path / "shared", KEY, 0o640))
    with pytest.raises(ConfigError, match="32 bytes or 64 hex digits"):
        load_key(write_key(tmp_path / "short", KEY[:16]))
    with pytest.raises(ConfigError, match="cannot read"):
        load_key(tmp_path / "missing")


def test_a_bad_key_file_stops_the_service_before_anything_starts(tmp_path) -> None:
    from companion.service.app import Service

    key = write_key(tmp_path / "k", KEY, 0o644)
    sock = tmp_path / "status.sock"
    cfg = load_config(
        None,
        {"service": {"signing": {"key_file": str(key)}, "status_socket": str(sock)}},
    )
    with pytest.raises(ConfigError, match=r"service\.signing\.key_file"):
        Service(cfg)
    assert not sock.exists()


def test_the_timestamp_never_goes_back(tmp_path) -> None:
    store = TimestampStore(tmp_path / "state" / "signing_timestamp")
    now_s = time.time()
    first = store.start(now_s)
    assert abs(first - wall_units(now_s)) <= 1
    assert store.read() == first + RESERVE_UNITS  # persisted ahead before it is used
    assert (tmp_path / "state" / "signing_timestamp").stat().st_mode & 0o777 == 0o600
    # a crash after using timestamps up to just below the persisted value...
    used = store.read() - 1
    # ...and a reboot with the wall clock a day behind (a board without a real-time clock)
    again = TimestampStore(store.path).start(now_s - 86400)
    assert again > used
    # the file is only rewritten when half the reserve is used
    s2 = TimestampStore(store.path)
    t = s2.start(now_s)
    writes = s2.writes
    s2.keep_ahead(t + RESERVE_UNITS // 4)
    assert s2.writes == writes
    s2.keep_ahead(t + RESERVE_UNITS)
    assert s2.writes == writes + 1 and s2.read() == t + 2 * RESERVE_UNITS
    assert not list(store.path.parent.glob("*.tmp"))  # atomic: no temporary left behind
    # a file that does not hold a timestamp is not taken for a fresh board (the wall clock
    # may be behind what was used): a config error, the file left as it is
    store.path.write_text("garbage")
    with pytest.raises(ConfigError, match="does not hold a timestamp"):
        TimestampStore(store.path).start(now_s)
    assert store.path.read_text() == "garbage"


def run_link(key_file: Path, state: Path, peer_key: bytes) -> tuple[list[str], dict, list[Any]]:
    """Our signed link (udpin) against a peer: the peer sends signed TIMESYNC requests and
    HEARTBEATs, plus one unsigned DISTANCE_SENSOR and one unsigned HEARTBEAT; we answer each
    request. Returns what reached our handler, our signing counters, what the peer parsed."""
    port = free_port(socket.SOCK_DGRAM)
    got: list[str] = []
    signing = Signing(load_key(key_file), TimestampStore(state), link_id=0)

    async def main() -> tuple[dict, list[Any]]:
        def on_message(msg: Any, _rx: int) -> None:
            got.append(msg.get_type())
            if msg.get_type() == "TIMESYNC" and msg.tc1 == 0:
                link.send(link.mav.timesync_encode(time.monotonic_ns(), msg.ts1))
            elif msg.get_type() == "HEARTBEAT":
                link.send(link.mav.heartbeat_encode(18, 8, 0, 0, 4))

        link = MavlinkLink(f"udpin:127.0.0.1:{port}", 1, 197, on_message, signing)
        async with link:
            peer = Peer(peer_key, port)
            unsigned = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
            for k in range(5):
                peer.send(peer.mav.heartbeat_encode(2, 12, 0, 0, 4))
                peer.send(peer.mav.timesync_encode(0, 1000 + k))
                await asyncio.sleep(0.02)
            peer.send(unsigned.distance_sensor_encode(1, 10, 4000, 500, 0, 0, 25, 0), unsigned)
            peer.send(unsigned.heartbeat_encode(2, 12, 0, 0, 4), unsigned)
            await asyncio.sleep(0.2)
            parsed = await asyncio.to_thread(peer.receive, 0.3)
        return signing.counters(), parsed

    counters, parsed = asyncio.run(main())
    return got, counters, parsed


def test_signed_link_with_the_right_key(tmp_path) -> None:
    key_file = write_key(tmp_path / "key", KEY)
    got, counters, parsed = run_link(key_file, tmp_path / "ts", KEY)
    assert got.count("TIMESYNC") == 5 and got.count("HEARTBEAT") == 6  # 5 signed + 1 unsigned
    assert "DISTANCE_SENSOR" not in got  # unsigned: refused
    assert counters["good_signatures"] == 10 and counters["refused"] == 1
    replies = [m for m in parsed if m.get_type() == "TIMESYNC"]
    assert len(replies) == 5 and sorted(m.ts1 for m in replies) == [1000, 1001, 1002, 1003, 1004]
    assert all(m.get_signed() for m in replies)  # and the peer, which requires it, took them
    assert len([m for m in parsed if m.get_type() == "HEARTBEAT"]) == 6
    assert (tmp_path / "ts").exists()


def test_a_wrong_key_is_refused_both_ways(tmp_path) -> None:
    key_file = write_key(tmp_path / "key", KEY)
    got, counters, parsed = run_link(key_file, tmp_path / "ts", bytes(32))
    assert got == ["HEARTBEAT"] * 6  # only heartbeats pass: the peer stays visible
    assert counters["good_signatures"] == 0 and counters["bad_signatures"] == 10
    # its heartbeats are visible but not authentic: we never learnt its address, so nothing
    # of ours went there; and what we sign, a peer with another key refuses
    assert parsed == []
    ours = mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
    Signing(KEY, None).apply(ours, mavlink.MAVLink(None))
    frame = ours.heartbeat_encode(18, 8, 0, 0, 4).pack(ours)
    assert [m.get_type() for m in Peer(bytes(32), 1).mav.parse_buffer(frame) or []] == ["BAD_DATA"]


def test_the_timestamp_follows_a_peer_that_is_ahead(tmp_path) -> None:
    """A peer whose clock is an hour ahead: after its first valid frame we sign with a newer
    timestamp (else it would refuse us as a stale stream) and persist it first."""
    key_file = write_key(tmp_path / "key", KEY)
    port = free_port(socket.SOCK_DGRAM)
    signing = Signing(load_key(key_file), TimestampStore(tmp_path / "ts"), link_id=0)

    async def main() -> int:
        link = MavlinkLink(f"udpin:127.0.0.1:{port}", 1, 197, lambda m, t: None, signing)
        async with link:
            peer = Peer(KEY, port)
            peer.mav.signing.timestamp = wall_units() + 3600 * UNITS_PER_S
            peer.send(peer.mav.heartbeat_encode(2, 12, 0, 0, 4))
            await asyncio.sleep(0.1)
            link.send(link.mav.heartbeat_encode(18, 8, 0, 0, 4))
            return int(link.mav.signing.timestamp)

    ts = asyncio.run(main())
    assert ts > wall_units() + 3500 * UNITS_PER_S
    assert TimestampStore(tmp_path / "ts").read() > ts  # persisted ahead of what was used


def test_an_unsigned_heartbeat_does_not_redirect_the_signed_link(tmp_path) -> None:
    port = free_port(socket.SOCK_DGRAM)
    signing = Signing(KEY, TimestampStore(tmp_path / "ts"), link_id=0)
    seen: list[str] = []

    async def main() -> tuple[Any, Any, int]:
        link = MavlinkLink(
            f"udpin:127.0.0.1:{port}", 1, 197, lambda m, t: seen.append(m.get_type()), signing
        )
        async with link:
            autopilot, attacker = Peer(KEY, port), Peer(None, port)
            autopilot.send(autopilot.mav.heartbeat_encode(2, 12, 0, 0, 4))
            await asyncio.sleep(0.1)
            peer_before = link._peer
            for _ in range(20):
                attacker.send(attacker.mav.heartbeat_encode(2, 12, 0, 0, 4))
            await asyncio.sleep(0.1)
            link.send(link.mav.heartbeat_encode(18, 8, 0, 0, 4))
            got = await asyncio.to_thread(autopilot.receive, 0.2)
            return peer_before, link._peer, len(got), link.stats.rx_other_address

    before, after, n_got, dropped = asyncio.run(main())
    # the autopilot's address is kept while it talks: the other sender is not even parsed
    assert seen.count("HEARTBEAT") == 1 and dropped == 20
    assert after == before and n_got == 1  # our output still goes to the autopilot


def test_an_unwritable_timestamp_file_is_a_config_error(tmp_path) -> None:
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("")
    with pytest.raises(ConfigError, match=r"service\.signing\.timestamp_file"):
        TimestampStore(blocker / "signing_timestamp").start()
    # later failures (a full disk) are counted, never raised into the sender
    store = TimestampStore(tmp_path / "ts")
    t = store.start()
    store.path = blocker / "gone"
    store.keep_ahead(t + RESERVE_UNITS)
    assert store.write_errors == 1


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (str(2**48), "48-bit limit"),
        (str(2**48 - 5), "48-bit limit"),  # no room left to count up
        (str(wall_units() + 2 * 366 * 86400 * UNITS_PER_S), "days ahead of the wall clock"),
        ("12abc", "does not hold a timestamp"),
        ("-5", "does not hold a timestamp"),
    ],
    # fixed ids: the wall-clock value differs between xdist workers, which must collect alike
    ids=["at-48-bits", "no-room-left", "two-years-ahead", "not-a-number", "negative"],
)
def test_an_impossible_stored_timestamp_stops_the_start(tmp_path, content, message) -> None:
    """Accepted, such a value made every genuine signed frame a 'replay' to the autopilot."""
    from companion.cli import main

    path = tmp_path / "signing_timestamp"
    path.write_text(content + "\n")
    with pytest.raises(ConfigError, match=rf"service\.signing\.timestamp_file: .*{message}"):
        TimestampStore(path).start()
    key = write_key(tmp_path / "k", KEY)
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        f'[service]\nstatus_socket = "{tmp_path / "s.sock"}"\n'
        f'signing = {{ key_file = "{key}", timestamp_file = "{path}" }}\n'
    )
    assert main(["config", "--config", str(cfg)]) == 2  # the same check as `run`
    assert path.read_text() == content + "\n"  # left for a person to look at


def test_a_timestamp_ahead_of_an_unset_clock_is_fine_and_never_written_past_48_bits(
    tmp_path,
) -> None:
    store = TimestampStore(tmp_path / "ts")
    real_now = wall_units()
    store.path.write_text(f"{real_now}\n")
    board_1970 = 0.0  # a board without a real-time clock: the stored value is the truth
    assert store.start(board_1970) == real_now + 1
    store.keep_ahead(2**48 - 10)  # a genuine peer far ahead moved us to the edge
    assert int(store.path.read_text()) == 2**48 - 1  # capped at 48 bits
    with pytest.raises(ConfigError, match="48-bit limit"):  # and said at the next start
        store.read(board_1970)
