"""The lens model checked at load (companion/geometry/lens_check.py): the lenses we ship pass,
a distortion that folds over inside the image is refused naming its key (exit 2), and a lens
that passes never fails to undistort a pixel of its image."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from companion.cli import main
from companion.config import CameraConfig, load_config
from companion.drivers.dataset import check_lens
from companion.errors import ConfigError, DatasetError, GeometryError
from companion.geometry.camera import CameraModel
from companion.geometry.lens_check import corner_radius, lens_problem, radial_fold


def test_the_default_and_plain_lenses_pass() -> None:
    assert lens_problem(CameraConfig().model()) is None
    assert lens_problem(CameraModel(640, 480, 460.0, 460.0, 319.5, 239.5)) is None
    # EuRoC's cam0 (radial-tangential, 752 x 480)
    euroc = CameraModel(752, 480, 458.654, 457.296, 367.215, 248.375, -0.2834, 0.0739, 1.9e-4)
    assert lens_problem(euroc) is None


def test_barrel_beyond_fold_over_is_refused_naming_the_key() -> None:
    with pytest.raises(ConfigError, match=r"^camera\.dist: .*stops increasing") as e:
        load_config(None, {"camera": {"dist": [-0.6, 0.0, 0.0, 0.0, 0.0]}})
    # k1 = -0.6 folds at r = 1/sqrt(1.8) = 0.745 where g = 0.497 < the corner's 0.870
    assert "corners reach 0.870" in str(e.value) and "0.497" in str(e.value)
    model = CameraModel(640, 480, 460.0, 460.0, 319.5, 239.5, -0.6)
    assert corner_radius(model) == pytest.approx(np.hypot(320.0, 240.0) / 460.0)
    with pytest.raises(DatasetError, match=r"calibration.toml \[camera\] dist: .*stops"):
        check_lens(model, "calibration.toml [camera]")
    with pytest.raises(GeometryError):  # what the VO met mid-run before the check
        model.pixels_to_normalized([[0.0, 0.0]])


def test_a_fold_is_found_where_the_slope_of_the_radial_map_vanishes() -> None:
    # g(r) = r (1 + k1 r^2): g'(r) = 1 + 3 k1 r^2 = 0 at r = 1 / sqrt(-3 k1)
    for k1 in (-0.2, -0.35, -0.5):
        model = CameraModel(100, 100, 50.0, 50.0, 49.5, 49.5, k1)
        r_fold = 1.0 / np.sqrt(-3.0 * k1)
        g_fold = r_fold * (1.0 + k1 * r_fold**2)
        assert radial_fold(model, 0.9 * g_fold) is None
        assert radial_fold(model, 1.01 * g_fold) is not None


def test_run_and_eval_exit_2_on_a_folding_lens(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "lens.toml"
    bad.write_text("[camera]\ndist = [-0.6, 0.0, 0.0, 0.0, 0.0]\n")
    assert main(["config", "--config", str(bad)]) == 2
    assert main(["run", "--config", str(bad)]) == 2
    out = tmp_path / "eval"
    assert main(["eval", "--config", str(bad), "--seconds", "1", "--out", str(out)]) == 2
    assert not out.exists()  # refused before anything ran
    err = capsys.readouterr().err
    assert "camera.dist" in err and "does not invert" in err


def test_a_lens_that_passes_undistorts_every_pixel_of_its_image() -> None:
    """Seeded random lenses, strong ones included: whichever passes the check undistorts a
    dense grid over the whole image (half a pixel beyond the centres of the border pixels)
    without 'did not converge', and back to the same pixel."""
    rng = np.random.default_rng(7)
    u = np.linspace(-0.5, 159.5, 161)
    v = np.linspace(-0.5, 119.5, 121)
    grid = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    passed = refused = 0
    for _ in range(150):
        k1, k2, k3 = rng.uniform(-0.8, 0.4), rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)
        p1, p2 = rng.uniform(-0.02, 0.02, 2)
        model = CameraModel(160, 120, 115.0, 115.0, 79.5, 59.5, k1, k2, p1, p2, k3)
        if lens_problem(model) is not None:
            refused += 1
            continue
        passed += 1
        xy = model.pixels_to_normalized(grid)
        back = model.normalized_to_pixels(xy)
        assert np.max(np.abs(back - grid)) < 1e-6
    assert passed >= 30 and refused >= 30
