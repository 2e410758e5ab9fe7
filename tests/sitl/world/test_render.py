"""Camera rendering: laser dots on the true hit points, plane homography, occlusion, depth."""

from __future__ import annotations

import pickle
from collections.abc import Callable
from dataclasses import replace

import cv2
import numpy as np
import pytest

from companion.config import Config, RenderConfig
from companion.geometry import se3, so3
from companion.sitl.world.render import Renderer
from companion.sitl.world.sensors import laser_hits
from companion.sitl.world.terrain import World
from companion.sitl.world.trajectory import Trajectory


def red_blobs(img: np.ndarray) -> np.ndarray:
    """Sub-pixel centres (K, 2) of red laser dots: redness-weighted centroids of components."""
    b, g, r = (img[..., i].astype(np.float64) for i in range(3))
    redness = r - 0.5 * (g + b)
    background = np.median(redness)
    mask = (redness - background > 60).astype(np.uint8)
    n, labels = cv2.connectedComponents(mask)
    centres = []
    for k in range(1, n):
        ys, xs = np.nonzero(labels == k)
        y0, y1 = max(ys.min() - 3, 0), min(ys.max() + 4, img.shape[0])
        x0, x1 = max(xs.min() - 3, 0), min(xs.max() + 4, img.shape[1])
        win = np.clip(redness[y0:y1, x0:x1] - background - 20, 0, None)
        yy, xx = np.mgrid[y0:y1, x0:x1]
        centres.append([(win * xx).sum() / win.sum(), (win * yy).sum() / win.sum()])
    return np.asarray(centres).reshape(-1, 2)


@pytest.mark.parametrize("terrain", ["flat", "hills", "slope"])
def test_laser_hit_points_project_onto_their_red_dots(
    terrain: str, world: Callable[[str, int], World], default_config: Config
) -> None:
    cfg = default_config
    w = world(terrain, 1)
    traj = Trajectory("figure8", w, 30.0, altitude_m=3.0)
    renderer = Renderer(w, cfg.camera, cfg.sitl.render, cfg.rangefinders, seed=1)
    checked = 0
    for t_s in (5.0, 11.0, 17.0, 23.0):
        frame = renderer.render_at(traj, t_s, int(t_s * 30))
        T_world_body = traj.T_world_body(t_s)
        _, pts = laser_hits(w, T_world_body, cfg.rangefinders)
        T_cam_world = se3.inverse(T_world_body @ cfg.camera.T_body_cam())
        uv, _ = renderer.model.project(se3.transform(T_cam_world, pts))
        blobs = red_blobs(frame.image_bgr)
        assert len(blobs) == len(pts)
        for p in uv:
            err = np.linalg.norm(blobs - p, axis=1).min()
            assert err < 1.0, f"dot {err:.2f} px from the projected hit point"
            checked += 1
    assert checked == 16


