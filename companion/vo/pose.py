"""Camera pose from 2D-3D correspondences (motion-only estimation).

Iterative PnP (Levenberg-Marquardt on the reprojection error, cv2.SOLVEPNP_ITERATIVE) from a
prediction, re-solved on the inliers twice; EPnP inside RANSAC (Lepetit et al., IJCV 2009;
Fischler & Bolles 1981) only when the prediction fails. Observations are undistorted
normalised coordinates; thresholds are in pixels through the focal length.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.geometry import se3
from companion.types import F64

B = NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class PoseResult:
    """T_cam_vo (4, 4), inlier mask (N,) and reprojection errors (N,) [px]."""

    T_cam_vo: F64
    inliers: B
    residual_px: F64


def reprojection_px(T_cam_vo: F64, points_vo: F64, xy: F64, focal_px: float) -> F64:
    """Reprojection error [px] of points (N, 3) observed at normalised xy (N, 2); inf behind."""
    p_c = se3.transform(T_cam_vo, points_vo)
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(p_c[:, :2] / p_c[:, 2:3] - xy, axis=1) * focal_px
    out: F64 = np.where(p_c[:, 2] > 0, err, np.inf)
    return out


def _to_T(rvec: F64, tvec: F64) -> F64:
    R, _ = cv2.Rodrigues(rvec)
    return se3.make(np.asarray(R, dtype=np.float64), np.asarray(tvec, dtype=np.float64).ravel())


def _refine(
    X: F64, x: F64, inl: B, rvec: F64, tvec: F64, focal_px: float, inlier_px: float
) -> tuple[F64, B, F64, F64, F64] | None:
    """One iterative PnP on the inliers from (rvec, tvec): the pose, the new inliers, the
    errors of every point [px] and the solver's vectors; None when the solver fails."""
    ok, rvec, tvec = cv2.solvePnP(
        X[inl],
        x[inl],
        np.eye(3),
        None,
        rvec,
        tvec,
        useExtrinsicGuess=True,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok:
        return None
    T = _to_T(rvec, tvec)
    err = reprojection_px(T, X, x, focal_px)
    return T, err < inlier_px, err, rvec, tvec


def estimate_pose(
    points_vo: F64, xy: F64, T_guess: F64, focal_px: float, inlier_px: float, min_inliers: int
) -> PoseResult | None:
    """Pose of a camera seeing points_vo (N, 3) at normalised xy (N, 2), or None."""
    n = len(points_vo)
    if n < max(min_inliers, 6):
        return None
    X = np.ascontiguousarray(points_vo, dtype=np.float64)
    x = np.ascontiguousarray(xy, dtype=np.float64)
    rvec, _ = cv2.Rodrigues(T_guess[:3, :3])
    tvec = T_guess[:3, 3].reshape(3, 1).copy()
    inl = np.ones(n, dtype=bool)
    T = T_guess
    solved = False
    for _ in range(3):
        if inl.sum() < 6:
            break
        step = _refine(X, x, inl, rvec, tvec, focal_px, inlier_px)
        if step is None:
            break
        solved = True
        T, inl, err, rvec, tvec = step
    if not solved or inl.sum() < min_inliers:
        ok, rvec, tvec, idx = cv2.solvePnPRansac(
            X,
            x,
            np.eye(3),
            None,
            reprojectionError=inlier_px / focal_px,
            iterationsCount=100,
            confidence=0.999,
            flags=cv2.SOLVEPNP_EPNP,
        )
        if not ok or idx is None or len(idx) < min_inliers:
            return None
        inl = np.zeros(n, dtype=bool)
        inl[np.asarray(idx).ravel()] = True
        step = _refine(X, x, inl, rvec, tvec, focal_px, inlier_px)
        if step is None:
            return None
        T, inl, err, rvec, tvec = step
        if inl.sum() < min_inliers:
            return None
    if not np.all(np.isfinite(T)):
        return None
    return PoseResult(T, inl, err)
