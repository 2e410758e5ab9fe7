"""Compare two `companion eval DIR` replays of one recording, pose by pose (`make check-arm64`,
systemd/check-arm64.sh: the same clip replayed on x86 and on emulated arm64).

Two stages are compared, in the pipeline's order, so that a difference is placed where it
starts: `vo.tum` (the odometry's camera poses T_vo_cam, TUM "t tx ty tz qx qy qz qw", up to
scale) and `poses.csv` (the published body poses T_world_body, NED/FRD, metres; the columns
time_us,x_m,y_m,z_m,qw,qx,qy,qz,...; docs/dataset.md). For each: the rows must carry the same
times, then the largest position difference [m] and rotation difference [rad] over the rows,
and the first row whose position differs by more than the tolerance.

    python systemd/compare_replays.py X86_DIR ARM64_DIR [--tolerance-m 1e-6] [--ate-rel 0.1]

prints one line per stage and a JSON summary (``COMPARE {...}``); exit 0 when every stage is
within the tolerance, 3 when one is not but both replays' published ATE agree within
``--ate-rel`` (another, equally good trajectory: OpenCV's float kernels round differently on
NEON and SSE/AVX, and the VO's RANSAC turns a 0.01 px difference into another track), 1 when
they do not, 2 for a missing or malformed file (named with its row).
Needs numpy only (the host's venv runs it).

When the poses differ, the frontend's first steps on the clip's first two frames show where:

    python systemd/compare_replays.py --probe CLIP OUT.npz [--reference X86.npz]

runs, with OpenCV, what companion/vo/frontend.py does (decode, grey, half-size pyramid, the
corner response of goodFeaturesToTrack, its corners, cornerSubPix, KLT) and saves each output;
with --reference each stage starts from the reference's output of the stage before, so a
difference belongs to the stage that shows it. Then

    python systemd/compare_replays.py --probe-diff X86.npz ARM64.npz

prints each stage's largest difference.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
Array = npt.NDArray[Any]


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


def published_ate_m(folder: Path) -> float | None:
    """The published poses' SE(3) ATE [m] from `companion eval`'s eval.json, or None."""
    try:
        return float(
            json.loads((folder / "eval.json").read_text())["tracks"]["published"]["ate_se3_m"]
        )
    except (OSError, ValueError, KeyError, TypeError):
        return None


def published_ate(folder: Path) -> str:
    """``FOLDER ATE m`` of the published poses, or ``FOLDER unavailable``."""
    ate = published_ate_m(folder)
    return f"{folder.name} unavailable" if ate is None else f"{folder.name} {ate:.4f} m"


def equally_accurate(a_m: float | None, b_m: float | None, rel: float) -> bool:
    """Whether two ATEs [m] agree within ``rel`` of the larger (False when one is missing)."""
    if a_m is None or b_m is None or not (np.isfinite(a_m) and np.isfinite(b_m)):
        return False
    return abs(a_m - b_m) <= rel * max(a_m, b_m)


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


# ------------------------------------------------------------------ where a difference starts
PROBE_STAGES = ("decode", "grey", "pyramid", "min_eigen", "corners", "subpix", "klt")


def probe_frontend(clip: Path, reference: Path | None) -> dict[str, Any]:
    """The frontend's steps on the first two frames of ``clip`` (frames.csv order), as
    companion/vo/frontend.py runs them (detect: pyrDown, goodFeaturesToTrack with blockSize
    3, quality 0.01, 9 px, a 4 px border mask, 200 corners; cornerSubPix 3x3, 10 iterations;
    track: KLT 15 px window, 3 levels, 20 iterations). Each stage's input is the reference's
    (``reference``, an earlier probe's .npz) when given, else this run's own."""
    import cv2

    ref = dict(np.load(reference)) if reference is not None else {}
    rows = (clip / "frames.csv").read_text().splitlines()[1:3]
    paths = [clip / row.split(",")[2] for row in rows]
    out: dict[str, Any] = {}
    images: list[Any] = [cv2.imread(str(p), cv2.IMREAD_COLOR) for p in paths]
    for path, image in zip(paths, images, strict=True):
        if image is None:
            raise ReplayFileError(f"{path}: not an image OpenCV reads")
    out["decode"] = np.stack(images)
    bgr = ref.get("decode", out["decode"])
    out["grey"] = np.stack([cv2.cvtColor(b, cv2.COLOR_BGR2GRAY) for b in bgr])
    grey = ref.get("grey", out["grey"])
    out["pyramid"] = cv2.pyrDown(grey[0])
    small = ref.get("pyramid", out["pyramid"])
    out["min_eigen"] = cv2.cornerMinEigenVal(small, 3, 3)
    mask = np.zeros(small.shape, np.uint8)
    mask[4:-4, 4:-4] = 255
    corners = cv2.goodFeaturesToTrack(small, 200, 0.01, 9.0, mask=mask, blockSize=3)
    out["corners"] = (corners.reshape(-1, 2) * 2.0 + 0.5).astype(np.float32)
    px = ref.get("corners", out["corners"]).astype(np.float32).copy()
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.03)
    cv2.cornerSubPix(grey[0], px.reshape(-1, 1, 2), (3, 3), (-1, -1), criteria)
    out["subpix"] = px
    start = ref.get("subpix", out["subpix"]).astype(np.float32).reshape(-1, 1, 2)
    nxt, _, _ = cv2.calcOpticalFlowPyrLK(
        grey[0],
        grey[1],
        start,
        None,
        winSize=(15, 15),
        maxLevel=3,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03),
    )
    out["klt"] = nxt.reshape(-1, 2)
    return out


def probe_diff(a: dict[str, Array], b: dict[str, Array]) -> list[tuple[str, str]]:
    """(stage, its largest difference, or what differs) for each stage, in order."""
    lines = []
    for stage in PROBE_STAGES:
        x, y = a[stage], b[stage]
        if x.shape != y.shape:
            lines.append((stage, f"shapes differ: {x.shape} vs {y.shape}"))
            continue
        d = np.abs(x.astype(np.float64) - y.astype(np.float64))
        size = float(np.abs(x).max()) if x.size else 0.0
        lines.append(
            (
                stage,
                f"largest difference {d.max():.3g} ({int((d > 0).sum())} of {d.size} "
                f"values differ; largest value {size:.3g})",
            )
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("x86", type=Path, help="the reference replay's folder (or probe)")
    parser.add_argument("arm64", type=Path, help="the other replay's folder (or probe)")
    parser.add_argument("--tolerance-m", type=float, default=1e-6)
    parser.add_argument(
        "--ate-rel", type=float, default=0.1, help="ATEs this close count as equally accurate"
    )
    parser.add_argument("--probe", action="store_true", help="X86 is a clip, ARM64 the .npz")
    parser.add_argument("--reference", type=Path, help="--probe: the reference probe's .npz")
    parser.add_argument("--probe-diff", action="store_true", help="compare two probes")
    args = parser.parse_args(argv)
    if args.probe:
        np.savez(args.arm64, **probe_frontend(args.x86, args.reference))
        return 0
    if args.probe_diff:
        for stage, text in probe_diff(dict(np.load(args.x86)), dict(np.load(args.arm64))):
            print(f"probe {stage}: {text}")
        return 0
    try:
        diffs = compare_dirs(args.x86, args.arm64, args.tolerance_m)
    except ReplayFileError as e:
        print(f"compare_replays: {e}", file=sys.stderr)
        return 2
    for d in diffs:
        print(describe(d, args.tolerance_m))
    print("published ATE (SE3): " + ", ".join(published_ate(f) for f in (args.x86, args.arm64)))
    print("COMPARE " + json.dumps([dataclasses.asdict(d) for d in diffs]))
    if all(d.within(args.tolerance_m) for d in diffs):
        return 0
    same = equally_accurate(published_ate_m(args.x86), published_ate_m(args.arm64), args.ate_rel)
    print(
        f"the poses differ; the published ATEs {'agree' if same else 'do NOT agree'} within "
        f"{100 * args.ate_rel:g} %: {'another, equally good' if same else 'a worse or better'} "
        "trajectory"
    )
    return 3 if same else 1


if __name__ == "__main__":
    sys.exit(main())
