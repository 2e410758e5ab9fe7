"""Datasets: record -> read round trip, bit-identical with a seed, EuRoC reader, contact sheet."""

from __future__ import annotations

import filecmp
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.cli import main
from companion.config import load_config
from companion.drivers.dataset import open_dataset
from companion.errors import DatasetError
from companion.sitl.world.dataset import contact_sheet, record
from companion.sitl.world.trajectory import Trajectory
from companion.types import AttitudeSample, CameraFrame, RangeSample

SHORT = {"sitl": {"terrain": "hills", "trajectory": "lawnmower", "seconds": 2.0, "seed": 4}}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ds") / "hills"
    record(load_config(overrides=SHORT), out, image_format="png", progress=False)
    return out


def test_round_trip(recorded: Path) -> None:
    ds = open_dataset(recorded)
    cfg = load_config(overrides=SHORT)
    assert ds.kind == "companion" and len(ds) == 60
    assert ds.camera == cfg.camera.model()
    assert np.allclose(ds.T_body_cam, cfg.camera.T_body_cam())
    assert [r.sensor_id for r in ds.rangefinders] == [0, 1, 2, 3]
    assert np.allclose(ds.rangefinders[2].T_body_rf, cfg.rangefinders[2].mount.T_body_sensor())
    assert np.array_equal(ds.frame_times_us, np.round(np.arange(60) / 30.0 * 1e6))
    frame = ds.load_frame(10)
    assert frame.image_bgr.shape == (480, 640, 3) and frame.time_us == 333333
    # samples up to the last frame (59 / 30 s): four sensors at 50 Hz, attitude at 100 Hz
    last_s = 59 / 30.0
    assert abs(len(ds.ranges) - 4 * 50 * last_s) <= 4 and len(ds.true_range_m) == len(ds.ranges)
    assert max(r.time_us for r in ds.ranges) <= ds.frame_times_us[-1]
    errors = [r.distance_m - t for r, t in zip(ds.ranges, ds.true_range_m, strict=True)]
    assert np.abs(errors).max() < 0.06
    assert len(ds.attitudes) == int(last_s * 100) + 1
    # ground truth equals the trajectory (to the file's printed precision)
    assert ds.sitl is not None
    from companion.sitl.world.terrain import make_world

    traj = Trajectory("lawnmower", make_world("hills", 4), 2.0)
    for i in (0, 31, 59):
        T = traj.T_world_body(ds.gt_times_us[i] * 1e-6)
        assert np.abs(ds.gt_T_world_body[i] - T).max() < 1e-8
    assert np.allclose(ds.gt_pose_at(int(ds.gt_times_us[5])), ds.gt_T_world_body[5])


def test_events_are_time_ordered(recorded: Path) -> None:
    ds = open_dataset(recorded)
    events = list(ds.events())
    assert sum(isinstance(e, CameraFrame) for e in events) == 60
    assert sum(isinstance(e, RangeSample) for e in events) == len(ds.ranges)
    assert sum(isinstance(e, AttitudeSample) for e in events) == len(ds.attitudes)
    times = [e.time_us for e in events]
    assert times == sorted(times)


def test_same_seed_bit_identical_other_seed_different(recorded: Path, tmp_path: Path) -> None:
    again = tmp_path / "again"
    record(load_config(overrides=SHORT), again, image_format="png", progress=False)
    names = ["frames.csv", "ranges.csv", "attitude.csv", "groundtruth.txt", "calibration.toml"]
    names += [f"images/{i:06d}.png" for i in range(60)]
    match, mismatch, errors = filecmp.cmpfiles(recorded, again, names, shallow=False)
    assert mismatch == [] and errors == [] and len(match) == len(names)
    other = tmp_path / "other"
    overrides = {"sitl": {**SHORT["sitl"], "seed": 5}}
    record(load_config(overrides=overrides), other, image_format="png", progress=False)
    a = cv2.imread(str(recorded / "images/000030.png"))
    b = cv2.imread(str(other / "images/000030.png"))
    assert np.abs(a.astype(int) - b.astype(int)).mean() > 5
    assert not filecmp.cmp(recorded / "ranges.csv", other / "ranges.csv", shallow=False)


def write_euroc(ds_path: Path, out: Path) -> None:
    """Convert one of our datasets to EuRoC's layout (z-up world, IMU = F * body)."""
    ds = open_dataset(ds_path)
    F = np.diag([1.0, -1.0, -1.0, 1.0])
    cam = out / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    lines = ["#timestamp [ns],filename"]
    for i, t in enumerate(ds.frame_times_us):
        name = f"{int(t) * 1000 + 1_403_636_579_763_555_584}.png"
        gray = cv2.cvtColor(ds.load_frame(i).image_bgr, cv2.COLOR_BGR2GRAY)
        cv2.imwrite(str(cam / "data" / name), gray)
        lines.append(f"{int(t) * 1000 + 1_403_636_579_763_555_584},{name}")
    (cam / "data.csv").write_text("\n".join(lines) + "\n")
    c = ds.camera
    T_bs = F @ ds.T_body_cam
    (cam / "sensor.yaml").write_text(
        "%YAML:1.0\n# General sensor definitions.\nsensor_type: camera\n"
        "comment: VI-Sensor cam0 (MT9M034)\n\n# Sensor extrinsics wrt. the body-frame.\n"
        "T_BS:\n  cols: 4\n  rows: 4\n  data: ["
        + ", ".join(f"{v:.15f}" for v in T_bs.ravel()[:8])
        + ",\n         "
        + ", ".join(f"{v:.15f}" for v in T_bs.ravel()[8:])
        + "]\n\n"
        f"rate_hz: 30\nresolution: [{c.width}, {c.height}]\ncamera_model: pinhole\n"
        f"intrinsics: [{c.fx}, {c.fy}, {c.cx}, {c.cy}] #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        f"distortion_coefficients: [{c.k1}, {c.k2}, {c.p1}, {c.p2}]\n"
    )
    gt = out / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir(parents=True)
    rows = [
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
        "q_RS_y [], q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], "
        "b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
        "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
    ]
    from companion.geometry import so3

    for t, T in zip(ds.gt_times_us, ds.gt_T_world_body, strict=True):
        Tz = F @ T @ F
        q = so3.matrix_to_quat(Tz[:3, :3])
        vals = [*Tz[:3, 3], *q] + [0.0] * 9
        rows.append(
            f"{int(t) * 1000 + 1_403_636_579_763_555_584}," + ",".join(f"{v:.12f}" for v in vals)
        )
    (gt / "data.csv").write_text("\n".join(rows) + "\n")


