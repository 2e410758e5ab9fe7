"""Gravity in the VO frame from the accelerometer and our motion (companion/attitude/gravity.py)
and its use as the VO's keyframe gravity prior (seeded synthetic flights)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from companion.attitude.gravity import (
    STANDARD_GRAVITY_M_S2,
    attitude_correction,
    gravity_from_motion,
    rotations_at,
    velocity_at,
)
from companion.geometry import so3
from companion.geometry.camera import CameraModel
from companion.vo.keyframes import gravity_cam
from companion.vo.odometry import VisualOdometry
from companion.vo.options import VoOptions

G_NED = np.array([0.0, 0.0, STANDARD_GRAVITY_M_S2])


def manoeuvre(t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A multirotor-like flight in NED: position (N, 3) [m], acceleration (N, 3) [m/s^2] and
    R_world_body (N, 3, 3) tilted with the horizontal acceleration (as a multirotor is), a
    slow yaw turn on top."""
    w = np.array([0.9, 0.7, 0.4])
    amp = np.array([3.0, 2.5, 0.5])
    p = amp * np.sin(np.outer(t_s, w))
    a = -amp * w**2 * np.sin(np.outer(t_s, w))
    R = []
    for ai, ti in zip(a, t_s, strict=True):
        # thrust along -z_body balances gravity and gives the acceleration: tilt towards it
        thrust = G_NED - ai
        z_body = -thrust / np.linalg.norm(thrust)
        yaw = 0.2 * ti
        x_ref = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        y_body = np.cross(z_body, x_ref)
        y_body /= np.linalg.norm(y_body)
        x_body = np.cross(y_body, z_body)
        R.append(np.stack([x_body, y_body, z_body], axis=1))
    return p, a, np.array(R)


