"""Read a folder of our format (docs/dataset.md): meta.toml, calibration.toml, config.toml,
frames.csv and the samples files. A recording that did not close (``complete = false``) is
read up to its last complete frame."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.config import Config, SitlConfig, from_dict
from companion.drivers.dataset.format import (
    ALGORITHM_SECTIONS,
    ATTITUDE_COLUMNS,
    FED,
    FORMAT_NAME,
    I64,
    IMU_COLUMNS,
    MAX_SEQ,
    RANGE_COLUMNS,
    RowCount,
)
from companion.drivers.dataset.model import Dataset, check_lens, decode_frame
from companion.drivers.dataset.rows import (
    attitude_row,
    imu_row,
    int_field,
    parse_rows,
    range_row,
    read_published,
    time_field,
)
from companion.drivers.dataset.tum import tum_poses
from companion.drivers.safe_files import (
    MAX_CSV_BYTES,
    CsvTable,
    SafeFolder,
)
from companion.errors import ConfigError, DatasetError


def _ours_config(folder: SafeFolder, meta: dict[str, Any]) -> tuple[Config, SitlConfig | None]:
    """The config of a dataset of ours: calibration.toml (camera, the declared rangefinders:
    none declared = none), config.toml (a recording's algorithm options) and, only when
    meta.toml declares a simulated world, its [sitl] table."""
    calib = folder.read_toml("calibration.toml")
    algo = folder.read_toml("config.toml") if folder.exists("config.toml") else {}
    return config_from_tables(calib, algo, meta, str(folder.shown))


def config_from_tables(
    calib: dict[str, Any], algo: dict[str, Any], meta: dict[str, Any], where: str
) -> tuple[Config, SitlConfig | None]:
    """The config of a dataset from its calibration.toml and config.toml tables (a folder's
    files, an MCAP recording's attachments) and the [sitl] table of its meta; DatasetError
    naming ``where`` for anything that is not a valid config."""
    calib = dict(calib)
    calib.pop("matrices", None)
    calib.setdefault("rangefinders", [])  # the dataset's sensors, never the built-in ones
    unknown = sorted(set(algo) - set(ALGORITHM_SECTIONS))
    if unknown:
        raise DatasetError(f"{where}/config.toml: unexpected tables {unknown[:5]}")
    has_world = "sitl" in meta and meta.get("world", "sitl") != "none"
    try:
        cfg = from_dict(Config, {**calib, **algo, "sitl": meta.get("sitl", {})})
    except ConfigError as e:
        raise DatasetError(f"{where}: bad calibration.toml/config.toml: {e}") from None
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
        time_field(table, line, row),
        int_field(table, line, row, "seq", 0, MAX_SEQ),
        filename,
        has_held and int_field(table, line, row, "held", 0, 1) == 1,
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
            decode_frame(folder, names[n - 1], size, f"frame {n - 1}")
            break
        except DatasetError:
            n -= 1
    return n


def read_ours(folder: SafeFolder) -> Dataset:
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
        return parse_rows(table, parse, counts[name], None if complete else n)

    range_rows, fed_r = samples("ranges.csv", RANGE_COLUMNS, range_row)
    atts, fed_a = samples("attitude.csv", ATTITUDE_COLUMNS, attitude_row)
    imus, fed_i = samples("imu.csv", IMU_COLUMNS, imu_row)
    ranges = [r for r, _ in range_rows]
    declared = {r.sensor_id for r in cfg.rangefinders}
    undeclared = sorted({r.sensor_id for r in ranges} - declared)
    if undeclared:
        raise DatasetError(
            f"{path}: ranges.csv has sensor ids {undeclared} that calibration.toml does not "
            "declare ([[rangefinders]] with their mounts)"
        )
    gt_t, gt_T = (
        tum_poses(folder.read_text("groundtruth.txt", MAX_CSV_BYTES), "groundtruth.txt")
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
        for p in read_published(folder, "published.csv", counts)
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
