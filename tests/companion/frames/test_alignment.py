"""The 4-DoF alignment of our track to the autopilot's GPS track (companion.frames.alignment).

Seeded flights (tests/peers/gps_tracks.py): a lawnmower (5 legs of 20 m, 60 s) and a hover,
through a known alignment (yaw 37 deg, offset (5, -3, 0.4) m), with GPS-like noise (0.3 m,
Gauss-Markov with a 1 s time constant, plus 5 cm white) and 1 deg of heading noise each side.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from peers.gps_tracks import TRUE_ALIGNMENT, fly, hover, lawnmower

from companion.frames.alignment import (
    FrameAlignment,
    PairWindow,
    apply,
    attitude_yaw,
    fit_track,
    match_pairs,
    wrap_rad,
)
from companion.geometry import so3
from companion.types import PoseEstimate


def _yaw_error_deg(a: FrameAlignment, b: FrameAlignment) -> float:
    return abs(math.degrees(wrap_rad(a.yaw_rad - b.yaw_rad)))


@pytest.mark.parametrize("seed", range(10))
def test_the_lawnmower_gives_the_yaw_within_1_deg_and_the_offset_within_02_m(seed: int) -> None:
    """The offset is judged where the vehicle flies (the track's centroid, 14 m from the
    origin): at the origin a yaw error of e adds 14 m x e (0.24 m per degree), which the
    translation's own bound states."""
    flight = fly(lawnmower(), seed)
    fit = fit_track(flight.gps_pairs())
    assert fit is not None and fit.yaw_source == "both"
    yaw_err = _yaw_error_deg(fit.alignment, TRUE_ALIGNMENT)
    assert yaw_err < 1.0
    centroid = flight.path.position_ned_m.mean(axis=0)
    at_centroid = fit.alignment.apply_points(centroid) - TRUE_ALIGNMENT.apply_points(centroid)
    assert np.linalg.norm(at_centroid) < 0.2
    lever = np.linalg.norm(centroid[:2]) * math.radians(yaw_err)
    t_err = np.linalg.norm(fit.alignment.translation_ned_m - TRUE_ALIGNMENT.translation_ned_m)
    assert t_err < 0.2 + lever
    # the agreement is the GPS noise (0.3 m per axis, 5 cm white): ~0.52 m in 3-D
    assert 0.35 < fit.residual_rms_m < 0.7
    assert np.all(fit.residual_rms_ned_m < 0.45)
    assert fit.travel_m == pytest.approx(33.2, abs=0.5)  # extent of the 20 m x 20 m lawnmower
    assert fit.yaw_sigma_rad < math.radians(1.0)
    assert fit.pairs == len(flight.gps_pairs())


@pytest.mark.parametrize("seed", range(5))
def test_a_hover_takes_the_attitude_yaw(seed: int) -> None:
    """Standing still the track gives no yaw (noise only): the headings' circular mean does;
    without headings there is no fit at all."""
    flight = fly(hover(20.0), seed)
    pairs = flight.gps_pairs()
    fit = fit_track(pairs)
    assert fit is not None and fit.yaw_source == "attitude"
    assert fit.travel_m < 0.5 and math.isnan(fit.yaw_track_rad)
    assert _yaw_error_deg(fit.alignment, TRUE_ALIGNMENT) < 1.0
    at = flight.path.position_ned_m[0]
    assert np.linalg.norm(fit.alignment.apply_points(at) - TRUE_ALIGNMENT.apply_points(at)) < 0.3
    blind = dataclasses.replace(pairs, our_yaw_rad=np.full(len(pairs), np.nan))
    assert fit_track(blind) is None