def synthetic(
    seed: int,
    tilt_rad: np.ndarray,
    accel_noise: float = 0.5,
    pos_noise_m: float = 0.003,
    imu_hz: float = 50.0,
    duration_s: float = 6.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Accelerometer samples and VO poses (30 Hz) of :func:`manoeuvre` seen from a VO frame
    tilted by exp(tilt_rad) against NED; returns (imu_t_us, f_body, pose_t_us, R_vo_body,
    p_vo_m, true down in the VO frame)."""
    rng = np.random.default_rng(seed)
    R_vo_world = so3.exp(tilt_rad)
    t_imu = np.arange(0.0, duration_s, 1.0 / imu_hz)
    _, a_imu, R_imu = manoeuvre(t_imu)
    f = np.einsum("nji,nj->ni", R_imu, a_imu - G_NED)  # R_body_world (a - g)
    f += rng.normal(0.0, accel_noise, f.shape)
    t_pose = np.arange(0.0, duration_s, 1.0 / 30.0)
    p_pose, _, R_pose = manoeuvre(t_pose)
    p_vo = (R_vo_world @ p_pose.T).T + rng.normal(0.0, pos_noise_m, p_pose.shape)
    R_vo_body = np.einsum("ij,njk->nik", R_vo_world, R_pose)
    return (
        (t_imu * 1e6).astype(np.int64),
        f,
        (t_pose * 1e6).astype(np.int64),
        R_vo_body,
        p_vo,
        R_vo_world @ np.array([0.0, 0.0, 1.0]),
    )


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_gravity_recovers_the_vo_frames_tilt_during_manoeuvres(seed: int) -> None:
    tilt = np.radians([2.0, -1.5, 0.0])  # the VO frame drifted 2.5 deg off level
    imu_t, f, pose_t, R, p, down_true = synthetic(seed, tilt)
    est = gravity_from_motion(imu_t, f, pose_t, R, p, window_s=4.0)
    assert est is not None
    err_rad = float(np.arccos(np.clip(est.down_vo @ down_true, -1.0, 1.0)))
    # 0.5 m/s^2 noise at 50 Hz over 4 s: the mean's 0.035 m/s^2 is 0.2 deg per axis
    assert err_rad < np.radians(0.5)
    assert err_rad < 3.0 * est.sigma_rad
    assert abs(est.norm_m_s2 - STANDARD_GRAVITY_M_S2) < 0.2
    assert np.isclose(np.linalg.norm(est.down_vo), 1.0)
    # ignoring the motion (a level-flight assumption) would be degrees off here: the
    # velocity term is what makes the estimate right
    naive = -np.einsum("nij,nj->ni", rotations_at(imu_t, pose_t, R), f)[
        (imu_t >= est.t0_us) & (imu_t < est.t1_us)
    ].mean(axis=0)
    naive /= np.linalg.norm(naive)
    assert np.degrees(np.arccos(naive @ down_true)) > 1.0


def test_gravity_sigma_grows_with_the_accelerometer_noise() -> None:
    tilt = np.zeros(3)
    quiet = gravity_from_motion(*synthetic(4, tilt, accel_noise=0.05)[:5], window_s=4.0)
    noisy = gravity_from_motion(*synthetic(4, tilt, accel_noise=5.0)[:5], window_s=4.0)
    assert quiet is not None and noisy is not None
    assert noisy.sigma_rad > 2.0 * quiet.sigma_rad
    assert quiet.sigma_rad >= np.radians(0.2)  # the floor


def test_gravity_refuses_what_it_cannot_support() -> None:
    imu_t, f, pose_t, R, p, _ = synthetic(5, np.zeros(3), duration_s=3.0)
    # the poses do not cover a 4 s window
    assert gravity_from_motion(imu_t, f, pose_t, R, p, window_s=4.0) is None
    # too few accelerometer samples (5 Hz where 20 Hz are needed)
    imu_t, f, pose_t, R, p, _ = synthetic(5, np.zeros(3), imu_hz=5.0)
    assert gravity_from_motion(imu_t, f, pose_t, R, p, window_s=4.0) is None
    # accelerometer in g instead of m/s^2: an implausible |g|
    imu_t, f, pose_t, R, p, _ = synthetic(5, np.zeros(3))
    assert gravity_from_motion(imu_t, f / 9.81, pose_t, R, p, window_s=4.0) is None


def test_velocity_fit_and_rotation_interpolation() -> None:
    t = np.arange(0, 1_000_000, 33_333, dtype=np.int64)
    p = np.outer(t * 1e-6, [1.0, -2.0, 0.5])  # constant velocity
    v, sigma = velocity_at(500_000.0, t, p, 100_000.0)
    assert np.allclose(v, [1.0, -2.0, 0.5])
    assert sigma < 1e-9
    with pytest.raises(ValueError):
        velocity_at(2_000_000.0, t, p, 100_000.0)
    Rs = np.stack([so3.rot_z(0.0), so3.rot_z(0.02)])
    mid = rotations_at(np.array([16_666]), np.array([0, 33_333]), Rs)[0]
    assert np.allclose(mid, so3.rot_z(0.01), atol=1e-4)


def test_attitude_correction_removes_the_autopilots_slow_tilt_error() -> None:
    """The autopilot's attitude is 2 deg off in roll for the whole window (a slow EKF tilt
    error) with 0.3 deg of fast noise; the window's measured gravity turns its mean down onto
    the VO frame's true down, and every corrected sample is within the fast noise."""
    rng = np.random.default_rng(11)
    tilt_vo = np.radians([1.0, -0.5, 0.0])  # the VO frame's own tilt against NED
    R_vo_world = so3.exp(tilt_vo)
    down_true = R_vo_world @ np.array([0.0, 0.0, 1.0])
    t = np.linspace(0.0, 4.0, 120)
    _, _, R_world_body = manoeuvre(t)
    R_vo_body = np.einsum("ij,njk->nik", R_vo_world, R_world_body)
    R_err = so3.exp(np.radians([2.0, 0.0, 0.0]))
    R_ap = np.array(
        [R_err @ so3.exp(rng.normal(0.0, np.radians(0.3), 3)) @ R for R in R_world_body]
    )
    c = attitude_correction(down_true, np.radians(0.4), R_vo_body, R_ap)
    assert c is not None
    assert np.degrees(c.angle_rad) == pytest.approx(2.0, abs=0.15)
    ez = np.array([0.0, 0.0, 1.0])
    before = [
        np.degrees(np.arccos(np.clip((Rv @ Ra.T @ ez) @ down_true, -1, 1)))
        for Rv, Ra in zip(R_vo_body, R_ap, strict=True)
    ]
    after = [
        np.degrees(np.arccos(np.clip((c.R_vo @ Rv @ Ra.T @ ez) @ down_true, -1, 1)))
        for Rv, Ra in zip(R_vo_body, R_ap, strict=True)
    ]
    assert min(before) > 1.0 and np.median(before) > 1.7
    assert np.percentile(after, 95) < 0.8 and np.median(after) < 0.5
    # its sigma holds the measurement's and the fast scatter (0.3 deg per axis)
    assert np.radians(0.4) < c.sigma_rad < np.radians(0.8)
    assert attitude_correction(down_true, 0.01, R_vo_body[:0], R_ap[:0]) is None


def gravity_of(
    vo: VisualOdometry, R_ap: np.ndarray | None, gravity: Any = None, axial: bool = False
) -> tuple[np.ndarray | None, float]:
    """The gravity prior (companion/vo/keyframes.py) a keyframe of ``vo`` would take now."""
    return gravity_cam(R_ap, vo.T_body_cam, vo.T_cam_vo, vo.opts, gravity, axial)


