"""The VO frame's heading from our own compass (companion/attitude/heading.py and the
pipeline's vo.heading_source = magnetometer): the tilt-compensated heading as a geometric
identity, its average and uncertainty over noisy samples at rest, the window's end at the
first motion, and a seeded SITL take-off whose autopilot heading is 3 deg off."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.attitude.heading import MagHeading, magnetic_yaw_rad
from companion.geometry import so3
from companion.types import ImuSample

G_NED = np.array([0.0, 0.0, 9.80665])
INCLINATION_RAD = math.radians(64.0)  # central Europe: the field dips 64 deg
FIELD_GAUSS = 0.48


def _field_world(declination_rad: float) -> np.ndarray:
    """(3,) the Earth's field in NED [gauss]: horizontal towards the declination, dipping."""
    h = FIELD_GAUSS * math.cos(INCLINATION_RAD)
    return np.array(
        [
            h * math.cos(declination_rad),
            h * math.sin(declination_rad),
            FIELD_GAUSS * math.sin(INCLINATION_RAD),
        ]
    )


def _still_samples(
    R_world_body: np.ndarray,
    declination_rad: float,
    n: int,
    rng: np.random.Generator,
    field_noise: float = 0.02,
    t0_us: int = 0,
) -> list[ImuSample]:
    """n samples at 50 Hz of a body at rest (accelerometer 0.05 m/s^2 and gyroscope 2 mrad/s
    of noise, the field with ``field_noise`` gauss per axis: PX4 SIH's)."""
    f = R_world_body.T @ -G_NED
    m = R_world_body.T @ _field_world(declination_rad)
    return [
        ImuSample(
            t0_us + 20_000 * k,
            f + rng.normal(0.0, 0.05, 3),
            rng.normal(0.0, 0.002, 3),
            m + rng.normal(0.0, field_noise, 3),
        )
        for k in range(n)
    ]


def test_the_tilt_compensated_heading_is_the_bodys_yaw_at_any_attitude() -> None:
    """Noise-free: equation (1) returns the ZYX yaw of R_world_body for tilts up to 30 deg,
    any heading and declination (a wrong sign on the declination or on the cross product, or
    a tilt left in, is off by degrees here)."""
    rng = np.random.default_rng(3)
    for _ in range(200):
        roll, pitch = np.radians(rng.uniform(-30, 30, 2))
        yaw = rng.uniform(-math.pi, math.pi)
        decl = math.radians(rng.uniform(-20, 20))
        R = so3.rpy_to_matrix(roll, pitch, yaw)
        got = magnetic_yaw_rad(R.T @ -G_NED, R.T @ _field_world(decl), decl)
        assert abs(math.remainder(got - yaw, 2 * math.pi)) < 1e-9, (roll, pitch, yaw, decl)


def test_a_field_without_horizontal_part_has_no_heading() -> None:
    assert math.isnan(magnetic_yaw_rad(-G_NED, np.array([0.0, 0.0, 0.5]), 0.0))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_average_at_rest_beats_one_sample_and_its_sigma_says_by_how_much(seed: int) -> None:
    """SIH's noise (0.02 gauss a sample, ~5 deg of heading): 20 s at 50 Hz put the heading
    within 4 sigma of the truth, sigma near the white-noise bound 5.2 deg / sqrt(1000)."""
    rng = np.random.default_rng(seed)
    R = so3.rpy_to_matrix(np.radians(1.5), np.radians(-2.0), np.radians(37.0))
    decl = math.radians(3.3)
    h = MagHeading(decl)
    for s in _still_samples(R, decl, 1000, rng):
        h.add(s)
    fix = h.fix()
    assert fix is not None and fix.samples == 1000 and not h.moved
    assert fix.span_us == 999 * 20_000
    one_sample_deg = math.degrees(0.02 / (FIELD_GAUSS * math.cos(INCLINATION_RAD)))
    assert 0.8 < math.degrees(fix.sigma_rad) / (one_sample_deg / math.sqrt(1000)) < 1.2
    error = math.remainder(fix.yaw_rad - math.radians(37.0), 2 * math.pi)
    assert abs(error) < 4 * fix.sigma_rad, (math.degrees(error), math.degrees(fix.sigma_rad))


