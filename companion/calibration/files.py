"""The file side of ``companion calibrate``: image folders and the laser check's ranges file.

Image folder: every ``*.png``, ``*.jpg``, ``*.jpeg``, ``*.bmp``, ``*.tif``, ``*.tiff`` directly
in the folder, in name order; all of one size.

Ranges file (``ranges.csv`` in the image folder unless given), one row per image and sensor::

    # comment lines start with '#'
    image,sensor_id,range_m
    img_000.png,0,2.513
    img_000.png,1,2.498
    img_001.png,0,1.874

``image`` is a file name in the folder, ``sensor_id`` the ``[[rangefinders]]`` id (the
DISTANCE_SENSOR id), ``range_m`` the reading [m] taken while that image was exposed (hold the
vehicle still). A sensor without a reading for an image is simply absent. Images without any
row are not used.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.calibration_maths.lasers import LaserFrame
from companion.errors import CalibrationError

U8 = NDArray[np.uint8]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
RANGES_HEADER = ("image", "sensor_id", "range_m")


def list_images(folder: Path) -> list[Path]:
    """The images of ``folder`` in name order; CalibrationError when there is none."""
    if not folder.is_dir():
        raise CalibrationError(f"{folder}: no such folder")
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not paths:
        raise CalibrationError(
            f"{folder}: no images ({', '.join(s[1:] for s in IMAGE_SUFFIXES)}) in this folder"
        )
    return paths


def read_image(path: Path, size: tuple[int, int] | None = None) -> U8:
    """A BGR image (H, W, 3) uint8; CalibrationError when unreadable or not ``size`` (W, H)."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise CalibrationError(f"{path}: not a readable image")
    h, w = img.shape[:2]
    if size is not None and (w, h) != size:
        raise CalibrationError(
            f"{path}: {w}x{h} px, but the other images are {size[0]}x{size[1]}: calibrate one "
            "camera mode at a time"
        )
    return np.asarray(img, dtype=np.uint8)


def read_ranges(path: Path) -> dict[str, dict[int, float]]:
    """Ranges file -> {image name: {sensor_id: range_m}}; errors name the file and line."""
    if not path.is_file():
        raise CalibrationError(
            f"{path}: no ranges file (CSV with columns {','.join(RANGES_HEADER)}; see "
            "docs/install.md, Calibration)"
        )
    out: dict[str, dict[int, float]] = {}
    with path.open(newline="") as fh:
        # comment lines become empty rows, so that reader.line_num is the file's line number
        rows = csv.reader("\n" if line.lstrip().startswith("#") else line for line in fh)
        header = next((row for row in rows if any(c.strip() for c in row)), None)
        if header is None or tuple(h.strip() for h in header) != RANGES_HEADER:
            raise CalibrationError(
                f"{path}: the first row must be {','.join(RANGES_HEADER)}, got {header}"
            )
        for row in rows:
            n = rows.line_num
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != 3:
                raise CalibrationError(f"{path}: line {n}: expected 3 values, got {row}")
            name, sid_text, range_text = (c.strip() for c in row)
            try:
                sid, range_m = int(sid_text), float(range_text)
            except ValueError:
                raise CalibrationError(
                    f"{path}: line {n}: sensor_id must be an integer and range_m a number, "
                    f"got {row}"
                ) from None
            if not math.isfinite(range_m) or range_m <= 0:
                raise CalibrationError(f"{path}: line {n}: range_m must be > 0, got {row}")
            per_image = out.setdefault(name, {})
            if sid in per_image:
                raise CalibrationError(f"{path}: line {n}: second reading of {sid} for {name}")
            per_image[sid] = range_m
    if not out:
        raise CalibrationError(f"{path}: no readings")
    return out


def read_laser_frames(folder: Path, ranges_file: Path | None = None) -> list[LaserFrame]:
    """The images of ``folder`` named in its ranges file, with their readings."""
    images = {p.name: p for p in list_images(folder)}
    ranges = read_ranges(ranges_file or folder / "ranges.csv")
    missing = sorted(set(ranges) - set(images))
    if missing:
        raise CalibrationError(
            f"{folder}: the ranges file names image(s) not in the folder: {', '.join(missing[:5])}"
        )
    frames = []
    size: tuple[int, int] | None = None
    for name in sorted(ranges):
        img = read_image(images[name], size)
        size = (img.shape[1], img.shape[0])
        frames.append(LaserFrame(name, img, ranges[name]))
    return frames


def write_laser_frames(folder: Path, frames: Iterable[LaserFrame]) -> Path:
    """Write images (PNG) and ``ranges.csv`` in the format :func:`read_laser_frames` reads."""
    folder.mkdir(parents=True, exist_ok=True)
    rows: list[tuple[str, int, str]] = []
    for f in frames:
        if not cv2.imwrite(str(folder / f.name), f.image_bgr):
            raise CalibrationError(f"{folder / f.name}: cannot write")
        rows.extend((f.name, sid, f"{d:.4f}") for sid, d in sorted(f.ranges_m.items()))
    path = folder / "ranges.csv"
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(RANGES_HEADER)
        w.writerows(rows)
    return path