def test_vo_turns_the_attitudes_gravity_by_the_measured_correction() -> None:
    cam = CameraModel(320, 240, 230.0, 230.0, 159.5, 119.5)
    vo = VisualOdometry(cam, np.eye(4), VoOptions(gravity_sigma_deg=1.0))
    R_cam_vo = so3.rpy_to_matrix(0.1, -0.05, 0.3)
    vo.T_cam_vo = np.eye(4)
    vo.T_cam_vo[:3, :3] = R_cam_vo
    R_ap = so3.rpy_to_matrix(0.02, 0.01, 0.3)
    ez = np.array([0.0, 0.0, 1.0])
    g_ap, s_ap = gravity_of(vo, R_ap)
    assert g_ap is not None and np.allclose(g_ap, R_ap.T @ ez)
    assert s_ap == pytest.approx(np.radians(1.0))
    R_corr = so3.exp(np.radians([0.0, 1.5, 0.0]))
    g, sigma = gravity_of(vo, R_ap, (R_corr, np.radians(0.6)))
    # the correction's own sigma and the attitude's (its fast error stays in the prior)
    assert g is not None and sigma == pytest.approx(np.radians(np.hypot(1.0, 0.6)))
    # the correction acts in the VO frame: seen from the VO frame the gravity turned by it
    assert np.allclose(R_cam_vo.T @ g, R_corr @ (R_cam_vo.T @ g_ap))
    assert 1.0 < np.degrees(np.arccos(np.clip(g @ g_ap, -1, 1))) <= 1.5 + 1e-9
    # no attitude: no prior (the correction corrects an attitude); images only: none
    assert gravity_of(vo, None, (R_corr, 0.01)) == (None, 0.0)
    images_only = VisualOdometry(cam, np.eye(4), VoOptions(gravity_sigma_deg=0.0))
    assert gravity_of(images_only, R_ap, (R_corr, 0.01)) == (None, 0.0)


def test_the_pipeline_removes_an_autopilots_constant_tilt_error_with_its_accelerometer() -> None:
    """A SITL lawnmower over hills with the autopilot's attitude 2 deg off in roll for the
    whole flight (an EKF's tilt error without GNSS), its accelerometer (specific force from the
    trajectory, 0.3 m/s^2 noise, 50 Hz) beside it. The VO frame starts on the biased attitude
    (2 deg off level); the accelerometer's correction brings it back: the window measures the
    2 deg, and the VO frame ends within 0.8 deg of level."""
    from peers import feed_biased_step

    from companion.config import load_config
    from companion.pipeline import Pipeline
    from companion.sitl.world.scenario import Scenario
    from companion.types import ImuSample

    cfg = load_config(
        None,
        {
            "sitl": {"terrain": "hills", "trajectory": "lawnmower", "seconds": 16.0, "seed": 5},
            # the stub's attitude is 0.1 deg of white noise on the truth (here on the 2 deg
            # bias): its fast error is small, and the BA's prior on it says so
            "vo": {"gravity_sigma_deg": 0.5},
        },
    )
    sc = Scenario(cfg)
    R_err = so3.rot_x(np.radians(2.0))
    rng = np.random.default_rng(5)
    t_imu = np.arange(0.0, cfg.sitl.seconds, 0.02)
    tr = sc.trajectory.sample(t_imu)
    f_body = np.einsum("nji,nj->ni", tr.R_world_body, tr.accel_m_s2 - G_NED)
    f_body += rng.normal(0.0, 0.3, f_body.shape)
    imus = [ImuSample(int(round(t * 1e6)), f) for t, f in zip(t_imu, f_body, strict=True)]
    p = Pipeline(cfg)
    k_imu = 0
    corrections, tilts = [], []
    for st in sc.steps(workers=2):
        k_imu = feed_biased_step(p, st, imus, k_imu, R_err)
        p.background_work()
        R_vo_body = p.R_vo_body()
        if R_vo_body is not None and p.vo.state.value == "tracking":
            down_in_vo = R_vo_body @ st.T_world_body[:3, :3].T @ np.array([0.0, 0.0, 1.0])
            tilts.append(np.degrees(np.arccos(np.clip(down_in_vo[2], -1.0, 1.0))))
            if p.imu_gravity.correction is not None:
                corrections.append(np.degrees(p.imu_gravity.correction.angle_rad))
    assert p.vo.resets == 0
    assert len(corrections) > 100, len(corrections)
    # the frame started on the biased attitude: ~2 deg off level
    assert 1.5 < tilts[0] < 2.5, tilts[0]
    # the window saw the 2 deg at first, and the frame came back towards level
    assert 1.2 < max(corrections[:30]) < 2.8, corrections[:30]
    assert np.median(tilts[-30:]) < 0.8, tilts[-30:]


