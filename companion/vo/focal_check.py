"""Are the camera's focal length and k1 the ones its file says? Tracked pixels against the
autopilot's rotation, in flight (issue "Real sequences: ... the faults that real cameras bring").

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
on the figure8).

Because the signal is of the order of the distortion's, an error in k1 reads as one in the
focal when the focal is searched alone: a lens rendered with k1 0.02 above the file's read
f_true / f_file = 1.137 over a 40 s lawnmower over hills (2026-11-29), and warned "39 % too
small" after 28 pairs. So each candidate is a lens (q, k1_delta): the focal ratio and the
error of k1 (k1_true - k1_file; the file's k2, k3, p1, p2 kept), searched together. A
coarse grid (15 log-spaced ratios in 0.7..1.4 by 9 k1 errors in -0.1..0.1), a parabola
along each axis through its least, a 3 x 3 grid at a third of its steps around that, and a
parabola again. The estimate of one pair is that lens; the flight's is the medians over
pairs with enough rotation across the optical axis (``min_tilt_deg``; per keyframe the two
most turned earlier ones, one once 50 pairs are in), with the spreads 1.4826 * MAD.

q estimates f_true / f_assumed: the factor to multiply [camera] fx fy by; k1_delta what to
add to the file's k1. Measured 2026-11-29 on the keyframes of 40 s hills lawnmower flights
(seed 1, the renderer's lens off the file's): k1 +0.02 -> 1.009 and +0.0207 (109 pairs; the
focal alone read 1.137); focal +10 % -> 1.111 and -0.0002 (121); the file's own lens -> 0.995
and -0.0006 (113); 6.9 ms a keyframe against the focal alone's 4.8 ms, on the same keyframes
in the same run (an AMD EPYC core). Before the joint search (the focal alone, 2026-11-28,
``Pipeline.status().lens_focal_ratio``, the camera file's fx fy = 1.1, 0.9 and 1.0 x the
renderer's): a 15 s figure8 over hills 0.920, 1.118, 1.008 (true 0.909, 1.111, 1.000); a
30 s lawnmower over the urban terrain 0.919, 1.109, 1.005. A rotation about the optical
axis carries nothing, so the check needs roll and pitch (a multirotor's accelerations); a
hover gives few pairs and no verdict.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.geometry.camera import CameraModel
from companion.types import F64

I64 = NDArray[np.int64]

Q_MIN, Q_MAX = 0.7, 1.4  # the focal ratios searched
Q_STEPS = 15  # the coarse log grid over them, 5 % apart
K1_MAX = 0.1  # the k1 errors searched: -K1_MAX..K1_MAX
K1_STEPS = 9  # the coarse grid over them, 0.025 apart (0.05 apart missed the valley that
# f and k1 trade along: a k1 +0.02 lens read 1.161 and +0.018)
FINE_STEPS = 3  # the fine grid: 3 x 3 at 1 / FINE_STEPS of the coarse steps, then a parabola
MAX_POINTS = 60  # points of a pair used (the cost is a mean: more only costs time)
# a pair rejects the file's lens when its best lens leaves at most this share of the file
# lens' cost; findings need most pairs to reject it (a flat floor seen with small tilts fits
# the file's lens nearly as well as any: its pairs' best lenses are weak and biased)
FILE_REJECT_RATIO = 0.9


@dataclass(frozen=True, slots=True)
class FocalRatio:
    """The flight's estimate of the lens: the median focal ``ratio`` f_true / f_assumed and
    the median ``k1_delta`` = k1_true - k1_assumed over ``samples`` keyframe pairs;
    ``spread``, ``k1_spread`` = 1.4826 * their median absolute deviations, ``sigma``,
    ``k1_sigma`` the medians' standard errors (1.2533 * spread / sqrt(samples));
    ``at_edge``: the pairs whose best lens lay at an end of the search (Q_MIN, Q_MAX or
    +-K1_MAX): no lens in the range fits them, so the lens model or the mount is wrong;
    ``rejecting``: the pairs whose best lens costs less than FILE_REJECT_RATIO of the file's
    lens (None: not counted)."""

    ratio: float
    spread: float
    sigma: float
    samples: int
    at_edge: int = 0
    k1_delta: float = 0.0
    k1_spread: float = 0.0
    k1_sigma: float = 0.0
    rejecting: int | None = None


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


@dataclass(frozen=True, slots=True)
class PairLens:
    """One keyframe pair's best lens: focal ratio ``q`` = f_true / f_assumed, ``k1_delta`` =
    k1_true - k1_assumed, ``at_edge`` when either lies at an end of its search;
    ``file_cost_ratio``: its cost over the file's lens' (q = 1, k1_delta = 0), 0 when the
    file's lens cannot be undone at the pair's pixels."""

    q: float
    k1_delta: float
    at_edge: bool
    file_cost_ratio: float = 1.0


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


def lens_costs(camera: CameraModel, centred: F64, R_c2_c1: F64, qs: F64, k1_deltas: F64) -> F64:
    """The pixel cost (C,) [px^2] of C candidate lenses, focal ratio ``qs`` (C,) and k1 error
    ``k1_deltas`` (C,), for the centred normalised pixels (2 M, 2) of M points in two views
    (the first M, then the second M). Every candidate's rays come from one undistortion call:
    the candidate divides the pixels before its distortion is undone, as a camera with that
    focal and that k1 would. A candidate whose lens cannot be undone at one of the pixels (it
    folds there) costs +inf."""
    n, m = len(qs), len(centred) // 2
    distorted = (centred[None, :, :] / qs[:, None, None]).reshape(-1, 2)  # (C 2 M, 2)
    k1 = np.repeat(camera.k1 + k1_deltas, 2 * m)
    rays = camera.undistort_normalized(distorted, k1=k1, nan_where_unconverged=True)
    rays = rays.reshape(n, 2, m, 2)
    folds = np.isnan(rays).any(axis=(1, 2, 3))
    rays[folds] = 0.0  # rays through the principal point: any finite value, costed +inf below
    homogeneous = np.concatenate([rays, np.ones((n, 2, m, 1))], axis=3)
    pixel_area = camera.fx * camera.fy * qs * qs  # normalised units^2 -> px^2 per candidate
    costs: F64 = epipolar_costs(homogeneous[:, 0], homogeneous[:, 1], R_c2_c1) * pixel_area
    costs[folds] = np.inf
    return costs


def _interior_step(costs: F64, k: int) -> float:
    """Where a parabola through ``costs[k - 1 : k + 2]`` (equally spaced) has its least, in
    steps from ``k`` (within +-0.5; 0 at an end of ``costs`` or when it is not convex)."""
    if not 0 < k < len(costs) - 1 or not np.all(np.isfinite(costs[k - 1 : k + 2])):
        return 0.0
    c0, c1, c2 = float(costs[k - 1]), float(costs[k]), float(costs[k + 1])
    curvature = c0 - 2.0 * c1 + c2
    return float(np.clip(0.5 * (c0 - c2) / curvature, -0.5, 0.5)) if curvature > 0 else 0.0


def pair_lens(camera: CameraModel, px1: F64, px2: F64, R_c2_c1: F64) -> PairLens | None:
    """The focal ratio and k1 error that best explain the pixels (N, 2) of N points in two
    views with the rotation R_c2_c1 (3, 3) between them; None when no candidate lens can be
    undone at every pixel (lens_costs). A coarse grid (Q_STEPS log-spaced ratios by
    K1_STEPS k1 errors), a parabola along each axis through its least, a 3 x 3 grid at
    1 / FINE_STEPS of its steps around that, and a parabola again. At most MAX_POINTS points
    (evenly spaced in the list) are used."""
    take = np.unique(np.linspace(0, len(px1) - 1, min(len(px1), MAX_POINTS)).astype(np.int64))
    px = np.concatenate([px1[take], px2[take]])  # (2 M, 2)
    centred = (px - np.array([camera.cx, camera.cy])) / np.array([camera.fx, camera.fy])
    log_q = np.linspace(np.log(Q_MIN), np.log(Q_MAX), Q_STEPS)
    k1s = np.linspace(-K1_MAX, K1_MAX, K1_STEPS)
    grid_q, grid_k = np.meshgrid(log_q, k1s, indexing="ij")
    costs = lens_costs(camera, centred, R_c2_c1, np.exp(grid_q.ravel()), grid_k.ravel())
    coarse = costs.reshape(grid_q.shape)
    i, j = np.unravel_index(int(np.argmin(coarse)), coarse.shape)
    if not np.isfinite(coarse[i, j]):
        return None
    at_edge = i in (0, Q_STEPS - 1) or j in (0, K1_STEPS - 1)
    step_q, step_k = log_q[1] - log_q[0], k1s[1] - k1s[0]
    centre_q = log_q[i] + _interior_step(coarse[:, j], int(i)) * step_q
    centre_k = k1s[j] + _interior_step(coarse[i, :], int(j)) * step_k
    step_q, step_k = step_q / FINE_STEPS, step_k / FINE_STEPS
    offsets = np.arange(-1.0, 2.0)
    fine_q, fine_k = np.meshgrid(
        centre_q + offsets * step_q, centre_k + offsets * step_k, indexing="ij"
    )
    fine = lens_costs(camera, centred, R_c2_c1, np.exp(fine_q.ravel()), fine_k.ravel())
    fine = fine.reshape(fine_q.shape)
    a, b = np.unravel_index(int(np.argmin(fine)), fine.shape)
    if not np.isfinite(fine[a, b]):
        return None
    log_best = fine_q[a, b] + _interior_step(fine[:, b], int(a)) * step_q
    q = float(np.exp(np.clip(log_best, np.log(Q_MIN), np.log(Q_MAX))))
    k1_delta = float(
        np.clip(fine_k[a, b] + _interior_step(fine[a, :], int(b)) * step_k, -K1_MAX, K1_MAX)
    )
    best, file = lens_costs(camera, centred, R_c2_c1, np.array([q, 1.0]), np.array([k1_delta, 0.0]))
    best = min(float(best), float(fine[a, b]))  # the parabola's step may not lower the cost
    ratio = best / float(file) if np.isfinite(file) and file > 0 else 0.0
    return PairLens(q, k1_delta, bool(at_edge), ratio)


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
    """The lens over a window of keyframe pairs. Feed keyframes with :meth:`add`; each is
    paired with up to ``pairs_per_keyframe`` earlier keyframes of its map between
    ``min_age_s`` and ``max_age_s`` older that share at least ``min_points`` points and are
    turned at least ``min_tilt_deg`` across the optical axis from it (by the autopilot), the
    most turned first (the rotation is the signal); one pair per keyframe once the window
    holds ``settled_after`` pairs (the lens does not change: the cost of a long flight is
    that of one pair a keyframe)."""

    def __init__(
        self,
        camera: CameraModel,
        window: int = 200,
        min_tilt_deg: float = 1.0,
        min_points: int = 30,
        min_age_s: float = 0.4,
        max_age_s: float = 2.0,
        pairs_per_keyframe: int = 2,
        settled_after: int = 50,
    ) -> None:
        self.camera = camera
        self.pairs: deque[PairLens] = deque(maxlen=window)
        self.min_tilt_rad = float(np.radians(min_tilt_deg))
        self.min_points = min_points
        self.min_age_us = int(min_age_s * 1e6)
        self.max_age_us = int(max_age_s * 1e6)
        self.pairs_per_keyframe = pairs_per_keyframe
        self.settled_after = settled_after  # pairs in the window, then one per keyframe
        self._kept: deque[KeyframeView] = deque(maxlen=64)

    def add(self, view: KeyframeView) -> int:
        """Pair a new keyframe with earlier ones; returns the pairs it gave."""
        candidates: list[tuple[float, KeyframeView, F64]] = []
        for old in self._kept:
            age_us = view.time_us - old.time_us
            if old.segment != view.segment or not self.min_age_us <= age_us <= self.max_age_us:
                continue
            R_c2_c1 = view.R_world_cam.T @ old.R_world_cam
            tilt_rad = tilt_angle_rad(R_c2_c1)
            if tilt_rad >= self.min_tilt_rad:
                candidates.append((tilt_rad, old, R_c2_c1))
        candidates.sort(key=lambda c: -c[0])
        given = 0
        wanted = self.pairs_per_keyframe if len(self.pairs) < self.settled_after else 1
        for _, old, R_c2_c1 in candidates:
            if given >= wanted:
                break
            common, i1, i2 = np.intersect1d(old.point_ids, view.point_ids, return_indices=True)
            if len(common) < self.min_points:
                continue
            pair = pair_lens(self.camera, old.pixels[i1], view.pixels[i2], R_c2_c1)
            if pair is not None:
                self.pairs.append(pair)
                given += 1
        self._kept.append(view)
        return given

    def estimate(self) -> FocalRatio | None:
        """The median ratio and k1 error, their spreads and standard errors over the window;
        None before any pair."""
        if not self.pairs:
            return None
        q = np.array([p.q for p in self.pairs])
        k1 = np.array([p.k1_delta for p in self.pairs])
        edge = sum(p.at_edge for p in self.pairs)
        rejecting = sum(p.file_cost_ratio < FILE_REJECT_RATIO for p in self.pairs)
        (ratio, spread, sigma), (k1_delta, k1_spread, k1_sigma) = (
            _median_stats(q),
            _median_stats(k1),
        )
        return FocalRatio(
            ratio, spread, sigma, len(q), edge, k1_delta, k1_spread, k1_sigma, rejecting
        )


def _median_stats(values: F64) -> tuple[float, float, float]:
    """The median of ``values`` (N,), 1.4826 * their median absolute deviation, and the
    median's standard error 1.2533 * that / sqrt(N)."""
    median = float(np.median(values))
    spread = 1.4826 * float(np.median(np.abs(values - median)))
    return median, spread, 1.2533 * spread / float(np.sqrt(len(values)))


