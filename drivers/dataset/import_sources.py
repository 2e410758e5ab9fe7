"""Read public real-sequence formats into one plain list of frames (``companion dataset
import``): TUM RGB-D (and its keyframe variant), ETH3D SLAM, Microsoft 7-Scenes, KITTI
odometry.

Every reader returns a :class:`SourceSequence`: the camera (intrinsics and distortion, the
mount the identity: body = camera), the frames (stamp [s], the image's and the depth image's
names inside the source folder, ``T_world_cam`` (4, 4) from the ground truth at the frame's
stamp) and what was left out, counted. Frames are OpenCV's camera frame (x right, y down, z
along the optical axis); the world is the sequence's own (the motion-capture room, KITTI's
first camera), not NED: the evaluation aligns trajectories before comparing them.

The public formats, as their pages give them:
- TUM RGB-D (Sturm et al., IROS 2012): ``rgb.txt`` / ``depth.txt`` lines "stamp name",
  ``groundtruth.txt`` lines "stamp tx ty tz qx qy qz qw" (the camera's optical frame in the
  mocap world), 16-bit depth PNG registered to the colour image, metres = value / 5000. Depth
  is associated to each colour image by the nearest stamp within 20 ms; the ground truth is
  interpolated at the colour stamp (linear position, slerp rotation); colour frames outside the
  ground truth's span (or in a gap of it longer than 0.1 s) are dropped and counted.
- The keyframe variant (a keyframe subset, e.g. cuboid_slam's fr3/cabinet): ``rgb.txt`` /
  ``depth.txt`` lines "index name", ``truth_cam_poses.txt`` in the same row order, whose stamps
  are the frames' stamps.
- ETH3D SLAM: as TUM, plus ``calibration.txt`` "fx fy cx cy" (no distortion).
- 7-Scenes: ``frame-NNNNNN.color.png``, ``.depth.png`` (16-bit millimetres, 65535 = none;
  the depth camera is not registered to the colour one), ``.pose.txt`` (4x4 camera-to-world);
  no stamps: 30 Hz; intrinsics 585 585 320 240.
- KITTI odometry: ``sequences/NN/image_0/NNNNNN.png``, ``times.txt`` (s), ``calib.txt``
  ("P0: " 12 numbers, 3x4 row-major), ``poses/NN.txt`` (12 numbers: 3x4 ``T_world_cam0``);
  no depth.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from companion.config import CameraConfig, MountConfig
from companion.drivers.dataset.tum import tum_poses
from companion.drivers.safe_files import MAX_CSV_BYTES, SafeFolder, image_header, parse_float
from companion.errors import DatasetError
from companion.geometry import se3
from companion.types import F64

ASSOCIATE_MAX_S = 0.020  # depth to colour: nearest stamp within this [s] (TUM's associate.py)
GT_MAX_GAP_S = 0.1  # a longer gap between ground-truth samples is not interpolated [s]
TUM_DEPTH_PER_M = 5000.0  # TUM and ETH3D 16-bit depth: value / 5000 = metres

# The TUM RGB-D cameras' published calibration (vision.in.tum.de, "file formats"): fx fy cx cy
# and k1 k2 p1 p2 k3 of the colour camera
TUM_CAMERAS: dict[str, tuple[tuple[float, float, float, float], tuple[float, ...]]] = {
    "fr1": ((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "fr2": ((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "fr3": ((535.4, 539.2, 320.1, 247.6), (0.0, 0.0, 0.0, 0.0, 0.0)),
}
SEVEN_SCENES_INTRINSICS = (585.0, 585.0, 320.0, 240.0)
SEVEN_SCENES_RATE_HZ = 30.0
SEVEN_SCENES_DEPTH_PER_M = 1000.0
FORMATS = ("tum-rgbd", "eth3d", "7scenes", "kitti")


@dataclass(frozen=True, slots=True)
class SourceFrame:
    """One frame of a source sequence: ``time_s`` its stamp [s] (the source's clock), ``image``
    its colour (or grey) image's name in the source folder, ``depth`` its depth image's name
    (None: none), ``depth_time_s`` that depth image's stamp [s], ``T_world_cam`` (4, 4)."""

    time_s: float
    image: str
    depth: str | None
    depth_time_s: float
    T_world_cam: F64


@dataclass(frozen=True, slots=True)
class SourceSequence:
    """A real sequence as read: its format, camera (``CameraConfig``, mount identity), depth
    scale (value per metre; 0 = no depth), frames in time order, a line for meta.toml saying
    where the intrinsics came from, and the counts of what was left out (by reason)."""

    format: str
    camera: CameraConfig
    depth_per_m: float
    frames: list[SourceFrame]
    camera_note: str
    dropped: dict[str, int] = field(default_factory=dict)


def _list_lines(folder: SafeFolder, name: str, columns: int) -> list[tuple[int, list[str]]]:
    """(line number, fields) of the non-comment lines of ``name``; DatasetError naming the file
    and the line when a line does not have ``columns`` fields."""
    out = []
    for number, raw in enumerate(folder.read_text(name, MAX_CSV_BYTES).splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        if len(fields) != columns:
            raise DatasetError(
                f"{folder.shown}/{name} line {number}: expected {columns} values, "
                f"got {len(fields)}: {line[:60]!r}"
            )
        out.append((number, fields))
    return out


def read_stamped_list(folder: SafeFolder, name: str) -> list[tuple[float, str]]:
    """TUM's ``rgb.txt`` / ``depth.txt``: (stamp [s], file name) per line, stamps increasing,
    names inside the folder; DatasetError naming the file and the line otherwise."""
    out: list[tuple[float, str]] = []
    for number, (stamp, fname) in _list_lines(folder, name, 2):
        where = f"{folder.shown}/{name} line {number}"
        t = parse_float(stamp, f"{where}, stamp", 0.0, 1e12)
        if out and t <= out[-1][0]:
            raise DatasetError(f"{where}: stamp {t} not after {out[-1][0]}")
        folder.check_name(fname, f"{where}, file name")
        out.append((t, fname))
    return out


def associate(rgb_s: F64, depth_s: F64, max_dt_s: float = ASSOCIATE_MAX_S) -> list[int | None]:
    """For each colour stamp (N,) [s], the index of the nearest depth stamp (M,) [s] (sorted)
    within ``max_dt_s``, or None."""
    out: list[int | None] = []
    if len(depth_s) == 0:
        return [None] * len(rgb_s)
    for t in rgb_s:
        k = int(np.searchsorted(depth_s, t))
        near = [j for j in (k - 1, k) if 0 <= j < len(depth_s)]
        best = min(near, key=lambda j: abs(depth_s[j] - t))
        out.append(best if abs(depth_s[best] - t) <= max_dt_s else None)
    return out


def interpolate_pose(
    times_s: F64, poses: F64, t: float, max_gap_s: float = GT_MAX_GAP_S
) -> F64 | None:
    """The pose (4, 4) at ``t`` [s] between the ground-truth samples (N,), (N, 4, 4) around it:
    linear in position, slerp in rotation (``se3.interpolate``); None outside their span or in
    a gap longer than ``max_gap_s``."""
    if len(times_s) == 0 or t < times_s[0] or t > times_s[-1]:
        return None
    k = int(np.searchsorted(times_s, t, side="right"))
    if k >= len(times_s):
        return np.array(poses[-1])
    t0, t1 = float(times_s[k - 1]), float(times_s[k])
    if t1 - t0 > max_gap_s:
        return None
    return se3.interpolate(poses[k - 1], poses[k], (t - t0) / (t1 - t0))


def _image_size(folder: SafeFolder, name: str) -> tuple[int, int]:
    """(width, height) [px] from a PNG's or JPEG's header."""
    head = image_header(folder.read_bytes(name, 64 << 20))
    if head is None:
        raise DatasetError(f"{folder.shown}/{name}: neither a PNG nor a JPEG")
    return head.width, head.height


def _camera(
    folder: SafeFolder, first_image: str, fxy_c: tuple[float, ...], dist: tuple[float, ...]
) -> CameraConfig:
    width, height = _image_size(folder, first_image)
    fx, fy, cx, cy = fxy_c
    k1, k2, p1, p2, k3 = (tuple(dist) + (0.0,) * 5)[:5]
    return CameraConfig(
        width=width,
        height=height,
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        dist=(k1, k2, p1, p2, k3),
        mount=MountConfig(),  # body = camera: T_body_cam = identity
    )


def _rgbd_frames(
    folder: SafeFolder, gt_name: str, keyframes: bool
) -> tuple[list[SourceFrame], dict[str, int]]:
    """Frames of a TUM-like folder (rgb.txt, depth.txt and ``gt_name``)."""
    rgb = read_stamped_list(folder, "rgb.txt")
    depth = read_stamped_list(folder, "depth.txt") if folder.exists("depth.txt") else []
    gt_t, gt_T = tum_poses(folder.read_text(gt_name, MAX_CSV_BYTES), f"{folder.shown}/{gt_name}")
    dropped = {"outside_ground_truth": 0, "without_depth": 0}
    frames: list[SourceFrame] = []
    if keyframes:  # rows in the same order: index i -> ground-truth row i (and its stamp)
        if len(gt_t) < len(rgb):
            raise DatasetError(
                f"{folder.shown}/{gt_name}: {len(gt_t)} poses for {len(rgb)} rgb.txt rows"
            )
        by_index = {int(t): name for t, name in depth}
        for i, (index, name) in enumerate(rgb):
            d = by_index.get(int(index))
            dropped["without_depth"] += d is None
            t = float(gt_t[i])
            frames.append(SourceFrame(t, name, d, t, np.array(gt_T[i])))
        return frames, dropped
    depth_s = np.array([t for t, _ in depth])
    for (t, name), j in zip(rgb, associate(np.array([t for t, _ in rgb]), depth_s), strict=True):
        T = interpolate_pose(gt_t, gt_T, t)
        if T is None:
            dropped["outside_ground_truth"] += 1
            continue
        dropped["without_depth"] += j is None
        d_name, d_t = (None, t) if j is None else (depth[j][1], depth[j][0])
        frames.append(SourceFrame(t, name, d_name, d_t, T))
    return frames, dropped


def read_tum_rgbd(folder: SafeFolder, camera: str = "fr1") -> SourceSequence:
    """A TUM RGB-D folder, or its keyframe variant (``truth_cam_poses.txt`` and no
    ``groundtruth.txt``), with the published intrinsics of ``camera`` (fr1, fr2, fr3)."""
    if camera not in TUM_CAMERAS:
        raise DatasetError(f"--camera: one of {sorted(TUM_CAMERAS)}, got {camera!r}")
    keyframes = not folder.exists("groundtruth.txt") and folder.exists("truth_cam_poses.txt")
    gt_name = "truth_cam_poses.txt" if keyframes else "groundtruth.txt"
    frames, dropped = _rgbd_frames(folder, gt_name, keyframes)
    if not frames:
        raise DatasetError(f"{folder.shown}: no frame inside the ground truth's span")
    fxy_c, dist = TUM_CAMERAS[camera]
    note = f"TUM RGB-D {camera} published calibration (fx fy cx cy {fxy_c}, k1 k2 p1 p2 k3 {dist})"
    return SourceSequence(
        "tum-rgbd-keyframes" if keyframes else "tum-rgbd",
        _camera(folder, frames[0].image, fxy_c, dist),
        TUM_DEPTH_PER_M,
        frames,
        note,
        dropped,
    )


def read_eth3d(folder: SafeFolder) -> SourceSequence:
    """An ETH3D SLAM folder: TUM's lists and ground truth, ``calibration.txt`` "fx fy cx cy"."""
    lines = _list_lines(folder, "calibration.txt", 4)
    if len(lines) != 1:
        raise DatasetError(f"{folder.shown}/calibration.txt: one line 'fx fy cx cy' expected")
    number, vals = lines[0]
    where = f"{folder.shown}/calibration.txt line {number}"
    fxy_c = tuple(parse_float(v, f"{where}, value {i + 1}", -1e5, 1e5) for i, v in enumerate(vals))
    frames, dropped = _rgbd_frames(folder, "groundtruth.txt", keyframes=False)
    if not frames:
        raise DatasetError(f"{folder.shown}: no frame inside the ground truth's span")
    return SourceSequence(
        "eth3d",
        _camera(folder, frames[0].image, fxy_c, ()),
        TUM_DEPTH_PER_M,
        frames,
        f"ETH3D calibration.txt (fx fy cx cy {fxy_c}, no distortion)",
        dropped,
    )


def _matrix_file(folder: SafeFolder, name: str, rows: int) -> F64:
    """A text file of ``rows`` x 4 numbers (7-Scenes' pose.txt)."""
    vals = [v for _, fields in _list_lines(folder, name, 4) for v in fields]
    if len(vals) != rows * 4:
        raise DatasetError(f"{folder.shown}/{name}: {rows}x4 numbers expected, got {len(vals)}")
    where = f"{folder.shown}/{name}"
    return np.array([parse_float(v, where, -1e6, 1e6) for v in vals]).reshape(rows, 4)


def read_7scenes(folder: SafeFolder) -> SourceSequence:
    """A 7-Scenes sequence folder (``frame-NNNNNN.color.png`` / ``.depth.png`` / ``.pose.txt``),
    stamped at 30 Hz from frame 0."""
    pattern = re.compile(r"^frame-(\d{6})\.color\.png$")
    indexes = sorted(int(m.group(1)) for p in folder.root.iterdir() if (m := pattern.match(p.name)))
    if not indexes:
        raise DatasetError(f"{folder.shown}: no frame-NNNNNN.color.png files")
    frames = []
    dropped = {"outside_ground_truth": 0, "without_depth": 0}
    for i in indexes:
        stem = f"frame-{i:06d}"
        T = _matrix_file(folder, f"{stem}.pose.txt", 4)
        if not np.all(np.isfinite(T)) or not se3.is_rigid(T, 1e-3):  # 7-Scenes' -inf poses
            dropped["outside_ground_truth"] += 1
            continue
        depth = f"{stem}.depth.png" if folder.exists(f"{stem}.depth.png") else None
        dropped["without_depth"] += depth is None
        t = i / SEVEN_SCENES_RATE_HZ
        frames.append(SourceFrame(t, f"{stem}.color.png", depth, t, T))
    if not frames:
        raise DatasetError(f"{folder.shown}: no frame with a valid pose")
    return SourceSequence(
        "7scenes",
        _camera(folder, frames[0].image, SEVEN_SCENES_INTRINSICS, ()),
        SEVEN_SCENES_DEPTH_PER_M,
        frames,
        f"7-Scenes published intrinsics {SEVEN_SCENES_INTRINSICS}, no distortion; depth "
        "camera not registered to the colour camera",
        dropped,
    )


def read_kitti(folder: SafeFolder, sequence: str = "") -> SourceSequence:
    """A KITTI odometry root (``sequences/NN/`` and ``poses/NN.txt``): the left grey camera
    (image_0), intrinsics from calib.txt's P0; ``sequence`` NN (default: the only one)."""
    if not sequence:
        found = sorted(p.name for p in (folder.root / "sequences").glob("*") if p.is_dir())
        if len(found) != 1:
            raise DatasetError(f"{folder.shown}: --sequence NN: one of {found[:10]}")
        sequence = found[0]
    seq = f"sequences/{sequence}"
    p0 = [f for _, f in _list_lines(folder, f"{seq}/calib.txt", 13) if f[0] == "P0:"]
    if not p0:
        raise DatasetError(f"{folder.shown}/{seq}/calib.txt: no 'P0:' line")
    P = np.array([parse_float(v, f"{seq}/calib.txt P0", -1e6, 1e6) for v in p0[0][1:]])
    P = P.reshape(3, 4)
    times = [
        parse_float(f[0], f"{folder.shown}/{seq}/times.txt line {n}", 0.0, 1e9)
        for n, f in _list_lines(folder, f"{seq}/times.txt", 1)
    ]
    rows = _list_lines(folder, f"poses/{sequence}.txt", 12)
    if len(rows) != len(times):
        raise DatasetError(
            f"{folder.shown}/poses/{sequence}.txt: {len(rows)} poses for {len(times)} times"
        )
    frames = []
    for i, ((n, vals), t) in enumerate(zip(rows, times, strict=True)):
        where = f"{folder.shown}/poses/{sequence}.txt line {n}"
        T = np.eye(4)
        T[:3, :] = np.array([parse_float(v, where, -1e6, 1e6) for v in vals]).reshape(3, 4)
        frames.append(SourceFrame(t, f"{seq}/image_0/{i:06d}.png", None, t, T))
    fxy_c = (float(P[0, 0]), float(P[1, 1]), float(P[0, 2]), float(P[1, 2]))
    return SourceSequence(
        "kitti",
        _camera(folder, frames[0].image, fxy_c, ()),
        0.0,
        frames,
        f"KITTI {seq}/calib.txt P0 (fx fy cx cy {fxy_c}, rectified: no distortion)",
        {"outside_ground_truth": 0, "without_depth": len(frames)},
    )


def read_source(
    fmt: str, folder: SafeFolder, camera: str = "fr1", sequence: str = ""
) -> SourceSequence:
    """The sequence of the folder in format ``fmt`` (one of :data:`FORMATS`)."""
    if fmt == "tum-rgbd":
        return read_tum_rgbd(folder, camera)
    if fmt == "eth3d":
        return read_eth3d(folder)
    if fmt == "7scenes":
        return read_7scenes(folder)
    if fmt == "kitti":
        return read_kitti(folder, sequence)
    raise DatasetError(f"unknown format {fmt!r}: one of {', '.join(FORMATS)}")
