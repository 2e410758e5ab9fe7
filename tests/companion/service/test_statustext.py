"""STATUSTEXT to the ground station (issue 20): the transitions, the rate limit with a fake
clock and the wire encoding (on the wire, end to end: tests/e2e/test_statustext_delivery.py)."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from peers.mavlink_peers import join_chunks
from pymavlink.dialects.v20 import common as mavlink

from companion.config import load_config
from companion.drivers import messages
from companion.service import statustext as st
from companion.service.statustext import INITIAL, Event, Limiter, OperatorState, Severity

PREFIX = "CMP: "


def texts(events: list[Event]) -> list[tuple[str, Severity, str]]:
    return [(e.key, e.severity, e.text) for e in events]


# ---------------------------------------------------------------------------------------------
# transitions: a pure function of two snapshots
# ---------------------------------------------------------------------------------------------

TRACKING = OperatorState(vo_state="TRACKING", scale_ready=True, scale_sensors=4)


@pytest.mark.parametrize(
    ("prev", "cur", "expected"),
    [
        (INITIAL, OperatorState(camera="no frames"), [("camera", 4, "camera lost: no frames")]),
        (
            INITIAL,
            OperatorState(camera="no frames (1280x720, calibrated 640x480)"),
            [("camera", 4, "camera lost: no frames (1280x720, calibrated 640x480)")],
        ),
        (
            OperatorState(armed=True),
            OperatorState(camera="frozen", armed=True),
            [("camera", 2, "camera lost: frozen frames")],  # CRITICAL in flight
        ),
        (
            OperatorState(camera="frozen"),
            OperatorState(camera="dark"),
            [("camera", 4, "camera lost: dark frames")],
        ),
        (OperatorState(camera="dark"), INITIAL, [("camera", 6, "camera ok")]),
        (
            INITIAL,
            TRACKING,
            [("vo", 6, "VO tracking"), ("scale", 6, "scale ready (4 sensors)")],
        ),
        (
            OperatorState(vo_state="TRACKING"),
            OperatorState(vo_state="TRACKING", scale_ready=True, scale_sensors=0),
            [("scale", 6, "scale ready")],  # a ground start's metric prior alone
        ),
        # a VO loss says the scale is gone too: no second message for it
        (TRACKING, OperatorState(vo_state="LOST"), [("vo", 4, "VO lost")]),
        (
            OperatorState(vo_state="INITIALIZING"),
            OperatorState(vo_state="TRACKING", vo_resets=2),
            [("vo", 5, "VO tracking again, reset 2")],
        ),
        (
            TRACKING,
            dataclasses.replace(TRACKING, vo_resets=1),  # lost and back between two snapshots
            [("vo", 5, "VO re-initialised, reset 1")],
        ),
        (
            dataclasses.replace(TRACKING, reset_counter=3),
            dataclasses.replace(TRACKING, reset_counter=4),
            [("reset", 5, "pose reset: counter 4")],
        ),
        (
            dataclasses.replace(TRACKING, reset_counter=None),
            dataclasses.replace(TRACKING, reset_counter=7),  # the first pose sent: no reset
            [],
        ),
        (
            TRACKING,
            dataclasses.replace(TRACKING, scale_ready=False),
            [("scale", 4, "scale lost: not publishing")],
        ),
        (
            TRACKING,
            dataclasses.replace(TRACKING, attitude_ready=True),
            [("attitude", 6, "roll/pitch from rangefinders ready")],
        ),
        (
            dataclasses.replace(TRACKING, attitude_ready=True),
            TRACKING,
            [("attitude", 5, "roll/pitch from rangefinders lost")],
        ),
        (
            OperatorState(autopilot_silent_s=2.9),
            OperatorState(autopilot_silent_s=3.1),
            [("link", 4, "no autopilot heartbeat for 3 s")],
        ),
        (
            OperatorState(autopilot_silent_s=12.4),
            OperatorState(autopilot_silent_s=0.1),
            [("link", 5, "autopilot link back after 12 s")],
        ),
        (OperatorState(autopilot_silent_s=None), OperatorState(autopilot_silent_s=0.5), []),
        (
            OperatorState(rangefinder_faults=frozenset({1})),
            OperatorState(rangefinder_faults=frozenset({3})),
            [("rf3", 4, "rangefinder 3: serial fault"), ("rf1", 6, "rangefinder 1: serial ok")],
        ),
        (
            TRACKING,
            dataclasses.replace(TRACKING, lens="k1 +0.021"),
            [("lens", 4, "camera calibration off: k1 +0.021")],
        ),
        (
            dataclasses.replace(TRACKING, lens="k1 +0.021"),
            dataclasses.replace(TRACKING, lens="k1 +0.021"),
            [],
        ),
        (
            INITIAL,
            OperatorState(dpose_armed=True, dpose_locked=True),
            [("dpose-armed", 6, "d-Pose armed: laser marks set"), ("dpose", 6, "d-Pose lock")],
        ),
        (
            OperatorState(dpose_armed=True, dpose_locked=True),
            OperatorState(dpose_armed=True),
            [("dpose", 5, "d-Pose lock lost")],
        ),
        # a second source speaking as the autopilot (a spoofer, a second router): named
        (
            INITIAL,
            OperatorState(link_rival="127.0.0.1:14555"),
            [("rival", 4, "second autopilot at 127.0.0.1:14555")],
        ),
        (
            OperatorState(armed=True, link_rival="127.0.0.1:14555"),
            OperatorState(armed=True, link_rival="10.0.0.9:14550"),
            [("rival", 2, "second autopilot at 10.0.0.9:14550")],  # CRITICAL in flight
        ),
        (OperatorState(link_rival="127.0.0.1:1"), OperatorState(link_rival="127.0.0.1:1"), []),
        (OperatorState(link_rival="127.0.0.1:1"), INITIAL, []),
    ],
)
def test_each_transition_gives_its_event(
    prev: OperatorState, cur: OperatorState, expected: list[tuple[str, int, str]]
) -> None:
    assert texts(st.transitions(prev, cur)) == expected


def random_state(rng: np.random.Generator) -> OperatorState:
    return OperatorState(
        camera=[None, "no frames", "frozen", "dark", "saturated", "blank", "out_of_order"][
            int(rng.integers(7))
        ],
        vo_state=["INITIALIZING", "TRACKING", "LOST"][int(rng.integers(3))],
        vo_resets=int(rng.integers(0, 300)),
        reset_counter=None if rng.random() < 0.2 else int(rng.integers(0, 256)),
        scale_ready=bool(rng.random() < 0.5),
        scale_sensors=int(rng.integers(0, 9)),
        attitude_ready=bool(rng.random() < 0.5),
        autopilot_silent_s=None if rng.random() < 0.2 else float(rng.uniform(0, 9999)),
        rangefinder_faults=frozenset(int(i) for i in rng.choice(10, int(rng.integers(0, 4)))),
        dpose_armed=bool(rng.random() < 0.5),
        dpose_locked=bool(rng.random() < 0.5),
        armed=bool(rng.random() < 0.5),
    )


def test_random_transitions_fit_one_statustext_and_nothing_changes_nothing() -> None:
    rng = np.random.default_rng(2020)
    n_events = 0
    for _ in range(3000):
        a, b = random_state(rng), random_state(rng)
        assert st.transitions(a, a) == [] and st.transitions(b, b) == []
        events = st.transitions(a, b)
        n_events += len(events)
        keys = [e.key for e in events]
        assert len(keys) == len(set(keys)), keys  # one event per subject and step
        assert [e.severity for e in events] == sorted(e.severity for e in events)
        for e in events:
            assert len(e.text) <= st.MAX_TEXT_CHARS and st.ascii_text(e.text) == e.text, e
            assert messages.statustext_chunk_count(PREFIX + e.text) == 1
        # the camera's severity follows the armed flag
        cam = [e for e in events if e.key == "camera" and b.camera is not None]
        assert all(e.severity == (Severity.CRITICAL if b.armed else Severity.WARNING) for e in cam)
    assert n_events > 3000


def test_start_and_stop_events() -> None:
    started = st.start_events("0.1.0", "odometry", ["service.camera_url: /dev/video9 gone"])
    assert texts(started) == [
        ("service", Severity.NOTICE, "started v0.1.0, ODOMETRY"),
        ("config0", Severity.WARNING, "config: service.camera_url: /dev/video9 gone"),
    ]
    assert st.stop_event(None, False) == Event("service", Severity.NOTICE, "stopping")
    assert st.stop_event(None, True).severity == Severity.WARNING
    assert st.stop_event("pipeline error (ValueError)", True) == Event(
        "service", Severity.CRITICAL, "stopped on pipeline error (ValueError)"
    )


def test_held_and_recent_increase() -> None:
    held = st.Held(1.0)
    assert [held.update(v, t) for v, t in [(False, 0.0), (True, 0.1), (False, 0.5)]] == [
        False,
        True,
        True,  # a short drop is held
    ]
    assert held.update(False, 1.2) is False
    lock = st.RecentIncrease(1.0)
    seq = [(5, 0.0), (5, 0.5), (6, 0.6), (6, 1.5), (6, 1.7), (9, 1.8)]
    assert [lock.update(c, t) for c, t in seq] == [False, False, True, True, False, True]


# ---------------------------------------------------------------------------------------------
# the limiter, with a fake clock
# ---------------------------------------------------------------------------------------------


def run_limiter(
    limiter: Limiter, offers: list[tuple[float, Event]], until_s: float, step_s: float = 0.1
) -> list[tuple[float, Severity, str]]:
    """Offer each event at its time and call take() every step_s (as the service's loop
    does) until ``until_s``; what was sent, with its time."""
    sent: list[tuple[float, Severity, str]] = []
    offers = sorted(offers, key=lambda o: o[0])
    i = 0
    for k in range(int(round(until_s / step_s)) + 1):
        now = k * step_s
        while i < len(offers) and offers[i][0] <= now + 1e-9:
            limiter.offer(offers[i][1], offers[i][0])
            i += 1
        sent += [(now, sev, text) for sev, text in limiter.take(now)]
    return sent


def test_a_camera_flapping_at_20_hz_is_one_message_per_interval_and_ends_on_its_last_state() -> (
    None
):
    limiter = Limiter(key_interval_s=2.0, burst=5, rate_hz=1.0, prefix=PREFIX)
    lost = Event("camera", Severity.WARNING, "camera lost: no frames")
    ok = Event("camera", Severity.INFO, "camera ok")
    # lost at 0.00, ok at 0.05, lost at 0.10, ... for 10 s, the last change "ok" at 9.95 s
    offers = [(k * 0.05, lost if k % 2 == 0 else ok) for k in range(200)]
    sent = run_limiter(limiter, offers, 20.0, step_s=0.05)
    times = [t for t, _, _ in sent]
    assert sent[0] == (0.0, Severity.WARNING, "CMP: camera lost: no frames")
    assert all(b - a >= 2.0 - 1e-9 for a, b in itertools.pairwise(times))
    assert len(sent) <= 10.0 / 2.0 + 2  # 200 changes: 6 messages
    # the last state is reported, with how many changes it stands for, soon after the burst
    assert sent[-1][2].startswith("CMP: camera ok [") and sent[-1][1] == Severity.INFO
    assert sent[-1][0] <= 9.95 + 2.0 + 1e-9
    assert limiter.pending == 0 and limiter.stats.last_sent["camera"] == "camera ok"
    assert limiter.stats.offered == 200 and limiter.stats.sent == len(sent)


def test_random_bursts_keep_every_limit_and_report_every_final_state() -> None:
    """Seeded random bursts on eight subjects: per-subject spacing, the token bucket over
    every window, per-subject order, and every subject's last state reported."""
    for seed in range(8):
        rng = np.random.default_rng([seed, 20])
        interval, burst, rate = 2.0, 5, 1.0
        limiter = Limiter(interval, burst, rate, prefix=PREFIX)
        keys = [f"k{i}" for i in range(8)]
        offers: list[tuple[float, Event]] = []
        t = 0.0
        for n in range(400):  # bursts: clusters of changes 0-5 ms apart, gaps up to 3 s
            t += float(rng.exponential(0.005) if rng.random() < 0.8 else rng.uniform(0.1, 3.0))
            key = keys[int(rng.integers(len(keys)))]
            sev = Severity(int(rng.integers(2, 7)))
            offers.append((t, Event(key, sev, f"{key} state {n}")))
        end = t
        sent = run_limiter(limiter, offers, end + 30.0)
        times = np.array([s[0] for s in sent])
        # the bucket: at most burst + rate * W messages in any window of W seconds
        for i in range(len(times)):
            for j in range(i, len(times)):
                assert j - i + 1 <= burst + rate * (times[j] - times[i]) + 1e-9
        by_key: dict[str, list[tuple[float, str]]] = {}
        for t_sent, _, text in sent:
            body = text.removeprefix(PREFIX).split(" [")[0]
            by_key.setdefault(body.split()[0], []).append((t_sent, body))
        offered_order = {e.text: n for n, (_, e) in enumerate(offers)}
        for key, items in by_key.items():
            ts = [x[0] for x in items]
            assert all(b - a >= interval - 1e-9 for a, b in itertools.pairwise(ts))
            order = [offered_order[x[1]] for x in items]
            assert order == sorted(order), key  # never an older state after a newer one
        for key in keys:  # no stale final state
            last = [e.text for _, e in offers if e.key == key]
            if last:
                assert by_key[key][-1][1] == last[-1], (seed, key)
        assert limiter.pending == 0
        # every offer was sent or replaced by a newer one of its subject, none lost
        assert (
            limiter.stats.sent + limiter.stats.coalesced
            == len(offers)
            == len(sent) + (limiter.stats.coalesced)
        )
        assert limiter.stats.coalesced > len(offers) / 2  # the bursts were coalesced


