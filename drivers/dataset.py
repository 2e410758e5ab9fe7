"""Read datasets: our own format (docs/dataset.md) and EuRoC folders; TUM trajectories; and
write our format frame by frame (``DatasetWriter``, the flight recorder's).

Both readers yield the same frozen types (CameraFrame, RangeSample, AttitudeSample) and the
same calibration objects, so the algorithms run offline on simulated and real recordings alike.
This is I/O (drivers/): the camera's ``folder:`` source and ``companion eval`` read recordings
through it; the simulator writes them (``sitl.dataset.record``), and so does the service's
recorder (``companion run --record DIR``) through ``DatasetWriter``.

A dataset declares what it has: its distance sensors (``[[rangefinders]]`` in
calibration.toml: none declared, none used), a simulated world (a ``[sitl]`` table in
meta.toml: without one ``Dataset.sitl`` is None and nothing may ray cast a world), ground
truth (groundtruth.txt) and the order in which the pipeline was fed (a ``fed_before_frame``
column in ranges.csv / attitude.csv).
"""

from __future__ import annotations

import csv
import datetime
import heapq
import json
import math
import os
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.config import Config, SitlConfig, from_dict, to_dict
from companion.drivers.files import atomic_write, open_new
from companion.drivers.safe_files import (
    MAX_CSV_BYTES,
    MAX_IMAGE_BYTES,
    CsvTable,
    SafeFolder,
    check_image_header,
    parse_float,
    parse_int,
)
from companion.errors import ConfigError, DatasetError, GeometryError
from companion.geometry import se3, so3
from companion.geometry.camera import CameraModel
from companion.types import (
    AttitudeSample,
    CameraFrame,
    ImuSample,
    PoseEstimate,
    RangeSample,
    RangeSensorSpec,
)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

FORMAT_NAME = "companion-dataset"
FORMAT_VERSION = 1
Event = CameraFrame | RangeSample | AttitudeSample | ImuSample
# the algorithm options a recording was processed with (config.toml of a recording)
ALGORITHM_SECTIONS = ("vo", "scale", "attitude", "dpose")
RANGE_COLUMNS = ["time_us", "sensor_id", "distance_m", "min_m", "max_m", "signal_quality"]
ATTITUDE_COLUMNS = ["time_us", "qw", "qx", "qy", "qz", "wx_rad_s", "wy_rad_s", "wz_rad_s"]
IMU_COLUMNS = ["time_us", "ax_m_s2", "ay_m_s2", "az_m_s2"]  # specific force, body FRD
# optional (recordings made before 2026-11-27 lack them; empty when the autopilot sent none):
# body rates and the raw magnetic field, body FRD
IMU_GYRO_COLUMNS = ["wx_rad_s", "wy_rad_s", "wz_rad_s"]
IMU_MAG_COLUMNS = ["mx_gauss", "my_gauss", "mz_gauss"]
PUBLISHED_COLUMNS = [
    "time_us",
    "x_m",
    "y_m",
    "z_m",
    "qw",
    "qx",
    "qy",
    "qz",
    "vx_m_s",
    "vy_m_s",
    "vz_m_s",
    "reset_counter",
    "quality_pct",
]
FED = "fed_before_frame"  # column: the index of the frame this sample was fed before


@dataclass(frozen=True, slots=True)
class PublishedPose:
    """A pose the service sent to the autopilot (published.csv of a recording): time_us of
    its frame, position (3,) NED [m], quat_wxyz (4,) NED <- FRD, velocity (3,) NED [m/s], the
    reset_counter as sent (the wire's, which continues across restarts) and quality [%]."""

    time_us: int
    position_ned_m: F64
    quat_wxyz: F64
    velocity_ned_m_s: F64
    reset_counter: int
    quality_pct: int


# ----------------------------------------------------------------------------- reading


