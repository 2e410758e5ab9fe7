"""The lens the user calibrated is not the lens: the renderer's camera differs from the
configured one by a focal error, a principal point offset, a k1 error and a mount rotation
(``[sitl.render.lens_error]``), and the image moves by what each predicts; the VO's camera
(the config) does not change. Also: with no effect on, the renderer is the kernel alone."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import pytest

from companion.config import CameraConfig, Config, MountConfig, RenderConfig, load_config
from companion.geometry import se3, so3
from companion.render_options import LensErrorOptions
from companion.sitl.world import _kernels
from companion.sitl.world.render import Renderer
from companion.sitl.world.terrain import World
from companion.types import F64

CAMERA = CameraConfig(dist=(0.0, 0.0, 0.0, 0.0, 0.0), mount=MountConfig())
# straight down from 6 m over the flat world: x east, y south, z down
T_DOWN = se3.make(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), [3, 2, -6.0])
CENTRES = ((319.5, 239.5), (199.5, 149.5), (449.5, 149.5), (199.5, 339.5), (449.5, 339.5))


def render(w: World, lens: LensErrorOptions) -> tuple[np.ndarray, np.ndarray]:
    r = Renderer(w, CAMERA, RenderConfig(noise_sigma_dn=0.0, laser_marks="off", lens_error=lens))
    f = r.render_pose(T_DOWN, 1)
    return f.image_bgr.mean(axis=2), f.depth_m


def shift_at(a: np.ndarray, b: np.ndarray, u: float, v: float, half: int = 40) -> F64:
    """(du, dv) [px] by which b's content near (u, v) is moved from a's (phase correlation)."""
    rows = slice(int(v + 0.5) - half, int(v + 0.5) + half)
    cols = slice(int(u + 0.5) - half, int(u + 0.5) + half)
    pa, pb = a[rows, cols].astype(np.float64), b[rows, cols].astype(np.float64)
    win = cv2.createHanningWindow(pa.shape[::-1], cv2.CV_64F)
    (du, dv), _ = cv2.phaseCorrelate(pa, pb, win)
    return np.array([du, dv])


@pytest.fixture(scope="module")
def reference(world: Callable[[str, int], World]) -> tuple[World, np.ndarray, np.ndarray]:
    w = world("flat", 1)
    image, depth = render(w, LensErrorOptions())
    return w, image, depth


@pytest.mark.parametrize(
    ("lens", "predict"),
    [
        # the principal point: the whole image moves by the offset
        (LensErrorOptions(principal_px=(3.0, -2.0)), lambda x, y: (3.0, -2.0)),
        # the focal length: pixels move away from the principal point by focal x (u - cx)
        (LensErrorOptions(focal=0.02), lambda x, y: (0.02 * 460 * x, 0.02 * 460 * y)),
        # k1: radially by f x dk1 r^2 (normalised x, y; r^2 = x^2 + y^2)
        (
            LensErrorOptions(k1=0.05),
            lambda x, y: (460 * x * 0.05 * (x * x + y * y), 460 * y * 0.05 * (x * x + y * y)),
        ),
    ],
    ids=["principal_point", "focal", "k1"],
)
def test_intrinsic_errors_move_the_image_by_their_prediction(
    reference: tuple[World, np.ndarray, np.ndarray],
    lens: LensErrorOptions,
    predict: Callable[[float, float], tuple[float, float]],
) -> None:
    w, image, _ = reference
    moved, _ = render(w, lens)
    for u, v in CENTRES:
        x, y = (u - 319.5) / 460, (v - 239.5) / 460
        got = shift_at(image, moved, u, v)
        assert np.allclose(got, predict(x, y), atol=0.25), (u, v, got, predict(x, y))


def test_a_mount_error_turns_the_view_about_the_camera_centre(
    reference: tuple[World, np.ndarray, np.ndarray],
) -> None:
    """Each ground point seen at configured pixel (u, v) is seen where the true camera,
    turned by R_err in the configured camera's frame, projects it: p_true = R_err^T p."""
    w, image, depth = reference
    rpy = np.radians([0.6, -0.6, 0.5])
    moved, _ = render(w, LensErrorOptions(mount_deg=(0.6, -0.6, 0.5)))
    R_err = so3.rpy_to_matrix(*rpy)
    for u, v in CENTRES:
        z = float(depth[int(v + 0.5), int(u + 0.5)])
        p = np.array([(u - 319.5) / 460 * z, (v - 239.5) / 460 * z, z])
        q = R_err.T @ p
        expected = np.array([460 * q[0] / q[2] + 319.5 - u, 460 * q[1] / q[2] + 239.5 - v])
        got = shift_at(image, moved, u, v)
        assert np.allclose(got, expected, atol=0.25), (u, v, got, expected)
        assert np.linalg.norm(expected) > 3.0  # ~1 deg at f = 460: several pixels


