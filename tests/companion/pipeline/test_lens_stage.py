"""The focal length checked in flight (companion/pipeline/lens_stage.py): a seeded simulated
figure8 (rolls, pitches and turns) rendered once, fed to pipelines whose camera file says
fx fy 10 % larger, 10 % smaller than the renderer's, and right, and one whose k1 is 0.02 too
small, measured and (with [vo] learn_lens) taken in flight."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import replace
from typing import Any

import pytest

from companion.config import Config, load_config
from companion.offline import feed_step
from companion.pipeline import Pipeline
from companion.pipeline.lens_stage import fitted_lens
from companion.pipeline.status import PipelineStatus
from companion.types import VoState
from companion.vo.focal_check import FocalRatio

# a 320 x 240 camera with the default's field of view keeps the flight short to render
SMALL_CAMERA = {"width": 320, "height": 240, "fx": 230.0, "fy": 230.0, "cx": 159.5, "cy": 119.5}


@pytest.fixture(scope="module")
def flight() -> tuple[Config, list[Any]]:
    from companion.sitl.world.scenario import Scenario

    sitl = {"terrain": "hills", "trajectory": "figure8", "seconds": 8.0, "seed": 3}
    cfg = load_config(None, {"camera": SMALL_CAMERA, "sitl": sitl})
    return cfg, list(Scenario(cfg).steps())


def _flown(pipe: Pipeline, steps: Iterable[Any]) -> PipelineStatus:
    """The pipeline's status after the flight's steps, each with its background work."""
    for step in steps:
        feed_step(pipe, step)
        pipe.background_work()
    return pipe.status()


@pytest.mark.parametrize("file_over_true", [1.1, 0.9, 1.0])
def test_a_wrong_focal_length_is_seen_in_flight(
    flight: tuple[Config, list[Any]], file_over_true: float
) -> None:
    cfg, steps = flight
    true = cfg.camera.model()
    camera_file = replace(true, fx=true.fx * file_over_true, fy=true.fy * file_over_true)
    status = _flown(Pipeline(cfg, camera=camera_file), steps)
    ratio = status.lens_focal_ratio
    assert ratio is not None and status.lens_focal_spread is not None
    assert status.lens_focal_samples >= 30
    if file_over_true == 1.0:
        assert ratio == pytest.approx(1.0, abs=0.02)
        assert status.lens_warning is None
    else:
        assert ratio == pytest.approx(1.0 / file_over_true, rel=0.03)
        way = "too large" if file_over_true > 1.0 else "too small"
        assert status.lens_warning is not None and way in status.lens_warning
        assert "check [camera] fx fy" in status.lens_warning


def test_a_wrong_k1_is_seen_in_flight_and_not_taken_for_the_focal(
    flight: tuple[Config, list[Any]],
) -> None:
    """Before the joint search of focal and k1, a k1 0.02 off read as a focal 13.7 % off
    (a 40 s hills lawnmower) and warned of the focal length."""
    cfg, steps = flight
    true = cfg.camera.model()
    status = _flown(Pipeline(cfg, camera=replace(true, k1=true.k1 - 0.02)), steps)
    assert status.lens_focal_samples >= 30
    assert status.lens_focal_ratio == pytest.approx(1.0, abs=0.04)  # 0.982 when written
    assert status.lens_k1_delta == pytest.approx(0.02, abs=0.006)
    warning = status.lens_warning or ""
    assert "k1 looks" in warning and "too small" in warning and "check [camera] dist" in warning
    assert "focal length" not in warning
    assert status.lens_brief is not None and status.lens_brief.startswith("k1 +0.0")


def test_a_learned_lens_is_taken_once_and_the_vo_goes_on_with_it(
    flight: tuple[Config, list[Any]],
) -> None:
    """[vo] learn_lens: the k1 the check finds replaces the file's in every stage that
    projects or undoes the lens (the VO restarts, once), and the flight goes on tracking."""
    cfg, steps = flight
    true = cfg.camera.model()
    learning = replace(cfg, vo=replace(cfg.vo, learn_lens=True))
    pipe = Pipeline(learning, camera=replace(true, k1=true.k1 - 0.02))
    resets_at_take = None
    for step in steps:
        feed_step(pipe, step)
        pipe.background_work()
        if resets_at_take is None and pipe.lens.taken:
            resets_at_take = pipe.vo.resets
    status = pipe.status()
    assert pipe.lens.taken == 1 and resets_at_take is not None
    assert pipe.camera.k1 == pytest.approx(true.k1, abs=0.006)
    assert pipe.camera.fx == true.fx and pipe.camera.fy == true.fy  # the focal was right
    assert pipe.vo.camera is pipe.camera and pipe.lens.check.camera is pipe.camera
    assert all(m.camera is pipe.camera for m in pipe.methods.values())
    assert status.lens_learned == (true.fx, true.fy, pipe.camera.k1)
    assert "learned in flight" in (status.lens_warning or "")
    assert status.vo_state == VoState.TRACKING.name and pipe.vo.resets == resets_at_take + 1


def test_the_fitted_lens_takes_what_was_found_and_nothing_else() -> None:
    camera = load_config().camera.model()
    est = FocalRatio(1.1, 0.05, 0.005, 80, 0, 0.021, 0.005, 0.0006)
    focal = fitted_lens(camera, est, ["focal x1.100"])
    assert focal is not None and focal.fx == pytest.approx(camera.fx * 1.1)
    assert focal.k1 == camera.k1 and focal.cx == camera.cx
    k1 = fitted_lens(camera, est, ["k1 +0.021"])
    assert k1 is not None and k1.fx == camera.fx and k1.k1 == pytest.approx(camera.k1 + 0.021)
    both = fitted_lens(camera, est, ["focal x1.100", "k1 +0.021"])
    assert both is not None and both.fy == pytest.approx(camera.fy * 1.1)
    assert both.k1 == pytest.approx(camera.k1 + 0.021)
    assert fitted_lens(camera, est, ["fits no lens model"]) is None


def test_the_lens_check_waits_for_a_frame_without_keyframe_or_ba_work(
    flight: tuple[Config, list[Any]],
) -> None:
    """With the local BA spread over frames, the lens check's pairing never shares a frame's
    work with a keyframe or a BA iteration, and finds what it finds when it never waits: the
    same ratio and k1 error, from the same keyframe pairs."""
    cfg, steps = flight
    cfg = replace(cfg, vo=replace(cfg.vo, ba_iterations_per_frame=1))
    results = []
    for wait in (True, False):
        pipe = Pipeline(cfg)
        lens_work = pipe.lens.work
        calls: list[tuple[bool, bool]] = []

        def work(
            busy: bool = False, lens_work: Any = lens_work, calls: Any = calls, wait: bool = wait
        ) -> bool:
            paired = bool(lens_work(busy and wait))
            calls.append((busy, paired))
            return paired

        pipe.lens.work = work  # type: ignore[method-assign]
        for step in steps:
            feed_step(pipe, step)
            pipe.background_work()
        assert pipe.vo.resets == 0
        busy = [b for b, _ in calls]
        paired = [p for _, p in calls]
        assert sum(busy) >= 20 and sum(paired) >= 10
        if wait:
            assert not any(b and p for b, p in calls)  # never on a busy frame
        else:
            assert any(b and p for b, p in calls)  # without waiting, it would share some
        results.append(pipe.lens.result())
    assert results[0] is not None and results[0] == results[1]


def test_a_rolling_shutter_is_not_taken_for_a_wrong_lens() -> None:
    """Under a rolling shutter each row is seen at its own time while the attitude is the
    stamp's: the check takes the features at the stamp (VisualOdometry.pixels_at_stamp). From
    the rows as seen, this flight (a quadrotor flown about by hand low over a checkerboard
    floor, 20 ms readout, the camera file right) read f x1.387 and warned "focal length looks
    18.7 % too small"."""
    from companion.sitl.world.scenario import Scenario

    camera = {**SMALL_CAMERA, "readout_ms": 20.0}
    sitl = {
        "terrain": "flat",
        "trajectory": "bob",
        "seconds": 12.0,
        "seed": 3,
        "render": {"readout_ms": 20.0},
        "ground": {"surface": "checkerboard", "checker_m": 0.05},
    }
    cfg = load_config(None, {"camera": camera, "sitl": sitl})
    status = _flown(Pipeline(cfg), Scenario(cfg).steps())
    assert status.lens_focal_samples >= 50
    assert status.lens_focal_ratio == pytest.approx(1.0, abs=0.03)  # 1.001 when written
    assert status.lens_k1_delta == pytest.approx(0.0, abs=0.006)
    assert status.lens_warning is None
