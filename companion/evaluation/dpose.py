"""d-Pose accuracy: pose errors by height band (of a flight, or of random poses), and checks
over random poses (synthetic projections, no rendering): how often the vertex map is wrong,
how often a pose is given, and its accuracy by height."""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.dpose.solve import Priors, reference_points, solve
from companion.geometry import se3, so3
from companion.geometry.camera import CameraModel
from companion.types import F64


@dataclass
class RandomPoseStudy:
    """Counts over the poses with all four marks in view, and errors of the correct ones."""

    visible: int = 0
    correct: int = 0
    wrong: int = 0
    refused: Counter[str] = field(default_factory=Counter)
    height_m: list[float] = field(default_factory=list)
    translation_err_m: list[float] = field(default_factory=list)
    rotation_err_deg: list[float] = field(default_factory=list)

    @property
    def pose_rate(self) -> float:
        return self.correct / self.visible if self.visible else 0.0


def random_pose_study(
    camera: CameraModel,
    T_body_cam: F64,
    pattern: F64,
    n: int,
    seed: int = 0,
    pixel_sigma: float = 1.0,
    distractors: int = 0,
    heights_m: tuple[float, float] = (2.0, 8.0),
    tilt_sigma_rad: float = float(np.radians(0.1)),
    height_sigma_m: float = 0.01,
) -> RandomPoseStudy:
    """n random body poses above a pattern (4, 3) (pattern frame = body at arming, marks
    around z = z0 below it): heights above the marks in ``heights_m``, yaw uniform over the
    full circle, roll/pitch ~ N(0, 5 deg), horizontal offset within +-0.3 m; detections with
    Gaussian noise pixel_sigma, shuffled, plus ``distractors`` random extra dots; the priors
    as the autopilot and the lasers would give them (tilt with tilt_sigma, height with
    height_sigma)."""
    rng = np.random.default_rng(seed)
    T_cam_body = se3.inverse(T_body_cam)
    z0 = float(pattern[:, 2].mean())
    centre = pattern.mean(axis=0)
    _, _, Vt = np.linalg.svd(pattern - centre)
    normal = Vt[2] if Vt[2][2] > 0 else -Vt[2]
    out = RandomPoseStudy()
    for _ in range(n):
        h = rng.uniform(*heights_m)
        R_pb = so3.rpy_to_matrix(
            rng.normal(0, 0.087), rng.normal(0, 0.087), rng.uniform(-np.pi, np.pi)
        )
        body = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), z0 - h])
        T_pattern_body = se3.make(R_pb, body)
        T_cam_pattern = se3.inverse(T_pattern_body @ T_body_cam)
        uv, in_front = camera.project(se3.transform(T_cam_pattern, pattern))
        if not (in_front.all() and camera.in_image(uv, 2.0).all()):
            continue
        out.visible += 1
        det = uv + rng.normal(0.0, pixel_sigma, uv.shape)
        if distractors:
            extra = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], (distractors, 2))
            det = np.vstack([det, extra])
        perm = rng.permutation(len(det))
        det = det[perm]
        R_noisy = R_pb @ so3.exp(tilt_sigma_rad * rng.standard_normal(3))
        h_body = float(normal @ centre - normal @ body)
        priors = Priors(
            R_noisy,
            2 * tilt_sigma_rad,
            T_cam_body[:3, :3],
            T_cam_body[:3, 3],
            h_body + rng.normal(0.0, height_sigma_m),
            2 * height_sigma_m,
            normal,
            float(normal @ centre),
        )
        sol, reason = solve(det, pattern, camera, T_cam_body[:3, :3], priors=priors)
        if sol is None:
            out.refused[reason.split(" (")[0]] += 1
            continue
        truth = tuple(int(np.flatnonzero(perm == k)[0]) for k in range(4))
        if sol.order != truth:
            out.wrong += 1
            continue
        out.correct += 1
        T_est = se3.inverse(sol.T_cam_pattern) @ T_cam_body
        out.height_m.append(h)
        out.translation_err_m.append(float(np.linalg.norm(T_est[:3, 3] - body)))
        out.rotation_err_deg.append(np.degrees(so3.angle_between(T_est[:3, :3], R_pb)))
    return out


