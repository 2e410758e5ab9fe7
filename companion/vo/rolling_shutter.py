"""The first-order rolling-shutter correction of tracked features.

A rolling-shutter camera reads its rows out one after the other, top to bottom, over the
readout time ``readout_s``. With the frame's stamp at the middle of the readout (the
convention of docs/dataset.md and of the simulator, sitl/world/rolling_shutter.py), row ``v``
of an ``H``-row image is exposed at

    dt(v) = ((v + 0.5) / H - 0.5) * readout_s                                          (1)

after the stamp: -readout/2 for the top row, +readout/2 for the bottom one. A feature seen at
pixel ``u`` in row ``v`` while the image moves with velocity ``w`` [px/s] would have been at

    u_mid = u - w * dt(v)                                                              (2)

at the stamp, to first order in the motion during the readout (the "first-order velocity
correction" of rolling-shutter VO, e.g. Li, Kim and Mourikis, ICRA 2013, section III, here in
the image instead of the state). The VO's geometry (the pose, the triangulation, the keyframe
observations) then sees every feature at one instant, the frame's stamp, and the pose it
solves is the camera's at that instant. Each feature's velocity is its own KLT displacement
over the frame interval (depth and rotation included, no model of the motion needed); a
feature with no displacement measured yet (new corners at a keyframe, tracks after a new map)
takes the affine velocity field fitted to the others (a downward camera over near-planar
ground moves the image nearly affinely over a frame).

Pixels are (x, y) = (column, row) in the raw image, as the frontend's; velocities [px/s].
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from companion.types import F64

MIN_FIELD_TRACKS = 8  # tracks with a measured displacement needed to fit the velocity field


def row_offsets_s(v_px: NDArray[np.floating], height: int, readout_s: float) -> F64:
    """(N,) equation (1): when each row ``v_px`` (N,) [px] was exposed, relative to the
    frame's stamp [s] (negative above the middle row)."""
    v = np.asarray(v_px, dtype=np.float64)
    out: F64 = ((v + 0.5) / height - 0.5) * readout_s
    return out


def fit_velocity_field(px: NDArray[np.floating], velocity_px_s: NDArray[np.floating]) -> F64 | None:
    """(2, 3) the affine image velocity field A with w(x, y) = A @ (x, y, 1) [px/s], fitted by
    least squares to tracks at ``px`` (N, 2) moving with ``velocity_px_s`` (N, 2), refitted
    once without the tracks whose residual exceeds three times the median (bad tracks, a
    building's roof over the ground); None with fewer than MIN_FIELD_TRACKS tracks."""
    p = np.asarray(px, dtype=np.float64)
    w = np.asarray(velocity_px_s, dtype=np.float64)
    if len(p) < MIN_FIELD_TRACKS:
        return None
    M = np.column_stack([p, np.ones(len(p))])
    A = np.linalg.lstsq(M, w, rcond=None)[0].T
    residual = np.linalg.norm(M @ A.T - w, axis=1)
    keep = residual <= 3.0 * float(np.median(residual)) + 1e-9
    if MIN_FIELD_TRACKS <= keep.sum() < len(p):
        A = np.linalg.lstsq(M[keep], w[keep], rcond=None)[0].T
    out: F64 = np.asarray(A, dtype=np.float64)
    return out


@dataclass
class ShutterCorrection:
    """The rolling-shutter correction of one camera (``readout_s`` > 0, ``height`` rows), with
    the image motion of the current frame (:meth:`update` after tracking)."""

    readout_s: float
    height: int
    interval_s: float = 0.0  # the frame interval the velocities are measured over
    field_A: F64 | None = field(default=None)  # (2, 3) the affine velocity field

    def update(
        self, px: NDArray[np.floating], prev_px: NDArray[np.floating] | None, interval_s: float
    ) -> None:
        """This frame's motion: the tracks at ``px`` (N, 2), at ``prev_px`` (N, 2) in the frame
        before (None: not followed), ``interval_s`` [s] apart (<= 0: unknown, no correction)."""
        self.interval_s = interval_s
        self.field_A = None
        if prev_px is None or interval_s <= 0:
            return
        moved = _measured(px, prev_px)
        p = np.asarray(px, dtype=np.float64)[moved]
        q = np.asarray(prev_px, dtype=np.float64)[moved]
        self.field_A = fit_velocity_field(p, (p - q) / interval_s)

    def velocity_px_s(self, px: NDArray[np.floating], prev_px: NDArray[np.floating] | None) -> F64:
        """(N, 2) the image velocity [px/s] of features at ``px`` (N, 2): their own
        displacement from ``prev_px`` (N, 2) over the interval where measured, the field's
        elsewhere, zero with neither."""
        p = np.asarray(px, dtype=np.float64)
        out = np.zeros_like(p)
        if self.field_A is not None:
            out = np.column_stack([p, np.ones(len(p))]) @ self.field_A.T
        if prev_px is not None and self.interval_s > 0:
            moved = _measured(px, prev_px)
            q = np.asarray(prev_px, dtype=np.float64)
            out[moved] = (p[moved] - q[moved]) / self.interval_s
        return out

    def at_frame_time(
        self, px: NDArray[np.floating], prev_px: NDArray[np.floating] | None = None
    ) -> F64:
        """(N, 2) equation (2): where the features seen at ``px`` (N, 2) were at the frame's
        stamp, with ``prev_px`` (N, 2) their pixels in the frame before (None: unknown)."""
        p = np.asarray(px, dtype=np.float64)
        if len(p) == 0:
            return p.reshape(0, 2)
        dt_s = row_offsets_s(p[:, 1], self.height, self.readout_s)
        out: F64 = p - self.velocity_px_s(p, prev_px) * dt_s[:, None]
        return out


def _measured(px: NDArray[np.floating], prev_px: NDArray[np.floating]) -> NDArray[np.bool_]:
    """(N,) whether a displacement was measured: the frontend gives a new corner its own
    pixel as the pixel before (companion/vo/frontend.py, Tracks.extend), exactly."""
    out: NDArray[np.bool_] = np.any(np.asarray(px) != np.asarray(prev_px), axis=1)
    return out