@dataclass
class Dataset:
    """A recording: calibration, time-stamped inputs and (when known) ground truth.

    frame_times_us: (F,) int64; frame_paths: F image files. gt_times_us: (G,) int64 and
    gt_T_world_body: (G, 4, 4) (world NED, body FRD). true_range_m: (len(ranges),) true
    distances when simulated (NaN otherwise). sitl: the simulator settings that rebuild the
    world for ground-truth ray casting (None unless the dataset declares a simulated world).
    rangefinders: the sensors the dataset declares (none: no ranges, none invented).
    frame_seqs (F,): the recorded sequence numbers (None: the index). fed_before: for a
    recording, the index of the frame each range (R,) and attitude (A,) sample was fed before
    (the exact ingest order of the run); None: merge by time. imus: the accelerometer samples
    (imu.csv, optional) and imu_fed (I,) their frame indices in a recording. frames_checked:
    the recorded frames passed the service's frame check (a replay must not check them again).
    published: the poses the service sent (a recording's published.csv). complete: False
    for a recording that did not close (a crash, SIGKILL, power loss): it was read up to its
    last complete frame.
    """

    path: Path
    kind: str
    camera: CameraModel
    T_body_cam: F64
    rangefinders: list[RangeSensorSpec]
    frame_times_us: I64
    frame_paths: list[Path]
    ranges: list[RangeSample] = field(default_factory=list)
    true_range_m: F64 = field(default_factory=lambda: np.zeros(0))
    attitudes: list[AttitudeSample] = field(default_factory=list)
    gt_times_us: I64 = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    gt_T_world_body: F64 = field(default_factory=lambda: np.zeros((0, 4, 4)))
    sitl: SitlConfig | None = None
    config: Config | None = None
    frame_seqs: I64 | None = None
    fed_before: tuple[I64, I64] | None = None
    frames_checked: bool = False
    published: list[PublishedPose] = field(default_factory=list)
    complete: bool = True
    meta: dict[str, Any] = field(default_factory=dict)
    imus: list[ImuSample] = field(default_factory=list)
    imu_fed: I64 | None = None
    frame_held: NDArray[np.bool_] | None = None  # (F,) frames the service held from its VO
    folder: SafeFolder | None = None  # where the files are read from (drivers/safe_files.py)
    frame_names: list[str] = field(default_factory=list)  # (F,) as frames.csv names them
    skipped: dict[str, RowCount] = field(default_factory=dict)  # per file: rows left out

    def __len__(self) -> int:
        return len(self.frame_paths)

    @property
    def has_world(self) -> bool:
        """Whether the dataset declares a simulated world (ray casting gives true depths)."""
        return self.sitl is not None

    @property
    def has_ground_truth(self) -> bool:
        return len(self.gt_times_us) > 0

    def load_frame(self, index: int) -> CameraFrame:
        """Read frame ``index`` as BGR (grey images are expanded to three channels): a regular
        file inside the folder whose header has the calibration's size (checked before it is
        decoded); DatasetError naming the frame otherwise."""
        size = (self.camera.width, self.camera.height)
        if self.folder is not None and index < len(self.frame_names):
            img = _decode_frame(self.folder, self.frame_names[index], size, f"frame {index}")
        else:
            path = self.frame_paths[index]
            img = _decode_frame(SafeFolder(path.parent), path.name, size, f"frame {index}")
        seq = index if self.frame_seqs is None else int(self.frame_seqs[index])
        return CameraFrame(int(self.frame_times_us[index]), seq, img)

    def skipped_text(self) -> list[str]:
        """One line per file with rows the reader left out: how many and the first reason."""
        return [
            f"{name}: {c.skipped} bad row{'s' if c.skipped > 1 else ''} left out (first: {c.first})"
            for name, c in self.skipped.items()
        ]

    def frames(self) -> Iterator[CameraFrame]:
        """Frames in time order, loaded lazily."""
        for i in range(len(self)):
            yield self.load_frame(i)

    def events(self) -> Iterator[Event]:
        """All inputs in the order the pipeline takes them: a recording's exact ingest order
        (per frame: its attitudes, its ranges, the frame), else merged in time order (at
        equal times attitude and ranges precede a frame)."""
        if self.fed_before is not None:
            yield from self._fed_events(*self.fed_before)
            return
        streams: list[Iterator[tuple[int, int, int, Any]]] = [
            ((a.time_us, 0, i, a) for i, a in enumerate(self.attitudes)),
            ((r.time_us, 1, i, r) for i, r in enumerate(self.ranges)),
            ((m.time_us, 1, i, m) for i, m in enumerate(self.imus)),
            ((int(t), 2, i, i) for i, t in enumerate(self.frame_times_us)),
        ]
        for _, kind, _, item in heapq.merge(*streams):
            yield self.load_frame(item) if kind == 2 else item

    def _fed_events(self, range_frame: I64, att_frame: I64) -> Iterator[Event]:
        ri = ai = mi = 0
        imu_frame = np.zeros(0, dtype=np.int64) if self.imu_fed is None else self.imu_fed
        for k in range(len(self)):
            while ai < len(self.attitudes) and att_frame[ai] == k:
                yield self.attitudes[ai]
                ai += 1
            while mi < len(imu_frame) and mi < len(self.imus) and imu_frame[mi] == k:
                yield self.imus[mi]
                mi += 1
            while ri < len(self.ranges) and range_frame[ri] == k:
                yield self.ranges[ri]
                ri += 1
            if self.frame_held is None or not self.frame_held[k]:
                yield self.load_frame(k)

    def gt_pose_at(self, time_us: int) -> F64:
        """Ground-truth T_world_body interpolated at ``time_us`` (clamped to the recording)."""
        if len(self.gt_times_us) == 0:
            raise DatasetError(f"{self.path}: no ground truth")
        t = self.gt_times_us
        i = int(np.searchsorted(t, time_us))
        if i <= 0 or i >= len(t):
            return np.array(self.gt_T_world_body[0 if i <= 0 else -1], dtype=np.float64)
        a = (time_us - t[i - 1]) / float(t[i] - t[i - 1])
        return se3.interpolate(self.gt_T_world_body[i - 1], self.gt_T_world_body[i], a)


@dataclass(frozen=True, slots=True)
class _Reading:
    """A recorded range reading in the shape of the simulator's TrueRange."""

    sample: RangeSample | None
    true_distance_m: float


