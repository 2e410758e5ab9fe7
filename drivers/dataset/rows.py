"""The rows of our CSV files, read under the bounded-reading discipline of
drivers/safe_files.py: every field finite and within its bound, a unit quaternion a unit one;
DatasetError naming the file, the row and the column otherwise. A samples file's bad rows are
left out and counted (``parse_rows``), as the live service counts bad MAVLink."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from companion.drivers.dataset.format import (
    ATTITUDE_COLUMNS,
    FED,
    I64,
    IMU_COLUMNS,
    IMU_GYRO_COLUMNS,
    IMU_MAG_COLUMNS,
    MAX_DISTANCE_M,
    MAX_MAGNETIC_GAUSS,
    MAX_POSITION_M,
    MAX_RATE_RAD_S,
    MAX_SEQ,
    MAX_SPECIFIC_FORCE_M_S2,
    MAX_TIME_US,
    MAX_VELOCITY_M_S,
    PUBLISHED_COLUMNS,
    QUAT_NORM_TOLERANCE,
    PublishedPose,
    RowCount,
)
from companion.drivers.safe_files import (
    CsvTable,
    SafeFolder,
    parse_float,
    parse_int,
)
from companion.errors import DatasetError
from companion.types import (
    F64,
    AttitudeSample,
    ImuSample,
    RangeSample,
)


def unit_quat_field(table: CsvTable, line: int, row: list[str], columns: Sequence[str]) -> F64:
    """A unit quaternion from four columns: finite, norm within QUAT_NORM_TOLERANCE of 1
    (kept as read); DatasetError naming the row otherwise (a zero quaternion)."""
    q = np.array([float_field(table, line, row, c, -2.0, 2.0) for c in columns])
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUAT_NORM_TOLERANCE:
        where = table.where(line, "/".join(columns))
        raise DatasetError(f"{where}: not a unit quaternion (norm {norm:.6g})")
    return q  # as recorded (a replay is bit-exact); the pipeline normalises it


def float_field(
    table: CsvTable,
    line: int,
    row: list[str],
    column: str,
    lo: float = -math.inf,
    hi: float = math.inf,
) -> float:
    """A finite float of ``column`` in [lo, hi] (DatasetError naming file, row, column)."""
    return parse_float(table.field(line, row, column), table.where(line, column), lo, hi)


def int_field(table: CsvTable, line: int, row: list[str], column: str, lo: int, hi: int) -> int:
    """An integer of ``column`` in [lo, hi] (DatasetError naming file, row, column)."""
    return parse_int(table.field(line, row, column), table.where(line, column), lo, hi)


def time_field(table: CsvTable, line: int, row: list[str]) -> int:
    return int_field(table, line, row, "time_us", 0, MAX_TIME_US)


def vector_field(
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


def range_row(table: CsvTable, line: int, row: list[str]) -> tuple[RangeSample, float]:
    """A ranges.csv row: the reading as recorded and its true distance (NaN if unknown)."""
    sample = RangeSample(
        time_field(table, line, row),
        int_field(table, line, row, "sensor_id", 0, 255),
        float_field(table, line, row, "distance_m", 0.0, MAX_DISTANCE_M),
        float_field(table, line, row, "min_m", 0.0, MAX_DISTANCE_M),
        float_field(table, line, row, "max_m", 0.0, MAX_DISTANCE_M),
        int_field(table, line, row, "signal_quality", 0, 100),
    )
    if sample.max_m <= sample.min_m:
        raise DatasetError(f"{table.where(line, 'max_m')}: not above min_m")
    truth = "true_distance_m"
    text = table.field(line, row, truth) if table.has(truth) else ""
    where = table.where(line, truth)
    true_m = parse_float(text, where, 0.0, MAX_DISTANCE_M, allow_nan=True) if text else math.nan
    return sample, true_m


def attitude_row(table: CsvTable, line: int, row: list[str]) -> AttitudeSample:
    """An attitude.csv row: a unit quaternion and finite rates below MAX_RATE_RAD_S."""
    return AttitudeSample(
        time_field(table, line, row),
        unit_quat_field(table, line, row, ATTITUDE_COLUMNS[1:5]),
        vector_field(table, line, row, ATTITUDE_COLUMNS[5:], MAX_RATE_RAD_S),
    )


def imu_row(table: CsvTable, line: int, row: list[str]) -> ImuSample:
    """An imu.csv row: the specific force (finite, below 16 g) and, when the columns are there
    and filled, the rates and the magnetic field."""
    accel = vector_field(table, line, row, IMU_COLUMNS[1:], MAX_SPECIFIC_FORCE_M_S2)
    if float(np.linalg.norm(accel)) > MAX_SPECIFIC_FORCE_M_S2:
        raise DatasetError(f"{table.where(line, 'ax_m_s2')}: specific force above 16 g")
    return ImuSample(
        time_field(table, line, row),
        accel,
        optional_vector_field(table, line, row, IMU_GYRO_COLUMNS, MAX_RATE_RAD_S),
        optional_vector_field(table, line, row, IMU_MAG_COLUMNS, MAX_MAGNETIC_GAUSS),
    )


def published_row(table: CsvTable, line: int, row: list[str]) -> PublishedPose:
    """A published.csv (or poses.csv) row."""
    return PublishedPose(
        time_field(table, line, row),
        vector_field(table, line, row, PUBLISHED_COLUMNS[1:4], MAX_POSITION_M),
        unit_quat_field(table, line, row, PUBLISHED_COLUMNS[4:8]),
        vector_field(table, line, row, PUBLISHED_COLUMNS[8:11], MAX_VELOCITY_M_S, allow_nan=True),
        int_field(table, line, row, "reset_counter", 0, 255),
        int_field(table, line, row, "quality_pct", 0, 100),
    )


def parse_rows(
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
            k = int_field(table, line, row, FED, 0, MAX_SEQ) if fed_column else 0
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


def optional_vector_field(
    table: CsvTable, line: int, row: list[str], columns: list[str], bound: float
) -> F64 | None:
    """(3,) finite floats within +-bound from a CSV row's optional columns; None when absent
    or empty."""
    if any(not table.has(c) or not table.field(line, row, c).strip() for c in columns):
        return None
    return vector_field(table, line, row, columns, bound)


def read_published(
    folder: SafeFolder, name: str, counts: dict[str, RowCount] | None = None
) -> list[PublishedPose]:
    """The poses of a published.csv-layout file in ``folder`` (none without the file); bad
    rows left out and counted in ``counts[name]``."""
    table = folder.read_csv(name, PUBLISHED_COLUMNS, optional=True)
    count = RowCount()
    poses, _ = parse_rows(table, published_row, count)
    if counts is not None and count.skipped:
        counts[name] = count
    return poses


def read_poses_csv(path: Path) -> list[PublishedPose]:
    """Poses in the published.csv layout (a recording's, or `eval`'s poses.csv); no file:
    none. A torn last row (a killed writer) and rows that do not parse are left out."""
    return read_published(SafeFolder(path.parent), path.name)
