"""Roll/pitch accuracy: RMSE in degrees against ground truth (docs/methods.md)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.types import F64


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


def rmse_summary(
    time_s: F64, est_rad: F64, truth_rad: F64, settle_s: float = 5.0
) -> dict[str, float]:
    """Roll, pitch and combined RMSE [deg] of one (F, 2) estimate after settle_s [s] (time_s
    from the start), its availability, and for runs of two minutes or more the RMSE of the
    first and the last minute."""
    e = angle_errors(est_rad, truth_rad, time_s >= settle_s)
    row = {
        "roll_rmse_deg": e.roll_rmse_deg,
        "pitch_rmse_deg": e.pitch_rmse_deg,
        "rmse_deg": e.rmse_deg,
        "available": e.available,
    }
    if time_s[-1] >= 120.0:
        first = (time_s >= settle_s) & (time_s < 60.0)
        row["first_min_rmse_deg"] = angle_errors(est_rad, truth_rad, first).rmse_deg
        last = time_s >= time_s[-1] - 60.0
        row["last_min_rmse_deg"] = angle_errors(est_rad, truth_rad, last).rmse_deg
    return row


# the studies of `companion eval --attitude --study`: sensor spacing [m], range noise sigma [m]
SPACING_STUDY_M = tuple(np.round(np.arange(0.1, 1.01, 0.1), 2))
SIGMA_STUDY_M = (0.0, 0.005, 0.01, 0.02, 0.05, 0.1)


def range_tilt_rmse(
    series: Mapping[str, F64],
    truth_rad: F64,
    mask: NDArray[np.bool_],
    sigma_m: float,
    spacing_m: float,
) -> dict[str, float]:
    """One point of a study: the RMSE [deg] of the range tilts ("ground", "gravity" of
    ``series``, (F, 2) [rad]) over ``mask``, and the single-sample bound of sensors
    spacing_m apart with noise sigma_m ("bound")."""
    vals = {n: angle_errors(series[n], truth_rad, mask).rmse_deg for n in ("ground", "gravity")}
    vals["bound"] = single_sample_bound_deg(sigma_m, spacing_m)
    return vals
