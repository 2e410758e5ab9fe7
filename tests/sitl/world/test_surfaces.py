"""Hard grounds (surfaces.py): the repeating period is in the image's autocorrelation, the low
texture has a small share of the photo's gradient energy, and the defaults change nothing."""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np
import pytest

from companion.config import CameraConfig, RenderConfig
from companion.errors import SitlError
from companion.sitl.world.render import Renderer
from companion.sitl.world.surfaces import CHECKER_M, TILE_M, SpecularPatches, surface_ground
from companion.sitl.world.terrain import World, make_world
from companion.sitl.world.trajectory import Trajectory
from companion.sitl_options import GroundOptions

ALTITUDE_M = 3.0
PINHOLE = CameraConfig(dist=(0.0, 0.0, 0.0, 0.0, 0.0))  # straight lines stay straight
# camera x east, y south, z down (NED), 3 m over the flat ground at h = 0
T_WORLD_CAM = np.array(
    [[0.0, -1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, -ALTITUDE_M], [0, 0, 0, 1.0]]
)


@cache
def nadir_grey(surface: str, checker_m: float = CHECKER_M) -> np.ndarray:
    """The grey image (H, W) float64 looking straight down at ``surface`` (no pixel noise)."""
    ground = GroundOptions(surface=surface, checker_m=checker_m)  # type: ignore[arg-type]
    world = make_world("flat", 1, 40.0, 0.05, ground)
    renderer = Renderer(world, PINHOLE, RenderConfig(noise_sigma_dn=0.0, laser_marks="off"))
    image = renderer.render_pose(T_WORLD_CAM, 0).image_bgr
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float64)


