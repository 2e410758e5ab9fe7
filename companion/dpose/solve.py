"""Vertex map and pose: which detected mark is which laser, and the camera's 6DoF pose
relative to the pattern (pure; thesis chapter 7, reconstructed in docs/methods.md).

The pattern frame is the body frame at the arming time: the marks' 3D points there are
``o_k + d_k u_k`` from the lasers' mounts and the four measured distances (metric).

Vertex map: every labelling (which detection is which mark) is solved and scored by its
reprojection RMS in pixels. With the autopilot's roll/pitch as a prior (the normal case), a
labelling's pose has only yaw and position left, found in closed form
(:func:`poses_known_tilt`), batched over all labellings, and with up to ``max_detections``
detections every ordered choice of four is tried (distractors must then lose like wrong
labellings do). Without the prior, exactly four detections are needed and each labelling is
solved by IPPE (both planar solutions) and kept only if the body's tilt is plausible. The best
labelling is accepted only if (a) its RMS is at most ``max_rms_px``, (b) every other labelling
is worse by ``ambiguity_ratio`` and by at least ``min_gap_px``, and (c) all marks are in front
of the camera. Anything else (three detections, an ambiguous or a bad fit) yields no pose and
a reason: a wrong vertex map would give a confidently wrong pose, which is worse than
none. The pattern's similarity margin (:mod:`companion.dpose.pattern`) is what keeps wrong
labellings far from the right one.

Pose: the accepted solution refined by Gauss-Newton on the reprojection error [px / sigma]
plus the priors (the autopilot's tilt, the lasers' height above the pattern plane);
covariance (J^T J)^-1 of that weighted problem over (rotation vector, translation) of
T_cam_pattern.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np

from companion.dpose.pattern import PERMUTATIONS
from companion.geometry import so3
from companion.geometry.camera import CameraModel
from companion.types import F64


@dataclass(frozen=True, slots=True)
class SolveOptions:
    """Acceptance of a vertex map."""

    max_rms_px: float = 3.0
    ambiguity_ratio: float = 4.0
    min_gap_px: float = 6.0
    pixel_sigma: float = 1.0  # detection noise for the covariance [px]
    max_tilt_deg: float = 35.0  # the body's tilt from its attitude at arming (no priors)
    max_detections: int = 7  # with priors, up to this many detections are sorted out


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


def poses_known_tilt(obj: F64, norms: F64, R_tilt_cam: F64) -> tuple[F64, F64, F64]:
    """T_cam_pattern for L labellings at once when the rotation is known up to a yaw:
    R_pattern_cam = Rz(psi) R_tilt_cam (the tilt from the autopilot). Linear; exact without
    noise (any point layout). obj (4, 3) pattern points; norms (L, 4, 2) normalised image
    points of each labelling. Returns R_cam_pattern (L, 3, 3), t_cam_pattern (L, 3) and a
    validity mask (L,).

    With w_k = R_tilt_cam (x_k, y_k, 1), u_k = w_k[:2] / w_k[2] and the camera centre c in
    the pattern frame: P_k,xy - c_xy = (P_k,z - c_z) Rot(psi) u_k.
    1. With the heights scaled as s_k = (P_k,z - c_z) / (z0 - c_z) (all 1 in the first pass),
       P_k,xy = c_xy + s_k Rot(psi) u_k (z0 - c_z) is linear in (c_x, c_y, K_a, K_b) with
       (K_a, K_b) = (z0 - c_z)(cos psi, sin psi), so psi = atan2(K_b, K_a).
    2. With psi known, P_k,xy - P_k,z q_k = c_xy - c_z q_k (q_k = Rot(psi) u_k) is linear in c.
    Two passes make a curved (non-planar) pattern exact as well."""
    L, n = norms.shape[0], norms.shape[1]
    w = np.concatenate([norms, np.ones((L, n, 1))], axis=2) @ R_tilt_cam.T  # (L, n, 3)
    valid = np.all(w[..., 2] > 1e-6, axis=1)
    wz = np.where(w[..., 2:3] > 1e-6, w[..., 2:3], 1.0)
    u = w[..., :2] / wz  # (L, n, 2)
    z0 = float(obj[:, 2].mean())
    scale = np.ones((L, n))
    rhs1 = np.broadcast_to(obj[:, :2].reshape(1, 2 * n), (L, 2 * n))
    eye2 = np.tile(np.eye(2), (n, 1))  # (2n, 2): the c_x, c_y columns
    c = np.zeros((L, 3))
    psi = np.zeros(L)
    for _ in range(2):
        A = np.zeros((L, 2 * n, 4))
        A[:, :, :2] = eye2
        su = u * scale[..., None]
        A[:, 0::2, 2], A[:, 0::2, 3] = su[..., 0], -su[..., 1]
        A[:, 1::2, 2], A[:, 1::2, 3] = su[..., 1], su[..., 0]
        At = np.swapaxes(A, 1, 2)
        sol = np.linalg.solve(At @ A + 1e-12 * np.eye(4), At @ rhs1[..., None])[..., 0]
        psi = np.arctan2(sol[:, 3], sol[:, 2])
        cp, sp = np.cos(psi)[:, None], np.sin(psi)[:, None]
        q = np.stack([cp * u[..., 0] - sp * u[..., 1], sp * u[..., 0] + cp * u[..., 1]], axis=2)
        B = np.zeros((L, 2 * n, 3))
        B[:, :, :2] = eye2
        B[:, :, 2] = -q.reshape(L, 2 * n)
        rhs2 = (obj[None, :, :2] - obj[None, :, 2:3] * q).reshape(L, 2 * n)
        Bt = np.swapaxes(B, 1, 2)
        c = np.linalg.solve(Bt @ B + 1e-12 * np.eye(3), Bt @ rhs2[..., None])[..., 0]
        height = z0 - c[:, 2]
        valid &= np.abs(height) > 1e-6
        height = np.where(np.abs(height) > 1e-6, height, 1.0)
        scale = (obj[None, :, 2] - c[:, 2:3]) / height[:, None]
    cz, sz = np.cos(psi), np.sin(psi)
    Rz = np.zeros((L, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = cz, -sz, sz, cz, 1.0
    R_pattern_cam = Rz @ R_tilt_cam
    R_cam_pattern = np.swapaxes(R_pattern_cam, 1, 2)
    t = -(R_cam_pattern @ c[..., None])[..., 0]
    return R_cam_pattern, t, valid


def _rms_px_batch(obj: F64, norms: F64, R: F64, t: F64, focal_px: float) -> F64:
    """Reprojection RMS [px] (L,) of L poses (R (L, 3, 3), t (L, 3)) against norms (L, n, 2);
    inf where a mark is behind the camera."""
    p = obj[None] @ np.swapaxes(R, 1, 2) + t[:, None, :]
    z = p[..., 2:3]
    behind = np.any(z[..., 0] <= 1e-6, axis=1)
    proj = p[..., :2] / np.where(z > 1e-6, z, 1.0)
    rms = np.sqrt(np.mean(np.sum((proj - norms) ** 2, axis=2), axis=1)) * focal_px
    return np.where(behind, np.inf, rms)


def solve(
    pixels: F64,
    pattern: F64,
    camera: CameraModel,
    R_cam_body: F64 | None = None,
    opts: SolveOptions | None = None,
    priors: Priors | None = None,
) -> tuple[DposeSolution | None, str]:
    """The vertex map and T_cam_pattern from detected mark centres (N, 2) [distorted px] and
    the pattern's points (4, 3) [m] (pattern frame = the body at arming); (None, reason) when
    there is no unambiguous answer. With R_cam_body, a labelling's pose counts only if the
    body is tilted at most ``max_tilt_deg`` from its attitude at arming (a multirotor over
    the ground it marked), which removes the strongly tilted poses that a wrong labelling of
    a small (weak-perspective) pattern can otherwise fit."""
    o = opts or SolveOptions()
    n_det = len(pixels)
    if n_det < 4:
        return None, f"{n_det} marks detected, 4 needed"
    if n_det > 4 and (priors is None or n_det > o.max_detections):
        return None, f"{n_det} marks detected, 4 needed"
    norm = camera.pixels_to_normalized(pixels)
    focal = 0.5 * (camera.fx + camera.fy)
    eye = np.eye(3)
    obj = np.ascontiguousarray(pattern, dtype=np.float64)
    scored: list[tuple[float, tuple[int, ...], F64, F64]] = []
    if priors is not None:  # the prior's roll/pitch in the pattern frame, yaw left free
        # every ordered choice of 4 of the detections (24 when there are exactly 4; with
        # distractors, every subset too: a wrong subset must then lose by the same margins)
        labellings = np.asarray(list(itertools.permutations(range(n_det), 4)))
        norms = norm[labellings]  # (L, 4, 2)
        r, p, _ = so3.matrix_to_rpy(priors.R_pattern_body)
        R_tilt_cam = so3.rpy_to_matrix(r, p, 0.0) @ priors.R_cam_body.T
        Rs, ts, valid = poses_known_tilt(obj, norms, R_tilt_cam)
        rms_all = np.where(valid, _rms_px_batch(obj, norms, Rs, ts, focal), np.inf)
        for k in np.argsort(rms_all)[:2]:
            scored.append(
                (
                    float(rms_all[k]),
                    tuple(int(i) for i in labellings[k]),
                    so3.log(Rs[k]).reshape(3, 1),
                    ts[k].reshape(3, 1),
                )
            )
    else:
        # a multirotor over the ground it marked: not far from its attitude at arming
        cos_max = np.cos(np.radians(o.max_tilt_deg))
        centre = obj.mean(axis=0)
        _, sv, Vt = np.linalg.svd(obj - centre)
        normal = Vt[2]
        obj_plane = np.ascontiguousarray(obj - np.outer((obj - centre) @ normal, normal))
        off_plane = np.abs((obj - centre) @ normal).max()
        planar = bool(sv[2] < 1e-3 * max(sv[0], 1e-9) or off_plane < 2e-3)
        for perm in PERMUTATIONS:
            img = np.ascontiguousarray(norm[list(perm)], dtype=np.float64)
            best: tuple[float, F64, F64] | None = None
            for rvec, tvec in _candidates(obj, obj_plane, img, planar, eye):
                if R_cam_body is not None:  # the body's tilt from its attitude at arming
                    R_pattern_body = so3.exp(rvec.ravel()).T @ R_cam_body
                    if float(R_pattern_body[2, 2]) < cos_max:
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
    T, cov = refine(obj, img, focal, best_s[2].ravel(), best_s[3].ravel(), priors, o.pixel_sigma)
    rms = _rms_px(obj, img, so3.log(T[:3, :3]), T[:3, 3], focal)
    return DposeSolution(T, tuple(int(i) for i in best_s[1]), rms, second_rms, cov), "ok"


@dataclass(frozen=True, slots=True)
class Priors:
    """What the other sensors say at the frame time, as soft constraints on the pose.

    R_pattern_body: (3, 3) the body's attitude relative to the pattern frame from the
    autopilot (its roll/pitch are drift-free; only the tilt is used), tilt_sigma_rad;
    R_cam_body: (3, 3) the camera mount; height_m: the body's height above the pattern's plane
    from the distance sensors (NaN = unknown), height_sigma_m; plane: (normal (3,), offset) of
    the pattern plane n . p = offset in the pattern frame (n pointing down, away from the body).
    """

    R_pattern_body: F64
    tilt_sigma_rad: float
    R_cam_body: F64
    body_in_cam_m: F64  # (3,) the body origin in the camera frame (T_cam_body's translation)
    height_m: float = float("nan")
    height_sigma_m: float = 0.02
    plane_normal: F64 | None = None
    plane_offset: float = 0.0


def _tilt_residual(R_pattern_body: F64, R_prior: F64) -> F64:
    """The tilt part (2,) [rad] of the rotation between two body attitudes (x, y of the cross
    product of the prior's down axis with the estimate's: small-angle rotation vector)."""
    a = R_pattern_body[:, 2]
    b = R_prior[:, 2]
    return np.array([b[1] * a[2] - b[2] * a[1], b[2] * a[0] - b[0] * a[2]])


def refine(
    obj: F64,
    img: F64,
    focal_px: float,
    rvec: F64,
    tvec: F64,
    priors: Priors | None,
    pixel_sigma: float,
) -> tuple[F64, F64]:
    """Gauss-Newton on the reprojection error [px / pixel_sigma] plus,
    when given, the tilt and height priors; returns T_cam_pattern (4, 4) and the covariance
    (6, 6) over (rotation vector, translation) from the weighted Jacobian."""

    def residuals(x: F64) -> F64:
        R = so3.exp(x[:3])
        p = obj @ R.T + x[3:]
        proj = p[:, :2] / p[:, 2:3]
        r = [((proj - img) * focal_px / pixel_sigma).ravel()]
        if priors is not None:
            R_pattern_cam = R.T
            R_pattern_body = R_pattern_cam @ priors.R_cam_body
            r.append(_tilt_residual(R_pattern_body, priors.R_pattern_body) / priors.tilt_sigma_rad)
            if np.isfinite(priors.height_m) and priors.plane_normal is not None:
                body = R_pattern_cam @ (priors.body_in_cam_m - x[3:])  # in the pattern frame
                h = priors.plane_offset - float(priors.plane_normal @ body)
                r.append(np.array([(h - priors.height_m) / priors.height_sigma_m]))
        return np.concatenate(r)

    # Gauss-Newton with a forward-difference Jacobian (6 parameters, ~11 residuals)
    x = np.concatenate([rvec, tvec]).astype(np.float64)
    h = 1e-6
    J = np.zeros((0, 6))
    for _ in range(8):
        r0 = residuals(x)
        J = np.column_stack([(residuals(x + h * np.eye(6)[k]) - r0) / h for k in range(6)])
        H = J.T @ J
        dx = np.linalg.solve(H + 1e-9 * np.eye(6), -J.T @ r0)
        x = x + dx
        if np.max(np.abs(dx)) < 1e-9:
            break
    try:
        cov = np.asarray(np.linalg.inv(J.T @ J), dtype=np.float64)
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.nan)
    T = np.eye(4)
    T[:3, :3] = so3.exp(x[:3])
    T[:3, 3] = x[3:]
    return T, cov
