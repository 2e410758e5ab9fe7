"""Write our format frame by frame (``DatasetWriter``, the flight recorder's) and poses in
the published.csv layout."""

from __future__ import annotations

import csv
import datetime
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.config import Config, to_dict
from companion.drivers.dataset.format import (
    ALGORITHM_SECTIONS,
    ATTITUDE_COLUMNS,
    FED,
    FORMAT_NAME,
    FORMAT_VERSION,
    IMU_COLUMNS,
    IMU_GYRO_COLUMNS,
    IMU_MAG_COLUMNS,
    PUBLISHED_COLUMNS,
    RANGE_COLUMNS,
)
from companion.drivers.dataset.toml_text import toml_dumps
from companion.drivers.files import atomic_write, open_new
from companion.errors import DatasetError
from companion.types import (
    AttitudeSample,
    CameraFrame,
    ImuSample,
    PoseEstimate,
    RangeSample,
)


def _num(v: float) -> str:
    """A float as its shortest exact text (reads back to the same double)."""
    return repr(float(v))


def _pose_row(pose: PoseEstimate) -> list[Any]:
    return [
        pose.time_us,
        *map(_num, pose.position_ned_m),
        *map(_num, pose.quat_wxyz_ned_frd),
        *map(_num, pose.velocity_ned_m_s),
        pose.reset_counter,
        pose.quality_pct,
    ]


def write_poses_csv(path: Path, poses: Sequence[PoseEstimate]) -> None:
    """Poses in the published.csv layout, floats as their exact shortest text."""
    with path.open("w") as fh:
        fh.write(",".join(PUBLISHED_COLUMNS) + "\n")
        for p in poses:
            fh.write(",".join(str(v) for v in _pose_row(p)) + "\n")


def png_params(level: int) -> list[int]:
    """cv2.imencode parameters of a PNG compression level: 0 stored; 1 the Sub filter with
    Huffman coding only (a camera image with sensor noise: 83 % of raw at a third of zlib
    level 1's time, docs/BENCHMARKS.md); 2..9 zlib's levels with adaptive filters."""
    if level == 1:
        return [
            cv2.IMWRITE_PNG_COMPRESSION,
            1,
            cv2.IMWRITE_PNG_STRATEGY,
            cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
            cv2.IMWRITE_PNG_FILTER,
            cv2.IMWRITE_PNG_FILTER_SUB,
        ]
    return [cv2.IMWRITE_PNG_COMPRESSION, level]


def calibration_tables(config: Config) -> dict[str, Any]:
    """calibration.toml of a dataset as plain data: the ``[camera]`` table and the
    ``[[rangefinders]]`` in our config schema, and ``[matrices]`` repeating every mount as a
    4x4 T_body_sensor (row-major lists) for other tools."""
    mounts = {
        f"T_body_rf{r.sensor_id}": r.mount.T_body_sensor().tolist() for r in config.rangefinders
    }
    return {
        "camera": to_dict(config.camera),
        "rangefinders": to_dict(config.rangefinders),
        "matrices": {"T_body_cam": config.camera.T_body_cam().tolist(), **mounts},
    }