def test_the_most_severe_goes_first_when_tokens_are_short() -> None:
    limiter = Limiter(key_interval_s=0.0, burst=4, rate_hz=0.5, prefix=PREFIX)
    for i in range(4):
        limiter.offer(Event(f"info{i}", Severity.INFO, f"info {i}"), 0.0)
    assert len(limiter.take(0.0)) == 4  # the bucket is empty now
    limiter.offer(Event("late-info", Severity.INFO, "late info"), 0.1)
    limiter.offer(Event("crit", Severity.CRITICAL, "camera lost"), 0.5)
    assert limiter.take(1.0) == []  # 0.5 tokens
    assert limiter.take(2.0) == [(Severity.CRITICAL, "CMP: camera lost")]
    assert limiter.take(3.9) == []
    assert limiter.take(4.0) == [(Severity.INFO, "CMP: late info")]


def test_a_long_text_costs_a_token_per_chunk_and_drain_ignores_the_limits() -> None:
    limiter = Limiter(key_interval_s=0.0, burst=4, rate_hz=1.0, prefix=PREFIX)
    long_text = "config: " + "x" * 120  # 133 characters with the prefix: 3 chunks
    limiter.offer(Event("config0", Severity.WARNING, long_text), 0.0)
    limiter.offer(Event("a", Severity.WARNING, "second"), 0.0)
    limiter.offer(Event("b", Severity.WARNING, "third"), 0.0)
    out = limiter.take(0.0)
    assert [t for _, t in out] == [PREFIX + long_text, "CMP: second"]  # 3 + 1 tokens
    assert limiter.stats.messages == 4 and limiter.pending == 1
    limiter.offer(Event("c", Severity.INFO, "fourth"), 0.0)
    assert limiter.take(0.0) == []
    assert [t for _, t in limiter.drain(0.0)] == ["CMP: third", "CMP: fourth"]
    assert limiter.pending == 0


