"""The rolling shutter: each row at its own pose (sitl/world/rolling_shutter.py).

A camera looking straight down pans sideways (and sinks) over the flat world at a known
speed: every row's image content is shifted by the camera's travel since the stamp, f * v *
dt(row) / Z pixels, and its depth is the height at that row's time; the middle of the image is
the global shutter's; a zero readout is the global shutter to the bit.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import pytest
from numpy.typing import ArrayLike

from companion.config import CameraConfig, MountConfig, RangefinderConfig, RenderConfig
from companion.geometry import se3
from companion.sitl.world.render import Renderer
from companion.sitl.world.rolling_shutter import project_rows, row_offsets_s
from companion.sitl.world.terrain import World
from companion.types import F64

# a camera looking straight down: x east (image right), y south (image down), z down
R_DOWN = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
HEIGHT_M = 6.0
CAMERA = CameraConfig(
    width=320,
    height=240,
    fx=230.0,
    fy=230.0,
    cx=159.5,
    cy=119.5,
    dist=(0.0, 0.0, 0.0, 0.0, 0.0),
    mount=MountConfig(),  # the body is the camera
)


class Pan:
    """A straight, constant-velocity flight of a downward camera: p(t) = p0 + v t (NED)."""

    def __init__(self, velocity_m_s: ArrayLike, time0_s: float = 1.0) -> None:
        self.v = np.asarray(velocity_m_s, dtype=np.float64)
        self.p0 = np.array([3.0, 2.0, -HEIGHT_M]) - self.v * time0_s

    def poses(self, times_s: ArrayLike) -> F64:
        t = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
        T = np.repeat(np.eye(4)[None], len(t), axis=0)
        T[:, :3, :3] = R_DOWN
        T[:, :3, 3] = self.p0 + t[:, None] * self.v
        return T

    def T_world_body(self, time_s: float) -> F64:
        T: F64 = self.poses([time_s])[0]
        return T


def band_shift(a: np.ndarray, b: np.ndarray, rows: slice) -> tuple[float, float]:
    """(du, dv) [px] that moves image a's band of rows onto b's (phase correlation)."""
    ga = a[rows].mean(axis=2).astype(np.float64)
    gb = b[rows].mean(axis=2).astype(np.float64)
    win = cv2.createHanningWindow(ga.shape[::-1], cv2.CV_64F)
    (du, dv), _ = cv2.phaseCorrelate(ga, gb, win)
    return float(du), float(dv)


def test_row_times_are_centred_on_the_stamp() -> None:
    t = row_offsets_s(480, 0.02)
    assert t[0] == pytest.approx(-0.01 + 0.01 / 480) and t[-1] == pytest.approx(0.01 - 0.01 / 480)
    assert t[239] + t[240] == pytest.approx(0.0, abs=1e-15)  # the middle of the image: the stamp
    assert np.allclose(np.diff(t), 0.02 / 480)
    assert not row_offsets_s(480, 0.0).any()


def test_a_sideways_pan_shears_the_image_by_speed_readout_over_depth(
    world: Callable[[str, int], World],
) -> None:
    w = world("flat", 1)
    speed, readout_s = 12.0, 0.03  # east: +u in the image
    pan = Pan([0.0, speed, 0.0])
    render = RenderConfig(noise_sigma_dn=0.0, laser_marks="off")
    gs = Renderer(w, CAMERA, render).render_at(pan, 1.0, 30)  # type: ignore[arg-type]
    rs = Renderer(w, CAMERA, RenderConfig(noise_sigma_dn=0.0, laser_marks="off", readout_ms=30.0))
    got = rs.render_at(pan, 1.0, 30)  # type: ignore[arg-type]
    depth = float(np.median(gs.depth_m))
    assert depth == pytest.approx(HEIGHT_M, abs=1e-6)
    offsets = row_offsets_s(CAMERA.height, readout_s)
    shifts = {}
    for name, rows in (
        ("top", slice(8, 56)),
        ("middle", slice(96, 144)),
        ("bottom", slice(184, 232)),
    ):
        du, dv = band_shift(gs.image_bgr, got.image_bgr, rows)
        # a row exposed dt later sees the ground moved by -v dt: the image content moves left
        expected = -CAMERA.fx * speed * float(offsets[rows].mean()) / depth
        assert du == pytest.approx(expected, abs=0.25), name
        assert abs(dv) < 0.2, name
        shifts[name] = du
    # top to bottom: f * v * (t_bottom - t_top) / Z = 230 * 12 * 0.022 / 6 ~ 10 px
    shear = shifts["top"] - shifts["bottom"]
    span_s = float(offsets[slice(184, 232)].mean() - offsets[slice(8, 56)].mean())
    assert shear == pytest.approx(CAMERA.fx * speed * span_s / depth, rel=0.03)
    assert shear > 9.0
    # the ground truth stays the stamp's pose
    assert np.array_equal(got.T_world_cam, pan.T_world_body(1.0))


def test_depth_is_each_rows_own_and_zero_readout_is_the_global_shutter(
    world: Callable[[str, int], World],
) -> None:
    w = world("flat", 1)
    pan = Pan([0.0, 4.0, 3.0])  # sinking at 3 m/s: later rows are nearer the ground
    rs = Renderer(w, CAMERA, RenderConfig(laser_marks="off", readout_ms=20.0), seed=3)
    frame = rs.render_at(pan, 1.0, 7)  # type: ignore[arg-type]
    expected = HEIGHT_M - 3.0 * row_offsets_s(CAMERA.height, 0.02)
    assert np.allclose(frame.depth_m, expected[:, None].astype(np.float32), atol=1e-5)
    # a zero readout: every row at the stamp's pose, the global shutter to the bit
    gs = Renderer(w, CAMERA, RenderConfig(laser_marks="off"), seed=3)
    T = pan.T_world_body(1.0)
    a = gs.render_at(pan, 1.0, 7)  # type: ignore[arg-type]
    b = gs.render_pose(T, 7, rows=np.repeat(T[None], CAMERA.height, axis=0))
    assert np.array_equal(a.image_bgr, b.image_bgr) and np.array_equal(a.depth_m, b.depth_m)
    assert not np.array_equal(a.image_bgr, frame.image_bgr)


def test_laser_marks_are_where_their_rows_saw_them(world: Callable[[str, int], World]) -> None:
    """A mark is drawn where the row that sees it was looking: projected through the pose of
    that row's own time, not the stamp's (several pixels apart at this speed)."""
    w = world("flat", 1)
    pan = Pan([0.0, 10.0, 0.0])
    sensors = [
        RangefinderConfig(sensor_id=k, mount=MountConfig(rpy_deg=(r, p, 0.0)))
        for k, (r, p) in enumerate(((-25.0, 0.0), (20.0, 0.0), (0.0, 15.0)))
    ]
    rs = Renderer(w, CAMERA, RenderConfig(readout_ms=30.0), sensors)
    frame = rs.render_at(pan, 1.0, 30)  # type: ignore[arg-type]
    assert len(frame.marks_world) == 3 and np.isfinite(frame.marks_uv).all()
    offsets = row_offsets_s(CAMERA.height, 0.03)
    moved = []
    for uv, p in zip(frame.marks_uv, frame.marks_world, strict=True):
        t_row = 1.0 + float(np.interp(uv[1], np.arange(CAMERA.height), offsets))
        p_cam = se3.transform(se3.inverse(pan.T_world_body(t_row)), p[None])
        at_row, _ = rs.model.project(p_cam)
        assert np.linalg.norm(at_row[0] - uv) < 0.01
        at_stamp, _ = rs.model.project(se3.transform(se3.inverse(pan.T_world_body(1.0)), p[None]))
        moved.append(abs(at_stamp[0, 0] - uv[0]))
    assert max(moved) > 2.0  # the rows' poses matter here
    # the fixed point alone, on the row poses
    rows = pan.poses(1.0 + offsets)
    uv2, front, origin = project_rows(rs.model, rows, frame.marks_world)
    assert front.all() and np.allclose(uv2, frame.marks_uv, atol=1e-9)
    assert np.allclose(origin[:, 2], -HEIGHT_M)
