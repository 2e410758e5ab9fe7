"""Trajectory alignment and absolute trajectory error.

Umeyama's closed form (S. Umeyama, "Least-squares estimation of transformation parameters
between two point patterns", IEEE PAMI 1991) aligns estimated positions to ground truth with a
rotation, a translation and optionally a scale; the ATE is the RMSE of the aligned positions
(Sturm et al., IROS 2012), as evo computes it (`evo_ape ... -a` / `-as`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.errors import GeometryError
from companion.types import F64


@dataclass(frozen=True, slots=True)
class Alignment:
    """p_gt ~= scale * R @ p_est + t."""

    R: F64
    t: F64
    scale: float

    def apply(self, points: F64) -> F64:
        """Aligned copy of points (N, 3)."""
        out: F64 = self.scale * points @ self.R.T + self.t
        return out


def umeyama(est: F64, gt: F64, with_scale: bool) -> Alignment:
    """Least-squares similarity (or rigid, with_scale=False) mapping est (N, 3) onto gt (N, 3)."""
    if est.shape != gt.shape or est.ndim != 2 or est.shape[1] != 3 or len(est) < 3:
        raise GeometryError("umeyama needs two (N, 3) arrays with N >= 3")
    mu_e = est.mean(axis=0)
    mu_g = gt.mean(axis=0)
    de = est - mu_e
    dg = gt - mu_g
    cov = dg.T @ de / len(est)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_e = float(np.mean(np.sum(de**2, axis=1)))
    scale = float(np.trace(np.diag(D) @ S) / var_e) if with_scale else 1.0
    t = mu_g - scale * R @ mu_e
    return Alignment(R, t, scale)


def ate_rmse(est: F64, gt: F64, align: str = "se3") -> tuple[float, Alignment]:
    """RMSE [m] of positions after alignment: 'se3' (rigid), 'sim3' (with scale) or 'none'."""
    if align == "none":
        a = Alignment(np.eye(3), np.zeros(3), 1.0)
    elif align in ("se3", "sim3"):
        a = umeyama(est, gt, with_scale=align == "sim3")
    else:
        raise ValueError(f"unknown alignment {align!r}")
    err = np.linalg.norm(a.apply(est) - gt, axis=1)
    return float(np.sqrt(np.mean(err**2))), a


def path_length(positions: F64) -> float:
    """Length [m] of the polyline through positions (N, 3)."""
    return float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum())


def final_error_m(position_m: F64, gt_position_m: F64, R_world_vo: F64) -> float:
    """Final-position error [m]: the estimate's displacement from its first position to its
    last, turned into the world by R_world_vo (3, 3), against the truth's (positions (N, 3),
    the estimate in the VO frame's orientation, the truth in the world)."""
    world = position_m @ R_world_vo.T
    return float(np.linalg.norm((world[-1] - world[0]) - (gt_position_m[-1] - gt_position_m[0])))


def poses_from_positions(positions: F64) -> F64:
    """Poses (N, 4, 4) with the identity rotation at positions (N, 3) (for TUM files of
    trajectories that have positions only)."""
    poses: F64 = np.repeat(np.eye(4)[None], len(positions), axis=0)
    poses[:, :3, 3] = positions
    return poses