K1_THRESHOLD = 0.01  # a k1 error warned of (about 3 px at the corner of a 640 x 480 image)


def lens_findings(
    est: FocalRatio,
    threshold: float = 0.05,
    min_samples: int = 20,
    k1_threshold: float = K1_THRESHOLD,
    camera: CameraModel | None = None,
) -> list[tuple[str, str]]:
    """What is confidently wrong with the lens, as (brief, text) pairs: the focal ratio off by
    more than ``threshold`` (|ratio - 1| - 2 sigma > threshold), k1 by more than
    ``k1_threshold`` (|k1_delta| - 2 k1_sigma > k1_threshold), or no lens in the search that
    fits most pairs; nothing before ``min_samples`` pairs, nor while most pairs fit the
    file's lens nearly as well as their best (``est.rejecting``, FILE_REJECT_RATIO). The brief
    ("k1 +0.021") is for the ground station's STATUSTEXT; the text for the log and the
    status, with the values that fit the flight when the file's ``camera`` is given."""
    if est.samples < min_samples:
        return []
    if est.rejecting is not None and 2 * est.rejecting <= est.samples:
        return []
    if 2 * est.at_edge > est.samples:
        text = (
            f"the autopilot's rotation fits the tracked pixels with no lens within "
            f"x{Q_MIN:.2f}..x{Q_MAX:.2f} of the file's focal length and +-{K1_MAX:.2f} of its "
            f"k1 in {est.at_edge} of {est.samples} keyframe pairs: check [camera] fx fy and "
            f"dist (a lens model that is wrong) and the camera mount"
        )
        return [("fits no lens model", text)]
    found = []
    if abs(est.ratio - 1.0) - 2.0 * est.sigma > threshold:
        way = "too small" if est.ratio > 1.0 else "too large"
        fits = (
            None
            if camera is None
            else f"fx {camera.fx * est.ratio:.1f}, fy {camera.fy * est.ratio:.1f}"
        )
        text = _finding_text(
            f"focal length looks {abs(est.ratio - 1.0) * 100.0:.1f} % {way}",
            f"f_true / f_file = {est.ratio:.3f}",
            est.spread,
            est.samples,
            "fx fy",
            fits,
        )
        found.append((f"focal x{est.ratio:.3f}", text))
    if abs(est.k1_delta) - 2.0 * est.k1_sigma > k1_threshold:
        way = "too small" if est.k1_delta > 0.0 else "too large"
        fits = None if camera is None else f"k1 {camera.k1 + est.k1_delta:.3f}"
        text = _finding_text(
            f"distortion k1 looks {abs(est.k1_delta):.3f} {way}",
            f"k1_true - k1_file = {est.k1_delta:+.3f}",
            est.k1_spread,
            est.samples,
            "dist",
            fits,
        )
        found.append((f"k1 {est.k1_delta:+.3f}", text))
    return found


