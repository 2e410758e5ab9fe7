"""M-MSC fusion: maximum likelihood over several sensors' MSC measurements.

For independent Gaussian measurements s_i with sigmas sigma_i, the ML estimate is the
inverse-variance weighted mean with sigma = (sum 1/sigma_i^2)^(-1/2). To be robust to a sensor
that sees a wall edge or a bad match, measurements further than k sigmas (with a floor of 2 %
of the scale) from the weighted median are dropped first.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from companion.types import F64


def weighted_median(values: F64, weights: F64) -> float:
    """Median of values (N,) with non-negative weights (N,)."""
    order = np.argsort(values)
    v = values[order]
    c = np.cumsum(weights[order])
    return float(v[np.searchsorted(c, 0.5 * c[-1])])


def fuse(
    scales: F64, sigmas: F64, outlier_sigmas: float = 3.0
) -> tuple[float, float, NDArray[np.bool_]] | None:
    """(scale, sigma, used mask) of the robust ML fusion, or None without measurements."""
    s = np.asarray(scales, dtype=np.float64)
    sg = np.asarray(sigmas, dtype=np.float64)
    ok = np.isfinite(s) & np.isfinite(sg) & (sg > 0) & (s > 0)
    if not ok.any():
        return None
    w = np.where(ok, 1.0 / np.where(ok, sg, 1.0) ** 2, 0.0)
    med = weighted_median(np.where(ok, s, 0.0), w)
    tol = outlier_sigmas * np.maximum(sg, 0.02 * med)
    used = ok & (np.abs(s - med) <= tol)
    if not used.any():
        return None
    wu = w * used
    scale = float(np.sum(wu * s) / np.sum(wu))
    return scale, float(1.0 / np.sqrt(np.sum(wu))), used
