"""The VO's states and how a map starts: INITIALIZING -> TRACKING <-> LOST.

INITIALIZING until the first initialisation; TRACKING; LOST from the frame where tracking
fails until a new initialisation succeeds (then ``resets`` counts up and the VO frame starts
anew). A map starts from a reference frame (:class:`Reference`, its features the anchors):
on the ground plane at once (metric, :func:`start_on_plane`) or from two views with enough
parallax (:func:`start_two_view`). The VO frame is gravity-aligned from the attitude at the
reference, its yaw the vehicle's heading then, its origin the reference camera.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from companion.geometry import se3, so3
from companion.types import F64, GroundPlane, VoState
from companion.vo.frontend import Tracks, detect
from companion.vo.initializer import initialize

if TYPE_CHECKING:
    from companion.vo.odometry import VisualOdometry

U8 = NDArray[np.uint8]


def level_R_vo_body(R_world_body: F64 | None) -> F64:
    """(3, 3) roll and pitch of the attitude with its yaw removed (the VO frame's
    orientation); identity without an attitude."""
    if R_world_body is None:
        return np.eye(3)
    roll, pitch, _ = so3.matrix_to_rpy(R_world_body)
    return so3.rpy_to_matrix(roll, pitch, 0.0)


@dataclass
class Reference:
    """The frame a new map would start from."""

    time_us: int = 0
    frames: int = 0  # frames since it was taken
    R_vo_cam: F64 = field(default_factory=lambda: np.eye(3))  # (3, 3) its camera in the VO frame
    yaw_rad: float = 0.0  # the vehicle's heading then
    yaw_known: bool = False  # whether yaw_rad is the autopilot's (else 0)

    def set_attitude(self, R_world_body: F64, R_body_cam: F64) -> None:
        """The autopilot's attitude (3, 3) at the reference, and the camera's (3, 3) mount."""
        self.R_vo_cam = level_R_vo_body(R_world_body) @ R_body_cam
        self.yaw_rad = so3.matrix_to_rpy(R_world_body)[2]
        self.yaw_known = True


def new_features(vo: VisualOdometry, gray: U8) -> None:
    """Fill the tracks up to ``max_features`` with new corners anchored at the newest
    keyframe."""
    px = detect(gray, vo.tracks.px, vo.opts.max_features - len(vo.tracks), vo.opts.min_distance_px)
    xy = vo.normalized(px) if vo.shutter is None else vo.normalized(vo.shutter.at_frame_time(px))
    vo.tracks = vo.tracks.extend(px, vo.map.keyframes[-1].kf_id, xy)


def restart_reference(vo: VisualOdometry, gray: U8, time_us: int, R_world_body: F64 | None) -> None:
    """This frame becomes the reference: new corners, the attitude's gravity and heading."""
    vo.tracks = Tracks.empty()
    px = detect(gray, vo.tracks.px, vo.opts.max_features, vo.opts.min_distance_px)
    vo.tracks = vo.tracks.extend(px, -1, vo.normalized(px))
    ref = vo.ref
    ref.time_us = time_us
    ref.frames = 0
    ref.R_vo_cam = level_R_vo_body(R_world_body) @ vo.T_body_cam[:3, :3]
    ref.yaw_rad = 0.0 if R_world_body is None else so3.matrix_to_rpy(R_world_body)[2]
    ref.yaw_known = R_world_body is not None


def _started(vo: VisualOdometry, T_cam_vo: F64, time_us: int) -> None:
    """What every new map sets: its pose, heading, keyframe clock."""
    vo.T_cam_vo = T_cam_vo
    vo.T_prev = T_cam_vo.copy()
    vo.yaw_vo_rad = vo.ref.yaw_rad  # heading of the VO frame's x axis in the world
    vo.yaw_vo_known = vo.ref.yaw_known
    vo.frames_since_kf = 0
    vo.last_keyframe_time_us = time_us


