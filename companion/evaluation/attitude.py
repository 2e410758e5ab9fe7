"""Roll/pitch accuracy: RMSE in degrees against ground truth (DESIGN.md section 5)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


def wrap_rad(angle: F64) -> F64:
    """Angles wrapped to [-pi, pi)."""
    return np.asarray((angle + np.pi) % (2 * np.pi) - np.pi, dtype=np.float64)


@dataclass(frozen=True, slots=True)
class AngleErrors:
    """RMSE [deg] of roll and pitch, and the share of frames with an estimate."""

    roll_rmse_deg: float
    pitch_rmse_deg: float
    available: float

    @property
    def rmse_deg(self) -> float:
        """RMSE over both angles [deg]."""
        return float(np.sqrt(0.5 * (self.roll_rmse_deg**2 + self.pitch_rmse_deg**2)))


def angle_errors(
    est_rad: F64, truth_rad: F64, mask: NDArray[np.bool_] | None = None
) -> AngleErrors:
    """Errors of (F, 2) roll/pitch estimates [rad] (NaN = none) against the truth (F, 2),
    over the frames selected by ``mask``."""
    sel = np.ones(len(est_rad), dtype=bool) if mask is None else mask
    e = np.degrees(wrap_rad(est_rad[sel] - truth_rad[sel]))
    ok = np.all(np.isfinite(e), axis=1)
    if not ok.any():
        return AngleErrors(float("nan"), float("nan"), 0.0)
    rmse = np.sqrt(np.mean(e[ok] ** 2, axis=0))
    return AngleErrors(float(rmse[0]), float(rmse[1]), float(ok.mean()))


def single_sample_bound_deg(sigma_m: float, spacing_m: float) -> float:
    """The single-sample sigma [deg] of a tilt from two readings spacing_m apart with noise
    sigma_m each: sigma sqrt(2) / L (small angles); also each axis of an equilateral triangle
    of side L over a level plane."""
    return float(np.degrees(sigma_m * np.sqrt(2.0) / spacing_m))
