"""The exposure as it changes, and vignetting (sitl/world/exposure.py), and their place in
the rendered image: the linear image times the gain, then noise, then the 8-bit clip."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from companion.config import CameraConfig, Config, RenderConfig
from companion.geometry import se3, so3
from companion.render_options import ExposureOptions
from companion.sitl.world.exposure import ExposureModel, vignette
from companion.sitl.world.render import Renderer
from companion.sitl.world.terrain import World

FRAME_S = 1.0 / 30.0
STEPS = ExposureOptions(steps_per_s=2.0, step_max=0.3)
EVERYTHING = ExposureOptions(
    steps_per_s=0.5, drift=0.15, clouds_per_min=3.0, cloud_depth=0.4, vignetting=0.6
)


def gains(opts: ExposureOptions, seed: int, seconds: float = 120.0) -> np.ndarray:
    model = ExposureModel(opts, seed)
    return np.array([model.gain(k * FRAME_S) for k in range(int(seconds / FRAME_S))])


def test_the_gain_is_the_same_whatever_was_asked_before() -> None:
    a = gains(EVERYTHING, 5)
    late_first = ExposureModel(EVERYTHING, 5)
    late = late_first.gain(3000 * FRAME_S)  # a frame far ahead first, then the start
    assert late_first.gain(10 * FRAME_S) == a[10] and late_first.gain(1000 * FRAME_S) == a[1000]
    assert late == ExposureModel(EVERYTHING, 5).gain(3000 * FRAME_S)
    assert not np.array_equal(a, gains(EVERYTHING, 6))  # another seed, another flight
    assert np.all(gains(ExposureOptions(), 5) == 1.0)  # off: exactly 1


def test_auto_exposure_steps_are_bounded_and_stay_near_one() -> None:
    for seed in (1, 2, 3):
        g = gains(STEPS, seed)
        ratio = np.abs(np.diff(np.log(g)))
        steps = ratio > 1e-12
        # about 2 steps a second, each at most +-30 % from one frame to the next
        assert 150 < steps.sum() < 330
        assert ratio.max() <= np.log1p(0.3) + 1e-12
        assert ratio[steps].max() > np.log1p(0.2)  # steps near the largest do occur
        # the auto-exposure aims at 1 with a metering error of half a step
        assert g.min() > 0.7 and g.max() < 1.45


def test_a_cloud_dims_by_its_depth_and_auto_exposure_wins_the_light_back() -> None:
    cloud = ExposureOptions(clouds_per_min=2.0, cloud_depth=0.4, cloud_s=4.0, cloud_ramp_s=1.0)
    g = gains(cloud, 3)
    assert g.max() == 1.0 and g.min() == pytest.approx(0.6, abs=1e-9)
    dim = (g < 0.999).mean()
    assert 0.05 < dim < 0.35  # ~2 clouds of ~5 s a minute
    # the ramps are smooth: at most 40 % over 1 s (30 frames), ~2.1 % between frames
    assert np.abs(np.diff(g)).max() < 0.4 * np.pi / 2 / 30 + 1e-9
    with_ae = gains(ExposureOptions(**{**_fields(cloud), "steps_per_s": 4.0}), 3)
    under = g < 0.61
    assert np.median(np.abs(np.log(with_ae[under]))) < 0.5 * abs(np.log(0.6))


def _fields(o: ExposureOptions) -> dict[str, float]:
    return {k: getattr(o, k) for k in o.__slots__}


def test_the_drift_is_slow_and_bounded() -> None:
    g = gains(ExposureOptions(drift=0.15, drift_period_s=30.0), 1)
    assert g.min() == pytest.approx(0.85, abs=1e-3) and g.max() == pytest.approx(1.15, abs=1e-3)
    assert np.abs(np.diff(g)).max() < 0.15 * 2 * np.pi / 30 * FRAME_S * 1.001


def test_vignetting_is_one_on_the_axis_symmetric_and_cos4() -> None:
    cam = CameraConfig(dist=(0.0, 0.0, 0.0, 0.0, 0.0))  # cx, cy at the image centre
    rays = cam.model().pixel_rays()
    v = vignette(rays.reshape(-1, 3), 0.6).reshape(cam.height, cam.width)
    assert np.allclose(v, v[::-1], atol=1e-12) and np.allclose(v, v[:, ::-1], atol=1e-12)
    centre = v[cam.height // 2 - 1 : cam.height // 2 + 1, cam.width // 2 - 1 : cam.width // 2 + 1]
    assert np.all(centre > 1 - 1e-5) and v.max() <= 1.0
    corner_cos = 1.0 / np.sqrt(1 + (319.5 / 460) ** 2 + (239.5 / 460) ** 2)
    assert v[0, 0] == pytest.approx(1 - 0.6 * (1 - corner_cos**4), abs=1e-12)
    assert np.all(vignette(rays.reshape(-1, 3), 0.0) == 1.0)


def test_the_image_is_the_linear_image_times_the_gain_clipped(
    world: Callable[[str, int], World], default_config: Config
) -> None:
    """8-bit = clip(round(linear * frame gain * vignette)): bright patches saturate at 255,
    never wrap; the frame gain is the model's at the frame's time."""
    cam = default_config.camera
    drift = ExposureOptions(drift=0.5, drift_period_s=4.0, vignetting=0.5)
    render = RenderConfig(noise_sigma_dn=0.0, laser_marks="off", exposure=drift)
    r = Renderer(world("urban", 1), cam, render, seed=4)
    T = se3.make(so3.rpy_to_matrix(0.05, 0.02, 1.0), [5.0, 3.0, -12.0]) @ cam.T_body_cam()
    linear = r.render_linear(T).reshape(-1, 3)
    saturated = 0
    for time_s in (0.3, 1.7, 3.1):
        gain = r.exposure.gain(time_s)
        img = r.render_pose(T, 2, time_s=time_s).image_bgr.reshape(-1, 3)
        factor = (vignette(r.rays_cam, 0.5).astype(np.float32) * np.float32(gain))[:, None]
        expected = np.clip(np.floor(linear * factor + 0.5), 0, 255)
        diff = np.abs(img.astype(float) - expected)
        assert diff.max() <= 1 and (diff > 0).mean() < 1e-3
        if gain > 1.3:
            assert (img == 255).mean() > 0.001  # saturated, not wrapped
            assert np.all(img[linear * factor > 256] >= 254)
            saturated += 1
    assert saturated >= 1
    assert r.render_pose(T, 2).image_bgr.mean() < 255  # no time: no frame gain


def test_every_effect_renders_ahead_on_threads_as_on_one() -> None:
    """Threads that render ahead (Scenario.steps(workers=N)) each hold their own exposure
    model; the frames are those one thread renders, with every effect but blur on."""
    from companion.config import load_config
    from companion.sitl.world.scenario import Scenario

    render = {
        "readout_ms": 20.0,
        "exposure": {"steps_per_s": 20.0, "drift": 0.2, "drift_period_s": 1.0, "vignetting": 0.5},
        "lens_error": {"focal": 0.01, "principal_px": [3.0, -2.0], "mount_deg": [0.6, -0.6, 0.5]},
    }
    cfg = load_config("config/sitl.toml", {"sitl": {"seconds": 0.2, "render": render}})
    one = Scenario(cfg)
    expected = [s.frame.image_bgr for s in one.steps()]
    got = [s.frame.image_bgr for s in Scenario(cfg, world=one.world).steps(workers=2)]
    assert len(expected) == 6 and len(got) == 6
    assert all(np.array_equal(a, b) for a, b in zip(got, expected, strict=True))
    means = [float(e.mean()) for e in expected]
    assert max(means) - min(means) > 1.0  # the gain changes within these 6 frames
