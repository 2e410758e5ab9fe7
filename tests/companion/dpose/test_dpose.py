"""d-Pose: pattern margin, exact poses, every labelling told apart, missing/extra dots,
random poses, detection on rendered frames."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from companion.config import dpose_rangefinders, load_config
from companion.dpose.detect import detect_marks
from companion.dpose.pattern import (
    DPOSE_BEAMS,
    PERMUTATIONS,
    ground_marks,
    similarity_margin,
)
from companion.dpose.solve import Priors, poses_known_tilt, reference_points, solve
from companion.evaluation.dpose import random_pose_study
from companion.geometry import se3, so3

CFG = load_config()
CAMERA = CFG.camera.model()
T_BODY_CAM = CFG.camera.T_body_cam()
T_CAM_BODY = se3.inverse(T_BODY_CAM)


def pattern_over_flat(height_m: float = 3.0) -> np.ndarray:
    T = np.stack([r.spec().T_body_rf for r in dpose_rangefinders()])
    o, u = T[:, :3, 3], T[:, :3, 2]
    return reference_points(o, u, (height_m - o[:, 2]) / u[:, 2])


def view(pattern, rpy_deg, body_xyz):
    """Exact pixels of the marks seen from a body pose (in the pattern frame)."""
    T_pattern_body = se3.make(so3.rpy_to_matrix(*np.radians(rpy_deg)), body_xyz)
    T_cam_pattern = se3.inverse(T_pattern_body @ T_BODY_CAM)
    uv, ok = CAMERA.project(se3.transform(T_cam_pattern, pattern))
    assert ok.all() and CAMERA.in_image(uv).all()
    return uv, T_pattern_body, T_cam_pattern


def priors_for(T_pattern_body, pattern, height_m=float("nan")):
    n = np.array([0.0, 0.0, 1.0])
    return Priors(
        T_pattern_body[:3, :3],
        np.radians(0.1),
        T_CAM_BODY[:3, :3],
        T_CAM_BODY[:3, 3],
        height_m,
        0.01,
        n,
        float(pattern[:, 2].mean()),
    )


def test_the_pattern_has_a_similarity_margin_and_a_square_has_none() -> None:
    assert similarity_margin(ground_marks(DPOSE_BEAMS)) > 0.4
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert similarity_margin(square) < 1e-9
    kite = np.array([[0.0, 1.0], [1.0, 0.0], [0.0, -2.0], [-1.0, 0.0]])  # mirror symmetric
    assert similarity_margin(kite) < 1e-9


@pytest.mark.parametrize(
    ("rpy_deg", "xyz"),
    [((0, 0, 0), (0, 0, -1)), ((4, -3, 75), (0.2, -0.1, -2.0)), ((-6, 5, -140), (-0.3, 0.2, -3.5))],
)
def test_known_poses_are_recovered_exactly(rpy_deg, xyz) -> None:
    pattern = pattern_over_flat()
    uv, T_pb, T_cp = view(pattern, rpy_deg, xyz)
    # the closed form with the true tilt
    norm = CAMERA.pixels_to_normalized(uv)
    r, p, _ = so3.matrix_to_rpy(T_pb[:3, :3])
    R_tilt_cam = so3.rpy_to_matrix(r, p, 0.0) @ T_CAM_BODY[:3, :3].T
    R, t, valid = poses_known_tilt(pattern, norm[None], R_tilt_cam)
    assert valid[0]
    np.testing.assert_allclose(R[0], T_cp[:3, :3], atol=1e-9)
    np.testing.assert_allclose(t[0], T_cp[:3, 3], atol=1e-9)
    # the whole solver, with and without priors
    for pri in (priors_for(T_pb, pattern), None):
        sol, why = solve(uv, pattern, CAMERA, T_CAM_BODY[:3, :3], priors=pri)
        assert sol is not None, why
        assert sol.order == (0, 1, 2, 3)
        np.testing.assert_allclose(sol.T_cam_pattern, T_cp, atol=1e-6)


def test_every_labelling_and_the_mirror_image_are_told_apart() -> None:
    pattern = pattern_over_flat()
    uv, T_pb, _ = view(pattern, (3, -2, 40), (0.1, 0.1, -2.5))
    for perm in PERMUTATIONS:
        shuffled = uv[list(perm)]
        sol, why = solve(
            shuffled, pattern, CAMERA, T_CAM_BODY[:3, :3], priors=priors_for(T_pb, pattern)
        )
        assert sol is not None, why
        # mark k is detection order[k], and detection j holds mark perm[j]
        assert [perm[i] for i in sol.order] == [0, 1, 2, 3]
    mirrored = pattern * np.array([1.0, -1.0, 1.0])  # the pattern's reflection
    uv_m, T_pb_m, _ = view(mirrored, (3, -2, 40), (0.1, 0.1, -2.5))
    for pri in (priors_for(T_pb_m, pattern), None):
        sol, _ = solve(uv_m, pattern, CAMERA, T_CAM_BODY[:3, :3], priors=pri)
        assert sol is None  # a mirror image is not the pattern, under any labelling


def test_a_missing_or_an_extra_dot_yields_no_wrong_pose() -> None:
    pattern = pattern_over_flat()
    uv, T_pb, _ = view(pattern, (2, 1, -60), (0.0, 0.2, -3.0))
    pri = priors_for(T_pb, pattern)
    for drop in range(4):
        sol, why = solve(
            np.delete(uv, drop, axis=0), pattern, CAMERA, T_CAM_BODY[:3, :3], priors=pri
        )
        assert sol is None and "3 marks" in why
    extra = np.vstack([uv, [[100.0, 400.0]]])
    sol, _ = solve(extra, pattern, CAMERA, T_CAM_BODY[:3, :3])  # no priors: refused
    assert sol is None
    sol, why = solve(extra, pattern, CAMERA, T_CAM_BODY[:3, :3], priors=pri)
    assert sol is not None, why  # with priors the stray dot cannot fit: sorted out
    assert sol.order == (0, 1, 2, 3)


def test_random_poses_give_no_wrong_vertex_map() -> None:
    pattern = pattern_over_flat()
    st = random_pose_study(CAMERA, T_BODY_CAM, pattern, 800, seed=3)
    assert st.visible > 700
    assert st.wrong == 0
    assert st.pose_rate >= 0.99
    h = np.array(st.height_m)
    band = (h >= 2) & (h <= 6)
    assert np.sqrt(np.mean(np.square(st.translation_err_m)[band])) <= 0.02
    assert np.sqrt(np.mean(np.square(st.rotation_err_deg)[band])) <= 0.5
    noisy = random_pose_study(CAMERA, T_BODY_CAM, pattern, 300, seed=4, distractors=2)
    assert noisy.wrong == 0 and noisy.pose_rate > 0.9


def test_marks_are_detected_on_rendered_frames(world) -> None:
    from companion.sitl.world.scenario import Scenario

    cfg = load_config(
        overrides={"sitl": {"terrain": "hills", "trajectory": "spiral", "seconds": 20.0}}
    )
    render = dataclasses.replace(cfg.sitl.render, laser_marks="painted", painted_time_s=1.0)
    cfg = dataclasses.replace(
        cfg, rangefinders=dpose_rangefinders(), sitl=dataclasses.replace(cfg.sitl, render=render)
    )
    sc = Scenario(cfg, world("hills", 1))
    for seq in (30, 150, 300, 450):
        st = sc.step(seq)
        det = detect_marks(st.frame.image_bgr)
        truth = st.rendered.marks_uv[np.all(np.isfinite(st.rendered.marks_uv), axis=1)]
        assert len(det) == len(truth) == 4
        for m in truth:
            assert np.min(np.linalg.norm(det - m, axis=1)) < 0.5
    # the same frame with the dots painted over in grey: nothing is found in the texture
    from companion.dpose.detect import redness

    clean = st.frame.image_bgr.copy()
    clean[redness(clean) > 40] = (90, 90, 90)
    assert len(detect_marks(clean)) == 0


def test_the_shipped_beams_are_what_design_finds() -> None:
    """DPOSE_BEAMS is design()'s output, written down: a change to the search or the margin
    that no longer reproduces it must update both (the calibration and the docs cite it)."""
    from companion.dpose.pattern import design

    beams, margin = design()
    assert beams == DPOSE_BEAMS
    assert margin == pytest.approx(similarity_margin(ground_marks(DPOSE_BEAMS)))
    assert margin > 0.4


def test_the_offset_takes_a_stale_gap_at_once_and_averages_at_rest() -> None:
    """companion/dpose/offset.py: after 50 m of VO path the offset is stale (sigma 0.25 m)
    and a 4 cm gap is taken almost whole (the published position is d-Pose's on the first
    frame back); hovering, the gain falls below 10 % and 1 cm noise is averaged down; a gap
    over reset_m is taken whole and counted."""
    from companion.dpose.offset import DposeOffset

    off = DposeOffset(drift_per_m=0.005, drift_m_per_s=0.001, reset_m=0.05)
    with pytest.raises(ValueError):
        off.update(0, np.zeros(3), np.zeros(3), 0.01)
    off.arm(0, np.zeros(3))
    # a 12 m square at 30 Hz for 20 s, back to 0.36 m from the start: the path counts (48 m)
    corners = np.array([[0, 0, 0], [12, 0, 0], [12, 12, 0], [0, 12, 0], [0.3, -0.2, 0]], float)
    for k in range(1, 601):
        u = 4 * k / 600
        i = min(int(u), 3)
        off.move(corners[i] + (u - i) * (corners[i + 1] - corners[i]))
    vo = corners[-1]
    assert off.predicted_sigma_m(20_000_000, vo) > 0.2  # 0.5 % of 48 m + 20 mm
    truth_offset = np.array([0.03, -0.02, 0.015])
    assert not off.update(20_000_000, vo, vo + truth_offset, 0.011)
    assert np.linalg.norm(off.offset_m - truth_offset) < 0.001
    # hovering at 30 Hz: noisy d-Pose poses about the same offset
    rng = np.random.default_rng(3)
    gains = []
    for k in range(1, 300):
        before = off.offset_m.copy()
        noise = 0.011 * rng.standard_normal(3)
        off.update(20_000_000 + k * 33_333, vo, vo + truth_offset + noise, 0.011)
        gains.append(
            np.linalg.norm(off.offset_m - before) / np.linalg.norm(truth_offset + noise - before)
        )
    assert np.median(gains[-100:]) < 0.1
    assert np.linalg.norm(off.offset_m - truth_offset) < 0.005  # 1.1 cm per pose averaged
    assert off.resets == 0 and off.updates == 300
    # a 6 cm jump (the VO re-initialised under us): taken whole, a reset
    assert off.update(31_000_000, vo - 0.06, vo + truth_offset, 0.011)
    assert off.resets == 1 and np.allclose(off.offset_m, truth_offset + 0.06)
    assert off.sigma_m == pytest.approx(0.011)


def test_a_mark_cut_by_the_image_edge_is_not_reported() -> None:
    """A dot half outside the image has its centroid pulled inwards by ~its radius: it is
    left out (d-Pose then waits for the four whole marks) rather than biasing the pose."""
    img = np.full((120, 160, 3), 90, np.uint8)
    yy, xx = np.mgrid[0:120, 0:160]
    for cx, cy in ((40.0, 60.0), (100.0, 1.0), (158.5, 80.0)):  # whole, top edge, right edge
        spot = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 2.0**2))
        img[..., 2] = np.maximum(img[..., 2], (90 + 165 * spot).astype(np.uint8))
    found = detect_marks(img)
    assert len(found) == 1 and np.allclose(found[0], (40.0, 60.0), atol=0.05)