@dataclass(frozen=True, slots=True)
class DatasetStep:
    """One frame of a dataset with the samples since the previous frame and its ground truth,
    in the shape of ``sitl.scenario.Step`` (so offline evaluation takes either)."""

    frame: CameraFrame
    T_world_body: F64
    ranges: list[_Reading]
    attitudes: list[AttitudeSample]
    imus: list[ImuSample] = field(default_factory=list)


def dataset_steps(ds: Dataset) -> Iterator[DatasetStep]:
    """Frames of a dataset with the samples fed before each (in the dataset's ingest order)
    and its true pose (all NaN without ground truth)."""
    ranges: list[_Reading] = []
    atts: list[AttitudeSample] = []
    imus: list[ImuSample] = []
    truth = ds.true_range_m if len(ds.true_range_m) == len(ds.ranges) else None
    index = {id(r): i for i, r in enumerate(ds.ranges)}
    no_truth = np.full((4, 4), np.nan)
    for ev in ds.events():
        if isinstance(ev, AttitudeSample):
            atts.append(ev)
        elif isinstance(ev, RangeSample):
            t = float(truth[index[id(ev)]]) if truth is not None else float("nan")
            ranges.append(_Reading(ev, t))
        elif isinstance(ev, ImuSample):
            imus.append(ev)
        else:
            T = ds.gt_pose_at(ev.time_us) if ds.has_ground_truth else no_truth
            yield DatasetStep(ev, T, ranges, atts, imus)
            ranges, atts, imus = [], [], []


MAX_TIME_US = 2**62  # a time stamp of ours: [0, 2**62] us (146,000 years)
MAX_SEQ = 2**62
QUAT_NORM_TOLERANCE = 0.01  # |norm - 1| of a stored unit quaternion (float32 sources: 1e-7)
MAX_RATE_RAD_S = 50.0  # as the live service refuses ATTITUDE (drivers/messages.py)
MAX_SPECIFIC_FORCE_M_S2 = 16 * 9.80665  # as it refuses SCALED_IMU
MAX_DISTANCE_M = 1000.0
MAX_POSITION_M = 1e7
MAX_VELOCITY_M_S = 1e4
MAX_MAGNETIC_GAUSS = 100.0


@dataclass
class RowCount:
    """The rows of one file left out by the reader: how many, and the first one's reason."""

    skipped: int = 0
    first: str = ""

    def add(self, reason: str) -> None:
        """Count a left-out row (its reason kept if it is the first)."""
        self.skipped += 1
        self.first = self.first or reason


def _unit_quat(table: CsvTable, line: int, row: list[str], columns: Sequence[str]) -> F64:
    """A unit quaternion from four columns: finite, norm within QUAT_NORM_TOLERANCE of 1
    (kept as read); DatasetError naming the row otherwise (a zero quaternion)."""
    q = np.array([_float(table, line, row, c, -2.0, 2.0) for c in columns])
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUAT_NORM_TOLERANCE:
        where = table.where(line, "/".join(columns))
        raise DatasetError(f"{where}: not a unit quaternion (norm {norm:.6g})")
    return q  # as recorded (a replay is bit-exact); the pipeline normalises it


def _float(
    table: CsvTable,
    line: int,
    row: list[str],
    column: str,
    lo: float = -math.inf,
    hi: float = math.inf,
) -> float:
    """A finite float of ``column`` in [lo, hi] (DatasetError naming file, row, column)."""
    return parse_float(table.field(line, row, column), table.where(line, column), lo, hi)


def _int(table: CsvTable, line: int, row: list[str], column: str, lo: int, hi: int) -> int:
    """An integer of ``column`` in [lo, hi] (DatasetError naming file, row, column)."""
    return parse_int(table.field(line, row, column), table.where(line, column), lo, hi)


def _time(table: CsvTable, line: int, row: list[str]) -> int:
    return _int(table, line, row, "time_us", 0, MAX_TIME_US)


def _vector(
    table: CsvTable,
    line: int,
    row: list[str],
    columns: Sequence[str],
    bound: float,
    allow_nan: bool = False,
) -> F64:
    """Floats of ``columns`` within +-bound (``allow_nan``: an unknown value may be NaN)."""
    return np.array(
        [
            parse_float(table.field(line, row, c), table.where(line, c), -bound, bound, allow_nan)
            for c in columns
        ]
    )


def _range_row(table: CsvTable, line: int, row: list[str]) -> tuple[RangeSample, float]:
    """A ranges.csv row: the reading as recorded and its true distance (NaN if unknown)."""
    sample = RangeSample(
        _time(table, line, row),
        _int(table, line, row, "sensor_id", 0, 255),
        _float(table, line, row, "distance_m", 0.0, MAX_DISTANCE_M),
        _float(table, line, row, "min_m", 0.0, MAX_DISTANCE_M),
        _float(table, line, row, "max_m", 0.0, MAX_DISTANCE_M),
        _int(table, line, row, "signal_quality", 0, 100),
    )
    if sample.max_m <= sample.min_m:
        raise DatasetError(f"{table.where(line, 'max_m')}: not above min_m")
    truth = "true_distance_m"
    text = table.field(line, row, truth) if table.has(truth) else ""
    where = table.where(line, truth)
    true_m = parse_float(text, where, 0.0, MAX_DISTANCE_M, allow_nan=True) if text else math.nan
    return sample, true_m


