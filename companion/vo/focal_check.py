"""Is the camera's focal length the one its file says? Tracked pixels against the autopilot's
rotation, in flight (issue "Real sequences: ... the faults that real cameras bring").

The idea: a rotation of the camera by theta moves the image by f_true * theta pixels, so with a
wrong focal f_assumed the rotation seen in the image is (f_true / f_assumed) * theta, and the
autopilot's attitude says what theta was. Rotation, not translation, because it needs no
scale: the VO's translation is in arbitrary units, its rotation in radians.

What our measurements showed (2026-11-28, a 15 s figure8 over hills, the camera file's fx fy
10 % off): the VO's own rotation between keyframes does **not** carry the ratio. The VO fits
rotation, translation and the 3D map together; a wrong focal is a scene stretched across the
optical axis by f_true / f_assumed, and the rigid motion closest to the true one in that
stretched scene has nearly the true rotation (the VO's roll/pitch increments were 0.98 and
0.99 of the autopilot's for both +10 % and -10 %). A rotation about the optical axis (the
yaw of a downward camera) moves pixels around the principal point whatever the focal. And
the first-order image shift of a tilt is the same as that of a sideways translation, which a
VO free to choose both explains away.

What does work: the **epipolar constraint with the autopilot's rotation**. For two keyframes
of one map, the pixels of the points both track, (N, 2) each, are turned into rays with a
candidate focal f = q * f_assumed (the camera file's distortion and principal point, the
pipeline's own undistortion). With R_c2_c1 the autopilot's camera rotation between them,
every pair of rays x1, x2 (homogeneous, (3,)) must satisfy x2^T [t]x R_c2_c1 x1 = 0 for one
unknown translation direction t (Hartley & Zisserman, eq. 9.12). For each q, t is the
smallest eigenvector of the Sampson-weighted normal matrix of the rows (R x1) x x2 (three
reweightings), and the cost is the mean Sampson distance squared in pixels (f^2 times the
normalised one, so that it does not shrink with q). Only the right q leaves residuals that a
translation explains: the rotation's second-order image motion (theta (1 + y^2), theta x y)
scales with the focal, a translation's does not. The candidate focal divides the pixels
before the undistortion, as a camera with that focal and the file's distortion would: that
second-order signal is of the order of the distortion's, and scaling the file's undistorted
rays by 1/q instead found only a third of the error (0.990 and 1.036 for 0.909 and 1.111
on the figure8). The estimate of one pair is the q of least
cost (a log grid, refined by a parabola); the flight's is the median over pairs with enough
rotation across the optical axis (``min_tilt_deg``), with the spread 1.4826 * MAD.

q estimates f_true / f_assumed: the factor to multiply [camera] fx fy by. Measured
2026-11-28 through the whole pipeline (``Pipeline.status().lens_focal_ratio``, the camera
file's fx fy = 1.1, 0.9 and 1.0 x the renderer's): a 15 s figure8 over hills 0.920, 1.118,
1.008 (true 0.909, 1.111, 1.000; 130-161 pairs, spread 0.06-0.075); a 30 s lawnmower over
the urban terrain 0.919, 1.109, 1.005 (103-121 pairs). A rotation about the optical axis
carries nothing, so the check needs roll and pitch (a multirotor's accelerations); a hover
gives few pairs and no verdict.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.errors import GeometryError
from companion.geometry.camera import CameraModel
from companion.types import F64

I64 = NDArray[np.int64]

Q_MIN, Q_MAX = 0.7, 1.4  # the focal ratios searched
Q_STEPS = 29  # log grid, 2.5 % apart, then a parabola through the least cost and neighbours
MAX_POINTS = 120  # points of a pair used (the cost is a mean: more only costs time)


@dataclass(frozen=True, slots=True)
class FocalRatio:
    """The flight's estimate of f_true / f_assumed: the median ``ratio`` over ``samples``
    keyframe pairs, ``spread`` = 1.4826 * their median absolute deviation, ``sigma`` the
    median's standard error (1.2533 * spread / sqrt(samples)); ``at_edge``: the pairs whose
    best focal lay at an end of the search (Q_MIN or Q_MAX): no focal in the range fits them,
    so the lens model or the mount is wrong rather than the focal length alone."""

    ratio: float
    spread: float
    sigma: float
    samples: int
    at_edge: int = 0


@dataclass(frozen=True, slots=True)
class KeyframeView:
    """What one keyframe leaves for the check: its time [us], VO map (reset count), the
    autopilot's R_world_cam (3, 3) at its time, and its tracked map points' ids (N,) and
    pixels (N, 2) [px]."""

    time_us: int
    segment: int
    R_world_cam: F64
    point_ids: I64
    pixels: F64


def epipolar_costs(x1: F64, x2: F64, R_c2_c1: F64) -> F64:
    """Mean squared Sampson distances (Q,) [normalised units^2] of Q candidate sets of rays
    x1, x2 (Q, M, 3) under the rotation R_c2_c1 (3, 3), each with its best translation
    direction (module docstring; three reweightings)."""
    rows = np.cross(x1 @ R_c2_c1.T, x2)  # (Q, M, 3): rows . t = x2^T [t]x R x1
    w = np.ones(rows.shape[:2])
    t = np.zeros((rows.shape[0], 3))
    for _ in range(3):
        normal = np.einsum("qm,qmi,qmj->qij", w, rows, rows)
        _, vectors = np.linalg.eigh(normal)
        t = vectors[:, :, 0]  # (Q, 3), the least eigenvalue's
        Rx1 = x1 @ R_c2_c1.T
        line2 = np.cross(t[:, None, :], Rx1)  # E x1 = t x (R x1)
        line1 = np.cross(x2, t[:, None, :]) @ R_c2_c1  # E^T x2 = R^T (x2 x t)
        den = line2[..., 0] ** 2 + line2[..., 1] ** 2 + line1[..., 0] ** 2 + line1[..., 1] ** 2
        w = 1.0 / np.maximum(den, 1e-18)
    residual = np.einsum("qmi,qi->qm", rows, t)
    costs: F64 = np.mean(residual**2 * w, axis=1)
    return costs


def pair_ratio(camera: CameraModel, px1: F64, px2: F64, R_c2_c1: F64) -> float | None:
    """f_true / f_assumed from the pixels (N, 2) of N points in two views and the rotation
    R_c2_c1 (3, 3) between them; None when a candidate's rays cannot be computed. At most
    MAX_POINTS points (evenly spaced in the list) are used; every candidate's rays come from
    one undistortion call."""
    take = np.unique(np.linspace(0, len(px1) - 1, min(len(px1), MAX_POINTS)).astype(np.int64))
    px = np.concatenate([px1[take], px2[take]])  # (2 M, 2)
    qs = np.exp(np.linspace(np.log(Q_MIN), np.log(Q_MAX), Q_STEPS))
    centred = (px - np.array([camera.cx, camera.cy])) / np.array([camera.fx, camera.fy])
    distorted = (centred[None, :, :] / qs[:, None, None]).reshape(-1, 2)  # (Q 2 M, 2)
    try:
        rays = camera.undistort_normalized(distorted).reshape(Q_STEPS, 2, len(take), 2)
    except GeometryError:
        return None
    homogeneous = np.concatenate([rays, np.ones((Q_STEPS, 2, len(take), 1))], axis=3)
    pixel_area = camera.fx * camera.fy * qs * qs  # normalised units^2 -> px^2 per candidate
    costs = epipolar_costs(homogeneous[:, 0], homogeneous[:, 1], R_c2_c1) * pixel_area
    i = int(np.argmin(costs))
    if i == 0 or i == Q_STEPS - 1:
        return float(qs[i])
    c0, c1, c2 = costs[i - 1], costs[i], costs[i + 1]
    curvature = c0 - 2.0 * c1 + c2
    step = 0.5 * (c0 - c2) / curvature if curvature > 0 else 0.0
    log_step = np.log(qs[1] / qs[0])
    return float(np.exp(np.log(qs[i]) + float(np.clip(step, -0.5, 0.5)) * log_step))


def tilt_angle_rad(R_c2_c1: F64) -> float:
    """The rotation's angle across the optical axis [rad]: the norm of the x, y components
    of its rotation vector (a rotation about the optical axis says nothing of the focal)."""
    cos = np.clip((np.trace(R_c2_c1) - 1.0) / 2.0, -1.0, 1.0)
    angle = float(np.arccos(cos))
    if angle < 1e-12:
        return 0.0
    axis = np.array(
        [
            R_c2_c1[2, 1] - R_c2_c1[1, 2],
            R_c2_c1[0, 2] - R_c2_c1[2, 0],
            R_c2_c1[1, 0] - R_c2_c1[0, 1],
        ]
    )
    norm = float(np.linalg.norm(axis))
    if norm < 1e-12:
        return angle
    return angle * float(np.hypot(axis[0], axis[1])) / norm


class FocalCheck:
    """The focal ratio over a window of keyframe pairs. Feed keyframes with :meth:`add`; each
    is paired with up to ``pairs_per_keyframe`` earlier keyframes of its map between
    ``min_age_s`` and ``max_age_s`` older that share at least ``min_points`` points and are
    turned at least ``min_tilt_deg`` across the optical axis from it (by the autopilot)."""

    def __init__(
        self,
        camera: CameraModel,
        window: int = 200,
        min_tilt_deg: float = 1.0,
        min_points: int = 30,
        min_age_s: float = 0.4,
        max_age_s: float = 2.0,
        pairs_per_keyframe: int = 3,
    ) -> None:
        self.camera = camera
        self.ratios: deque[float] = deque(maxlen=window)
        self.min_tilt_rad = float(np.radians(min_tilt_deg))
        self.min_points = min_points
        self.min_age_us = int(min_age_s * 1e6)
        self.max_age_us = int(max_age_s * 1e6)
        self.pairs_per_keyframe = pairs_per_keyframe
        self._kept: deque[KeyframeView] = deque(maxlen=64)

    def add(self, view: KeyframeView) -> int:
        """Pair a new keyframe with earlier ones; returns the pairs it gave."""
        given = 0
        for old in reversed(self._kept):
            if given >= self.pairs_per_keyframe:
                break
            age_us = view.time_us - old.time_us
            if old.segment != view.segment or age_us > self.max_age_us:
                continue
            if age_us < self.min_age_us:
                continue
            R_c2_c1 = view.R_world_cam.T @ old.R_world_cam
            if tilt_angle_rad(R_c2_c1) < self.min_tilt_rad:
                continue
            common, i1, i2 = np.intersect1d(old.point_ids, view.point_ids, return_indices=True)
            if len(common) < self.min_points:
                continue
            q = pair_ratio(self.camera, old.pixels[i1], view.pixels[i2], R_c2_c1)
            if q is not None:
                self.ratios.append(q)
                given += 1
        self._kept.append(view)
        return given

    def estimate(self) -> FocalRatio | None:
        """The median ratio, its spread and standard error over the window; None before any."""
        if not self.ratios:
            return None
        q = np.asarray(self.ratios, dtype=np.float64)
        median = float(np.median(q))
        spread = 1.4826 * float(np.median(np.abs(q - median)))
        sigma = 1.2533 * spread / float(np.sqrt(len(q)))
        edge = int(np.sum((q <= Q_MIN * (1 + 1e-9)) | (q >= Q_MAX * (1 - 1e-9))))
        return FocalRatio(median, spread, sigma, len(q), edge)


def focal_warning(est: FocalRatio, threshold: float = 0.05, min_samples: int = 20) -> str | None:
    """The operator's warning once the ratio is confidently off by more than ``threshold``
    (|ratio - 1| - 2 sigma > threshold over at least ``min_samples`` pairs), else None."""
    if est.samples < min_samples:
        return None
    if 2 * est.at_edge > est.samples:
        return (
            f"the autopilot's rotation fits the tracked pixels at no focal length within "
            f"x{Q_MIN:.2f}..x{Q_MAX:.2f} of the file's in {est.at_edge} of {est.samples} keyframe "
            f"pairs: check [camera] fx fy and dist (a lens model that is wrong) and the camera "
            f"mount"
        )
    if abs(est.ratio - 1.0) - 2.0 * est.sigma <= threshold:
        return None
    way = "too small" if est.ratio > 1.0 else "too large"
    pct = abs(est.ratio - 1.0) * 100.0
    return (
        f"camera focal length looks {pct:.1f} % {way} (autopilot rotation against the tracked "
        f"pixels: f_true / f_file = {est.ratio:.3f} +- {est.spread:.3f} over {est.samples} "
        f"keyframe pairs); check [camera] fx fy"
    )


def focal_summary(est: FocalRatio | None, warning: str | None = None) -> str:
    """What ``companion eval`` prints: the ratio, its spread and the pairs (or why none), and
    the warning on a line of its own when there is one."""
    line = "lens focal ratio (f_true / f_file): no keyframe pairs with enough rotation"
    if est is not None:
        line = (
            f"lens focal ratio (f_true / f_file): {est.ratio:.3f} (spread {est.spread:.3f}, "
            f"+- {est.sigma:.3f}) over {est.samples} keyframe pairs"
            + (f", {est.at_edge} at an end of the search" if est.at_edge else "")
        )
    return line if warning is None else f"{line}\nwarning: {warning}"
