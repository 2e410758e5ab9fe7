"""Camera intrinsics and distortion from views of a planar board (pure).

Model: :class:`companion.geometry.camera.CameraModel`, i.e. OpenCV's pinhole with the five
coefficients k1 k2 p1 p2 k3 (no rational or thin-prism terms), so the result pastes into the
``[camera]`` table unchanged. Method: Zhang's planar calibration (Zhang, "A flexible new
technique for camera calibration", PAMI 2000) as implemented by ``cv2.calibrateCameraExtended``:
a closed-form start from the board homographies, then Levenberg-Marquardt on the reprojection
error over the intrinsics and every view's pose ``T_cam_board``.

Figures reported (all in pixels unless named otherwise):
- ``rms_px``: sqrt(mean over every corner of |observed - projected|^2) — below ~0.3 px for a
  good board and sharp images, ~0.5 px is acceptable, above 1 px something is wrong;
- per-view RMS, the same over one image's corners; a view far above the others (blur, a
  misdetection, a board that is not flat) is dropped once and the calibration re-run;
- standard deviations of fx fy cx cy k1 k2 p1 p2 k3 from OpenCV's covariance estimate
  (sigma^2 (J^T J)^-1 with sigma^2 the residual variance): they shrink with more, and more
  varied, views;
- coverage: the fraction of an 8 x 6 grid of image cells that hold at least one corner. The
  distortion is only measured where corners were seen; elsewhere it is extrapolated.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.calibration_maths.board import BoardView
from companion.errors import CalibrationError, NotEnoughViewsError
from companion.geometry import se3, so3
from companion.geometry.camera import CameraModel
from companion.options import opt
from companion.types import F64

PARAM_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
COVERAGE_GRID = (8, 6)  # image cells across and down for the coverage figure


@dataclass(frozen=True, slots=True)
class IntrinsicsOptions:
    """Intrinsic calibration settings (``companion calibrate intrinsics`` flags)."""

    min_views: int = opt(8, "usable board views needed; fewer is refused", ge=3, le=1000)
    max_view_rms_px: float = opt(
        1.0, "drop (once) views whose RMS exceeds this and twice the median [px]", gt=0
    )
    fix_k3: bool = opt(False, "keep k3 = 0 (little distortion, or views only near the centre)")
    fix_tangential: bool = opt(False, "keep p1 = p2 = 0")
    min_coverage: float = opt(
        0.6, "warn when corners cover less of the image than this (8x6 cells)", ge=0, le=1
    )
    min_tilted_views: int = opt(
        3, "warn when fewer views are tilted >= 20 deg (focal length poorly fixed)", ge=0
    )


@dataclass(frozen=True, slots=True)
class IntrinsicsResult:
    """A calibration: ``camera`` (the model), ``rms_px`` over all used corners, per-view
    ``view_rms_px`` (V,), ``std`` (9,) standard deviations of PARAM_NAMES (units of each
    parameter), ``T_cam_board`` (V, 4, 4) board -> camera per view, ``tilt_deg`` (V,) angle
    between the board normal and the optical axis, ``dropped`` (name, rms_px) of views left
    out, ``coverage`` in [0, 1], ``warnings`` for the user."""

    camera: CameraModel
    rms_px: float
    view_names: tuple[str, ...]
    view_rms_px: F64
    view_corners: tuple[int, ...]
    std: F64
    T_cam_board: F64
    tilt_deg: F64
    dropped: tuple[tuple[str, float], ...]
    coverage: float
    warnings: tuple[str, ...]

    @property
    def n_corners(self) -> int:
        """Corners used over every view."""
        return int(sum(self.view_corners))

    def camera_toml(self) -> str:
        """A ``[camera]`` snippet for the config (width, height, fx, fy, cx, cy, dist), with the
        standard deviations and RMS as comments."""
        c, s = self.camera, dict(zip(PARAM_NAMES, self.std, strict=True))
        dist = ", ".join(f"{v:.6g}" for v in c.dist_coeffs)
        dist_sd = ", ".join(f"{s[n]:.2g}" for n in ("k1", "k2", "p1", "p2", "k3"))
        return "\n".join(
            [
                f"# companion calibrate intrinsics: {len(self.view_names)} views, "
                f"{self.n_corners} corners, RMS {self.rms_px:.3f} px",
                "# paste over the same keys of your [camera] table (keep [camera.mount])",
                "[camera]",
                f"width = {c.width}",
                f"height = {c.height}",
                f"fx = {c.fx:.4f}  # ± {s['fx']:.2f}",
                f"fy = {c.fy:.4f}  # ± {s['fy']:.2f}",
                f"cx = {c.cx:.4f}  # ± {s['cx']:.2f}",
                f"cy = {c.cy:.4f}  # ± {s['cy']:.2f}",
                f"dist = [{dist}]  # k1 k2 p1 p2 k3, ± [{dist_sd}]",
                "",
            ]
        )

    def report(self) -> dict[str, Any]:
        """Everything as plain JSON-able values."""
        c = self.camera
        return {
            "image_size": [c.width, c.height],
            "camera": {
                "fx": c.fx,
                "fy": c.fy,
                "cx": c.cx,
                "cy": c.cy,
                "dist": [float(v) for v in c.dist_coeffs],
            },
            "std": {n: float(v) for n, v in zip(PARAM_NAMES, self.std, strict=True)},
            "rms_px": self.rms_px,
            "views_used": len(self.view_names),
            "corners_used": self.n_corners,
            "coverage": self.coverage,
            "views": [
                {"image": n, "rms_px": float(e), "corners": k, "tilt_deg": float(t)}
                for n, e, k, t in zip(
                    self.view_names,
                    self.view_rms_px,
                    self.view_corners,
                    self.tilt_deg,
                    strict=True,
                )
            ],
            "dropped": [{"image": n, "rms_px": e} for n, e in self.dropped],
            "warnings": list(self.warnings),
        }


def coverage(
    points_px: F64, width: int, height: int, grid: tuple[int, int] = COVERAGE_GRID
) -> float:
    """Fraction of the grid's image cells holding at least one of ``points_px`` (N, 2)."""
    gx, gy = grid
    p = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    i = np.clip(np.floor((p[:, 0] + 0.5) * gx / width), 0, gx - 1).astype(int)
    j = np.clip(np.floor((p[:, 1] + 0.5) * gy / height), 0, gy - 1).astype(int)
    return len(set(zip(i.tolist(), j.tolist(), strict=True))) / (gx * gy)