def _attitude_row(table: CsvTable, line: int, row: list[str]) -> AttitudeSample:
    """An attitude.csv row: a unit quaternion and finite rates below MAX_RATE_RAD_S."""
    return AttitudeSample(
        _time(table, line, row),
        _unit_quat(table, line, row, ATTITUDE_COLUMNS[1:5]),
        _vector(table, line, row, ATTITUDE_COLUMNS[5:], MAX_RATE_RAD_S),
    )


def _imu_row(table: CsvTable, line: int, row: list[str]) -> ImuSample:
    """An imu.csv row: the specific force (finite, below 16 g) and, when the columns are there
    and filled, the rates and the magnetic field."""
    accel = _vector(table, line, row, IMU_COLUMNS[1:], MAX_SPECIFIC_FORCE_M_S2)
    if float(np.linalg.norm(accel)) > MAX_SPECIFIC_FORCE_M_S2:
        raise DatasetError(f"{table.where(line, 'ax_m_s2')}: specific force above 16 g")
    return ImuSample(
        _time(table, line, row),
        accel,
        _optional_vector(table, line, row, IMU_GYRO_COLUMNS, MAX_RATE_RAD_S),
        _optional_vector(table, line, row, IMU_MAG_COLUMNS, MAX_MAGNETIC_GAUSS),
    )


def _pose_row_read(table: CsvTable, line: int, row: list[str]) -> PublishedPose:
    """A published.csv (or poses.csv) row."""
    return PublishedPose(
        _time(table, line, row),
        _vector(table, line, row, PUBLISHED_COLUMNS[1:4], MAX_POSITION_M),
        _unit_quat(table, line, row, PUBLISHED_COLUMNS[4:8]),
        _vector(table, line, row, PUBLISHED_COLUMNS[8:11], MAX_VELOCITY_M_S, allow_nan=True),
        _int(table, line, row, "reset_counter", 0, 255),
        _int(table, line, row, "quality_pct", 0, 100),
    )


def _rows(
    table: CsvTable, parse: Any, counts: RowCount, n_frames: int | None = None
) -> tuple[list[Any], I64 | None]:
    """The rows of a samples file parsed by ``parse`` and, when the file has the column, the
    frame each was fed before. A row that does not parse (a word or NaN in a number, a zero
    quaternion, a short or long row, a fed_before_frame that decreases) is left out and
    counted in ``counts``, as the live service counts bad MAVLink. ``n_frames``: the samples
    fed before a frame that was not written (an unfinished recording) are not part of it."""
    fed_column = table.has(FED)
    samples: list[Any] = []
    fed: list[int] = []
    width = len(table.columns)
    for line, row in table.rows:
        try:
            if len(row) != width:
                raise DatasetError(f"{table.name} row {line}: {len(row)} fields, header {width}")
            sample = parse(table, line, row)
            k = _int(table, line, row, FED, 0, MAX_SEQ) if fed_column else 0
            if fed and k < fed[-1]:
                raise DatasetError(f"{table.where(line, FED)}: {k} after {fed[-1]} (decreases)")
        except DatasetError as e:
            counts.add(str(e))
            continue
        if n_frames is not None and fed_column and k >= n_frames:
            break
        samples.append(sample)
        fed.append(k)
    return samples, (np.array(fed, dtype=np.int64) if fed_column else None)


def read_tum(path: Path) -> tuple[F64, F64]:
    """TUM trajectory: times (N,) [s] and poses (N, 4, 4) from 'time tx ty tz qx qy qz qw';
    DatasetError naming the line for anything else (8 finite numbers, a unit quaternion,
    increasing times)."""
    folder = SafeFolder(path.parent)
    return _tum_poses(folder.read_text(path.name, MAX_CSV_BYTES), path.name)


def _tum_poses(text: str, name: str) -> tuple[F64, F64]:
    """Times (N,) [s] and poses (N, 4, 4) of the TUM ``text`` (file ``name``)."""
    times: list[float] = []
    poses: list[F64] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        vals = line.split()
        where = f"{name} line {number}"
        if len(vals) != 8:
            raise DatasetError(f"{where}: a TUM line needs 8 values, got {len(vals)}")
        t, *xyz_q = (
            parse_float(v, f"{where}, value {i + 1}", -1e12, 1e12) for i, v in enumerate(vals)
        )
        q = so3.quat_xyzw_to_wxyz(np.array(xyz_q[3:]))
        if abs(float(np.linalg.norm(q)) - 1.0) > QUAT_NORM_TOLERANCE:
            raise DatasetError(f"{where}: not a unit quaternion")
        if times and t <= times[-1]:
            raise DatasetError(f"{where}: time {t} not after {times[-1]}")
        times.append(t)
        poses.append(se3.from_quat(q, xyz_q[:3]))
    return np.array(times, dtype=np.float64), (np.stack(poses) if poses else np.zeros((0, 4, 4)))


