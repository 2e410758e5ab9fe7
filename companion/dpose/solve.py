"""Vertex map and pose: which detected mark is which laser, and the camera's 6DoF pose
relative to the pattern (pure; thesis chapter 7, reconstructed in DESIGN.md section 4).

The pattern frame is the body frame at the arming time: the marks' 3D points there are
``o_k + d_k u_k`` from the lasers' mounts and the four measured distances (metric).

Vertex map: with exactly four detections, every one of the 24 labellings is solved by PnP
(SQPnP, OpenCV, globally optimal for any 4 points, coplanar or not) and scored by its
reprojection RMS in pixels. The best labelling is accepted only if (a) its RMS is at most
``max_rms_px``, (b) every other labelling is worse by ``ambiguity_ratio`` and by at least
``min_gap_px``, and (c) all marks are in front of the camera. Anything else (three or five
detections, an ambiguous or a bad fit) yields no pose and a reason: a wrong vertex map would
give a confidently wrong pose, which is worse than none. The pattern's similarity margin
(:mod:`companion.dpose.pattern`) is what keeps wrong labellings far from the right one.

Pose: the accepted PnP solution refined by Levenberg-Marquardt on the reprojection error;
covariance sigma_px^2 (J^T J)^-1 over (rotation vector, translation) of T_cam_pattern.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.dpose.pattern import PERMUTATIONS
from companion.geometry import so3
from companion.geometry.camera import CameraModel

F64 = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class SolveOptions:
    """Acceptance of a vertex map."""

    max_rms_px: float = 3.0
    ambiguity_ratio: float = 4.0
    min_gap_px: float = 6.0
    pixel_sigma: float = 1.0  # detection noise for the covariance [px]
    max_tilt_deg: float = 35.0  # the body's tilt from its attitude at arming


@dataclass(frozen=True, slots=True)
class DposeSolution:
    """T_cam_pattern (4, 4); order (4,): the detection index of each mark; rms_px of the
    accepted labelling and second_rms_px of the best wrong one; cov_6x6 over (rotation
    vector [rad], translation [m]) of T_cam_pattern."""

    T_cam_pattern: F64
    order: tuple[int, ...]
    rms_px: float
    second_rms_px: float
    cov_6x6: F64


def reference_points(origins: F64, beams: F64, range_m: F64) -> F64:
    """The marks' 3D points (4, 3) [m] in the pattern frame (the body at arming)."""
    return origins + range_m[:, None] * beams


def _rms_px(pattern: F64, norm: F64, rvec: F64, tvec: F64, focal_px: float) -> float:
    R = so3.exp(rvec.ravel())
    p = pattern @ R.T + tvec.ravel()
    if np.any(p[:, 2] <= 1e-6):
        return np.inf
    proj = p[:, :2] / p[:, 2:3]
    return float(np.sqrt(np.mean(np.sum((proj - norm) ** 2, axis=1))) * focal_px)


def _candidates(
    obj: F64, obj_plane: F64, img: F64, planar: bool, eye: F64
) -> list[tuple[F64, F64]]:
    """PnP solutions of one labelling: both IPPE solutions of the planar approximation (the
    two-fold ambiguity of a plane seen in perspective), refined on the true points when the
    marks are not coplanar."""
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj_plane, img, eye, None, flags=cv2.SOLVEPNP_IPPE)
    out = []
    for k in range(int(n)):
        r, t = rvecs[k].reshape(3, 1).copy(), tvecs[k].reshape(3, 1).copy()
        if not planar:
            r, t = cv2.solvePnPRefineLM(obj, img, eye, None, r, t)
        out.append((r, t))
    return out


def solve(
    pixels: F64,
    pattern: F64,
    camera: CameraModel,
    R_cam_body: F64 | None = None,
    opts: SolveOptions | None = None,
) -> tuple[DposeSolution | None, str]:
    """The vertex map and T_cam_pattern from detected mark centres (N, 2) [distorted px] and
    the pattern's points (4, 3) [m] (pattern frame = the body at arming); (None, reason) when
    there is no unambiguous answer. With R_cam_body, a labelling's pose counts only if the
    body is tilted at most ``max_tilt_deg`` from its attitude at arming (a multirotor over
    the ground it marked), which removes the strongly tilted poses that a wrong labelling of
    a small (weak-perspective) pattern can otherwise fit."""
    o = opts or SolveOptions()
    if len(pixels) != 4:
        return None, f"{len(pixels)} marks detected, 4 needed"
    norm = camera.pixels_to_normalized(pixels)
    focal = 0.5 * (camera.fx + camera.fy)
    eye = np.eye(3)
    obj = np.ascontiguousarray(pattern, dtype=np.float64)
    centre = obj.mean(axis=0)
    _, sv, Vt = np.linalg.svd(obj - centre)
    normal = Vt[2]
    obj_plane = np.ascontiguousarray(obj - np.outer((obj - centre) @ normal, normal))
    planar = bool(sv[2] < 1e-3 * max(sv[0], 1e-9) or np.abs((obj - centre) @ normal).max() < 2e-3)
    cos_max = np.cos(np.radians(o.max_tilt_deg))
    scored: list[tuple[float, tuple[int, ...], F64, F64]] = []
    for perm in PERMUTATIONS:
        img = np.ascontiguousarray(norm[list(perm)], dtype=np.float64)
        best: tuple[float, F64, F64] | None = None
        for rvec, tvec in _candidates(obj, obj_plane, img, planar, eye):
            if R_cam_body is not None:
                R_pattern_body = so3.exp(rvec.ravel()).T @ R_cam_body
                if R_pattern_body[2, 2] < cos_max:
                    continue
            rms = _rms_px(obj, img, rvec, tvec, focal)
            if best is None or rms < best[0]:
                best = (rms, rvec, tvec)
        if best is not None:
            scored.append((best[0], perm, best[1], best[2]))
    if not scored:
        return None, "no plausible pose for any labelling"
    scored.sort(key=lambda s: s[0])
    best_s = scored[0]
    second_rms = scored[1][0] if len(scored) > 1 else np.inf
    if not np.isfinite(best_s[0]) or best_s[0] > o.max_rms_px:
        return None, f"no labelling fits (best {best_s[0]:.1f} px)"
    if second_rms < max(o.ambiguity_ratio * best_s[0], best_s[0] + o.min_gap_px):
        return None, f"ambiguous labelling ({best_s[0]:.1f} px vs {second_rms:.1f} px)"
    img = np.ascontiguousarray(norm[list(best_s[1])], dtype=np.float64)
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, eye, None, best_s[2].copy(), best_s[3].copy())
    rms = _rms_px(obj, img, rvec, tvec, focal)
    _, J = cv2.projectPoints(obj, rvec, tvec, eye, None)
    Jp = J[:, :6] * focal  # d(px)/d(rvec, tvec)
    try:
        cov = np.linalg.inv(Jp.T @ Jp) * o.pixel_sigma**2
    except np.linalg.LinAlgError:
        return None, "degenerate pattern geometry"
    T = np.eye(4)
    T[:3, :3] = so3.exp(rvec.ravel())
    T[:3, 3] = tvec.ravel()
    return DposeSolution(T, tuple(int(i) for i in best_s[1]), rms, second_rms, cov), "ok"
