"""What ``companion calibrate`` shows of its results: the intrinsics summary, the corner
coverage image and the laser-check overlays. Arrays in, text or images out; no file I/O."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from companion.calibration_maths.board import BoardSpec
from companion.calibration_maths.intrinsics import COVERAGE_GRID, IntrinsicsResult
from companion.calibration_maths.lasers import LaserCheckReport, LaserFrame, Verdict


def coverage_image(result: IntrinsicsResult, views: list[Any]) -> Any:
    """Every used corner over the image frame, one colour per view, empty cells shaded."""
    c = result.camera
    img = np.full((c.height, c.width, 3), 255, dtype=np.uint8)
    gx, gy = COVERAGE_GRID
    seen = np.zeros((gy, gx), dtype=bool)
    for v in views:
        p = v.image_points_px
        i = np.clip(((p[:, 0] + 0.5) * gx / c.width).astype(int), 0, gx - 1)
        j = np.clip(((p[:, 1] + 0.5) * gy / c.height).astype(int), 0, gy - 1)
        seen[j, i] = True
    for j in range(gy):
        for i in range(gx):
            if not seen[j, i]:
                x0, y0 = i * c.width // gx, j * c.height // gy
                x1, y1 = (i + 1) * c.width // gx, (j + 1) * c.height // gy
                img[y0:y1, x0:x1] = (205, 205, 255)
    for k in range(1, gx):
        cv2.line(img, (k * c.width // gx, 0), (k * c.width // gx, c.height), (200, 200, 200))
    for k in range(1, gy):
        cv2.line(img, (0, k * c.height // gy), (c.width, k * c.height // gy), (200, 200, 200))
    rng = np.random.default_rng(0)
    for v in views:
        colour = tuple(int(x) for x in rng.integers(0, 200, 3))
        for u, w in v.image_points_px:
            cv2.circle(img, (int(round(u)), int(round(w))), 2, colour, -1)
    return img


def intrinsics_summary(r: IntrinsicsResult, found: int, total: int, spec: BoardSpec) -> str:
    c, s = r.camera, r.std
    e = r.view_rms_px
    worst = sorted(zip(r.view_names, e, strict=True), key=lambda x: -x[1])[:3]
    lines = [
        f"board {spec.text()} found in {found} of {total} images; {len(r.view_names)} views "
        f"used, {r.n_corners} corners",
        f"fx {c.fx:9.3f} ± {s[0]:.3f}   fy {c.fy:9.3f} ± {s[1]:.3f}   [px]",
        f"cx {c.cx:9.3f} ± {s[2]:.3f}   cy {c.cy:9.3f} ± {s[3]:.3f}   [px]",
        "k1 k2 p1 p2 k3 "
        + "  ".join(f"{v:+.5f} ± {sd:.5f}" for v, sd in zip(c.dist_coeffs, s[4:], strict=True)),
        f"RMS {r.rms_px:.3f} px (views {e.min():.3f}-{e.max():.3f}; worst "
        + ", ".join(f"{n} {v:.3f}" for n, v in worst)
        + f"); coverage {100 * r.coverage:.0f} % of the image; "
        f"tilts {r.tilt_deg.min():.0f}-{r.tilt_deg.max():.0f} deg",
    ]
    lines.extend(f"dropped {n}: RMS {v:.3f} px" for n, v in r.dropped)
    lines.extend(f"warning: {w}" for w in r.warnings)
    return "\n".join(lines)


def laser_overlay(frame: LaserFrame, report: LaserCheckReport) -> Any:
    """The image with each sensor's predicted dot (green cross) and matched dot (yellow
    circle), joined by a line, labelled with the sensor id."""
    img = frame.image_bgr.copy()
    for s in report.sensors:
        for o in s.observations:
            if o.image != frame.name:
                continue
            pu, pv = (int(round(x)) for x in o.predicted_px)
            colour = (0, 200, 0) if s.verdict is Verdict.OK else (0, 140, 255)
            cv2.drawMarker(img, (pu, pv), colour, cv2.MARKER_CROSS, 14, 1)
            cv2.putText(img, str(s.sensor_id), (pu + 6, pv - 6), cv2.FONT_HERSHEY_SIMPLEX,
                        0.45, colour, 1, cv2.LINE_AA)  # fmt: skip
            if o.found:
                du, dv = (int(round(x)) for x in o.detected_px)
                cv2.circle(img, (du, dv), 6, (0, 255, 255), 1, cv2.LINE_AA)
                cv2.line(img, (pu, pv), (du, dv), (0, 255, 255), 1, cv2.LINE_AA)
    return img
