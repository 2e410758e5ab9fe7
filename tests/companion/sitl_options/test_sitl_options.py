"""[sitl.ground] and [sitl.rangefinder]: read from TOML, off by default, bad values named."""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.config import load_config
from companion.errors import ConfigError
from companion.sitl_options import GroundOptions, RangeEffects


def test_the_defaults_turn_every_effect_off() -> None:
    cfg = load_config()
    assert cfg.sitl.ground == GroundOptions()
    g = cfg.sitl.ground
    assert (g.surface, g.specular_patches, g.downwash_m, g.shadow) == ("photo", 0.0, 0.0, False)
    r = cfg.sitl.rangefinder
    assert r == RangeEffects()
    assert (r.bias_sigma_m, r.edge_outlier_prob, r.specular_miss_prob) == (0.0, 0.0, 0.0)
    assert (r.specular_through_prob, r.below_min) == (0.0, "min")


def test_a_toml_sets_them(tmp_path: Path) -> None:
    path = tmp_path / "hard.toml"
    path.write_text(
        '[sitl.ground]\nsurface = "checkerboard"\nspecular_patches = 0.1\nshadow = true\n'
        '[sitl.rangefinder]\nbias_sigma_m = 0.02\nbelow_min = "zero"\n'
    )
    cfg = load_config(path)
    assert cfg.sitl.ground.surface == "checkerboard" and cfg.sitl.ground.shadow
    assert cfg.sitl.ground.specular_patches == 0.1
    assert cfg.sitl.rangefinder.bias_sigma_m == 0.02 and cfg.sitl.rangefinder.below_min == "zero"


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ('[sitl.ground]\nsurface = "marble"\n', "sitl.ground.surface"),
        ("[sitl.ground]\nspecular_patches = 0.9\n", "sitl.ground.specular_patches"),
        ("[sitl.rangefinder]\nbias_sigma_m = -0.1\n", "sitl.rangefinder.bias_sigma_m"),
        ('[sitl.rangefinder]\nbelow_min = "max"\n', "sitl.rangefinder.below_min"),
        ("[sitl.rangefinder]\nglass = 1\n", "sitl.rangefinder.glass"),
    ],
)
def test_a_bad_value_is_refused_by_its_key(tmp_path: Path, text: str, key: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(path)