def _flags(opts: IntrinsicsOptions) -> int:
    flags = 0
    if opts.fix_k3:
        flags |= cv2.CALIB_FIX_K3
    if opts.fix_tangential:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    return flags


def _solve(
    views: Sequence[BoardView], size: tuple[int, int], flags: int
) -> tuple[float, F64, F64, list[F64], F64, F64]:
    """calibrateCameraExtended: rms, K (3, 3), dist (5,), T_cam_board list, std (9,), per-view."""
    obj = [v.object_points_m.astype(np.float32).reshape(-1, 1, 3) for v in views]
    img = [v.image_points_px.astype(np.float32).reshape(-1, 1, 2) for v in views]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        rms, K, dist, rvecs, tvecs, std_in, _, per_view = cv2.calibrateCameraExtended(
            obj, img, size, None, None, flags=flags, criteria=criteria
        )
    except cv2.error as e:
        raise CalibrationError(f"OpenCV could not calibrate these views: {e}") from None
    T = [se3.make(so3.exp(np.ravel(r)), np.ravel(t)) for r, t in zip(rvecs, tvecs, strict=True)]
    d = np.zeros(5)
    dv = np.ravel(dist)
    d[: min(5, len(dv))] = dv[:5]
    std = np.ravel(std_in)[:9].astype(np.float64)
    return (
        float(rms),
        np.asarray(K, np.float64),
        d,
        T,
        std,
        np.ravel(per_view).astype(np.float64),
    )


def calibrate_intrinsics(
    views: Sequence[BoardView],
    image_size: tuple[int, int],
    opts: IntrinsicsOptions | None = None,
) -> IntrinsicsResult:
    """Calibrate from ``views`` of one board in images of ``image_size`` = (width, height) [px].

    Raises NotEnoughViewsError with fewer than ``opts.min_views`` views (before or after
    dropping bad ones) and CalibrationError when OpenCV fails.
    """
    o = opts or IntrinsicsOptions()
    width, height = image_size
    views = list(views)
    if len(views) < o.min_views:
        raise NotEnoughViewsError(
            f"only {len(views)} usable view(s) of the board, {o.min_views} needed: take more "
            "pictures (15-25 is good), the board tilted 20-45 degrees in varied directions and "
            "reaching every part of the image, corners included"
        )
    flags = _flags(o)
    rms, K, dist, T, std, per_view = _solve(views, (width, height), flags)
    dropped: list[tuple[str, float]] = []
    bad = per_view > max(o.max_view_rms_px, 2.0 * float(np.median(per_view)))
    if bad.any() and len(views) - int(bad.sum()) >= o.min_views:
        dropped = [(v.name, float(e)) for v, e, b in zip(views, per_view, bad, strict=True) if b]
        views = [v for v, b in zip(views, bad, strict=True) if not b]
        rms, K, dist, T, std, per_view = _solve(views, (width, height), flags)
    camera = CameraModel(
        width, height, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
        *(float(v) for v in dist),
    )  # fmt: skip
    T_cam_board = np.stack(T)
    # board normal (board z) in the camera vs the optical axis: 0 deg = facing the camera
    tilt = np.degrees(np.arccos(np.clip(np.abs(T_cam_board[:, 2, 2]), 0.0, 1.0)))
    cover = coverage(np.concatenate([v.image_points_px for v in views]), width, height)
    warnings = _warnings(camera, rms, std, tilt, cover, o)
    return IntrinsicsResult(
        camera=camera,
        rms_px=rms,
        view_names=tuple(v.name for v in views),
        view_rms_px=per_view,
        view_corners=tuple(len(v.image_points_px) for v in views),
        std=std,
        T_cam_board=T_cam_board,
        tilt_deg=tilt,
        dropped=tuple(dropped),
        coverage=cover,
        warnings=tuple(warnings),
    )


def _warnings(
    camera: CameraModel,
    rms_px: float,
    std: F64,
    tilt_deg: F64,
    cover: float,
    o: IntrinsicsOptions,
) -> list[str]:
    out = []
    if rms_px > 0.5:
        out.append(
            f"RMS {rms_px:.2f} px is high (< 0.3 px is good): blurred or badly exposed images, "
            "a board that is not flat, or a lens the 5-coefficient model does not fit"
        )
    if cover < o.min_coverage:
        out.append(
            f"the corners cover only {100 * cover:.0f} % of the image: add views with the board "
            "near the edges and corners of the image, where the distortion is largest"
        )
    tilted = int(np.sum(tilt_deg >= 20.0))
    if tilted < o.min_tilted_views:
        out.append(
            f"only {tilted} view(s) tilted 20 degrees or more: the focal length is poorly "
            "determined from boards facing the camera; tilt the board 20-45 degrees"
        )
    rel_f = max(std[0] / camera.fx, std[1] / camera.fy)
    if math.isfinite(rel_f) and rel_f > 0.005:
        out.append(
            f"focal length uncertain to {100 * rel_f:.2f} % (1 sigma): add more varied views"
        )
    return out