def write_tum(path: Path, times_s: F64, poses: F64) -> None:
    """Write poses (N, 4, 4) at times (N,) [s] as TUM lines 'time tx ty tz qx qy qz qw'."""
    with path.open("w") as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, T in zip(times_s, poses, strict=True):
            q = so3.quat_wxyz_to_xyzw(so3.matrix_to_quat(T[:3, :3]))
            fh.write(
                f"{t:.6f} {T[0, 3]:.9f} {T[1, 3]:.9f} {T[2, 3]:.9f} "
                f"{q[0]:.12f} {q[1]:.12f} {q[2]:.12f} {q[3]:.12f}\n"
            )


def _ours_config(folder: SafeFolder, meta: dict[str, Any]) -> tuple[Config, SitlConfig | None]:
    """The config of a dataset of ours: calibration.toml (camera, the declared rangefinders:
    none declared = none), config.toml (a recording's algorithm options) and, only when
    meta.toml declares a simulated world, its [sitl] table."""
    calib = folder.read_toml("calibration.toml")
    algo = folder.read_toml("config.toml") if folder.exists("config.toml") else {}
    calib.pop("matrices", None)
    calib.setdefault("rangefinders", [])  # the dataset's sensors, never the built-in ones
    unknown = sorted(set(algo) - set(ALGORITHM_SECTIONS))
    if unknown:
        raise DatasetError(f"{folder.shown}/config.toml: unexpected tables {unknown[:5]}")
    has_world = "sitl" in meta and meta.get("world", "sitl") != "none"
    try:
        cfg = from_dict(Config, {**calib, **algo, "sitl": meta.get("sitl", {})})
    except ConfigError as e:
        raise DatasetError(f"{folder.shown}: bad calibration.toml/config.toml: {e}") from None
    return cfg, (cfg.sitl if has_world else None)


@dataclass(frozen=True, slots=True)
class _Frames:
    """frames.csv as read: times, sequence numbers, the file names and the held flags."""

    times_us: I64
    seqs: I64
    names: list[str]
    held: NDArray[np.bool_]


def _read_frames(folder: SafeFolder, complete: bool, name: str = "frames.csv") -> _Frames:
    """The frames of frames.csv; DatasetError naming the row and the field for any bad one
    (a frame's index is what the samples refer to: none may be left out), for a file name
    outside the folder, and for a time that does not increase. ``complete``: False for a
    recording that did not close, whose first bad row ends it (a writer killed mid-row)."""
    table = folder.read_csv(name, ["time_us", "seq", "filename"])
    times: list[int] = []
    seqs: list[int] = []
    names: list[str] = []
    held: list[bool] = []
    for line, row in table.rows:
        try:
            t, seq, filename, is_held = _frame_row(folder, table, line, row)
            if times and t <= times[-1]:
                raise DatasetError(f"{table.where(line, 'time_us')}: {t} not after {times[-1]}")
        except DatasetError:
            if complete:
                raise
            break
        times.append(t)
        seqs.append(seq)
        names.append(filename)
        held.append(is_held)
    return _Frames(
        np.array(times, dtype=np.int64),
        np.array(seqs, dtype=np.int64),
        names,
        np.array(held, dtype=bool),
    )


def _frame_row(
    folder: SafeFolder, table: CsvTable, line: int, row: list[str]
) -> tuple[int, int, str, bool]:
    """time_us, seq, filename (a name inside the folder) and held (optional: 0) of a row."""
    filename = table.field(line, row, "filename")
    folder.check_name(filename, table.where(line, "filename"))
    has_held = table.has("held") and table.columns["held"] < len(row)
    return (
        _time(table, line, row),
        _int(table, line, row, "seq", 0, MAX_SEQ),
        filename,
        has_held and _int(table, line, row, "held", 0, 1) == 1,
    )


def _complete_frames(folder: SafeFolder, names: list[str], size: tuple[int, int]) -> int:
    """How many leading frames of an unfinished recording have their image: the first missing
    or empty file ends it, and the last one must decode (a power cut may keep the rows but
    not the images)."""
    n = len(names)
    for i, name in enumerate(names):
        real = folder.resolve(name, f"frames.csv row {i + 2}, filename")
        try:
            empty = os.stat(real).st_size == 0
        except OSError:
            empty = True
        if empty:
            n = i
            break
    while n > 0:
        try:
            _decode_frame(folder, names[n - 1], size, f"frame {n - 1}")
            break
        except DatasetError:
            n -= 1
    return n


def _decode_frame(
    folder: SafeFolder, name: str, size: tuple[int, int], where: str
) -> NDArray[np.uint8]:
    """The BGR image of file ``name``: read under the folder's discipline, its header's size
    checked against ``size`` (the calibration's) before it is decoded."""
    data = folder.read_bytes(name, MAX_IMAGE_BYTES, f"{where} ({name})")
    check_image_header(data, f"{where} ({name})", size)
    flags = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    if img is None or img.shape[:2] != (size[1], size[0]):
        raise DatasetError(f"{where} ({name}): the image does not decode")
    return np.asarray(img, dtype=np.uint8)


