"""Simulated distance sensors and autopilot attitude, ray cast against the same world.

Range model (per sensor, from its RangefinderConfig): the beam leaves the sensor origin along
+z of the sensor frame (T_body_rf); the true distance is the exact ray-cast distance to the
first surface; the reading is true + N(0, sigma), sigma = a + b * range. With probability
``dropout_prob`` no reading is produced; with ``outlier_prob`` the reading is uniform in
[min_m, max_m]. A true distance outside [min_m, max_m] yields signal_quality 1 (invalid) and the
nearest limit, as a TFmini-class sensor reports. Each sensor runs at its own rate with a seeded
phase. Randomness is drawn from per-sample seeded generators, so the readings do not depend
on the order or grouping of queries.

The sensors as they are ([sitl.rangefinder], companion/sitl_options.py; all off by default, and
then every reading is the one above to the bit), each from its own seeded draws:
- a constant bias per sensor, N(0, bias_sigma_m) drawn once per (seed, sensor id);
- depth edges: six more rays on the beam's cone (half of beam_fov_deg off its axis); when the
  distances inside the beam spread by more than edge_jump_m (a miss counts as far), the reading
  is, with edge_outlier_prob, a mixed pixel (uniform between the nearest and the farthest
  surface) or, for edge_wild_share of them, a wild value (uniform in [min_m, max_m]);
- specular patches (water, glass: surfaces.SpecularPatches, weight >= 0.5 at the hit): no
  return (the maximum, flagged invalid) with specular_miss_prob, or a reading through to the
  bottom (true + the patch's depth) with specular_through_prob;
- below min_m (on the ground, the sensor in its blind zone): ``below_min`` says what is read,
  always flagged invalid: ``min`` the minimum (as PX4 publishes), ``zero`` 0 m (TFmini Plus
  manual: Dist = 0 when the signal strength is < 100 or saturated at 65535, as it is that
  close), ``saturated`` 655.34 m (TFmini-S manual: Dist = -2 on a saturated signal, 0xFFFE cm).
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
from companion.sitl_options import RangeEffects
from companion.types import F64, AttitudeSample, RangeSample

_BELOW_MIN = {"zero": 0.0, "saturated": 655.34}  # what a TFmini reads in its blind zone [m]


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
        effects: RangeEffects | None = None,
    ) -> None:
        self.world = world
        self.trajectory = trajectory
        self.rangefinders = tuple(rangefinders)
        self.seed = seed
        self.effects = effects or RangeEffects()
        self.bias_m = np.array(
            [
                self.effects.bias_sigma_m
                * np.random.default_rng([seed, 606, rf.sensor_id]).standard_normal()
                for rf in self.rangefinders
            ]
        )
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
            true_d = float(hits.t_m[0])
            edge = self.beam_edge(T_world_rf, true_d) if self.effects.edge_outlier_prob else None
            out.append(self._reading(i, int(tu), true_d, hits.points_world[0], edge))
        return out

    def beam_edge(self, T_world_rf: F64, true_d: float) -> tuple[float, float] | None:
        """(nearest, farthest) distance [m] inside the beam of a sensor at pose T_world_rf when
        they spread by more than edge_jump_m (a depth edge in the beam; a miss counts as the
        sensor's reach), else None. Six rays on the cone at half the beam's divergence."""
        half = np.radians(0.5 * self.effects.beam_fov_deg)
        phi = np.arange(6) * (np.pi / 3.0)
        axes = T_world_rf[:3, :3]
        dirs = np.cos(half) * axes[:, 2][None, :] + np.sin(half) * (
            np.cos(phi)[:, None] * axes[:, 0] + np.sin(phi)[:, None] * axes[:, 1]
        )
        t = self.world.raycast(np.repeat(T_world_rf[None, :3, 3], 6, axis=0), dirs).t_m
        reach = max(rf.max_m for rf in self.rangefinders) * 2.0
        ts = np.minimum(np.append(t, true_d), reach)
        near, far = float(ts.min()), float(ts.max())
        return (near, far) if far - near > self.effects.edge_jump_m else None

    def _reading(
        self,
        index: int,
        time_us: int,
        true_d: float,
        hit: F64,
        edge: tuple[float, float] | None = None,
    ) -> TrueRange:
        """The noise model on a true distance [m] (its draws seeded by seed, sensor, time)."""
        rf = self.rangefinders[index]
        rng = np.random.default_rng([self.seed, 202, rf.sensor_id, time_us])
        u_drop, u_out, u_val, noise = rng.uniform(), rng.uniform(), rng.uniform(), rng.normal()
        if u_drop < rf.dropout_prob:
            return TrueRange(None, true_d, hit)
        seen, wild = self._seen(rf, time_us, true_d, hit, edge)
        if not np.isfinite(seen) or seen > rf.max_m:
            d, quality = rf.max_m, 1
        elif true_d < rf.min_m:
            d, quality = _BELOW_MIN.get(self.effects.below_min, rf.min_m), 1
        elif wild:
            d, quality = seen, 100
        elif u_out < rf.outlier_prob:
            d, quality = rf.min_m + u_val * (rf.max_m - rf.min_m), 100
        else:
            sigma = rf.sigma_a_m + rf.sigma_b * seen
            d = seen + sigma * noise
            if self.bias_m[index]:
                d += float(self.bias_m[index])
            d = min(max(d, rf.min_m), rf.max_m)
            quality = max(2, int(round(100 - 50 * seen / rf.max_m)))
        sample = RangeSample(time_us, rf.sensor_id, float(d), rf.min_m, rf.max_m, quality)
        return TrueRange(sample, true_d, hit)

    def _seen(
        self,
        rf: RangefinderConfig,
        time_us: int,
        true_d: float,
        hit: F64,
        edge: tuple[float, float] | None,
    ) -> tuple[float, bool]:
        """The distance the sensor takes for the surface's [m] (inf: no return), and whether
        that is a wild value: the depth-edge and specular-patch models (module docstring)."""
        e = self.effects
        patches = self.world.specular
        on_patch = (
            patches is not None
            and np.isfinite(true_d)
            and float(patches.weight(hit[0], hit[1])[0]) >= 0.5
        )
        if edge is None and not on_patch:
            return true_d, False
        draws = np.random.default_rng([self.seed, 203, rf.sensor_id, time_us]).uniform(size=3)
        u_fx, u_kind, u_mix = (float(u) for u in draws)
        if edge is not None:
            if u_fx >= e.edge_outlier_prob:
                return true_d, False
            if u_kind < e.edge_wild_share:
                return rf.min_m + u_mix * (rf.max_m - rf.min_m), True
            return edge[0] + u_mix * (edge[1] - edge[0]), False
        assert patches is not None
        if u_fx < e.specular_miss_prob:
            return float("inf"), False
        if u_fx < e.specular_miss_prob + e.specular_through_prob:
            return true_d + patches.bottom_depth_m(hit[0], hit[1]), False
        return true_d, False

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
