"""The VO's frontend: corners detected on a grid-spread mask and followed by pyramidal KLT.

Pixels are (x, y) in the full-resolution image; normalised coordinates are (x, y) on the
plane z = 1 of the camera frame (OpenCV: x right, y down, z forward).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.geometry.camera import CameraModel
from companion.types import F64
from companion.vo.options import VoOptions

F32 = NDArray[np.float32]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]
B = NDArray[np.bool_]


@dataclass
class Tracks:
    """Features followed from frame to frame.

    px: (N, 2) float32 pixels in the current frame; pid: (N,) map point id or -1 (candidate);
    anchor: (N,) keyframe id where a candidate was first seen (-1 = the init reference);
    anchor_xy: (N, 2) its normalised coordinates there; prev_px: (N, 2) float32 pixels in the
    frame before, right after :func:`track` (None once the tracks were re-made: a new map).
    """

    px: F32
    pid: I64
    anchor: I64
    anchor_xy: F64
    prev_px: F32 | None = None

    @staticmethod
    def empty() -> Tracks:
        return Tracks(
            np.zeros((0, 2), np.float32),
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            np.zeros((0, 2)),
        )

    def __len__(self) -> int:
        return len(self.pid)

    def select(self, keep: NDArray[np.bool_]) -> Tracks:
        prev = None if self.prev_px is None else self.prev_px[keep]
        return Tracks(self.px[keep], self.pid[keep], self.anchor[keep], self.anchor_xy[keep], prev)

    def extend(self, px: F32, anchor: int, anchor_xy: F64) -> Tracks:
        n = len(px)
        new_px = px.astype(np.float32)
        return Tracks(
            np.concatenate([self.px, new_px]),
            np.concatenate([self.pid, -np.ones(n, np.int64)]),
            np.concatenate([self.anchor, np.full(n, anchor, np.int64)]),
            np.concatenate([self.anchor_xy, anchor_xy]),
            None if self.prev_px is None else np.concatenate([self.prev_px, new_px]),
        )


REFERENCE_SIZE_PX = (640, 480)  # the image size MIN_DISTANCE_PX is for
MIN_DISTANCE_PX = 18.0  # vo.min_distance_px = 0 (auto) at 640 x 480


def scaled_to_image(opts: VoOptions, width: int, height: int) -> VoOptions:
    """The options with ``min_distance_px`` resolved for a width x height image: a value set
    (> 0) as it is; 0 (auto) = 18 px scaled by min(width / 640, height / 480) when the image
    is smaller than 640 x 480 (a 320 x 240 camera gets 9 px: 18 px there leaves too few
    corners in view to start or keep a map), never enlarged (752 x 480 keeps 18 px)."""
    if opts.min_distance_px > 0:
        return opts
    ratio = min(width / REFERENCE_SIZE_PX[0], height / REFERENCE_SIZE_PX[1], 1.0)
    return dataclasses.replace(opts, min_distance_px=MIN_DISTANCE_PX * ratio)


def detect(gray: U8, avoid_px: F32, n_max: int, min_distance_px: float) -> F32:
    """Up to n_max corners (K, 2) [px] at least ``min_distance_px`` from each other and from
    ``avoid_px`` (N, 2), the current tracks (half-resolution detection, sub-pixel refinement
    at full resolution)."""
    if n_max <= 0:
        return np.zeros((0, 2), np.float32)
    small = cv2.pyrDown(gray)
    mask = np.full(small.shape, 255, np.uint8)
    r = max(1, int(round(min_distance_px / 2)))
    for x, y in (avoid_px * 0.5).astype(int):
        cv2.circle(mask, (int(x), int(y)), r, 0, -1)
    border = 4
    mask[:border] = 0
    mask[-border:] = 0
    mask[:, :border] = 0
    mask[:, -border:] = 0
    corners = cv2.goodFeaturesToTrack(
        small, n_max, 0.01, min_distance_px / 2, mask=mask, blockSize=3
    )
    if corners is None:
        return np.zeros((0, 2), np.float32)
    pts = (corners.reshape(-1, 2) * 2.0 + 0.5).astype(np.float32)
    cv2.cornerSubPix(
        gray,
        pts.reshape(-1, 1, 2),
        (3, 3),
        (-1, -1),
        (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.03),
    )
    out: F32 = pts.reshape(-1, 2)
    return out


def track(
    prev_gray: U8 | None,
    gray: U8,
    tracks: Tracks,
    camera: CameraModel,
    opts: VoOptions,
    guess_px: F32 | None = None,
) -> Tracks:
    """The tracks followed by KLT from ``prev_gray`` into ``gray``, the lost and out-of-image
    ones dropped, then :func:`thin`. ``guess_px`` (N, 2): where the features are expected
    (after skipped frames), else no motion."""
    if prev_gray is None or len(tracks) == 0:
        return Tracks.empty()
    if opts.klt_normalize:
        prev_gray, gray = normalized_grey(prev_gray), normalized_grey(gray)
    w = opts.klt_window_px
    flags = 0
    nxt_in = None
    if guess_px is not None:
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        nxt_in = np.ascontiguousarray(guess_px, dtype=np.float32).reshape(-1, 1, 2)
    nxt, status, _ = cv2.calcOpticalFlowPyrLK(
        prev_gray,
        gray,
        tracks.px.reshape(-1, 1, 2),
        nxt_in,
        winSize=(w, w),
        maxLevel=opts.klt_levels,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03),
        flags=flags,
    )
    nxt = nxt.reshape(-1, 2)
    ok = (status.ravel() == 1) & camera.in_image(nxt, margin_px=2.0)
    if opts.klt_fb_max_px > 0 and ok.any():
        ok &= _forward_backward_ok(prev_gray, gray, tracks.px, nxt, opts)
    kept = tracks.select(ok)
    kept.prev_px = tracks.px[ok]
    kept.px = nxt[ok].astype(np.float32)
    return thin(kept, opts.min_distance_px)


def normalized_grey(gray: U8) -> U8:
    """(H, W) the image with its mean moved to 128 and its standard deviation to 48 grey
    levels: an exposure's gain and offset removed before KLT, whose brightness-constancy
    assumption a camera's auto-exposure breaks."""
    mean, std = cv2.meanStdDev(gray)
    gain = 48.0 / max(float(std[0, 0]), 1.0)
    out: U8 = cv2.convertScaleAbs(gray, alpha=gain, beta=128.0 - gain * float(mean[0, 0]))
    return out