def test_bad_limits_are_refused() -> None:
    with pytest.raises(ValueError):
        Limiter(burst=0)
    with pytest.raises(ValueError):
        Limiter(rate_hz=0.0)


# ---------------------------------------------------------------------------------------------
# the wire
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [0, 1, 49, 50, 51, 99, 100, 101, 150, 199])
def test_statustext_chunks_round_trip_through_pymavlink(n: int) -> None:
    text = "".join(chr(ord("a") + k % 26) for k in range(n))
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
    msgs = messages.statustext(mav, 4, text, 77)
    assert len(msgs) == messages.statustext_chunk_count(text)
    rx = mavlink.MAVLink(None)
    got = [rx.parse_char(m.pack(mav)) for m in msgs]
    assert [int(g.chunk_seq) for g in got] == list(range(len(got)))
    assert {int(g.id) for g in got} == ({0} if n <= 50 else {77})
    assert join_chunks(got) == [(4, text)]


def test_statustext_is_cut_to_four_chunks_and_ascii() -> None:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
    msgs = messages.statustext(mav, 3, "é" + "y" * 400, 5)
    rx = mavlink.MAVLink(None)
    ((sev, text),) = join_chunks([rx.parse_char(m.pack(mav)) for m in msgs])
    assert len(msgs) == messages.STATUSTEXT_MAX_CHUNKS and sev == 3
    assert text.startswith("?yyy") and text.endswith("...") and len(text) == 199
    with pytest.raises(ValueError):
        messages.statustext(mav, 3, "z" * 60, 0)  # a chunked text needs an id


def test_the_prefix_is_checked_in_the_config() -> None:
    from companion.errors import ConfigError

    with pytest.raises(ConfigError, match=r"service\.statustext\.prefix"):
        load_config(None, {"service": {"statustext": {"prefix": "COMPANION: "}}})
    with pytest.raises(ConfigError, match=r"service\.statustext\.burst"):
        load_config(None, {"service": {"statustext": {"burst": 1}}})
