"""The take-off pad's gravity (companion/attitude/pad.py, the pipeline's vo.pad_* options)."""

from __future__ import annotations

import numpy as np
import pytest

from companion.attitude.pad import PadLevel
from companion.geometry import so3

E_Z = np.array([0.0, 0.0, 1.0])


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(a @ b / np.linalg.norm(a) / np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _noisy(n: np.ndarray, rng: np.random.Generator, sigma_deg: float) -> np.ndarray:
    """A unit vector turned by a random small rotation (sigma per horizontal axis)."""
    e = rng.normal(0.0, np.radians(sigma_deg), 2)
    return so3.exp(np.array([e[0], e[1], 0.0])) @ n


def test_the_pad_corrects_the_autopilots_tilt_error_from_the_planes_over_it() -> None:
    """A pad tilted 4 deg, seen at rest for 5 s with the autopilot right, then from the air
    with the autopilot 1.5 deg off (a world-frame rotation): each plane is 1.6 deg noisy (one
    fit of four readings with 1 cm of noise, 0.5 m apart), 100 per second. Half a second of them
    puts the corrected gravity 0.23 deg per axis from the truth, where the autopilot's own is
    1.5 deg off."""
    rng = np.random.default_rng(3)
    n_pad = so3.exp(np.radians([4.0, 1.0, 0.0])) @ E_Z
    pad = PadLevel(window_us=500_000, sigma_floor_rad=np.radians(0.1), max_error_rad=0.09)
    t = 0
    for _ in range(500):  # 5 s at rest, the vehicle on its legs a little crooked
        R_true = so3.rpy_to_matrix(np.radians(0.7), np.radians(-0.4), 1.2)
        pad.at_rest(t, _noisy(R_true.T @ n_pad, rng, 1.6), R_true, np.zeros(3), "map 0")
        t += 10_000
    assert pad.n_pad is not None and _angle_deg(pad.n_pad, n_pad) < 0.3  # 0.08 per axis
    R_err = so3.exp(np.radians([1.2, -0.9, 0.0]))  # 1.5 deg
    errors, own, sigmas = [], [], []
    for k in range(2000):  # 20 s in the air, rolling and pitching
        roll, pitch = np.radians(3 * np.sin(k / 40)), np.radians(2 * np.cos(k / 30))
        R_true = so3.rpy_to_matrix(roll, pitch, 1.2)
        R_ap = R_err @ R_true
        pad.sample(t, _noisy(R_true.T @ n_pad, rng, 1.6), R_ap)
        got = pad.down_body(t, R_ap)
        if k % 50 == 49:  # one per window: independent estimates
            assert got is not None
            errors.append(_angle_deg(got[0], R_true.T @ E_Z))
            own.append(_angle_deg(R_ap.T @ E_Z, R_true.T @ E_Z))
            sigmas.append(np.degrees(got[1]))
        t += 10_000
    assert np.median(own) == pytest.approx(1.5, abs=0.05)
    # 1.6 deg / sqrt(50) = 0.23 deg per axis: an RMS angle of 0.32 deg over the 40 windows
    rms = float(np.sqrt(np.mean(np.square(errors))))
    assert rms < 0.45, errors
    # the sigma it states (per axis) is the samples' scatter over their count
    assert 0.18 < np.median(sigmas) < 0.28, sigmas


def test_the_pad_refuses_what_it_cannot_support() -> None:
    """No gravity before the pad is measured or with too few samples; a hit off the pad
    (more than max_error_rad off the autopilot) is refused and counted; only near the rest
    and in the same map; the rest's last rest_guard_us (the lift-off) stays out of the pad."""
    pad = PadLevel(window_us=500_000, sigma_floor_rad=0.002, max_error_rad=np.radians(5.0))
    assert not pad.sample(0, E_Z, np.eye(3))  # no pad yet
    assert pad.down_body(0, np.eye(3)) is None
    for k in range(150):  # 1.5 s level, then 0.5 s tilted 3 deg: the lift-off's first moments
        R = np.eye(3) if k < 100 else so3.rot_x(np.radians(3.0))
        pad.at_rest(k * 10_000, E_Z, R, np.array([1.0, 2.0, 0.0]), "map 0")
    assert pad.n_pad is not None and _angle_deg(pad.n_pad, E_Z) < 1e-9
    assert pad.near(np.array([2.0, 2.5, -4.0]), "map 0", 1.5)
    assert not pad.near(np.array([2.0, 3.5, -4.0]), "map 0", 1.5)  # 1.8 m away
    assert not pad.near(np.array([1.0, 2.0, -4.0]), "map 1", 1.5)  # another VO map
    assert not pad.near(None, "map 0", 1.5)
    t0 = 2_000_000
    for k in range(9):
        assert pad.sample(t0 + k * 10_000, E_Z, np.eye(3))
    assert pad.down_body(t0 + 80_000, np.eye(3)) is None  # 9 < min_samples
    assert not pad.sample(t0 + 90_000, so3.rot_x(np.radians(8.0)) @ E_Z, np.eye(3))
    assert pad.refused == 1
    assert pad.sample(t0 + 100_000, E_Z, np.eye(3))
    got = pad.down_body(t0 + 100_000, np.eye(3))
    assert got is not None and _angle_deg(got[0], E_Z) < 1e-9 and got[1] == 0.002
    assert pad.down_body(t0 + 700_000, np.eye(3)) is None  # the samples aged out


@pytest.mark.parametrize("seed", [1, 2])
def test_the_pad_holds_the_vo_frame_through_a_climb_on_a_wrong_attitude(seed: int) -> None:
    """The SITL's vertical take-off from flat ground to 4 m (the PX4 loop's 320x240 camera and
    2 deg prior), with the autopilot's attitude right on the ground and 1.5 deg off in roll
    from 0.3 m up (an EKF without GNSS in the air: PX4 on SIH was 0.5-1.2 deg off in its
    climbs). Without the pad's gravity the VO frame tilted 8.3 / 6.1 deg (seeds 1 / 2) in the
    climb and ended it 0.6 / 1.2 deg off; with it (vo.pad_gravity_sigma_deg 0.3) 1.9 / 2.2 deg
    at worst, in the lift-off's first half second, and 0.3 / 0.5 deg at the top."""
    from peers import small_camera_takeoff

    from companion.offline import feed_step
    from companion.pipeline import Pipeline
    from companion.sitl.world.scenario import Scenario
    from companion.types import AttitudeSample

    cfg = small_camera_takeoff(seed, pad_gravity_sigma_deg=0.3)
    p = Pipeline(cfg)
    assert p.pad.level is not None
    R_err, R_of = so3.rot_x(np.radians(1.5)), so3.quat_to_matrix
    tilt_deg, height_m = [], []
    for st in Scenario(cfg).steps(stop=210, workers=2):  # the ground and the climb
        R_off = R_err if -st.T_world_body[2, 3] > 0.3 else np.eye(3)
        attitudes = [
            AttitudeSample(a.time_us, so3.matrix_to_quat(R_off @ R_of(a.quat_wxyz)), a.rates_rad_s)
            for a in st.attitudes
        ]
        feed_step(p, type(st)(st.frame, st.rendered, st.T_world_body, st.ranges, attitudes))
        p.background_work()
        R_vo_body = p.R_vo_body()
        if R_vo_body is None:
            continue
        down_vo = R_vo_body @ st.T_world_body[:3, :3].T @ E_Z
        tilt_deg.append(np.degrees(np.arccos(np.clip(down_vo[2], -1.0, 1.0))))
        height_m.append(-st.T_world_body[2, 3])
    assert p.vo.resets == 0 and max(height_m) > 3.5
    assert p.vo.pad_keyframes >= 15
    assert p.pad.level.refused <= 5
    assert max(tilt_deg) <= 3.0, (max(tilt_deg), seed)
    assert np.mean(tilt_deg[-15:]) <= 0.7, (tilt_deg[-15:], seed)


def test_the_pads_normal_is_the_mean_of_the_settled_planes_of_the_current_rest() -> None:
    """``at_rest`` keeps a running sum (a rest is ~30 planes a second): at every step its
    normal equals the mean, recomputed from scratch, of the current rest's planes older than
    the guard and within the window; a pause longer than the guard starts a new rest."""
    rng = np.random.default_rng(11)
    window_us, guard_us = 2_000_000, 300_000
    pad = PadLevel(500_000, 0.001, 0.09, rest_window_us=window_us, rest_guard_us=guard_us)
    seen: list[tuple[int, np.ndarray]] = []
    t = 0
    for k in range(900):
        t += int(rng.integers(5_000, 40_000)) + (1_000_000 if k == 500 else 0)  # one new rest
        if seen and t - seen[-1][0] > guard_us:
            seen = []
        R = so3.exp(rng.normal(0.0, 0.05, 3))
        n_body = _noisy(E_Z, rng, 2.0)
        seen.append((t, R @ n_body))
        pad.at_rest(t, n_body, R, None, "map 0")
        settled = [v for s, v in seen if guard_us <= t - s <= window_us]
        if settled and k != 500:  # just after the new rest, none has settled yet
            m = np.mean(settled, axis=0)
            assert pad.n_pad is not None
            assert np.allclose(pad.n_pad, m / np.linalg.norm(m), atol=1e-12), k
    assert len(seen) > 100  # the window was full many times over
