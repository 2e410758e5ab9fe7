"""The ground under the vehicle from the distance sensors: a VO map's start, the pad's gravity.

Planes are fitted in the body frame (FRD, metres) through the sensors' hit points
(companion/attitude/ground.py); a plane is ``n . p = h`` with ``n`` the downward unit normal
(3,) and ``h`` the body origin's distance to it [m]. Times are microseconds.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from companion.attitude import ground as ground_fit
from companion.attitude.pad import PadLevel
from companion.config import Config
from companion.scale.laser import RangeHistory
from companion.types import F64, GroundPlane
from companion.vo.keyframes import Down

LANDED_HEIGHT_SIGMA_M = 0.02  # a configured landing-gear height: its uncertainty [m]
GROUND_REST_SPREAD_M = 0.02  # readings spreading more than this (or 3 sigma) are not at rest
# the take-off pad's gravity (companion/attitude/pad.py): a plane of the readings every 10 ms
# (the TFmini's rate) while over the pad; at rest means still readings with the body at most
# PAD_REST_HEIGHT_M over their plane (a landing gear), and a sample further than
# PAD_MAX_ERROR_DEG from the autopilot's tilt is refused (a hit off the pad)
PAD_STEP_US = 10_000
PAD_REST_HEIGHT_M = 0.6
PAD_MAX_ERROR_DEG = 5.0
PAD_SIGMA_FLOOR_DEG = 0.1


class RestPlane(NamedTuple):
    """The ground plane of the readings at rest, in the body frame."""

    n_body: F64  # (3,) downward unit normal
    h_body_m: float  # the body origin's distance to the plane [m]
    sigma_m: float  # that distance's sigma [m]


class RangeGround:
    """The ground planes of the buffered ranges (``ranges``, by sensor id in ``specs``)."""

    def __init__(self, config: Config, T_body_cam: F64, ranges: RangeHistory) -> None:
        self.config = config
        self.T_body_cam = T_body_cam
        self.ranges = ranges
        self.specs = {r.sensor_id: r.spec() for r in config.rangefinders}
        self._beams_of: dict[tuple[int, ...], tuple[F64, F64]] = {}  # by sensor ids: origins, beams

    def ground_plane(self, time_us: int, R_world_body: F64 | None) -> GroundPlane | None:
        """The ground under the camera in metres, or None (it starts a VO map).

        The plane of the readings at rest (:meth:`rest_plane_body`) when the camera is within
        ``vo.ground_max_height_m`` of it. When >= 3 sensors read below their minimum instead
        (too close: on the ground), the plane is level at ``vo.landed_camera_height_m`` under
        the autopilot's attitude, if that height is configured."""
        o = self.config.vo
        rest = self.rest_plane_body(time_us)
        if rest is not None:
            return self._plane_in_camera(*rest, "ranges")
        t0 = time_us - int(o.ground_window_ms * 1e3)
        too_close = [s for s, t in self.ranges.too_close_us.items() if t >= t0]
        if len(too_close) >= 3 and o.landed_camera_height_m > 0 and R_world_body is not None:
            n_body = R_world_body.T @ np.array([0.0, 0.0, 1.0])  # level ground: gravity
            h_cam = o.landed_camera_height_m
            h_body = h_cam + float(n_body @ self.T_body_cam[:3, 3])
            return self._plane_in_camera(n_body, h_body, LANDED_HEIGHT_SIGMA_M, "landed")
        return None

    def rest_plane_body(self, time_us: int) -> RestPlane | None:
        """The ground plane of the readings at rest, or None.

        From the readings of the last ``vo.ground_window_ms`` of each sensor (their median;
        none when any sensor's readings spread more than 3 sigma or 2 cm: the vehicle is not at
        rest, e.g. low over a roof edge), >= 3 sensors: the least-squares plane through
        their hit points in the body frame, refused unless it fits them within
        ``vo.ground_max_rms_m``. The distance's sigma propagates each median's sigma (reading
        sigma / sqrt(n)) through the fit."""
        o = self.config.vo
        t0 = time_us - int(o.ground_window_ms * 1e3)
        ids, med, sig = [], [], []
        for sid in sorted(self.specs):
            d = self.ranges.window(sid, t0, time_us)
            if len(d) < 3:
                continue
            m = float(np.median(d))
            sigma = self.specs[sid].sigma_m(m)
            mad = 1.4826 * float(np.median(np.abs(d - m)))  # robust spread of the window
            if mad > max(3.0 * sigma, GROUND_REST_SPREAD_M):
                return None  # readings moving: not at rest on the ground (a roof edge, a climb)
            ids.append(sid)
            med.append(m)
            sig.append(sigma * 1.25 / np.sqrt(len(d)))
        if len(ids) < 3:
            return None
        fit = self.range_plane(ids, np.array(med))
        if fit is None:
            return None
        n_body, h_body, M = fit
        sigma_a = float(np.sqrt(np.sum((M[0] * np.array(sig)) ** 2)))
        return RestPlane(n_body, h_body, max(sigma_a, 1e-3))

    def range_plane(self, ids: list[int], range_m: F64) -> tuple[F64, float, F64] | None:
        """The plane through the hits of sensors ``ids`` at ``range_m`` (K,): (downward normal
        (3,), body origin's distance [m], the fit's (3, K) matrix), in the body frame; None
        when the hits are nearly on a line or fit no plane within ``vo.ground_max_rms_m``."""
        key = tuple(ids)
        beams_of = self._beams_of.get(key)
        if beams_of is None:
            T = np.stack([self.specs[s].T_body_rf for s in ids])
            beams_of = self._beams_of[key] = ground_fit.beams_body(T)
        origins, beams = beams_of
        pts = ground_fit.ground_points_body(origins, beams, range_m)
        (a, b, c), M = ground_fit.plane_fit(pts)
        rms = float(np.sqrt(np.mean((pts[:, 2] - (a + b * pts[:, 0] + c * pts[:, 1])) ** 2)))
        if rms > self.config.vo.ground_max_rms_m or ground_fit.spread_m(pts) < 0.05:
            return None
        n_body = ground_fit.normal_of(b, c)
        return n_body, float(n_body @ np.array([0.0, 0.0, a])), M

    def ranges_at(self, time_us: int) -> tuple[list[int], list[float]]:
        """(sensor ids, ranges [m]) of the sensors with a reading at ``time_us`` (within the
        scale's gap and age limits), by sensor id."""
        opts = self.config.scale
        ids, range_m = [], []
        for sid in sorted(self.specs):
            d = self.ranges.at(sid, time_us, opts.max_range_gap_us, opts.max_range_age_us)
            if d is not None:
                ids.append(sid)
                range_m.append(d)
        return ids, range_m

    def _plane_in_camera(
        self, n_body: F64, h_body: float, sigma_m: float, source: str
    ) -> GroundPlane | None:
        """The plane n_body . p = h_body (body frame) seen from the camera, if near enough."""
        R_body_cam, t_body_cam = self.T_body_cam[:3, :3], self.T_body_cam[:3, 3]
        n_cam = R_body_cam.T @ n_body
        d_cam = h_body - float(n_body @ t_body_cam)
        if not 0.0 < d_cam <= self.config.vo.ground_max_height_m:
            return None
        return GroundPlane(np.asarray(n_cam, dtype=np.float64), d_cam, sigma_m, source)