def autocorrelation_x(grey: np.ndarray, lags: range) -> np.ndarray:
    """Normalised autocorrelation (len(lags),) of the central 240 x 400 crop along image x."""
    h, w = grey.shape
    a = grey[h // 2 - 120 : h // 2 + 120, w // 2 - 200 : w // 2 + 200]
    a = a - a.mean()
    var = (a * a).mean()
    return np.array([(a[:, :-k] * a[:, k:]).mean() / var for k in lags])


def gradient_energy(grey: np.ndarray) -> float:
    gx = cv2.Sobel(grey, cv2.CV_64F, 1, 0)
    gy = cv2.Sobel(grey, cv2.CV_64F, 0, 1)
    return float((gx * gx + gy * gy).mean())


@pytest.mark.parametrize(
    ("surface", "period_m"), [("checkerboard", 2 * CHECKER_M), ("tiles", TILE_M)]
)
def test_a_repeating_floor_shows_its_period_in_the_autocorrelation(
    surface: str, period_m: float
) -> None:
    lags = range(20, 200)
    ac = autocorrelation_x(nadir_grey(surface), lags)
    expected_px = period_m * PINHOLE.fx / ALTITUDE_M
    peak = lags[int(np.argmax(ac))]
    assert abs(peak - expected_px) <= 2.0, f"{surface}: peak at {peak} px, period {expected_px:.1f}"
    assert ac.max() > 0.8
    # the photo ground has no such period
    assert autocorrelation_x(nadir_grey("photo"), lags).max() < 0.4


def test_the_checkerboard_takes_its_square_size() -> None:
    """Printed sheets of 8 cm squares (the real downward flight's floor): the period follows
    ``checker_m``; a size out of range is refused."""
    lags = range(20, 60)  # one period (a multiple of it correlates as well)
    ac = autocorrelation_x(nadir_grey("checkerboard", 0.12), lags)
    peak = lags[int(np.argmax(ac))]
    expected_px = 2 * 0.12 * PINHOLE.fx / ALTITUDE_M
    assert abs(peak - expected_px) <= 2.0 and ac.max() > 0.8
    with pytest.raises(SitlError, match="checker_m"):
        surface_ground("checkerboard", 1, (8, 8), 0.5, checker_m=0.0)


def test_checker_sheets_break_the_boards_period_and_keep_its_squares() -> None:
    """The same squares on overlapping sheets (the real downward flight's floor, where an
    endless board left a simulated camera 0.3 m over it ~8 corners, all alike): the
    board's period still dominates a view, but across sheets it slips (each sheet its own
    phase and turn), so the correlation at one period is clearly below the board's."""
    checker_m = 0.12
    lags = range(20, 60)
    board = autocorrelation_x(nadir_grey("checkerboard", checker_m), lags)
    sheets = autocorrelation_x(nadir_grey("checker_sheets", checker_m), lags)
    period_px = 2 * checker_m * PINHOLE.fx / ALTITUDE_M
    peak = lags[int(np.argmax(sheets))]
    assert abs(peak - period_px) <= 3.0
    assert sheets.max() < board.max() - 0.15
    # dark squares, white paper and its margins: both ends of the range are there
    grey = nadir_grey("checker_sheets", checker_m)
    assert (grey < 60).mean() > 0.2 and (grey > 150).mean() > 0.3
    with pytest.raises(SitlError, match="checker_m"):
        surface_ground("checker_sheets", 1, (8, 8), 0.5, checker_m=3.0)


@pytest.mark.parametrize(("surface", "share"), [("concrete", 0.1), ("carpet", 0.03)])
def test_low_texture_has_a_small_share_of_the_photos_gradient_energy(
    surface: str, share: float
) -> None:
    grey = nadir_grey(surface)
    ratio = gradient_energy(grey) / gradient_energy(nadir_grey("photo"))
    assert ratio < share, f"{surface}: {ratio:.4f} of the photo's gradient energy"
    # realistic, not perfectly flat: a few levels of fine noise are left
    assert grey.std() > 0.5
    assert gradient_energy(grey) > 1.0


def test_the_parking_lot_has_bright_lines_on_dark_asphalt() -> None:
    world = make_world("flat", 1, 40.0, 0.05, GroundOptions(surface="parking"))
    renderer = Renderer(world, PINHOLE, RenderConfig(noise_sigma_dn=0.0, laser_marks="off"))
    # 9 m up: at least one 2.5 m bay's two lines are in view
    T = T_WORLD_CAM.copy()
    T[2, 3] = -9.0
    grey = cv2.cvtColor(renderer.render_pose(T, 0).image_bgr, cv2.COLOR_BGR2GRAY)
    bright = (grey > 150).mean()
    assert 0.01 < bright < 0.25
    assert 50 < np.median(grey) < 110


def test_every_surface_is_seeded_and_unknown_ones_are_refused() -> None:
    for surface in ("tiles", "checkerboard", "checker_sheets", "parking", "concrete", "carpet"):
        a = surface_ground(surface, 3, (9, 9), 0.5)
        b = surface_ground(surface, 3, (9, 9), 0.5)
        assert all(np.array_equal(x, y) for x, y in zip(a[0], b[0], strict=True))
        assert np.array_equal(a[2], b[2])
        assert all(t.shape == (512, 512) and t.min() >= 0 and t.max() <= 1 for t in a[0])
    with pytest.raises(SitlError, match="unknown surface 'marble'"):
        surface_ground("marble", 1, (9, 9), 0.5)


def test_specular_patches_cover_their_share_with_soft_edges() -> None:
    patches = SpecularPatches(2, 60.0, 0.2)
    share = float((patches.grid >= 0.5).mean())
    assert 0.18 < share < 0.26
    x, y, _r = patches.discs[0]
    assert patches.weight(x, y)[0] > 0.99
    # far outside every disc: nothing
    d = np.hypot(patches.discs[:, 0] - 29.0, patches.discs[:, 1] - 29.0) - patches.discs[:, 2]
    if d.min() > 0.3:
        assert patches.weight(29.0, 29.0)[0] == 0.0
    assert 0.2 <= patches.bottom_depth_m(x, y) <= 0.8
    with pytest.raises(SitlError, match="specular_patches"):
        SpecularPatches(1, 60.0, 0.9)


def test_the_default_ground_is_the_photo_world_and_render_at_adds_nothing() -> None:
    """Rule one: with the default options the frames are those of before (the one-off check
    against the previous code's frames and ranges hashed 3 flights x 12 frames identical)."""
    plain = World("flat", 1, 40.0, np.zeros((2, 2), np.float32), 40.0, np.zeros((0, 6)), 6.0)
    dressed = make_world("flat", 1, 40.0, 0.05, GroundOptions())
    assert dressed.specular is None and dressed.surface_textures == []
    assert np.array_equal(plain.fields, dressed.fields)
    assert np.array_equal(plain.layers, dressed.layers)
    assert dressed.textures[0].shape == plain.textures[0].shape
    cfg = RenderConfig(noise_sigma_dn=2.0, laser_marks="off")
    renderer = Renderer(dressed, CameraConfig(), cfg, seed=4)
    traj = Trajectory("hover", dressed, 4.0, 3.0)
    at = renderer.render_at(traj, 1.0, 30)
    pose = renderer.render_pose(traj.T_world_body(1.0) @ renderer.T_body_cam, 30)
    assert np.array_equal(at.image_bgr, pose.image_bgr)


def test_a_surface_changes_the_ground_but_not_the_roofs_and_walls() -> None:
    photo = make_world("urban", 1, 60.0)
    tiles = make_world("urban", 1, 60.0, ground=GroundOptions(surface="tiles"))
    assert np.array_equal(photo.layers[2:], tiles.layers[2:])
    assert np.array_equal(photo.boxes, tiles.boxes)
    assert not np.array_equal(photo.layers[:2], tiles.layers[:2])
    assert len(tiles.textures[1]) == 5  # grass, gravel, brick, then the tiles' two
