"""Synthetic inputs of ``companion calibrate``: board photographs and laser-check frames.

Board views are rendered exactly through a :class:`CameraModel` (distortion included): every
pixel is split into ``supersample`` x ``supersample`` sub-pixels whose rays (the model's
``pixels_to_rays``) are intersected with the board plane; each hit samples the printable board
image (:func:`companion.calibration_maths.board.board_image`, bilinear, texel centres at integers,
so a black/white edge sits exactly on the square boundary) and the sub-pixels are averaged
(box filter = the pixel's area). Then a Gaussian optical blur and pixel noise are added and
the result is quantised to 8 bits. Rays that miss the board see a mid-grey floor.

Board poses (``T_cam_board``, board -> camera) are seeded: the board's centre is put on the ray
through a random pixel at a random distance, turned by a random tilt (``tilt_deg``) about a
random in-plane axis and a random roll, and the pose is kept only when every board corner (and
its white margin) is inside the image.

Laser-check frames: the vehicle at seeded poses (height above ground, roll, pitch, yaw) over a
world; the distance sensors of ``hardware`` (the real mounts, which may differ from the
config under test) give the readings (exact ray cast + the sensor's Gaussian noise) and leave
red dots rendered by :class:`companion.sitl.world.render.Renderer`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.calibration_maths.board import BoardSpec, board_image
from companion.calibration_maths.lasers import LaserFrame
from companion.config import Config, RangefinderConfig
from companion.errors import SitlError
from companion.geometry import se3, so3
from companion.geometry.camera import CameraModel
from companion.sitl.world.render import Renderer
from companion.sitl.world.sensors import laser_hits
from companion.sitl.world.terrain import World, make_world
from companion.types import F64

U8 = NDArray[np.uint8]

_FLOOR_DN = 110.0  # grey level where the rays miss the board
_TEXELS_PER_SQUARE = 120  # board texture resolution (a sub-pixel spans ~1 texel at 0.3 m)


def _subpixel_rays(camera: CameraModel, supersample: int) -> F64:
    """Unit rays (H*s, W*s, 3) through the centres of s x s sub-pixels of every pixel."""
    s = supersample
    offs = (np.arange(s) + 0.5) / s - 0.5
    u = (np.arange(camera.width)[:, None] + offs[None, :]).ravel()
    v = (np.arange(camera.height)[:, None] + offs[None, :]).ravel()
    uu, vv = np.meshgrid(u, v)
    rays = camera.pixels_to_rays(np.stack([uu.ravel(), vv.ravel()], axis=1))
    return rays.reshape(camera.height * s, camera.width * s, 3)


def random_board_poses(
    camera: CameraModel,
    board: BoardSpec,
    n_views: int,
    seed: int,
    distance_m: tuple[float, float] = (0.3, 0.7),
    tilt_deg: tuple[float, float] = (10.0, 45.0),
) -> list[F64]:
    """``n_views`` seeded poses T_cam_board (4, 4) with the whole board in the image."""
    rng = np.random.default_rng([seed, 808])
    nx, ny = board.squares
    sq = board.square_m
    # outer corners of the printed board plus half a square of its white margin (board frame)
    if board.kind == "chessboard":
        x0, y0 = -1.5 * sq, -1.5 * sq
    else:
        x0, y0 = -0.5 * sq, -0.5 * sq
    x1, y1 = x0 + (nx + 1) * sq, y0 + (ny + 1) * sq
    outline = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], dtype=np.float64)
    centre = outline.mean(axis=0)
    poses: list[F64] = []
    for _ in range(2000 * n_views):
        if len(poses) == n_views:
            return poses
        uv = rng.uniform([0.05 * camera.width, 0.05 * camera.height],
                         [0.95 * camera.width, 0.95 * camera.height])  # fmt: skip
        ray = camera.pixels_to_rays(uv)[0]
        axis_angle = rng.uniform(0, 2 * np.pi)
        axis = np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0])
        R_tilt = so3.exp(axis * np.radians(rng.uniform(*tilt_deg)))
        R = R_tilt @ so3.rot_z(rng.uniform(-np.pi, np.pi))
        t = ray / ray[2] * rng.uniform(*distance_m) - R @ centre
        T = se3.make(R, t)
        corners_cam = se3.transform(T, outline)
        if np.any(corners_cam[:, 2] < 0.05):
            continue
        p, ok = camera.project(corners_cam)
        if ok.all() and camera.in_image(p, margin_px=4.0).all():
            poses.append(T)
    raise SitlError(f"no {n_views} board poses fit in the image; use a smaller board")


class BoardRenderer:
    """Renders board photographs through one camera (the sub-pixel rays are computed once)."""

    def __init__(self, camera: CameraModel, supersample: int = 3) -> None:
        self.camera = camera
        self.supersample = supersample
        self.rays_cam = _subpixel_rays(camera, supersample)

    def render(
        self,
        board: BoardSpec,
        poses: Sequence[F64],
        seed: int,
        noise_sigma_dn: float = 2.0,
        blur_sigma_px: float = 0.6,
    ) -> list[U8]:
        """Grey images (H, W) uint8 of ``board`` seen at each T_cam_board (4, 4) of ``poses``."""
        cam, s, rays = self.camera, self.supersample, self.rays_cam
        tex = board_image(board, _TEXELS_PER_SQUARE / board.square_m)
        texture = tex.image.astype(np.float32)
        rng = np.random.default_rng([seed, 809])
        images = []
        for T in poses:
            R, t = T[:3, :3], T[:3, 3]
            n = R[:, 2]  # board normal in the camera
            with np.errstate(divide="ignore", invalid="ignore"):
                depth = (n @ t) / (rays @ n)  # ray parameter of the plane hit
            hit = np.where((depth > 0)[..., None], depth[..., None] * rays, np.nan)
            xy = (hit - t) @ R[:, :2]  # board coordinates (H*s, W*s, 2) [m]
            map_x = np.nan_to_num(tex.origin_px[0] + tex.px_per_m * xy[..., 0], nan=-1e6)
            map_y = np.nan_to_num(tex.origin_px[1] + tex.px_per_m * xy[..., 1], nan=-1e6)
            fine = cv2.remap(
                texture, map_x.astype(np.float32), map_y.astype(np.float32), cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT, borderValue=_FLOOR_DN,
            )  # fmt: skip
            img = fine.reshape(cam.height, s, cam.width, s).mean(axis=(1, 3))
            if blur_sigma_px > 0:
                img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
            img = img + rng.normal(0.0, noise_sigma_dn, img.shape)
            images.append(np.clip(np.round(img), 0, 255).astype(np.uint8))
        return images


def tilt_sensor(
    rangefinders: Sequence[RangefinderConfig], sensor_id: int, pitch_deg: float
) -> tuple[RangefinderConfig, ...]:
    """A copy of ``rangefinders`` with one sensor's mount pitch changed by ``pitch_deg``."""
    if sensor_id not in [r.sensor_id for r in rangefinders]:
        raise SitlError(f"no rangefinder with sensor_id {sensor_id}")
    out = []
    for rf in rangefinders:
        if rf.sensor_id == sensor_id:
            r, p, y = rf.mount.rpy_deg
            mount = dataclasses.replace(rf.mount, rpy_deg=(r, p + pitch_deg, y))
            rf = dataclasses.replace(rf, mount=mount)
        out.append(rf)
    return tuple(out)


