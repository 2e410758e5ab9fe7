"""The local bundle adjustment one iteration at a time: the same result to the bit as at once,
for the solver and for the map; spread over the frames after its keyframe, a flight still
tracked to the same bound as with the BA at its keyframe."""

from __future__ import annotations

import copy
import dataclasses
from typing import Any

import numpy as np
import pytest

from companion.config import Config, load_config
from companion.evaluation.trajectory import ate_rmse, path_length
from companion.geometry import se3, so3
from companion.sitl.world.scenario import Scenario, Step
from companion.types import VoState
from companion.vo import ba
from companion.vo.ba import BundleAdjustment
from companion.vo.odometry import VisualOdometry

F = 460.0


def _problem(rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """Five cameras over 200 points at 3-8 m, 0.5 px noise, the last three perturbed."""
    X = np.column_stack([rng.uniform(-3, 3, (200, 2)), rng.uniform(3.0, 8.0, 200)])
    T_true = np.stack(
        [
            se3.make(so3.rpy_to_matrix(0.02 * k, -0.01 * k, 0.05 * k), [-0.3 * k, 0.1 * k, 0.0])
            for k in range(5)
        ]
    )
    cams, pts, xys = [], [], []
    for k in range(5):
        p = se3.transform(T_true[k], X)
        xy = p[:, :2] / p[:, 2:3] + rng.normal(0, 0.5 / F, (len(X), 2))
        seen = np.flatnonzero(rng.uniform(size=len(X)) < 0.85)
        cams.append(np.full(len(seen), k))
        pts.append(seen)
        xys.append(xy[seen])
    T0 = T_true.copy()
    for k in range(2, 5):
        T0[k] = se3.exp(rng.normal(0, [0.03, 0.03, 0.03, 0.01, 0.01, 0.01])) @ T_true[k]
    X0 = X + rng.normal(0, 0.05, X.shape)
    gravity = T0[:, :3, 2] + rng.normal(0, 0.002, (5, 3))  # a gravity prior on every camera
    return T0, X0, np.concatenate(cams), np.concatenate(pts), np.concatenate(xys), gravity


def _levenberg_marquardt(args: tuple[Any, ...]) -> tuple[np.ndarray, np.ndarray, int]:
    """The loop the BA ran before it could be stepped, written out on the module's parts:
    iterate until the iterations are spent or the damping passes 1e6."""
    T, X, oc, op, ox, fixed, focal_px, huber_px, iterations, gravity, weight = args
    win = ba._window(oc, op, ox, fixed, focal_px, len(X))
    prior = ba._gravity_prior(gravity, weight, fixed)
    r, p_c = win.residuals(T, X)
    state = ba._State(T.copy(), X.copy(), r, p_c, ba._total_cost(r, T, huber_px, prior))
    lam, done = 1e-4, 0
    for it in range(1, iterations + 1):
        done = it
        ne = ba._normal_equations(state, win, prior, huber_px)
        state, lam = ba._damped_step(state, lam, ne, win, prior, huber_px)
        if lam > 1e6:
            break
    return state.T, state.X, done


def test_the_bundle_adjustment_stepped_is_the_loop_at_once_to_the_bit() -> None:
    T0, X0, oc, op, ox, gravity = _problem(np.random.default_rng(8))
    T0_kept = T0.copy()
    fixed = np.array([True, True, False, False, False])
    args = (T0, X0, oc, op, ox, fixed, F, 2.0, 6, gravity, 50.0)
    T_ref, X_ref, iterations = _levenberg_marquardt(args)
    stepped = BundleAdjustment(*args)
    costs = [stepped.result().cost_after]
    while stepped.step():
        costs.append(stepped.result().cost_after)
    costs.append(stepped.result().cost_after)
    assert stepped.done and not stepped.step()  # nothing left: a step more changes nothing
    res = stepped.result()
    assert res.iterations == iterations == 6
    assert np.array_equal(res.T_cam_vo, T_ref) and np.array_equal(res.points_vo, X_ref)
    run = BundleAdjustment(*args).run()
    for name in ("T_cam_vo", "points_vo", "residual_px"):
        assert np.array_equal(getattr(res, name), getattr(run, name)), name
    assert np.all(np.diff(costs) <= 0)  # LM never goes up
    assert costs[-1] < 0.05 * costs[0]
    assert np.array_equal(T0, T0_kept)  # the caller's arrays are not touched
    assert not np.array_equal(res.T_cam_vo[2:], T0[2:])  # and the free cameras moved


@pytest.fixture(scope="module")
def hills_flight() -> tuple[Config, list[Step]]:
    """14 s of a hills figure-eight, seed 2 (the VO's accuracy test's flight)."""
    sitl = {"terrain": "hills", "trajectory": "figure8", "seconds": 14.0, "seed": 2}
    cfg = load_config(overrides={"sitl": sitl})
    return cfg, list(Scenario(cfg).steps(workers=2))


def _vo(cfg: Config, per_frame: int) -> VisualOdometry:
    opts = dataclasses.replace(cfg.vo, ba_iterations_per_frame=per_frame)
    return VisualOdometry(cfg.camera.model(), cfg.camera.T_body_cam(), opts)


def test_the_local_ba_of_a_map_stepped_is_the_one_at_once(
    hills_flight: tuple[Config, list[Step]],
) -> None:
    """A flown map's local BA, begun, iterated one step at a time and ended, leaves every
    keyframe, point and observation as VoMap.local_ba does."""
    cfg, steps = hills_flight
    vo = _vo(cfg, 0)
    for s in steps[:150]:
        vo.process(s.frame, s.T_world_body[:3, :3])
    assert vo.state == VoState.TRACKING and len(vo.map.keyframes) >= 4
    # The flight may end just after a keyframe's BA converged (no step lowers the cost then):
    # seeded noise of 0.5 % of the points' typical distance gives the BA something to undo.
    rng = np.random.default_rng(0)
    spread = float(np.median([np.linalg.norm(x) for x in vo.map.points.values()]))
    for p in vo.map.points:
        vo.map.points[p] = vo.map.points[p] + rng.normal(0.0, 0.005 * spread, 3)
    a, b = copy.deepcopy(vo.map), copy.deepcopy(vo.map)
    T_a = a.local_ba(vo.opts, vo.focal_px)
    job = b.begin_local_ba(vo.opts, vo.focal_px)
    assert T_a is not None and job is not None
    while job.problem.step():
        pass
    T_b = b.end_local_ba(job, vo.opts.inlier_px)
    assert np.array_equal(T_a, T_b)
    for kf_a, kf_b in zip(a.keyframes, b.keyframes, strict=True):
        assert np.array_equal(kf_a.T_cam_vo, kf_b.T_cam_vo)
        assert kf_a.obs.keys() == kf_b.obs.keys()
    assert a.points.keys() == b.points.keys()
    assert all(np.array_equal(a.points[p], b.points[p]) for p in a.points)
    moved = [not np.array_equal(a.points[p], vo.map.points[p]) for p in a.points]
    assert np.mean(moved) > 0.3  # the BA did move the points


def test_a_flight_with_the_local_ba_spread_over_frames(
    hills_flight: tuple[Config, list[Step]],
) -> None:
    """One BA iteration in each frame's work after a keyframe (``refine_map``, run after the
    pose as the pipeline runs it): each BA ends within its iterations' frames, its result
    moves the current pose and the one before with the newest keyframe (the motion since it
    kept: T T_kf^-1 the same before and after), and the flight is tracked to the bound of the
    BA at its keyframe (test_vo.py: 98 % tracked, no reset, Sim(3) ATE under 1 %)."""
    cfg, steps = hills_flight
    vo = _vo(cfg, 1)
    outs, running, moved = [], [], []
    for s in steps:
        outs.append(vo.process(s.frame, s.T_world_body[:3, :3]))
        built = vo.finish_pending()  # the keyframe's work, then an iteration: background_work
        job = vo.map.ba_job
        if built:  # a BA begun: its first iteration in the next frame's work
            assert job is not None and job.problem.iterations_done == 0
            assert not vo.refine_map()
        elif job is not None:
            kf = job.window[-1]
            T_kf = kf.T_cam_vo
            rel = (vo.T_cam_vo @ se3.inverse(T_kf), vo.T_prev @ se3.inverse(T_kf))
            assert vo.refine_map()
            if vo.map.ba_job is None:  # it ended here: the pose moved with the keyframe
                after = (
                    vo.T_cam_vo @ se3.inverse(kf.T_cam_vo),
                    vo.T_prev @ se3.inverse(kf.T_cam_vo),
                )
                np.testing.assert_allclose(after[0], rel[0], atol=1e-9)
                np.testing.assert_allclose(after[1], rel[1], atol=1e-9)
                moved.append(np.linalg.norm(se3.log(kf.T_cam_vo @ se3.inverse(T_kf))))
            assert not vo.refine_map()  # once a frame
        running.append(vo.map.ba_job is not None)
    first = [o.state for o in outs].index(VoState.TRACKING)
    tracked = [o.state == VoState.TRACKING for o in outs[first:]]
    assert vo.resets == 0 and np.mean(tracked) >= 0.98
    runs = np.diff(np.flatnonzero(np.diff(np.r_[0, running, 0])))[::2]  # frames per BA
    assert len(runs) >= 10 and runs.max() <= cfg.vo.ba_iterations, runs
    assert len(moved) >= 10 and np.median(moved) > 1e-6  # the BAs moved their keyframes
    T_body_cam = cfg.camera.T_body_cam()
    ok = [i for i in range(first, len(outs)) if outs[i].state == VoState.TRACKING]
    est = np.array([outs[i].T_vo_cam[:3, 3] for i in ok])
    gt = np.array([(steps[i].T_world_body @ T_body_cam)[:3, 3] for i in ok])
    ate, _ = ate_rmse(est, gt, "sim3")
    assert ate / path_length(gt) < 0.01
