"""Simulated distance sensors and attitude: noise model, faults, range limits, determinism."""

from __future__ import annotations

import itertools
from collections.abc import Callable

import numpy as np

from companion.config import MountConfig, RangefinderConfig
from companion.geometry import so3
from companion.sitl.world.sensors import AttitudeSimulator, RangeSimulator, laser_hits
from companion.sitl.world.terrain import World
from companion.sitl.world.trajectory import Trajectory


def test_true_distance_is_exact_on_flat_ground(world: Callable[[str, int], World]) -> None:
    w = world("flat", 1)
    traj = Trajectory("hover", w, 10.0, altitude_m=5.0)
    rf = RangefinderConfig(sensor_id=0, mount=MountConfig((0.1, 0.0, 0.06), (0.0, 10.0, 0.0)))
    t, pts = laser_hits(w, traj.T_world_body(1.0), [rf])
    # beam pitched 10 deg forward from 5 m - 0.06 m above flat ground
    assert np.isclose(t[0], (5.0 - 0.06) / np.cos(np.radians(10.0)), atol=1e-9)
    assert np.isclose(pts[0, 2], 0.0, atol=1e-9)


def test_noise_model_dropouts_outliers(world: Callable[[str, int], World]) -> None:
    w = world("hills", 1)
    traj = Trajectory("lawnmower", w, 60.0)
    rf = RangefinderConfig(
        sensor_id=4,
        sigma_a_m=0.02,
        sigma_b=0.01,
        rate_hz=100.0,
        dropout_prob=0.2,
        outlier_prob=0.05,
    )
    sim = RangeSimulator(w, traj, [rf], seed=3)
    readings = sim.between(0.0, 40.0)
    assert len(readings) == 4000
    missing = np.mean([r.sample is None for r in readings])
    assert 0.17 < missing < 0.23
    present = [r for r in readings if r.sample is not None]
    z = np.array(
        [
            (r.sample.distance_m - r.true_distance_m) / (0.02 + 0.01 * r.true_distance_m)
            for r in present
        ]
    )
    outliers = np.abs(z) > 6
    assert 0.035 < outliers.mean() < 0.065
    assert 0.93 < np.std(z[~outliers]) < 1.07
    assert abs(np.mean(z[~outliers])) < 0.08
    # deterministic in (seed, sensor, time), whatever the query order
    again = sim.measure(0, present[100].sample.time_us)
    assert again.sample == present[100].sample


def test_out_of_range_is_flagged_invalid(world: Callable[[str, int], World]) -> None:
    w = world("flat", 1)
    traj = Trajectory("hover", w, 10.0, altitude_m=6.0)
    far = RangefinderConfig(sensor_id=0, min_m=0.1, max_m=3.0)
    near = RangefinderConfig(sensor_id=1, min_m=8.0, max_m=20.0)
    readings = RangeSimulator(w, traj, [far, near], seed=1).between(0.0, 1.0)
    assert readings and all(r.sample is not None for r in readings)
    for r in readings:
        assert r.sample is not None
        assert r.sample.signal_quality == 1 and not r.sample.is_valid
        assert r.sample.distance_m == (3.0 if r.sample.sensor_id == 0 else 8.0)


def test_rates_and_order(world: Callable[[str, int], World], default_config) -> None:  # type: ignore[no-untyped-def]
    w = world("hills", 2)
    traj = Trajectory("circle", w, 10.0)
    sim = RangeSimulator(w, traj, default_config.rangefinders, seed=2)
    readings = sim.between(0.0, 2.0)
    assert len(readings) == 4 * 50 * 2
    times = [r.sample.time_us for r in readings if r.sample]
    assert times == sorted(times)
    valid = [r for r in readings if r.sample and r.sample.is_valid]
    assert len(valid) == len(readings)


def test_readings_do_not_depend_on_how_they_are_asked_for(  # type: ignore[no-untyped-def]
    world: Callable[[str, int], World], default_config
) -> None:
    """The SITL autopilot asks for the readings of whatever time passed since its last loop
    (a few ms, or a stall's worth): the same reading, to the bit, whatever the windows, and
    each one equal to measure()'s at its time (the batched pose evaluation of between())."""
    w = world("hills", 2)
    traj = Trajectory("lawnmower", w, 10.0, takeoff_landing=True)
    sim = RangeSimulator(w, traj, default_config.rangefinders, seed=2)
    whole = sim.between(0.0, 3.0)
    rng = np.random.default_rng(7)
    cuts = np.concatenate([[0.0], np.sort(rng.uniform(0.0, 3.0, 40)), [3.0]])
    pieces = [r for a, b in itertools.pairwise(cuts) for r in sim.between(a, b)]
    assert len(whole) == len(pieces) == 4 * 50 * 3
    for a, b in zip(whole, pieces, strict=True):
        assert a.sample == b.sample and a.true_distance_m == b.true_distance_m
        assert np.array_equal(a.hit_world, b.hit_world)
    index = {rf.sensor_id: i for i, rf in enumerate(default_config.rangefinders)}
    for r in whole[::37]:
        if r.sample is None:
            continue
        one = sim.measure(index[r.sample.sensor_id], r.sample.time_us)
        assert one.sample == r.sample and np.array_equal(one.hit_world, r.hit_world)
    # the poses behind them: sample()'s, to the bit
    t = np.linspace(0.0, 10.0, 101)
    s = traj.sample(t)
    P = traj.poses(t)
    assert all(np.array_equal(P[i], s.T_world_body(i)) for i in range(len(t)))


def test_attitude_is_truth_with_small_error(world: Callable[[str, int], World]) -> None:
    w = world("hills", 1)
    traj = Trajectory("figure8", w, 20.0)
    samples = AttitudeSimulator(traj, seed=1, rate_hz=100.0, noise_deg=0.1).between(0.0, 10.0)
    assert len(samples) == 1000
    errs = [
        np.degrees(
            so3.angle_between(
                so3.quat_to_matrix(a.quat_wxyz), traj.T_world_body(a.time_us * 1e-6)[:3, :3]
            )
        )
        for a in samples[::10]
    ]
    assert 0.05 < np.mean(errs) < 0.3
