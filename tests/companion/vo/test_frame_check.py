"""Camera faults before the VO: the frame check, and the pipeline's behaviour around them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from companion.config import load_config
from companion.offline import feed_step
from companion.pipeline import Pipeline
from companion.sitl.world.scenario import Scenario
from companion.types import CameraFrame
from companion.vo.frame_check import FrameCheck, FrameProblem, _channel_mean


@pytest.fixture(scope="module")
def steps() -> list[object]:
    cfg = load_config(
        overrides={"sitl": {"terrain": "hills", "trajectory": "lawnmower", "seconds": 14.0}}
    )
    return list(Scenario(cfg).steps(workers=2))  # rendered on 2 threads


def _frame(t_us: int, seq: int, img: np.ndarray) -> CameraFrame:
    return CameraFrame(t_us, seq, img)


def test_each_failure_mode_has_its_verdict(steps: list[object]) -> None:
    img = steps[40].frame.image_bgr  # type: ignore[attr-defined]
    other = steps[41].frame.image_bgr  # type: ignore[attr-defined]
    chk = FrameCheck()
    assert chk.check(_frame(1000, 0, img)) is None
    assert chk.check(_frame(2000, 1, other)) is None  # noise: two exposures always differ
    assert chk.check(_frame(3000, 2, other.copy())) == FrameProblem.FROZEN
    assert chk.check(_frame(2500, 3, img)) == FrameProblem.OUT_OF_ORDER
    assert chk.check(_frame(4000, 4, np.zeros_like(img))) == FrameProblem.DARK
    assert chk.check(_frame(5000, 5, np.full_like(img, 255))) == FrameProblem.SATURATED
    assert chk.check(_frame(6000, 6, np.full_like(img, 128))) == FrameProblem.BLANK
    # a noisy but textureless frame (a lens against a wall) is blank too, a dim one is fine
    rng = np.random.default_rng(3)
    flat = np.clip(128 + rng.normal(0, 1.0, img.shape), 0, 255).astype(np.uint8)
    assert chk.check(_frame(7000, 7, flat)) == FrameProblem.BLANK
    dim = (img.astype(np.float64) * 0.25).astype(np.uint8)
    assert chk.check(_frame(8000, 8, dim)) is None
    night = (img.astype(np.float64) * 0.02).astype(np.uint8)  # dark, with a few lights
    night[::40, ::40] = 255
    night[100:140, 200:260] = 230
    assert float(night.mean()) < 12 and chk.check(_frame(9000, 9, night)) is None
    assert chk.counts == {
        "out_of_order": 1,
        "frozen": 1,
        "dark": 1,
        "saturated": 1,
        "blank": 2,
    }


def _run(steps: list[object], faulty: dict[int, np.ndarray | None]) -> tuple[Pipeline, list]:
    """Feed the flight; frames listed in ``faulty`` get that image (None: the frame is lost)."""
    pipe = Pipeline(load_config())
    poses = []
    for s in steps:
        seq = s.frame.seq  # type: ignore[attr-defined]
        if seq in faulty:
            img = faulty[seq]
            if img is None:
                poses.append(None)
                continue
            s = dataclasses.replace(s, frame=CameraFrame(s.frame.time_us, seq, img))  # type: ignore
        poses.append(feed_step(pipe, s))
    return pipe, poses


def test_a_frozen_camera_gives_no_pose_and_resumes_with_a_new_reset_counter(
    steps: list[object],
) -> None:
    frozen_img = steps[209].frame.image_bgr  # type: ignore[attr-defined]
    pipe, poses = _run(steps, {k: frozen_img.copy() for k in range(210, 240)})  # 1 s frozen
    assert poses[209] is not None and poses[209].reset_counter == 0
    assert all(p is None for p in poses[210:240])  # nothing from a frozen image
    assert pipe.frame_check.counts["frozen"] == 30
    back = [k for k in range(240, len(poses)) if poses[k] is not None]
    assert back and back[0] < 240 + 90, "no pose within 3 s of the camera's return"
    assert poses[back[0]].reset_counter == 1  # the autopilot is told: a discontinuity
    assert pipe.gaps == 1 and pipe.vo.resets == 1
    # the new map's scale starts weak (init_sigma_rel 0.2, a few matches in by its first
    # pose): the covariance (one sample's noise: 2 cm + the scale's relative sigma over 1 m)
    # and the quality say so, then the sigma shrinks as the lasers' matches come in
    # (0.026 m before the freeze, 0.064 at the first new pose, 0.029 a second later)
    sigma_m = [np.sqrt(p.covariance_6x6[0, 0]) if p is not None else np.nan for p in poses]
    assert sigma_m[back[0]] > 2.0 * sigma_m[209]
    assert poses[back[0]].quality_pct < poses[209].quality_pct - 20
    assert np.nanmax(sigma_m[back[0] + 30 : back[0] + 45]) < 0.5 * sigma_m[back[0]]


def test_one_bad_frame_is_skipped_without_a_reset(steps: list[object]) -> None:
    img = steps[150].frame.image_bgr  # type: ignore[attr-defined]
    pipe, poses = _run(steps, {150: np.zeros_like(img), 151: None, 152: None})
    assert poses[149] is not None and poses[150] is None
    assert all(p is not None and p.reset_counter == 0 for p in poses[153:])
    assert pipe.gaps == 0 and pipe.frame_check.counts["dark"] == 1


def test_a_gap_without_frames_resets(steps: list[object]) -> None:
    pipe, poses = _run(steps, dict.fromkeys(range(210, 255)))  # 1.5 s unplugged
    assert pipe.gaps == 1
    back = [p for p in poses[255:] if p is not None]
    assert back and all(p.reset_counter == 1 for p in back)


def test_gaps_shorter_than_max_gap_are_tracked_across(steps: list[object]) -> None:
    """A busy machine's camera path loses runs of frames: the PX4 loop on a slow 2-core host
    (2026-11-27) had gaps of up to 433 ms, and each one over the old 250 ms limit re-initialised
    the VO in the air. 0.8 s without frames every 3 s of a lawnmower over hills: no reset, and
    the positions stay within 0.15 m of the flight without gaps (6.6 cm measured on
    2026-11-27; 10.9 cm on the machine of 2026-11-28 with b6f1fd7's code as well: a reset or a lost
    map is metres)."""
    gaps = {k for k in range(120, len(steps)) if (k - 120) % 90 < 24}  # 24 frames = 0.8 s
    pipe, poses = _run(steps, dict.fromkeys(gaps))
    assert pipe.gaps == 0 and pipe.vo.resets == 0
    _, ref = _run(steps, {})
    both = [k for k in range(len(steps)) if poses[k] is not None and ref[k] is not None]
    assert len(both) > 250 and all(k not in gaps for k in both)
    dev = [np.linalg.norm(poses[k].position_ned_m - ref[k].position_ned_m) for k in both]
    assert max(dev) < 0.15, max(dev)


def test_skipped_frames_do_not_lose_tracking(steps: list[object]) -> None:
    """The service hands the VO the newest frame: a stall after a keyframe skips 2-4 frames
    (67-133 ms, 15-30 px of flow), beyond what a KLT started at zero motion follows. Skip 3
    frames out of every 20 for the whole flight: tracking must never be lost."""
    lost = {k for k in range(100, len(steps)) if k % 20 in (1, 2, 3)}
    pipe, poses = _run(steps, dict.fromkeys(lost))
    assert pipe.vo.resets == 0 and pipe.gaps == 0
    tracked = [k for k in range(100, len(steps)) if k not in lost]
    assert all(poses[k] is not None for k in tracked)


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_the_channel_mean_is_numpys_to_the_bit(channels: int) -> None:
    """The check's grey level is the channels' mean, the same bits as NumPy's (its verdicts
    then cannot move): random levels, a saturated band and a black one."""
    rng = np.random.default_rng(channels)
    sample = rng.integers(0, 256, (60, 80, channels), dtype=np.uint8)
    sample[:5] = 255
    sample[5:10] = 0
    got = _channel_mean(sample)
    assert got.dtype == np.float64
    assert np.array_equal(got, sample.mean(axis=2))
    assert float(got.std()) == float(sample.mean(axis=2).std())
