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
initialisation. Poses are kept as T_cam_vo (world to camera).

Metric initialisation on the ground (issue 18): when the caller gives a ground plane in metres
(the distance sensors' hits, the vehicle near the ground), the features of one frame are
back-projected onto it: a map without parallax whose unit is the metre (``metric_sigma_rel``
says how well). The two-view initialisation stays for starts in the air.

Turning in place (issue "Real sequences", 2026-11-28): when PnP fails but the 2D tracks agree
on one rotation from the frame before (companion/vo/rotation.py), the pose follows it with the
camera's centre held, for at most ``rotation_hold_frames`` frames in a row; a keyframe taken
meanwhile gives its new features a depth prior (``rotation_depth_prior``), so the map does not
starve while there is no parallax to triangulate.

States (companion/vo/states.py): INITIALIZING until the first initialisation; TRACKING;
LOST from the frame where tracking fails until a new initialisation succeeds (then ``resets``
counts up and the VO frame starts anew). A failed frame never produces a pose.

This module is the facade and the tracking step; the parts sit beside it as SVO splits them:
``frontend`` (corners and KLT), ``map`` (keyframes, points, local BA), ``keyframes`` (when to
take one, its gravity prior), ``states`` (the state machine and the map's start).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.errors import GeometryError
from companion.geometry import se3, so3
from companion.geometry.camera import CameraModel
from companion.types import F64, CameraFrame, GroundPlane, VoFeatures, VoOutput, VoState
from companion.vo import keyframes as policy
from companion.vo.frontend import Tracks, scaled_to_image, track
from companion.vo.keyframes import Down, Gravity, PendingKeyframe
from companion.vo.map import VoMap
from companion.vo.options import VoOptions
from companion.vo.pose import estimate_pose
from companion.vo.rolling_shutter import ShutterCorrection
from companion.vo.rotation import fit_rotation
from companion.vo.stage_times import Laps
from companion.vo.states import (
    Reference,
    lose_map,
    new_features,
    restart_reference,
    step_not_tracking,
)

F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]


class VisualOdometry:
    """Monocular VO for one camera. Feed frames in time order with :meth:`process`."""

    def __init__(
        self,
        camera: CameraModel,
        T_body_cam: F64,
        options: VoOptions | None = None,
        readout_s: float = 0.0,
    ) -> None:
        """``readout_s``: the camera's rolling-shutter readout time [s] (0: a global shutter);
        the tracks' pixels are then moved to the frame's stamp for the geometry
        (companion/vo/rolling_shutter.py)."""
        self.camera = camera
        self.shutter = ShutterCorrection(readout_s, camera.height) if readout_s > 0 else None
        self.T_body_cam = np.asarray(T_body_cam, dtype=np.float64)
        self.opts = scaled_to_image(options or VoOptions(), camera.width, camera.height)
        self.focal_px = 0.5 * (camera.fx + camera.fy)
        self.state = VoState.INITIALIZING
        self.resets = 0
        self.n_frames = 0
        self.ever_initialized = False
        self._prev_gray: U8 | None = None
        self.tracks = Tracks.empty()
        self.map = VoMap()
        self.axial_keyframes = 0  # keyframes that took the axial prior (keyframes.is_axial)
        self.pad_keyframes = 0  # keyframes whose gravity the caller measured (``down``)
        self.T_cam_vo = np.eye(4)
        self.T_prev = np.eye(4)  # the pose of the frame before
        self._prev_time_us: int | None = None  # the last frame given to process()
        self._velocity_dt_us: int | None = None  # the interval T_prev -> T_cam_vo spans
        self._T_pred: F64 | None = None  # this frame's predicted pose (interval-scaled)
        self.frames_since_kf = 0
        self.laps = Laps()  # the wall time of each stage of the last frame [ms]
        self.rotation_frames = 0  # frames in a row whose pose is a rotation held in place
        self.rotation_held = 0  # frames whose pose was held on a rotation (all maps)
        self.outside_lens = 0  # tracks dropped: at the frame's stamp outside the lens model
        self._pending_keyframe: PendingKeyframe | None = None  # built by finish_pending
        self._keyframe_question: PendingKeyframe | None = None  # asked by decide_keyframe
        self._keyframe_added = False  # a keyframe was built since the last output
        self._ba_step_due = False  # refine_map has not yet run since the last pose
        self.ref = Reference()  # the frame a new map would start from
        self.last_keyframe_time_us = -1
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

    def normalized(self, px: NDArray[np.floating]) -> F64:
        """(N, 2) normalised camera coordinates of pixels (N, 2)."""
        return self.camera.pixels_to_normalized(np.asarray(px, dtype=np.float64))

    def frame_xy(self, tr: Tracks, sel: NDArray[np.bool_] | None = None) -> F64:
        """(N, 2) normalised coordinates of the tracks (those of ``sel``) at the frame's stamp:
        their pixels, moved along their image motion to the middle of the readout under a
        rolling shutter (companion/vo/rolling_shutter.py).

        Computed once for all the tracks and kept in ``tr.xy`` (each point's undistortion
        stops on its own: a subset's values are those of the whole set); GeometryError when
        a selected point is outside the lens model."""
        if tr.xy is None or len(tr.xy) != len(tr):
            tr.xy = self._stamp_xy(tr)
        xy = tr.xy if sel is None else tr.xy[sel]
        if not np.isfinite(xy).all():
            raise GeometryError("undistortion did not converge (point outside the lens model)")
        return xy

    def _stamp_xy(self, tr: Tracks) -> F64:
        """(N, 2) the tracks' normalised coordinates at the frame's stamp, NaN where the
        undistortion does not converge (the values ``frame_xy`` keeps in ``tracks.xy``)."""
        px = tr.px if self.shutter is None else self.shutter.at_frame_time(tr.px, tr.prev_px)
        return self.camera.pixels_to_normalized(px, nan_where_unconverged=True)

    def _drop_outside_lens(self) -> None:
        """Under a rolling shutter: drop the tracks whose position at the frame's stamp is
        outside the lens model (``frame_xy`` would raise). The correction moves each track
        along its image motion over the frame interval; over a 1 us interval (a clock that
        keeps its stamps in order by a microsecond) a few pixels of motion carry a track far
        past the image, where a strong lens does not invert: the look-alike of the real
        downward flight (k1 -0.33) stopped ``companion eval`` there. The others' coordinates
        are kept in ``tracks.xy``, the values ``frame_xy`` gives."""
        tr = self.tracks
        if self.shutter is None or len(tr) == 0:
            return
        tr.xy = self._stamp_xy(tr)
        ok: NDArray[np.bool_] = np.all(np.isfinite(tr.xy), axis=1)
        if not ok.all():
            self.tracks = tr.select(ok)
            self.outside_lens += int((~ok).sum())

    def pixels_at_stamp(self) -> F64:
        """(N, 2) the current tracks' pixels [px, raw image] at the frame's stamp: as tracked
        under a global shutter, moved along their image motion to the middle of the readout
        under a rolling shutter (companion/vo/rolling_shutter.py, equation (2)); in the
        order of the last output's features."""
        tr = self.tracks
        if self.shutter is None:
            return tr.px.astype(np.float64)
        return self.shutter.at_frame_time(tr.px, tr.prev_px)

    def _output(self, time_us: int, is_kf: bool) -> VoOutput:
        tr = self.tracks
        n = len(tr)
        pts = np.full((n, 3), np.nan)
        sig = np.full(n, np.nan)
        has = tr.pid >= 0
        if has.any():
            pts[has] = self.map.points_of(tr.pid[has])
            sig[has] = [self.map.point_sigma[p] for p in tr.pid[has].tolist()]
        feats = VoFeatures(tr.px.astype(np.float64), tr.pid.copy(), pts, sig)
        tracking = self.state == VoState.TRACKING
        T_vo_cam = se3.inverse(self.T_cam_vo) if tracking else np.full((4, 4), np.nan)
        return VoOutput(time_us, self.state, is_kf, T_vo_cam, feats)

    @property
    def reference_time_us(self) -> int | None:
        """The time of the frame a new map would start from (its first keyframe), None while
        tracking or before any reference."""
        if self.state == VoState.TRACKING or not len(self.tracks):
            return None
        return self.ref.time_us

    def set_reference_attitude(self, R_world_body: F64) -> None:
        """The autopilot's attitude (3, 3) at the reference frame, as known now: the
        samples around that frame's time usually arrive after the frame itself (a link's
        latency, a backlog after a stall), so the caller refines the reference's gravity and
        heading with them before the map starts. Ignored while tracking."""
        if self.state == VoState.TRACKING:
            return
        self.ref.set_attitude(R_world_body, self.T_body_cam[:3, :3])

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
        T_rel = self.T_cam_vo @ se3.inverse(self.T_prev)  # motion over dt_v
        if regular:  # the guess only: the motion of the last interval, as it was
            T_new_old, pose = T_rel, None  # current camera -> predicted camera
        else:
            try:
                T_pred = se3.exp(ratio * se3.log(T_rel)) @ self.T_cam_vo
            except GeometryError:  # not rigid (numerically): keep the plain prediction
                return None, None
            T_new_old, pose = T_pred @ se3.inverse(self.T_cam_vo), T_pred
        if (ratio < 1.0 and not regular) or len(self.tracks) == 0:
            return pose, None
        tr = self.tracks
        xy = self.frame_xy(tr) if self.shutter is None else self.normalized(tr.px)
        rays = np.column_stack([xy, np.ones(len(tr))])
        has = tr.pid >= 0
        if has.any():  # the points in the camera; the others at their median depth
            P_cam = se3.transform(self.T_cam_vo, self.map.points_of(tr.pid[has]))
            p_cur = rays * float(np.median(P_cam[:, 2]))
            p_cur[has] = P_cam
        else:
            p_cur = rays  # no depth known: 1, as VoMap.median_depth says
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
        X = self.map.points_of(tr.pid[has])
        xy = self.frame_xy(tr, has)
        # constant-velocity prediction (over this frame's interval when frames were skipped)
        T_pred = self._T_pred
        if T_pred is None:
            T_pred = self.T_cam_vo @ se3.inverse(self.T_prev) @ self.T_cam_vo
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
        self.T_prev = self.T_cam_vo
        self.T_cam_vo = T_new
        self.rotation_frames = 0
        return True

    def _hold_rotation(self) -> bool:
        """This frame's pose when PnP failed: the rotation every 2D track agrees on
        (companion/vo/rotation.py) from the frame before, the camera's centre held, for at
        most ``rotation_hold_frames`` frames in a row. False when off, too long, or the
        tracks do not fit one rotation (the camera also moved: parallax)."""
        o = self.opts
        tr = self.tracks
        if self.rotation_frames >= o.rotation_hold_frames or tr.prev_px is None:
            return False
        if len(tr) < o.min_tracked_points:
            return False
        fit = fit_rotation(
            self.normalized(tr.prev_px),
            self.normalized(tr.px),
            o.rotation_inlier_px / self.focal_px,
            o.min_tracked_points,
        )
        if fit is None or fit.inliers.mean() < o.rotation_min_inlier_ratio:
            return False
        if np.degrees(so3.angle_between(fit.R_c1_c0, np.eye(3))) > o.max_rotation_deg_per_frame:
            return False
        R_new = fit.R_c1_c0 @ self.T_cam_vo[:3, :3]
        centre = policy.camera_centre(self.T_cam_vo)
        self.tracks = tr.select(fit.inliers)
        self.T_prev = self.T_cam_vo
        self.T_cam_vo = se3.make(R_new, -R_new @ centre)
        self.rotation_frames += 1
        self.rotation_held += 1
        return True

    def _check_candidates(self) -> None:
        """Epipolar (Sampson) check of candidates against their anchor keyframe."""
        tr = self.tracks
        cand = np.flatnonzero(tr.pid < 0)
        if len(cand) == 0:
            return
        xy = self.frame_xy(tr, tr.pid < 0)
        keep = np.ones(len(tr), dtype=bool)
        for a in np.unique(tr.anchor[cand]):
            kf_a = self.map.keyframe(int(a))
            if kf_a is None:
                continue
            T_a = kf_a.T_cam_vo
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

    def _add_keyframe(self, pending: PendingKeyframe) -> None:
        """The keyframe of a pending frame (at the current pose): its gravity prior, its
        observations, the candidates triangulated, new corners, the local BA, the map
        bounded."""
        gray, time_us, R_world_body, gravity, down, held = pending
        o = self.opts
        self._end_local_ba()  # the last keyframe's BA, if still under way: finished first
        axial = False
        if o.axial_gravity_sigma_deg > 0:  # off: not worked out
            last = self.map.keyframes[-1] if self.map.keyframes else None
            depth = self.map.median_depth(self.tracks, self.T_cam_vo)
            axial = policy.is_axial(last, self.T_cam_vo, depth, o)
        self.axial_keyframes += axial and down is None
        self.pad_keyframes += down is not None and R_world_body is not None
        g_cam, g_sigma = policy.gravity_cam(
            R_world_body, self.T_body_cam, self.T_cam_vo, o, gravity, axial, down
        )
        kf = self.map.new_keyframe(time_us, self.T_cam_vo.copy(), g_cam, g_sigma)
        tr = self.tracks
        xy = self.frame_xy(tr)
        for i in np.flatnonzero(tr.pid >= 0):
            kf.obs[int(tr.pid[i])] = xy[i]
        self.tracks = self.map.triangulate_candidates(tr, kf, xy, self.focal_px, o)
        self.map.keyframes.append(kf)
        new_features(self, gray)
        if held and o.rotation_depth_prior > 0:
            depth = self.map.scene_depth(self.T_cam_vo)
            xy = self.frame_xy(self.tracks)
            self.tracks = self.map.seed_candidates(
                self.tracks, kf, xy, depth, o.rotation_depth_prior
            )
        if o.ba_iterations_per_frame == 0:
            T_refined = self.map.local_ba(o, self.focal_px)
            if T_refined is not None:
                self.T_cam_vo = T_refined
        else:  # iterated by refine_map in the frames' work after this one
            self.map.ba_job = self.map.begin_local_ba(o, self.focal_px)
            self._ba_step_due = False
        tracks = self.tracks
        self.map.bound(tracks, o.max_keyframes, lambda lost: self.frame_xy(tracks, lost))
        self.frames_since_kf = 0
        self.last_keyframe_time_us = time_us

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
        laps = self.laps
        laps.start()
        if self.finish_pending():  # the previous frame's keyframe, if the caller did not run it
            laps.lap("keyframe")
        if self.refine_map():  # and the local BA's iterations of its work
            laps.lap("local BA")
        self.n_frames += 1
        img = frame.image_bgr
        gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
        is_kf = self._keyframe_added
        self._keyframe_added = False
        laps.lap("grey")
        self._T_pred, guess_px = self._interval_prediction(frame.time_us)
        laps.lap("predict")
        self.tracks = track(self._prev_gray, gray, self.tracks, self.camera, self.opts, guess_px)
        if self.shutter is not None:
            prev_us = self._prev_time_us
            interval_s = 0.0 if prev_us is None else (frame.time_us - prev_us) * 1e-6
            self.shutter.update(self.tracks.px, self.tracks.prev_px, interval_s)
            self._drop_outside_lens()
        laps.lap("track")
        if self.state != VoState.TRACKING:
            if step_not_tracking(self, gray, frame.time_us, R_world_body, ground):
                is_kf = True
        elif not self._estimate_pose() and not self._hold_rotation():
            lose_map(self)
            self.rotation_frames = 0
            # with an attitude stream, the reference's attitude is refined by the caller from
            # the samples that arrive after this frame (set_reference_attitude); without one
            # it may be this frame's nearest sample, up to the caller's gap old
            restart_reference(self, gray, frame.time_us, R_world_body)
        else:
            self.frames_since_kf += 1
            held = self.rotation_frames > 0  # whether it becomes a keyframe: after the pose
            self._keyframe_question = PendingKeyframe(
                gray, frame.time_us, R_world_body, gravity, down, held
            )
        self._prev_gray = gray
        self._T_pred = None
        if self.state == VoState.TRACKING and self._prev_time_us is not None:
            self._velocity_dt_us = frame.time_us - self._prev_time_us
        self._prev_time_us = frame.time_us
        self._ba_step_due = True
        laps.lap("pose")
        out = self._output(frame.time_us, is_kf)
        laps.lap("vo output")
        return out

    def lose(self) -> None:
        """Drop tracking and the map (the input was interrupted: a camera fault or a gap).
        The next frames start a new initialisation; its success counts a reset, so the
        poses after it carry a new reset_counter."""
        lose_map(self)
        self.rotation_frames = 0
        self.tracks = Tracks.empty()
        self._pending_keyframe = None
        self._keyframe_question = None
        self._prev_gray = None

    def decide_keyframe(self) -> None:
        """The last tracked frame's work on its tracks after its pose is out: the candidates'
        epipolar check, then whether it becomes a keyframe (the keyframe policy on its tracks
        and pose, companion/vo/keyframes.py). Nothing changes the tracks or the pose between
        the pose and this, and the next frame tracks what it leaves: the same poses as when it
        ran before the output. :meth:`finish_pending` builds the keyframe."""
        asked, self._keyframe_question = self._keyframe_question, None
        if asked is None or self.state != VoState.TRACKING:
            return
        self._check_candidates()
        depth = self.map.median_depth(self.tracks, self.T_cam_vo)
        last = self.map.keyframes[-1]
        o = self.opts
        if (asked.held and len(self.tracks) < 0.5 * o.max_features) or policy.need_keyframe(
            last, self.T_cam_vo, self.tracks, depth, self.frames_since_kf, self.camera, o
        ):
            self._pending_keyframe = asked

    def finish_pending(self) -> bool:
        """Build the keyframe the last frame asked for (new points, triangulation, local BA),
        off the latency-critical path: the service calls this after publishing; otherwise
        the next ``process`` does. The next output has is_keyframe = True. Returns whether
        a keyframe was built."""
        self.decide_keyframe()
        pending, self._pending_keyframe = self._pending_keyframe, None
        if pending is None or self.state != VoState.TRACKING:
            return False
        self._add_keyframe(pending)
        self._keyframe_added = True
        return True

    def refine_map(self) -> bool:
        """The ``ba_iterations_per_frame`` iterations of the local BA under way that the last
        frame's work takes (once a frame, after its pose: the service calls this after
        publishing, else the next ``process`` does); the BA's result applied once it ends
        (:meth:`_end_local_ba`). Returns whether an iteration ran."""
        job = self.map.ba_job
        if job is None or not self._ba_step_due or self.state != VoState.TRACKING:
            return False
        self._ba_step_due = False
        for _ in range(self.opts.ba_iterations_per_frame):
            if not job.problem.step():
                self._end_local_ba()
                break
        return True

    def _end_local_ba(self) -> None:
        """The local BA under way finished (its iterations left taken) and written into the
        map; the current pose and the one before moved with its newest keyframe, T <- T
        T_kf^-1 T_kf' (the motion since that keyframe kept: the frames since tracked the
        unrefined map), as the BA at the keyframe itself sets the pose to T_kf'."""
        job, self.map.ba_job = self.map.ba_job, None
        if job is None:
            return
        job.problem.run()
        T_kf = job.window[-1].T_cam_vo
        T_kf_refined = self.map.end_local_ba(job, self.opts.inlier_px)
        correction = se3.inverse(T_kf) @ T_kf_refined
        self.T_cam_vo = self.T_cam_vo @ correction
        self.T_prev = self.T_prev @ correction