def test_flat_image_motion_is_the_plane_homography(
    world: Callable[[str, int], World], default_config: Config
) -> None:
    cfg = default_config
    w = world("flat", 2)
    quiet = RenderConfig(noise_sigma_dn=0.0, laser_marks="off")
    renderer = Renderer(w, cfg.camera, quiet, seed=2)
    T_body_cam = cfg.camera.T_body_cam()
    T_wa = se3.make(so3.rpy_to_matrix(0.04, -0.03, 0.3), [3.0, -2.0, -6.0]) @ T_body_cam
    T_wb = se3.make(so3.rpy_to_matrix(-0.02, 0.05, 0.38), [3.5, -1.7, -6.4]) @ T_body_cam
    img_a = renderer.render_pose(T_wa, 0).image_bgr
    img_b = renderer.render_pose(T_wb, 1).image_bgr
    gray_a = cv2.cvtColor(img_a, cv2.COLOR_BGR2GRAY)
    gray_b = cv2.cvtColor(img_b, cv2.COLOR_BGR2GRAY)
    pa = cv2.goodFeaturesToTrack(gray_a, 400, 0.01, 12, blockSize=7)
    pb, status, _ = cv2.calcOpticalFlowPyrLK(gray_a, gray_b, pa, None, winSize=(21, 21), maxLevel=3)
    back, status_back, _ = cv2.calcOpticalFlowPyrLK(
        gray_b, gray_a, pb, None, winSize=(21, 21), maxLevel=3
    )
    # keep tracks that are consistent forwards and backwards (a tracker's, not a renderer's, check)
    fb = np.linalg.norm(back.reshape(-1, 2) - pa.reshape(-1, 2), axis=1)
    ok = (status.ravel() == 1) & (status_back.ravel() == 1) & (fb < 0.1)
    pa, pb = pa.reshape(-1, 2)[ok], pb.reshape(-1, 2)[ok]
    assert len(pa) > 150
    # analytic homography of the ground plane z = 0 between the two cameras
    T_ba = se3.inverse(T_wb) @ T_wa
    n_a = T_wa[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    d_a = -T_wa[2, 3]
    H = T_ba[:3, :3] + np.outer(T_ba[:3, 3], n_a) / d_a
    xa = renderer.model.pixels_to_normalized(pa)
    xb_pred = (H @ np.column_stack([xa, np.ones(len(xa))]).T).T
    uv_pred = renderer.model.normalized_to_pixels(xb_pred[:, :2] / xb_pred[:, 2:])
    err = np.linalg.norm(uv_pred - pb, axis=1)
    assert np.median(err) < 0.1
    assert np.percentile(err, 95) < 0.3
    # and the motion is real: without the homography the points moved tens of pixels
    assert np.median(np.linalg.norm(pa - pb, axis=1)) > 20


def test_depth_map_is_the_ray_cast_depth(
    world: Callable[[str, int], World], default_config: Config
) -> None:
    cfg = default_config
    w = world("urban", 1)
    renderer = Renderer(w, cfg.camera, RenderConfig(laser_marks="off"), seed=1)
    # beside a building, so walls and roofs are in view
    k = int(np.argmax(w.boxes[:, 5]))
    _, x1, y0, y1, _, top = w.boxes[k]
    T_wc = (
        se3.make(so3.rpy_to_matrix(0.1, -0.1, 0.5), [x1 + 1.0, 0.5 * (y0 + y1), -(top + 6.0)])
        @ cfg.camera.T_body_cam()
    )
    frame = renderer.render_pose(T_wc, 0)
    rng = np.random.default_rng(3)
    uv = np.column_stack([rng.integers(0, 640, 2000), rng.integers(0, 480, 2000)])
    rays_cam = renderer.model.pixels_to_rays(uv.astype(float))
    hits = w.raycast(np.repeat(T_wc[None, :3, 3], len(uv), axis=0), rays_cam @ T_wc[:3, :3].T)
    depth_ref = hits.t_m * rays_cam[:, 2]
    depth = frame.depth_m[uv[:, 1], uv[:, 0]]
    assert np.allclose(depth, depth_ref, rtol=1e-5)
    assert (hits.kind == 2).sum() > 20 and (hits.kind == 1).sum() > 20  # walls and roofs seen
    # occlusion: wall pixels are nearer than the ground behind them along the same ray
    wall = hits.kind == 2
    t_ground = (-T_wc[2, 3]) / (rays_cam[wall] @ T_wc[:3, :3].T)[:, 2]
    assert (hits.t_m[wall] < t_ground).all()


def test_painted_marks_stay_on_the_ground(
    world: Callable[[str, int], World], default_config: Config
) -> None:
    cfg = default_config
    w = world("flat", 1)
    traj = Trajectory("circle", w, 20.0, altitude_m=3.0)
    painted = replace(cfg.sitl.render, laser_marks="painted", painted_time_s=2.0)
    renderer = Renderer(w, cfg.camera, painted, cfg.rangefinders, seed=1)
    _, pts_ref = laser_hits(w, traj.T_world_body(2.0), cfg.rangefinders)
    frame = renderer.render_at(traj, 2.6, 78)  # the vehicle has moved ~1.7 m
    assert np.allclose(frame.marks_world, pts_ref)
    blobs = red_blobs(frame.image_bgr)
    visible = frame.marks_uv[np.isfinite(frame.marks_uv[:, 0])]
    assert len(visible) == 4 and len(blobs) == 4
    for p in visible:
        assert np.linalg.norm(blobs - p, axis=1).min() < 1.0
    live = Renderer(w, cfg.camera, cfg.sitl.render, cfg.rangefinders, seed=1)
    moved = live.render_at(traj, 2.6, 78).marks_world
    assert np.linalg.norm(moved - pts_ref, axis=1).min() > 1.0  # live marks followed the beams


def test_noise_and_motion_blur(world: Callable[[str, int], World], default_config: Config) -> None:
    cfg = default_config
    w = world("hills", 1)
    traj = Trajectory("lawnmower", w, 20.0)
    clean = Renderer(w, cfg.camera, RenderConfig(noise_sigma_dn=0.0, laser_marks="off"))
    noisy = Renderer(w, cfg.camera, RenderConfig(noise_sigma_dn=4.0, laser_marks="off"))
    blurred = Renderer(
        w,
        cfg.camera,
        RenderConfig(noise_sigma_dn=0.0, laser_marks="off", motion_blur=True, exposure_s=0.02),
    )
    a = clean.render_at(traj, 8.0, 1).image_bgr.astype(float)
    b = noisy.render_at(traj, 8.0, 1).image_bgr.astype(float)
    c = blurred.render_at(traj, 8.0, 1).image_bgr.astype(float)
    assert 3.5 < np.std(b - a) < 4.5  # the configured sigma (before clipping)
    # blur at ~3 m/s over 20 ms (~5 px) removes high frequencies
    lap = lambda im: np.var(cv2.Laplacian(im.mean(axis=2), cv2.CV_64F))  # noqa: E731
    assert lap(c) < 0.7 * lap(a)


def test_direct_8bit_output_equals_linear_plus_noise(
    world: Callable[[str, int], World], default_config: Config
) -> None:
    """The fused kernel (used per frame) and linear + finish (used for blur) agree: the same
    noise samples, differing only where float32 storage of the linear value flips a rounding."""
    from companion.sitl.world import _kernels

    cfg = default_config
    w = world("urban", 1)
    renderer = Renderer(w, cfg.camera, RenderConfig(laser_marks="off"), seed=9)
    T_wc = se3.make(so3.rpy_to_matrix(0.05, 0.02, 1.0), [5.0, 3.0, -12.0]) @ cfg.camera.T_body_cam()
    direct = renderer.render_pose(T_wc, 17).image_bgr
    linear = renderer.render_linear(T_wc).reshape(-1, 3)
    start = int(np.random.default_rng([9, 405, 17]).integers(0, 1 << 21))
    out = np.empty_like(linear, dtype=np.uint8)
    _kernels.finish(linear, renderer.noise_bank, start, 2.0, out)
    diff = np.abs(out.reshape(direct.shape).astype(int) - direct.astype(int))
    assert diff.max() <= 1 and (diff > 0).mean() < 1e-3
    assert 20 < direct.mean() < 230  # a real image, not blank


@pytest.mark.parametrize(("marks", "blur", "workers"), [("live", False, 3), ("painted", True, 2)])
def test_rendering_ahead_on_threads_gives_what_one_thread_renders(
    marks: str, blur: bool, workers: int
) -> None:
    """The SITL camera prerenders a flight on one thread per core (sitl/stub/autopilot.py) and
    ``Scenario.steps(workers=N)`` renders ahead on N threads: every frame must be bit for bit
    the image a single thread renders in order (noise, motion blur, laser marks), and every
    step the same samples and pose (2 threads, and 3 for an uneven share)."""
    from companion.config import load_config
    from companion.sitl.stub.camera import prerender_frames
    from companion.sitl.world.scenario import Scenario, Step

    cfg = load_config(
        "config/sitl.toml",
        {"sitl": {"seconds": 0.2, "render": {"laser_marks": marks, "motion_blur": blur}}},
    )
    one = Scenario(cfg)
    expected = list(one.steps())
    images = [e.frame.image_bgr for e in expected]
    assert len(expected) == 6 and len({i.tobytes() for i in images}) == 6  # they differ

    def same_step(a: Step, b: Step) -> None:
        assert a.frame.seq == b.frame.seq and a.frame.time_us == b.frame.time_us
        assert np.array_equal(a.frame.image_bgr, b.frame.image_bgr), a.frame.seq
        assert np.array_equal(a.T_world_body, b.T_world_body)
        for x, y in ((a.ranges, b.ranges), (a.attitudes, b.attitudes)):  # to the last bit
            assert pickle.dumps(x) == pickle.dumps(y), a.frame.seq
        assert len(a.ranges) >= 4 and len(a.attitudes) >= 1

    sc = Scenario(cfg, world=one.world)  # the world is built once (0.9 s)
    sc.step(0)
    got = prerender_frames(sc, sc.n_frames, workers)
    assert len(got) == 6
    for k, (a, b) in enumerate(zip(got, images, strict=True)):
        assert a.shape == (480, 640, 3) and np.array_equal(a, b), k
    ahead = list(Scenario(cfg, world=one.world).steps(start=1, workers=workers))
    assert [s.frame.seq for s in ahead] == list(range(1, 6))
    for a, b in zip(ahead, expected[1:], strict=True):
        same_step(a, b)
