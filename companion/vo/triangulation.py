"""Two-view triangulation with parallax and depth-uncertainty checks.

Linear (DLT) triangulation of normalised observations (Hartley & Zisserman, section 12.2),
then the checks a VO needs: positive depth in both views, small reprojection error, a
triangulation angle above a minimum, and the depth standard deviation from the angular noise:
sigma_depth ~= depth * sigma_angle / sin(parallax) with sigma_angle = sigma_px / f.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.types import F64

B = NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class Triangulated:
    """points_vo (N, 3); ok (N,) passed every check; parallax_deg (N,); depth_sigma (N,) in the
    units of the camera translations; reproj_px (N,) the larger of the two reprojection errors."""

    points_vo: F64
    ok: B
    parallax_deg: F64
    depth_sigma: F64
    reproj_px: F64


def triangulate(
    T_c1_vo: F64,
    T_c2_vo: F64,
    xy1: F64,
    xy2: F64,
    focal_px: float,
    pixel_sigma_px: float = 1.0,
    min_parallax_deg: float = 1.0,
    max_reproj_px: float = 3.0,
) -> Triangulated:
    """Triangulate N points seen at normalised xy1 in camera 1 and xy2 in camera 2 (N, 2)."""
    n = len(xy1)
    if n == 0:
        z = np.zeros(0)
        return Triangulated(np.zeros((0, 3)), np.zeros(0, dtype=bool), z, z, z)
    Xh = cv2.triangulatePoints(
        T_c1_vo[:3], T_c2_vo[:3], xy1.T.astype(np.float64), xy2.T.astype(np.float64)
    )
    w = Xh[3]
    w = np.where(np.abs(w) < 1e-12, 1e-12, w)
    X = (Xh[:3] / w).T
    p1 = X @ T_c1_vo[:3, :3].T + T_c1_vo[:3, 3]
    p2 = X @ T_c2_vo[:3, :3].T + T_c2_vo[:3, 3]
    z1 = p1[:, 2]
    z2 = p2[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        e1 = np.linalg.norm(p1[:, :2] / z1[:, None] - xy1, axis=1) * focal_px
        e2 = np.linalg.norm(p2[:, :2] / z2[:, None] - xy2, axis=1) * focal_px
    c1 = -T_c1_vo[:3, :3].T @ T_c1_vo[:3, 3]
    c2 = -T_c2_vo[:3, :3].T @ T_c2_vo[:3, 3]
    r1 = X - c1
    r2 = X - c2
    cos_a = np.einsum("ij,ij->i", r1, r2) / (
        np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1) + 1e-300
    )
    parallax = np.degrees(np.arccos(np.clip(cos_a, -1.0, 1.0)))
    reproj = np.maximum(e1, e2)
    ok = (
        (z1 > 0)
        & (z2 > 0)
        & np.isfinite(X).all(axis=1)
        & (reproj < max_reproj_px)
        & (parallax > min_parallax_deg)
    )
    sigma_angle = pixel_sigma_px / focal_px
    depth_sigma = z1 * sigma_angle / np.maximum(np.sin(np.radians(parallax)), 1e-9)
    return Triangulated(X, ok, parallax, depth_sigma, reproj)
