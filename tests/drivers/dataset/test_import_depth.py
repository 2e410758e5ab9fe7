"""Distance sensors synthesised from depth images: the marched range equals the analytic
distance to a plane, holes and depth edges drop the reading, the noise model keeps its sigma
and its limits."""

from __future__ import annotations

import numpy as np
import pytest

from companion.config import MountConfig, RangefinderConfig
from companion.drivers.dataset.import_depth import (
    BeamHit,
    BeamMiss,
    beam_in_camera,
    depth_at,
    march_beam,
    noisy_reading,
)
from companion.drivers.dataset.import_sources import TUM_CAMERAS
from companion.drivers.dataset.import_write import DEFAULT_BEAMS
from companion.geometry.camera import CameraModel
from companion.types import F64


def _fr1() -> CameraModel:
    (fx, fy, cx, cy), dist = TUM_CAMERAS["fr1"]
    return CameraModel(640, 480, fx, fy, cx, cy, *dist)


def _plane_depth(camera: CameraModel, normal: F64, offset_m: float) -> F64:
    """Depth image (H, W) [m] of the plane n . p = c seen through every pixel (its z)."""
    rays = camera.pixel_rays()  # (H, W, 3), distortion undone
    t = offset_m / (rays @ normal)
    return np.asarray(t * rays[..., 2], dtype=np.float64)


def test_the_marched_range_is_the_analytic_distance_to_a_tilted_plane() -> None:
    camera = _fr1()  # with the fr1 distortion: the beam is projected as the image is
    normal = np.array([0.25, -0.15, 1.0])
    normal /= np.linalg.norm(normal)  # a plane tilted 17 deg to the optical axis
    offset_m = 1.3
    depth = _plane_depth(camera, normal, offset_m)
    for rf in DEFAULT_BEAMS:
        o, d = beam_in_camera(rf)
        hit = march_beam(depth, camera, o, d)
        assert isinstance(hit, BeamHit)
        analytic_m = (offset_m - normal @ o) / (normal @ d)
        assert abs(hit.range_m - analytic_m) < 1e-3, (rf.sensor_id, hit.range_m, analytic_m)
        # the pixel it reports is where the hit point projects
        uv, _ = camera.project((o + analytic_m * d)[None, :])
        assert np.linalg.norm(hit.uv_px - uv[0]) < 0.5


def test_the_default_beams_leave_the_lens_tilted_outward_and_land_apart() -> None:
    camera = _fr1()
    depth = np.full((480, 640), 1.0)
    pixels = []
    for rf in DEFAULT_BEAMS:
        o, d = beam_in_camera(rf)
        tilt_deg = np.degrees(np.arccos(d[2]))
        assert 5.0 <= tilt_deg <= 12.5 and 0.0 < np.linalg.norm(o) < 0.06
        assert float(o[:2] @ d[:2]) > 0  # outward: the beam leans towards its own side
        hit = march_beam(depth, camera, o, d)
        assert isinstance(hit, BeamHit)
        pixels.append(hit.uv_px)
    gaps = [np.linalg.norm(a - b) for i, a in enumerate(pixels) for b in pixels[i + 1 :]]
    assert min(gaps) > 60.0  # well-separated pixels at 1 m


def test_missing_depth_where_the_beam_lands_drops_the_reading() -> None:
    camera = _fr1()
    depth = np.full((480, 640), 1.2)
    o, d = beam_in_camera(DEFAULT_BEAMS[2])
    hit = march_beam(depth, camera, o, d)
    assert isinstance(hit, BeamHit)
    u, v = np.rint(hit.uv_px).astype(int)
    holed = depth.copy()
    holed[v - 6 : v + 7, u - 6 : u + 7] = 0.0  # a Kinect hole around the spot
    assert march_beam(holed, camera, o, d) == BeamMiss("missing_depth")
    assert march_beam(np.zeros_like(depth), camera, o, d) == BeamMiss("no_surface")
    assert march_beam(np.full_like(depth, 20.0), camera, o, d) == BeamMiss("no_surface")


def test_a_beam_that_passes_behind_a_depth_edge_is_dropped() -> None:
    camera = CameraModel(640, 480, 517.0, 517.0, 320.0, 240.0)
    depth = np.full((480, 640), 3.0)
    depth[:, :270] = 0.5  # near on the left of u = 270, far on the right
    tilt = np.radians(10.0)
    o, d = np.array([0.05, 0.0, 0.0]), np.array([-np.sin(tilt), 0.0, np.cos(tilt)])
    # the beam starts over the far side and crosses u = 270 at z = 0.63 m, behind the near
    # surface (0.5 m): no surface of the image is hit there (the near object's side is)
    assert march_beam(depth, camera, o, d) == BeamMiss("depth_edge")
    depth[:, :270] = 3.0
    hit = march_beam(depth, camera, o, d)
    assert isinstance(hit, BeamHit) and abs(hit.range_m - 3.0 / np.cos(tilt)) < 1e-3


def test_depth_lookup_is_bilinear_on_a_smooth_surface_and_nearest_at_an_edge() -> None:
    depth = np.array([[1.0, 1.02], [1.01, 1.03]])
    assert depth_at(depth, np.array([[0.5, 0.5]]))[0] == pytest.approx(1.015)
    edge = np.array([[1.0, 2.0], [1.0, 2.0]])
    assert depth_at(edge, np.array([[0.4, 0.5]]))[0] == 1.0  # no 1.4 m phantom surface
    assert depth_at(edge, np.array([[1.5, 0.5]]))[0] == 0.0  # outside the image


def test_the_noise_model_keeps_its_sigma_and_the_limits_read_as_invalid() -> None:
    rf = RangefinderConfig(
        sensor_id=0, mount=MountConfig(), min_m=0.3, max_m=4.0, sigma_a_m=0.01, sigma_b=0.01
    )
    rng = np.random.default_rng(3)
    got = np.array([noisy_reading(rf, 2.0, rng).distance_m for _ in range(4000)])
    assert abs(got.mean() - 2.0) < 0.002
    assert abs(got.std() - 0.03) < 0.003  # sigma = a + b r = 0.01 + 0.01 * 2
    far, near = noisy_reading(rf, 5.0, rng), noisy_reading(rf, 0.2, rng)
    assert (far.distance_m, far.signal_quality, far.true_distance_m) == (4.0, 1, 5.0)
    assert (near.distance_m, near.signal_quality) == (0.3, 1)
    ok = noisy_reading(rf, 1.0, rng)
    assert 2 <= ok.signal_quality <= 100 and ok.true_distance_m == 1.0
