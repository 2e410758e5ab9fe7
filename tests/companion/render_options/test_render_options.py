"""The camera effects' options ([sitl.render], companion/render_options.py): off by default,
loaded from TOML, a bad value refused naming its key; config/ideal.toml is the defaults and
config/realistic.toml turns every effect on."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from companion.config import Config, load_config
from companion.errors import ConfigError
from companion.render_options import ExposureOptions, LensErrorOptions, RenderConfig


def test_every_effect_is_off_by_default() -> None:
    r = RenderConfig()
    assert r.readout_ms == 0.0 and not r.motion_blur
    assert not r.exposure.any and not r.exposure.frame_gain_varies and not r.lens_error.any
    # a step size or a depth alone changes nothing: only a rate turns them on
    assert not ExposureOptions(step_max=0.5, cloud_depth=0.9).any
    assert (
        ExposureOptions(vignetting=0.1).any
        and not ExposureOptions(vignetting=0.1).frame_gain_varies
    )
    assert LensErrorOptions(mount_deg=(0.0, 0.0, 0.1)).any


def test_ideal_is_the_defaults_and_realistic_turns_every_effect_on() -> None:
    assert load_config("config/ideal.toml") == Config()
    r = load_config("config/realistic.toml").sitl.render
    assert r.readout_ms == 20.0 and r.motion_blur
    assert r.exposure.frame_gain_varies and r.exposure.vignetting > 0
    assert r.exposure.step_max == 0.3
    lens = r.lens_error
    assert (lens.focal, lens.principal_px, lens.k1) == (0.01, (3.0, -2.0), 0.02)


@pytest.mark.parametrize(
    ("render", "message"),
    [
        ({"readout_ms": -1.0}, "sitl.render.readout_ms: must be >= 0"),
        ({"readout_ms": "20"}, "sitl.render.readout_ms: expected a number"),
        ({"exposure": {"step_max": 0.8}}, "sitl.render.exposure.step_max: must be <= 0.5"),
        ({"exposure": {"vignetting": 1.5}}, "sitl.render.exposure.vignetting: must be <= 1"),
        ({"exposure": {"cloud_s": 0}}, "sitl.render.exposure.cloud_s: must be > 0"),
        ({"exposure": {"gain": 2}}, "sitl.render.exposure.gain: unknown key"),
        (
            {"lens_error": {"principal_px": [1.0]}},
            "sitl.render.lens_error.principal_px: expected 2",
        ),
        (
            {"lens_error": {"mount_deg": [0, 0, 20]}},
            "sitl.render.lens_error.mount_deg: must be <= 10",
        ),
        ({"lens_error": {"focal": 0.5}}, "sitl.render.lens_error.focal: must be <= 0.2"),
        # a k1 that folds the image over: the rendered lens does not invert
        ({"lens_error": {"k1": -0.3}}, "sitl.render.lens_error: the rendered lens"),
    ],
)
def test_a_bad_value_names_its_key(render: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as e:
        load_config(None, {"sitl": {"render": render}})
    assert str(e.value).startswith(message), str(e.value)


def test_the_effects_load_from_a_file(tmp_path: Path) -> None:
    path = tmp_path / "rs.toml"
    path.write_text("[sitl.render]\nreadout_ms = 12.5\n[sitl.render.lens_error]\nk1 = 0.01\n")
    cfg = load_config(path, {"sitl": {"seed": 3}})
    assert cfg.sitl.render.readout_ms == 12.5 and cfg.sitl.render.lens_error.k1 == 0.01
    assert cfg.sitl.seed == 3 and cfg.camera == Config().camera  # the VO's camera unchanged
