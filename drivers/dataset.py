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
import io
import json
import os
import re
import tomllib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.config import Config, SitlConfig, from_dict, to_dict
from companion.errors import ConfigError, DatasetError
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
from drivers.files import atomic_write

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
# optional (recordings before session 20 lack them; empty when the autopilot sent none):
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
        """Read frame ``index`` as BGR (grey images are expanded to three channels)."""
        path = self.frame_paths[index]
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DatasetError(f"cannot read image {path}")
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        seq = index if self.frame_seqs is None else int(self.frame_seqs[index])
        return CameraFrame(int(self.frame_times_us[index]), seq, np.asarray(img, dtype=np.uint8))

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


def _read_csv(path: Path, optional: bool = False) -> list[dict[str, str]]:
    """The rows of a CSV file with a header. A last line without its newline is a row the
    writer did not finish (a recording killed mid-write): it is left out. ``optional``: a
    missing file has no rows."""
    if not path.exists():
        if optional:
            return []
        raise DatasetError(f"missing file {path}")
    text = path.read_text()
    if text and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]
    return list(csv.DictReader(io.StringIO(text, newline="")))


def read_tum(path: Path) -> tuple[F64, F64]:
    """TUM trajectory: times (N,) [s] and poses (N, 4, 4) from 'time tx ty tz qx qy qz qw'."""
    rows = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        vals = line.split()
        if len(vals) != 8:
            raise DatasetError(f"{path}: a TUM line needs 8 values, got {len(vals)}")
        rows.append([float(v) for v in vals])
    arr = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    poses = (
        np.stack([se3.from_quat(so3.quat_xyzw_to_wxyz(r[4:8]), r[1:4]) for r in arr])
        if len(arr)
        else np.zeros((0, 4, 4))
    )
    return arr[:, 0], poses


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


def _ours_config(path: Path, meta: dict[str, Any]) -> tuple[Config, SitlConfig | None]:
    """The config of a dataset of ours: calibration.toml (camera, the declared rangefinders:
    none declared = none), config.toml (a recording's algorithm options) and, only when
    meta.toml declares a simulated world, its [sitl] table."""
    try:
        calib = tomllib.loads((path / "calibration.toml").read_text())
        algo = (
            tomllib.loads((path / "config.toml").read_text())
            if (path / "config.toml").exists()
            else {}
        )
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise DatasetError(f"{path}: cannot read calibration/config: {e}") from None
    calib.pop("matrices", None)
    calib.setdefault("rangefinders", [])  # the dataset's sensors, never the built-in ones
    unknown = sorted(set(algo) - set(ALGORITHM_SECTIONS))
    if unknown:
        raise DatasetError(f"{path}/config.toml: unexpected tables {unknown}")
    has_world = "sitl" in meta and meta.get("world", "sitl") != "none"
    try:
        cfg = from_dict(Config, {**calib, **algo, "sitl": meta.get("sitl", {})})
    except ConfigError as e:
        raise DatasetError(f"{path}: bad calibration: {e}") from None
    return cfg, (cfg.sitl if has_world else None)


def _fed_column(rows: list[dict[str, str]], name: str) -> I64 | None:
    """The fed_before_frame column of a recording's samples (None if the file has none);
    rows must be in frame order (the writer appends them so)."""
    if not rows or FED not in rows[0]:
        return None
    fed = np.array([int(r[FED]) for r in rows], dtype=np.int64)
    if np.any(np.diff(fed) < 0) or (len(fed) and fed[0] < 0):
        raise DatasetError(f"{name}: {FED} must not decrease")
    return fed


def _complete_frames(paths: list[Path]) -> int:
    """How many leading frames of an unfinished recording have their image: the first missing
    or empty file ends it, and the last one must decode (a power cut may keep the rows but
    not the images)."""
    n = next(
        (i for i, p in enumerate(paths) if not p.exists() or p.stat().st_size == 0), len(paths)
    )
    while n > 0 and cv2.imread(str(paths[n - 1]), cv2.IMREAD_UNCHANGED) is None:
        n -= 1
    return n