def laser_check_frames(
    cfg: Config,
    n_frames: int,
    seed: int,
    hardware: Sequence[RangefinderConfig] | None = None,
    world: World | None = None,
    height_m: tuple[float, float] = (1.2, 4.0),
    tilt_deg: float = 8.0,
) -> list[LaserFrame]:
    """``n_frames`` seeded frames with live laser dots and the matching readings.

    The camera is ``cfg.camera``; the sensors are ``hardware`` (default ``cfg.rangefinders``)
    over ``world`` (default a flat floor); roll and pitch uniform in +-``tilt_deg``, the height
    above ground uniform in ``height_m``.
    """
    rfs = tuple(hardware if hardware is not None else cfg.rangefinders)
    w = world or make_world("flat", seed, 60.0)
    render = dataclasses.replace(cfg.sitl.render, laser_marks="live", motion_blur=False)
    renderer = Renderer(w, cfg.camera, render, rfs, seed)
    T_body_cam = cfg.camera.T_body_cam()
    rng = np.random.default_rng([seed, 810])
    half = 0.3 * w.size_m
    frames: list[LaserFrame] = []
    for k in range(n_frames):
        x, y = rng.uniform(-half, half, 2)
        ground = w.raycast(np.array([[x, y, -1000.0]]), np.array([[0.0, 0.0, 1.0]]))
        z = float(ground.points_world[0, 2]) - rng.uniform(*height_m)
        roll, pitch = np.radians(rng.uniform(-tilt_deg, tilt_deg, 2))
        T_world_body = se3.make(so3.rpy_to_matrix(roll, pitch, rng.uniform(-np.pi, np.pi)),
                                [x, y, z])  # fmt: skip
        t_true, pts = laser_hits(w, T_world_body, rfs)
        ranges: dict[int, float] = {}
        marks = []
        for rf, d, p in zip(rfs, t_true, pts, strict=True):
            if not (np.isfinite(d) and rf.min_m <= d <= rf.max_m):
                continue
            sigma = rf.sigma_a_m + rf.sigma_b * d
            ranges[rf.sensor_id] = float(d + sigma * rng.standard_normal())
            marks.append(p)
        frame = renderer.render_pose(T_world_body @ T_body_cam, k, np.array(marks).reshape(-1, 3))
        frames.append(LaserFrame(f"laser_{k:03d}.png", frame.image_bgr, ranges))
    return frames
