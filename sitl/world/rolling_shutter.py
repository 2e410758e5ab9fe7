"""A rolling shutter: each image row exposed at its own time, so rendered at its own pose.

Convention (the frame stamp, docs/dataset.md): a frame is stamped at the middle of its
exposure, and with a rolling shutter that is the middle of the readout. Row ``r`` of an image
``H`` rows high, read top to bottom in ``readout_s``, is exposed at

    t_r = t_frame + ((r + 0.5) / H - 0.5) * readout_s

so the first row is ``readout_s / 2`` early, the last ``readout_s / 2`` late, and the image's
middle (between rows H/2 - 1 and H/2) at the stamp. The ground truth (``T_world_body`` in
``groundtruth.txt``, ``RenderedFrame.T_world_cam``) stays the pose at the stamp.

Every row is rendered at the trajectory's exact pose at its time (``Trajectory.poses`` is
vectorised: 480 rows cost about one spline evaluation of 480 times, ~1 ms, against ~60 ms for
the ray casting), so there are no row bands. A world point seen by the camera is where the
row that sees it was looking: :func:`project_rows` solves that fixed point (the point's row
depends on the pose, the pose on the row).
"""

from __future__ import annotations

import numpy as np

from companion.geometry import se3
from companion.geometry.camera import B, CameraModel
from companion.sitl.world.trajectory import Trajectory
from companion.types import F64


def row_offsets_s(height: int, readout_s: float) -> F64:
    """(H,) each row's exposure time minus the frame stamp [s]."""
    return ((np.arange(height) + 0.5) / height - 0.5) * readout_s


def row_poses(trajectory: Trajectory, time_s: float, offsets_s: F64, T_body_cam: F64) -> F64:
    """(H, 4, 4) T_world_cam of each row: the body at ``time_s + offsets_s`` [s] times the
    camera mount ``T_body_cam`` (4, 4)."""
    T_world_body = trajectory.poses(time_s + offsets_s)
    return np.asarray(T_world_body @ T_body_cam, dtype=np.float64)


def project_rows(
    model: CameraModel, T_rows: F64, points_world: F64, iterations: int = 4
) -> tuple[F64, B, F64]:
    """Project world points (K, 3) through a rolling-shutter camera of row poses T_rows
    (H, 4, 4): uv (K, 2) [px], in_front (K,) bool, and the origin (K, 3) of the camera (row
    pose) each point was seen from. Starts from the middle row's pose and moves each point to
    the pose of the row it lands on (rows between are interpolated linearly); four rounds
    settle to ~1e-6 px for rows a few pixels apart."""
    pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    h = T_rows.shape[0]
    row = np.full(len(pts), 0.5 * (h - 1))
    uv = np.zeros((len(pts), 2))
    front = np.zeros(len(pts), dtype=bool)
    origin = np.zeros((len(pts), 3))
    for _ in range(iterations):
        r0 = np.clip(np.floor(row).astype(int), 0, h - 1)
        r1 = np.minimum(r0 + 1, h - 1)
        a = np.clip(row - r0, 0.0, 1.0)
        for k in range(len(pts)):
            T = T_rows[r0[k]] if a[k] == 0.0 else _lerp_pose(T_rows[r0[k]], T_rows[r1[k]], a[k])
            p_cam = se3.transform(se3.inverse(T), pts[k : k + 1])
            uv_k, front_k = model.project(p_cam)
            uv[k] = uv_k[0]
            front[k] = bool(front_k[0])
            origin[k] = T[:3, 3]
        row = np.clip(uv[:, 1], 0.0, h - 1.0)  # a pixel centre's v is its row index
    return uv, front, origin


def _lerp_pose(Ta: F64, Tb: F64, a: float) -> F64:
    """A pose a fraction ``a`` from Ta to Tb: positions linear, rotation re-orthonormalised
    (rows are ~0.05 ms apart: the difference is far below any pixel)."""
    T = (1.0 - a) * Ta + a * Tb
    u, _, vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = u @ vt
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return np.asarray(T, dtype=np.float64)