def armed_pattern(T_body_rf: F64, height_m: float = 3.0) -> F64:
    """The marks (4, 3) that lasers with extrinsics T_body_rf (4, 4, 4) paint when armed
    height_m over level ground (pattern frame = the body at arming)."""
    o, u = T_body_rf[:, :3, 3], T_body_rf[:, :3, 2]
    return reference_points(o, u, (height_m - o[:, 2]) / u[:, 2])


def pose_errors(est: F64, truth: F64) -> tuple[F64, F64]:
    """Translation [m] and rotation [deg] errors (F,) of (F, 4, 4) poses; NaN where missing."""
    t = np.linalg.norm(est[:, :3, 3] - truth[:, :3, 3], axis=1)
    r = np.full(len(est), np.nan)
    ok = np.all(np.isfinite(est[:, :3, :3]), axis=(1, 2))
    for k in np.flatnonzero(ok):
        r[k] = np.degrees(so3.angle_between(est[k, :3, :3], truth[k, :3, :3]))
    return t, r


def height_bands(height_m: F64) -> list[tuple[str, NDArray[np.bool_]]]:
    """The height bands the errors are given in: all, 2-6 m and 6-8 m above the marks."""
    h = height_m
    return [
        ("all", np.ones(len(h), dtype=bool)),
        ("2-6 m", (h >= 2.0) & (h <= 6.0)),
        ("6-8 m", (h > 6.0) & (h <= 8.0)),
    ]


@dataclass(frozen=True, slots=True)
class BandErrors:
    """MSE and RMSE of translation [m] and orientation [deg] over the frames of one band that
    have an estimate (NaN if none); frames in the band and the share with an estimate."""

    frames: int
    available: float
    t_mse_m2: float
    t_rmse_m: float
    r_mse_deg2: float
    r_rmse_deg: float


def band_errors(t_err: F64, r_err: F64, sel: NDArray[np.bool_]) -> BandErrors:
    """:class:`BandErrors` of the errors (F,) (NaN = no estimate) over the frames ``sel``."""
    ok = sel & np.isfinite(t_err) & np.isfinite(r_err)
    n = int(ok.sum())
    frames = int(sel.sum())
    nan = float("nan")
    return BandErrors(
        frames,
        float(n / max(frames, 1)),
        float(np.mean(t_err[ok] ** 2)) if n else nan,
        float(np.sqrt(np.mean(t_err[ok] ** 2))) if n else nan,
        float(np.mean(r_err[ok] ** 2)) if n else nan,
        float(np.sqrt(np.mean(r_err[ok] ** 2))) if n else nan,
    )


def dpose_metrics(truth: F64, height_m: F64, estimates: Mapping[str, F64]) -> list[dict[str, Any]]:
    """One row per estimate (name -> (F, 4, 4) poses, NaN where missing) and height band:
    MSE and RMSE of translation and orientation against ``truth`` (F, 4, 4), availability."""
    rows = []
    for name, poses in estimates.items():
        t_err, r_err = pose_errors(poses, truth)
        for band, sel in height_bands(height_m):
            e = band_errors(t_err, r_err, sel)
            rows.append(
                {
                    "estimate": name,
                    "heights": band,
                    "frames": e.frames,
                    "available": e.available,
                    "t_mse_m2": e.t_mse_m2,
                    "t_rmse_m": e.t_rmse_m,
                    "r_mse_deg2": e.r_mse_deg2,
                    "r_rmse_deg": e.r_rmse_deg,
                }
            )
    return rows


def study_bands(study: RandomPoseStudy) -> dict[str, BandErrors]:
    """The errors of a random-pose study's correct poses in the 2-6 m and 6-8 m bands."""
    h = np.array(study.height_m)
    te, re = np.array(study.translation_err_m), np.array(study.rotation_err_deg)
    return {band: band_errors(te, re, sel) for band, sel in height_bands(h) if band != "all"}
