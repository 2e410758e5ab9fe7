"""Compare two `companion eval DIR` replays of one recording, pose by pose (`make check-arm64`,
systemd/check-arm64.sh: the same clip replayed on x86 and on emulated arm64).

Two stages are compared, in the pipeline's order, so that a difference is placed where it
starts: `vo.tum` (the odometry's camera poses T_vo_cam, TUM "t tx ty tz qx qy qz qw", up to
scale) and `poses.csv` (the published body poses T_world_body, NED/FRD, metres; the columns
time_us,x_m,y_m,z_m,qw,qx,qy,qz,...; docs/dataset.md). For each: the rows must carry the same
times, then the largest position difference [m] and rotation difference [rad] over the rows,
and the first row whose position differs by more than the tolerance.

    python systemd/compare_replays.py X86_DIR ARM64_DIR [--tolerance-m 1e-6]

prints one line per stage and a JSON summary (``COMPARE {...}``); exit 0 when every stage is
within the tolerance, 1 when one is not, 2 for a missing or malformed file (named with its row).
Needs numpy only (the host's venv runs it).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


class ReplayFileError(ValueError):
    """A replay file that is missing or cannot be read (the message names file and row)."""


@dataclasses.dataclass(frozen=True)
class Poses:
    """Stamped poses of one file: ``time_us`` (N,) int64, ``position_m`` (N, 3), ``quat_wxyz``
    (N, 4) unit quaternions (Hamilton, scalar first)."""

    time_us: npt.NDArray[np.int64]
    position_m: FloatArray
    quat_wxyz: FloatArray


@dataclasses.dataclass(frozen=True)
class StageDiff:
    """How two replays of one stage differ. ``max_position_m`` / ``max_rotation_rad`` are None
    when the rows' times differ (then ``first_time_mismatch_row`` says where)."""

    stage: str
    rows: tuple[int, int]
    max_position_m: float | None
    max_rotation_rad: float | None
    first_row_over_tolerance: int | None
    first_time_mismatch_row: int | None

    def within(self, tolerance_m: float) -> bool:
        """Same rows, same times, every position within ``tolerance_m``."""
        return (
            self.first_time_mismatch_row is None
            and self.max_position_m is not None
            and self.max_position_m <= tolerance_m
        )


def _floats(path: Path, row: int, fields: list[str]) -> list[float]:
    try:
        return [float(f) for f in fields]
    except ValueError as e:
        raise ReplayFileError(f"{path}: row {row}: {e}") from None


def read_poses_csv(path: Path) -> Poses:
    """``poses.csv`` of `companion eval` (time_us,x_m,y_m,z_m,qw,qx,qy,qz,...)."""
    if not path.is_file():
        raise ReplayFileError(f"{path}: no such file")
    times: list[int] = []
    rows: list[list[float]] = []
    with path.open(newline="") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        want = ["time_us", "x_m", "y_m", "z_m", "qw", "qx", "qy", "qz"]
        if header is None or header[: len(want)] != want:
            raise ReplayFileError(f"{path}: row 1: header must start with {','.join(want)}")
        for i, fields in enumerate(reader, start=2):
            if len(fields) < len(want):
                raise ReplayFileError(f"{path}: row {i}: {len(fields)} fields, want >= 8")
            values = _floats(path, i, fields[: len(want)])
            times.append(int(values[0]))
            rows.append(values[1:])
    a = np.array(rows, dtype=np.float64).reshape(-1, 7)
    return Poses(np.array(times, dtype=np.int64), a[:, :3], a[:, 3:])


def read_tum(path: Path) -> Poses:
    """A TUM file ("t tx ty tz qx qy qz qw", t in seconds) as Poses (time rounded to us)."""
    if not path.is_file():
        raise ReplayFileError(f"{path}: no such file")
    times: list[int] = []
    rows: list[list[float]] = []
    for i, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        values = _floats(path, i, line.split())
        if len(values) != 8:
            raise ReplayFileError(f"{path}: row {i}: {len(values)} fields, want 8")
        t, x, y, z, qx, qy, qz, qw = values
        times.append(round(t * 1e6))
        rows.append([x, y, z, qw, qx, qy, qz])
    a = np.array(rows, dtype=np.float64).reshape(-1, 7)
    return Poses(np.array(times, dtype=np.int64), a[:, :3], a[:, 3:])


