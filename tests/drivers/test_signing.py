"""MAVLink 2 signing: the key file's checks, the persisted timestamp, and a live link against a
pymavlink peer that requires signing (the right key, then a wrong one)."""

from __future__ import annotations

import asyncio
import socket
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from peers import free_port
from pymavlink.dialects.v20 import common as mavlink

from companion.config import load_config
from companion.drivers.mavlink import MavlinkLink
from companion.drivers.mavlink_parser import LinkStats, Parser
from companion.drivers.signing import (
    RESERVE_UNITS,
    UNITS_PER_S,
    Signing,
    TimestampStore,
    load_key,
    wall_units,
)
from companion.errors import ConfigError

KEY = bytes(range(100, 132))


def write_key(path: Path, data: bytes, mode: int = 0o600) -> Path:
    path.write_bytes(data)
    path.chmod(mode)
    return path


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


class Peer:
    """A pymavlink autopilot on a UDP socket; signs with ``key`` and requires signatures."""

    def __init__(self, key: bytes | None, port: int) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.mav.robust_parsing = True
        if key is not None:
            s = self.mav.signing
            s.secret_key, s.link_id, s.sign_outgoing = key, 3, True
            s.timestamp = wall_units()
            s.allow_unsigned_callback = None  # every frame must be signed
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = port

    def send(self, msg: Any, mav: Any = None) -> None:
        self.sock.sendto(msg.pack(mav or self.mav), ("127.0.0.1", self.port))

    def receive(self, seconds: float) -> list[Any]:
        out: list[Any] = []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            out += self.mav.parse_buffer(data) or []
        return out


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


def _parser_with_signing() -> tuple[Parser, Any]:
    sig = Signing(KEY, None, link_id=0)
    ours = mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
    parser = Parser()
    sig.apply(ours, parser.mav)
    parser.signing_state = ours.signing
    return parser, ours.signing


def _signer(key: bytes, timestamp: int) -> Any:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    s = mav.signing
    s.secret_key, s.link_id, s.sign_outgoing, s.timestamp = key, 0, True, timestamp
    return mav


def test_a_forged_frame_cannot_lock_out_the_autopilot() -> None:
    """pymavlink records a stream's timestamp before checking the MAC: one frame with a
    junk signature and timestamp 2**48 - 2 would make every later genuine frame 'old'."""
    parser, state = _parser_with_signing()
    autopilot, attacker = _signer(KEY, wall_units()), _signer(bytes(32), 2**48 - 2)
    stats = LinkStats()

    def attitude(mav: Any) -> bytes:
        return bytes(mav.attitude_encode(1, 0, 0, 0, 0, 0, 0).pack(mav))

    assert [m.get_type() for m in parser.feed(attitude(autopilot), stats, True)] == ["ATTITUDE"]
    for _ in range(1000):  # forged frames: refused, and they leave no trace
        attacker.srcComponent = int(np.random.default_rng(_).integers(0, 256))
        assert parser.feed(attitude(attacker), stats, True) == []
    for _ in range(3):
        assert [m.get_type() for m in parser.feed(attitude(autopilot), stats, True)] == ["ATTITUDE"]
    assert len(state.stream_timestamps) == 1  # only the genuine stream is remembered
    assert state.timestamp < 2**48 - 2


def test_unknown_message_ids_are_bad_data_not_messages() -> None:
    """pymavlink returns frames of unknown ids before checking their CRC or signature."""
    parser, _ = _parser_with_signing()
    u = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    buf = bytearray(u.heartbeat_encode(2, 12, 0, 0, 4).pack(u))
    buf[7:10] = (0x123456).to_bytes(3, "little")
    stats = LinkStats()
    assert parser.feed(bytes(buf), stats, True) == [] and stats.rx_bad == 1


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


YEAR_S = 365 * 86400


def _heartbeat(mav: Any) -> bytes:
    return bytes(mav.heartbeat_encode(2, 12, 0, 0, 4).pack(mav))


