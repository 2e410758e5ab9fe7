"""How the simulated camera delivers its frames ([sitl.delivery], sitl/world/scenario.py):
lossy periods lose frames without losing a sample, and jittered stamps stay in order."""

from __future__ import annotations

import pickle

import numpy as np

from companion.config import Config, load_config
from companion.sitl.world.scenario import Scenario, lost_frames
from companion.sitl_options import DeliveryFaults

PERIOD_S = 1.0 / 30.0
SMALL_CAMERA = {"width": 160, "height": 120, "fx": 115.0, "fy": 115.0, "cx": 79.5, "cy": 59.5}


def _config(delivery: dict[str, float], seconds: float = 1.0) -> Config:
    return load_config(
        None,
        {
            "camera": SMALL_CAMERA,
            "sitl": {"terrain": "flat", "seconds": seconds, "seed": 2, "delivery": delivery},
        },
    )


def test_a_lossy_period_loses_its_share_of_frames_there_only() -> None:
    assert lost_frames(DeliveryFaults(), 3000, PERIOD_S, 1) == frozenset()
    window = DeliveryFaults(loss_from_s=20.0, loss_to_s=50.0, loss_in_burst=0.4)
    lost = lost_frames(window, 3000, PERIOD_S, 1)
    assert lost == lost_frames(window, 3000, PERIOD_S, 1)  # seeded
    times_s = np.array(sorted(lost)) * PERIOD_S
    assert times_s.min() >= 20.0 and times_s.max() < 50.0
    assert 0.35 < len(lost) / 900 < 0.45  # 900 frames in the window
    # random periods: about the rate x length x probability of the flight's frames
    bursts = DeliveryFaults(loss_bursts_per_min=3.0, loss_burst_s=5.0, loss_in_burst=0.5)
    shares = [len(lost_frames(bursts, 18000, PERIOD_S, s)) / 18000 for s in range(1, 9)]
    assert 0.05 < float(np.mean(shares)) < 0.25  # expected 3 x 5 / 60 x 0.5 = 0.125


def _runs(lost: frozenset[int]) -> list[int]:
    """The lengths of the runs of consecutive sequence numbers in ``lost``."""
    runs: list[int] = []
    for q in sorted(lost):
        if runs and q - 1 in lost:
            runs[-1] += 1
        else:
            runs.append(1)
    return runs


def test_a_capture_that_stalls_loses_its_share_in_runs() -> None:
    """The real downward flight lost 43 % of its frames in runs of 7 on the mean: runs of that
    mean at that share; one frame at a time (the default) the runs are 1 / (1 - 0.42) = 1.7."""
    window = {"loss_from_s": 10.0, "loss_to_s": 610.0, "loss_in_burst": 0.42}
    alone = lost_frames(DeliveryFaults(**window), 40000, 1 / 60, 3)
    runs = lost_frames(DeliveryFaults(**window, loss_run_frames=7.0), 40000, 1 / 60, 3)
    assert 1.5 < float(np.mean(_runs(alone))) < 1.9
    assert 6.0 < float(np.mean(_runs(runs))) < 8.0 and max(_runs(runs)) >= 20
    for lost in (alone, runs):
        times_s = np.array(sorted(lost)) / 60
        assert times_s.min() >= 10.0 and times_s.max() < 610.0
        assert 0.39 < len(lost) / 36000 < 0.45  # the window's 36,000 frames
    assert runs == lost_frames(DeliveryFaults(**window, loss_run_frames=7.0), 40000, 1 / 60, 3)


def test_lost_frames_are_not_delivered_and_their_samples_come_with_the_next() -> None:
    plain = list(Scenario(_config({})).steps())
    lossy_cfg = _config({"loss_from_s": 0.2, "loss_to_s": 0.8, "loss_in_burst": 0.5})
    lossy = Scenario(lossy_cfg)
    got = list(lossy.steps())
    assert lossy.lost and [s.frame.seq for s in got] == [
        s.frame.seq for s in plain if s.frame.seq not in lossy.lost
    ]
    last = got[-1].frame.seq
    for name in ("ranges", "attitudes"):  # every sample up to the last frame, once, in order
        want = [x for s in plain if s.frame.seq <= last for x in getattr(s, name)]
        assert pickle.dumps([x for s in got for x in getattr(s, name)]) == pickle.dumps(want)
    by_seq = {s.frame.seq: s for s in plain}
    for s in got:  # the image and the truth of its own capture
        assert np.array_equal(s.frame.image_bgr, by_seq[s.frame.seq].frame.image_bgr)
        assert np.array_equal(s.T_world_body, by_seq[s.frame.seq].T_world_body)


def test_a_capture_that_numbers_only_what_it_delivers() -> None:
    """With numbers_lost false the delivered frames are numbered 0, 1, 2, ... (the gap is
    only in the stamps, as in the real downward flight's files); the images are the same."""
    window = {"loss_from_s": 0.2, "loss_to_s": 0.8, "loss_in_burst": 0.5}
    skipped = list(Scenario(_config(window)).steps())
    counted = Scenario(_config({**window, "numbers_lost": False}))
    got = list(counted.steps(workers=2))
    assert counted.lost and [s.frame.seq for s in got] == list(range(len(got)))
    assert [s.frame.seq for s in skipped] != list(range(len(skipped)))
    for a, b in zip(skipped, got, strict=True):
        assert a.frame.time_us == b.frame.time_us
        assert np.array_equal(a.frame.image_bgr, b.frame.image_bgr)


def test_jittered_stamps_stay_near_the_capture_and_in_order() -> None:
    sc = Scenario(_config({"stamp_jitter_ms": 14.0}, seconds=20.0))
    capture = np.array([sc.frame_time_us(q) for q in range(sc.n_frames)])
    stamps = np.array([sc.stamp_us(q) for q in range(sc.n_frames)])
    off_ms = (stamps - capture) * 1e-3
    assert np.all(np.diff(stamps) >= 1000)
    assert off_ms.min() >= -14.0 and off_ms.max() <= 14.0 + 2.0  # +1 ms per frame in order
    assert 6.0 < off_ms.std() < 10.0  # uniform in +-14 ms: 8.1 ms
    plain = Scenario(_config({}, seconds=20.0))
    assert [plain.stamp_us(q) for q in range(5)] == [plain.frame_time_us(q) for q in range(5)]
