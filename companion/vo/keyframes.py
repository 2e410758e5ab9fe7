"""The VO's keyframe policy: when to take a keyframe, and the gravity prior it carries.

Frames: poses are T_cam_vo (4, 4, VO -> camera); a camera centre is -R^T t in the VO frame;
gravity is the unit down direction; angles in radians unless named ``_deg``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from companion.geometry.camera import CameraModel
from companion.types import F64
from companion.vo.frontend import Tracks, coverage
from companion.vo.map import Keyframe
from companion.vo.options import VoOptions

U8 = NDArray[np.uint8]
Gravity = tuple[F64, float]  # (R_vo correction (3, 3), sigma_rad)
Down = tuple[F64, float]  # (gravity (down, unit) in the body frame (3,), sigma_rad)

# an axial keyframe must have moved at least this share of vo.kf_translation_ratio (of the
# median depth): a short move's direction is noise (a low urban flight at 12 m/s had one
# "axial" keyframe while flying level, 0.03 of the depth)
AXIAL_MIN_MOVE = 0.5


class PendingKeyframe(NamedTuple):
    """A frame whose keyframe is still to be built (after the frame's pose is out)."""

    gray: U8  # (H, W) the frame's grey image
    time_us: int
    R_world_body: F64 | None  # (3, 3) the autopilot's attitude at the frame
    gravity: Gravity | None  # the caller's tilt correction in the VO frame
    down: Down | None  # the caller's measured gravity in the body frame
    held: bool = False  # the pose is a rotation held in place (odometry._hold_rotation)


def camera_centre(T_cam_vo: F64) -> F64:
    """(3,) the camera's position in the VO frame."""
    c: F64 = -T_cam_vo[:3, :3].T @ T_cam_vo[:3, 3]
    return c


def need_keyframe(
    last: Keyframe,
    T_cam_vo: F64,
    tracks: Tracks,
    median_depth: float,
    frames_since_kf: int,
    camera: CameraModel,
    opts: VoOptions,
) -> bool:
    """Whether the frame at T_cam_vo becomes a keyframe: moved ``kf_translation_ratio`` of
    the median depth since ``last``; or fewer tracks left than ``kf_low_tracks_ratio`` of
    ``max_features`` (a view turned away in place); or (unless hovering) too few of its points still
    tracked, the points huddled in part of the image, too few tracks, or too many frames."""
    moved = float(np.linalg.norm(camera_centre(T_cam_vo) - camera_centre(last.T_cam_vo)))
    moved /= max(median_depth, 1e-9)
    n_pts = int((tracks.pid >= 0).sum())
    if moved > opts.kf_translation_ratio:
        return True
    if len(tracks) < opts.kf_low_tracks_ratio * opts.max_features:
        return True  # even hovering or turning in place: new features before the tracks starve
    if moved < 0.01:
        return False  # hovering: a keyframe would add no parallax
    if n_pts < opts.kf_tracked_ratio * max(len(last.obs), 1):
        return True
    if coverage(tracks, camera) < opts.kf_min_coverage:
        return True  # the points huddle in part of the image (a climb, a turn)
    if len(tracks) < 0.5 * opts.max_features:
        return True
    return frames_since_kf >= opts.kf_max_frames


def is_axial(last: Keyframe | None, T_cam_vo: F64, median_depth: float, opts: VoOptions) -> bool:
    """Whether the camera reached T_cam_vo moving along its optical axis (within
    ``axial_max_angle_deg``) since the ``last`` keyframe: a climb or descent over the ground,
    where a tilt and a sideways move look alike in the images (ba.py)."""
    if last is None:
        return False
    d_cam = T_cam_vo[:3, :3] @ (camera_centre(T_cam_vo) - camera_centre(last.T_cam_vo))
    n = float(np.linalg.norm(d_cam))
    min_move = AXIAL_MIN_MOVE * opts.kf_translation_ratio * median_depth
    if not np.isfinite(n) or n < min_move:  # a keyframe taken for coverage, not distance
        return False
    return bool(abs(float(d_cam[2])) >= n * np.cos(np.radians(opts.axial_max_angle_deg)))


def gravity_cam(
    R_world_body: F64 | None,
    T_body_cam: F64,
    T_cam_vo: F64,
    opts: VoOptions,
    gravity: Gravity | None = None,
    axial: bool = False,
    down: Down | None = None,
) -> tuple[F64 | None, float]:
    """(3,) gravity (down) in the camera frame and its sigma [rad] for the BA's prior.

    From the attitude: R_cam_body R_body_world e_z (the VO frame's yaw does not matter:
    gravity is its +z too), sigma ``gravity_sigma_deg``. With ``gravity`` = (R_vo (3, 3),
    sigma_rad), the correction of the autopilot's tilt that the caller measured in the VO
    frame (the accelerometer against our motion, companion/attitude/gravity.py): the
    attitude's gravity turned by R_vo seen from the camera (R_cam_vo R_vo R_cam_vo^T),
    sigma hypot(``gravity_sigma_deg``, sigma_rad): the correction removes the attitude's
    error averaged over its window, not its fast part (a keyframe's own error), so the
    attitude's sigma stays in. ``axial`` (:func:`is_axial`, a climb or a descent): the
    attitude's gravity alone at ``axial_gravity_sigma_deg`` (when > 0), tighter than the
    cruise's: there the images leave the tilt free (ba.py) and the accelerometer's window
    straddles the lift-off. ``down``: a gravity the caller measured at this frame (body
    frame, with its sigma: the distance sensors over the take-off pad,
    companion/attitude/pad.py) replaces all of these. None (and 0) without an attitude or
    with ``gravity_sigma_deg`` 0."""
    sigma_ap = np.radians(opts.gravity_sigma_deg)
    if R_world_body is None or sigma_ap <= 0:
        return None, 0.0
    if down is not None:
        return T_body_cam[:3, :3].T @ down[0], float(down[1])
    g: F64 = T_body_cam[:3, :3].T @ (R_world_body.T @ np.array([0.0, 0.0, 1.0]))
    if axial and opts.axial_gravity_sigma_deg > 0:
        return g, float(np.radians(opts.axial_gravity_sigma_deg))
    if gravity is None or gravity[1] <= 0:
        return g, float(sigma_ap)
    R_cam_vo = T_cam_vo[:3, :3]
    g = R_cam_vo @ (gravity[0] @ (R_cam_vo.T @ g))
    return g, float(np.hypot(sigma_ap, gravity[1]))