def check_lens(model: CameraModel, where: str) -> None:
    """DatasetError naming ``where`` unless the camera model can serve the pipeline: finite,
    positive intrinsics, and a distortion that inverts (undistortion converges) over the whole
    image: its border and a grid inside (a hostile or broken calibration made the VO raise
    deep inside a run)."""
    try:
        model.validate()
        u = np.linspace(0.0, model.width - 1.0, 33)
        v = np.linspace(0.0, model.height - 1.0, 25)
        grid = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
        model.pixels_to_normalized(grid)
    except (GeometryError, FloatingPointError, ValueError) as e:
        raise DatasetError(f"{where}: the camera model cannot be used: {e}") from None


def _read_ours(folder: SafeFolder) -> Dataset:
    path = folder.shown
    meta = folder.read_toml("meta.toml")
    if meta.get("format") != FORMAT_NAME:
        raise DatasetError(f"{path}: not a {FORMAT_NAME} folder")
    cfg, sitl = _ours_config(folder, meta)
    check_lens(cfg.camera.model(), "calibration.toml [camera]")
    size = (cfg.camera.width, cfg.camera.height)
    complete = meta.get("complete", True) is not False
    frames = _read_frames(folder, complete)
    n = len(frames.names) if complete else _complete_frames(folder, frames.names, size)
    folder.check_files(frames.names[:n], "frame")
    counts: dict[str, RowCount] = {}

    def samples(name: str, required: list[str], parse: Any) -> tuple[list[Any], I64 | None]:
        table = folder.read_csv(name, required, optional=True)
        counts[name] = RowCount()
        return _rows(table, parse, counts[name], None if complete else n)

    range_rows, fed_r = samples("ranges.csv", RANGE_COLUMNS, _range_row)
    atts, fed_a = samples("attitude.csv", ATTITUDE_COLUMNS, _attitude_row)
    imus, fed_i = samples("imu.csv", IMU_COLUMNS, _imu_row)
    ranges = [r for r, _ in range_rows]
    declared = {r.sensor_id for r in cfg.rangefinders}
    undeclared = sorted({r.sensor_id for r in ranges} - declared)
    if undeclared:
        raise DatasetError(
            f"{path}: ranges.csv has sensor ids {undeclared} that calibration.toml does not "
            "declare ([[rangefinders]] with their mounts)"
        )
    gt_t, gt_T = (
        _tum_poses(folder.read_text("groundtruth.txt", MAX_CSV_BYTES), "groundtruth.txt")
        if folder.exists("groundtruth.txt")
        else (np.zeros(0), np.zeros((0, 4, 4)))
    )
    fed = None
    if fed_r is not None or fed_a is not None or meta.get("ingest_order", False) is True:
        _check_fed_columns(
            {"ranges.csv": (ranges, fed_r), "attitude.csv": (atts, fed_a), "imu.csv": (imus, fed_i)}
        )
        empty = np.zeros(0, dtype=np.int64)
        fed = (empty if fed_r is None else fed_r, empty if fed_a is None else fed_a)
    last_us = int(frames.times_us[n - 1]) if n else -1
    published = [
        p
        for p in _read_published(folder, "published.csv", counts)
        if complete or p.time_us <= last_us
    ]
    held = frames.held[:n]
    return Dataset(
        path,
        "companion",
        cfg.camera.model(),
        cfg.camera.T_body_cam(),
        [r.spec() for r in cfg.rangefinders],
        frames.times_us[:n],
        [path / name for name in frames.names[:n]],
        ranges,
        np.array([t for _, t in range_rows], dtype=np.float64),
        atts,
        np.round(gt_t * 1e6).astype(np.int64),
        gt_T,
        sitl,
        cfg,
        frame_seqs=frames.seqs[:n],
        fed_before=fed,
        imus=imus,
        imu_fed=fed_i,
        frame_held=held if held.any() else None,
        frames_checked=meta.get("frames_checked", False) is True,
        published=published,
        complete=complete,
        meta=meta,
        folder=folder,
        frame_names=frames.names[:n],
        skipped={k: c for k, c in counts.items() if c.skipped},
    )


def _check_fed_columns(files: dict[str, tuple[list[Any], I64 | None]]) -> None:
    """A recording replays in its ingest order: every samples file with rows needs its
    fed_before_frame column (DatasetError naming the first without)."""
    for name, (samples, fed) in files.items():
        if samples and fed is None:
            raise DatasetError(
                f"{name} row 1 (header): missing column {FED!r} (a recording in its ingest "
                "order needs it in every samples file)"
            )


def _read_published(
    folder: SafeFolder, name: str, counts: dict[str, RowCount] | None = None
) -> list[PublishedPose]:
    """The poses of a published.csv-layout file in ``folder`` (none without the file); bad
    rows left out and counted in ``counts[name]``."""
    table = folder.read_csv(name, PUBLISHED_COLUMNS, optional=True)
    count = RowCount()
    poses, _ = _rows(table, _pose_row_read, count)
    if counts is not None and count.skipped:
        counts[name] = count
    return poses


