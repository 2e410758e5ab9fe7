"""Distance sensors synthesised from a real depth image (``companion dataset import``).

A sensor's beam starts at ``origin_cam`` (3,) [m] and runs along the unit ``dir_cam`` (3,), both
in the camera frame (OpenCV: x right, y down, z along the optical axis). The depth image
(H, W) [m] is registered to the colour camera (TUM RGB-D), so pixel (u, v) holds the z of the
surface point seen through it (0 = no depth). The true distance r solves

    f(r) = D(pi(o + r d)) - (o + r d).z = 0,

pi the camera's projection (its distortion included), D the depth looked up at that pixel: the
first r where the ray passes behind the surface. We march along the ray in steps of
``step_m`` (the first sample behind the surface, the one before it in front with depth; the
samples near the lens that project outside the image are passed over), then bisect the
bracket with the depth interpolated bilinearly (nearest at an edge or beside a missing pixel).
A reading is **dropped** (``BeamMiss``, with its reason) when the beam never meets the surface
inside the image, crosses it beside a pixel without depth, or when |f| at the solution is
above ``tolerance_m`` (the ray passed behind a depth edge: no surface there). The noise model
and the limits then follow docs/dataset.md (``RangefinderConfig``: sigma = a + b r, seeded;
outside [min_m, max_m] the nearest limit with signal_quality 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.config import RangefinderConfig
from companion.geometry.camera import CameraModel
from companion.types import F64

STEP_M = 0.005  # march step along the beam [m]
MAX_RANGE_M = 12.0  # march no farther [m]
TOLERANCE_M = 0.02  # |f| at the solution above this: the ray is behind a depth edge [m]
EDGE_RATIO = 0.05  # 4 neighbours further apart than 5 % of their depth: an edge (nearest)


@dataclass(frozen=True, slots=True)
class BeamMiss:
    """Why a beam gives no reading: ``no_surface`` (it never passes behind the depth surface
    inside the image), ``missing_depth`` (it crosses the surface beside a pixel without depth)
    or ``depth_edge`` (it passes behind a depth edge: no surface of the image there)."""

    reason: str


@dataclass(frozen=True, slots=True)
class BeamHit:
    """A beam's true distance ``range_m`` [m] to the depth surface and the pixel ``uv_px`` (2,)
    where it lands."""

    range_m: float
    uv_px: F64


def depth_at(depth_m: F64, uv_px: F64) -> F64:
    """Depth [m] at pixels (N, 2): bilinear between the four neighbours when all have depth
    and agree within :data:`EDGE_RATIO`, else the nearest pixel's; 0 outside the image or
    where the chosen pixel has none."""
    h, w = depth_m.shape
    uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
    out = np.zeros(len(uv))
    ok = np.all(np.isfinite(uv), axis=1)
    ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    if not ok.any():
        return out
    u, v = uv[ok, 0], uv[ok, 1]
    u0 = np.minimum(np.floor(u).astype(int), w - 2)
    v0 = np.minimum(np.floor(v).astype(int), h - 2)
    a, b = u - u0, v - v0
    q = np.stack(
        [depth_m[v0, u0], depth_m[v0, u0 + 1], depth_m[v0 + 1, u0], depth_m[v0 + 1, u0 + 1]]
    )
    bilinear = q[0] * (1 - a) * (1 - b) + q[1] * a * (1 - b) + q[2] * (1 - a) * b + q[3] * a * b
    smooth = np.all(q > 0, axis=0) & (np.ptp(q, axis=0) <= EDGE_RATIO * q.mean(axis=0))
    nearest = depth_m[np.rint(v).astype(int), np.rint(u).astype(int)]
    out[ok] = np.where(smooth, bilinear, nearest)
    return out


def march_beam(
    depth_m: F64,
    camera: CameraModel,
    origin_cam: F64,
    dir_cam: F64,
    *,
    step_m: float = STEP_M,
    max_range_m: float = MAX_RANGE_M,
    tolerance_m: float = TOLERANCE_M,
) -> BeamHit | BeamMiss:
    """The beam's distance to the depth surface (the module's equation), or why there is none
    (a dropped reading)."""
    o = np.asarray(origin_cam, dtype=np.float64)
    d = np.asarray(dir_cam, dtype=np.float64)
    d = d / np.linalg.norm(d)
    r = np.arange(step_m, max_range_m + step_m, step_m)
    pts = o[None, :] + r[:, None] * d[None, :]
    uv, front = camera.project(pts, min_z=1e-3)
    inside = front & camera.in_image(uv)
    z_surface = depth_at(depth_m, uv)
    f = z_surface - pts[:, 2]
    behind = inside & (z_surface > 0) & (f <= 0)
    if not behind.any():
        return BeamMiss("no_surface")
    k = int(np.argmax(behind))
    if k == 0:
        return BeamMiss("no_surface")  # starts behind the surface
    if not (inside[k - 1] and z_surface[k - 1] > 0):
        return BeamMiss("missing_depth")  # crosses the surface at a hole in the depth
    lo, hi = float(r[k - 1]), float(r[k])
    for _ in range(30):  # bisection: f(lo) > 0 >= f(hi)
        mid = 0.5 * (lo + hi)
        p = o + mid * d
        uv_mid, _ = camera.project(p[None, :], min_z=1e-3)
        z = float(depth_at(depth_m, uv_mid)[0])
        if z <= 0:
            return BeamMiss("missing_depth")
        if z - p[2] > 0:
            lo = mid
        else:
            hi = mid
    r_hit = 0.5 * (lo + hi)
    p = o + r_hit * d
    uv_hit, _ = camera.project(p[None, :], min_z=1e-3)
    if abs(float(depth_at(depth_m, uv_hit)[0]) - p[2]) > tolerance_m:
        return BeamMiss("depth_edge")
    return BeamHit(r_hit, uv_hit[0])


@dataclass(frozen=True, slots=True)
class SynthReading:
    """A synthesised reading: what the sensor reports (``distance_m``, ``signal_quality`` as
    docs/dataset.md says) and the noise-free ``true_distance_m`` [m]."""

    distance_m: float
    signal_quality: int
    true_distance_m: float


def noisy_reading(rf: RangefinderConfig, true_m: float, rng: np.random.Generator) -> SynthReading:
    """The sensor's noise model on a true distance [m]: sigma = sigma_a_m + sigma_b * r
    (Gaussian), clipped to [min_m, max_m]; a true distance outside the limits reads the nearest
    limit with signal_quality 1 (invalid), as the simulator's sensors do."""
    noise = float(rng.normal())
    if true_m > rf.max_m:
        return SynthReading(rf.max_m, 1, true_m)
    if true_m < rf.min_m:
        return SynthReading(rf.min_m, 1, true_m)
    sigma = rf.sigma_a_m + rf.sigma_b * true_m
    d = min(max(true_m + sigma * noise, rf.min_m), rf.max_m)
    return SynthReading(d, max(2, int(round(100 - 50 * true_m / rf.max_m))), true_m)


def beam_in_camera(rf: RangefinderConfig) -> tuple[F64, F64]:
    """Origin (3,) [m] and unit direction (3,) of a sensor's beam (+z of its frame) in the
    camera frame, the body being the camera (T_body_cam = identity)."""
    T = rf.mount.T_body_sensor()
    return np.array(T[:3, 3]), np.array(T[:3, 2])