def test_travel_weighs_the_track_yaw_against_a_biased_heading() -> None:
    """A 5 deg heading bias (a declination error on one side): the lawnmower's track yaw
    outweighs it (track sigma 0.3 m / 33 m = 0.5 deg against the 2 deg floor), the hover has
    nothing else and carries the bias whole."""
    moving = fit_track(fly(lawnmower(), 3, heading_bias_deg=5.0).gps_pairs())
    assert moving is not None
    assert math.degrees(moving.yaw_attitude_rad - TRUE_ALIGNMENT.yaw_rad) == pytest.approx(
        5, abs=0.3
    )
    assert _yaw_error_deg(moving.alignment, TRUE_ALIGNMENT) < 1.0
    still = fit_track(fly(hover(20.0), 3, heading_bias_deg=5.0).gps_pairs())
    assert still is not None
    assert _yaw_error_deg(still.alignment, TRUE_ALIGNMENT) == pytest.approx(5.0, abs=0.5)


def test_the_fit_of_an_applied_track_is_the_inverse_exactly() -> None:
    """Without noise: ours = T(x), theirs = x  ->  the fit is T^-1, residual 0; also through the
    headings alone (a hover) and through both."""
    T = FrameAlignment(math.radians(-123.0), np.array([40.0, -7.5, 2.0]))
    path = lawnmower(legs=3)
    x = path.position_ned_m
    n = len(x)
    no_heading = np.full(n, np.nan)
    reset = np.zeros(n, dtype=np.int64)
    pairs = PairWindow(path.time_us, T.apply_points(x), x, no_heading, no_heading, reset)
    fit = fit_track(pairs)
    assert fit is not None and fit.yaw_source == "track"
    inv = T.inverse()
    assert fit.alignment.yaw_rad == pytest.approx(inv.yaw_rad, abs=1e-12)
    np.testing.assert_allclose(fit.alignment.translation_ned_m, inv.translation_ned_m, atol=1e-9)
    assert fit.residual_rms_m < 1e-9
    np.testing.assert_allclose(fit.alignment.apply_points(T.apply_points(x)), x, atol=1e-9)
    ours_yaw = np.array([wrap_rad(y + T.yaw_rad) for y in path.yaw_rad])
    both = fit_track(PairWindow(path.time_us, T.apply_points(x), x, ours_yaw, path.yaw_rad, reset))
    assert both is not None and both.yaw_source == "both"
    assert both.alignment.yaw_rad == pytest.approx(inv.yaw_rad, abs=1e-12)
    still = np.tile(x[:1], (n, 1))
    held = fit_track(
        PairWindow(path.time_us, T.apply_points(still), still, ours_yaw, path.yaw_rad, reset)
    )
    assert held is not None and held.yaw_source == "attitude"
    np.testing.assert_allclose(held.alignment.translation_ned_m, inv.translation_ned_m, atol=1e-9)


def test_weights_leave_out_what_they_zero() -> None:
    flight = fly(lawnmower(), 1)
    pairs = flight.gps_pairs()
    clean = fit_track(pairs)
    bad = dataclasses.replace(pairs, ref_ned_m=pairs.ref_ned_m.copy())
    bad.ref_ned_m[::10] += np.array([50.0, -80.0, 10.0])  # a multipath burst every 2 s
    w = np.ones(len(pairs))
    w[::10] = 0.0
    weighted, unweighted = fit_track(bad, w), fit_track(bad)
    assert clean is not None and weighted is not None and unweighted is not None
    assert weighted.alignment.yaw_rad == pytest.approx(clean.alignment.yaw_rad, abs=0.01)
    assert unweighted.residual_rms_m > 10.0  # the outliers, unweighted, are the agreement
    with pytest.raises(ValueError, match="weights"):
        fit_track(pairs, -w)
    assert fit_track(pairs.take(np.arange(1))) is None


def test_the_attitude_yaw_is_a_circular_mean_across_pi() -> None:
    ours = np.radians([170.0, -175.0, 179.0, -179.0])
    theirs = np.array([wrap_rad(y + math.radians(15.0)) for y in ours])
    result = attitude_yaw(ours, theirs, np.ones(4))
    assert result is not None
    assert math.degrees(result[0]) == pytest.approx(15.0, abs=1e-9)
    assert result[1] < 1e-6
    across = attitude_yaw(np.zeros(2), np.radians([179.0, -179.0]), np.ones(2))
    assert across is not None and abs(math.degrees(across[0])) == pytest.approx(180.0, abs=1e-9)
    assert attitude_yaw(np.zeros(2), np.full(2, np.nan), np.ones(2)) is None