def read_poses_csv(path: Path) -> list[PublishedPose]:
    """Poses in the published.csv layout (a recording's, or `eval`'s poses.csv); no file:
    none. A torn last row (a killed writer) and rows that do not parse are left out."""
    return _read_published(SafeFolder(path.parent), path.name)


def _yaml_list(text: str, key: str, count: int | None = None) -> list[float]:
    """The numbers of ``key: [a, b, ...]`` in sensor.yaml (``count`` of them when given)."""
    m = re.search(rf"^\s*{key}\s*:\s*\[([^\]]{{0,4096}})\]", text, re.MULTILINE)
    if not m:
        raise DatasetError(f"sensor.yaml: no '{key}' list")
    parts = [v for v in m.group(1).replace("\n", " ").split(",") if v.strip()]
    if count is not None and len(parts) != count:
        raise DatasetError(f"sensor.yaml: '{key}' needs {count} numbers, got {len(parts)}")
    return [parse_float(v, f"sensor.yaml, {key}[{i}]", -1e6, 1e6) for i, v in enumerate(parts)]


def _euroc_camera(text: str) -> tuple[CameraModel, F64]:
    """The camera model and T_imu_cam of an EuRoC sensor.yaml's text (comments removed)."""
    fu, fv, cu, cv = _yaml_list(text, "intrinsics", 4)
    width, height = (int(v) for v in _yaml_list(text, "resolution", 2))
    if not (16 <= width <= 8192 and 16 <= height <= 8192) or min(fu, fv) <= 0:
        raise DatasetError(f"sensor.yaml: resolution {width} x {height} or focal length <= 0")
    dist = (_yaml_list(text, "distortion_coefficients") + [0.0] * 5)[:5]
    m = re.search(r"T_BS\s*:.{0,200}?data\s*:\s*\[([^\]]{0,4096})\]", text, re.DOTALL)
    if not m:
        raise DatasetError("sensor.yaml: no T_BS data")
    parts = [v for v in m.group(1).replace("\n", " ").split(",") if v.strip()]
    if len(parts) != 16:
        raise DatasetError(f"sensor.yaml: T_BS needs 16 numbers, got {len(parts)}")
    T = np.array(
        [parse_float(v, f"sensor.yaml, T_BS[{i}]", -1e6, 1e6) for i, v in enumerate(parts)]
    )
    model = CameraModel(width, height, fu, fv, cu, cv, *dist)
    check_lens(model, "sensor.yaml")
    return model, T.reshape(4, 4)


