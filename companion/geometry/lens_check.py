"""Whether a camera's distortion model inverts over its whole image (checked at load).

The pipeline turns every tracked pixel into a ray by inverting the Brown-Conrady distortion
(``CameraModel.undistort_normalized``, Newton's method). A calibration whose model folds over
inside the image has no inverse there: two rays land on one pixel, Newton finds the wrong one
or none, and the VO stopped mid-run ("undistortion did not converge"). This module refuses
such a model when it is loaded, with the reason.

Maths (normalised coordinates x = X/Z, y = Y/Z, r = sqrt(x^2 + y^2); OpenCV's k1 k2 p1 p2 k3):

1. **Radial monotonicity.** The radial part maps r -> g(r) = r (1 + k1 r^2 + k2 r^4 + k3 r^6),
   g'(r) = 1 + 3 k1 r^2 + 5 k2 r^4 + 7 k3 r^6. The image's largest distorted radius is that of
   its farthest corner, r_d,max = max |((u - cx) / fx, (v - cy) / fy)| over the corners
   (u, v) = (-0.5 | W - 0.5, -0.5 | H - 0.5) [px]. The model inverts radially when g is strictly
   increasing on [0, r*] with g(r*) = r_d,max: we ask g'(r) >= MIN_RADIAL_SLOPE there (a pixel
   at the corner then spans at most 1 / MIN_RADIAL_SLOPE times the angle of a central one,
   and Newton's method converges quadratically). Barrel distortion k1 < 0 alone folds at
   r = 1 / sqrt(-3 k1), where g = (2/3) r: with k1 = -0.6 at r = 0.745, g = 0.497, short of
   a 640 x 480, f = 460 px image's corner (0.870).
2. **Round trip.** With the tangential terms (p1, p2) the map is not radial: every pixel of
   the image border (one per pixel, where the radius is largest) and of a 33 x 25 grid inside
   is undistorted by the pipeline's own Newton iteration, must converge (distort(undistort(x))
   = x to 1e-9) and land where the map's Jacobian determinant is positive (the unfolded
   sheet, not a solution beyond a fold).
"""

from __future__ import annotations

import numpy as np

from companion.errors import GeometryError
from companion.geometry.camera import CameraModel
from companion.types import F64

MIN_RADIAL_SLOPE = 0.05  # g'(r) below this inside the image: the model folds (or nearly)
MAX_UNDISTORTED_RADIUS = 20.0  # tan(87 deg): a pinhole model's corner beyond is not a lens
_RADIAL_STEPS = 20_000
_MIN_JACOBIAN_DET = 1e-3


def corner_radius(model: CameraModel) -> float:
    """The image's largest distorted normalised radius r_d,max (at its farthest corner)."""
    u = np.array([-0.5, model.width - 0.5])
    v = np.array([-0.5, model.height - 0.5])
    x = (u - model.cx) / model.fx
    y = (v - model.cy) / model.fy
    return float(np.sqrt(float(np.max(x * x)) + float(np.max(y * y))))


def radial_fold(model: CameraModel, r_d_max: float) -> str | None:
    """Why g(r) = r (1 + k1 r^2 + k2 r^4 + k3 r^6) does not invert on [0, r_d_max] (module
    docstring, 1.), or None when it does."""
    k1, k2, k3 = model.k1, model.k2, model.k3
    r = np.linspace(0.0, MAX_UNDISTORTED_RADIUS, _RADIAL_STEPS + 1)
    r2 = r * r
    g = r * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
    slope = 1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + r2 * 7.0 * k3))
    reached = np.flatnonzero(g >= r_d_max)
    end = int(reached[0]) if len(reached) else len(r) - 1
    low = np.flatnonzero(slope[: end + 1] < MIN_RADIAL_SLOPE)
    if len(low):
        i = int(low[0])
        peak = float(np.max(g[: end + 1]))
        return (
            f"the radial map r*(1+k1 r^2+k2 r^4+k3 r^6) stops increasing (slope "
            f"{slope[i]:.3f} < {MIN_RADIAL_SLOPE}) at r = {r[i]:.3f} (distorted {g[i]:.3f}), "
            f"inside the image (its corners reach {r_d_max:.3f}; the largest radius the model "
            f"reaches before that is {peak:.3f})"
        )
    if not len(reached):
        return (
            f"the radial map never reaches the image's corner radius {r_d_max:.3f} "
            f"(r up to {MAX_UNDISTORTED_RADIUS:g})"
        )
    return None


def _jacobian_det(model: CameraModel, xy: F64) -> F64:
    """Determinant (N,) of d distort / d (x, y) at undistorted normalised points (N, 2)."""
    x, y = xy[:, 0], xy[:, 1]
    k1, k2, k3, p1, p2 = model.k1, model.k2, model.k3, model.p1, model.p2
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    j11 = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
    j12 = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    j21 = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    j22 = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
    det: F64 = j11 * j22 - j12 * j21
    return det


def check_pixels(model: CameraModel) -> F64:
    """The pixels (N, 2) the round trip checks: the whole border (one per pixel, corners at
    -0.5 and size - 0.5) and a 33 x 25 grid inside."""
    w, h = model.width, model.height
    u = np.concatenate([np.arange(-0.5, w - 0.5), [w - 0.5]])
    v = np.concatenate([np.arange(-0.5, h - 0.5), [h - 0.5]])
    border = np.concatenate(
        [
            np.stack([u, np.full_like(u, -0.5)], axis=1),
            np.stack([u, np.full_like(u, h - 0.5)], axis=1),
            np.stack([np.full_like(v, -0.5), v], axis=1),
            np.stack([np.full_like(v, w - 0.5), v], axis=1),
        ]
    )
    gu, gv = np.meshgrid(np.linspace(0.0, w - 1.0, 33), np.linspace(0.0, h - 1.0, 25))
    grid = np.stack([gu.ravel(), gv.ravel()], axis=1)
    return np.concatenate([border, grid])


def _first_failing(model: CameraModel, uv: F64) -> tuple[float, float]:
    """The first pixel of ``uv`` (N, 2) whose undistortion raises (one exists)."""
    for u, v in uv:
        try:
            model.pixels_to_normalized(np.array([[u, v]]))
        except GeometryError:
            return float(u), float(v)
    return float("nan"), float("nan")


def lens_problem(model: CameraModel) -> str | None:
    """Why ``model`` cannot serve the pipeline over its whole image (module docstring), or
    None when it can: impossible intrinsics, a radial map that folds inside the image, or a
    pixel whose undistortion does not converge or lands beyond a fold."""
    try:
        model.validate()
    except GeometryError as e:
        return str(e)
    if not model.has_distortion:
        return None
    folded = radial_fold(model, corner_radius(model))
    if folded is not None:
        return folded
    uv = check_pixels(model)
    with np.errstate(all="ignore"):
        try:
            xy = model.pixels_to_normalized(uv)
        except GeometryError:
            u0, v0 = _first_failing(model, uv)
            return f"undistortion does not converge at pixel ({u0:.1f}, {v0:.1f})"
        det = _jacobian_det(model, xy)
    bad = np.flatnonzero(~(det > _MIN_JACOBIAN_DET))
    if len(bad):
        u0, v0 = uv[int(bad[0])]
        return f"the distortion folds over near pixel ({u0:.1f}, {v0:.1f})"
    return None