def start_on_plane(
    vo: VisualOdometry, gray: U8, time_us: int, R_world_body: F64 | None, plane: GroundPlane
) -> bool:
    """A metric map from one frame: each feature's ray meets the ground plane at depth
    z = distance / (normal . ray) (normalised ray (x, y, 1), camera frame); the VO frame
    is gravity-aligned from the attitude with the camera at its origin, its unit the
    metre. Rays within ~70 deg of the plane are left as candidates (grazing: a depth
    error of the plane grows as 1 / cos)."""
    if vo.heading_required and R_world_body is None:
        return False
    if len(vo.tracks) < vo.opts.init_min_points:
        restart_reference(vo, gray, time_us, R_world_body)
    else:  # the reference orientation of this frame, not of the frame the tracks began
        vo.ref.R_vo_cam = level_R_vo_body(R_world_body) @ vo.T_body_cam[:3, :3]
        if R_world_body is not None:
            vo.ref.yaw_rad = so3.matrix_to_rpy(R_world_body)[2]
            vo.ref.yaw_known = True
    tr = vo.tracks
    xy = vo.normalized(tr.px)
    rays = np.column_stack([xy, np.ones(len(tr))])
    cos = (rays @ plane.normal_cam) / np.linalg.norm(rays, axis=1)
    good = cos > 0.35
    if good.sum() < vo.opts.init_min_points:
        return False
    depth = plane.distance_m / (rays @ plane.normal_cam)
    T_vo_c0 = se3.make(vo.ref.R_vo_cam, np.zeros(3))
    T_c0_vo = se3.inverse(T_vo_c0)
    pts_vo = se3.transform(T_vo_c0, rays * depth[:, None])
    sigma_rel = plane.sigma_m / plane.distance_m
    vo.map.clear()
    kf0 = vo.map.new_keyframe(time_us, T_c0_vo)
    pid = tr.pid.copy()
    for i in np.flatnonzero(good):
        pid[i] = p = vo.map.add_point(pts_vo[i], float(depth[i] * sigma_rel))
        kf0.obs[p] = xy[i].copy()
    vo.tracks = Tracks(tr.px, pid, np.full(len(tr), kf0.kf_id, np.int64), xy.copy())
    vo.map.keyframes = [kf0]
    _started(vo, T_c0_vo, time_us)
    vo.metric_sigma_rel = sigma_rel
    new_features(vo, gray)
    return True


def start_two_view(vo: VisualOdometry, gray: U8, time_us: int, R_world_body: F64 | None) -> bool:
    """A map from the reference and this frame when the features moved enough between them
    (relative pose and points, companion/vo/initializer.py); its unit is the median depth."""
    tr = vo.tracks
    if len(tr) < vo.opts.init_min_points:
        return False
    if vo.heading_required and not vo.ref.yaw_known:
        # no map on a heading that is not the autopilot's: this frame is the reference
        restart_reference(vo, gray, time_us, R_world_body)
        return False
    x1 = vo.normalized(tr.px)
    flow_px = np.linalg.norm(x1 - tr.anchor_xy, axis=1) * vo.focal_px
    if np.median(flow_px) < vo.opts.init_min_parallax_px:
        return False
    gravity_c0 = vo.ref.R_vo_cam.T @ np.array([0.0, 0.0, 1.0])
    o = vo.opts
    result = initialize(
        tr.anchor_xy, x1, vo.focal_px, gravity_c0, o.pixel_sigma_px, o.min_parallax_deg
    )
    if result is None:
        return False
    good = result.good
    scale = 1.0 / float(np.median(result.points_c0[good, 2]))
    T_c1_c0 = result.T_c1_c0.copy()
    T_c1_c0[:3, 3] *= scale
    T_vo_c0 = se3.make(vo.ref.R_vo_cam, np.zeros(3))
    T_c0_vo = se3.inverse(T_vo_c0)
    T_c1_vo = T_c1_c0 @ T_c0_vo
    pts_vo = se3.transform(T_vo_c0, result.points_c0 * scale)
    vo.map.clear()  # the map starts afresh
    kf0 = vo.map.new_keyframe(vo.ref.time_us, T_c0_vo)
    kf1 = vo.map.new_keyframe(time_us, T_c1_vo)
    pid = tr.pid.copy()
    for i in np.flatnonzero(good):
        pid[i] = p = vo.map.add_point(pts_vo[i], float(result.depth_sigma[i] * scale))
        kf0.obs[p] = tr.anchor_xy[i].copy()
        kf1.obs[p] = x1[i].copy()
    anchor = np.where(good, -1, kf0.kf_id)
    vo.tracks = Tracks(tr.px, pid, anchor.astype(np.int64), tr.anchor_xy)
    vo.map.keyframes = [kf0, kf1]
    vo.metric_sigma_rel = None  # the unit is the median depth, not a metre
    _started(vo, T_c1_vo, time_us)
    new_features(vo, gray)
    return True


def step_not_tracking(
    vo: VisualOdometry,
    gray: U8,
    time_us: int,
    R_world_body: F64 | None,
    ground: GroundPlane | None,
) -> bool:
    """A frame while INITIALIZING or LOST: a map on the ground plane when given, else a new
    reference when too few features are left or it is too old, else a two-view start.
    Returns whether a map started (then TRACKING, and a reset if one had started before)."""
    vo.ref.frames += 1
    if ground is not None and start_on_plane(vo, gray, time_us, R_world_body, ground):
        started = True
    elif len(vo.tracks) < vo.opts.init_min_points or vo.ref.frames > vo.opts.init_max_frames:
        restart_reference(vo, gray, time_us, R_world_body)
        started = False
    else:
        started = start_two_view(vo, gray, time_us, R_world_body)
    if started:
        if vo.ever_initialized:
            vo.resets += 1
        vo.ever_initialized = True
        vo.state = VoState.TRACKING
    return started


def lose_map(vo: VisualOdometry) -> None:
    """TRACKING -> LOST (if tracking): the map and the tracks are dropped."""
    if vo.state == VoState.TRACKING:
        vo.state = VoState.LOST
    vo.map.clear()