def test_the_config_keeps_the_calibrated_camera() -> None:
    cfg = load_config("config/realistic.toml")
    lens = cfg.sitl.render.lens_error
    model = cfg.camera.model()
    assert (model.fx, model.cx, model.cy, model.k1) == (460.0, 319.5, 239.5, -0.12)
    rendered = lens.rendered_model(model)
    assert rendered.fx == pytest.approx(464.6) and rendered.fy == pytest.approx(464.6)
    assert (rendered.cx, rendered.cy) == (322.5, 237.5)
    assert rendered.k1 == pytest.approx(-0.10) and rendered.k2 == model.k2
    angle = np.degrees(np.arccos((np.trace(lens.T_configured_rendered()[:3, :3]) - 1) / 2))
    assert angle == pytest.approx(1.0, abs=0.05)  # the mount: about 1 deg


def test_with_no_effect_the_renderer_is_the_kernel_alone(
    world: Callable[[str, int], World], default_config: Config
) -> None:
    """The default image is the ray-casting kernel's 8-bit output at the frame's one pose, the
    noise drawn from (seed, 405, seq): no effect adds to it (the published figures stay)."""
    cfg = default_config
    w = world("hills", 1)
    r = Renderer(w, cfg.camera, RenderConfig(laser_marks="off"), seed=7)
    T = se3.make(so3.rpy_to_matrix(0.04, -0.03, 0.7), [10.0, -4.0, -8.0]) @ cfg.camera.T_body_cam()
    got = r.render_pose(T, 11, time_s=2.0)
    n = cfg.camera.width * cfg.camera.height
    rays = np.ascontiguousarray(cfg.camera.model().pixel_rays().reshape(-1, 3))
    out = np.empty((n, 3), np.uint8)
    linear = np.empty((n, 3), np.float32)
    depth = np.empty(n, np.float32)
    tex = w.textures
    start = int(np.random.default_rng([7, 405, 11]).integers(0, 1 << 21))
    el, az = np.radians(55.0), np.radians(140.0)
    sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)])
    rows = cfg.camera.height
    _kernels.render(
        np.ascontiguousarray(np.repeat(T[None, :3, :3], rows, axis=0)),
        np.ascontiguousarray(np.repeat(T[None, :3, 3], rows, axis=0)),
        rays,
        cfg.camera.width,
        460.0,
        w.kernel_geometry(),
        *tex,
        w.layers,
        w.fields,
        w.x0,
        w.y0,
        w.f_inv,
        w.box_tint,
        sun,
        0.45,
        linear,
        depth,
        r.noise_bank,
        start,
        2.0,
        out,
    )
    assert np.array_equal(got.image_bgr.reshape(-1, 3), out)
    assert np.array_equal(got.depth_m.reshape(-1), depth)
    assert np.array_equal(got.T_world_cam, T)
    ideal = Renderer(w, cfg.camera, load_config("config/ideal.toml").sitl.render, seed=7)
    assert np.array_equal(ideal.render_pose(T, 11, time_s=2.0).image_bgr, got.image_bgr)