def _euroc_frames(folder: SafeFolder, cam: str) -> tuple[I64, list[str]]:
    """The frames of an EuRoC cam0/data.csv (ns -> us), by time; DatasetError naming the row
    for a bad one, a file name outside the folder or a repeated time."""
    table = folder.read_csv(f"{cam}/data.csv")
    rows: list[tuple[int, str]] = []
    for line, row in table.all_rows():
        if row[0].lstrip().startswith("#"):
            continue
        where = f"{cam}/data.csv row {line}"
        if len(row) < 2:
            raise DatasetError(f"{where}: expected timestamp,filename")
        name = f"{cam}/data/{row[1].strip()}"
        folder.check_name(row[1].strip(), f"{where}, filename")
        rows.append((parse_int(row[0], f"{where}, timestamp", 0, MAX_TIME_US) // 1000, name))
    rows.sort()
    times = np.array([t for t, _ in rows], dtype=np.int64)
    if len(times) > 1 and np.any(np.diff(times) <= 0):
        raise DatasetError(f"{cam}/data.csv: two frames at the same time")
    return times, [name for _, name in rows]


def _euroc_truth(
    folder: SafeFolder, name: str, F: F64, counts: dict[str, RowCount]
) -> tuple[I64, F64]:
    """Ground-truth times [us] and T_world_body (z-down) of state_groundtruth_estimate0; rows
    that do not parse (or a quaternion that is not a unit one) are left out and counted."""
    table = folder.read_csv(name)
    count = counts.setdefault(name, RowCount())
    times: list[int] = []
    poses: list[F64] = []
    for line, row in table.all_rows():
        if row[0].lstrip().startswith("#"):
            continue
        where = f"{name} row {line}"
        try:
            if len(row) < 8:
                raise DatasetError(f"{where}: {len(row)} fields, at least 8 needed")
            t = parse_int(row[0], f"{where}, timestamp", 0, MAX_TIME_US) // 1000
            v = [
                parse_float(x, f"{where}, field {i + 2}", -1e7, 1e7) for i, x in enumerate(row[1:8])
            ]
            q = np.array(v[3:7])
            if abs(float(np.linalg.norm(q)) - 1.0) > QUAT_NORM_TOLERANCE:
                raise DatasetError(f"{where}: not a unit quaternion")
            if times and t <= times[-1]:
                raise DatasetError(f"{where}: time not after the previous row's")
        except DatasetError as e:
            count.add(str(e))
            continue
        times.append(t)
        poses.append(F @ se3.from_quat(q, v[:3]) @ F)
    T = np.stack(poses) if poses else np.zeros((0, 4, 4))
    return np.array(times, dtype=np.int64), T


def _read_euroc(folder: SafeFolder) -> Dataset:
    """EuRoC MAV layout: mav0/cam0/{data.csv,data/*.png,sensor.yaml} and ground truth.

    EuRoC's world is z-up and its body is the IMU frame; both are turned by 180 degrees about
    x (F = diag(1, -1, -1)) to give a z-down world and a z-down body, as our NED/FRD algorithms
    expect. No distance sensors; the attitude input is the ground-truth orientation.
    """
    path = folder.shown
    mav = "mav0" if folder.exists("mav0") else ""
    cam = f"{mav}/cam0".lstrip("/")
    if not folder.exists(f"{cam}/sensor.yaml"):
        raise DatasetError(f"{path}: missing mav0/cam0/sensor.yaml")
    yaml_text = re.sub(r"#.*", "", folder.read_text(f"{cam}/sensor.yaml"))
    model, T_imu_cam = _euroc_camera(yaml_text)
    F = np.diag([1.0, -1.0, -1.0, 1.0])
    times, names = _euroc_frames(folder, cam)
    folder.check_files(names, "frame")
    gt_name = f"{mav}/state_groundtruth_estimate0/data.csv".lstrip("/")
    counts: dict[str, RowCount] = {}
    gt_times = np.zeros(0, dtype=np.int64)
    gt_T = np.zeros((0, 4, 4))
    if folder.exists(gt_name):
        gt_times, gt_T = _euroc_truth(folder, gt_name, F, counts)
    atts = [
        AttitudeSample(int(t), so3.matrix_to_quat(T[:3, :3]), np.zeros(3))
        for t, T in zip(gt_times, gt_T, strict=True)
    ]
    return Dataset(
        path,
        "euroc",
        model,
        F @ T_imu_cam,
        [],
        times,
        [path / name for name in names],
        attitudes=atts,
        gt_times_us=gt_times,
        gt_T_world_body=gt_T,
        folder=folder,
        frame_names=names,
        skipped={k: c for k, c in counts.items() if c.skipped},
    )


def open_dataset(path: str | Path) -> Dataset:
    """Open a dataset folder of our format or EuRoC's (detected by its files), read under
    the discipline of drivers/safe_files.py: DatasetError naming the file, the row and the
    field for anything it cannot take; rows of samples that do not parse are left out and
    counted (``Dataset.skipped``)."""
    p = Path(path)
    if not p.is_dir():
        raise DatasetError(f"dataset folder not found: {p}")
    folder = SafeFolder(p)
    if folder.exists("meta.toml"):
        return _read_ours(folder)
    if folder.exists("mav0/cam0") or folder.exists("cam0/data.csv"):
        return _read_euroc(folder)
    raise DatasetError(f"{p}: neither a {FORMAT_NAME} folder (meta.toml) nor EuRoC (mav0/cam0)")


# ----------------------------------------------------------------------------- writing


_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v)  # shortest exact text; inf and nan are TOML's spelling too
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string (\uXXXX escapes are TOML's too)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"no TOML for {type(v).__name__}")


def _toml_key(k: str) -> str:
    return k if _BARE_KEY.match(k) else json.dumps(k)


def _toml_lines(data: dict[str, Any], prefix: tuple[str, ...] = ()) -> list[str]:
    def table_list(v: Any) -> bool:
        return isinstance(v, (list, tuple)) and bool(v) and all(isinstance(x, dict) for x in v)

    lines = [
        f"{_toml_key(k)} = {_toml_value(v)}"
        for k, v in data.items()
        if not isinstance(v, dict) and not table_list(v)
    ]
    for k, v in data.items():
        name = ".".join(_toml_key(p) for p in (*prefix, k))
        if isinstance(v, dict):
            lines += ["", f"[{name}]", *_toml_lines(v, (*prefix, k))]
        elif table_list(v):
            for item in v:
                lines += ["", f"[[{name}]]", *_toml_lines(item, (*prefix, k))]
    return lines


def toml_dumps(data: dict[str, Any]) -> str:
    """TOML text of plain data (tables, arrays of tables, scalars, lists), floats exact: the
    recorder's small files, without a TOML writer among the service's dependencies."""
    return "\n".join(_toml_lines(data)).lstrip("\n") + "\n"


def _optional_vector(
    table: CsvTable, line: int, row: list[str], columns: list[str], bound: float
) -> F64 | None:
    """(3,) finite floats within +-bound from a CSV row's optional columns; None when absent
    or empty."""
    if any(not table.has(c) or not table.field(line, row, c).strip() for c in columns):
        return None
    return _vector(table, line, row, columns, bound)


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


def _png_params(level: int) -> list[int]:
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
            _png_params(png_compression)
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
        calib = {
            "camera": to_dict(config.camera),
            "rangefinders": to_dict(config.rangefinders),
            "matrices": {
                "T_body_cam": config.camera.T_body_cam().tolist(),
                **{
                    f"T_body_rf{r.sensor_id}": r.mount.T_body_sensor().tolist()
                    for r in config.rangefinders
                },
            },
        }
        self._write_small("calibration.toml", calib)
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
