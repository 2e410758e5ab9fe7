"""What moves on the ground (ground_effects.py): the specular highlight follows the camera, the
vehicle's shadow lies on the sun line from the vehicle, the downwash stirs only the grass
under the vehicle, and only while time passes."""

from __future__ import annotations

import copy

import cv2
import numpy as np

from companion.config import CameraConfig, RenderConfig
from companion.geometry import se3
from companion.sitl.world import ground_effects
from companion.sitl.world._ground_kernel import downwash_offsets
from companion.sitl.world.render import RenderedFrame, Renderer
from companion.sitl.world.terrain import make_world
from companion.sitl_options import GroundOptions

PINHOLE = CameraConfig(dist=(0.0, 0.0, 0.0, 0.0, 0.0))
SUN = RenderConfig(noise_sigma_dn=0.0, laser_marks="off", sun_elevation_deg=70.0)


def nadir(north_m: float, east_m: float, altitude_m: float) -> np.ndarray:
    """T_world_cam (4, 4): camera x east, y south, z down, over (north, east) at altitude."""
    return np.array(
        [
            [0.0, -1.0, 0.0, north_m],
            [1.0, 0.0, 0.0, east_m],
            [0.0, 0.0, 1.0, -altitude_m],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def world_points(renderer: Renderer, frame: RenderedFrame) -> np.ndarray:
    """(H*W, 3) NED point of every pixel."""
    rays = renderer.rays_cam
    p_cam = rays * (frame.depth_m.ravel() / rays[:, 2])[:, None]
    return se3.transform(frame.T_world_cam, p_cam)


def glint_centre(renderer: Renderer, T_world_cam: np.ndarray) -> np.ndarray:
    """World (north, east) [m] of the highlight's brightest part (the top 2 % of pixels)."""
    frame = renderer.render_pose(T_world_cam, 0)
    ground_effects.apply(renderer, frame, T_world_cam, 0.0)
    grey = frame.image_bgr.astype(np.float64).mean(axis=2).ravel()
    top = grey >= np.quantile(grey, 0.98)
    return world_points(renderer, frame)[top, :2].mean(axis=0)


def test_the_specular_highlight_sits_at_the_suns_mirror_point_and_moves_with_the_camera() -> None:
    world = make_world("flat", 1, 40.0, ground=GroundOptions(specular_patches=0.1))
    assert world.specular is not None
    world.specular.grid[:] = 1.0  # water over the whole ground
    renderer = Renderer(world, PINHOLE, SUN)
    up = np.array([0.0, 0.0, -1.0])
    mirror = 2.0 * float(up @ renderer.sun_ned) * up - renderer.sun_ned
    centres = []
    for north_m in (0.0, 1.5):
        T = nadir(north_m, 0.5, 3.0)
        camera = T[:3, 3]
        expected = camera - (camera[2] / mirror[2]) * mirror  # on the ground z = 0
        got = glint_centre(renderer, T)
        assert np.linalg.norm(got - expected[:2]) < 0.15, (got, expected)
        centres.append(got)
    shift = centres[1] - centres[0]
    assert abs(shift[0] - 1.5) < 0.1 and abs(shift[1]) < 0.1


def test_the_shadow_lies_on_the_sun_line_from_the_vehicle() -> None:
    world = make_world("flat", 1, 40.0, ground=GroundOptions(shadow=True, shadow_radius_m=0.3))
    renderer = Renderer(world, PINHOLE, SUN)
    T_cam = nadir(0.0, 0.0, 4.0)
    lit = renderer.render_pose(T_cam, 0)
    shaded = copy.deepcopy(lit)
    vehicle = T_cam.copy()  # the vehicle where the camera is
    ground_effects.apply(renderer, shaded, vehicle, 0.0)
    ratio = (shaded.image_bgr.astype(np.float64) + 1) / (lit.image_bgr.astype(np.float64) + 1)
    ratio = ratio.mean(axis=2).ravel()
    dark = ratio < 0.7
    assert dark.sum() > 200
    centre = world_points(renderer, lit)[dark, :2].mean(axis=0)
    sun = renderer.sun_ned
    expected = vehicle[:3, 3] - (vehicle[2, 3] / sun[2]) * sun  # along -sun down to z = 0
    assert np.linalg.norm(centre - expected[:2]) < 0.05, (centre, expected)
    # the full shadow keeps the ambient light only: 1 - 0.55 of a sunlit level ground
    assert abs(np.quantile(ratio, 0.001) - (1 - ground_effects.SHADOW_DEPTH)) < 0.05
    # nothing far from it changes
    far = np.linalg.norm(world_points(renderer, lit)[:, :2] - expected[:2], axis=1) > 1.0
    assert np.all(ratio[far] == 1.0)


def test_the_downwash_stirs_the_grass_under_the_vehicle_only_and_over_time() -> None:
    ground = GroundOptions(downwash_m=0.04, downwash_radius_m=1.0)
    world = make_world("flat", 1, 40.0, ground=ground)
    renderer = Renderer(world, PINHOLE, SUN)
    T_cam = nadir(2.0, 1.0, 4.0)
    base = renderer.render_pose(T_cam, 0)
    frames = []
    for time_s in (0.0, 0.07):
        frame = copy.deepcopy(base)
        ground_effects.apply(renderer, frame, T_cam, time_s)
        frames.append(frame.image_bgr.astype(np.int32))
    r = np.linalg.norm(world_points(renderer, base)[:, :2] - T_cam[None, :2, 3], axis=1)
    moved = np.abs(frames[0] - frames[1]).max(axis=2).ravel() > 3
    assert moved[r < 0.8].mean() > 0.3  # the grass moves under the vehicle
    assert not moved[r > 3.0].any()  # and stays still beyond three radii
    untouched = np.abs(frames[0] - base.image_bgr.astype(np.int32)).max(axis=2).ravel()
    assert np.all(untouched[r > 3.0] == 0)
    # the displacement's size: at most the amplitude
    pts = world_points(renderer, base)[r < 3.0]
    d = downwash_offsets(pts, T_cam[:3, 3], 0.3, 0.04, 1.0)
    assert np.linalg.norm(d, axis=1).max() <= 0.04 * 1.3 + 1e-9
    assert np.linalg.norm(d, axis=1).max() > 0.04 * 0.5
    assert np.all(d[:, 2] == 0.0)


def test_no_effect_leaves_the_frame_alone() -> None:
    world = make_world("flat", 1, 40.0)
    renderer = Renderer(world, PINHOLE, SUN)
    frame = renderer.render_pose(nadir(0.0, 0.0, 3.0), 0)
    before = frame.image_bgr.copy()
    ground_effects.apply(renderer, frame, nadir(0.0, 0.0, 3.0), 1.0)
    assert not ground_effects.any_on(renderer)
    assert np.array_equal(before, frame.image_bgr)


def reference_apply(
    renderer: Renderer, frame: RenderedFrame, vehicle: np.ndarray, t: float
) -> None:
    """The module docstring's model as whole-frame array passes (what the compiled pass
    replaced), in place on frame.image_bgr."""
    world, g = renderer.world, renderer.world.ground
    h, w = frame.depth_m.shape
    depth = frame.depth_m.ravel().astype(np.float64)
    ok = np.isfinite(depth)
    rays = renderer.rays_cam
    p = se3.transform(frame.T_world_cam, rays * np.where(ok, depth / rays[:, 2], 0.0)[:, None])
    ground_h = np.full(h * w, np.nan)
    ground_h[ok] = world.height(p[ok, 0], p[ok, 1])
    on_ground = ok & (np.abs(p[:, 2] + ground_h) < 0.03)
    out = frame.image_bgr.reshape(-1, 3).astype(np.float64)
    near = on_ground & (np.linalg.norm(p[:, :2] - vehicle[None, :2], axis=1) < 3.0 * 1.0)
    src = p[near] - downwash_offsets(p[near], vehicle, t, g.downwash_m, g.downwash_radius_m)
    uv, _ = renderer.model.project(se3.transform(se3.inverse(frame.T_world_cam), src))
    n = len(uv)
    maps = np.zeros((2, -(-n // 512) * 512), dtype=np.float32)  # remap takes <= 32767 columns
    maps[:, :n] = uv.T
    rows = maps.reshape(2, -1, 512)
    sampled = cv2.remap(
        frame.image_bgr, rows[0], rows[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    out[near] = sampled.reshape(-1, 3)[:n]
    q = vehicle[None, :] - p[ok]
    along = q @ renderer.sun_ned
    d = np.linalg.norm(q - along[:, None] * renderer.sun_ned[None, :], axis=1)
    soft = 0.08 + 0.01 * np.maximum(along, 0.0)
    x = np.clip((g.shadow_radius_m + soft - d) / (2.0 * soft), 0.0, 1.0)
    cover = np.where(along > 0.0, x * x * (3.0 - 2.0 * x), 0.0)
    out[ok] *= (1.0 - ground_effects.SHADOW_DEPTH * cover)[:, None]
    assert world.specular is not None
    wgt = np.zeros(h * w)
    wgt[on_ground] = world.specular.weight(p[on_ground, 0], p[on_ground, 1])
    lit = wgt > 0.0
    v = frame.T_world_cam[None, :3, 3] - p[lit]
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    sun = renderer.sun_ned
    mirror = np.array([-sun[0], -sun[1], sun[2]])
    glint = np.maximum(v @ mirror, 0.0) ** g.specular_exponent
    water = 0.06 * ground_effects.SKY_BGR[None, :] + 255.0 * g.specular_strength * glint[:, None]
    out[lit] = out[lit] * (1.0 - 0.6 * wgt[lit][:, None]) + wgt[lit][:, None] * water
    frame.image_bgr[:] = np.clip(np.floor(out + 0.5), 0, 255).astype(np.uint8).reshape(h, w, 3)


def test_the_compiled_pass_is_the_models_arrays_bit_for_bit() -> None:
    # all three effects at once over hills, a distorted lens, the vehicle 1.2 m over the
    # camera's ground point so that all three land in the frame
    ground = GroundOptions(
        specular_patches=0.3, shadow=True, downwash_m=0.05, downwash_radius_m=1.0
    )
    world = make_world("hills", 2, 60.0, ground=ground)
    renderer = Renderer(world, CameraConfig(), SUN)
    for north_m, t in ((0.0, 0.0), (3.0, 0.41), (-7.0, 1.3)):
        T_cam = nadir(north_m, 2.0, 5.0)
        T_cam[2, 3] -= float(world.height(north_m, 2.0)[0])
        vehicle = T_cam.copy()
        vehicle[0, 3] += 0.6
        base = renderer.render_pose(T_cam, 0)
        ours, reference = copy.deepcopy(base), copy.deepcopy(base)
        ground_effects.apply(renderer, ours, vehicle, t)
        reference_apply(renderer, reference, vehicle[:3, 3], t)
        changed = (reference.image_bgr != base.image_bgr).any(axis=2)
        assert changed.mean() > 0.05  # the effects are in the frame
        differ = (ours.image_bgr != reference.image_bgr).any(axis=2)
        assert not differ.any(), (north_m, int(differ.sum()), np.argwhere(differ)[:5])