def test_a_genuine_frame_stamped_far_ahead_is_refused_counted_and_logged_once(caplog) -> None:
    """An autopilot holding the key with a wrong real-time clock: its frames stamped two
    years ahead, or at the 48-bit edge, must not move our timestamp (accepted, the first
    was persisted and refused by our next start; the second made ours wrap within a few
    frames: every later frame a replay) nor its stream's (its later right frames would be
    replays); they are refused, counted, logged once; the right frames still pass."""
    parser, state = _parser_with_signing()
    ours_before = state.timestamp
    now = wall_units()
    stats = LinkStats()
    hostile = [_signer(KEY, now + 2 * YEAR_S * UNITS_PER_S), _signer(KEY, 2**48 - 60)]
    with caplog.at_level("WARNING", logger="companion.signing"):
        for mav in hostile * 3:
            got = parser.feed(_heartbeat(mav), stats, True)
            # the heartbeat stays visible (as an unsigned one may), never authentic
            assert [(m.get_type(), m.get_signed()) for m in got] == [("HEARTBEAT", False)]
    assert state.timestamp < now + 60 * UNITS_PER_S  # ours did not move
    assert state.stream_timestamps == {}  # nor the stream's
    autopilot = _signer(KEY, now)
    got = parser.feed(_heartbeat(autopilot), stats, True)
    assert [(m.get_type(), m.get_signed()) for m in got] == [("HEARTBEAT", True)]
    sig = Signing(KEY, None)
    sig.state = state
    counters = sig.counters()
    assert counters["far_ahead"] == 6 and counters["good_signatures"] == 1
    assert counters["far_ahead_s"] > 70 * YEAR_S  # the last one: near 2**48 (in 2104)
    warnings = [r for r in caplog.records if "ahead of our clock" in r.getMessage()]
    assert len(warnings) == 1 and "730.0 days ahead" in warnings[0].getMessage()
    assert state.timestamp >= ours_before


def test_a_peer_ahead_by_up_to_30_days_is_followed_but_cannot_walk_us_forward() -> None:
    """A companion without a real-time clock restores an old time at boot while the autopilot
    has GPS time: up to 30 days ahead of both our wall clock and our own timestamp is
    followed. Our own timestamp (where we started plus monotonic time) is the reference, not
    what peers moved ours to, so a key holder cannot walk us forward 29 days per frame."""
    parser, state = _parser_with_signing()
    now = wall_units()
    stats = LinkStats()
    day = 86400 * UNITS_PER_S
    ahead = _signer(KEY, now + 29 * day)
    assert [m.get_signed() for m in parser.feed(_heartbeat(ahead), stats, True)] == [True]
    assert state.timestamp >= now + 29 * day  # followed (the specification's rule)
    ahead.signing.timestamp = now + 58 * day  # the same stream, another 29 days on
    assert [m.get_signed() for m in parser.feed(_heartbeat(ahead), stats, True)] == [False]
    assert state.timestamp < now + 30 * day and state.far_ahead == 1
    # the bound, on a wall clock that is set: 30 days ahead of it
    assert abs(state.peer_limit_units(now) - (now + 30 * day)) < 10 * UNITS_PER_S
    # a board at 1970 (clock not set): 30 days ahead of our own timestamp
    own = state.own_units()
    assert abs(state.peer_limit_units(0) - (own + 30 * day)) < 10 * UNITS_PER_S


def test_what_a_far_ahead_peer_leaves_behind_passes_the_next_start(tmp_path) -> None:
    """Whatever a peer moved us to is persisted ahead and must pass the next start's check
    (at most a year ahead of a set wall clock): followed up to there, refused beyond, also
    when our own timestamp was already far ahead of the wall clock."""
    from companion.drivers.signing import OWN_LIMIT_UNITS, SigningState

    day = 86400 * UNITS_PER_S
    for days_ahead_of_wall in (0, 200, 340):  # where our stored timestamp already was
        store = TimestampStore(tmp_path / f"ts{days_ahead_of_wall}")
        store.path.write_text(f"{wall_units() + days_ahead_of_wall * day}\n")
        sig = Signing(KEY, store)
        ours, parser = mavlink.MAVLink(None), Parser()
        sig.apply(ours, parser.mav)
        parser.signing_state = ours.signing
        peer = _signer(KEY, wall_units() + min(days_ahead_of_wall + 29, 365) * day)
        followed = peer.signing.timestamp
        stats = LinkStats()
        assert [m.get_signed() for m in parser.feed(_heartbeat(peer), stats, True)] == [True]
        peer.signing.timestamp = wall_units() + 400 * day  # beyond what a start accepts
        assert [m.get_signed() for m in parser.feed(_heartbeat(peer), stats, True)] == [False]
        sig.tick()
        assert TimestampStore(store.path).read() > followed  # the next start takes it
    # a board whose clock is unset (1970), with our own timestamp a day from the margin
    assert SigningState(OWN_LIMIT_UNITS - day).peer_limit_units(0) == OWN_LIMIT_UNITS


