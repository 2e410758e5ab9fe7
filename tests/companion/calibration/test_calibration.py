"""companion calibrate: intrinsics recovered from exactly rendered board views of a known
camera, and the laser-dot check of the rangefinder mounts on SITL frames."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import tomli_w

from companion.calibration.files import read_laser_frames, write_laser_frames
from companion.calibration_maths.board import BoardDetector, BoardSpec, BoardView, board_image
from companion.calibration_maths.intrinsics import IntrinsicsOptions, calibrate_intrinsics
from companion.calibration_maths.lasers import (
    LaserCheckReport,
    LaserFrame,
    Verdict,
    check_lasers,
    observed_beam_body,
    predict_dot_px,
    rpy_for_beam_deg,
)
from companion.cli import main
from companion.config import Config, MountConfig, load_config, to_dict
from companion.errors import CalibrationError, NotEnoughViewsError
from companion.geometry import se3
from companion.geometry.camera import CameraModel
from companion.sitl.world.calibration import (
    BoardRenderer,
    laser_check_frames,
    random_board_poses,
    tilt_sensor,
)

# the camera to recover: not the config default, fx != fy, off-centre, stronger barrel
TRUTH = CameraModel(640, 480, 452.0, 455.0, 326.4, 236.9, -0.21, 0.08, 0.0008, -0.0005, 0.0)
CHESS = BoardSpec.parse("chessboard:9x6:0.025")
CHARUCO = BoardSpec.parse("charuco:10x7:0.03:0.022:DICT_5X5_100")


@pytest.fixture(scope="module")
def renderer() -> BoardRenderer:
    return BoardRenderer(TRUTH)


@pytest.fixture(scope="module")
def chess(renderer: BoardRenderer) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """15 seeded views: (grey images, T_cam_board)."""
    poses = random_board_poses(TRUTH, CHESS, 15, seed=3)
    return renderer.render(CHESS, poses, seed=3), poses


@pytest.fixture(scope="module")
def chess_views(chess: tuple[list[np.ndarray], list[np.ndarray]]) -> list[BoardView]:
    det = BoardDetector(CHESS)
    views = [det.detect(img, f"board_{k:03d}.png") for k, img in enumerate(chess[0])]
    assert all(v is not None for v in views)
    return [v for v in views if v is not None]


def ray_error_px(cam: CameraModel, uv: np.ndarray) -> float:
    """Largest distance [px] between pixels ``uv`` (N, 2) of TRUTH and where ``cam`` images the
    same rays: distortion and intrinsics errors together."""
    uv_cam, _ = cam.project(TRUTH.pixels_to_rays(uv))
    return float(np.max(np.linalg.norm(uv_cam - uv, axis=1)))


# ------------------------------------------------------------------------------ boards
def test_board_specs_parse_and_bad_ones_are_refused() -> None:
    for text in ("chessboard:9x6:0.025", "charuco:11x8:0.03:0.022:DICT_4X4_50"):
        assert BoardSpec.parse(text).text() == text
    assert BoardSpec.parse("charuco:5x4:0.04:0.03").dictionary == "DICT_5X5_100"
    assert CHESS.squares == (10, 7) and CHARUCO.squares == (10, 7)
    assert CHESS.corner_points_m().shape == (54, 3) and CHARUCO.corner_points_m().shape == (54, 3)
    for bad in (
        "chessboard:9x6",  # no square size
        "chessboard:7x7:0.03",  # square: ambiguous under a 90 degree turn
        "chessboard:9x6:-0.03",
        "charuco:10x7:0.03:0.04",  # marker larger than the square
        "charuco:10x7:0.03:0.02:DICT_NOPE",
        "grid:9x6:0.03",
    ):
        with pytest.raises(CalibrationError):
            BoardSpec.parse(bad)


def test_printable_board_has_its_corners_where_it_says() -> None:
    img = board_image(CHESS, 1000.0 / CHESS.square_m * 0.04)  # 40 px per square
    ok, corners = cv2.findChessboardCornersSB(img.image, (CHESS.cols, CHESS.rows))
    assert ok
    expected = img.origin_px + img.px_per_m * CHESS.corner_points_m()[:, :2]
    found = corners.reshape(-1, 2)
    err = min(
        np.abs(found - expected).max(), np.abs(found[::-1] - expected).max()
    )  # either end first
    assert err < 0.1


def test_rendered_corners_are_where_the_true_camera_projects_them(
    chess: tuple[list[np.ndarray], list[np.ndarray]], chess_views: list[BoardView]
) -> None:
    """The renderer and the detector agree with the camera model to a small fraction of a pixel
    (the ground truth of the calibration tests below)."""
    residuals = []
    for T, view in zip(chess[1], chess_views, strict=True):
        truth, _ = TRUTH.project(se3.transform(T, CHESS.corner_points_m()))
        a, b = view.image_points_px - truth, view.image_points_px[::-1] - truth  # either end
        res = a if np.abs(a).max() < np.abs(b).max() else b
        assert np.linalg.norm(res.mean(axis=0)) < 0.1  # no bias (a half-pixel slip shows here)
        assert np.linalg.norm(res, axis=1).max() < 0.6
        residuals.append(res)
    r = np.concatenate(residuals)
    assert np.sqrt(np.mean(np.sum(r**2, axis=1))) < 0.2


# ------------------------------------------------------------------------------ intrinsics
def test_chessboard_calibration_recovers_the_true_camera(chess_views: list[BoardView]) -> None:
    r = calibrate_intrinsics(chess_views, (640, 480))
    c = r.camera
    assert abs(c.fx - TRUTH.fx) < 0.005 * TRUTH.fx and abs(c.fx - TRUTH.fx) < 2.0
    assert abs(c.fy - TRUTH.fy) < 0.005 * TRUTH.fy and abs(c.fy - TRUTH.fy) < 2.0
    assert abs(c.cx - TRUTH.cx) < 1.5 and abs(c.cy - TRUTH.cy) < 1.5
    assert abs(c.k1 - TRUTH.k1) < 0.02
    assert r.rms_px < 0.3
    assert ray_error_px(c, np.concatenate([v.image_points_px for v in chess_views])) < 1.5
    # the estimated sigmas are honest: the errors are within 4 of them
    est = np.array([c.fx, c.fy, c.cx, c.cy])
    true = np.array([TRUTH.fx, TRUTH.fy, TRUTH.cx, TRUTH.cy])
    assert np.all(np.abs(est - true) < 4 * r.std[:4])
    assert len(r.view_names) == 15 and r.n_corners == 15 * 54 and not r.dropped
    assert r.coverage > 0.6 and np.all(r.view_rms_px < 0.3)


def test_charuco_calibration_uses_partly_hidden_boards(renderer: BoardRenderer) -> None:
    poses = random_board_poses(TRUTH, CHARUCO, 14, seed=5, distance_m=(0.3, 0.55))
    images = renderer.render(CHARUCO, poses, seed=5)
    for img in images[:5]:  # hide the left third of the image: part of the board is lost
        img[:, : TRUTH.width // 3] = 110
    det = BoardDetector(CHARUCO)
    views = [v for k, img in enumerate(images) if (v := det.detect(img, str(k))) is not None]
    assert len(views) >= 12
    partial = [v for v in views if len(v.corner_ids) < 54]
    assert partial, "no partial view: the occlusion did not bite"
    for v in views:  # ids index the board's corners: their 3D points are the board's
        assert np.array_equal(v.object_points_m, CHARUCO.corner_points_m()[v.corner_ids])
    r = calibrate_intrinsics(views, (640, 480))
    c = r.camera
    assert abs(c.fx - TRUTH.fx) < 2.0 and abs(c.fy - TRUTH.fy) < 2.0
    assert abs(c.cx - TRUTH.cx) < 1.5 and abs(c.cy - TRUTH.cy) < 1.5
    assert abs(c.k1 - TRUTH.k1) < 0.02
    assert r.rms_px < 0.3
    assert ray_error_px(c, np.concatenate([v.image_points_px for v in views])) < 1.5


def test_too_few_views_are_refused(chess_views: list[BoardView]) -> None:
    with pytest.raises(NotEnoughViewsError, match="only 5 usable"):
        calibrate_intrinsics(chess_views[:5], (640, 480))
    r = calibrate_intrinsics(chess_views[:6], (640, 480), IntrinsicsOptions(min_views=6))
    assert len(r.view_names) == 6
    assert r.warnings  # six views do not cover the image: the user is told


def test_a_bad_view_is_dropped_and_the_camera_stays_right(chess_views: list[BoardView]) -> None:
    views = list(chess_views)
    bad = views[7]
    shifted = bad.image_points_px.copy()
    shifted[::4] += np.array([2.5, -2.0])  # a quarter of the corners mislocated
    views[7] = dataclasses.replace(bad, image_points_px=shifted)
    r = calibrate_intrinsics(views, (640, 480))
    assert [n for n, _ in r.dropped] == [bad.name]
    assert bad.name not in r.view_names and r.rms_px < 0.3
    assert abs(r.camera.fx - TRUTH.fx) < 2.0


def test_camera_snippet_pastes_into_a_config(chess_views: list[BoardView], tmp_path: Path) -> None:
    r = calibrate_intrinsics(chess_views, (640, 480))
    path = tmp_path / "board.toml"
    path.write_text(r.camera_toml() + "\n[camera.mount]\nrpy_deg = [0.0, 0.0, 90.0]\n")
    cam = load_config(path).camera
    assert (cam.width, cam.height) == (640, 480)
    assert abs(cam.fx - r.camera.fx) < 1e-3 and abs(cam.cy - r.camera.cy) < 1e-3
    assert np.allclose(cam.dist, r.camera.dist_coeffs, rtol=1e-5, atol=1e-9)
    rep = r.report()
    assert json.loads(json.dumps(rep))["views_used"] == 15


def test_intrinsics_command(
    chess: tuple[list[np.ndarray], list[np.ndarray]],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    def folder(name: str, images: list[np.ndarray]) -> str:
        (tmp_path / name).mkdir()
        for k, img in enumerate(images):
            cv2.imwrite(str(tmp_path / name / f"board_{k:03d}.png"), img)
        return str(tmp_path / name)

    out = tmp_path / "out"
    argv = ["calibrate", "intrinsics", "--board", CHESS.text(), "--out", str(out), "--images"]
    assert main([*argv, folder("all", chess[0])]) == 0
    cam = load_config(out / "camera.toml").camera
    assert abs(cam.fx - TRUTH.fx) < 2.0 and abs(cam.cx - TRUTH.cx) < 1.5
    rep = json.loads((out / "intrinsics.json").read_text())
    assert rep["views_used"] == 15 and rep["images_without_board"] == []
    assert (out / "coverage.png").is_file()
    assert "fx = " in capsys.readouterr().out
    # bad input: exit 2 and a message that says what is wrong
    assert main([*argv, folder("few", chess[0][:4])]) == 2
    assert "only 4 usable view(s)" in capsys.readouterr().err
    noise = np.random.default_rng(1).integers(0, 255, (3, 480, 640), dtype=np.uint8)
    assert main([*argv, folder("none", list(noise))]) == 2
    assert "not found in any of the 3" in capsys.readouterr().err
    assert main([*argv, str(tmp_path / "nope")]) == 2
    assert "no such folder" in capsys.readouterr().err


# ------------------------------------------------------------------------------ lasers
def test_laser_geometry_identities(default_config: Config) -> None:
    cam = default_config.camera
    T_body_cam = cam.T_body_cam()
    for rf in default_config.rangefinders:
        spec = rf.spec()
        for d in (0.8, 3.0, 9.0):
            uv = predict_dot_px(cam.model(), se3.inverse(T_body_cam), spec.T_body_rf, d)
            u = observed_beam_body(cam.model(), T_body_cam, spec.T_body_rf[:3, 3], uv, d)
            assert u is not None
            assert np.degrees(np.arccos(min(1.0, float(u @ spec.T_body_rf[:3, 2])))) < 1e-5
        rpy = rpy_for_beam_deg(spec.T_body_rf[:3, 2], rf.mount.rpy_deg[2])
        assert np.allclose(rpy, rf.mount.rpy_deg, atol=1e-9)
    # a range shorter than the camera-sensor distance has no answer
    spec = default_config.rangefinders[0].spec()
    assert observed_beam_body(cam.model(), T_body_cam, spec.T_body_rf[:3, 3], uv, 0.05) is None


@pytest.fixture(scope="module")
def laser_frames() -> list[LaserFrame]:
    """12 frames over a flat floor, 1.2-4 m, the default sensors mounted as configured."""
    return laser_check_frames(load_config(), 12, seed=5)


def _check(cfg: Config, frames: list[LaserFrame]) -> LaserCheckReport:
    specs = [rf.spec() for rf in cfg.rangefinders]
    return check_lasers(cfg.camera.model(), cfg.camera.T_body_cam(), specs, frames)


def test_correct_mounts_pass(laser_frames: list[LaserFrame], default_config: Config) -> None:
    rep = _check(default_config, laser_frames)
    assert rep.all_ok and rep.stray_dots == 0 and not rep.notes
    for s in rep.sensors:
        assert s.n_found == s.n_predicted >= 10
        assert s.offset_norm_px < 0.5 and s.beam_error_deg < 0.1
        assert s.spread_px < 1.0


def test_a_sensor_rotated_by_2_degrees_is_flagged(
    laser_frames: list[LaserFrame], default_config: Config
) -> None:
    # the config says sensor 2 is pitched 2 degrees more than it is on the vehicle
    wrong = dataclasses.replace(
        default_config, rangefinders=tilt_sensor(default_config.rangefinders, 2, 2.0)
    )
    rep = _check(wrong, laser_frames)
    verdicts = {s.sensor_id: s.verdict for s in rep.sensors}
    assert verdicts == {0: Verdict.OK, 1: Verdict.OK, 2: Verdict.CHECK_MOUNT, 3: Verdict.OK}
    s2 = rep.sensors[2]
    assert s2.offset_norm_px > 8.0 and abs(s2.beam_error_deg - 2.0) < 0.15
    # the suggestion points back at the real mount (the default config's)
    assert np.allclose(
        s2.suggested_rpy_deg, default_config.rangefinders[2].mount.rpy_deg, atol=0.15
    )
    assert not rep.all_ok


def test_a_rotated_camera_shifts_every_dot_alike(
    laser_frames: list[LaserFrame], default_config: Config
) -> None:
    cam = default_config.camera
    mount = MountConfig(cam.mount.xyz_m, (1.5, 0.0, 90.0))  # camera rolled 1.5 degrees
    wrong = dataclasses.replace(default_config, camera=dataclasses.replace(cam, mount=mount))
    rep = _check(wrong, laser_frames)
    assert all(s.verdict is Verdict.CHECK_MOUNT for s in rep.sensors)
    assert any("shifted alike" in n for n in rep.notes)


def test_laser_check_input_errors(laser_frames: list[LaserFrame], default_config: Config) -> None:
    stranger = [LaserFrame("x.png", laser_frames[0].image_bgr, {9: 2.0})]
    with pytest.raises(CalibrationError, match="sensor_id"):
        _check(default_config, stranger)
    out_of_range = [LaserFrame("x.png", laser_frames[0].image_bgr, {0: 500.0})]
    with pytest.raises(CalibrationError, match="none of the 1"):
        _check(default_config, out_of_range)
    # no dot where the model puts it (a grey image): NOT FOUND, not OK
    grey = np.full_like(laser_frames[0].image_bgr, 120)
    blank = [LaserFrame(f"{k}.png", grey, f.ranges_m) for k, f in enumerate(laser_frames[:4])]
    rep = _check(default_config, blank)
    assert {s.verdict for s in rep.sensors} == {Verdict.NOT_FOUND}


def _config_file(path: Path, cfg: Config) -> Path:
    path.write_text(tomli_w.dumps({"rangefinders": [to_dict(rf) for rf in cfg.rangefinders]}))
    return path


def test_lasers_command_on_a_simulated_folder(
    default_config: Config, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "frames"
    argv = ["calibrate", "sim-lasers", "--out", str(folder), "--frames", "5", "--seed", "7"]
    assert main([*argv, "--tilt-sensor", "1:-2"]) == 0
    frames = read_laser_frames(folder)
    assert len(frames) == 5 and all(len(f.ranges_m) == 4 for f in frames)
    cfg_path = _config_file(tmp_path / "vehicle.toml", default_config)
    out = tmp_path / "report"
    check = ["calibrate", "lasers", "--config", str(cfg_path), "--images", str(folder)]
    assert main([*check, "--out", str(out)]) == 1  # sensor 1 is off: flagged, exit 1
    rep = json.loads((out / "lasers.json").read_text())
    assert [s["verdict"] for s in rep["sensors"]] == ["OK", "CHECK MOUNT", "OK", "OK"]
    assert "sensor 1: the dots say" in capsys.readouterr().out
    assert len(list((out / "overlays").glob("*.png"))) == 5
    # the config that matches the vehicle passes
    fixed = tilt_sensor(default_config.rangefinders, 1, -2.0)
    fixed_path = _config_file(
        tmp_path / "fixed.toml", dataclasses.replace(default_config, rangefinders=fixed)
    )
    check[3] = str(fixed_path)
    assert main([*check, "--out", str(out)]) == 0
    # bad ranges file, missing folder, wrong image size: exit 2
    (folder / "ranges.csv").write_text("img,id,d\n")
    assert main([*check, "--out", str(out)]) == 2
    assert "first row must be image,sensor_id,range_m" in capsys.readouterr().err
    check[5] = str(tmp_path / "nope")
    assert main(check) == 2
    small = tmp_path / "small"
    write_laser_frames(small, [LaserFrame("a.png", frames[0].image_bgr[:240, :320], {0: 2.0})])
    check[5] = str(small)
    assert main(check) == 2
    assert "320x240" in capsys.readouterr().err


def test_the_ranges_file_round_trips(laser_frames: list[LaserFrame], tmp_path: Path) -> None:
    path = write_laser_frames(tmp_path, laser_frames[:3])
    text = path.read_text()
    assert text.splitlines()[0] == "image,sensor_id,range_m"
    path.write_text("# taken 2024-05-01, vehicle on stands\n" + text + "\n")
    back = read_laser_frames(tmp_path)
    assert [f.name for f in back] == [f.name for f in laser_frames[:3]]
    for a, b in zip(back, laser_frames[:3], strict=True):
        assert np.array_equal(a.image_bgr, b.image_bgr)
        assert a.ranges_m.keys() == b.ranges_m.keys()
        assert all(math.isclose(a.ranges_m[k], b.ranges_m[k], abs_tol=6e-5) for k in a.ranges_m)


def test_ranges_file_errors_name_the_file_line(tmp_path: Path) -> None:
    from companion.calibration.files import read_ranges

    path = tmp_path / "ranges.csv"
    path.write_text(
        "# readings of the laser check\nimage,sensor_id,range_m\n# first pose\n"
        "a.png,0,1.50\n\na.png,1,1.52\n# second pose\nb.png,0,-1\n"
    )
    with pytest.raises(CalibrationError, match=r"ranges.csv: line 8: range_m must be > 0"):
        read_ranges(path)
    path.write_text("image,sensor_id,range_m\n# c\na.png,0,1.5\na.png,1,1.5,7\n")
    with pytest.raises(CalibrationError, match=r"line 4: expected 3 values"):
        read_ranges(path)
    path.write_text("# c\nimage,sensor_id,range_m\n# c\na.png,0,1.5\nb.png,2,2.25\n")
    assert read_ranges(path) == {"a.png": {0: 1.5}, "b.png": {2: 2.25}}
