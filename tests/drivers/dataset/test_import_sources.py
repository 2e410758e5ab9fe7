"""The real-sequence readers on tiny synthetic folders written here (TUM RGB-D and its
keyframe variant, ETH3D, 7-Scenes, KITTI): association across stamps, ground truth
interpolated by slerp, frames outside the ground truth dropped and counted, malformed lines
named, and the imported folder read back by ``open_dataset``."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.cli import main
from companion.config import MountConfig, RangefinderConfig
from companion.drivers.dataset import open_dataset
from companion.drivers.dataset.import_depth import beam_in_camera
from companion.drivers.dataset.import_sources import (
    associate,
    interpolate_pose,
    read_source,
    read_stamped_list,
)
from companion.drivers.dataset.import_write import import_sequence, select_frames
from companion.drivers.safe_files import SafeFolder
from companion.errors import DatasetError
from companion.geometry import se3, so3

W, H = 640, 480
PLANE_M = 1.5  # the synthetic scene: a wall facing the camera at z = 1.5 m
EXACT = (  # noise-free sensors: the reading is the geometry
    RangefinderConfig(sensor_id=0, mount=MountConfig(), sigma_a_m=0.0),
    RangefinderConfig(
        sensor_id=5,
        mount=MountConfig(xyz_m=(0.03, 0.0, 0.0), rpy_deg=(0.0, 8.0, 0.0)),
        sigma_a_m=0.0,
    ),
)


def _image(path: Path, k: int, grey: bool = False) -> None:
    rng = np.random.default_rng(k)
    img = cv2.resize(rng.integers(0, 255, (H // 16, W // 16, 3), dtype=np.uint8), (W, H))
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if grey else img)


def _depth(path: Path, per_m: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.full((H, W), round(PLANE_M * per_m), dtype=np.uint16))


def _pose_line(t: float, T: np.ndarray, sep: str = " ") -> str:
    q = so3.quat_wxyz_to_xyzw(so3.matrix_to_quat(T[:3, :3]))
    return sep.join(f"{v:.6f}" for v in (t, *T[:3, 3], *q))


def _path_pose(t: float) -> np.ndarray:
    """The synthetic camera: 0.4 m/s along x, turning 20 deg/s about its optical axis."""
    return se3.make(so3.rot_z(np.radians(20.0 * t)), [0.4 * t, 0.0, 0.0])


def _tum_folder(root: Path, rgb_s: list[float], depth_s: list[float], gt_s: np.ndarray) -> Path:
    lines = {"rgb.txt": ["# color images", "# timestamp filename"], "depth.txt": ["# depth"]}
    for k, t in enumerate(rgb_s):
        _image(root / f"rgb/{t:.6f}.png", k)
        lines["rgb.txt"].append(f"{t:.6f} rgb/{t:.6f}.png")
    for t in depth_s:
        _depth(root / f"depth/{t:.6f}.png", 5000.0)
        lines["depth.txt"].append(f"{t:.6f} depth/{t:.6f}.png")
    lines["groundtruth.txt"] = ["# timestamp tx ty tz qx qy qz qw"]
    lines["groundtruth.txt"] += [_pose_line(t, _path_pose(t)) for t in gt_s]
    for name, text in lines.items():
        (root / name).write_text("\n".join(text) + "\n")
    return root


def test_association_takes_the_nearest_depth_within_20_ms() -> None:
    rgb = np.array([0.0, 0.033, 0.066, 0.1])
    depth = np.array([0.005, 0.045, 0.2])
    assert associate(rgb, depth) == [0, 1, None, None]
    assert associate(rgb, np.zeros(0)) == [None] * 4


def test_ground_truth_is_interpolated_by_slerp_and_not_across_gaps() -> None:
    times = np.array([0.0, 0.05, 1.0])
    poses = np.stack([np.eye(4), se3.make(so3.rot_z(np.radians(90.0)), [1.0, 0.0, 0.0]), np.eye(4)])
    T = interpolate_pose(times, poses, 0.0125)
    assert T is not None
    assert so3.angle_between(T[:3, :3], so3.rot_z(np.radians(22.5))) < 1e-9  # a quarter of 90
    assert np.allclose(T[:3, 3], [0.25, 0.0, 0.0])
    assert interpolate_pose(times, poses, 0.5) is None  # a 0.95 s gap
    assert interpolate_pose(times, poses, -0.01) is None
    assert interpolate_pose(times, poses, 1.01) is None


def test_a_malformed_list_line_names_the_file_and_the_line(tmp_path: Path) -> None:
    (tmp_path / "rgb.txt").write_text("# header\n1.0 rgb/a.png\n1.1 rgb/b.png extra\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt line 3: expected 2 values, got 3"):
        read_stamped_list(SafeFolder(tmp_path), "rgb.txt")
    (tmp_path / "rgb.txt").write_text("1.0 rgb/a.png\n0.9 rgb/b.png\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt line 2: stamp 0\.9 not after 1\.0"):
        read_stamped_list(SafeFolder(tmp_path), "rgb.txt")
    (tmp_path / "rgb.txt").write_text("1.0 ../outside.png\n")
    with pytest.raises(DatasetError, match=r"rgb\.txt line 1, file name.*outside"):
        read_stamped_list(SafeFolder(tmp_path), "rgb.txt")


def test_tum_rgbd_import_round_trip(tmp_path: Path) -> None:
    rgb_s = [10.0 + k / 30.0 for k in range(7)]
    depth_s = [t + 0.004 for t in rgb_s[:5]] + [rgb_s[6] + 0.030]  # frame 5: none, 6: too far
    gt_s = np.arange(10.02, 10.19, 0.01)  # covers frames 1..5 only
    src = _tum_folder(tmp_path / "src", rgb_s, depth_s, gt_s)
    seq = read_source("tum-rgbd", SafeFolder(src), "fr3")
    assert seq.format == "tum-rgbd" and len(seq.frames) == 5
    assert seq.dropped == {"outside_ground_truth": 2, "without_depth": 1}
    out = tmp_path / "out"
    summary = import_sequence(seq, SafeFolder(src), out, EXACT, seed=2)
    assert summary.readings == 2 * 4 and summary.frames == 5
    ds = open_dataset(out)
    assert len(ds) == 5 and np.allclose(ds.T_body_cam, np.eye(4))
    assert ds.camera.fx == 535.4 and not ds.camera.has_distortion
    # frames stamped from the earliest kept stamp; ground truth = the camera's path there
    assert np.allclose(ds.frame_times_us * 1e-6 + rgb_s[1], rgb_s[1:6], atol=1e-6)
    for t_us, T in zip(ds.gt_times_us, ds.gt_T_world_body, strict=True):
        expected = _path_pose(t_us * 1e-6 + rgb_s[1])
        assert np.allclose(T, expected, atol=1e-5)
    # each reading at its depth image's stamp, the analytic distance to the wall
    by_sensor = {rf.sensor_id: beam_in_camera(rf) for rf in EXACT}
    for r in ds.ranges:
        o, d = by_sensor[r.sensor_id]
        assert r.distance_m == pytest.approx((PLANE_M - o[2]) / d[2], abs=1e-3)
    stamps = sorted({r.time_us for r in ds.ranges})
    want = [(t + 0.004 - rgb_s[1]) * 1e6 for t in rgb_s[1:5]]
    assert np.allclose(stamps, want, atol=1.5)  # the lists' stamps have 6 decimals
    meta = (out / "meta.toml").read_text()
    assert 'rangefinders_source = "synthesised from depth images"' in meta
    assert (out / "images/000000.png").read_bytes() == (
        src / f"rgb/{rgb_s[1]:.6f}.png"
    ).read_bytes()
    assert select_frames(seq, "1:3").frames == seq.frames[1:3]
    with pytest.raises(DatasetError, match="--frames"):
        select_frames(seq, "3")


def test_the_keyframe_variant_takes_ground_truth_rows_in_order(tmp_path: Path) -> None:
    src = tmp_path / "kf"
    gt_s = [100.0, 100.7, 101.3]
    lines = {"rgb.txt": ["# color images"], "depth.txt": ["# depth"], "truth_cam_poses.txt": []}
    for k, t in enumerate(gt_s):
        _image(src / f"raw_imgs/{k:04d}_rgb_raw.jpg", k)
        _depth(src / f"depth_imgs/{k:04d}_depth_raw.png", 5000.0)
        lines["rgb.txt"].append(f"{k} raw_imgs/{k:04d}_rgb_raw.jpg")
        lines["depth.txt"].append(f"{k} depth_imgs/{k:04d}_depth_raw.png")
        lines["truth_cam_poses.txt"].append(_pose_line(t, _path_pose(t), "\t") + "\t")
    for name, text in lines.items():
        (src / name).write_text("\n".join(text) + "\n")
    seq = read_source("tum-rgbd", SafeFolder(src), "fr3")
    assert seq.format == "tum-rgbd-keyframes"
    assert [f.time_s for f in seq.frames] == gt_s
    import_sequence(seq, SafeFolder(src), tmp_path / "out", EXACT)
    ds = open_dataset(tmp_path / "out")
    assert list(ds.frame_times_us) == [0, 700000, 1300000] and len(ds.ranges) == 6
    assert np.allclose(ds.gt_T_world_body[2], _path_pose(101.3), atol=1e-5)


def test_eth3d_reads_its_calibration_file(tmp_path: Path) -> None:
    rgb_s = [5.0 + k / 30.0 for k in range(3)]
    src = _tum_folder(tmp_path / "eth", rgb_s, rgb_s, np.arange(4.9, 5.2, 0.01))
    (src / "calibration.txt").write_text("726.28 726.28 354.65 186.46\n")
    seq = read_source("eth3d", SafeFolder(src))
    assert (seq.camera.fx, seq.camera.cy) == (726.28, 186.46) and len(seq.frames) == 3
    (src / "calibration.txt").write_text("726.28 726.28 354.65\n")
    with pytest.raises(DatasetError, match=r"calibration\.txt line 1: expected 4 values"):
        read_source("eth3d", SafeFolder(src))


def test_7scenes_reads_camera_to_world_poses_and_millimetre_depth(tmp_path: Path) -> None:
    src = tmp_path / "seq-01"
    src.mkdir()
    for k in range(3):
        stem = src / f"frame-{k:06d}"
        _image(Path(f"{stem}.color.png"), k)
        _depth(Path(f"{stem}.depth.png"), 1000.0)
        T = _path_pose(k / 30.0)
        Path(f"{stem}.pose.txt").write_text(
            "\n".join(" ".join(f"{v:.8e}" for v in row) for row in T) + "\n"
        )
    seq = read_source("7scenes", SafeFolder(src))
    assert seq.camera.fx == 585.0 and seq.depth_per_m == 1000.0
    import_sequence(seq, SafeFolder(src), tmp_path / "out", EXACT)
    ds = open_dataset(tmp_path / "out")
    assert np.allclose(ds.gt_T_world_body[2], _path_pose(2 / 30.0), atol=1e-6)
    assert all(abs(r.distance_m - PLANE_M) < 0.02 for r in ds.ranges if r.sensor_id == 0)


def test_kitti_reads_p0_times_and_3x4_poses_without_depth(tmp_path: Path) -> None:
    root = tmp_path / "kitti"
    seq_dir = root / "sequences/04"
    for k in range(3):
        _image(seq_dir / f"image_0/{k:06d}.png", k, grey=True)
    p0 = "718.856 0 607.1928 0 0 718.856 185.2157 0 0 0 1 0"
    (seq_dir / "calib.txt").write_text(f"P0: {p0}\nP1: {p0}\n")
    (seq_dir / "times.txt").write_text("0.000000e+00\n1.036223e-01\n2.072446e-01\n")
    poses = [_path_pose(0.1 * k) for k in range(3)]
    (root / "poses").mkdir()
    (root / "poses/04.txt").write_text(
        "\n".join(" ".join(f"{v:.9e}" for v in T[:3].ravel()) for T in poses) + "\n"
    )
    seq = read_source("kitti", SafeFolder(root))
    assert (seq.camera.fx, seq.camera.cx, seq.depth_per_m) == (718.856, 607.1928, 0.0)
    out = tmp_path / "out"
    summary = import_sequence(seq, SafeFolder(root), out, EXACT)
    assert summary.readings == 0
    ds = open_dataset(out)
    assert ds.rangefinders == [] and len(ds) == 3
    assert np.allclose(ds.gt_T_world_body[1], poses[1], atol=1e-6)
    assert 'rangefinders_source = "none"' in (out / "meta.toml").read_text()


def test_the_cli_imports_and_refuses_bad_input_with_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rgb_s = [1.0 + k / 30.0 for k in range(3)]
    src = _tum_folder(tmp_path / "src", rgb_s, rgb_s, np.arange(0.9, 1.2, 0.01))
    cfg = tmp_path / "beams.toml"
    cfg.write_text("[[rangefinders]]\nsensor_id = 7\nsigma_a_m = 0.0\n")
    argv = ["dataset", "import", "tum-rgbd", str(src), "--camera", "fr3", "--config", str(cfg)]
    assert main([*argv, "--out", str(tmp_path / "a"), "--image-format", "jpg"]) == 0
    ds = open_dataset(tmp_path / "a")
    assert [r.sensor_id for r in ds.rangefinders] == [7] and len(ds.ranges) == 3
    assert ds.frame_paths[0].suffix == ".jpg"
    assert main([*argv, "--out", str(tmp_path / "a")]) == 2  # not empty
    cfg.write_text("[[rangefinders]]\nsensor_id = 7\nmax_m = -1.0\n")
    assert main([*argv, "--out", str(tmp_path / "b")]) == 2
    assert "max_m" in capsys.readouterr().err
    with (src / "depth.txt").open("a") as fh:
        fh.write("2.0\n")
    assert main([*argv[:-2], "--out", str(tmp_path / "c")]) == 2
    assert "depth.txt line" in capsys.readouterr().err
