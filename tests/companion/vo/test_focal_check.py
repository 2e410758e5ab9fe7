"""The focal length and k1 against the autopilot's rotation (companion/vo/focal_check.py), on
seeded synthetic views: the pair estimate recovers f_true / f_file and k1_true - k1_file
apart (an error in k1 is not read as one in the focal), a rotation about the optical axis
counts for nothing, and the warning needs a confident estimate."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from companion.geometry import so3
from companion.geometry.camera import CameraModel
from companion.vo.focal_check import (
    FILE_REJECT_RATIO,
    FocalCheck,
    FocalRatio,
    KeyframeView,
    focal_summary,
    focal_warning,
    lens_findings,
    pair_lens,
    tilt_angle_rad,
)

TRUE = CameraModel(640, 480, 460.0, 460.0, 319.5, 239.5, -0.12, 0.05, 0.0005, -0.0003)


def _views(seed: int, tilt_deg: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (N, 2) of N ground points (hilly, 6 m below) seen from two poses with a tilt and
    a sideways translation; R_c2_c1 (3, 3)."""
    rng = np.random.default_rng(seed)
    n = 150
    P1 = np.column_stack(
        [rng.uniform(-3.5, 3.5, n), rng.uniform(-2.5, 2.5, n), 6.0 + rng.uniform(-0.5, 0.5, n)]
    )
    R_c2_c1 = so3.exp(np.radians([tilt_deg, -0.5 * tilt_deg, 8.0]))
    t = np.array([0.6, -0.3, 0.05])  # sideways motion, as a multirotor tilts to accelerate
    P2 = P1 @ R_c2_c1.T + t
    uv1, _ = TRUE.project(P1)
    uv2, _ = TRUE.project(P2)
    keep = TRUE.in_image(uv1) & TRUE.in_image(uv2)
    noise = rng.normal(0.0, 0.2, (2, int(keep.sum()), 2))  # KLT noise [px]
    return uv1[keep] + noise[0], uv2[keep] + noise[1], R_c2_c1


@pytest.mark.parametrize(
    ("file_over_true", "k1_file_minus_true"),
    [(1.1, 0.0), (1.0, 0.0), (0.9, 0.0), (1.0, 0.02), (1.0, -0.02), (1.1, 0.02)],
)
def test_a_pair_recovers_the_focal_ratio_and_the_k1_error(
    file_over_true: float, k1_file_minus_true: float
) -> None:
    """Each lens error apart and both together; before the joint search a k1 0.02 off moved
    the focal ratio alone (13.7 % in a simulated flight)."""
    file_model = replace(
        TRUE,
        fx=TRUE.fx * file_over_true,
        fy=TRUE.fy * file_over_true,
        k1=TRUE.k1 + k1_file_minus_true,
    )
    estimates = [pair_lens(file_model, *_views(seed)) for seed in range(8)]
    assert all(e is not None and not e.at_edge for e in estimates)
    q = np.median([e.q for e in estimates if e is not None])
    k1_delta = np.median([e.k1_delta for e in estimates if e is not None])
    assert q == pytest.approx(1.0 / file_over_true, rel=0.02)
    assert k1_delta == pytest.approx(-k1_file_minus_true, abs=0.005)
    # the file's lens fits a pair nearly as well as its best when it is right, not otherwise
    rejects = [e.file_cost_ratio < FILE_REJECT_RATIO for e in estimates if e is not None]
    if file_over_true == 1.0 and k1_file_minus_true == 0.0:
        assert not any(rejects)
    else:
        assert sum(rejects) >= 6


def test_rotation_about_the_optical_axis_is_no_tilt() -> None:
    assert tilt_angle_rad(so3.exp(np.array([0.0, 0.0, 0.7]))) == pytest.approx(0.0, abs=1e-12)
    rotvec = np.array([0.03, -0.04, 0.5])
    assert tilt_angle_rad(so3.exp(rotvec)) == pytest.approx(0.05, rel=1e-9)


def test_the_window_pairs_keyframes_of_one_map_with_enough_tilt() -> None:
    file_model = replace(TRUE, fx=TRUE.fx * 1.1, fy=TRUE.fy * 1.1)
    check = FocalCheck(file_model, min_points=30)
    px1, px2, R_c2_c1 = _views(3)
    ids = np.arange(len(px1), dtype=np.int64)
    first = KeyframeView(0, 0, np.eye(3), ids, px1)
    assert check.add(first) == 0
    second = KeyframeView(500_000, 0, R_c2_c1.T, ids, px2)  # R_world_c2 = R_c1_c2
    assert check.add(second) == 1
    other_map = KeyframeView(1_000_000, 1, np.eye(3), ids, px1)
    assert check.add(other_map) == 0
    too_soon = KeyframeView(1_100_000, 1, R_c2_c1.T, ids, px2)  # 0.1 s < min_age_s
    assert check.add(too_soon) == 0
    est = check.estimate()
    assert est is not None and est.samples == 1
    assert est.ratio == pytest.approx(1.0 / 1.1, rel=0.03)


