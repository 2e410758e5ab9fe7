"""Read a EuRoC MAV folder: mav0/cam0 (sensor.yaml, data.csv, the images) and
state_groundtruth_estimate0, turned into a z-down world and body."""

from __future__ import annotations

import re

import numpy as np

from companion.drivers.dataset.format import I64, MAX_TIME_US, QUAT_NORM_TOLERANCE, RowCount
from companion.drivers.dataset.model import Dataset, check_lens
from companion.drivers.safe_files import (
    SafeFolder,
    parse_float,
    parse_int,
)
from companion.errors import DatasetError
from companion.geometry import se3, so3
from companion.geometry.camera import CameraModel
from companion.types import (
    F64,
    AttitudeSample,
)


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
    check_lens(model, "sensor.yaml", "distortion_coefficients")
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


def read_euroc(folder: SafeFolder) -> Dataset:
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
