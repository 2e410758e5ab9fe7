"""MSC: metric scale from one distance sensor matched to the VO point cloud.

At a frame, the sensor's laser point P_cam (camera frame, metres) is projected with the full
camera model (distortion included); among the VO features with a 3D point inside a square
patch around that pixel, the closest one is taken (the thesis prefers the closest point to a
plane fit on rough terrain). The scale is the ratio of the metric distance camera -> laser
point to the VO distance camera -> matched map point (docs/methods.md):

    s = |P_cam| / |T_cam_vo @ X_vo|

Its uncertainty combines, relatively: the range noise sigma_r / d, the VO depth sigma of the
point, and the offset between the matched pixel and the laser pixel, which on a surface
inclined to the ray changes the distance by about slope_factor * offset / f.

Depth-step check (ours, not in the thesis): the beam and the matched map point can sit on
either side of a depth step (a roof edge, a wall) a few pixels apart, and then the match is off
by the step's height (tens of percent over buildings). When the map points within
``edge_radius_px`` of the laser pixel span more depth than ``edge_depth_rel`` times their
median, the match is refused (``spans_depth_step``). Smooth terrain passes: a plane inclined
15 deg to the image plane spans ~4 % over a 72 px wide neighbourhood at f = 460 px (the SITL
slope flights: at most 5.6 %), 30 deg ~9 %; a 1.2 m step seen from 12 m spans 10 %.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.geometry import se3
from companion.geometry.camera import CameraModel
from companion.types import F64, VoFeatures


@dataclass(frozen=True, slots=True)
class MscMeasurement:
    """One scale measurement: scale [m per VO unit] and its sigma, with what produced it."""

    sensor_id: int
    scale: float
    sigma: float
    pixel_offset_px: float
    metric_distance_m: float
    vo_distance: float
    point_id: int


def laser_pixel(camera: CameraModel, laser_cam: F64) -> F64 | None:
    """Pixel (2,) of a laser point in the camera frame, or None if outside the image."""
    uv, ok = camera.project(laser_cam.reshape(1, 3))
    if not ok[0] or not camera.in_image(uv)[0]:
        return None
    out: F64 = uv[0]
    return out


def laser_pixels(camera: CameraModel, lasers_cam: F64) -> F64:
    """Pixels (K, 2) of K laser points (K, 3) in the camera frame, NaN rows for those behind
    the camera or outside the image: :func:`laser_pixel` of each, in one projection (the same
    arithmetic, row by row, so the same bits)."""
    uv, ok = camera.project(np.asarray(lasers_cam, dtype=np.float64).reshape(-1, 3))
    ok &= camera.in_image(uv)
    uv[~ok] = np.nan
    return uv


def spans_depth_step(
    features: VoFeatures, T_cam_vo: F64, uv: F64, radius_px: float, depth_rel: float
) -> bool:
    """Whether the map points within ``radius_px`` of pixel ``uv`` (2,) span a depth range
    (camera z, VO units) larger than ``depth_rel`` times their median; False with fewer than
    two points or when ``depth_rel`` is 0 (check off)."""
    if depth_rel <= 0:
        return False
    has = features.point_ids >= 0
    near = np.linalg.norm(features.pixels[has] - uv, axis=1) <= radius_px
    if int(near.sum()) < 2:
        return False
    z = se3.transform(T_cam_vo, features.points_vo[has][near])[:, 2]
    z_med = float(np.median(z))
    return bool(z_med <= 0 or float(np.max(z) - np.min(z)) > depth_rel * z_med)


def measure(
    sensor_id: int,
    features: VoFeatures,
    T_cam_vo: F64,
    camera: CameraModel,
    laser_cam: F64,
    range_sigma_m: float,
    patch_half_px: float,
    slope_factor: float,
    edge_radius_px: float = 0.0,
    edge_depth_rel: float = 0.0,
    laser_uv: F64 | None = None,
) -> MscMeasurement | None:
    """The MSC measurement of one sensor at one frame, or None when nothing matches (or the
    laser pixel's neighbourhood spans a depth step, see ``spans_depth_step``). ``laser_uv``
    (2,): the laser's pixel when the caller projected it (:func:`laser_pixels`; NaN: not in
    the image), else it is projected here."""
    uv = laser_pixel(camera, laser_cam) if laser_uv is None else laser_uv
    if uv is None or not np.isfinite(uv).all():
        return None
    has = features.point_ids >= 0
    if not has.any():
        return None
    d = features.pixels[has] - uv
    inside = np.max(np.abs(d), axis=1) <= patch_half_px
    if not inside.any():
        return None
    if spans_depth_step(features, T_cam_vo, uv, edge_radius_px, edge_depth_rel):
        return None
    cand = np.flatnonzero(has)[inside]
    dist_px = np.linalg.norm(d[inside], axis=1)
    k = int(np.argmin(dist_px))
    i = int(cand[k])
    X_cam = se3.transform(T_cam_vo, features.points_vo[i])
    vo_dist = float(np.linalg.norm(X_cam))
    metric = float(np.linalg.norm(laser_cam))
    if not np.isfinite(vo_dist) or vo_dist <= 0 or X_cam[2] <= 0:
        return None
    scale = metric / vo_dist
    f = 0.5 * (camera.fx + camera.fy)
    rel_depth = features.depth_sigma[i] / max(float(X_cam[2]), 1e-12)
    rel = np.sqrt(
        (range_sigma_m / metric) ** 2
        + (slope_factor * dist_px[k] / f) ** 2
        + (rel_depth if np.isfinite(rel_depth) else 0.1) ** 2
    )
    return MscMeasurement(
        sensor_id,
        scale,
        float(scale * rel),
        float(dist_px[k]),
        metric,
        vo_dist,
        int(features.point_ids[i]),
    )