def _forward_backward_ok(prev_gray: U8, gray: U8, px0: F32, px1: F32, opts: VoOptions) -> B:
    """(N,) whether KLT from ``gray`` back into ``prev_gray`` returns each feature at px1
    (N, 2) to within ``klt_fb_max_px`` of where it started, px0 (N, 2) (the forward-backward
    check, Kalal et al., ICPR 2010): on a repeated texture (a checkerboard floor) a window can
    lock one period off, and the way back then lands elsewhere."""
    w = opts.klt_window_px
    back, status, _ = cv2.calcOpticalFlowPyrLK(
        gray,
        prev_gray,
        np.ascontiguousarray(px1, dtype=np.float32).reshape(-1, 1, 2),
        px0.reshape(-1, 1, 2).copy(),
        winSize=(w, w),
        maxLevel=opts.klt_levels,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    err_px = np.linalg.norm(back.reshape(-1, 2) - px0, axis=1)
    out: B = (status.ravel() == 1) & (err_px < opts.klt_fb_max_px)
    return out


def thin(tracks: Tracks, min_distance_px: float) -> Tracks:
    """The tracks without those that crowd another one (closer than half
    ``min_distance_px``): when the scene recedes (a climb: the image contracts thirty-fold
    from the ground to 6 m) the features converge on one small patch; the freed slots are
    filled with new, spread-out features at the next keyframe. Tracks with a map point are
    kept first, then older."""
    tr = tracks
    n = len(tr)
    if n < 2:
        return tr
    r2 = (0.5 * min_distance_px) ** 2
    x, y = tr.px[:, 0], tr.px[:, 1]
    dx, dy = x[:, None] - x[None, :], y[:, None] - y[None, :]
    d2 = dx * dx + dy * dy  # (N, N); a tenth of the time of a sum over a (N, N, 2) axis
    close = d2 < r2
    np.fill_diagonal(close, False)
    if not close.any():
        return tr
    # a track with no close neighbour is kept and blocks none: the greedy pass runs over
    # the crowded ones only (same result as over all, a fraction of the work)
    crowded = np.flatnonzero(close.any(axis=1))
    order = crowded[np.lexsort((crowded, tr.pid[crowded] < 0))]  # with a point, then older
    keep = np.ones(n, dtype=bool)
    keep[crowded] = False
    blocked = np.zeros(n, dtype=bool)
    for i in order.tolist():
        if not blocked[i]:
            keep[i] = True
            blocked |= close[i]
    return tr.select(keep)


def coverage(tracks: Tracks, camera: CameraModel) -> float:
    """Share of the cells of a 4 x 4 grid over the image that hold a tracked map point."""
    px = tracks.px[tracks.pid >= 0]
    if len(px) == 0:
        return 0.0
    gx = np.clip((px[:, 0] / camera.width * 4).astype(int), 0, 3)
    gy = np.clip((px[:, 1] / camera.height * 4).astype(int), 0, 3)
    return len(set(zip(gx.tolist(), gy.tolist(), strict=True))) / 16.0
