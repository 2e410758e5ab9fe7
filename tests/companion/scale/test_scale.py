"""Metric scale: MSC on a known scale, the Kalman filter, ML fusion, baselines on hand-made
inputs, time alignment of ranges, and no position jump when the scale changes."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from companion.config import load_config
from companion.geometry import se3
from companion.geometry.camera import CameraModel
from companion.scale import msc
from companion.scale.fusion import fuse
from companion.scale.kalman import ScaleKalman
from companion.scale.laser import RangeHistory, laser_point_cam
from companion.scale.methods import (
    MMSC,
    B7WindowML,
    B8PerFrame,
    B9Plane,
    MetricTrajectory,
    MMSCwK,
    ReuseCounter,
    ScaleInput,
)
from companion.scale.options import ScaleOptions
from companion.types import RangeSample, VoFeatures, VoOutput, VoState

CAM = CameraModel(640, 480, 460.0, 460.0, 319.5, 239.5, -0.12, 0.05, 0.0005, -0.0003, 0.0)


def scene_features(
    depth_of_ray: Callable[[np.ndarray], np.ndarray],
    T_cam_vo: np.ndarray,
    scale: float,
    rng: np.random.Generator | None = None,
) -> VoFeatures:
    """Map points on a 16 px pixel grid (jittered by up to 4 px when ``rng`` is given) whose
    metric depth (camera z) is ``depth_of_ray(rays (N, 3))``, in VO units (metres / scale)."""
    u, v = np.meshgrid(np.arange(8, 632, 16.0), np.arange(8, 472, 16.0))
    pix = np.column_stack([u.ravel(), v.ravel()])
    if rng is not None:
        pix = pix + rng.uniform(-4, 4, (u.size, 2))
    n = len(pix)
    rays = CAM.pixels_to_rays(pix)
    P_cam = rays * (depth_of_ray(rays) / rays[:, 2])[:, None]
    X_vo = se3.transform(se3.inverse(T_cam_vo), P_cam / scale)
    return VoFeatures(pix, np.arange(n, dtype=np.int64), X_vo, np.full(n, 0.001))


def ground_features(T_cam_vo: np.ndarray, scale: float, rng: np.random.Generator) -> VoFeatures:
    """Map points of a flat ground 5 m below a level camera, at jittered pixels."""
    return scene_features(lambda r: np.full(len(r), 5.0), T_cam_vo, scale, rng)


def test_msc_recovers_a_known_scale_with_noiseless_ranges() -> None:
    rng = np.random.default_rng(1)
    s_true = 7.3
    T_cam_vo = se3.make(np.eye(3), [0.1, -0.2, 0.05])
    feats = ground_features(T_cam_vo, s_true, rng)
    cfg = load_config()
    T_cam_body = se3.inverse(cfg.camera.T_body_cam())
    for rf in cfg.rangefinders:
        spec = rf.spec()
        # the true range of a level vehicle: the beam hits z_cam = 5
        beam_cam = T_cam_body[:3, :3] @ spec.T_body_rf[:3, 2]
        o_cam = se3.transform(T_cam_body, spec.T_body_rf[:3, 3])
        d = (5.0 - o_cam[2]) / beam_cam[2]
        p_cam = laser_point_cam(spec, T_cam_body, d)
        assert np.isclose(p_cam[2], 5.0)
        m = msc.measure(rf.sensor_id, feats, T_cam_vo, CAM, p_cam, 0.0, 12.0, 0.5)
        assert m is not None and m.pixel_offset_px <= 12.0 * np.sqrt(2)
        assert abs(m.scale / s_true - 1) < 0.005
        assert m.sigma > 0
    # nothing in the patch: no measurement
    empty = VoFeatures(np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0))
    assert msc.measure(0, empty, T_cam_vo, CAM, np.array([0, 0, 5.0]), 0.01, 12, 0.5) is None
    assert msc.measure(0, feats, T_cam_vo, CAM, np.array([50.0, 0, 5.0]), 0.01, 12, 0.5) is None


def _laser_at(pixel: tuple[float, float], depth_m: float) -> np.ndarray:
    ray = CAM.pixels_to_rays(np.array([pixel]))[0]
    return np.asarray(ray * depth_m / ray[2])


def test_msc_refuses_a_match_across_a_roof_edge_but_not_on_a_slope() -> None:
    """A roof 2 m above the ground (12 m below the camera) covers the image left of u = 316;
    the beam hits the ground at (318, 236), whose nearest map point (312, 232) is on the
    roof: the plain match is off by the step (+20 %), the depth-step check refuses it. On a
    plane inclined 15 deg and on a plane ground the check lets the match through."""
    opts = ScaleOptions()
    assert opts.edge_depth_rel > 0  # on by default
    s_true = 3.0
    T_cam_vo = se3.make(np.eye(3), [0.2, 0.1, -0.3])
    roof_u = CAM.pixels_to_rays(np.array([[316.0, 240.0]]))[0, 0]

    def roof(rays: np.ndarray) -> np.ndarray:
        return np.where(rays[:, 0] < roof_u, 10.0, 12.0)

    feats = scene_features(roof, T_cam_vo, s_true)
    laser = _laser_at((318.0, 236.0), 12.0)
    args = (feats, T_cam_vo, CAM, laser, 0.01, opts.patch_half_px, opts.slope_factor)
    plain = msc.measure(0, *args)
    assert plain is not None and plain.scale / s_true - 1 > 0.15  # 12 m / 10 m
    uv = msc.laser_pixel(CAM, laser)
    assert uv is not None
    assert msc.spans_depth_step(feats, T_cam_vo, uv, opts.edge_radius_px, opts.edge_depth_rel)
    assert msc.measure(0, *args, opts.edge_radius_px, opts.edge_depth_rel) is None
    # off (0) means no check
    assert msc.measure(0, *args, opts.edge_radius_px, 0.0) is not None

    tan15 = np.tan(np.radians(15.0))
    for name, depth in {
        "slope 15 deg": lambda r: 8.0 / (1.0 - r[:, 0] * tan15),
        "level": lambda r: np.full(len(r), 8.0),
    }.items():
        feats = scene_features(depth, T_cam_vo, s_true)
        for pixel in [(318.0, 236.0), (100.0, 60.0), (600.0, 420.0)]:
            ray = CAM.pixels_to_rays(np.array([pixel]))
            laser = _laser_at(pixel, float(depth(ray)[0]))
            m = msc.measure(
                0,
                feats,
                T_cam_vo,
                CAM,
                laser,
                0.01,
                opts.patch_half_px,
                opts.slope_factor,
                opts.edge_radius_px,
                opts.edge_depth_rel,
            )
            assert m is not None, (name, pixel)
            assert abs(m.scale / s_true - 1) < 0.03, (name, pixel, m.scale)


def test_kalman_converges_and_rejects_a_10x_outlier() -> None:
    rng = np.random.default_rng(2)
    kf = ScaleKalman(random_walk_per_s=0.01, gate_chi2=6.63)
    kf.initialize(0, 4.0, 1.0)
    for k in range(1, 200):
        assert kf.update(k * 33_333, 5.0 + rng.normal(0, 0.05), 0.05)
    # steady state of a 1 %/sqrt(s) random walk with 0.05 measurements at 30 Hz: sigma ~0.021
    assert kf.sigma < 0.025 and abs(kf.scale - 5.0) < 3 * kf.sigma
    before = kf.scale
    assert not kf.update(200 * 33_333, 50.0, 0.05)  # 10x: gated out
    assert kf.scale == before and kf.rejected == 1
    assert not kf.update(201 * 33_333, float("nan"), 0.05)


def test_ml_fusion_is_the_inverse_variance_mean_and_drops_outliers() -> None:
    s = np.array([5.0, 5.1, 4.95, 5.05])
    sg = np.array([0.05, 0.1, 0.02, 0.04])
    res = fuse(s, sg)
    assert res is not None
    w = 1 / sg**2
    assert np.isclose(res[0], np.sum(w * s) / np.sum(w))
    assert np.isclose(res[1], 1 / np.sqrt(np.sum(w)))
    assert res[2].all()
    res2 = fuse(np.append(s, 9.0), np.append(sg, 0.05))  # a wall edge
    assert res2 is not None and not res2[2][-1] and np.isclose(res2[0], res[0])
    assert fuse(np.array([np.nan]), np.array([0.1])) is None


def test_applying_a_new_scale_does_not_move_the_position() -> None:
    traj = MetricTrajectory()
    p = np.array([1.0, 2.0, -1.0])
    a = traj.step(p, 5.0, 0)
    b = traj.step(p, 6.0, 0)  # scale update while hovering: no jump
    assert np.array_equal(a, b)
    c = traj.step(p + np.array([0.1, 0.0, 0.0]), 6.0, 0)
    assert np.allclose(c - b, [0.6, 0, 0])
    d = traj.step(np.zeros(3), 6.0, 1)  # VO re-initialised: hold, count the reset
    assert np.array_equal(d, c) and traj.reset_counter == 1


def test_range_history_alignment() -> None:
    h = RangeHistory()
    assert h.add(RangeSample(1_000, 0, 5.0, 0.1, 40.0, 100))
    assert h.add(RangeSample(21_000, 0, 5.2, 0.1, 40.0, 100))
    assert np.isclose(h.at(0, 11_000, 60_000, 40_000), 5.1)  # interpolated
    assert h.at(0, 11_000, 10_000, 5_000) is None  # gap too wide, both too far
    assert np.isclose(h.at(0, 30_000, 60_000, 40_000), 5.2)  # nearest, fresh enough
    assert h.at(0, 90_000, 60_000, 40_000) is None  # stale
    assert h.at(3, 11_000, 60_000, 40_000) is None  # unknown sensor
    assert not h.add(RangeSample(30_000, 0, 0.05, 0.1, 40.0, 100))  # below min
    assert not h.add(RangeSample(31_000, 0, 5.0, 0.1, 40.0, 1))  # flagged invalid
    assert not h.add(RangeSample(32_000, 0, float("nan"), 0.1, 40.0, 100))
    assert not h.add(RangeSample(20_000, 0, 5.0, 0.1, 40.0, 100))  # out of order
    assert h.rejected == 4


def _inp(
    time_us: int, T_cam_vo: np.ndarray, feats: VoFeatures, p_cam: np.ndarray, kf: bool = False
) -> ScaleInput:
    vo = VoOutput(time_us, VoState.TRACKING, kf, se3.inverse(T_cam_vo), feats)
    return ScaleInput(time_us, vo, T_cam_vo, {0: (float(np.linalg.norm(p_cam)), p_cam, 0.01)}, 0)


def test_b8_and_b9_reproduce_their_formulas() -> None:
    opts = ScaleOptions()
    T = np.eye(4)
    # three VO points around the laser pixel on the plane z = 2 (VO units); laser at 10 m
    uv = np.array([[319.5, 239.5], [329.5, 239.5], [319.5, 249.5], [600.0, 400.0]])
    rays = CAM.pixels_to_rays(uv)
    pts = rays * (2.0 / rays[:, 2:3])
    feats = VoFeatures(uv, np.arange(4, dtype=np.int64), pts, np.full(4, 0.01))
    p_cam = np.array([0.0, 0.0, 10.0])  # on the optical axis: pixel (319.5, 239.5)
    b8 = B8PerFrame("B8 per-frame", CAM, opts)
    b8.update(_inp(0, T, feats, p_cam))
    # inverse-distance weights 1/0.5, 1/10, 1/10 over depths 2, 2, 2
    assert np.isclose(b8.scale, 10.0 / 2.0)
    b9 = B9Plane("B9 plane", CAM, opts)
    b9.update(_inp(0, T, feats, p_cam))
    assert np.isclose(b9.scale, 10.0 / 2.0)  # the ray meets the plane z = 2 at distance 2


def test_m_msc_does_not_take_a_lone_match_at_a_keyframe() -> None:
    """M-MSC updates at a keyframe only when >= mmsc_min_sensors matches agree: a single
    sensor reading 37 % long (a bad map point, a beam past an edge) is not taken; two
    agreeing sensors move it; with mmsc_min_sensors = 1 the lone match is taken (the thesis'
    literal fusion)."""
    s_true = 3.0
    T_cam_vo = se3.make(np.eye(3), [0.2, 0.1, -0.3])
    feats = scene_features(lambda r: np.full(len(r), 8.0), T_cam_vo, s_true)
    pixels = {0: (200.0, 120.0), 1: (440.0, 120.0), 2: (200.0, 360.0), 3: (440.0, 360.0)}

    def keyframe(time_us: int, factors: dict[int, float]) -> ScaleInput:
        lasers = {}
        for sid, f in factors.items():
            p_cam = _laser_at(pixels[sid], 8.0 * f)
            lasers[sid] = (float(np.linalg.norm(p_cam)), p_cam, 0.01)
        vo = VoOutput(time_us, VoState.TRACKING, True, se3.inverse(T_cam_vo), feats)
        return ScaleInput(time_us, vo, T_cam_vo, lasers, 0)

    results = {}
    for min_sensors in (2, 1):
        mmsc = MMSC("M-MSC", CAM, ScaleOptions(mmsc_min_sensors=min_sensors))
        first = mmsc.step(keyframe(0, {0: 1.0, 1: 1.0, 2: 1.0, 3: 1.0}))
        assert first is not None and abs(first.scale / s_true - 1) < 0.01 and first.n_used == 4
        lone = mmsc.step(keyframe(100_000, {2: 1.37}))
        assert lone is not None
        two = mmsc.step(keyframe(200_000, {0: 1.02, 1: 1.02}))
        assert two is not None and abs(two.scale / (1.02 * s_true) - 1) < 0.01
        results[min_sensors] = lone.scale / s_true
    assert abs(results[2] - 1) < 0.01  # held
    assert abs(results[1] - 1.37) < 0.02  # taken


def test_reuse_counter_counts_a_pair_until_it_is_forgotten() -> None:
    rc = ReuseCounter(memory_us=2_000_000)
    assert list(rc.factors(0, [(1, 7), (2, 7)])) == [1.0, 1.0]  # per sensor and point
    assert list(rc.factors(50_000, [(1, 7)])) == [np.sqrt(2)]
    assert list(rc.factors(100_000, [(1, 7), (1, 8)])) == [np.sqrt(3), 1.0]
    assert list(rc.factors(1_900_000, [(1, 8)])) == [np.sqrt(2)]  # 1.8 s later: remembered
    assert list(rc.factors(2_200_000, [(1, 7)])) == [1.0]  # unused for 2.1 s: a new start
    assert list(rc.factors(2_300_000, [(1, 7)])) == [np.sqrt(2)]
    assert list(ReuseCounter(0).factors(0, [(1, 7), (1, 7)])) == [1.0, 1.0]  # off


def _mmscwk_after_a_biased_stretch(reuse_memory_s: float, fresh_points: bool) -> float:
    """M-MSCwK at 20 Hz over a static scene: 2 s of four sensors reading the true scale,
    then 3 s of all four reading 4 % short, each match 5 % sigma (a descent's matches: a
    weak, biased point under each beam). Returns the final scale over the true one."""
    s_true = 3.0
    T_cam_vo = se3.make(np.eye(3), [0.2, 0.1, -0.3])
    feats = scene_features(lambda r: np.full(len(r), 8.0), T_cam_vo, s_true)
    pixels = {0: (200.0, 120.0), 1: (440.0, 120.0), 2: (200.0, 360.0), 3: (440.0, 360.0)}
    method = MMSCwK("M-MSCwK", CAM, ScaleOptions(reuse_memory_s=reuse_memory_s))
    est = None
    for k in range(100):
        f = 1.0 if k < 40 else 0.96
        lasers = {}
        for sid, px in pixels.items():
            p_cam = _laser_at(px, 8.0 * f)
            lasers[sid] = (float(np.linalg.norm(p_cam)), p_cam, 0.05 * 8.0)
        ids = feats.point_ids + (k * 10_000 if fresh_points else 0)
        fk = VoFeatures(feats.pixels, ids, feats.points_vo, feats.depth_sigma)
        vo = VoOutput(k * 50_000, VoState.TRACKING, False, se3.inverse(T_cam_vo), fk)
        est = method.step(ScaleInput(k * 50_000, vo, T_cam_vo, lasers, 0, (s_true, 0.01 * s_true)))
    assert est is not None
    return est.scale / s_true


def test_mmscwk_does_not_take_one_point_seen_again_as_new_evidence() -> None:
    """The beams resting on the same map points frame after frame give one measurement, not
    sixty: the filter moves far less towards their 4 % bias than it does when every frame
    brings new points (which are independent evidence, and taken as such)."""
    repeated = 1.0 - _mmscwk_after_a_biased_stretch(2.0, fresh_points=False)
    as_independent = 1.0 - _mmscwk_after_a_biased_stretch(0.0, fresh_points=False)
    fresh = 1.0 - _mmscwk_after_a_biased_stretch(2.0, fresh_points=True)
    assert as_independent > 0.025  # the old filter followed the bias most of the way
    assert repeated < 0.5 * as_independent
    assert fresh > 0.025 and abs(fresh - as_independent) < 1e-9  # new points: unchanged


def test_b7_window_ml_closed_form() -> None:
    """Noise-free pairs x = lambda * y give exactly scale = 1 / lambda (Engel et al. 2012)."""
    opts = ScaleOptions(b7_window_s=100.0, b7_min_step_m=0.05)
    b7 = B7WindowML("B7 window-ML", CAM, opts)
    lam = 0.25  # VO units per metre: scale 4 m per unit
    feats = VoFeatures(np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0))
    for k in range(40):
        h = 6.0 + 2.0 * np.sin(0.2 * k)  # height above level ground [m]
        c_vo_z = -(h - 6.0) * lam  # the camera rises: VO z (down) decreases
        T_cam_vo = se3.make(np.eye(3), [0.0, 0.0, -c_vo_z])
        b7.update(_inp(k * 100_000, T_cam_vo, feats, np.array([0.0, 0.0, h])))
    assert b7.scale is not None and abs(b7.scale - 4.0) < 1e-9


def test_pipeline_publishes_metric_poses_on_a_hills_flight() -> None:
    from companion.offline import run_scale
    from companion.sitl.world.scenario import Scenario

    cfg = load_config(
        overrides={
            "sitl": {"terrain": "hills", "trajectory": "lawnmower", "seconds": 16.0, "seed": 2}
        }
    )
    sc = Scenario(cfg)
    run = run_scale(cfg, sc.steps(workers=2), sc.world)  # rendered ahead on 2 threads
    metrics = {m.method: m for m in run.metrics()}
    for name in ("M-MSC", "M-MSCwK"):
        assert metrics[name].scale_mean_abs_rel_pct < 1.0
        assert metrics[name].ate_pct < 1.0
        assert metrics[name].scale_mse < metrics["B8 per-frame"].scale_mse
        assert metrics[name].scale_mse < metrics["MSC"].scale_mse  # more sensors help


@pytest.mark.parametrize(
    "bad",
    [
        RangeSample(0, 0, 0.0, 0.1, 40.0, 100),
        RangeSample(0, 0, 655.35, 0.1, 40.0, 100),
        RangeSample(0, 9, 5.0, 0.1, 40.0, 100),
        RangeSample(0, 0, 5.0, 0.1, 40.0, 1),
    ],
)
def test_pipeline_ignores_and_counts_bad_ranges(bad: RangeSample) -> None:
    from companion.pipeline import Pipeline

    pipe = Pipeline(load_config())
    pipe.feed_range(bad)
    assert pipe.ranges.rejected == 1 and pipe.ranges.sensors() == []


def test_the_range_history_window_and_lookup_agree_with_a_scan_of_every_reading() -> None:
    """RangeHistory.window scans from the newest end and stops at the window's start: the
    same readings, in time order, as filtering all of them."""
    from companion.scale.laser import RangeHistory
    from companion.types import RangeSample

    rng = np.random.default_rng(5)
    hist = RangeHistory(maxlen=64)
    kept: list[tuple[int, float]] = []
    t = 0
    for _ in range(300):
        t += int(rng.integers(1_000, 30_000))
        d = float(rng.uniform(0.5, 8.0))
        if hist.add(RangeSample(t, 0, d, 0.1, 12.0, 100)):
            kept = [*kept, (t, d)][-64:]
        t0 = t - int(rng.integers(0, 600_000))
        t1 = t - int(rng.integers(0, 100_000))
        want = [v for s, v in kept if t0 <= s <= t1]
        assert hist.window(0, t0, t1).tolist() == want
    assert hist.window(1, 0, t).size == 0  # a sensor never seen


def test_the_lasers_projected_together_are_each_one_projected_alone() -> None:
    """laser_pixels: every sensor's pixel in one projection, bit for bit laser_pixel's, NaN
    for a point behind the camera or outside the image; measure takes it as it is."""
    rng = np.random.default_rng(7)
    rays = CAM.pixels_to_rays(rng.uniform([0.0, 0.0], [640.0, 480.0], (40, 2)))
    points = np.concatenate(
        [rays * rng.uniform(0.5, 12.0, (40, 1)), [[0.0, 0.0, -2.0], [30.0, 0.0, 1.0]]]
    )
    together = msc.laser_pixels(CAM, points)
    for point, uv in zip(points, together, strict=True):
        alone = msc.laser_pixel(CAM, point)
        if alone is None:
            assert np.isnan(uv).all()
        else:
            assert np.array_equal(uv, alone)
    assert np.isnan(together[-2:]).all() and np.isfinite(together[:40]).all()
    s_true = 3.0
    T_cam_vo = se3.make(np.eye(3), [0.2, 0.1, -0.3])
    feats = scene_features(lambda r: np.full(len(r), 8.0), T_cam_vo, s_true)
    laser = _laser_at((318.0, 236.0), 8.0)
    args = (feats, T_cam_vo, CAM, laser, 0.01, 6.0, 1.0, 0.0, 0.0)
    own = msc.measure(0, *args)
    given = msc.measure(0, *args, msc.laser_pixels(CAM, laser[None])[0])
    assert own is not None and own == given
    assert msc.measure(0, *args, np.array([np.nan, np.nan])) is None