def _read_ours(path: Path) -> Dataset:
    try:
        meta = tomllib.loads((path / "meta.toml").read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise DatasetError(f"{path}: cannot read meta/calibration: {e}") from None
    if meta.get("format") != FORMAT_NAME:
        raise DatasetError(f"{path}: not a {FORMAT_NAME} folder")
    cfg, sitl = _ours_config(path, meta)
    complete = bool(meta.get("complete", True))
    frames = _read_csv(path / "frames.csv")
    paths = [path / r["filename"] for r in frames]
    n = len(frames) if complete else _complete_frames(paths)
    frames, paths = frames[:n], paths[:n]
    times = np.array([int(r["time_us"]) for r in frames], dtype=np.int64)
    seqs = np.array([int(r["seq"]) for r in frames], dtype=np.int64)
    held = np.array([r.get("held", "0") == "1" for r in frames], dtype=bool)
    range_rows = _read_csv(path / "ranges.csv", optional=True)
    att_rows = _read_csv(path / "attitude.csv", optional=True)
    fed_r = _fed_column(range_rows, "ranges.csv")
    fed_a = _fed_column(att_rows, "attitude.csv")
    imu_rows = _read_csv(path / "imu.csv", optional=True)
    fed_i = _fed_column(imu_rows, "imu.csv")
    if fed_i is not None:
        imu_rows, fed_i = imu_rows[: int(np.searchsorted(fed_i, n))], fed_i[fed_i < n]
    imus = [
        ImuSample(
            int(r["time_us"]),
            np.array([float(r[k]) for k in IMU_COLUMNS[1:]]),
            _optional_vector(r, IMU_GYRO_COLUMNS),
            _optional_vector(r, IMU_MAG_COLUMNS),
        )
        for r in imu_rows
    ]
    if fed_r is not None:  # samples fed before a frame that was not written: not part of it
        range_rows, fed_r = range_rows[: int(np.searchsorted(fed_r, n))], fed_r[fed_r < n]
    if fed_a is not None:
        att_rows, fed_a = att_rows[: int(np.searchsorted(fed_a, n))], fed_a[fed_a < n]
    declared = {r.sensor_id for r in cfg.rangefinders}
    ranges = [
        RangeSample(
            int(r["time_us"]),
            int(r["sensor_id"]),
            float(r["distance_m"]),
            float(r["min_m"]),
            float(r["max_m"]),
            int(r["signal_quality"]),
        )
        for r in range_rows
    ]
    undeclared = sorted({r.sensor_id for r in ranges} - declared)
    if undeclared:
        raise DatasetError(
            f"{path}: ranges.csv has sensor ids {undeclared} that calibration.toml does not "
            "declare ([[rangefinders]] with their mounts)"
        )
    true_m = np.array([float(r.get("true_distance_m") or "nan") for r in range_rows])
    atts = [
        AttitudeSample(
            int(r["time_us"]),
            np.array([float(r[k]) for k in ("qw", "qx", "qy", "qz")]),
            np.array([float(r[k]) for k in ("wx_rad_s", "wy_rad_s", "wz_rad_s")]),
        )
        for r in att_rows
    ]
    gt_t, gt_T = (
        read_tum(path / "groundtruth.txt")
        if (path / "groundtruth.txt").exists()
        else (np.zeros(0), np.zeros((0, 4, 4)))
    )
    fed = None
    if fed_r is not None or fed_a is not None or meta.get("ingest_order", False):
        empty = np.zeros(0, dtype=np.int64)
        fed = (empty if fed_r is None else fed_r, empty if fed_a is None else fed_a)
    last_us = int(times[-1]) if n else -1
    published = [
        p for p in read_poses_csv(path / "published.csv") if complete or p.time_us <= last_us
    ]
    return Dataset(
        path,
        "companion",
        cfg.camera.model(),
        cfg.camera.T_body_cam(),
        [r.spec() for r in cfg.rangefinders],
        times,
        paths,
        ranges,
        true_m,
        atts,
        np.round(gt_t * 1e6).astype(np.int64),
        gt_T,
        sitl,
        cfg,
        frame_seqs=seqs,
        fed_before=fed,
        imus=imus,
        imu_fed=fed_i,
        frame_held=held if held.any() else None,
        frames_checked=bool(meta.get("frames_checked", False)),
        published=published,
        complete=complete,
        meta=meta,
    )


def read_poses_csv(path: Path) -> list[PublishedPose]:
    """Poses in the published.csv layout (a recording's, or `eval`'s poses.csv); no file:
    none. A torn last row (a killed writer) is left out."""
    return [
        PublishedPose(
            int(r["time_us"]),
            np.array([float(r[k]) for k in ("x_m", "y_m", "z_m")]),
            np.array([float(r[k]) for k in ("qw", "qx", "qy", "qz")]),
            np.array([float(r[k]) for k in ("vx_m_s", "vy_m_s", "vz_m_s")]),
            int(r["reset_counter"]),
            int(r["quality_pct"]),
        )
        for r in _read_csv(path, optional=True)
    ]


def _yaml_list(text: str, key: str) -> list[float]:
    m = re.search(rf"^\s*{key}\s*:\s*\[([^\]]*)\]", text, re.MULTILINE)
    if not m:
        raise DatasetError(f"sensor.yaml: no '{key}' list")
    return [float(v) for v in m.group(1).replace("\n", " ").split(",") if v.strip()]


def _read_euroc(path: Path) -> Dataset:
    """EuRoC MAV layout: mav0/cam0/{data.csv,data/*.png,sensor.yaml} and ground truth.

    EuRoC's world is z-up and its body is the IMU frame; both are turned by 180 degrees about
    x (F = diag(1, -1, -1)) to give a z-down world and a z-down body, as our NED/FRD algorithms
    expect. No distance sensors; the attitude input is the ground-truth orientation.
    """
    mav = path / "mav0" if (path / "mav0").exists() else path
    cam = mav / "cam0"
    yaml_text = (
        re.sub(r"#.*", "", (cam / "sensor.yaml").read_text())
        if (cam / "sensor.yaml").exists()
        else None
    )
    if yaml_text is None:
        raise DatasetError(f"{path}: missing mav0/cam0/sensor.yaml")
    fu, fv, cu, cv = _yaml_list(yaml_text, "intrinsics")
    res = _yaml_list(yaml_text, "resolution")
    dist = _yaml_list(yaml_text, "distortion_coefficients") + [0.0] * 5
    m = re.search(r"T_BS\s*:.*?data\s*:\s*\[([^\]]*)\]", yaml_text, re.DOTALL)
    if not m:
        raise DatasetError(f"{path}: sensor.yaml has no T_BS")
    T_imu_cam = np.array(
        [float(v) for v in m.group(1).replace("\n", " ").split(",") if v.strip()]
    ).reshape(4, 4)
    F = np.diag([1.0, -1.0, -1.0, 1.0])
    model = CameraModel(
        int(res[0]), int(res[1]), fu, fv, cu, cv, dist[0], dist[1], dist[2], dist[3], dist[4]
    )
    rows = []
    with (cam / "data.csv").open() as fh:
        for line in fh:
            if line.startswith("#") or not line.strip():
                continue
            ts, name = [v.strip() for v in line.split(",")[:2]]
            rows.append((int(ts) // 1000, cam / "data" / name))
    rows.sort()
    times = np.array([r[0] for r in rows], dtype=np.int64)
    gt_file = mav / "state_groundtruth_estimate0" / "data.csv"
    gt_times = np.zeros(0, dtype=np.int64)
    gt_T = np.zeros((0, 4, 4))
    atts: list[AttitudeSample] = []
    if gt_file.exists():
        vals = np.loadtxt(gt_file, delimiter=",", comments="#", ndmin=2)
        gt_times = (vals[:, 0].astype(np.int64)) // 1000
        gt_T = np.stack([F @ se3.from_quat(v[4:8], v[1:4]) @ F for v in vals])
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
        [r[1] for r in rows],
        attitudes=atts,
        gt_times_us=gt_times,
        gt_T_world_body=gt_T,
    )


def open_dataset(path: str | Path) -> Dataset:
    """Open a dataset folder of our format or EuRoC's (detected by its files)."""
    p = Path(path)
    if not p.is_dir():
        raise DatasetError(f"dataset folder not found: {p}")
    if (p / "meta.toml").exists():
        return _read_ours(p)
    if (p / "mav0" / "cam0").exists() or (p / "cam0" / "data.csv").exists():
        return _read_euroc(p)
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


def _optional_vector(row: dict[str, str], columns: list[str]) -> F64 | None:
    """(3,) floats from a CSV row's optional columns; None when absent or empty."""
    if any(not row.get(c) for c in columns):
        return None
    return np.array([float(row[c]) for c in columns])


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
        (path / "images").mkdir(parents=True, exist_ok=True)
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
            name: (path / name).open("w", newline="")
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
        with (self.path / name).open("wb") as fh:
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
