"""MAVLink signing against hostile clocks: a frame stamped far ahead refused, counted and
logged once, a peer ahead by up to 30 days followed without walking us forward, what it leaves
behind passing the next start, our timestamp within the 48-bit margin whatever the wall clock;
and the signing parser against forged frames and unknown message ids."""

from __future__ import annotations

import socket
import time
from typing import Any

import numpy as np
from peers import free_port
from peers.signing_peers import KEY, Peer, parser_with_signing, signer, write_key
from pymavlink.dialects.v20 import common as mavlink

from companion.drivers.mavlink_parser import LinkStats, Parser
from companion.drivers.signing import (
    RESERVE_UNITS,
    UNITS_PER_S,
    Signing,
    TimestampStore,
    wall_units,
)


def test_a_forged_frame_cannot_lock_out_the_autopilot() -> None:
    """pymavlink records a stream's timestamp before checking the MAC: one frame with a
    junk signature and timestamp 2**48 - 2 would make every later genuine frame 'old'."""
    parser, state = parser_with_signing()
    autopilot, attacker = signer(KEY, wall_units()), signer(bytes(32), 2**48 - 2)
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
    parser, _ = parser_with_signing()
    u = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    buf = bytearray(u.heartbeat_encode(2, 12, 0, 0, 4).pack(u))
    buf[7:10] = (0x123456).to_bytes(3, "little")
    stats = LinkStats()
    assert parser.feed(bytes(buf), stats, True) == [] and stats.rx_bad == 1


YEAR_S = 365 * 86400


def _heartbeat(mav: Any) -> bytes:
    return bytes(mav.heartbeat_encode(2, 12, 0, 0, 4).pack(mav))


def test_a_genuine_frame_stamped_far_ahead_is_refused_counted_and_logged_once(caplog) -> None:
    """An autopilot holding the key with a wrong real-time clock: its frames stamped two
    years ahead, or at the 48-bit edge, must not move our timestamp (accepted, the first
    was persisted and refused by our next start; the second made ours wrap within a few
    frames: every later frame a replay) nor its stream's (its later right frames would be
    replays); they are refused, counted, logged once; the right frames still pass."""
    parser, state = parser_with_signing()
    ours_before = state.timestamp
    now = wall_units()
    stats = LinkStats()
    hostile = [signer(KEY, now + 2 * YEAR_S * UNITS_PER_S), signer(KEY, 2**48 - 60)]
    with caplog.at_level("WARNING", logger="companion.signing"):
        for mav in hostile * 3:
            got = parser.feed(_heartbeat(mav), stats, True)
            # the heartbeat stays visible (as an unsigned one may), never authentic
            assert [(m.get_type(), m.get_signed()) for m in got] == [("HEARTBEAT", False)]
    assert state.timestamp < now + 60 * UNITS_PER_S  # ours did not move
    assert state.stream_timestamps == {}  # nor the stream's
    autopilot = signer(KEY, now)
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
    parser, state = parser_with_signing()
    now = wall_units()
    stats = LinkStats()
    day = 86400 * UNITS_PER_S
    ahead = signer(KEY, now + 29 * day)
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
        peer = signer(KEY, wall_units() + min(days_ahead_of_wall + 29, 365) * day)
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
        signer(KEY, wall_units() + 2 * YEAR_S * UNITS_PER_S),
        signer(KEY, 2**48 - 60),
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