class DatasetWriter:
    """Our format written frame by frame, append-only (the flight recorder's writer).

    Per frame, in this order: its image file, the samples fed before it (ranges.csv and
    attitude.csv rows with ``fed_before_frame`` = the frame's index), then its frames.csv row;
    every file is flushed after each frame, so a process killed at any point (SIGKILL) leaves
    every frame listed in frames.csv complete, and the reader leaves out a torn last row.
    meta.toml says ``complete = false`` until :meth:`close` rewrites it (atomically). Floats
    are written as their shortest exact text, images losslessly as PNG (or JPEG when asked):
    the replay of a PNG recording is fed exactly what the pipeline was fed. Not thread-safe:
    one thread writes.
    """

    def __init__(
        self,
        path: Path,
        config: Config,
        *,
        image_format: str = "png",
        png_compression: int = 1,
        jpg_quality: int = 95,
        software: str = "",
    ) -> None:
        if path.exists() and (not path.is_dir() or any(path.iterdir())):
            raise DatasetError(f"{path} exists and is not an empty folder")
        if image_format not in ("png", "jpg"):
            raise DatasetError(f"image format must be png or jpg, got {image_format!r}")
        path.mkdir(parents=True, exist_ok=True)
        (path / "images").mkdir()  # new: never a planted link
        self.path = path
        self.image_format = image_format
        self._encode_params = (
            png_params(png_compression)
            if image_format == "png"
            else [cv2.IMWRITE_JPEG_QUALITY, jpg_quality]
        )
        self.frames = 0
        self.poses = 0
        self.bytes_written = 0
        self.meta: dict[str, Any] = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "software": software,
            "source": "recorder",
            "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "clock": "time_us: the recording machine's monotonic clock (the pipeline's)",
            "world": "none",
            "ingest_order": True,
            "frames_checked": True,
            "image_format": image_format,
            "complete": False,
        }
        self._write_small("meta.toml", self.meta)
        self._write_small("calibration.toml", calibration_tables(config))
        self._write_small(
            "config.toml", {k: to_dict(getattr(config, k)) for k in ALGORITHM_SECTIONS}
        )
        self._files = {
            name: open_new(path / name, newline="")  # O_EXCL | O_NOFOLLOW
            for name in ("frames.csv", "ranges.csv", "attitude.csv", "imu.csv", "published.csv")
        }
        self._csv = {name: csv.writer(fh, lineterminator="\n") for name, fh in self._files.items()}
        self._row("frames.csv", ["time_us", "seq", "filename", "held"])
        self._row("ranges.csv", [*RANGE_COLUMNS, FED])
        self._row("attitude.csv", [*ATTITUDE_COLUMNS, FED])
        self._row("imu.csv", [*IMU_COLUMNS, *IMU_GYRO_COLUMNS, *IMU_MAG_COLUMNS, FED])
        self._row("published.csv", PUBLISHED_COLUMNS)
        self._flush()

    def _write_small(self, name: str, data: dict[str, Any]) -> None:
        blob = toml_dumps(data).encode()
        atomic_write(self.path / name, blob, 0o644)
        self.bytes_written += len(blob)

    def _row(self, name: str, values: Sequence[Any]) -> None:
        line = ",".join(str(v) for v in values) + "\n"
        self._files[name].write(line)
        self.bytes_written += len(line)

    def _flush(self) -> None:
        for fh in self._files.values():
            fh.flush()

    def encode(self, image_bgr: NDArray[np.uint8]) -> bytes:
        """The image file's bytes (PNG or JPEG) — the costly part; any thread may call it."""
        ok, buf = cv2.imencode(f".{self.image_format}", image_bgr, self._encode_params)
        if not ok:
            raise DatasetError(f"cannot encode a {image_bgr.shape} image as {self.image_format}")
        return bytes(buf)

    def frame_bytes(self, encoded: bytes, n_ranges: int, n_attitudes: int, n_imus: int = 0) -> int:
        """About what a frame adds to the folder [bytes] (for a disk budget)."""
        return len(encoded) + 40 + 90 * n_ranges + 200 * n_attitudes + 80 * n_imus

    def write_frame(
        self,
        frame: CameraFrame,
        encoded: bytes,
        ranges: Sequence[RangeSample],
        attitudes: Sequence[AttitudeSample],
        imus: Sequence[ImuSample] = (),
        held: bool = False,
    ) -> None:
        """Append one frame with the samples fed before it (in the order they were fed).
        ``held``: the service held the frame from its VO (it waited for the autopilot's
        attitude): a replay feeds its samples but not the frame."""
        k = self.frames
        name = f"images/{k:06d}.{self.image_format}"
        with open_new(self.path / name, binary=True) as fh:
            fh.write(encoded)
        self.bytes_written += len(encoded)
        for a in attitudes:
            self._row(
                "attitude.csv",
                [a.time_us, *map(_num, a.quat_wxyz), *map(_num, a.rates_rad_s), k],
            )
        for m in imus:
            gyro = ["", "", ""] if m.gyro_frd_rad_s is None else list(map(_num, m.gyro_frd_rad_s))
            mag = ["", "", ""] if m.mag_frd_gauss is None else list(map(_num, m.mag_frd_gauss))
            self._row("imu.csv", [m.time_us, *map(_num, m.accel_frd_m_s2), *gyro, *mag, k])
        for r in ranges:
            self._row(
                "ranges.csv",
                [
                    r.time_us,
                    r.sensor_id,
                    _num(r.distance_m),
                    _num(r.min_m),
                    _num(r.max_m),
                    r.signal_quality,
                    k,
                ],
            )
        self._files["attitude.csv"].flush()
        self._files["imu.csv"].flush()
        self._files["ranges.csv"].flush()
        self._row("frames.csv", [frame.time_us, frame.seq, name, int(held)])
        self._files["frames.csv"].flush()
        self.frames += 1

    def write_pose(self, pose: PoseEstimate) -> None:
        """Append a pose the service sent (published.csv)."""
        self._row("published.csv", _pose_row(pose))
        self._files["published.csv"].flush()
        self.poses += 1

    def write_state(self, time_us: int, status: Any, autopilot_offset_us: float | None) -> None:
        """Nothing: a folder keeps what a replay needs (an MCAP also keeps the pipeline's
        state and the service's lines for its viewers)."""

    def log(self, time_us: int, text: str, level: str = "WARNING", name: str = "") -> None:
        """Nothing (see :meth:`write_state`)."""

    def sync(self) -> None:
        """fsync the CSV files (what a power cut keeps; the images are checked on read)."""
        for fh in self._files.values():
            fh.flush()
            os.fsync(fh.fileno())

    def close(self, stop_reason: str = "") -> None:
        """Flush and fsync everything, then mark the recording complete in meta.toml."""
        if not self._files:
            return
        self.sync()
        for fh in self._files.values():
            fh.close()
        self._files = {}
        self.meta.update(
            complete=True, frames=self.frames, published=self.poses, stop_reason=stop_reason
        )
        self._write_small("meta.toml", self.meta)