def _finding_text(
    looks: str, measured: str, spread: float, samples: int, keys: str, fits: str | None
) -> str:
    """One finding's warning: what looks wrong, the measurement and its spread over the
    pairs, the [camera] keys to check, and the values that fit the flight (if known)."""
    text = (
        f"camera {looks} (autopilot rotation against the tracked pixels: {measured} +- "
        f"{spread:.3f} over {samples} keyframe pairs); check [camera] {keys}"
    )
    return text if fits is None else f"{text} (the flight fits {fits})"


def focal_warning(
    est: FocalRatio,
    threshold: float = 0.05,
    min_samples: int = 20,
    k1_threshold: float = K1_THRESHOLD,
    camera: CameraModel | None = None,
) -> str | None:
    """The operator's warning (:func:`lens_findings`' texts), or None when nothing is found."""
    found = lens_findings(est, threshold, min_samples, k1_threshold, camera)
    return "; ".join(text for _, text in found) if found else None


def focal_summary(est: FocalRatio | None, warning: str | None = None) -> str:
    """What ``companion eval`` prints: the ratio, its spread and the pairs (or why none), and
    the warning on a line of its own when there is one."""
    line = "lens focal ratio (f_true / f_file): no keyframe pairs with enough rotation"
    if est is not None:
        line = (
            f"lens focal ratio (f_true / f_file): {est.ratio:.3f} (spread {est.spread:.3f}, "
            f"+- {est.sigma:.3f}), k1 error (k1_true - k1_file): {est.k1_delta:+.4f} (spread "
            f"{est.k1_spread:.4f}, +- {est.k1_sigma:.4f}) over {est.samples} keyframe pairs"
            + (f", {est.at_edge} at an end of the search" if est.at_edge else "")
            + (
                ""
                if est.rejecting is None
                else f"; {est.rejecting} fit another lens better than the file's by "
                f"{(1.0 - FILE_REJECT_RATIO) * 100:.0f} % or more"
            )
        )
    return line if warning is None else f"{line}\nwarning: {warning}"