def test_the_warning_needs_a_confident_estimate() -> None:
    assert focal_warning(FocalRatio(1.103, 0.05, 0.007, 84)) is not None
    text = focal_warning(FocalRatio(1.103, 0.05, 0.007, 84))
    assert text is not None and "10.3 % too small" in text and "84 keyframe pairs" in text
    assert "too large" in (focal_warning(FocalRatio(0.9, 0.05, 0.007, 84)) or "")
    assert focal_warning(FocalRatio(1.103, 0.05, 0.007, 10)) is None  # too few pairs
    assert focal_warning(FocalRatio(1.06, 0.05, 0.007, 84)) is None  # 6 % - 2 sigma < 5 %
    assert focal_warning(FocalRatio(1.01, 0.05, 0.007, 84)) is None
    k1_off = focal_warning(FocalRatio(1.01, 0.05, 0.007, 84, 0, 0.021, 0.006, 0.0008)) or ""
    assert "k1 looks 0.021 too small" in k1_off and "check [camera] dist" in k1_off
    assert "focal length" not in k1_off and "fits" not in k1_off
    named = focal_warning(FocalRatio(0.9, 0.05, 0.007, 84, 0, 0.021, 0.006, 0.0008), camera=TRUE)
    assert "(the flight fits fx 414.0, fy 414.0)" in (named or "")  # 460 x 0.9
    assert "(the flight fits k1 -0.099)" in (named or "")  # -0.12 + 0.021
    briefs = lens_findings(FocalRatio(0.9, 0.05, 0.007, 84, 0, 0.021, 0.006, 0.0008))
    assert [brief for brief, _ in briefs] == ["focal x0.900", "k1 +0.021"]
    both = focal_warning(FocalRatio(0.9, 0.05, 0.007, 84, 0, -0.03, 0.006, 0.0008)) or ""
    assert "focal length looks 10.0 % too large" in both and "k1 looks 0.030 too large" in both
    # within the threshold once its uncertainty is counted: no warning
    assert focal_warning(FocalRatio(1.0, 0.05, 0.007, 84, 0, 0.012, 0.01, 0.002)) is None
    assert "no keyframe pairs" in focal_summary(None)
    assert "1.103 (spread 0.050" in focal_summary(FocalRatio(1.103, 0.05, 0.007, 84))


def test_no_finding_while_most_pairs_fit_the_files_lens_nearly_as_well() -> None:
    """A flat floor seen with small tilts: the pairs' best lenses are weak and biased (a
    simulated look-alike of rislab_downward, its lens within 1 % of the file's, read f x1.17
    with most pairs at an end of the search) while the file's lens costs them little more."""
    weak = FocalRatio(1.17, 0.25, 0.02, 200, 130, -0.06, 0.06, 0.005, rejecting=99)
    assert lens_findings(weak) == []
    assert "99 fit another lens better than the file's by 10 % or more" in focal_summary(weak)
    strong = FocalRatio(1.17, 0.25, 0.02, 200, 0, 0.0, 0.06, 0.005, rejecting=150)
    assert [brief for brief, _ in lens_findings(strong)] == ["focal x1.170"]
    edges = FocalRatio(0.81, 0.16, 0.014, 200, 147, -0.05, 0.07, 0.006, rejecting=155)
    assert [brief for brief, _ in lens_findings(edges)] == ["fits no lens model"]


def test_pairs_that_no_focal_fits_say_the_lens_or_mount_is_wrong() -> None:
    """When most pairs' best lens is at an end of the search, the median is not a
    measurement: the warning says that no lens in the range fits, not a percentage."""
    est = FocalRatio(0.7, 0.0, 0.0, 200, at_edge=180)
    text = focal_warning(est) or ""
    assert "no lens within x0.70..x1.40" in text and "+-0.10 of its k1" in text
    assert "180 of 200" in text
    assert "% too" not in text
    assert "180 at an end of the search" in focal_summary(est)
    assert [brief for brief, _ in lens_findings(est)] == ["fits no lens model"]
