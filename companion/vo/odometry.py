"""Keyframe-based sparse monocular visual odometry.

Per frame: KLT tracking (pyramidal Lucas-Kanade) of grid-spread corners, then the camera pose
against the map by iterative PnP from a constant-velocity prediction, refined on the inliers
(RANSAC PnP only as a fallback). Keyframes are taken on translation relative to the scene
depth or loss of tracked points; at a keyframe, candidate features are triangulated against
the keyframe where they were first seen (parallax and reprojection checks, depth sigma), new
corners fill the empty image areas, and a local bundle adjustment refines the last keyframes
and their points. The map keeps at most ``max_keyframes`` keyframes and the points they see.

Frames: the VO frame ``vo`` is gravity-aligned at initialisation from the attitude input,
with yaw = the vehicle heading then, origin = first keyframe, unit = median scene depth at
initialisation (DESIGN.md section 2). Poses are kept as T_cam_vo (world to camera).

Metric initialisation on the ground (issue 18): when the caller gives a ground plane in metres
(the distance sensors' hits, the vehicle near the ground), the features of one frame are
back-projected onto it: a map without parallax whose unit is the metre (``metric_sigma_rel``
says how well). The two-view initialisation stays for starts in the air.

States (DESIGN.md section 3): INITIALIZING until the first initialisation; TRACKING;
LOST from the frame where tracking fails until a new initialisation succeeds (then ``resets``
counts up and the VO frame starts anew). A failed frame never produces a pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.errors import GeometryError
from companion.geometry import se3, so3
from companion.geometry.camera import CameraModel
from companion.types import CameraFrame, GroundPlane, VoFeatures, VoOutput, VoState
from companion.vo.ba import bundle_adjust
from companion.vo.initializer import initialize
from companion.vo.options import VoOptions
from companion.vo.pose import estimate_pose
from companion.vo.triangulation import triangulate

# an axial keyframe must have moved at least this share of vo.kf_translation_ratio (of the
# median depth): a short move's direction is noise (a low urban flight at 12 m/s had one
# "axial" keyframe while flying level, 0.03 of the depth)
AXIAL_MIN_MOVE = 0.5

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
Gravity = tuple[NDArray[np.float64], float]  # (R_vo correction (3, 3), sigma_rad)
Down = tuple[NDArray[np.float64], float]  # (gravity (down, unit) in the body frame (3,), sigma_rad)
Pending = tuple[NDArray[np.uint8], int, NDArray[np.float64] | None, Gravity | None, Down | None]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]


@dataclass
class Keyframe:
    """A keyframe: its pose T_cam_vo (4, 4), observations {point id: normalised xy (2,)} and
    the gravity direction the autopilot's attitude gave at its time (for the BA's prior)."""

    kf_id: int
    time_us: int
    T_cam_vo: F64
    obs: dict[int, F64] = field(default_factory=dict)
    gravity_cam: F64 | None = None  # (3,) gravity in the camera frame (attitude and/or IMU)
    gravity_sigma_rad: float = 0.0  # its direction's sigma [rad] (0: gravity_cam is None)


@dataclass
class Tracks:
    """Features followed from frame to frame.

    px: (N, 2) float32 pixels in the current frame; pid: (N,) map point id or -1 (candidate);
    anchor: (N,) keyframe id where a candidate was first seen (-1 = the init reference);
    anchor_xy: (N, 2) its normalised coordinates there.
    """

    px: F32
    pid: I64
    anchor: I64
    anchor_xy: F64

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
        return Tracks(self.px[keep], self.pid[keep], self.anchor[keep], self.anchor_xy[keep])

    def extend(self, px: F32, anchor: int, anchor_xy: F64) -> Tracks:
        n = len(px)
        return Tracks(
            np.concatenate([self.px, px.astype(np.float32)]),
            np.concatenate([self.pid, -np.ones(n, np.int64)]),
            np.concatenate([self.anchor, np.full(n, anchor, np.int64)]),
            np.concatenate([self.anchor_xy, anchor_xy]),
        )


class VisualOdometry:
    """Monocular VO for one camera. Feed frames in time order with :meth:`process`."""

    def __init__(
        self, camera: CameraModel, T_body_cam: F64, options: VoOptions | None = None
    ) -> None:
        self.camera = camera
        self.T_body_cam = np.asarray(T_body_cam, dtype=np.float64)
        self.opts = options or VoOptions()
        self.focal_px = 0.5 * (camera.fx + camera.fy)
        self.state = VoState.INITIALIZING
        self.resets = 0
        self.n_frames = 0
        self.ever_initialized = False
        self._prev_gray: U8 | None = None
        self.tracks = Tracks.empty()
        self.points: dict[int, F64] = {}
        self.point_sigma: dict[int, float] = {}
        self.keyframes: list[Keyframe] = []
        self._next_pid = 0
        self._next_kf = 0
        self.axial_keyframes = 0  # keyframes that took the axial prior (_axial, _gravity_cam)
        self.pad_keyframes = 0  # keyframes whose gravity the caller measured (``down``)
        self.T_cam_vo = np.eye(4)
        self._T_prev = np.eye(4)
        self._prev_time_us: int | None = None  # the last frame given to process()
        self._velocity_dt_us: int | None = None  # the interval _T_prev -> T_cam_vo spans
        self._T_pred: F64 | None = None  # this frame's predicted pose (interval-scaled)
        self._frames_since_kf = 0
        # (gray, time_us, R_world_body, gravity, down) of the frame whose keyframe is still
        # to be built
        self._pending_keyframe: Pending | None = None
        self._keyframe_added = False  # a keyframe was built since the last output
        self._ref_time_us = 0
        self._ref_frames = 0
        self._ref_R_vo_cam = np.eye(3)
        self.last_keyframe_time_us = -1
        self._ref_yaw_rad = 0.0
        self._ref_yaw_known = False
        self.yaw_vo_rad = 0.0
        # whether yaw_vo_rad is the autopilot's heading at initialisation (False: no attitude
        # was at hand, the VO frame's x axis is the camera's first heading, 0)
        self.yaw_vo_known = False
        # whether a map may start only on a reference frame with an attitude (set by the
        # caller once an autopilot's attitude stream exists): then a map never takes the
        # camera's first heading as north (a stall's re-initialisation did, turning every
        # later pose by the vehicle's heading: issue "The live service under attack ...")
        self.heading_required = False
        # the relative sigma of the VO unit in metres when the map started on a metric ground
        # plane (None: a two-view start, arbitrary unit)
        self.metric_sigma_rel: float | None = None

    # ------------------------------------------------------------------ helpers
    def _normalized(self, px: NDArray[np.floating]) -> F64:
        return self.camera.pixels_to_normalized(np.asarray(px, dtype=np.float64))

    def _detect(self, gray: U8, n_max: int) -> F32:
        """Up to n_max corners (K, 2) away from the current tracks (half-resolution detection,
        sub-pixel refinement at full resolution)."""
        if n_max <= 0:
            return np.zeros((0, 2), np.float32)
        small = cv2.pyrDown(gray)
        mask = np.full(small.shape, 255, np.uint8)
        r = max(1, int(round(self.opts.min_distance_px / 2)))
        for x, y in (self.tracks.px * 0.5).astype(int):
            cv2.circle(mask, (int(x), int(y)), r, 0, -1)
        border = 4
        mask[:border] = 0
        mask[-border:] = 0
        mask[:, :border] = 0
        mask[:, -border:] = 0
        corners = cv2.goodFeaturesToTrack(
            small, n_max, 0.01, self.opts.min_distance_px / 2, mask=mask, blockSize=3
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

    def _track(self, gray: U8, guess_px: F32 | None = None) -> None:
        """KLT from the previous image; drops lost and out-of-image features. ``guess_px``
        (N, 2): where the features are expected (after skipped frames), else no motion."""
        if self._prev_gray is None or len(self.tracks) == 0:
            self.tracks = Tracks.empty()
            return
        w = self.opts.klt_window_px
        flags = 0
        nxt_in = None
        if guess_px is not None:
            flags = cv2.OPTFLOW_USE_INITIAL_FLOW
            nxt_in = np.ascontiguousarray(guess_px, dtype=np.float32).reshape(-1, 1, 2)
        nxt, status, _ = cv2.calcOpticalFlowPyrLK(
            self._prev_gray,
            gray,
            self.tracks.px.reshape(-1, 1, 2),
            nxt_in,
            winSize=(w, w),
            maxLevel=self.opts.klt_levels,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.03),
            flags=flags,
        )
        nxt = nxt.reshape(-1, 2)
        ok = (status.ravel() == 1) & self.camera.in_image(nxt, margin_px=2.0)
        self.tracks = self.tracks.select(ok)
        self.tracks.px = nxt[ok].astype(np.float32)
        self._thin()

    def _thin(self) -> None:
        """Drop tracks that crowd another one (closer than half ``min_distance_px``): when the
        scene recedes (a climb: the image contracts thirty-fold from the ground to 6 m) the
        features converge on one small patch; the freed slots are filled with new, spread-out
        features at the next keyframe. Tracks with a map point are kept first, then older."""
        tr = self.tracks
        n = len(tr)
        if n < 2:
            return
        r2 = (0.5 * self.opts.min_distance_px) ** 2
        d2 = np.sum((tr.px[:, None, :] - tr.px[None, :, :]) ** 2, axis=2)
        close = d2 < r2
        np.fill_diagonal(close, False)
        if not close.any():
            return
        order = np.lexsort((np.arange(n), tr.pid < 0))  # with a point first, then older
        keep = np.zeros(n, dtype=bool)
        blocked = np.zeros(n, dtype=bool)
        for i in order:
            if not blocked[i]:
                keep[i] = True
                blocked |= close[i]
        self.tracks = tr.select(keep)

    def _coverage(self) -> float:
        """Share of the cells of a 4 x 4 grid over the image that hold a tracked map point."""
        px = self.tracks.px[self.tracks.pid >= 0]
        if len(px) == 0:
            return 0.0
        gx = np.clip((px[:, 0] / self.camera.width * 4).astype(int), 0, 3)
        gy = np.clip((px[:, 1] / self.camera.height * 4).astype(int), 0, 3)
        return len(set(zip(gx.tolist(), gy.tolist(), strict=True))) / 16.0

    def _gravity_R_vo_body(self, R_world_body: F64 | None) -> F64:
        """Roll and pitch of the attitude with its yaw removed (the VO frame's orientation)."""
        if R_world_body is None:
            return np.eye(3)
        roll, pitch, _ = so3.matrix_to_rpy(R_world_body)
        return so3.rpy_to_matrix(roll, pitch, 0.0)

    def _output(self, time_us: int, is_kf: bool) -> VoOutput:
        tr = self.tracks
        n = len(tr)
        pts = np.full((n, 3), np.nan)
        sig = np.full(n, np.nan)
        has = tr.pid >= 0
        for i in np.flatnonzero(has):
            pts[i] = self.points[int(tr.pid[i])]
            sig[i] = self.point_sigma[int(tr.pid[i])]
        feats = VoFeatures(tr.px.astype(np.float64), tr.pid.copy(), pts, sig)
        tracking = self.state == VoState.TRACKING
        T_vo_cam = se3.inverse(self.T_cam_vo) if tracking else np.full((4, 4), np.nan)
        return VoOutput(time_us, self.state, is_kf, T_vo_cam, feats)

    # ------------------------------------------------------------------ reference / init
    @property
    def reference_time_us(self) -> int | None:
        """The time of the frame a new map would start from (its first keyframe), None while
        tracking or before any reference."""
        if self.state == VoState.TRACKING or not len(self.tracks):
            return None
        return self._ref_time_us

    def set_reference_attitude(self, R_world_body: F64) -> None:
        """The autopilot's attitude (3, 3) at the reference frame, as known now: the
        samples around that frame's time usually arrive after the frame itself (a link's
        latency, a backlog after a stall), so the caller refines the reference's gravity and
        heading with them before the map starts. Ignored while tracking."""
        if self.state == VoState.TRACKING:
            return
        self._ref_R_vo_cam = self._gravity_R_vo_body(R_world_body) @ self.T_body_cam[:3, :3]
        self._ref_yaw_rad = so3.matrix_to_rpy(R_world_body)[2]
        self._ref_yaw_known = True

    def _restart_reference(self, gray: U8, time_us: int, R_world_body: F64 | None) -> None:
        self.tracks = Tracks.empty()
        px = self._detect(gray, self.opts.max_features)
        self.tracks = self.tracks.extend(px, -1, self._normalized(px))
        self._ref_time_us = time_us
        self._ref_frames = 0
        self._ref_R_vo_cam = self._gravity_R_vo_body(R_world_body) @ self.T_body_cam[:3, :3]
        self._ref_yaw_rad = 0.0 if R_world_body is None else so3.matrix_to_rpy(R_world_body)[2]
        self._ref_yaw_known = R_world_body is not None

    def _initialize_on_plane(
        self, gray: U8, time_us: int, R_world_body: F64 | None, plane: GroundPlane
    ) -> bool:
        """A metric map from one frame: each feature's ray meets the ground plane at depth
        z = distance / (normal . ray) (normalised ray (x, y, 1), camera frame); the VO frame
        is gravity-aligned from the attitude with the camera at its origin, its unit the
        metre. Rays within ~70 deg of the plane are left as candidates (grazing: a depth
        error of the plane grows as 1 / cos)."""
        if self.heading_required and R_world_body is None:
            return False
        if len(self.tracks) < self.opts.init_min_points:
            self._restart_reference(gray, time_us, R_world_body)
        else:  # the reference orientation of this frame, not of the frame the tracks began
            self._ref_R_vo_cam = self._gravity_R_vo_body(R_world_body) @ self.T_body_cam[:3, :3]
            if R_world_body is not None:
                self._ref_yaw_rad = so3.matrix_to_rpy(R_world_body)[2]
                self._ref_yaw_known = True
        tr = self.tracks
        xy = self._normalized(tr.px)
        rays = np.column_stack([xy, np.ones(len(tr))])
        cos = (rays @ plane.normal_cam) / np.linalg.norm(rays, axis=1)
        good = cos > 0.35
        if good.sum() < self.opts.init_min_points:
            return False
        depth = plane.distance_m / (rays @ plane.normal_cam)
        T_vo_c0 = se3.make(self._ref_R_vo_cam, np.zeros(3))
        T_c0_vo = se3.inverse(T_vo_c0)
        pts_vo = se3.transform(T_vo_c0, rays * depth[:, None])
        sigma_rel = plane.sigma_m / plane.distance_m
        self.points.clear()
        self.point_sigma.clear()
        kf0 = Keyframe(self._next_kf, time_us, T_c0_vo)
        self._next_kf += 1
        pid = tr.pid.copy()
        for i in np.flatnonzero(good):
            p = self._next_pid
            self._next_pid += 1
            self.points[p] = pts_vo[i]
            self.point_sigma[p] = float(depth[i] * sigma_rel)
            kf0.obs[p] = xy[i].copy()
            pid[i] = p
        self.tracks = Tracks(tr.px, pid, np.full(len(tr), kf0.kf_id, np.int64), xy.copy())
        self.keyframes = [kf0]
        self.T_cam_vo = T_c0_vo
        self._T_prev = T_c0_vo.copy()
        self.yaw_vo_rad = self._ref_yaw_rad
        self.yaw_vo_known = self._ref_yaw_known
        self._frames_since_kf = 0
        self.last_keyframe_time_us = time_us
        self.metric_sigma_rel = sigma_rel
        new_px = self._detect(gray, self.opts.max_features - len(self.tracks))
        self.tracks = self.tracks.extend(new_px, kf0.kf_id, self._normalized(new_px))
        return True

    def _try_initialize(self, gray: U8, time_us: int, R_world_body: F64 | None) -> bool:
        tr = self.tracks
        if len(tr) < self.opts.init_min_points:
            return False
        if self.heading_required and not self._ref_yaw_known:
            # no map on a heading that is not the autopilot's: this frame is the reference
            self._restart_reference(gray, time_us, R_world_body)
            return False
        x1 = self._normalized(tr.px)
        flow_px = np.linalg.norm(x1 - tr.anchor_xy, axis=1) * self.focal_px
        if np.median(flow_px) < self.opts.init_min_parallax_px:
            return False
        gravity_c0 = self._ref_R_vo_cam.T @ np.array([0.0, 0.0, 1.0])
        result = initialize(
            tr.anchor_xy,
            x1,
            self.focal_px,
            gravity_c0,
            self.opts.pixel_sigma_px,
            self.opts.min_parallax_deg,
        )
        if result is None:
            return False
        good = result.good
        scale = 1.0 / float(np.median(result.points_c0[good, 2]))
        T_c1_c0 = result.T_c1_c0.copy()
        T_c1_c0[:3, 3] *= scale
        T_vo_c0 = se3.make(self._ref_R_vo_cam, np.zeros(3))
        T_c0_vo = se3.inverse(T_vo_c0)
        T_c1_vo = T_c1_c0 @ T_c0_vo
        pts_vo = se3.transform(T_vo_c0, result.points_c0 * scale)
        # the map starts afresh
        self.points.clear()
        self.point_sigma.clear()
        self.keyframes = []
        kf0 = Keyframe(self._next_kf, self._ref_time_us, T_c0_vo)
        kf1 = Keyframe(self._next_kf + 1, time_us, T_c1_vo)
        self._next_kf += 2
        pid = tr.pid.copy()
        for i in np.flatnonzero(good):
            p = self._next_pid
            self._next_pid += 1
            self.points[p] = pts_vo[i]
            self.point_sigma[p] = float(result.depth_sigma[i] * scale)
            kf0.obs[p] = tr.anchor_xy[i].copy()
            kf1.obs[p] = x1[i].copy()
            pid[i] = p
        anchor = np.where(good, -1, kf0.kf_id)
        self.tracks = Tracks(tr.px, pid, anchor.astype(np.int64), tr.anchor_xy)
        self.keyframes = [kf0, kf1]
        self.metric_sigma_rel = None  # the unit is the median depth, not a metre
        self.T_cam_vo = T_c1_vo
        self.yaw_vo_rad = self._ref_yaw_rad  # heading of the VO frame's x axis in the world
        self.yaw_vo_known = self._ref_yaw_known
        self._T_prev = T_c1_vo.copy()
        self._frames_since_kf = 0
        self.last_keyframe_time_us = time_us
        new_px = self._detect(gray, self.opts.max_features - len(self.tracks))
        self.tracks = self.tracks.extend(new_px, kf1.kf_id, self._normalized(new_px))
        return True

    # ------------------------------------------------------------------ tracking
    def _interval_prediction(self, time_us: int) -> tuple[F64 | None, F32 | None]:
        """The constant-velocity prediction of this frame: (pose, where the tracks should be).

        The pose (4, 4) only when this frame's interval differs from the one the velocity was
        measured over (frames skipped upstream: the service takes the newest frame while the
        last one's keyframe work runs), else None. The track guess (N, 2) [px], the KLT's
        start, whenever the predicted flow is large (median > ``klt_predict_min_px``): from
        no motion a pyramidal KLT loses most features beyond ~20 px of flow (12 m/s at 6 m
        is ~30 px per frame at 30 Hz); slow, regular streams are tracked as before."""
        last, dt_v = self._prev_time_us, self._velocity_dt_us
        if self.state != VoState.TRACKING or last is None or not dt_v or dt_v <= 0:
            return None, None
        ratio = (time_us - last) / dt_v
        regular = 0.5 <= ratio <= 1.5
        T_rel = self.T_cam_vo @ se3.inverse(self._T_prev)  # motion over dt_v
        try:
            T_pred = se3.exp(ratio * se3.log(T_rel)) @ self.T_cam_vo
        except GeometryError:  # not rigid (numerically): keep the plain prediction
            return None, None
        pose = None if regular else T_pred
        if (ratio < 1.0 and not regular) or len(self.tracks) == 0:
            return pose, None
        tr = self.tracks
        T_new_old = T_pred @ se3.inverse(self.T_cam_vo)  # current camera -> predicted camera
        rays = np.column_stack([self._normalized(tr.px), np.ones(len(tr))])
        has = tr.pid >= 0
        p_cur = rays * self._median_depth()  # features without a 3D point: at median depth
        if has.any():
            X = np.array([self.points[int(p)] for p in tr.pid[has]])
            p_cur[has] = se3.transform(self.T_cam_vo, X)
        uv, ok = self.camera.project(se3.transform(T_new_old, p_cur))
        ok &= np.all(np.isfinite(uv), axis=1)
        if not ok.any():
            return pose, None
        flow_px = float(np.median(np.linalg.norm(uv[ok] - tr.px[ok], axis=1)))
        if regular and flow_px <= self.opts.klt_predict_min_px:
            return pose, None
        guess = np.where(ok[:, None], uv, tr.px).astype(np.float32)
        return pose, guess

    def _estimate_pose(self) -> bool:
        tr = self.tracks
        has = tr.pid >= 0
        if has.sum() < self.opts.min_tracked_points:
            return False
        X = np.array([self.points[int(p)] for p in tr.pid[has]])
        xy = self._normalized(tr.px[has])
        # constant-velocity prediction (over this frame's interval when frames were skipped)
        T_pred = self._T_pred
        if T_pred is None:
            T_pred = self.T_cam_vo @ se3.inverse(self._T_prev) @ self.T_cam_vo
        result = estimate_pose(
            X, xy, T_pred, self.focal_px, self.opts.inlier_px, self.opts.min_tracked_points
        )
        if result is None:
            return False
        T_new = result.T_cam_vo
        inl = result.inliers
        # a physically impossible jump is a failure, never a pose
        dR = so3.angle_between(T_new[:3, :3], self.T_cam_vo[:3, :3])
        if np.degrees(dR) > self.opts.max_rotation_deg_per_frame or not np.all(np.isfinite(T_new)):
            return False
        # drop map-point outliers from the tracks
        keep = np.ones(len(tr), dtype=bool)
        keep[np.flatnonzero(has)[~inl]] = False
        self.tracks = tr.select(keep)
        self._T_prev = self.T_cam_vo
        self.T_cam_vo = T_new
        return True

    def _anchor_pose(self, anchor: int) -> F64 | None:
        for kf in self.keyframes:
            if kf.kf_id == anchor:
                return kf.T_cam_vo
        return None

    def _check_candidates(self) -> None:
        """Epipolar (Sampson) check of candidates against their anchor keyframe."""
        tr = self.tracks
        cand = np.flatnonzero(tr.pid < 0)
        if len(cand) == 0:
            return
        xy = self._normalized(tr.px[cand])
        keep = np.ones(len(tr), dtype=bool)
        for a in np.unique(tr.anchor[cand]):
            T_a = self._anchor_pose(int(a))
            if T_a is None:
                continue
            sel = tr.anchor[cand] == a
            T_c_a = self.T_cam_vo @ se3.inverse(T_a)
            t = T_c_a[:3, 3]
            if np.linalg.norm(t) < 1e-9:
                continue
            E = so3.hat(t) @ T_c_a[:3, :3]
            h0 = np.column_stack([tr.anchor_xy[cand[sel]], np.ones(sel.sum())])
            h1 = np.column_stack([xy[sel], np.ones(sel.sum())])
            Ex0 = h0 @ E.T
            Etx1 = h1 @ E
            num = np.einsum("ij,ij->i", h1, Ex0) ** 2
            den = Ex0[:, 0] ** 2 + Ex0[:, 1] ** 2 + Etx1[:, 0] ** 2 + Etx1[:, 1] ** 2
            sampson_px = np.sqrt(num / np.maximum(den, 1e-300)) * self.focal_px
            keep[cand[sel]] = sampson_px < 2.0 * self.opts.inlier_px
        self.tracks = tr.select(keep)

    def _median_depth(self) -> float:
        has = self.tracks.pid >= 0
        if not has.any():
            return 1.0
        X = np.array([self.points[int(p)] for p in self.tracks.pid[has]])
        z = se3.transform(self.T_cam_vo, X)[:, 2]
        return float(np.median(z))

    def _need_keyframe(self) -> bool:
        kf = self.keyframes[-1]
        c_kf = -kf.T_cam_vo[:3, :3].T @ kf.T_cam_vo[:3, 3]
        c = -self.T_cam_vo[:3, :3].T @ self.T_cam_vo[:3, 3]
        moved = float(np.linalg.norm(c - c_kf)) / max(self._median_depth(), 1e-9)
        n_pts = int((self.tracks.pid >= 0).sum())
        if moved > self.opts.kf_translation_ratio:
            return True
        if moved < 0.01:
            return False  # hovering: a keyframe would add no parallax
        if n_pts < self.opts.kf_tracked_ratio * max(len(kf.obs), 1):
            return True
        if self._coverage() < self.opts.kf_min_coverage:
            return True  # the points huddle in part of the image (a climb, a turn)
        if len(self.tracks) < 0.5 * self.opts.max_features:
            return True
        return self._frames_since_kf >= self.opts.kf_max_frames

    # ------------------------------------------------------------------ keyframes
    def _axial(self) -> bool:
        """Whether the camera reached this pose moving along its optical axis (within
        ``axial_max_angle_deg``) since the last keyframe: a climb or descent over the ground,
        where a tilt and a sideways move look alike in the images (ba.py)."""
        if not self.keyframes:
            return False
        T_prev = self.keyframes[-1].T_cam_vo
        c_prev = -T_prev[:3, :3].T @ T_prev[:3, 3]
        c_now = -self.T_cam_vo[:3, :3].T @ self.T_cam_vo[:3, 3]
        d_cam = self.T_cam_vo[:3, :3] @ (c_now - c_prev)
        n = float(np.linalg.norm(d_cam))
        min_move = AXIAL_MIN_MOVE * self.opts.kf_translation_ratio * self._median_depth()
        if not np.isfinite(n) or n < min_move:  # a keyframe taken for coverage, not distance
            return False
        return bool(abs(float(d_cam[2])) >= n * np.cos(np.radians(self.opts.axial_max_angle_deg)))

    def _gravity_cam(
        self,
        R_world_body: F64 | None,
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
        attitude's sigma stays in. ``axial`` (:meth:`_axial`, a climb or a descent): the
        attitude's gravity alone at ``axial_gravity_sigma_deg`` (when > 0), tighter than the
        cruise's: there the images leave the tilt free (ba.py) and the accelerometer's window
        straddles the lift-off. ``down``: a gravity the caller measured at this frame (body
        frame, with its sigma: the distance sensors over the take-off pad,
        companion/attitude/pad.py) replaces all of these. None (and 0) without an attitude or
        with ``gravity_sigma_deg`` 0."""
        sigma_ap = np.radians(self.opts.gravity_sigma_deg)
        if R_world_body is None or sigma_ap <= 0:
            return None, 0.0
        if down is not None:
            return self.T_body_cam[:3, :3].T @ down[0], float(down[1])
        g: F64 = self.T_body_cam[:3, :3].T @ (R_world_body.T @ np.array([0.0, 0.0, 1.0]))
        if axial and self.opts.axial_gravity_sigma_deg > 0:
            return g, float(np.radians(self.opts.axial_gravity_sigma_deg))
        if gravity is None or gravity[1] <= 0:
            return g, float(sigma_ap)
        R_cam_vo = self.T_cam_vo[:3, :3]
        g = R_cam_vo @ (gravity[0] @ (R_cam_vo.T @ g))
        return g, float(np.hypot(sigma_ap, gravity[1]))

    def _add_keyframe(
        self,
        gray: U8,
        time_us: int,
        R_world_body: F64 | None = None,
        gravity: Gravity | None = None,
        down: Down | None = None,
    ) -> None:
        axial = self.opts.axial_gravity_sigma_deg > 0 and self._axial()  # off: not worked out
        self.axial_keyframes += axial and down is None
        self.pad_keyframes += down is not None and R_world_body is not None
        g_cam, g_sigma = self._gravity_cam(R_world_body, gravity, axial, down)
        kf = Keyframe(
            self._next_kf,
            time_us,
            self.T_cam_vo.copy(),
            gravity_cam=g_cam,
            gravity_sigma_rad=g_sigma,
        )
        self._next_kf += 1
        tr = self.tracks
        xy = self._normalized(tr.px)
        for i in np.flatnonzero(tr.pid >= 0):
            kf.obs[int(tr.pid[i])] = xy[i]
        # triangulate candidates against their anchor keyframes
        pid = tr.pid.copy()
        anchor = tr.anchor.copy()
        anchor_xy = tr.anchor_xy.copy()
        cand = np.flatnonzero(pid < 0)
        for a in np.unique(anchor[cand]):
            sel = cand[anchor[cand] == a]
            T_a = self._anchor_pose(int(a))
            if T_a is None:  # anchor gone: start over from this keyframe
                anchor[sel] = kf.kf_id
                anchor_xy[sel] = xy[sel]
                continue
            tri = triangulate(
                T_a,
                kf.T_cam_vo,
                anchor_xy[sel],
                xy[sel],
                self.focal_px,
                self.opts.pixel_sigma_px,
                self.opts.min_parallax_deg,
                2.0 * self.opts.inlier_px,
            )
            kf_a = next(k for k in self.keyframes if k.kf_id == a)
            for j, i in enumerate(sel):
                if not tri.ok[j]:
                    continue
                p = self._next_pid
                self._next_pid += 1
                self.points[p] = tri.points_vo[j]
                self.point_sigma[p] = float(tri.depth_sigma[j])
                kf_a.obs[p] = anchor_xy[i].copy()
                kf.obs[p] = xy[i].copy()
                pid[i] = p
        self.tracks = Tracks(tr.px, pid, anchor, anchor_xy)
        self.keyframes.append(kf)
        new_px = self._detect(gray, self.opts.max_features - len(self.tracks))
        self.tracks = self.tracks.extend(new_px, kf.kf_id, self._normalized(new_px))
        self._local_ba()
        self._bound_map()
        self._frames_since_kf = 0
        self.last_keyframe_time_us = time_us

    def _local_ba(self) -> None:
        window = self.keyframes[-self.opts.window_keyframes :]
        if len(window) < 3 or self.opts.ba_iterations == 0:
            return
        count: dict[int, int] = {}
        for kf in window:
            for p in kf.obs:
                count[p] = count.get(p, 0) + 1
        pids = [p for p, c in count.items() if c >= 2]
        if len(pids) < 10:
            return
        index = {p: i for i, p in enumerate(pids)}
        obs_cam, obs_pt, obs_xy = [], [], []
        for k, kf in enumerate(window):
            for p, xy in kf.obs.items():
                if p in index:
                    obs_cam.append(k)
                    obs_pt.append(index[p])
                    obs_xy.append(xy)
        T = np.stack([kf.T_cam_vo for kf in window])
        X = np.stack([self.points[p] for p in pids])
        fixed = np.zeros(len(window), dtype=bool)
        fixed[:2] = True
        gravity = np.array(
            [kf.gravity_cam if kf.gravity_cam is not None else np.full(3, np.nan) for kf in window]
        )
        sigma_rad = np.array([kf.gravity_sigma_rad for kf in window])
        weight = np.zeros(len(window))
        weight[sigma_rad > 0] = self.opts.pixel_sigma_px / sigma_rad[sigma_rad > 0]
        res = bundle_adjust(
            T,
            X,
            np.asarray(obs_cam),
            np.asarray(obs_pt),
            np.asarray(obs_xy),
            fixed,
            self.focal_px,
            huber_px=self.opts.inlier_px,
            iterations=self.opts.ba_iterations,
            gravity_cam=gravity,
            gravity_weight=weight,
        )
        for k, kf in enumerate(window):
            kf.T_cam_vo = res.T_cam_vo[k]
        for i, p in enumerate(pids):
            self.points[p] = res.points_vo[i]
        # observations that stay far off after BA are removed
        bad = res.residual_px > 3.0 * self.opts.inlier_px
        for o in np.flatnonzero(bad):
            window[obs_cam[o]].obs.pop(pids[obs_pt[o]], None)
        self.T_cam_vo = window[-1].T_cam_vo.copy()

    def _bound_map(self) -> None:
        while len(self.keyframes) > self.opts.max_keyframes:
            self.keyframes.pop(0)
        seen: set[int] = set()
        for kf in self.keyframes:
            seen.update(kf.obs)
        tracked = set(int(p) for p in self.tracks.pid if p >= 0)
        for p in list(self.points):
            if p not in seen and p not in tracked:
                del self.points[p]
                del self.point_sigma[p]
        # tracked points no keyframe sees any more become candidates again
        lost = np.array([p >= 0 and int(p) not in seen for p in self.tracks.pid], dtype=bool)
        if lost.any():
            tr = self.tracks
            xy = self._normalized(tr.px[lost])
            tr.pid[lost] = -1
            tr.anchor[lost] = self.keyframes[-1].kf_id
            tr.anchor_xy[lost] = xy

    # ------------------------------------------------------------------ entry point
    def process(
        self,
        frame: CameraFrame,
        R_world_body: F64 | None = None,
        ground: GroundPlane | None = None,
        gravity: Gravity | None = None,
        down: Down | None = None,
    ) -> VoOutput:
        """One frame in, one VoOutput out. ``R_world_body``: the attitude at the frame time
        (used to gravity-align the VO frame at initialisation), or None. ``ground``: the
        ground plane in metres when the caller knows it (the vehicle near the ground): while
        not tracking, the map then starts on it at once, metric, without parallax.
        ``gravity``: (R_vo (3, 3), sigma_rad), the correction of the attitude's tilt in this VO
        map's frame that the caller measured (companion/attitude/gravity.py), applied to the
        keyframe prior's gravity; None: the attitude's alone. ``down``: (gravity in the body
        frame (3,), sigma_rad) measured by the caller at this frame, which replaces the
        attitude's for this frame's keyframe (the take-off pad's, companion/attitude/pad.py)."""
        self.finish_pending()  # the previous frame's keyframe, if the caller did not run it
        self.n_frames += 1
        img = frame.image_bgr
        gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
        is_kf = self._keyframe_added
        self._keyframe_added = False
        self._T_pred, guess_px = self._interval_prediction(frame.time_us)
        self._track(gray, guess_px)
        if self.state != VoState.TRACKING:
            self._ref_frames += 1
            if ground is not None and self._initialize_on_plane(
                gray, frame.time_us, R_world_body, ground
            ):
                if self.ever_initialized:
                    self.resets += 1
                self.ever_initialized = True
                self.state = VoState.TRACKING
                is_kf = True
            elif len(self.tracks) < self.opts.init_min_points or (
                self._ref_frames > self.opts.init_max_frames
            ):
                self._restart_reference(gray, frame.time_us, R_world_body)
            elif self._try_initialize(gray, frame.time_us, R_world_body):
                if self.ever_initialized:
                    self.resets += 1
                self.ever_initialized = True
                self.state = VoState.TRACKING
                is_kf = True
        elif not self._estimate_pose():
            self.state = VoState.LOST
            self.points.clear()
            self.point_sigma.clear()
            self.keyframes = []
            # with an attitude stream, the reference's attitude is refined by the caller from
            # the samples that arrive after this frame (set_reference_attitude); without one
            # it may be this frame's nearest sample, up to the caller's gap old
            self._restart_reference(gray, frame.time_us, R_world_body)
        else:
            self._check_candidates()
            self._frames_since_kf += 1
            if self._need_keyframe():  # built after this frame's output (finish_pending)
                self._pending_keyframe = (gray, frame.time_us, R_world_body, gravity, down)
        self._prev_gray = gray
        self._T_pred = None
        if self.state == VoState.TRACKING and self._prev_time_us is not None:
            self._velocity_dt_us = frame.time_us - self._prev_time_us
        self._prev_time_us = frame.time_us
        return self._output(frame.time_us, is_kf)

    def lose(self) -> None:
        """Drop tracking and the map (the input was interrupted: a camera fault or a gap).
        The next frames start a new initialisation; its success counts a reset, so the
        poses after it carry a new reset_counter."""
        if self.state == VoState.TRACKING:
            self.state = VoState.LOST
        self.points.clear()
        self.point_sigma.clear()
        self.keyframes = []
        self.tracks = Tracks.empty()
        self._pending_keyframe = None
        self._prev_gray = None

    def finish_pending(self) -> bool:
        """Build the keyframe the last frame asked for (new points, triangulation, local BA),
        off the latency-critical path: the service calls this after publishing; otherwise
        the next ``process`` does. The next output has is_keyframe = True. Returns whether
        a keyframe was built."""
        pending, self._pending_keyframe = self._pending_keyframe, None
        if pending is None or self.state != VoState.TRACKING:
            return False
        self._add_keyframe(*pending)
        self._keyframe_added = True
        return True