class PadGravity:
    """The take-off pad's gravity for the VO's keyframes (companion/attitude/pad.py), or off
    (``vo.pad_gravity_sigma_deg`` = 0: ``level`` is None)."""

    def __init__(self, config: Config, ground: RangeGround) -> None:
        o = config.vo
        self.config = config
        self.ground = ground
        self.level: PadLevel | None = None
        if o.pad_gravity_sigma_deg > 0:
            self.level = PadLevel(
                int(o.pad_window_s * 1e6),
                float(np.radians(max(o.pad_gravity_sigma_deg, PAD_SIGMA_FLOOR_DEG))),
                float(np.radians(PAD_MAX_ERROR_DEG)),
            )
        self._sampled_us = 0  # the last plane sampled over the pad

    def down(
        self,
        time_us: int,
        R_world_body: F64 | None,
        position_vo_m: F64 | None,
        segment: tuple[int, int],
        attitude_at: Callable[[int], F64 | None],
    ) -> Down | None:
        """The pad's gravity for this frame's keyframe, or None (off, no attitude, not over
        the pad, too few samples yet). At rest on the pad it measures the pad; at rest and
        over it (within ``vo.pad_radius_m`` of the rest, ``position_vo_m`` the last frame's
        metric body position in the VO frame, ``segment`` its (VO map, reset counter)) it
        samples the readings' plane every PAD_STEP_US since the last frame against the
        autopilot's attitude at that instant (``attitude_at``)."""
        pad = self.level
        if pad is None or R_world_body is None:
            return None
        rest = self.ground.rest_plane_body(time_us)
        if rest is not None and rest.h_body_m <= PAD_REST_HEIGHT_M:
            pad.at_rest(time_us, rest.n_body, R_world_body, position_vo_m, segment)
        elif not pad.near(position_vo_m, segment, self.config.vo.pad_radius_m):
            self._sampled_us = time_us
            return None
        t = max(self._sampled_us, time_us - int(self.config.vo.pad_window_s * 1e6))
        while t + PAD_STEP_US <= time_us:
            t += PAD_STEP_US
            ids, range_m = self.ground.ranges_at(t)
            R = attitude_at(t)
            fit = self.ground.range_plane(ids, np.array(range_m)) if len(ids) >= 3 else None
            if fit is not None and R is not None:
                pad.sample(t, fit[0], R)
        self._sampled_us = t
        return pad.down_body(time_us, R_world_body)
