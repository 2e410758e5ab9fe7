"""The distance sensors as they are ([sitl.rangefinder]): outliers at the configured rate and
only on depth edges and specular patches, a per-sensor bias within its sigma, the blind zone's
readings, and, with the defaults, the readings of before to the bit."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from companion.config import MountConfig, RangefinderConfig
from companion.sitl.world.sensors import RangeSimulator
from companion.sitl.world.terrain import World, make_world
from companion.sitl.world.trajectory import Trajectory
from companion.sitl_options import GroundOptions, RangeEffects
from companion.types import RangeSample

DOWN = RangefinderConfig(sensor_id=2, sigma_a_m=0.01, rate_hz=100.0)
TIMES_US = range(1_000, 3_001_000, 1_000)  # 3000 readings' seeds


def old_reading(
    rf: RangefinderConfig, seed: int, time_us: int, true_d: float
) -> RangeSample | None:
    """The range model before [sitl.rangefinder] existed, copied as it was (the reference)."""
    rng = np.random.default_rng([seed, 202, rf.sensor_id, time_us])
    u_drop, u_out, u_val, noise = rng.uniform(), rng.uniform(), rng.uniform(), rng.normal()
    if u_drop < rf.dropout_prob:
        return None
    if not np.isfinite(true_d) or true_d > rf.max_m:
        d, quality = rf.max_m, 1
    elif true_d < rf.min_m:
        d, quality = rf.min_m, 1
    elif u_out < rf.outlier_prob:
        d, quality = rf.min_m + u_val * (rf.max_m - rf.min_m), 100
    else:
        sigma = rf.sigma_a_m + rf.sigma_b * true_d
        d = true_d + sigma * noise
        d = min(max(d, rf.min_m), rf.max_m)
        quality = max(2, int(round(100 - 50 * true_d / rf.max_m)))
    return RangeSample(time_us, rf.sensor_id, float(d), rf.min_m, rf.max_m, quality)


def test_with_the_defaults_every_reading_is_the_one_of_before(
    world: Callable[[str, int], World],
) -> None:
    w = world("urban", 2)
    traj = Trajectory("lawnmower", w, 30.0, takeoff_landing=True)
    rfs = [
        RangefinderConfig(
            sensor_id=0, min_m=0.5, dropout_prob=0.1, outlier_prob=0.05, sigma_b=0.01
        ),
        RangefinderConfig(sensor_id=1, mount=MountConfig((0.2, 0.0, 0.06), (0.0, 20.0, 0.0))),
    ]
    sim = RangeSimulator(w, traj, rfs, 5, RangeEffects())
    readings = sim.between(0.0, 30.0)
    assert len(readings) > 2500
    kinds = set()
    for r in readings:
        if r.sample is not None:
            rf = rfs[r.sample.sensor_id]
            ref = old_reading(rf, 5, r.sample.time_us, r.true_distance_m)
            assert ref == r.sample  # the same floats, the same quality
            kinds.add("invalid" if ref.signal_quality == 1 else "valid")
    assert kinds == {"invalid", "valid"}  # the ground (below min_m) and the air were both read


def hover_sim(
    effects: RangeEffects, ground: GroundOptions | None = None, seed: int = 1
) -> RangeSimulator:
    w = make_world("flat", seed, 40.0, ground=ground)
    return RangeSimulator(w, Trajectory("hover", w, 5.0, 3.0), [DOWN], seed, effects)


def test_a_sensors_bias_is_constant_and_drawn_within_its_sigma() -> None:
    sigma = 0.03
    biases = np.array(
        [hover_sim(RangeEffects(bias_sigma_m=sigma), seed=s).bias_m[0] for s in range(1, 61)]
    )
    assert 0.7 * sigma < biases.std() < 1.3 * sigma
    assert np.all(np.abs(biases) < 4 * sigma)
    sim = hover_sim(RangeEffects(bias_sigma_m=sigma), seed=7)
    errors = np.array(
        [r.sample.distance_m - r.true_distance_m for r in sim.between(0.5, 4.5) if r.sample]
    )
    # 400 readings of 1 cm noise: their mean error is the bias within 3 sigma / sqrt(400)
    assert abs(errors.mean() - sim.bias_m[0]) < 3 * 0.01 / 20 + 1e-4
    assert sim.bias_m[0] != 0.0


def test_edge_outliers_come_at_their_rate_and_only_on_edges() -> None:
    sim = hover_sim(RangeEffects(edge_outlier_prob=0.25, edge_wild_share=0.4))
    hit = np.zeros(3)
    errors_edge = np.array(
        [sim._reading(0, t, 3.0, hit, (3.0, 8.0)).sample.distance_m - 3.0 for t in TIMES_US]  # type: ignore[union-attr]
    )
    outlier = np.abs(errors_edge) > 0.06
    n = len(TIMES_US)
    band = 4 * np.sqrt(0.25 * 0.75 / n)
    assert abs(outlier.mean() - 0.25) < band
    # mixed ones lie between the two surfaces; wild ones anywhere in the range
    mixed = outlier & (errors_edge > -0.06) & (errors_edge < 5.06)
    assert abs((outlier & ~mixed).sum() / outlier.sum() - 0.4 * 0.7) < 0.1  # wild outside [3, 8]
    # no edge in the beam: never an outlier
    plain = [sim._reading(0, t, 3.0, hit, None).sample.distance_m - 3.0 for t in TIMES_US]  # type: ignore[union-attr]
    assert np.max(np.abs(plain)) < 0.06


def test_the_beam_sees_a_roof_edge_and_not_the_open_ground() -> None:
    w = make_world("urban", 1, 80.0)
    sim = RangeSimulator(
        w, Trajectory("hover", w, 2.0), [DOWN], 1, RangeEffects(edge_outlier_prob=0.5)
    )
    xmin, _xmax, ymin, ymax, _, top = w.boxes[0]
    T = np.eye(4)  # beam straight down (+z of the sensor frame is down in NED)
    T[:3, 3] = (xmin, 0.5 * (ymin + ymax), -(top + 3.0))
    edge = sim.beam_edge(T, 3.0)
    assert edge is not None and abs(edge[0] - 3.0) < 0.01 and abs(edge[1] - (top + 3.0)) < 0.05
    T[:3, 3] = (0.0, 0.0, -3.0)  # the clear take-off area
    assert sim.beam_edge(T, 3.0) is None


def test_specular_patches_miss_or_read_through_at_their_rates() -> None:
    effects = RangeEffects(specular_miss_prob=0.2, specular_through_prob=0.3)
    sim = hover_sim(effects, GroundOptions(specular_patches=0.2))
    patches = sim.world.specular
    assert patches is not None
    x, y, _ = patches.discs[0]
    on = np.array([x, y, 0.0])
    depth = patches.bottom_depth_m(x, y)
    got = [sim._reading(0, t, 3.0, on).sample for t in TIMES_US]
    miss = np.array(
        [s is not None and s.signal_quality == 1 and s.distance_m == DOWN.max_m for s in got]
    )
    through = np.array([s is not None and abs(s.distance_m - 3.0 - depth) < 0.06 for s in got])
    band = 4 * np.sqrt(0.25 / len(got))
    assert abs(miss.mean() - 0.2) < band and abs(through.mean() - 0.3) < band
    # off the patches: the plain model
    far = patches.weight(19.0, -19.0)[0] < 0.5
    if far:
        plain = [sim._reading(0, t, 3.0, np.array([19.0, -19.0, 0])).sample for t in TIMES_US[:500]]
        assert all(abs(s.distance_m - 3.0) < 0.06 for s in plain if s is not None)


@pytest.mark.parametrize(
    ("below_min", "reads"), [("min", 0.1), ("zero", 0.0), ("saturated", 655.34)]
)
def test_in_the_blind_zone_the_sensor_reads_as_its_datasheet_says(
    below_min: str, reads: float
) -> None:
    sim = hover_sim(RangeEffects(below_min=below_min))  # type: ignore[arg-type]
    s = sim._reading(0, 5_000, 0.04, np.zeros(3)).sample
    assert s is not None and s.distance_m == reads and s.signal_quality == 1
    assert not s.is_valid
