"""Camera rendering by exact ray casting, with noise, optional motion blur and laser marks.

Every pixel centre's ray (from the full camera model, distortion included) is cast against the
world (:mod:`._kernels`); the surface is textured and Lambert-shaded, then Gaussian sensor
noise is added and the result quantised to 8-bit BGR. Laser marks are drawn as Gaussian red
spots centred on the exact projection of the lasers' 3D hit points, hidden when the surface
occludes them. ``live`` marks follow the beams; ``painted`` marks are the four hit points at
``painted_time_s``, left on the surface (what d-Pose uses).

A real camera's effects, each off by default (``[sitl.render]``; with none on, every image is
the idealised renderer's to the bit): a rolling shutter (:mod:`.rolling_shutter`: each row at
its own pose), the exposure and vignetting (:mod:`.exposure`: the linear image times a frame
gain and a per-pixel falloff, before the noise and the 8-bit clip) and a lens that is not the
configured one (``LensErrorOptions`` in ``companion/render_options.py``: the renderer casts the
rays of the perturbed intrinsics from the perturbed mount; poses handed in are the configured
camera's, as the VO knows it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.config import CameraConfig, RangefinderConfig, RenderConfig
from companion.geometry import se3
from companion.sitl.world import _kernels, ground_effects
from companion.sitl.world.exposure import ExposureModel, vignette
from companion.sitl.world.rolling_shutter import project_rows, row_offsets_s, row_poses
from companion.sitl.world.sensors import laser_hits
from companion.sitl.world.terrain import World
from companion.sitl.world.trajectory import Trajectory
from companion.types import F64

F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]

LASER_BGR = np.array([40.0, 45.0, 255.0], dtype=np.float32)
_NOISE_BANK = 1 << 21
_AMBIENT = 0.45


@dataclass(frozen=True, slots=True)
class RenderedFrame:
    """image_bgr (H, W, 3) uint8; depth_m (H, W) float32 z-depth in the camera frame (inf = sky;
    with a rolling shutter, in the frame of the pixel's row); T_world_cam (4, 4) the rendering
    camera at the frame time (with a lens error: the true mount, not the configured one);
    marks_uv (K, 2) pixel centres of the visible laser marks (NaN when not visible);
    marks_world (K, 3) their 3D points (NED)."""

    image_bgr: U8
    depth_m: F32
    T_world_cam: F64
    marks_uv: F64
    marks_world: F64


class Renderer:
    """Renders the camera of one vehicle in one world. Deterministic in (seed, seq)."""

    def __init__(
        self,
        world: World,
        camera: CameraConfig,
        render: RenderConfig,
        rangefinders: Sequence[RangefinderConfig] = (),
        seed: int = 1,
    ) -> None:
        self.world = world
        self.camera_cfg = camera
        self.cfg = render
        self.configured_model = camera.model()
        self.model = render.lens_error.rendered_model(self.configured_model)
        self.model.validate()
        self.T_body_cam = camera.T_body_cam()  # the configured mount
        self.T_cam_rendered = (
            render.lens_error.T_configured_rendered() if render.lens_error.any else None
        )
        self.rangefinders = tuple(rangefinders)
        self.seed = seed
        h, w = camera.height, camera.width
        self.rays_cam = np.ascontiguousarray(self.model.pixel_rays().reshape(-1, 3))
        self.noise_bank = np.random.default_rng([seed, 404]).standard_normal(
            _NOISE_BANK, dtype=np.float32
        )
        el = np.radians(render.sun_elevation_deg)
        az = np.radians(render.sun_azimuth_deg)
        self.sun_ned = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)])
        self._linear = np.empty((h * w, 3), dtype=np.float32)
        self._accum = np.empty((h * w, 3), dtype=np.float32)
        self._depth = np.empty(h * w, dtype=np.float32)
        self._painted: F64 | None = None
        self.row_offsets_s = row_offsets_s(h, render.readout_ms * 1e-3)
        self.exposure = ExposureModel(render.exposure, seed)
        strength = render.exposure.vignetting
        self._vignette = (
            vignette(self.rays_cam, strength).astype(np.float32) if strength > 0 else None
        )

    # ------------------------------------------------------------------ core
    def _rendered(self, T_world_cam: F64) -> F64:
        """The configured camera's pose(s) (4, 4) or (H, 4, 4) -> the rendering camera's."""
        if self.T_cam_rendered is None:
            return T_world_cam
        return np.asarray(T_world_cam @ self.T_cam_rendered, dtype=np.float64)

    def _kernel(self, T_world_cam: F64, linear: F32, depth: F32, out_u8: U8, start: int) -> None:
        """Ray cast from the rendering camera: one pose (4, 4), or one per row (H, 4, 4)."""
        tex_data, tex_offs, tex_sizes = self.world.textures
        w = self.world
        h = self.camera_cfg.height
        T_rows = T_world_cam if T_world_cam.ndim == 3 else np.broadcast_to(T_world_cam, (h, 4, 4))
        _kernels.render(
            np.ascontiguousarray(T_rows[:, :3, :3]),
            np.ascontiguousarray(T_rows[:, :3, 3]),
            self.rays_cam,
            self.camera_cfg.width,
            float(self.model.fx),
            w.kernel_geometry(),
            tex_data,
            tex_offs,
            tex_sizes,
            w.layers,
            w.fields,
            w.x0,
            w.y0,
            w.f_inv,
            w.box_tint,
            self.sun_ned,
            _AMBIENT,
            linear,
            depth,
            self.noise_bank,
            start,
            float(self.cfg.noise_sigma_dn),
            out_u8,
        )

    def render_pose(
        self,
        T_world_cam: F64,
        seq: int,
        marks_world: F64 | None = None,
        blur_poses: Sequence[F64] = (),
        rows: F64 | None = None,
        time_s: float | None = None,
    ) -> RenderedFrame:
        """Render at a pose of the configured camera, T_world_cam (4, 4). ``blur_poses``:
        sub-frame poses averaged for motion blur, each (4, 4), or (H, 4, 4) per row with a
        rolling shutter; ``rows``: (H, 4, 4) the pose of each row (rolling shutter); ``time_s``:
        the frame's time [s], for the exposure's frame gain (None: no frame gain)."""
        h, w = self.camera_cfg.height, self.camera_cfg.width
        start = int(np.random.default_rng([self.seed, 405, seq]).integers(0, _NOISE_BANK))
        out = np.empty((h * w, 3), dtype=np.uint8)
        no_u8 = np.empty((0, 3), dtype=np.uint8)
        T_true = self._rendered(T_world_cam)
        T_rows = T_true if rows is None else self._rendered(rows)
        gain = self._pixel_gain(time_s)
        if blur_poses:
            self._accum.fill(0.0)
            for T in blur_poses:
                self._kernel(self._rendered(T), self._linear, self._depth, no_u8, 0)
                self._accum += self._linear
            self._accum *= np.float32(1.0 / len(blur_poses))
            # depth at the frame's own pose
            self._kernel(T_rows, self._linear, self._depth, no_u8, 0)
            if gain is not None:
                self._accum *= gain
            _kernels.finish(
                self._accum, self.noise_bank, start, float(self.cfg.noise_sigma_dn), out
            )
        elif gain is not None:
            self._kernel(T_rows, self._linear, self._depth, no_u8, 0)
            self._linear *= gain
            _kernels.finish(
                self._linear, self.noise_bank, start, float(self.cfg.noise_sigma_dn), out
            )
        else:
            self._kernel(T_rows, self._linear, self._depth, out, start)
        depth = self._depth.reshape(h, w).copy()
        image = out.reshape(h, w, 3)
        uv = np.full((0, 2), np.nan)
        pts = np.zeros((0, 3))
        if marks_world is not None and len(marks_world):
            pts = np.asarray(marks_world, dtype=np.float64)
            uv = self._draw_marks(image, T_rows, pts)
        return RenderedFrame(image, depth, T_true, uv, pts)

    def _pixel_gain(self, time_s: float | None) -> F32 | None:
        """(H*W, 1) the exposure's factor on the linear image (frame gain x vignetting), or
        None when both are 1."""
        frame = 1.0
        if time_s is not None and self.cfg.exposure.frame_gain_varies:
            frame = self.exposure.gain(time_s)
        if self._vignette is None and frame == 1.0:
            return None
        v = (
            self._vignette
            if self._vignette is not None
            else np.ones(len(self.rays_cam), np.float32)
        )
        return np.asarray((v * np.float32(frame))[:, None], dtype=np.float32)

    def render_linear(self, T_world_cam: F64) -> F32:
        """Noise-free linear BGR image (H, W, 3) float32 at a pose (no marks)."""
        h, w = self.camera_cfg.height, self.camera_cfg.width
        T = self._rendered(T_world_cam)
        self._kernel(T, self._linear, self._depth, np.empty((0, 3), np.uint8), 0)
        return self._linear.reshape(h, w, 3).copy()

    def _draw_marks(self, img: U8, T_world_cam: F64, pts_world: F64) -> F64:
        """Blend red Gaussian spots at the projections of visible 3D points; returns uv (K, 2).
        ``T_world_cam``: the rendering camera (4, 4), or its rows' poses (H, 4, 4)."""
        if T_world_cam.ndim == 3:
            uv, in_front, origins = project_rows(self.model, T_world_cam, pts_world)
            T_mid = T_world_cam[len(T_world_cam) // 2]
            p_cam = se3.transform(se3.inverse(T_mid), pts_world)  # for the spots' size
        else:
            p_cam = se3.transform(se3.inverse(T_world_cam), pts_world)
            uv, in_front = self.model.project(p_cam)
            origins = np.repeat(T_world_cam[None, :3, 3], len(pts_world), axis=0)
        rays = pts_world - origins
        dist = np.linalg.norm(rays, axis=1)
        hits = self.world.raycast(origins, rays)
        visible = in_front & (hits.t_m > dist - 0.02) & self.model.in_image(uv, margin_px=1.0)
        uv = np.where(visible[:, None], uv, np.nan)
        h, w = img.shape[:2]
        for k in np.flatnonzero(visible):
            radius_px = 0.5 * self.cfg.spot_diameter_m * self.model.fx / p_cam[k, 2]
            sigma = max(0.5 * radius_px, 0.7)
            r = int(np.ceil(4 * sigma))
            u, v = uv[k]
            c0, c1 = max(int(np.floor(u)) - r, 0), min(int(np.floor(u)) + r + 2, w)
            r0, r1 = max(int(np.floor(v)) - r, 0), min(int(np.floor(v)) + r + 2, h)
            yy, xx = np.mgrid[r0:r1, c0:c1]
            alpha = 0.95 * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma**2))
            patch = img[r0:r1, c0:c1].astype(np.float64)
            blended = patch * (1 - alpha[..., None]) + alpha[..., None] * LASER_BGR
            img[r0:r1, c0:c1] = np.clip(np.floor(blended + 0.5), 0, 255).astype(np.uint8)
        return np.asarray(uv, dtype=np.float64)

    # ------------------------------------------------------------------ flight
    def marks_at(self, trajectory: Trajectory, time_s: float) -> F64 | None:
        """World points of the laser marks visible at ``time_s`` under the configured mode."""
        mode = self.cfg.laser_marks
        if mode == "off" or not self.rangefinders:
            return None
        if mode == "painted":
            if self._painted is None:
                T = trajectory.T_world_body(self.cfg.painted_time_s)
                t, pts = laser_hits(self.world, T, self.rangefinders)
                self._painted = pts[np.isfinite(t)]
            return self._painted
        t, pts = laser_hits(self.world, trajectory.T_world_body(time_s), self.rangefinders)
        ok = np.isfinite(t) & np.array(
            [rf.min_m <= d <= rf.max_m for rf, d in zip(self.rangefinders, t, strict=True)]
        )
        return np.asarray(pts[ok], dtype=np.float64)

    def render_at(self, trajectory: Trajectory, time_s: float, seq: int) -> RenderedFrame:
        """Render frame ``seq`` stamped at ``time_s`` (the middle of the exposure, and of the
        readout with a rolling shutter: rolling_shutter.py)."""
        T_world_cam = trajectory.T_world_body(time_s) @ self.T_body_cam
        rolling = self.cfg.readout_ms > 0
        rows = None
        if rolling:
            rows = row_poses(trajectory, time_s, self.row_offsets_s, self.T_body_cam)
        blur: list[F64] = []
        if self.cfg.motion_blur:
            n = self.cfg.blur_samples
            ts = time_s + self.cfg.exposure_s * (np.arange(n) / (n - 1) - 0.5)
            if rolling:
                blur = [row_poses(trajectory, t, self.row_offsets_s, self.T_body_cam) for t in ts]
            else:
                s = trajectory.sample(ts)
                blur = [s.T_world_body(i) @ self.T_body_cam for i in range(n)]
        marks = self.marks_at(trajectory, time_s)
        frame = self.render_pose(T_world_cam, seq, marks, blur, rows=rows, time_s=time_s)
        ground_effects.apply(self, frame, trajectory.T_world_body(time_s), time_s)  # [sitl.ground]
        return frame
