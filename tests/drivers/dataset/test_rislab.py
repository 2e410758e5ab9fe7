"""The RIS lab downward-flight importer (drivers/dataset/rislab.py) on a small synthetic copy
of its source layout: the capture record's frames and conventions, exposure times from
jittery stamps, floor distances along tilted beams, and the folder our reader opens."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import scipy.io

from companion.config import load_config
from companion.drivers.dataset import open_dataset, read_tum
from companion.drivers.dataset.rislab import (
    FLOOR_Z_M,
    LATENCY_S,
    RISLAB_BEAMS,
    Capture,
    beam_range_m,
    body_poses,
    exposure_times,
    import_rislab,
    read_capture,
)
from companion.errors import DatasetError
from companion.geometry import se3, so3

PERIOD_S = 1 / 60


def write_source(folder: Path, n_frames: int = 40, first: int = 10) -> np.ndarray:
    """A source folder: ``n_frames`` textured images ``test<N>.png`` and a capture record at
    500 Hz climbing at 0.5 m/s from 0.4 m, level; each frame tagged from 0-40 ms after its
    exposure (late deliveries). Returns the exposure times [s] of the frames."""
    rng = np.random.default_rng(2)
    (folder / "images60fps").mkdir(parents=True)
    texture = (rng.random((240, 320)) * 255).astype(np.uint8)
    for i in range(first, first + n_frames):
        cv2.imwrite(str(folder / "images60fps" / f"test{i}.png"), texture)
    exposure = 0.2 + PERIOD_S * np.arange(n_frames)
    tagged = exposure + LATENCY_S + rng.uniform(0.0, 0.04, n_frames)
    tagged[1:] = np.maximum(tagged[1:], tagged[:-1] + 0.003)  # each tagged on its own sample
    time = np.arange(0.0, tagged[-1] + 0.1, 0.002)
    frame = np.zeros(len(time), dtype=np.uint16)
    for k, t in enumerate(tagged):
        frame[time >= t] = first + k
    frame[0] = 0  # the source's first row is all zeros: left out
    z = 0.4 + 0.5 * time
    record = {
        "time": time,
        "frame": frame,
        "X": np.full_like(time, 0.3),
        "Y": np.full_like(time, -0.2),
        "Z": z,
        "qx": np.zeros_like(time),
        "qy": np.zeros_like(time),
        "qz": np.zeros_like(time),
    }
    scipy.io.savemat(str(folder / "mocap_data.mat"), {"mocap": record})
    return exposure


def test_exposure_times_remove_late_deliveries() -> None:
    """Stamps up to 40 ms late around a 16.7 ms camera: the local line's times are within a
    few ms of a steady clock (the raw stamps are off by up to 40 ms)."""
    rng = np.random.default_rng(5)
    frames = np.arange(300)
    truth = 1.0 + PERIOD_S * frames
    late = rng.uniform(0.0, 0.04, 300) * (rng.random(300) < 0.3)
    out = exposure_times(frames, truth + late)
    offset = np.median(out - truth)  # a constant latency is not the jitter's
    assert np.max(np.abs(out - truth - offset)) < 0.004
    assert np.max(np.abs(late - offset)) > 0.03


def test_a_beam_meets_the_floor_at_its_slant_distance() -> None:
    """A sensor 0.05 m off the body origin tilted 10 deg, the body 1.2 m above the floor and
    rolled 5 deg: the distance is the analytic slant range."""
    floor_z = 0.0
    T_world_body = se3.make(so3.rot_x(np.radians(5.0)), [0.0, 0.0, -1.2])
    T_body_rf = se3.make(so3.rot_y(np.radians(10.0)), [0.05, 0.0, 0.0])
    got = beam_range_m(T_world_body, T_body_rf, floor_z)
    T = T_world_body @ T_body_rf
    assert got is not None
    assert T[2, 3] + got * T[2, 2] == pytest.approx(floor_z)
    assert beam_range_m(se3.make(so3.rot_x(np.pi), [0, 0, -1.0]), np.eye(4), floor_z) is None


def test_the_import_opens_as_a_dataset_with_its_truth(tmp_path: Path) -> None:
    exposure = write_source(tmp_path / "src")
    summary = import_rislab(
        tmp_path / "src",
        tmp_path / "out",
        load_config(),
        focal_px=235.5,
        dist=(-0.2, 0.0, 0.0, 0.0, 0.0),
    )
    assert summary.frames == 40 and sum(summary.dropped.values()) == 0
    ds = open_dataset(tmp_path / "out")
    assert ds.camera.width == 320 and ds.camera.fx == 235.5
    assert np.allclose(ds.T_body_cam[:3, :3], so3.rot_z(np.radians(90.0)))
    times_s, poses = read_tum(tmp_path / "out" / "groundtruth.txt")
    assert len(times_s) == 40
    # exposure times: the steady 60 Hz clock, not the late stamps
    assert np.allclose(np.diff(times_s), PERIOD_S, atol=0.004)
    assert np.allclose(times_s - times_s[0], exposure - exposure[0], atol=0.004)
    # the truth at the exposure (the tag less the latency); our world is z down: the height
    # above the floor is -z - floor, climbing at 0.5 m/s
    height = -poses[:, 2, 3] - FLOOR_Z_M
    assert np.allclose(height, 0.4 + 0.5 * exposure - FLOOR_Z_M, atol=0.01)
    # level body, camera down: the body's z axis points down in our world
    assert np.allclose(poses[:, :3, 2], [0.0, 0.0, 1.0], atol=1e-6)
    ranges = np.genfromtxt(tmp_path / "out" / "ranges.csv", delimiter=",", names=True)
    assert summary.readings == len(ranges) > 0
    assert set(np.unique(ranges["sensor_id"]).astype(int)) == {r.sensor_id for r in RISLAB_BEAMS}
    # the attitude an autopilot would send: the true (level) one within its 0.1 deg noise, at
    # 100 Hz over the frames, with the body rates of a body that does not turn
    att = np.genfromtxt(tmp_path / "out" / "attitude.csv", delimiter=",", names=True)
    assert len(att) >= 0.6 * 100 and np.all(np.diff(att["time_us"]) == 10_000)
    quats = np.column_stack([att["qw"], att["qx"], att["qy"], att["qz"]])
    down = np.array([so3.quat_to_matrix(q)[:, 2] for q in quats])  # body z in the world
    tilt_deg = np.degrees(np.arccos(np.clip(down[:, 2], -1.0, 1.0)))
    assert np.all(tilt_deg < 0.6) and np.allclose(att["wz_rad_s"], 0.0, atol=1e-6)
    # a level body: each beam's true distance is its mount's height above the floor / cos(tilt)
    assert np.all(np.abs(ranges["distance_m"] - ranges["true_distance_m"]) < 0.06)
    # the body 0.49-0.81 m above the floor over the frames, the beams a few degrees off
    assert np.all((ranges["true_distance_m"] > 0.48) & (ranges["true_distance_m"] < 0.83))


def test_a_broken_capture_record_is_refused_by_name(tmp_path: Path) -> None:
    bad = tmp_path / "mocap_data.mat"
    scipy.io.savemat(str(bad), {"other": np.zeros(3)})
    with pytest.raises(DatasetError, match=r"mocap_data\.mat"):
        read_capture(bad)


def test_the_attitudes_world_is_the_positions_turned_about_the_vertical() -> None:
    """The record's attitudes are in a world turned 90 deg about z from its positions' (the
    module's "Frames", measured from the floor's flow): a body tilted about the attitudes'
    x axis comes out tilted about our world's y axis, and a level body's camera looks down
    with its image x along the body's y."""
    tilt = np.radians(10.0)
    R_body_world = so3.rot_x(tilt).T  # the record's quaternion turns the world into the body
    capture = Capture(
        np.array([0.0, 0.002]),
        np.array([1, 1]),
        np.zeros((2, 3)),
        np.stack([R_body_world, np.eye(3)]),
    )
    poses = body_poses(capture, np.array([0.0, 0.002]))
    cam = poses @ se3.make(so3.rot_z(np.radians(90.0)), [0, 0, 0])  # the mount, rpy 0 0 90
    # level: the camera's optical axis down (+z of our world), its image x along body y
    assert np.allclose(cam[1, :3, 2], [0.0, 0.0, 1.0], atol=1e-9)
    assert np.allclose(poses[1, :3, :3] @ [0.0, 1.0, 0.0], cam[1, :3, 0], atol=1e-9)
    # tilted about the attitudes' x axis: the optical axis leans along our world's x
    axis = cam[0, :3, 2]
    assert abs(axis[1]) < 1e-9 and abs(abs(axis[0]) - np.sin(tilt)) < 1e-9