def rotation_angle_rad(q_a_wxyz: FloatArray, q_b_wxyz: FloatArray) -> FloatArray:
    """Angle [rad] of the rotation between unit quaternions, row by row ((N, 4) each):
    2·atan2(|v|, |w|) of q_a⁻¹·q_b, which is exact near 0 (no acos of a number near 1) and
    the same for q and -q."""
    dot = np.abs(np.sum(q_a_wxyz * q_b_wxyz, axis=1))
    # |v| of the relative quaternion: sqrt(|q_a|²|q_b|² - dot²), computed as the norm of the
    # antisymmetric part to keep its small values exact
    w_a, v_a = q_a_wxyz[:, :1], q_a_wxyz[:, 1:]
    w_b, v_b = q_b_wxyz[:, :1], q_b_wxyz[:, 1:]
    v_rel = w_a * v_b - w_b * v_a - np.cross(v_a, v_b)
    result: FloatArray = 2.0 * np.arctan2(np.linalg.norm(v_rel, axis=1), dot)
    return result


def compare(stage: str, a: Poses, b: Poses, tolerance_m: float) -> StageDiff:
    """The difference of two replays of ``stage`` (a: the reference, e.g. x86)."""
    rows = (len(a.time_us), len(b.time_us))
    n = min(rows)
    mismatch = np.flatnonzero(a.time_us[:n] != b.time_us[:n])
    if len(mismatch) or rows[0] != rows[1]:
        first = int(mismatch[0]) if len(mismatch) else n
        return StageDiff(stage, rows, None, None, None, first)
    if n == 0:
        return StageDiff(stage, rows, 0.0, 0.0, None, None)
    d_pos = np.linalg.norm(a.position_m - b.position_m, axis=1)
    d_rot = rotation_angle_rad(a.quat_wxyz, b.quat_wxyz)
    # a pose that is NaN on both sides (nothing published yet) is equal; on one side only, it
    # is as far as can be
    nan_a = np.isnan(a.position_m).any(axis=1) | np.isnan(a.quat_wxyz).any(axis=1)
    nan_b = np.isnan(b.position_m).any(axis=1) | np.isnan(b.quat_wxyz).any(axis=1)
    d_pos[nan_a & nan_b] = 0.0
    d_rot[nan_a & nan_b] = 0.0
    d_pos[nan_a ^ nan_b] = np.inf
    d_rot[nan_a ^ nan_b] = np.inf
    over = np.flatnonzero(d_pos > tolerance_m)
    first_over = int(over[0]) if len(over) else None
    return StageDiff(stage, rows, float(d_pos.max()), float(d_rot.max()), first_over, None)


def compare_dirs(x86: Path, arm64: Path, tolerance_m: float) -> list[StageDiff]:
    """Both stages of two `companion eval` output folders, in the pipeline's order."""
    return [
        compare("vo.tum", read_tum(x86 / "vo.tum"), read_tum(arm64 / "vo.tum"), tolerance_m),
        compare(
            "poses.csv",
            read_poses_csv(x86 / "poses.csv"),
            read_poses_csv(arm64 / "poses.csv"),
            tolerance_m,
        ),
    ]


def describe(d: StageDiff, tolerance_m: float) -> str:
    """One line for a person."""
    if d.first_time_mismatch_row is not None:
        return (
            f"{d.stage}: rows {d.rows[0]} vs {d.rows[1]}, times differ from data row "
            f"{d.first_time_mismatch_row}"
        )
    verdict = "equal" if d.within(tolerance_m) else "DIFFERENT"
    row = d.first_row_over_tolerance
    first = "" if row is None else f", first over it at data row {row}"
    return (
        f"{d.stage}: {d.rows[0]} rows, largest position difference {d.max_position_m:.3e} m, "
        f"rotation {d.max_rotation_rad:.3e} rad: {verdict} to {tolerance_m:g} m{first}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("x86", type=Path, help="the reference replay's folder")
    parser.add_argument("arm64", type=Path, help="the other replay's folder")
    parser.add_argument("--tolerance-m", type=float, default=1e-6)
    args = parser.parse_args(argv)
    try:
        diffs = compare_dirs(args.x86, args.arm64, args.tolerance_m)
    except ReplayFileError as e:
        print(f"compare_replays: {e}", file=sys.stderr)
        return 2
    for d in diffs:
        print(describe(d, args.tolerance_m))
    print("COMPARE " + json.dumps([dataclasses.asdict(d) for d in diffs]))
    return 0 if all(d.within(args.tolerance_m) for d in diffs) else 1


if __name__ == "__main__":
    sys.exit(main())