def test_euroc_reader(recorded: Path, tmp_path: Path) -> None:
    write_euroc(recorded, tmp_path / "euroc")
    ours = open_dataset(recorded)
    euroc = open_dataset(tmp_path / "euroc")
    assert euroc.kind == "euroc" and len(euroc) == len(ours)
    c1, c2 = ours.camera, euroc.camera
    assert (c1.width, c1.height, c1.fx, c1.k1, c1.p2) == (c2.width, c2.height, c2.fx, c2.k1, c2.p2)
    assert np.allclose(euroc.T_body_cam, ours.T_body_cam, atol=1e-12)
    assert np.array_equal(
        euroc.frame_times_us - euroc.frame_times_us[0], ours.frame_times_us - ours.frame_times_us[0]
    )
    assert np.abs(euroc.gt_T_world_body - ours.gt_T_world_body).max() < 1e-9
    f = euroc.load_frame(7)
    assert f.image_bgr.shape == (480, 640, 3)
    gray = cv2.cvtColor(ours.load_frame(7).image_bgr, cv2.COLOR_BGR2GRAY)
    assert np.array_equal(f.image_bgr[..., 0], gray)
    assert len(euroc.attitudes) == len(ours.gt_times_us) and euroc.ranges == []


def test_bad_folders_give_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="not found"):
        open_dataset(tmp_path / "nope")
    with pytest.raises(DatasetError, match="neither"):
        open_dataset(tmp_path)
    (tmp_path / "meta.toml").write_text('format = "something-else"\n')
    (tmp_path / "calibration.toml").write_text("")
    with pytest.raises(DatasetError, match="not a companion-dataset"):
        open_dataset(tmp_path)


def test_cli_record_refuses_to_overwrite_and_writes_sheet(
    recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert (
        main(["sitl", "record", "--seconds", "1", "--out", str(recorded), "--no-progress"]) == 2
    )  # a refused output folder: bad input
    assert "exists" in capsys.readouterr().err
    out = tmp_path / "rec"
    assert (
        main(
            [
                "sitl",
                "record",
                "--terrain",
                "urban",
                "--trajectory",
                "figure8",
                "--seconds",
                "0.5",
                "--seed",
                "2",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    assert capsys.readouterr().out.strip() == str(out)
    assert open_dataset(out).sitl.terrain == "urban"  # type: ignore[union-attr]
    assert main(["sitl", "sheet", str(out)]) == 0
    sheet = cv2.imread(capsys.readouterr().out.strip())
    assert sheet.shape == (720, 1280, 3)
    path = contact_sheet(open_dataset(recorded), tmp_path / "s.png", n=8, cols=4)
    assert cv2.imread(str(path)).shape == (480, 1280, 3)


def test_a_dataset_declares_its_sensors_and_its_world(recorded: Path, tmp_path: Path) -> None:
    """What a dataset does not declare, it does not have: no [sitl] table, no world (not the
    default hills); no [[rangefinders]], no sensors (not the four built-in ones); a range
    from an undeclared sensor is refused by name. EuRoC declares none."""
    import shutil
    import tomllib

    import tomli_w

    from companion.cli.evaluate_dataset import dataset_config

    sim = open_dataset(recorded)
    assert sim.has_world and sim.sitl is not None and sim.sitl.seed == 4
    real = tmp_path / "real"
    shutil.copytree(recorded, real)
    meta = tomllib.loads((real / "meta.toml").read_text())
    del meta["sitl"]
    (real / "meta.toml").write_text(tomli_w.dumps(meta))
    ds = open_dataset(real)
    assert ds.sitl is None and not ds.has_world and len(ds.rangefinders) == 4
    calib = tomllib.loads((real / "calibration.toml").read_text())
    del calib["rangefinders"]
    (real / "calibration.toml").write_text(tomli_w.dumps(calib))
    with pytest.raises(DatasetError, match=r"sensor ids \[0, 1, 2, 3\] .* does not declare"):
        open_dataset(real)
    (real / "ranges.csv").unlink()
    ds = open_dataset(real)
    assert ds.rangefinders == [] and ds.ranges == [] and len(ds.attitudes) > 0
    assert ds.config is not None and ds.config.rangefinders == ()
    write_euroc(recorded, tmp_path / "euroc")
    euroc = open_dataset(tmp_path / "euroc")
    assert euroc.sitl is None and euroc.config is None
    cfg = dataset_config(euroc, None)
    assert cfg.rangefinders == () and cfg.attitude.sensor_ids == ()