def test_our_timestamp_never_passes_the_48_bit_margin_whatever_the_wall_clock(tmp_path) -> None:
    """A board whose clock says 2110 (past 2**48 units since 2015): our timestamp stops a day
    short of 2**48 instead of wrapping (every frame after the wrap a replay), and what is
    persisted passes the next start's check."""
    from companion.drivers.signing import OWN_LIMIT_UNITS

    year_2110_s = 4_417_977_600.0
    assert wall_units(year_2110_s) >= 2**48
    store = TimestampStore(tmp_path / "ts")
    first = store.start(year_2110_s)
    assert first <= OWN_LIMIT_UNITS
    assert TimestampStore(store.path).read(year_2110_s) > first  # the next start accepts it


def _autopilot_side(peer: Peer, stop: Any, hostile: list[Any], log: list[tuple[str, int]]) -> None:
    """An autopilot holding the key: a signed HEARTBEAT every 0.1 s; once the service answers,
    the ``hostile`` signers' HEARTBEATs (its own address and stream, a wrong clock) once.
    Logs what it took from the service: ("signed", our stream's timestamp) or ("refused", 0)."""
    sent_hostile = False
    next_beat = 0.0
    while not stop.is_set():
        if time.monotonic() >= next_beat:
            peer.send(peer.mav.heartbeat_encode(2, 12, 0, 0, 4))
            next_beat = time.monotonic() + 0.1
        try:
            data = peer.sock.recv(4096)
        except TimeoutError:
            continue
        for m in peer.mav.parse_buffer(data) or []:
            if m.get_type() == "BAD_DATA":
                log.append(("refused", 0))
            elif m.get_srcComponent() == 197:
                log.append(("signed", int(peer.mav.signing.stream_timestamps[(0, 1, 197)])))
        if log and not sent_hostile:
            for mav in hostile:
                peer.send(mav.heartbeat_encode(2, 12, 0, 0, 4), mav)
            sent_hostile = True


def test_hostile_clocks_on_a_signed_link_neither_stop_signing_nor_the_next_start(
    tmp_path,
) -> None:
    """The real start-up path (``companion run``) twice against an autopilot holding the key:
    during the first run it also sends one HEARTBEAT stamped two years ahead and one at the
    48-bit edge. The service keeps signing frames the autopilot takes (our timestamp near
    the wall clock), says what it refused, and its second start succeeds and signs: before,
    the first frame's timestamp was persisted and the second start exited 2, and the second
    made our timestamp wrap (replays)."""
    import json
    import threading

    from companion.cli import main

    port = free_port(socket.SOCK_DGRAM)
    key = write_key(tmp_path / "key", KEY)
    ts_file = tmp_path / "state" / "signing_timestamp"
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        f'[service]\nmavlink_url = "udpin:127.0.0.1:{port}"\n'
        f'camera_url = "sitl://127.0.0.1:{free_port()}"\n'
        f'status_socket = "{tmp_path / "s.sock"}"\nstate_dir = "{tmp_path / "state"}"\n'
        f'signing = {{ key_file = "{key}", timestamp_file = "{ts_file}" }}\n'
    )
    autopilot = Peer(KEY, port)
    wrong_clocks = [
        _signer(KEY, wall_units() + 2 * YEAR_S * UNITS_PER_S),
        _signer(KEY, 2**48 - 60),
    ]
    for mav in wrong_clocks:
        mav.signing.link_id = 3  # the autopilot's own stream
    runs: list[tuple[int, list[tuple[str, int]]]] = []
    for k, hostile in enumerate([wrong_clocks, []]):
        stop, got = threading.Event(), []
        side = threading.Thread(target=_autopilot_side, args=(autopilot, stop, hostile, got))
        side.start()
        try:
            report = tmp_path / f"report{k}.json"
            code = main(["run", "--config", str(cfg), "--duration", "3", "--report", str(report)])
        finally:
            stop.set()
            side.join()
        runs.append((code, got))
    for code, got in runs:
        assert code == 0
        assert len(got) >= 5 and all(kind == "signed" for kind, _ in got)
        assert max(ts for _, ts in got) < wall_units() + 2 * RESERVE_UNITS  # near the clock
    signing = json.loads((tmp_path / "report0.json").read_text())["signing"]
    assert signing["far_ahead"] == 2 and signing["good_signatures"] >= 10


def test_companion_status_shows_the_frames_stamped_too_far_ahead() -> None:
    """The operator's view says why the autopilot's frames are refused (its clock)."""
    from companion.cli.service import _signing_text

    counters = {
        "good_signatures": 5,
        "bad_signatures": 2,
        "refused": 0,
        "far_ahead": 2,
    }
    assert _signing_text({"signing": counters}).endswith("0 refused, 2 stamped too far ahead")
    counters["far_ahead"] = 0
    assert _signing_text({"signing": counters}).endswith("0 refused")
