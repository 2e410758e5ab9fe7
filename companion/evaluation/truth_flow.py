"""Does a dataset's ground truth move like its images? The floor's flow against the truth's.

For a camera over a flat floor (the plane z = ``floor_z_m`` of the world, NED), a pixel u_a
of frame a sees the floor point P = C_a + s r_a (r_a its ray in the world from the camera's
pose T_world_cam_a, s such that P_z = floor_z_m); the truth then says where frame b sees it,
u_b = project(T_cam_world_b P) (Hartley & Zisserman, the plane-induced homography of ch.
13, written point by point so that the lens can bend it). KLT tracks of the floor from a to
b (forward-backward checked) measure where it is. The error |u_b(truth) - u_b(KLT)| is
small only when the truth's poses, the camera's mount, the time of each frame and the lens
are all right; set against the error of predicting no motion (|u_b(KLT) - u_a|), it says how
much of the image's motion the truth explains, with no VO in between.

Used on rislab_downward (docs/decisions.md, "rislab's truth, reconciled with its images"):
with the attitudes in the positions' world the truth explained 8.3 px of an 11.0 px flow at
best; with them turned 90 deg about z, 1.3 px.

Units: pixels, metres; poses T_world_cam (4, 4), world NED (z down: the floor below the
camera has the larger z).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize

from companion.errors import GeometryError
from companion.geometry.camera import CameraModel
from companion.types import F64

KLT_WINDOW_PX = 21
KLT_LEVELS = 3
FB_MAX_PX = 0.5  # a track that KLT back into frame a misses its start by more is dropped
MIN_TRACKS = 10


@dataclass(frozen=True, slots=True)
class FloorPair:
    """Floor tracks between two frames: pixels (N, 2) in a and (N, 2) in b, and the camera
    poses the truth gives the two frames, T_world_cam (4, 4) each."""

    px_a: F64
    px_b: F64
    T_world_cam_a: F64
    T_world_cam_b: F64


def track_floor(
    grey_a: NDArray[np.uint8], grey_b: NDArray[np.uint8], max_corners: int = 200
) -> tuple[F64, F64]:
    """Corners of grey image a (H, W) tracked into b by pyramidal KLT, kept when tracking back
    lands within FB_MAX_PX of the start: pixels (N, 2) in a and in b (N may be 0)."""
    corners = cv2.goodFeaturesToTrack(grey_a, max_corners, 0.01, 6)
    none = np.zeros((0, 2))
    if corners is None:
        return none, none
    win = (KLT_WINDOW_PX, KLT_WINDOW_PX)
    fwd, st, _ = cv2.calcOpticalFlowPyrLK(
        grey_a, grey_b, corners, None, winSize=win, maxLevel=KLT_LEVELS
    )
    back, st2, _ = cv2.calcOpticalFlowPyrLK(
        grey_b, grey_a, fwd, None, winSize=win, maxLevel=KLT_LEVELS
    )
    ok = (st[:, 0] == 1) & (st2[:, 0] == 1)
    ok &= np.linalg.norm((back - corners)[:, 0], axis=1) < FB_MAX_PX
    return corners[ok, 0].astype(np.float64), fwd[ok, 0].astype(np.float64)


def floor_px_in_b(model: CameraModel, pair: FloorPair, floor_z_m: float) -> F64 | None:
    """Where the truth puts pair.px_a's floor points in frame b: pixels (N, 2), or None when a
    ray misses the floor (the pose or the floor is wrong for this pair)."""
    xy = model.pixels_to_normalized(pair.px_a)
    rays = np.column_stack([xy, np.ones(len(xy))]) @ pair.T_world_cam_a[:3, :3].T
    origin = pair.T_world_cam_a[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (floor_z_m - origin[2]) / rays[:, 2]
    if not np.all(np.isfinite(s) & (s > 0.0)):
        return None
    points = origin + rays * s[:, None]
    R, t = pair.T_world_cam_b[:3, :3], pair.T_world_cam_b[:3, 3]
    uv, in_front = model.project((points - t) @ R)
    return uv if bool(np.all(in_front)) else None


def pair_errors(model: CameraModel, pairs: Sequence[FloorPair], floor_z_m: float) -> F64:
    """Each pair's median error [px] (P,) of the truth's prediction against the tracks (inf
    where a ray misses the floor)."""
    out = np.full(len(pairs), np.inf)
    for k, pair in enumerate(pairs):
        uv = floor_px_in_b(model, pair, floor_z_m)
        if uv is not None:
            out[k] = float(np.median(np.linalg.norm(uv - pair.px_b, axis=1)))
    return out


def no_motion_errors(pairs: Sequence[FloorPair]) -> F64:
    """Each pair's median flow [px] (P,): the error of predicting that nothing moved."""
    return np.array([float(np.median(np.linalg.norm(p.px_b - p.px_a, axis=1))) for p in pairs])


TRIM = 0.8  # the trimmed mean keeps the best 80 % of the pairs (KLT on blur, a jolt)


def trimmed_mean(errors: F64) -> float:
    """The mean of the smallest TRIM share of ``errors`` (P,) [px]."""
    keep = max(1, int(np.ceil(TRIM * len(errors))))
    return float(np.mean(np.sort(errors)[:keep]))


@dataclass(frozen=True, slots=True)
class LensFit:
    """The lens that makes the truth explain the tracks best: focal [px] (fx = fy), k1, k2
    (the model's principal point and other terms kept), the trimmed mean and the median of
    the pairs' median errors [px] with it."""

    focal_px: float
    k1: float
    k2: float
    trimmed_error_px: float
    median_error_px: float


def fit_lens(model: CameraModel, pairs: Sequence[FloorPair], floor_z_m: float) -> LensFit:
    """Nelder-Mead over (focal, k1, k2) from the model's own, minimising the trimmed mean of
    the pairs' median errors (a lens that does not undistort every track costs 1e9)."""

    def cost(x: F64) -> float:
        f, k1, k2 = (float(v) for v in x)
        try:
            errors = pair_errors(replace(model, fx=f, fy=f, k1=k1, k2=k2), pairs, floor_z_m)
        except GeometryError:
            return 1e9
        return trimmed_mean(errors) if np.all(np.isfinite(errors)) else 1e9

    start = np.array([model.fx, model.k1, model.k2])
    options = {"xatol": 1e-3, "fatol": 1e-4, "maxiter": 400}
    best = minimize(cost, start, method="Nelder-Mead", options=options)
    f, k1, k2 = (float(v) for v in best.x)
    errors = pair_errors(replace(model, fx=f, fy=f, k1=k1, k2=k2), pairs, floor_z_m)
    return LensFit(f, k1, k2, float(best.fun), float(np.median(errors)))
