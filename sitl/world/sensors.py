"""Simulated distance sensors and autopilot attitude, ray cast against the same world.

Range model (per sensor, from its RangefinderConfig): the beam leaves the sensor origin along
+z of the sensor frame (T_body_rf); the true distance is the exact ray-cast distance to the
first surface; the reading is true + N(0, sigma), sigma = a + b * range. With probability
``dropout_prob`` no reading is produced; with ``outlier_prob`` the reading is uniform in
[min_m, max_m]. A true distance outside [min_m, max_m] yields signal_quality 1 (invalid) and the
nearest limit, as a TFmini-class sensor reports. Each sensor runs at its own rate with a seeded
phase. Randomness is drawn from per-sample seeded generators, so the readings do not depend
on the order or grouping of queries.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.config import RangefinderConfig
from companion.geometry import so3
from companion.sitl.world.terrain import World
from companion.sitl.world.trajectory import Trajectory
from companion.types import F64, AttitudeSample, RangeSample


@dataclass(frozen=True, slots=True)
class TrueRange:
    """A range sample with its ground truth: true distance [m] and hit point (3,) NED [m]."""

    sample: RangeSample | None  # None = dropout
    true_distance_m: float
    hit_world: F64


def laser_hits(
    world: World, T_world_body: F64, rangefinders: Sequence[RangefinderConfig]
) -> tuple[F64, F64]:
    """Exact beam distances (K,) [m] and hit points (K, 3) for the sensors at a body pose."""
    origins = np.empty((len(rangefinders), 3))
    dirs = np.empty((len(rangefinders), 3))
    for i, rf in enumerate(rangefinders):
        T_world_rf = T_world_body @ rf.mount.T_body_sensor()
        origins[i] = T_world_rf[:3, 3]
        dirs[i] = T_world_rf[:3, 2]
    hits = world.raycast(origins, dirs)
    return hits.t_m, hits.points_world


class RangeSimulator:
    """Produces the range samples of every sensor over a flight, in time order."""

    def __init__(
        self,
        world: World,
        trajectory: Trajectory,
        rangefinders: Sequence[RangefinderConfig],
        seed: int,
    ) -> None:
        self.world = world
        self.trajectory = trajectory
        self.rangefinders = tuple(rangefinders)
        self.seed = seed
        phase_rng = np.random.default_rng([seed, 101])
        self.phase_s = phase_rng.uniform(0.0, 1.0, len(self.rangefinders))
        self._T_body_rf = [rf.mount.T_body_sensor() for rf in self.rangefinders]

    def sample_times_us(self, index: int, t0_s: float, t1_s: float) -> NDArray[np.int64]:
        """Measurement times [us] of sensor ``index`` within [t0_s, t1_s)."""
        rf = self.rangefinders[index]
        period = 1.0 / rf.rate_hz
        k0 = int(np.ceil(t0_s / period - self.phase_s[index]))
        k1 = int(np.ceil(t1_s / period - self.phase_s[index]))
        k = np.arange(max(k0, 0), max(k1, 0))
        times: NDArray[np.int64] = np.round((k + self.phase_s[index]) * period * 1e6).astype(
            np.int64
        )
        return times

    def measure(self, index: int, time_us: int) -> TrueRange:
        """The reading of sensor ``index`` at ``time_us`` (deterministic in seed, sensor, time)."""
        return self.measure_many([index], [time_us])[0]

    def measure_many(self, indices: Sequence[int], times_us: Sequence[int]) -> list[TrueRange]:
        """The readings of sensors ``indices`` at ``times_us`` (paired), each equal to the bit
        to measure()'s, with the poses from one spline evaluation."""
        if len(indices) == 0:
            return []
        poses = self.trajectory.poses(np.asarray(times_us, dtype=np.float64) * 1e-6)
        out = []
        for n, (i, tu) in enumerate(zip(indices, times_us, strict=True)):
            # one beam per cast: the ray-casting kernel's last bits depend on the batch (1e-8 m),
            # and a reading must not depend on which others were asked with it
            T_world_rf = poses[n] @ self._T_body_rf[i]
            hits = self.world.raycast(T_world_rf[:3, 3], T_world_rf[:3, 2])
            out.append(self._reading(i, int(tu), float(hits.t_m[0]), hits.points_world[0]))
        return out

    def _reading(self, index: int, time_us: int, true_d: float, hit: F64) -> TrueRange:
        """The noise model on a true distance [m] (its draws seeded by seed, sensor, time)."""
        rf = self.rangefinders[index]
        rng = np.random.default_rng([self.seed, 202, rf.sensor_id, time_us])
        u_drop, u_out, u_val, noise = rng.uniform(), rng.uniform(), rng.uniform(), rng.normal()
        if u_drop < rf.dropout_prob:
            return TrueRange(None, true_d, hit)
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
        sample = RangeSample(time_us, rf.sensor_id, float(d), rf.min_m, rf.max_m, quality)
        return TrueRange(sample, true_d, hit)

    def valid_at(self, time_us: int) -> dict[int, float]:
        """The valid readings [m] of every sensor at ``time_us`` by id (dropouts and invalid
        readings left out): what a replay at frame times needs."""
        got = {}
        for i, rf in enumerate(self.rangefinders):
            smp = self.measure(i, time_us).sample
            if smp is not None and smp.is_valid:
                got[rf.sensor_id] = smp.distance_m
        return got

    def between(self, t0_s: float, t1_s: float) -> list[TrueRange]:
        """All readings of all sensors with times in [t0_s, t1_s), sorted by time then id."""
        keys: list[tuple[int, int, int]] = []  # (time, id, sensor index)
        for i, rf in enumerate(self.rangefinders):
            keys += [(int(tu), rf.sensor_id, i) for tu in self.sample_times_us(i, t0_s, t1_s)]
        keys.sort()
        return self.measure_many([i for _, _, i in keys], [tu for tu, _, _ in keys])


class AttitudeSimulator:
    """The autopilot's attitude estimate: truth plus a small seeded error (white + slow bias)."""

    def __init__(
        self, trajectory: Trajectory, seed: int, rate_hz: float = 100.0, noise_deg: float = 0.1
    ) -> None:
        self.trajectory = trajectory
        self.seed = seed
        self.rate_hz = rate_hz
        self.noise_rad = np.radians(noise_deg)

    def between(self, t0_s: float, t1_s: float) -> list[AttitudeSample]:
        """Samples with times in [t0_s, t1_s)."""
        period = 1.0 / self.rate_hz
        k = np.arange(
            max(int(np.ceil(t0_s / period - 1e-9)), 0), max(int(np.ceil(t1_s / period - 1e-9)), 0)
        )
        if len(k) == 0:
            return []
        times_us = np.round(k * period * 1e6).astype(np.int64)
        s = self.trajectory.sample(times_us * 1e-6)
        out = []
        for i, tu in enumerate(times_us):
            rng = np.random.default_rng([self.seed, 303, int(tu)])
            err = so3.exp(self.noise_rad * rng.standard_normal(3))
            q = so3.matrix_to_quat(s.R_world_body[i] @ err)
            out.append(AttitudeSample(int(tu), q, s.omega_body_rad_s[i].copy()))
        return out
