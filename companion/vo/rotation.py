"""The camera's rotation between two frames from 2D tracks alone (no map points, no depth).

Under a pure rotation the bearing of every scene point turns by the same R: b1 = R_c1_c0 b0
(b = the unit ray (x, y, 1) / |(x, y, 1)| of a normalised observation), whatever its depth
(the homography at infinity, Hartley & Zisserman section 8.4.5). R is the orthogonal
Procrustes (Kabsch 1976) solution of the bearing pairs: with M = sum_i b1_i b0_i^T = U S V^T,
R = U diag(1, 1, det(U V^T)) V^T. Two pairs fix it, so a RANSAC over 2-point samples
(Fischler & Bolles 1981) finds the rotation that most tracks agree on, re-fitted on them.

A translation t between the frames moves a point at depth z by about |t| / z (radians) off
that model: when every track fits within a pixel or two, the camera turned about a nearly
fixed point (a hand-held camera turned in place, a multirotor yawing in a hover), and its
position can be held while its orientation follows R.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.types import F64

B = NDArray[np.bool_]

RANSAC_ITERATIONS = 64
RANSAC_SEED = 0  # the samples are drawn from a fixed seed: a replay gives the same poses


@dataclass(frozen=True, slots=True)
class RotationFit:
    """R_c1_c0 (3, 3): the rotation taking bearings of frame 0 into frame 1; inliers (N,)
    the tracks within the threshold; residual_rad (N,) each track's angle off the model."""

    R_c1_c0: F64
    inliers: B
    residual_rad: F64


def bearings(xy: F64) -> F64:
    """(N, 3) unit rays of normalised observations xy (N, 2) (camera frame, z forward)."""
    rays = np.column_stack([xy, np.ones(len(xy))])
    out: F64 = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    return out


def kabsch(b0: F64, b1: F64) -> F64:
    """(3, 3) the rotation R minimising sum |b1_i - R b0_i|^2 over unit vectors (N, 3)."""
    M = b1.T @ b0
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R: F64 = U @ np.diag([1.0, 1.0, d]) @ Vt
    return R


def angle_off_rad(R_c1_c0: F64, b0: F64, b1: F64) -> F64:
    """(N,) the angle [rad] between each b1 and R b0."""
    cos = np.clip(np.einsum("ij,ij->i", b0 @ R_c1_c0.T, b1), -1.0, 1.0)
    out: F64 = np.arccos(cos)
    return out


def fit_rotation(xy0: F64, xy1: F64, threshold_rad: float, min_inliers: int) -> RotationFit | None:
    """The rotation of the camera between two frames from the same tracks seen at normalised
    xy0 and xy1 (N, 2): 2-point RANSAC on the bearings, then Kabsch on the inliers (twice).
    ``threshold_rad``: a track farther off the model than this is an outlier (a pixel
    threshold over the focal length). None when fewer than ``min_inliers`` (>= 3) agree."""
    n = len(xy0)
    if n < max(min_inliers, 3):
        return None
    b0, b1 = bearings(xy0), bearings(xy1)
    rng = np.random.default_rng(RANSAC_SEED)
    best = np.zeros(n, dtype=bool)
    for _ in range(RANSAC_ITERATIONS):
        i, j = rng.choice(n, 2, replace=False)
        if np.linalg.norm(np.cross(b0[i], b0[j])) < 1e-3:  # (nearly) the same ray
            continue
        inl = angle_off_rad(kabsch(b0[[i, j]], b1[[i, j]]), b0, b1) < threshold_rad
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < max(min_inliers, 3):
        return None
    R = kabsch(b0[best], b1[best])
    for _ in range(2):
        err = angle_off_rad(R, b0, b1)
        inl = err < threshold_rad
        if inl.sum() < max(min_inliers, 3):
            return None
        R = kabsch(b0[inl], b1[inl])
    err = angle_off_rad(R, b0, b1)
    return RotationFit(R, err < threshold_rad, err)
