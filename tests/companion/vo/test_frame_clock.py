"""The steady clock of camera frames (companion/vo/frame_clock.py): jittered stamps are
re-timed, a steady clock is left alone, and a simulated flight whose stamps alternate 2 ms /
64 ms intervals (as a real downward camera's did) tracks without a reset."""

from __future__ import annotations

import csv
import dataclasses
import itertools
from pathlib import Path

import numpy as np
import pytest

from companion.config import load_config
from companion.drivers.dataset import open_dataset
from companion.offline import run_vo
from companion.sitl.world.dataset import record
from companion.types import VoState
from companion.vo.frame_clock import FrameClock, jitter_warning

PERIOD_US = 33_333


def alternating(n: int, short_us: int = 2_000) -> list[int]:
    """Stamps of frames exposed every PERIOD_US whose odd frames are stamped ``short_us``
    after the even frame before them (intervals short, 2 periods - short, ...)."""
    true = [k * PERIOD_US for k in range(n)]
    return [t if k % 2 == 0 else true[k - 1] + short_us for k, t in enumerate(true)]


def retime(clock: FrameClock, stamps: list[int], seqs: list[int] | None = None) -> list[int]:
    seqs = seqs if seqs is not None else list(range(len(stamps)))
    return [clock.time_us(s, t) for s, t in zip(seqs, stamps, strict=True)]


def test_a_steady_clock_is_left_alone() -> None:
    """Stamps with 0.5 ms of noise and frames dropped upstream (sequence gaps) pass through
    unchanged: re-timing them would only add the line's error."""
    rng = np.random.default_rng(4)
    seqs = [k for k in range(400) if k % 7 != 3]  # every 7th frame dropped upstream
    stamps = [int(k * PERIOD_US + rng.normal(0, 500)) for k in seqs]
    clock = FrameClock()
    assert retime(clock, stamps, seqs) == stamps
    assert clock.retimed == 0
    report = clock.report()
    assert report is not None and not report.jittery
    assert report.period_ms == pytest.approx(PERIOD_US * 1e-3, rel=0.01)


def test_alternating_stamps_are_re_timed_to_the_steady_period() -> None:
    stamps = alternating(300)
    clock = FrameClock()
    out = retime(clock, stamps)
    steps = np.diff(out[clock.min_frames :])
    # the raw intervals are 2 and 64.7 ms; re-timed ones within 10 % of the period
    assert np.all(np.abs(steps - PERIOD_US) < 0.1 * PERIOD_US)
    assert clock.retimed == len(stamps) - clock.min_frames + 1
    # the line passes through the middle of the stamps: half the 31 ms offset of odd frames
    true = np.arange(300) * PERIOD_US
    offset_ms = (np.array(out[60:]) - true[60:]).mean() * 1e-3
    assert offset_ms == pytest.approx(-(PERIOD_US - 2_000) * 0.5e-3, abs=1.0)
    report = clock.report()
    assert report is not None and report.jittery
    assert report.min_interval_ms == pytest.approx(2.0) and report.max_interval_ms > 60.0
    text = jitter_warning(report)
    assert "2.0...64.7 ms" in text and "33.3 ms" in text and f"{clock.retimed} frames" in text


def test_re_timed_frames_keep_the_gaps_of_dropped_frames() -> None:
    seqs = [k for k in range(300) if k % 5 != 2]
    stamps = [alternating(300)[k] for k in seqs]
    out = retime(FrameClock(), stamps, seqs)
    steps = np.diff(out[20:]) / np.diff(seqs[20:])  # per frame step
    assert np.all(np.abs(steps - PERIOD_US) < 0.1 * PERIOD_US)


def test_a_pause_restarts_the_line_and_times_stay_increasing() -> None:
    """A camera that stops 5 s: the first frame after keeps its stamp (a break of the clock),
    and the frames stay in strict time order throughout."""
    stamps = alternating(100) + [t + 5_000_000 for t in alternating(100)[1:]]
    clock = FrameClock()
    out = retime(clock, stamps)
    assert clock.breaks == 1
    assert out[100] == stamps[100]
    assert all(b > a for a, b in itertools.pairwise(out))


@pytest.fixture(scope="module")
def jittered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated 8 s figure-eight recorded at 30 Hz whose frames.csv stamps then alternate
    2 ms / 64.7 ms intervals (the images, ranges and attitude stay where they were)."""
    folder = tmp_path_factory.mktemp("jitter") / "figure8"
    cfg = load_config(
        overrides={"sitl": {"terrain": "hills", "trajectory": "figure8", "seconds": 8.0}}
    )
    record(cfg, folder, progress=False)
    rows = list(csv.reader((folder / "frames.csv").open()))
    stamps = alternating(len(rows) - 1)
    assert [int(r[0]) for r in rows[1:3]] == [0, PERIOD_US]  # as rendered
    with (folder / "frames.csv").open("w", newline="") as fh:
        csv.writer(fh).writerows(
            [rows[0], *([str(t), *r[1:]] for t, r in zip(stamps, rows[1:], strict=True))]
        )
    return folder


@pytest.mark.parametrize("steady_clock", [True, False])
def test_a_flight_with_alternating_stamps_tracks_without_a_reset(
    jittered: Path, steady_clock: bool
) -> None:
    """With the steady clock: 0 resets and every frame after the start tracked. Without it
    (the VO's constant-velocity prediction scaled by the raw intervals) the same frames
    break the tracking: the test would catch the clock being bypassed."""
    ds = open_dataset(jittered)
    assert ds.config is not None
    cfg = dataclasses.replace(
        ds.config, vo=dataclasses.replace(ds.config.vo, steady_clock=steady_clock)
    )
    run = run_vo(cfg, ds.events(), camera=ds.camera, T_body_cam=ds.T_body_cam)
    tracking = np.array([s == VoState.TRACKING for s in run.state])
    after_start = tracking[int(np.argmax(tracking)) :]
    if steady_clock:
        assert run.resets == 0 and after_start.mean() >= 0.98
        assert run.clock is not None and run.clock.jittery
        assert run.clock.retimed >= len(run.state) - 10  # all but the first few
    else:
        assert run.resets >= 3 and after_start.mean() < 0.9
        assert run.clock is None


def test_frames_lost_without_a_sequence_gap_are_not_jitter() -> None:
    """A steady camera that lost every 5th frame while its frames were numbered 0, 1, 2, ...
    (a converted list of kept frames): intervals of one and two periods, stamps exact, so they
    pass unchanged."""
    stamps = [k * PERIOD_US for k in range(300) if k % 5 != 2]
    clock = FrameClock()
    assert retime(clock, stamps) == stamps and clock.retimed == 0
