"""Roll and pitch per frame: range tilt, terrain compensation and fusion (pure).

Inputs at a frame time: the valid readings of the attitude sensors (interpolated to the frame),
the VO rotation R_vo_body, the VO map points and the metric scale. Outputs: the tilt relative
to the ground under the hits ("ground"), the compensated tilt ("gravity") and the fused
attitude ("fused"), each None with a reason when the input does not allow it. Reasons are
short sentences for the status ("sensor 2: hit 0.31 m off the surface around it (edge?)").
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from companion.attitude.fusion import TiltFilter, vo_tilt_cov_in_body
from companion.attitude.ground import RangeTilt, beams_body, tilt_from_normal, tilt_from_ranges
from companion.attitude.options import AttitudeOptions
from companion.attitude.terrain import compensate, surfaces_under, terrain_tilt_cov
from companion.errors import ConfigError, GeometryError
from companion.types import F64, RangeSensorSpec, TiltEstimate


@dataclass(frozen=True, slots=True)
class CloudView:
    """What the compensation needs from the VO at a frame.

    R_vo_body: (3, 3); body_position_m: (3,) body origin in the scaled VO frame [m];
    points_m: (N, 3) map points in the scaled VO frame [m] (gravity-aligned, z down).
    """

    R_vo_body: F64
    body_position_m: F64
    points_m: F64


@dataclass(frozen=True, slots=True)
class TiltStep:
    """Result of one frame (see the module docstring); reasons explain every None."""

    ground: TiltEstimate | None
    gravity: TiltEstimate | None
    fused: TiltEstimate | None
    reasons: tuple[str, ...] = field(default=())
    terrain_tilt_rad: float = float("nan")  # angle of the terrain under the hits from level


class RollPitch:
    """Range-based roll/pitch with terrain compensation and the VO-tilt filter."""

    def __init__(self, specs: Mapping[int, RangeSensorSpec], opts: AttitudeOptions) -> None:
        ids = tuple(opts.sensor_ids) or tuple(sorted(specs))
        unknown = [i for i in ids if i not in specs]
        if unknown:
            raise ConfigError(f"attitude.sensor_ids: no rangefinder with id {unknown}")
        if len(ids) < 3:
            raise ConfigError(f"attitude.sensor_ids: 3 sensors needed, got {list(ids)}")
        self.opts = opts
        self.ids = ids
        self.specs = {i: specs[i] for i in ids}
        origins, beams = beams_body(np.stack([specs[i].T_body_rf for i in ids]))
        self.origins = dict(zip(ids, origins, strict=True))
        self.beams = dict(zip(ids, beams, strict=True))
        self.filter = TiltFilter(
            np.radians(opts.drift_deg_per_sqrt_s),
            np.radians(opts.init_sigma_deg),
            opts.gate_chi2,
            opts.error_correlation_s,
        )
        self.segment = -1
        self.refused = 0

    def _ground(self, ids: list[int], range_m: Mapping[int, float]) -> RangeTilt:
        d = np.array([range_m[i] for i in ids])
        sigma = np.array([self.specs[i].sigma_m(range_m[i]) for i in ids])
        return tilt_from_ranges(
            np.stack([self.origins[i] for i in ids]),
            np.stack([self.beams[i] for i in ids]),
            d,
            np.maximum(sigma, 1e-4),
            tuple(ids),
            self.opts.min_spread_m,
        )

    def step(
        self,
        time_us: int,
        range_m: Mapping[int, float],
        cloud: CloudView | None,
        segment: int,
        R_world_body_autopilot: F64 | None = None,
    ) -> TiltStep:
        """One frame: ``range_m`` holds the valid readings [m] by sensor id at ``time_us``;
        ``cloud`` the VO view (None when not tracking with a scale); ``segment`` the VO map
        index (a new one resets the filter); ``R_world_body_autopilot`` the autopilot's
        attitude at that time, used as a gravity anchor when attitude.autopilot_sigma_deg > 0."""
        o = self.opts
        reasons: list[str] = []
        if cloud is not None and segment != self.segment:
            self.filter.reset(time_us)
            self.segment = segment
        if cloud is not None and R_world_body_autopilot is not None and o.autopilot_sigma_deg > 0:
            roll_ap, pitch_ap = tilt_from_normal(R_world_body_autopilot.T @ np.array([0, 0, 1.0]))
            self.filter.update(
                time_us,
                roll_ap,
                pitch_ap,
                np.eye(2) * np.radians(o.autopilot_sigma_deg) ** 2,
                cloud.R_vo_body,
                source="autopilot",
                correlation_s=o.autopilot_correlation_s,
            )
        ids = [i for i in self.ids if i in range_m and np.isfinite(range_m[i])]
        for i in self.ids:
            if i not in ids:
                reasons.append(f"sensor {i}: no valid reading")
        if len(ids) < 3:
            self.refused += 1
            reason = f"{len(ids)} valid readings, 3 needed"
            return TiltStep(None, None, self._fused(time_us, cloud), (*reasons, reason))
        try:
            raw = self._ground(ids, range_m)
        except GeometryError as e:
            self.refused += 1
            return TiltStep(None, None, self._fused(time_us, cloud), (*reasons, str(e)))
        if np.degrees(np.arccos(np.clip(raw.normal_body[2], -1, 1))) > o.max_tilt_deg:
            self.refused += 1
            reason = f"ground plane tilted more than {o.max_tilt_deg:g} deg from the body"
            return TiltStep(None, None, self._fused(time_us, cloud), (*reasons, reason))
        ground = TiltEstimate(
            time_us, raw.roll_rad, raw.pitch_rad, raw.cov_rad2, "ground", len(ids)
        )
        gravity: TiltEstimate | None = None
        terrain_tilt = float("nan")
        if cloud is None:
            reasons.append("no VO cloud: tilt relative to the ground only")
        else:
            gravity, terrain_tilt, why = self._compensated(time_us, ids, range_m, raw, cloud)
            reasons.extend(why)
        measurement = gravity if o.compensate else ground
        if cloud is not None and measurement is not None and o.fuse_ranges:
            self.filter.update(
                time_us,
                measurement.roll_rad,
                measurement.pitch_rad,
                measurement.cov_rad2,
                cloud.R_vo_body,
                source="ranges",
            )
        return TiltStep(ground, gravity, self._fused(time_us, cloud), tuple(reasons), terrain_tilt)

    def _compensated(
        self,
        time_us: int,
        ids: list[int],
        range_m: Mapping[int, float],
        raw: RangeTilt,
        cloud: CloudView,
    ) -> tuple[TiltEstimate | None, float, list[str]]:
        o = self.opts
        reasons: list[str] = []
        if len(cloud.points_m) == 0:
            return None, float("nan"), ["no metric VO cloud yet: compensation waits for the scale"]
        hits_m = cloud.body_position_m + raw.points_body @ cloud.R_vo_body.T
        keep: list[int] = []
        heights: list[float] = []
        sigmas: list[float] = []
        patches = surfaces_under(
            cloud.points_m, hits_m[:, :2], o.patch_radius_m, o.min_patch_points
        )
        for k, (i, patch) in enumerate(zip(ids, patches, strict=True)):
            if patch is None:
                reasons.append(f"sensor {i}: too few cloud points around the hit")
            elif patch.rms_m > o.max_patch_rms_m:
                reasons.append(
                    f"sensor {i}: surface around the hit too rough ({patch.rms_m:.2f} m)"
                )
            elif abs(hits_m[k, 2] - patch.height_m) > o.edge_gate_m:
                off = abs(hits_m[k, 2] - patch.height_m)
                reasons.append(f"sensor {i}: hit {off:.2f} m off the surface around it (edge?)")
            else:
                keep.append(k)
                heights.append(patch.height_m)
                sigmas.append(patch.sigma_m)
        if len(keep) < 3:
            self.refused += 1
            return None, float("nan"), [*reasons, "terrain compensation needs 3 good hits"]
        if len(keep) < len(ids):
            try:
                raw = self._ground([ids[k] for k in keep], range_m)
            except GeometryError as e:
                self.refused += 1
                return None, float("nan"), [*reasons, str(e)]
        xy = hits_m[keep, :2]
        n_vo, cov_t = terrain_tilt_cov(xy, np.array(heights), np.array(sigmas))
        terrain_tilt = float(np.arccos(np.clip(n_vo[2], -1.0, 1.0)))
        if np.degrees(terrain_tilt) > o.max_terrain_tilt_deg:
            self.refused += 1
            why = f"terrain under the hits steeper than {o.max_terrain_tilt_deg:g} deg"
            return None, terrain_tilt, [*reasons, why]
        g_b = compensate(raw.normal_body, n_vo, cloud.R_vo_body)
        roll, pitch = tilt_from_normal(g_b)
        cov = raw.cov_rad2 + vo_tilt_cov_in_body(cov_t, cloud.R_vo_body)
        est = TiltEstimate(time_us, roll, pitch, cov, "gravity", len(keep))
        return est, terrain_tilt, reasons

    def _fused(self, time_us: int, cloud: CloudView | None) -> TiltEstimate | None:
        if cloud is None or cloud.R_vo_body is None:
            return None
        self.filter.predict(time_us)
        roll, pitch, cov = self.filter.attitude(cloud.R_vo_body)
        return TiltEstimate(time_us, roll, pitch, cov, "fused", 0)
