"""Two-view initialisation with homography vs essential-matrix model selection.

The ground below a downward camera is often nearly planar, where the essential matrix is
ill-conditioned; like ORB-SLAM (Mur-Artal, Montiel, Tardos, IEEE T-RO 2015, section IV) we fit
both models with RANSAC, score them with truncated chi-square costs (T_H = 5.99, T_F = 3.84,
Gamma = 5.99) and choose the homography when S_H / (S_H + S_F) > 0.45. The homography's
up-to-four decompositions (Faugeras & Lustman 1988; cv2.decomposeHomographyMat) are told apart
by cheirality and, when the gravity direction is known, by the plane normal closest to it.
Coordinates are undistorted normalised; the translation has unit length.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.geometry import se3
from companion.types import F64
from companion.vo.ba import BundleAdjustment
from companion.vo.triangulation import triangulate

B = NDArray[np.bool_]

_T_H = 5.99
_T_F = 3.84


@dataclass(frozen=True, slots=True)
class TwoView:
    """Relative pose T_c1_c0 (4, 4) with |t| = 1, triangulated points in camera 0 (N, 3), the
    points that passed every check (N,), the chosen model and the selection ratio R_H."""

    T_c1_c0: F64
    points_c0: F64
    good: B
    depth_sigma: F64
    model: str
    ratio_h: float


def _score_homography(H: F64, x0: F64, x1: F64, inv_sigma2: float) -> F64:
    def transfer(M: F64, a: F64, b: F64) -> F64:
        p = np.column_stack([a, np.ones(len(a))]) @ M.T
        with np.errstate(divide="ignore", invalid="ignore"):
            d2 = np.sum((p[:, :2] / p[:, 2:3] - b) ** 2, axis=1) * inv_sigma2
        out: F64 = np.nan_to_num(d2, nan=np.inf)
        return out

    d01 = transfer(H, x0, x1)
    d10 = transfer(np.asarray(np.linalg.inv(H), dtype=np.float64), x1, x0)
    score: F64 = np.where(d01 < _T_H, _T_H - d01, 0.0) + np.where(d10 < _T_H, _T_H - d10, 0.0)
    return score


def _score_essential(E: F64, x0: F64, x1: F64, inv_sigma2: float) -> F64:
    h0 = np.column_stack([x0, np.ones(len(x0))])
    h1 = np.column_stack([x1, np.ones(len(x1))])
    l1 = h0 @ E.T  # epipolar lines in image 1
    l0 = h1 @ E  # epipolar lines in image 0
    num = np.einsum("ij,ij->i", h1, l1) ** 2
    d1 = num / (l1[:, 0] ** 2 + l1[:, 1] ** 2 + 1e-300) * inv_sigma2
    d0 = num / (l0[:, 0] ** 2 + l0[:, 1] ** 2 + 1e-300) * inv_sigma2
    return np.where(d1 < _T_F, _T_H - d1, 0.0) + np.where(d0 < _T_F, _T_H - d0, 0.0)


def initialize(
    x0: F64,
    x1: F64,
    focal_px: float,
    gravity_c0: F64 | None = None,
    pixel_sigma_px: float = 1.0,
    min_parallax_deg: float = 1.0,
) -> TwoView | None:
    """Relative pose and structure from N >= 8 normalised correspondences (N, 2) each.

    Returns None when neither model explains the motion well enough (too little parallax,
    too few inliers).
    """
    n = len(x0)
    if n < 8:
        return None
    thr = 1.5 * pixel_sigma_px / focal_px
    inv_sigma2 = (focal_px / pixel_sigma_px) ** 2
    H, mask_h = cv2.findHomography(x0, x1, cv2.RANSAC, thr, maxIters=300, confidence=0.999)
    E, mask_e = cv2.findEssentialMat(x0, x1, np.eye(3), cv2.RANSAC, 0.999, thr, 300)
    s_h = float(_score_homography(H, x0, x1, inv_sigma2).sum()) if H is not None else 0.0
    if E is not None and E.shape != (3, 3):
        E = E[:3]  # several solutions: the first
    s_e = float(_score_essential(E, x0, x1, inv_sigma2).sum()) if E is not None else 0.0
    if s_h + s_e <= 0:
        return None
    ratio = s_h / (s_h + s_e)
    candidates: list[tuple[F64, F64, F64 | None]] = []
    if ratio > 0.45 and H is not None:
        model = "homography"
        _, Rs, ts, normals = cv2.decomposeHomographyMat(H, np.eye(3))
        candidates = [
            (R, t.ravel(), nrm.ravel()) for R, t, nrm in zip(Rs, ts, normals, strict=True)
        ]
        inliers = mask_h.ravel().astype(bool)
    elif E is not None:
        model = "essential"
        inliers = mask_e.ravel().astype(bool)
        R1, R2, t = cv2.decomposeEssentialMat(E)
        candidates = [(R, s * t.ravel(), None) for R in (R1, R2) for s in (1.0, -1.0)]
    else:
        return None
    best: TwoView | None = None
    best_key = (-1, -1.0)
    for R, t, normal in candidates:
        tn = float(np.linalg.norm(t))
        if tn < 1e-9:
            continue
        T = se3.make(R, t / tn)
        tri = triangulate(np.eye(4), T, x0, x1, focal_px, pixel_sigma_px, min_parallax_deg)
        good = tri.ok & inliers
        count = int(good.sum())
        align = 0.0
        if normal is not None and gravity_c0 is not None:
            align = abs(float(normal @ gravity_c0)) / (float(np.linalg.norm(normal)) + 1e-12)
        # cheirality first; among near-equal counts prefer the normal along gravity
        key = (count // max(1, n // 20), align)
        if key > best_key:
            best_key = key
            best = TwoView(T, tri.points_vo, good, tri.depth_sigma, model, ratio)
    if best is None or int(best.good.sum()) < max(8, n // 3):
        return None
    return _refine(best, x0, x1, focal_px)


def _refine(view: TwoView, x0: F64, x1: F64, focal_px: float) -> TwoView:
    """Two-view bundle adjustment of the chosen solution (camera 0 fixed), |t| renormalised.

    The model fits (RANSAC homography or essential matrix) ignore the noise structure; a
    decomposed homography in particular leaves degrees of error in the translation direction.
    """
    good = np.flatnonzero(view.good)
    m = len(good)
    obs_cam = np.concatenate([np.zeros(m, np.int64), np.ones(m, np.int64)])
    obs_pt = np.concatenate([np.arange(m), np.arange(m)])
    obs_xy = np.concatenate([x0[good], x1[good]])
    T = np.stack([np.eye(4), view.T_c1_c0])
    res = BundleAdjustment(
        T,
        view.points_c0[good],
        obs_cam,
        obs_pt,
        obs_xy,
        np.array([True, False]),
        focal_px,
        huber_px=2.0,
        iterations=8,
    ).run()
    T1 = res.T_cam_vo[1].copy()
    s = float(np.linalg.norm(T1[:3, 3]))
    if not np.isfinite(s) or s < 1e-9:
        return view
    T1[:3, 3] /= s
    points = view.points_c0.copy()
    points[good] = res.points_vo / s
    return TwoView(T1, points, view.good, view.depth_sigma, view.model, view.ratio_h)
