"""SO(3)/SE(3) identities and the camera model against OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from companion.errors import GeometryError
from companion.geometry import se3, so3
from companion.geometry.camera import CameraModel

RNG = np.random.default_rng(42)


def random_rotvecs(n: int) -> np.ndarray:
    axis = RNG.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return axis * RNG.uniform(0.0, np.pi - 1e-3, (n, 1))


def test_so3_exp_log_identity() -> None:
    for w in random_rotvecs(200):
        R = so3.exp(w)
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(so3.log(R), w, atol=1e-9)


def test_so3_small_angles_and_hat() -> None:
    w = np.array([1e-12, -2e-12, 3e-12])
    assert np.allclose(so3.log(so3.exp(w)), w, atol=1e-15)
    a, b = RNG.normal(size=3), RNG.normal(size=3)
    assert np.allclose(so3.hat(a) @ b, np.cross(a, b))


def test_quaternion_round_trip() -> None:
    for w1, w2 in zip(random_rotvecs(50), random_rotvecs(50), strict=True):
        R1, R2 = so3.exp(w1), so3.exp(w2)
        q1, q2 = so3.matrix_to_quat(R1), so3.matrix_to_quat(R2)
        assert np.allclose(so3.quat_to_matrix(q1), R1, atol=1e-12)
        assert np.allclose(so3.quat_to_matrix(q2), R2, atol=1e-12)
    # order conversion for scipy / TUM
    q = np.array([0.1, 0.2, 0.3, 0.4])
    assert np.allclose(so3.quat_xyzw_to_wxyz(so3.quat_wxyz_to_xyzw(q)), q)
    with pytest.raises(GeometryError):
        so3.normalize_quat([0, 0, 0, 0])


def test_quaternion_matches_scipy() -> None:
    from scipy.spatial.transform import Rotation

    for w in random_rotvecs(20):
        q_wxyz = so3.matrix_to_quat(so3.exp(w))
        R_scipy = Rotation.from_quat(so3.quat_wxyz_to_xyzw(q_wxyz)).as_matrix()
        assert np.allclose(R_scipy, so3.exp(w), atol=1e-12)


def test_rpy_round_trip_and_convention() -> None:
    for _ in range(100):
        r, p, y = RNG.uniform(-3, 3), RNG.uniform(-1.5, 1.5), RNG.uniform(-3, 3)
        R = so3.rpy_to_matrix(r, p, y)
        assert np.allclose(so3.matrix_to_rpy(R), (r, p, y), atol=1e-9)
    # a positive pitch lifts the nose: body x (forward) gets a negative z (up in NED)
    assert so3.rpy_to_matrix(0, 0.3, 0)[2, 0] < 0
    # docs/architecture.md: downward camera, image top to the nose: cam x = body +y, cam y = body -x
    R_body_cam = so3.rpy_to_matrix(0, 0, np.pi / 2)
    assert np.allclose(R_body_cam @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    assert np.allclose(R_body_cam @ [0, 1, 0], [-1, 0, 0], atol=1e-12)
    assert np.allclose(R_body_cam @ [0, 0, 1], [0, 0, 1], atol=1e-12)


def test_se3_inverse_exp_log_interpolate() -> None:
    for w in random_rotvecs(50):
        T = se3.make(so3.exp(w), RNG.normal(size=3) * 5)
        assert np.allclose(se3.inverse(T) @ T, np.eye(4), atol=1e-12)
        assert np.allclose(se3.exp(se3.log(T)), T, atol=1e-9)
        p = RNG.normal(size=(5, 3))
        assert np.allclose(se3.transform(se3.inverse(T), se3.transform(T, p)), p, atol=1e-12)
        assert np.allclose(se3.interpolate(np.eye(4), T, 1.0), T, atol=1e-9)
        assert np.allclose(se3.interpolate(np.eye(4), T, 0.0), np.eye(4), atol=1e-12)
        mid = se3.interpolate(np.eye(4), T, 0.5)
        assert np.allclose(mid[:3, 3], 0.5 * T[:3, 3])
        assert np.isclose(
            so3.angle_between(np.eye(3), mid[:3, :3]), 0.5 * so3.angle_between(np.eye(3), T[:3, :3])
        )


CAMERAS = [
    CameraModel(640, 480, 460.0, 462.0, 319.5, 239.5, -0.12, 0.05, 0.0005, -0.0003, 0.0),
    CameraModel(
        752,
        480,
        458.654,
        457.296,
        367.215,
        248.375,
        -0.28340811,
        0.07395907,
        0.00019359,
        1.76187114e-05,
        0.0,
    ),  # EuRoC cam0
    CameraModel(640, 480, 500.0, 500.0, 320.0, 240.0, 0.1, -0.05, 0.001, 0.002, 0.01),
    CameraModel(320, 240, 300.0, 300.0, 160.0, 120.0),
]


@pytest.mark.parametrize("cam", CAMERAS)
def test_projection_matches_opencv(cam: CameraModel) -> None:
    pts = np.column_stack(
        [RNG.uniform(-2, 2, 500), RNG.uniform(-1.5, 1.5, 500), RNG.uniform(2, 10, 500)]
    )
    ours, ok = cam.project(pts)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
    assert ok.all()
    assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-9


@pytest.mark.parametrize("cam", CAMERAS)
def test_undistortion_matches_opencv_and_inverts_projection(cam: CameraModel) -> None:
    uv = np.column_stack([RNG.uniform(0, cam.width - 1, 400), RNG.uniform(0, cam.height - 1, 400)])
    ours = cam.pixels_to_normalized(uv)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
        ref = cv2.undistortPointsIter(
            uv.reshape(-1, 1, 2), cam.K, cam.dist_coeffs, None, None, criteria
        )
    else:  # OpenCV 5 folded the criteria into undistortPoints
        ref = cv2.undistortPoints(
            uv.reshape(-1, 1, 2), cam.K, cam.dist_coeffs, None, None, None, criteria
        )
    assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-7
    # our inverse is exact: re-projecting the rays gives the pixels back
    rays = cam.pixels_to_rays(uv)
    back, _ = cam.project(rays * 7.0)
    assert np.abs(back - uv).max() < 1e-9
    assert np.allclose(np.linalg.norm(rays, axis=1), 1.0)


@pytest.mark.parametrize("cam", CAMERAS)
def test_a_k1_per_point_is_the_lens_with_that_k1(cam: CameraModel) -> None:
    """The lens check's candidates (companion/vo/focal_check.py): undistorting and distorting
    with k1 given point by point is, for each point, what the model with that k1 gives; the
    lens without distortion is not short-cut when a k1 is given."""
    from dataclasses import replace

    xy = np.column_stack([RNG.uniform(-0.6, 0.6, 300), RNG.uniform(-0.45, 0.45, 300)])
    k1 = np.repeat(cam.k1 + np.array([-0.05, 0.0, 0.04]), 100)
    ours = cam.undistort_normalized(xy, k1=k1)
    distorted = cam.distort(ours, k1)
    assert np.abs(distorted - xy).max() < 1e-12
    for k, value in enumerate(cam.k1 + np.array([-0.05, 0.0, 0.04])):
        alone = replace(cam, k1=float(value))
        rows = slice(100 * k, 100 * (k + 1))
        assert np.abs(alone.undistort_normalized(xy[rows]) - ours[rows]).max() < 1e-12
        assert np.abs(alone.distort(ours[rows]) - distorted[rows]).max() < 1e-12
    assert not np.allclose(ours[:100], xy[:100])  # k1 -0.05 moved them, distortion or not


@pytest.mark.parametrize("cam", CAMERAS)
def test_a_points_undistortion_does_not_depend_on_the_other_points_of_the_call(
    cam: CameraModel,
) -> None:
    """The VO undistorts a frame's tracks once and hands each stage its subset: every
    point's result is the same to the bit alone, in any subset, and among points that need
    more iterations (the image's corners) or that do not converge (NaN rows)."""
    uv = np.column_stack([RNG.uniform(0, cam.width - 1, 200), RNG.uniform(0, cam.height - 1, 200)])
    corners = np.array([[0.0, 0.0], [cam.width - 1.0, cam.height - 1.0], [np.nan, 3.0]])
    every = np.vstack([uv, corners])
    whole = cam.pixels_to_normalized(every, nan_where_unconverged=True)
    for rows in (np.arange(0, 200, 7), np.arange(200), np.array([5, 201])):
        part = cam.pixels_to_normalized(every[rows], nan_where_unconverged=True)
        assert np.array_equal(part, whole[rows])
    for k in (0, 77, 200, 201):
        alone = cam.pixels_to_normalized(every[k : k + 1], nan_where_unconverged=True)
        assert np.array_equal(alone, whole[k : k + 1])
    assert np.isnan(whole[202]).any() and np.isfinite(whole[:202]).all()


def test_undistortion_of_no_point_and_of_a_nan_pixel() -> None:
    """An empty set is an empty answer (no iteration); a set with a NaN pixel raises instead
    of returning coordinates (a folding lens: companion/geometry/lens_check.py)."""
    cam = CAMERAS[0]
    assert cam.pixels_to_normalized(np.zeros((0, 2))).shape == (0, 2)
    with pytest.raises(GeometryError, match="did not converge"):
        cam.pixels_to_normalized(np.array([[10.0, 10.0], [np.nan, 5.0]]))


def test_pixel_rays_grid_and_behind_camera() -> None:
    cam = CAMERAS[0]
    rays = cam.pixel_rays()
    assert rays.shape == (480, 640, 3)
    uv, _ = cam.project(rays[::37, ::41].reshape(-1, 3))
    vv, uu = np.mgrid[0:480:37, 0:640:41]
    assert np.abs(uv - np.column_stack([uu.ravel(), vv.ravel()])).max() < 1e-9
    uv_b, ok = cam.project(np.array([[0.0, 0.0, -1.0]]))
    assert not ok[0] and np.isnan(uv_b).all()
    assert cam.in_image(np.array([[0.0, 0.0], [639.4, 479.4], [-1.0, 5.0]])).tolist() == [
        True,
        True,
        False,
    ]


def test_rpy_to_matrices_is_rpy_to_matrix_of_each_triple() -> None:
    rng = np.random.default_rng(3)
    roll, pitch, yaw = rng.uniform(-3.0, 3.0, (3, 50))
    pitch = pitch / 2.5  # within (-pi/2, pi/2)
    R = so3.rpy_to_matrices(roll, pitch, yaw)
    assert R.shape == (50, 3, 3)
    for k in range(50):
        assert np.allclose(R[k], so3.rpy_to_matrix(roll[k], pitch[k], yaw[k]), atol=1e-14)
    assert np.allclose(so3.rpy_to_matrices(0.1, -0.2, 0.3), so3.rpy_to_matrix(0.1, -0.2, 0.3))


def test_the_mean_of_rotations_scattered_around_one_is_that_one() -> None:
    """so3.mean (d-Pose's arming attitude over its window): samples scattered symmetrically
    around an attitude average back to it, and the mean of one rotation is that rotation."""
    R_true = so3.rpy_to_matrix(0.02, -0.03, 1.2)
    rng = np.random.default_rng(4)
    noise = rng.normal(0.0, np.radians(0.15), (20, 3))
    Rs = [R_true @ so3.exp(n) for n in (*noise, *(-noise))]
    assert so3.angle_between(so3.mean(Rs), R_true) < 1e-6
    assert so3.angle_between(Rs[0], R_true) > np.radians(0.05)
    assert so3.angle_between(so3.mean([Rs[3]]), Rs[3]) < 1e-12
