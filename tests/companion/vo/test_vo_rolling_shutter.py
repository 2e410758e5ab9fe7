"""The first-order rolling-shutter correction (companion/vo/rolling_shutter.py): a camera
moving and turning over uneven ground, every row exposed at its own time; the corrected pixels
are where a global shutter at the frame's stamp would have seen the points."""

from __future__ import annotations

import numpy as np

from companion.geometry import so3
from companion.geometry.camera import CameraModel
from companion.vo.rolling_shutter import (
    ShutterCorrection,
    fit_velocity_field,
    row_offsets_s,
)

CAMERA = CameraModel(640, 480, 460.0, 460.0, 319.5, 239.5)
READOUT_S = 0.020
RATE_HZ = 30.0


def _pose(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(R_cam_world, camera centre) of a camera 6 m over the ground looking down, flying 3 m/s
    along x while turning 30 deg/s about its optical axis."""
    R_world_cam = so3.rot_z(np.radians(30.0) * t_s) @ so3.rot_x(np.pi)
    return R_world_cam.T, np.array([3.0 * t_s, 0.0, 6.0])


def _rolling_pixels(X_world: np.ndarray, t_s: float, readout_s: float) -> np.ndarray:
    """(N, 2) where a rolling-shutter camera at stamp ``t_s`` sees the points (N, 3): each row
    at its own time (equation (1)), solved as a fixed point over the row."""
    R, c = _pose(t_s)
    uv, _ = CAMERA.project((X_world - c) @ R.T)
    for _ in range(8):
        uv_next = np.empty_like(uv)
        for i, (x, v) in enumerate(zip(X_world, uv[:, 1], strict=True)):
            R, c = _pose(t_s + float(row_offsets_s(np.array([v]), 480, readout_s)[0]))
            uv_next[i] = CAMERA.project(((x - c) @ R.T)[None])[0][0]
        uv = uv_next
    return uv


def _ground(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-3.5, 3.5, (n, 2)) * [1.0, 0.75]
    return np.column_stack([xy, rng.uniform(0.0, 1.5, n)])  # bumps up to 1.5 m


def _two_frames(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rolling-shutter pixels (N, 2) of seeded ground points in two frames 1/30 s apart, and
    where a global shutter at the second frame's stamp sees them."""
    X = _ground(60, seed)
    t1 = 1.0 / RATE_HZ
    R, c = _pose(t1)
    truth, _ = CAMERA.project((X - c) @ R.T)
    return _rolling_pixels(X, 0.0, READOUT_S), _rolling_pixels(X, t1, READOUT_S), truth


def test_row_offsets_span_the_readout_about_the_stamp() -> None:
    dt = row_offsets_s(np.array([-0.5, 239.5, 479.5]), 480, READOUT_S)
    assert np.allclose(dt, [-0.010, 0.0, 0.010])


def test_the_field_fit_recovers_an_affine_motion_despite_outliers() -> None:
    rng = np.random.default_rng(3)
    px = rng.uniform(0, 640, (80, 2))
    A = np.array([[0.5, -2.0, 90.0], [2.0, 0.5, -40.0]])
    w = np.column_stack([px, np.ones(80)]) @ A.T
    w[:10] += rng.uniform(-500, 500, (10, 2))  # one track in eight jumped
    fit = fit_velocity_field(px, w)
    assert fit is not None and np.abs(fit - A).max() < 1e-6
    assert fit_velocity_field(px[:7], w[:7]) is None


def test_corrected_pixels_are_the_global_shutter_ones_at_the_stamp() -> None:
    prev_px, px, truth = _two_frames(1)
    shutter = ShutterCorrection(READOUT_S, 480)
    shutter.update(px, prev_px, 1.0 / RATE_HZ)
    corrected = shutter.at_frame_time(px, prev_px)
    before = np.linalg.norm(px - truth, axis=1)
    after = np.linalg.norm(corrected - truth, axis=1)
    assert before.max() > 2.0  # the rolling shutter moves the edge rows by pixels
    assert after.max() < 0.1 * before.max() and after.max() < 0.2


def test_new_corners_take_the_field_and_a_global_shutter_is_untouched() -> None:
    prev_px, px, truth = _two_frames(2)
    t1 = 1.0 / RATE_HZ
    shutter = ShutterCorrection(READOUT_S, 480)
    shutter.update(px[:40], prev_px[:40], t1)
    new = px[40:]
    corrected = shutter.at_frame_time(new)  # no pixel before: the field's motion
    same = shutter.at_frame_time(new, new.copy())  # a new corner's own pixel as before
    before = np.linalg.norm(new - truth[40:], axis=1)
    assert np.linalg.norm(corrected - truth[40:], axis=1).max() < 0.35 * before.max()
    assert np.array_equal(same, corrected)
    still = ShutterCorrection(READOUT_S, 480)
    still.update(px, None, t1)  # nothing followed: no motion known, nothing moved
    assert np.array_equal(still.at_frame_time(px), px)
    assert shutter.at_frame_time(np.zeros((0, 2))).shape == (0, 2)


def test_a_pipeline_told_the_readout_publishes_the_true_track() -> None:
    """10 s of hills lawnmower at 3 m/s under a 20 ms rolling shutter, one rendered flight fed
    to two pipelines: the one told ``camera.readout_ms`` publishes a track within 3 cm RMS of
    the truth (translation-aligned); the other is sheared by the shutter (6.4 cm when
    written, 2.5x the told one's at least)."""
    from companion.config import load_config
    from companion.offline import feed_step
    from companion.pipeline import Pipeline
    from companion.sitl.world.scenario import Scenario

    over: dict = {
        "sitl": {
            "terrain": "hills",
            "trajectory": "lawnmower",
            "seconds": 10.0,
            "seed": 2,
            "render": {"readout_ms": 20.0},
        }
    }
    cfg = load_config(None, over)
    pipes = {
        "untold": Pipeline(cfg),
        "told": Pipeline(load_config(None, {**over, "camera": {"readout_ms": 20.0}})),
    }
    assert pipes["told"].vo.shutter is not None and pipes["untold"].vo.shutter is None
    est: dict[str, list] = {k: [] for k in pipes}
    truth: list = []
    for k, step in enumerate(Scenario(cfg).steps()):
        poses = {}
        for name, p in pipes.items():
            poses[name] = feed_step(p, step)
            p.background_work()
        if k > 60 and all(pose is not None for pose in poses.values()):
            for name, pose in poses.items():
                est[name].append(pose.position_ned_m)
            truth.append(step.T_world_body[:3, 3].copy())
    gt = np.array(truth)
    rms = {}
    for name, positions in est.items():
        e = np.array(positions)
        err = np.linalg.norm((e - e.mean(axis=0)) - (gt - gt.mean(axis=0)), axis=1)
        rms[name] = float(np.sqrt(np.mean(err**2)))
        assert pipes[name].vo.resets == 0
    assert len(gt) > 200
    assert rms["told"] < 0.03 and rms["untold"] > 2.5 * rms["told"], rms