def test_vo_calls_a_keyframe_axial_when_the_camera_moved_along_its_optical_axis() -> None:
    """keyframes.is_axial: the camera centre's move since the last keyframe, seen from the
    camera, within axial_max_angle_deg of the optical axis (a climb or a descent under a
    downward camera), and not a sideways move or no move at all."""
    from companion.vo.keyframes import is_axial
    from companion.vo.map import Keyframe

    cam = CameraModel(320, 240, 230.0, 230.0, 159.5, 119.5)
    vo = VisualOdometry(
        cam, np.eye(4), VoOptions(axial_max_angle_deg=30.0, axial_gravity_sigma_deg=0.0)
    )
    R_cam_vo = so3.rpy_to_matrix(0.05, -0.03, 1.0)

    def at(c_vo: np.ndarray) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = R_cam_vo
        T[:3, 3] = -R_cam_vo @ c_vo
        return T

    axis_vo = R_cam_vo.T @ np.array([0.0, 0.0, 1.0])  # the optical axis in the VO frame
    side_vo = R_cam_vo.T @ np.array([1.0, 0.0, 0.0])

    def axial_now() -> bool:  # no tracks: the median depth is 1
        last = vo.map.keyframes[-1] if vo.map.keyframes else None
        return is_axial(last, vo.T_cam_vo, 1.0, vo.opts)

    vo.T_cam_vo = at(np.zeros(3))
    assert not axial_now()  # no keyframe yet
    vo.map.keyframes = [Keyframe(0, 0, at(np.array([0.3, -0.2, 1.0])))]
    c0 = np.array([0.3, -0.2, 1.0])
    for move, axial in [
        (-0.1 * axis_vo, True),  # climbing (backwards along the axis)
        (0.1 * axis_vo + 0.04 * side_vo, True),  # descending, drifting 22 deg off the axis
        (0.1 * axis_vo + 0.07 * side_vo, False),  # 35 deg off the axis
        (0.2 * side_vo, False),  # cruising
        (0.02 * axis_vo, False),  # along the axis but short: its direction is noise
        (np.zeros(3), False),  # hovering
    ]:
        vo.T_cam_vo = at(c0 + move)
        assert axial_now() is axial, move
    # an axial keyframe takes the axial sigma on the attitude's gravity, with or without
    # the accelerometer's correction; off (0) it keeps gravity_sigma_deg
    R_ap = so3.rpy_to_matrix(0.02, 0.01, 0.3)
    tight = VisualOdometry(
        cam, np.eye(4), VoOptions(gravity_sigma_deg=2.0, axial_gravity_sigma_deg=0.5)
    )
    g, sigma = gravity_of(tight, R_ap, None, axial=True)
    assert g is not None and sigma == pytest.approx(np.radians(0.5))
    assert gravity_of(tight, R_ap, None, axial=False)[1] == pytest.approx(np.radians(2.0))
    assert gravity_of(vo, R_ap, None, axial=True)[1] == pytest.approx(np.radians(1.0))


@pytest.mark.parametrize("seed", [1, 2])
def test_the_axial_prior_holds_the_vo_frame_level_through_a_take_off(seed: int) -> None:
    """A vertical take-off from flat ground to 4 m (SITL, the PX4 loop's 320x240 camera): over
    a plane seen from above, a tilt and a sideways move look alike in the images, and with the
    PX4 loop's loose 2 deg prior the VO frame tilted 1.5-4 deg in this climb (4-9 deg with no
    prior at all). With the axial prior (0.5 deg on keyframes reached moving along the optical
    axis) on the stub's attitude (0.1 deg of noise) it stays within 1.5 deg of level and ends
    the climb within 0.5 deg."""
    from peers import small_camera_takeoff

    from companion.offline import feed_step
    from companion.pipeline import Pipeline
    from companion.sitl.world.scenario import Scenario

    cfg = small_camera_takeoff(seed, axial_gravity_sigma_deg=0.5)
    p = Pipeline(cfg)
    tilt_deg, height_m = [], []
    for st in Scenario(cfg).steps(stop=210, workers=2):  # the ground and the climb
        feed_step(p, st)
        R_vo_body = p.R_vo_body()
        if R_vo_body is None:
            continue
        down_vo = R_vo_body @ st.T_world_body[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        tilt_deg.append(np.degrees(np.arccos(np.clip(down_vo[2], -1.0, 1.0))))
        height_m.append(-st.T_world_body[2, 3])
    h = np.array(height_m)
    assert p.vo.resets == 0 and h.max() > 3.5  # it climbed, on one VO map
    assert p.vo.axial_keyframes >= 10
    # the lift-off (0.3-0.5 m up, the scene expanding fastest) is the worst moment: 0.7 and
    # 1.2 deg at seeds 1 and 2 (4-6 deg without the axial prior); 0.1-0.2 deg at the top
    assert max(tilt_deg) <= 1.5, (max(tilt_deg), seed)
    assert np.mean(tilt_deg[-15:]) <= 0.5, (tilt_deg[-15:], seed)
