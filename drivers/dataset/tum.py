"""TUM trajectories: 'time tx ty tz qx qy qz qw' lines, read with their bounds and written
with fixed decimals."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from companion.drivers.dataset.format import QUAT_NORM_TOLERANCE
from companion.drivers.safe_files import (
    MAX_CSV_BYTES,
    SafeFolder,
    parse_float,
)
from companion.errors import DatasetError
from companion.geometry import se3, so3
from companion.types import F64


def read_tum(path: Path) -> tuple[F64, F64]:
    """TUM trajectory: times (N,) [s] and poses (N, 4, 4) from 'time tx ty tz qx qy qz qw';
    DatasetError naming the line for anything else (8 finite numbers, a unit quaternion,
    increasing times)."""
    folder = SafeFolder(path.parent)
    return tum_poses(folder.read_text(path.name, MAX_CSV_BYTES), path.name)


def tum_poses(text: str, name: str) -> tuple[F64, F64]:
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