def test_matching_interpolates_ours_and_drops_resets_gaps_and_the_outside() -> None:
    t = np.array([0, 100_000, 200_000, 300_000, 700_000, 800_000], dtype=np.int64)
    p = np.column_stack([t * 1e-5, -t * 2e-5, np.zeros(6)])  # 1 m/s north, 2 m/s west
    yaw = np.radians([170.0, 178.0, -178.0, -170.0, 0.0, 0.0])
    reset = np.array([0, 0, 0, 1, 1, 1])
    ref_t = np.array([-10, 50_000, 150_000, 200_000, 250_000, 500_000, 750_000, 900_000])
    ref_p = np.zeros((len(ref_t), 3))
    pairs = match_pairs(t, p, yaw, reset, ref_t, ref_p)
    # -10 before ours; 250 000 across the reset; 500 000 in a 400 ms gap; 900 000 after
    assert list(pairs.time_us) == [50_000, 150_000, 200_000, 750_000]
    np.testing.assert_allclose(pairs.ours_ned_m[:, 0], [0.5, 1.5, 2.0, 7.5])
    np.testing.assert_allclose(pairs.ours_ned_m[:, 1], [-1.0, -3.0, -4.0, -15.0])
    assert abs(math.degrees(pairs.our_yaw_rad[1])) == pytest.approx(180.0, abs=1e-9)
    assert list(pairs.reset_counter) == [0, 0, 0, 1]
    assert list(pairs.latest_epoch().time_us) == [750_000]
    assert np.all(np.isnan(pairs.ref_yaw_rad))


def _pose(yaw_deg: float, cov: np.ndarray) -> PoseEstimate:
    q = so3.matrix_to_quat(so3.rpy_to_matrix(0.1, -0.2, math.radians(yaw_deg)))
    return PoseEstimate(7, np.array([3.0, 4.0, -5.0]), q, np.array([1.0, 0.0, 0.2]), cov, 2, 80)


def test_apply_turns_position_attitude_velocity_and_covariance() -> None:
    T = FrameAlignment(math.radians(90.0), np.array([1.0, 2.0, 0.5]))
    cov = np.diag([0.04, 0.01, 0.09, 1e-4, 1e-4, 4e-4])
    out = apply(T, _pose(10.0, cov))
    np.testing.assert_allclose(out.position_ned_m, [1.0 - 4.0, 2.0 + 3.0, -4.5], atol=1e-12)
    roll, pitch, yaw = so3.matrix_to_rpy(so3.quat_to_matrix(out.quat_wxyz_ned_frd))
    assert (roll, pitch) == pytest.approx((0.1, -0.2), abs=1e-12)
    assert math.degrees(yaw) == pytest.approx(100.0, abs=1e-9)
    np.testing.assert_allclose(out.velocity_ned_m_s, [0.0, 1.0, 0.2], atol=1e-12)
    np.testing.assert_allclose(np.diag(out.covariance_6x6), [0.01, 0.04, 0.09, 1e-4, 1e-4, 4e-4])
    assert (out.time_us, out.reset_counter, out.quality_pct) == (7, 2, 80)
    back = apply(T.inverse(), out)
    np.testing.assert_allclose(back.position_ned_m, [3.0, 4.0, -5.0], atol=1e-12)
    np.testing.assert_allclose(back.covariance_6x6, cov, atol=1e-15)
    # an unknown attitude variance stays unknown and does not spread into the position
    partial = cov.copy()
    partial[5, 5] = np.nan
    turned = apply(T, _pose(10.0, partial)).covariance_6x6
    assert np.isnan(turned[5, 5]) and np.isfinite(turned[:5, :5]).all()
    unknown_x = cov.copy()
    unknown_x[0, 0] = np.nan
    turned_x = apply(T, _pose(10.0, unknown_x)).covariance_6x6
    assert np.isnan(turned_x[:2, :2]).all() and turned_x[2, 2] == pytest.approx(0.09)
