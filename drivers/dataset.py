"""Read datasets: our own format (docs/dataset.md) and EuRoC folders; TUM trajectories.

Both readers yield the same frozen types (CameraFrame, RangeSample, AttitudeSample) and the
same calibration objects, so the algorithms run offline on simulated and real recordings alike.
This is I/O (drivers/): the camera's ``folder:`` source and ``companion eval`` read recordings
through it; the simulator writes them (``sitl.dataset.record``).
"""

from __future__ import annotations

import csv
import heapq
import re
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.config import Config, SitlConfig, from_dict
from companion.errors import ConfigError, DatasetError
from companion.geometry import se3, so3
from companion.geometry.camera import CameraModel
from companion.types import AttitudeSample, CameraFrame, RangeSample, RangeSensorSpec

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

FORMAT_NAME = "companion-dataset"
FORMAT_VERSION = 1
Event = CameraFrame | RangeSample | AttitudeSample


# ----------------------------------------------------------------------------- reading


@dataclass
class Dataset:
    """A recording: calibration, time-stamped inputs and (when known) ground truth.

    frame_times_us: (F,) int64; frame_paths: F image files. gt_times_us: (G,) int64 and
    gt_T_world_body: (G, 4, 4) (world NED, body FRD). true_range_m: (len(ranges),) true
    distances when simulated (NaN otherwise). sitl: the simulator settings that rebuild the
    world for ground-truth ray casting (None for real recordings).
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

    def __len__(self) -> int:
        return len(self.frame_paths)

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
        return CameraFrame(int(self.frame_times_us[index]), index, np.asarray(img, dtype=np.uint8))

    def frames(self) -> Iterator[CameraFrame]:
        """Frames in time order, loaded lazily."""
        for i in range(len(self)):
            yield self.load_frame(i)

    def events(self) -> Iterator[Event]:
        """All inputs merged in time order; at equal times ranges and attitude precede a frame."""
        streams: list[Iterator[tuple[int, int, int, Any]]] = [
            ((a.time_us, 0, i, a) for i, a in enumerate(self.attitudes)),
            ((r.time_us, 1, i, r) for i, r in enumerate(self.ranges)),
            ((int(t), 2, i, i) for i, t in enumerate(self.frame_times_us)),
        ]
        for _, kind, _, item in heapq.merge(*streams):
            yield self.load_frame(item) if kind == 2 else item

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


def dataset_steps(ds: Dataset) -> Iterator[DatasetStep]:
    """Frames of a dataset with their samples (times <= the frame's) and true poses."""
    ranges: list[_Reading] = []
    atts: list[AttitudeSample] = []
    truth = ds.true_range_m if len(ds.true_range_m) == len(ds.ranges) else None
    index = {id(r): i for i, r in enumerate(ds.ranges)}
    for ev in ds.events():
        if isinstance(ev, AttitudeSample):
            atts.append(ev)
        elif isinstance(ev, RangeSample):
            t = float(truth[index[id(ev)]]) if truth is not None else float("nan")
            ranges.append(_Reading(ev, t))
        else:
            yield DatasetStep(ev, ds.gt_pose_at(ev.time_us), ranges, atts)
            ranges, atts = [], []


def _read_csv(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        raise DatasetError(f"missing file {path}")
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


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


def _read_ours(path: Path) -> Dataset:
    try:
        meta = tomllib.loads((path / "meta.toml").read_text())
        calib = tomllib.loads((path / "calibration.toml").read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise DatasetError(f"{path}: cannot read meta/calibration: {e}") from None
    if meta.get("format") != FORMAT_NAME:
        raise DatasetError(f"{path}: not a {FORMAT_NAME} folder")
    calib.pop("matrices", None)
    try:
        cfg = from_dict(Config, {**calib, "sitl": meta.get("sitl", {})})
    except ConfigError as e:
        raise DatasetError(f"{path}: bad calibration: {e}") from None
    frames = _read_csv(path / "frames.csv")
    times = np.array([int(r["time_us"]) for r in frames], dtype=np.int64)
    paths = [path / r["filename"] for r in frames]
    ranges = [
        RangeSample(
            int(r["time_us"]),
            int(r["sensor_id"]),
            float(r["distance_m"]),
            float(r["min_m"]),
            float(r["max_m"]),
            int(r["signal_quality"]),
        )
        for r in (_read_csv(path / "ranges.csv"))
    ]
    true_m = np.array([float(r["true_distance_m"]) for r in _read_csv(path / "ranges.csv")])
    atts = [
        AttitudeSample(
            int(r["time_us"]),
            np.array([float(r[k]) for k in ("qw", "qx", "qy", "qz")]),
            np.array([float(r[k]) for k in ("wx_rad_s", "wy_rad_s", "wz_rad_s")]),
        )
        for r in _read_csv(path / "attitude.csv")
    ]
    gt_t, gt_T = read_tum(path / "groundtruth.txt")
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
        cfg.sitl,
        cfg,
    )


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
