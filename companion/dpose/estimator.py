"""d-Pose as one object: arm it, then feed frames (pure; docs/methods.md).

Arming (``arm``): the four lasers' distances and mounts give the marks' metric 3D points in the
pattern frame, which is the body frame at that moment; the reference pose T_world_body at that
moment places the pattern in the world. Afterwards (``step``): detect the red marks, find the
vertex map and the pose with the autopilot's roll/pitch and the lasers' current heights as
priors (:mod:`companion.dpose.solve`), and return the body's pose in the world with its
covariance, or a reason for not giving one.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.dpose.detect import DetectOptions, detect_marks
from companion.dpose.solve import DposeSolution, Priors, SolveOptions, reference_points, solve
from companion.errors import GeometryError
from companion.geometry import se3
from companion.geometry.camera import CameraModel
from companion.types import F64, RangeSensorSpec

U8 = NDArray[np.uint8]


@dataclass(frozen=True, slots=True)
class DposeResult:
    """T_world_body (4, 4), T_pattern_body (4, 4), cov_6x6 over (rotation vector, translation)
    of T_cam_pattern, and the solution (vertex map, residuals)."""

    time_us: int
    T_world_body: F64
    T_pattern_body: F64
    cov_6x6: F64
    solution: DposeSolution


class Dpose:
    """The d-Pose estimator for four laser sensors (their ids in the order of the pattern)."""

    def __init__(
        self,
        camera: CameraModel,
        T_body_cam: F64,
        lasers: Mapping[int, RangeSensorSpec],
        tilt_sigma_rad: float = float(np.radians(0.2)),
        height_sigma_m: float = 0.02,
        detect: DetectOptions | None = None,
        solve_opts: SolveOptions | None = None,
    ) -> None:
        if len(lasers) != 4:
            raise GeometryError(f"d-Pose needs four lasers, got {len(lasers)}")
        self.camera = camera
        self.T_body_cam = T_body_cam
        self.T_cam_body = se3.inverse(T_body_cam)
        self.ids = tuple(lasers)
        T = np.stack([lasers[i].T_body_rf for i in self.ids])
        self.origins, self.beams = T[:, :3, 3], T[:, :3, 2]
        self.tilt_sigma_rad = tilt_sigma_rad
        self.height_sigma_m = height_sigma_m
        self.detect_opts = detect or DetectOptions()
        self.solve_opts = solve_opts or SolveOptions()
        self.pattern: F64 | None = None
        self.T_world_pattern: F64 | None = None
        self.R_world_body_arm: F64 | None = None
        self.plane_normal = np.array([0.0, 0.0, 1.0])
        self.plane_offset = 0.0
        self.last_reason = "not armed"

    @property
    def armed(self) -> bool:
        return self.pattern is not None

    def arm(self, range_m: Mapping[int, float], T_world_body: F64, R_world_body_ap: F64) -> None:
        """Fix the pattern: the four distances [m] at the moment the marks are left, the body's
        pose then (the world reference) and the autopilot's attitude then."""
        d = np.array([range_m[i] for i in self.ids], dtype=np.float64)
        if not np.all(np.isfinite(d)) or np.any(d <= 0):
            raise GeometryError("d-Pose: arming needs four valid distances")
        self.pattern = reference_points(self.origins, self.beams, d)
        self.T_world_pattern = T_world_body.copy()
        self.R_world_body_arm = R_world_body_ap.copy()
        centre = self.pattern.mean(axis=0)
        _, _, Vt = np.linalg.svd(self.pattern - centre)
        n = Vt[2] if Vt[2][2] > 0 else -Vt[2]  # pointing down, away from the body
        self.plane_normal, self.plane_offset = n, float(n @ centre)
        self.last_reason = "armed"

    def step(
        self,
        time_us: int,
        image_bgr: U8,
        R_world_body_ap: F64 | None,
        range_m: Mapping[int, float] | None = None,
    ) -> DposeResult | None:
        """The body's pose from one frame, or None (``last_reason`` says why)."""
        if self.pattern is None or self.T_world_pattern is None:
            self.last_reason = "not armed"
            return None
        pixels = detect_marks(image_bgr, self.detect_opts)
        priors = None
        if R_world_body_ap is not None and self.R_world_body_arm is not None:
            R_pattern_body = self.R_world_body_arm.T @ R_world_body_ap
            height = self._height(range_m, R_pattern_body)
            priors = Priors(
                R_pattern_body,
                self.tilt_sigma_rad,
                self.T_cam_body[:3, :3],
                self.T_cam_body[:3, 3],
                height,
                self.height_sigma_m,
                self.plane_normal,
                self.plane_offset,
            )
        sol, reason = solve(
            pixels, self.pattern, self.camera, self.T_cam_body[:3, :3], self.solve_opts, priors
        )
        self.last_reason = reason
        if sol is None:
            return None
        T_pattern_body = se3.inverse(sol.T_cam_pattern) @ self.T_cam_body
        return DposeResult(
            time_us, self.T_world_pattern @ T_pattern_body, T_pattern_body, sol.cov_6x6, sol
        )

    def _height(self, range_m: Mapping[int, float] | None, R_pattern_body: F64) -> float:
        """The body's height above the pattern plane [m] from the lasers' current readings
        (their hits are on the ground around the pattern), NaN without them."""
        if range_m is None:
            return float("nan")
        n_body = R_pattern_body.T @ self.plane_normal
        heights = [
            float((self.origins[k] + range_m[i] * self.beams[k]) @ n_body)
            for k, i in enumerate(self.ids)
            if i in range_m and np.isfinite(range_m[i])
        ]
        return float(np.median(heights)) if len(heights) >= 2 else float("nan")
