"""Red laser marks in a colour image, with sub-pixel centres (pure).

Redness r = max(R - max(G, B), 0) (8-bit) is high for a red laser dot and low for grass,
gravel, asphalt and most bricks (whose red excess stays below ~90 levels in our textures and in
daylight photographs). Pixels above ``threshold`` form connected blobs; a blob is a mark when
its area is plausible for a dot (blur spreads it, so up to ``max_area_px``) and its peak is
well above the threshold. The centre is the redness-weighted centroid of the blob's pixels
above threshold (sub-pixel; exact for a symmetric spot).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.types import F64

U8 = NDArray[np.uint8]


@dataclass(frozen=True, slots=True)
class DetectOptions:
    """Thresholds of the red-dot detector."""

    threshold: int = 90  # redness R - max(G, B) of a dot's pixels [8-bit levels]
    min_peak: int = 120  # a blob's brightest redness
    min_area_px: int = 1
    max_area_px: int = 400


def redness(image_bgr: U8) -> U8:
    """max(R - max(G, B), 0) per pixel (H, W), uint8 (saturating OpenCV arithmetic)."""
    b, g, r = cv2.split(image_bgr)
    out: U8 = cv2.subtract(r, cv2.max(g, b))
    return out


def detect_marks(image_bgr: U8, opts: DetectOptions | None = None) -> F64:
    """Centres (N, 2) [px, distorted image coordinates] of the red marks, brightest first."""
    o = opts or DetectOptions()
    red = redness(image_bgr)
    _, mask = cv2.threshold(red, o.threshold, 1, cv2.THRESH_BINARY)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    found: list[tuple[float, float, float]] = []
    for k in range(1, n):
        area = int(stats[k, cv2.CC_STAT_AREA])
        if not o.min_area_px <= area <= o.max_area_px:
            continue
        x0, y0 = int(stats[k, cv2.CC_STAT_LEFT]), int(stats[k, cv2.CC_STAT_TOP])
        w, h = int(stats[k, cv2.CC_STAT_WIDTH]), int(stats[k, cv2.CC_STAT_HEIGHT])
        if x0 == 0 or y0 == 0 or x0 + w == red.shape[1] or y0 + h == red.shape[0]:
            continue  # cut by the image's edge: its centroid is pulled inwards
        sub = red[y0 : y0 + h, x0 : x0 + w].astype(np.float64)
        lab = labels[y0 : y0 + h, x0 : x0 + w] == k
        peak = float(sub[lab].max())
        if peak < o.min_peak:
            continue
        wgt = np.where(lab, sub - o.threshold, 0.0)
        total = float(wgt.sum())
        ys, xs = np.mgrid[y0 : y0 + h, x0 : x0 + w]
        found.append((float((wgt * xs).sum() / total), float((wgt * ys).sum() / total), peak))
    found.sort(key=lambda f: -f[2])
    return np.array([(x, y) for x, y, _ in found], dtype=np.float64).reshape(-1, 2)
