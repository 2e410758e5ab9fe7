"""Pinhole camera with radial-tangential (Brown-Conrady) distortion, OpenCV conventions.

Camera frame: x right, y down, z along the optical axis. Pixel (u, v) = (column, row); the
centre of pixel (0, 0) is at (0.0, 0.0), as in OpenCV.

Distortion (thesis section 3.2.2; OpenCV's model with 5 coefficients k1 k2 p1 p2 k3), for
normalised coordinates x = X/Z, y = Y/Z and r^2 = x^2 + y^2:
    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y
    u = fx x_d + cx,  v = fy y_d + cy
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.errors import GeometryError
from companion.types import F64

B = NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class CameraModel:
    """Intrinsics [px] and distortion of one camera; image size (width x height) [px]."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    @property
    def K(self) -> F64:
        """Intrinsic matrix (3, 3)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> F64:
        """OpenCV distortion vector (5,) = (k1, k2, p1, p2, k3)."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def has_distortion(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return bool(np.any(self.dist_coeffs != 0.0))

    def distort(self, xy_norm: ArrayLike, k1: F64 | None = None) -> F64:
        """Undistorted normalised coordinates (N, 2) -> distorted normalised (N, 2); ``k1``
        (N,), when given, replaces the model's k1 point by point."""
        p = np.asarray(xy_norm, dtype=np.float64).reshape(-1, 2)
        x, y = p[:, 0], p[:, 1]
        r2 = x * x + y * y
        k1_ = self.k1 if k1 is None else k1
        radial = 1.0 + r2 * (k1_ + r2 * (self.k2 + r2 * self.k3))
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return np.stack([xd, yd], axis=1)

    def normalized_to_pixels(self, xy_norm: ArrayLike) -> F64:
        """Undistorted normalised coordinates (N, 2) -> pixels (N, 2), distortion applied."""
        d = self.distort(xy_norm)
        return np.stack([self.fx * d[:, 0] + self.cx, self.fy * d[:, 1] + self.cy], axis=1)

    def project(self, points_cam: ArrayLike, min_z: float = 1e-6) -> tuple[F64, B]:
        """Points in the camera frame (N, 3) [m] -> pixels (N, 2) and a mask (N,) of z > min_z.

        Pixels of points behind the camera are NaN.
        """
        P = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        in_front = P[:, 2] > min_z
        z = np.where(in_front, P[:, 2], 1.0)
        uv = self.normalized_to_pixels(P[:, :2] / z[:, None])
        uv[~in_front] = np.nan
        return uv, in_front

    def in_image(self, uv: ArrayLike, margin_px: float = 0.0) -> B:
        """Mask (N,) of pixels inside the image, at least margin_px from the border."""
        p = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            return np.asarray(
                (p[:, 0] >= -0.5 + margin_px)
                & (p[:, 0] <= self.width - 0.5 - margin_px)
                & (p[:, 1] >= -0.5 + margin_px)
                & (p[:, 1] <= self.height - 0.5 - margin_px),
                dtype=np.bool_,
            )

    def undistort_normalized(
        self,
        xy_dist: ArrayLike,
        iterations: int = 20,
        k1: F64 | None = None,
        nan_where_unconverged: bool = False,
    ) -> F64:
        """Distorted normalised (N, 2) -> undistorted normalised (N, 2) by Newton's method;
        ``k1`` (N,), when given, replaces the model's k1 point by point (the lens check's
        candidate lenses, companion/vo/focal_check.py).

        Converges to ~1e-14 for the distortion of real lenses within their image; raises
        GeometryError when it does not converge (distortion model not invertible there), or
        with ``nan_where_unconverged`` gives NaN rows for those points.
        """
        d = np.asarray(xy_dist, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion and k1 is None:
            return d.copy()
        # x and y as their own contiguous arrays (a tenth less time than columns of (N, 2));
        # the arithmetic is the same, term by term
        d_x, d_y = d[:, 0].copy(), d[:, 1].copy()
        x, y = d_x.copy(), d_y.copy()
        k1_: float | F64 = self.k1 if k1 is None else k1
        k2, k3, p1, p2 = self.k2, self.k3, self.p1, self.p2
        for _ in range(iterations if len(d) else 0):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1_ + r2 * (k2 + r2 * k3))
            dradial = k1_ + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
            fx_ = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - d_x
            fy_ = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - d_y
            j11 = radial + x * dradial * 2 * x + 2 * p1 * y + p2 * 6 * x
            j12 = x * dradial * 2 * y + 2 * p1 * x + p2 * 2 * y
            j21 = y * dradial * 2 * x + p1 * 2 * x + 2 * p2 * y
            j22 = radial + y * dradial * 2 * y + p1 * 6 * y + 2 * p2 * x
            det = j11 * j22 - j12 * j21
            step_x = (j22 * fx_ - j12 * fy_) / det
            step_y = (-j21 * fx_ + j11 * fy_) / det
            x -= step_x
            y -= step_y
            # the largest step (NaN if any is: then no convergence is claimed)
            if float(np.maximum(np.abs(step_x).max(), np.abs(step_y).max())) < 1e-15:
                break
        p = np.column_stack([x, y])
        residual = self.distort(p, k1) - d
        if nan_where_unconverged:
            with np.errstate(invalid="ignore"):
                p[~(np.abs(residual) <= 1e-9).all(axis=1)] = np.nan
            return p
        if not np.all(np.isfinite(residual)) or float(np.max(np.abs(residual), initial=0)) > 1e-9:
            raise GeometryError("undistortion did not converge (point outside the lens model)")
        return p

    def pixels_to_normalized(self, uv: ArrayLike) -> F64:
        """Pixels (N, 2) -> undistorted normalised coordinates (N, 2)."""
        p = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        xd = np.stack([(p[:, 0] - self.cx) / self.fx, (p[:, 1] - self.cy) / self.fy], axis=1)
        return self.undistort_normalized(xd)

    def pixels_to_rays(self, uv: ArrayLike) -> F64:
        """Pixels (N, 2) -> unit ray directions in the camera frame (N, 3)."""
        n = self.pixels_to_normalized(uv)
        rays = np.concatenate([n, np.ones((n.shape[0], 1))], axis=1)
        return np.asarray(rays / np.linalg.norm(rays, axis=1, keepdims=True), dtype=np.float64)

    def pixel_rays(self) -> F64:
        """Unit rays through every pixel centre, (H, W, 3) in the camera frame."""
        u, v = np.meshgrid(
            np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64)
        )
        uv = np.stack([u.ravel(), v.ravel()], axis=1)
        return self.pixels_to_rays(uv).reshape(self.height, self.width, 3)

    def validate(self) -> None:
        """Raise GeometryError for impossible intrinsics."""
        vals = [self.fx, self.fy, self.cx, self.cy, *self.dist_coeffs]
        if not all(np.isfinite(vals)):
            raise GeometryError("camera intrinsics must be finite")
        if self.width <= 0 or self.height <= 0 or self.fx <= 0 or self.fy <= 0:
            raise GeometryError("camera size and focal lengths must be positive")