def test_the_window_ends_at_the_first_motion_and_ignores_what_comes_after() -> None:
    """A rate above 0.05 rad/s (or a specific force 0.5 m/s^2 off 1 g) ends the window for
    good: a turned body's samples afterwards do not move the fix. Samples without a field
    keep the window open but add nothing; older samples are ignored."""
    rng = np.random.default_rng(4)
    decl = 0.0
    R0 = so3.rot_z(np.radians(10.0))
    h = MagHeading(decl)
    still = _still_samples(R0, decl, 100, rng, field_noise=0.001)
    for s in still:
        h.add(s)
    before = h.fix()
    assert before is not None and abs(math.degrees(before.yaw_rad) - 10.0) < 0.1
    h.add(ImuSample(2_000_000, -G_NED, np.zeros(3), None))  # no magnetometer: kept open
    h.add(ImuSample(1_500_000, -G_NED, np.zeros(3), np.array([0.2, 0.0, 0.4])))  # older
    assert not h.moved and h.samples == 100
    h.add(ImuSample(2_010_000, -G_NED, np.zeros(3), still[-1].mag_frd_gauss))  # sent again
    assert h.samples == 100
    h.add(ImuSample(2_020_000, -G_NED, np.array([0.0, 0.0, 0.3]), np.array([0.2, 0.0, 0.4])))
    assert h.moved
    for s in _still_samples(so3.rot_z(np.radians(50.0)), decl, 50, rng, t0_us=2_040_000):
        h.add(s)
    assert h.fix() == before
    accelerating = MagHeading(decl)
    accelerating.add(ImuSample(0, -G_NED * 1.1, None, np.array([0.2, 0.0, 0.4])))
    assert accelerating.moved and accelerating.fix() is None


def test_the_pipeline_takes_its_frames_heading_from_the_compass_before_the_take_off() -> None:
    """A SITL take-off (3.5 s on the ground, then a climb) with the autopilot's heading 3 deg
    off the truth and a compass beside it (SCALED_IMU's field at 50 Hz, 0.005 gauss of noise,
    declination 3.3 deg). The VO frame starts on the autopilot's heading (3 deg off); after
    vo.mag_heading_min_s at rest it takes the compass's (within 0.3 deg of the truth), and at
    the take-off it stops refining and keeps it through the climb. With heading_source =
    autopilot the same flight keeps the 3 deg."""
    from peers import feed_biased_step

    from companion.config import load_config
    from companion.pipeline import Pipeline
    from companion.sitl.world.scenario import Scenario

    decl = math.radians(3.3)

    def fly(source: str) -> tuple[Pipeline, list[float], list[float | None]]:
        cfg = load_config(
            None,
            {
                "sitl": {
                    "terrain": "flat",
                    "trajectory": "hover",
                    "takeoff_landing": True,
                    "seconds": 10.0,
                    "seed": 2,
                },
                "vo": {
                    "heading_source": source,
                    "mag_declination_deg": 3.3,
                    "mag_heading_min_s": 1.5,
                },
            },
        )
        sc = Scenario(cfg)
        rng = np.random.default_rng(2)
        t_imu = np.arange(0.0, cfg.sitl.seconds, 0.02)
        tr = sc.trajectory.sample(t_imu)
        f_body = np.einsum("nji,nj->ni", tr.R_world_body, tr.accel_m_s2 - G_NED)
        m_body = np.einsum("nji,j->ni", tr.R_world_body, _field_world(decl))
        imus = [
            ImuSample(
                int(round(t * 1e6)),
                f + rng.normal(0.0, 0.05, 3),
                rng.normal(0.0, 0.002, 3),
                m + rng.normal(0.0, 0.005, 3),
            )
            for t, f, m in zip(t_imu, f_body, m_body, strict=True)
        ]
        R_err = so3.rot_z(np.radians(3.0))  # the autopilot's heading error
        p = Pipeline(cfg)
        errors_deg, final = [], []
        k_imu = 0
        for st in sc.steps(stop=140, workers=2):  # the ground and the climb to ~3 m
            k_imu = feed_biased_step(p, st, imus, k_imu, R_err)
            R_vo_body = p.R_vo_body()
            if R_vo_body is None or p.vo.state.value != "tracking":
                continue
            # the VO frame's true heading: the body's true yaw minus its yaw in the VO frame
            true_rad = (
                so3.matrix_to_rpy(st.T_world_body[:3, :3])[2] - so3.matrix_to_rpy(R_vo_body)[2]
            )
            errors_deg.append(math.degrees(math.remainder(p.vo.yaw_vo_rad - true_rad, 2 * math.pi)))
            final.append(p.vo.yaw_vo_rad if p.compass.ended else None)
        return p, errors_deg, final

    p, errors_deg, final = fly("magnetometer")
    assert p.vo.resets == 0
    assert 2.5 < errors_deg[0] < 3.5, errors_deg[:3]  # the autopilot's heading first
    assert p.compass.fix is not None and p.compass.ended
    assert p.compass.fix.samples >= 75  # >= 1.5 s at 50 Hz
    assert abs(errors_deg[-1]) < 0.3, errors_deg[-1]
    k_final = next(k for k, yaw in enumerate(final) if yaw is not None)
    assert 40 < k_final < 100  # the take-off (3.5 s on the ground at 20-30 Hz)
    assert len(set(final[k_final:])) == 1  # the frame's heading kept through the climb
    assert max(abs(e) for e in errors_deg[k_final:]) < 0.3  # (the VO's own yaw drift on it)
    status = p.status()
    assert status.mag_heading_final and status.mag_heading_samples == p.compass.fix.samples

    p, errors_deg, _ = fly("autopilot")
    assert p.compass.fix is None and all(2.5 < e < 3.5 for e in errors_deg), errors_deg[-3:]
