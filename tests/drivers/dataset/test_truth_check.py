"""`companion dataset truth-check` (drivers/dataset/truth_check.py, evaluation/truth_flow.py):
on a simulated flight over a flat floor, whose conventions are known, the truth explains the
floor's image motion; a camera mount turned about the optical axis, a truth 100 ms off the
frames or a focal length 20 % off are each caught, and the fitted lens comes back near the
true one."""

from __future__ import annotations

import re
import shutil
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from peers import small_camera

from companion.cli import main
from companion.config import load_config
from companion.drivers.dataset import open_dataset
from companion.drivers.dataset.toml_text import toml_dumps
from companion.drivers.dataset.truth_check import check_truth
from companion.errors import DatasetError
from companion.evaluation.truth_flow import FloorPair, floor_px_in_b
from companion.geometry import se3, so3


@pytest.fixture(scope="module")
def flat_flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 s of a lawnmower at 4 m over flat ground (the floor z = 0), 320 x 240, no lens
    distortion, global shutter."""
    from companion.sitl.world.dataset import record

    overrides = small_camera()
    overrides["camera"]["dist"] = [0.0, 0.0, 0.0, 0.0, 0.0]
    overrides["sitl"] = {"terrain": "flat", "trajectory": "lawnmower", "seconds": 4.0, "seed": 2}
    out = tmp_path_factory.mktemp("truth") / "flat"
    record(load_config(overrides=overrides), out, image_format="png", progress=False)
    return out


def with_calibration(src: Path, dst: Path, camera: dict[str, object]) -> Path:
    """A copy of the dataset ``src`` with these keys of its calibration's [camera] replaced."""
    shutil.copytree(src, dst)
    data = tomllib.loads((dst / "calibration.toml").read_text())
    data["camera"].update(camera)
    data.pop("matrices", None)  # other tools' copy of the mounts
    (dst / "calibration.toml").write_text(toml_dumps(data))
    return dst


def test_the_floor_point_goes_where_the_plane_sends_it() -> None:
    """Frame b 0.5 m east of a (both 4 m over the floor, looking down): a floor point moves
    by f * 0.5 / 4 px across the image, and a ray that misses the floor gives None."""
    lens = load_config(overrides=small_camera()).camera.model()
    model = replace(lens, k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0)  # a pinhole: exact shifts
    down = np.eye(3)  # camera z = world z (down), camera x = north, y = east
    T_a = se3.make(down, [0.0, 0.0, -4.0])
    T_b = se3.make(down, [0.0, 0.5, -4.0])
    px_a = np.array([[model.cx, model.cy], [model.cx + 40.0, model.cy - 30.0]])
    pair = FloorPair(px_a, px_a, T_a, T_b)
    uv = floor_px_in_b(model, pair, 0.0)
    assert uv is not None
    shift = uv - px_a
    assert np.allclose(shift[:, 1], -model.fy * 0.5 / 4.0, atol=1e-6)
    assert np.allclose(shift[:, 0], 0.0, atol=1e-6)
    up = se3.make(so3.rot_x(np.pi), [0.0, 0.0, -4.0])  # looking at the sky
    assert floor_px_in_b(model, FloorPair(px_a, px_a, up, T_b), 0.0) is None


def test_the_truth_of_a_simulated_flight_explains_its_floors_flow(flat_flight: Path) -> None:
    ds = open_dataset(flat_flight)
    check = check_truth(ds, 0.0, offsets_s=(-0.1, 0.0, 0.1))
    assert check.pairs >= 15 and check.no_motion_px > 3.0
    by_offset = {round(o, 3): median for o, median, _ in check.truth_px}
    assert by_offset[0.0] < 0.15 * check.no_motion_px
    # a truth 100 ms off the frames explains less
    assert by_offset[0.1] > 2.0 * by_offset[0.0] and by_offset[-0.1] > 2.0 * by_offset[0.0]
    assert check.best_offset_s == 0.0


def test_a_mount_turned_about_the_optical_axis_is_caught(flat_flight: Path, tmp_path: Path) -> None:
    ds = open_dataset(flat_flight)
    assert np.allclose(ds.T_body_cam[:3, :3], so3.rot_z(np.radians(90.0)))  # recorded: 90
    mount = {"xyz_m": [float(v) for v in ds.T_body_cam[:3, 3]], "rpy_deg": [0.0, 0.0, -90.0]}
    turned = with_calibration(flat_flight, tmp_path / "turned", {"mount": mount})
    right = check_truth(ds, 0.0)
    wrong = check_truth(open_dataset(turned), 0.0)
    assert wrong.truth_px[0][1] > 0.8 * wrong.no_motion_px
    assert wrong.truth_px[0][1] > 5.0 * right.truth_px[0][1]


def test_a_focal_length_20_percent_off_is_caught_and_fitted_back(
    flat_flight: Path, tmp_path: Path
) -> None:
    ds = open_dataset(flat_flight)
    f = ds.camera.fx
    off = with_calibration(flat_flight, tmp_path / "off", {"fx": 0.8 * f, "fy": 0.8 * f})
    right = check_truth(ds, 0.0)
    wrong = check_truth(open_dataset(off), 0.0, lens=True)
    assert wrong.truth_px[0][1] > 3.0 * right.truth_px[0][1]
    assert wrong.lens is not None
    assert wrong.lens.focal_px == pytest.approx(f, rel=0.05)
    assert wrong.lens.median_error_px < 1.5 * right.truth_px[0][1]


def test_the_command_prints_the_check_and_refuses_a_dataset_without_truth(
    flat_flight: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["dataset", "truth-check", str(flat_flight), "--floor-z", "0"]) == 0
    out = capsys.readouterr().out
    explained = r"truth at \+0 ms: [0-9.]+ px \((8[0-9]|9[0-9]|100) % of the flow explained"
    assert re.search(explained, out)
    bare = tmp_path / "bare"
    shutil.copytree(flat_flight, bare)
    (bare / "groundtruth.txt").unlink()
    with pytest.raises(DatasetError, match="no ground truth"):
        check_truth(open_dataset(bare), 0.0)
    assert main(["dataset", "truth-check", str(bare), "--floor-z", "0"]) == 2
