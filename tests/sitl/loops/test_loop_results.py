"""The closed loops' summary figures (sitl/loops/px4_results.py): our frame's heading error and the
error in that frame's axes, on a seeded synthetic flight whose frame is turned by a known
angle."""

from __future__ import annotations

import numpy as np

from companion.geometry import so3
from companion.sitl.loops.px4_results import _frame_heading_error, _turned_p95


def _square(n: int = 400, side_m: float = 20.0) -> np.ndarray:
    """A 20 m square at 5 m up (N, 3), NED."""
    s = np.linspace(0.0, 4.0, n, endpoint=False)
    leg, f = np.floor(s).astype(int), s - np.floor(s)
    corners = np.array([[0, 0], [side_m, 0], [side_m, side_m], [0, side_m], [0, 0]], float)
    xy = corners[leg] + f[:, None] * (corners[leg + 1] - corners[leg])
    return np.column_stack([xy, np.full(n, -5.0)])


def test_a_frame_turned_by_the_autopilots_heading_error_is_measured_and_undone() -> None:
    rng = np.random.default_rng(19)
    true_yaw_rad = np.radians(30.0)  # the vehicle rests at yaw 30 deg before the take-off
    error_rad = np.radians(0.9)  # the autopilot's compass is 0.9 deg past the truth then
    t_ns = np.arange(200) * 50_000_000
    q = so3.matrix_to_quat(so3.rpy_to_matrix(0.0, 0.0, true_yaw_rad))
    q_tr = np.tile(q, (len(t_ns), 1))
    vo_heading_deg = float(np.degrees(true_yaw_rad + error_rad))  # what the service took
    got = _frame_heading_error(t_ns, q_tr, t_ns[-1] + 1, vo_heading_deg)
    assert got is not None and abs(got - error_rad) < 1e-9
    assert _frame_heading_error(t_ns, q_tr, t_ns[-1] + 1, None) is None
    assert _frame_heading_error(t_ns, q_tr, t_ns[5], vo_heading_deg) is None  # too few at rest

    # positions in a frame whose north is the autopilot's: a compass 0.9 deg past the truth
    # puts its north 0.9 deg west of true north, so every true vector reads 0.9 deg further
    # east in it (turned north -> east by +error)
    gt = _square()
    c, s = np.cos(error_rad), np.sin(error_rad)
    est = gt @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
    est += rng.normal(0.0, 0.01, est.shape)  # 1 cm of estimate noise
    seg = np.zeros(len(gt), dtype=np.int64)
    north_aligned = _turned_p95(est, gt, seg, 0.0)
    in_our_axes = _turned_p95(est, gt, seg, -got)
    assert north_aligned > 0.2  # 0.9 deg at up to 28 m from home (after the median offset)
    assert in_our_axes < 0.03  # only the noise left
    assert _turned_p95(est, gt, seg, got) > 1.8 * north_aligned  # the wrong way: twice the angle


def test_one_translation_for_the_flight_beside_the_per_stretch_figures() -> None:
    """A flight whose estimate is 0.2 m higher after a fusion restart (counted as a position
    reset, our frame unmoved): each stretch after its own translation shows none of it, one
    translation for the whole flight shows it (0.1 m each way of the median)."""
    from companion.sitl.loops.loop_results import segment_errors

    gt = _square()
    est = gt.copy()
    est[200:, 2] -= 0.2  # NED: up
    seg = np.r_[np.zeros(200, dtype=np.int64), np.ones(200, dtype=np.int64)]
    s: dict = {}
    segment_errors(s, est, gt, seg)
    assert s["vertical_error_m_p95"] < 1e-9 and s["horizontal_error_m_p95"] < 1e-9
    assert abs(s["vertical_error_m_p95_one_translation"] - 0.1) < 1e-9
    assert s["horizontal_error_m_p95_one_translation"] < 1e-9


def test_a_nan_sample_leaves_its_stretch_measured() -> None:
    """A sample with a NaN in the estimate (a CSV row cut short) is left out, not the
    stretch: a NaN in a stretch's median once made a real PX4 hover's p95 None."""
    from companion.sitl.loops.loop_results import segment_errors

    gt = _square()
    est = gt + 0.05
    est[17, 1] = np.nan
    s: dict = {}
    segment_errors(s, est, gt, np.zeros(len(gt), dtype=np.int64))
    assert s["horizontal_error_m_p95"] is not None and s["horizontal_error_m_p95"] < 1e-9
    assert s["vertical_error_m_p95_one_translation"] < 1e-9


def test_px4_truth_is_read_in_px4s_own_clock() -> None:
    """PX4's estimate is compared with SIH's ground truth at the same PX4 timestamps: a clock
    line that is 35 ms off (SIH's lockstep pace varies) would put 0.1 m of error at 3 m/s into
    the figure; the truth in PX4's clock leaves only the estimate's own."""
    from companion.sitl.loops.loop_results import segment_errors
    from companion.sitl.loops.px4_results import _px4_clock_truth

    rng = np.random.default_rng(22)
    gt = _square(n=800)  # 80 m in 26.7 s at 3 m/s
    t_px4_us = np.arange(len(gt), dtype=np.float64) * 33_333.0 + 5e6
    est = gt + rng.normal(0.0, 0.01, gt.shape)
    vlp = np.zeros(len(gt), dtype=[("timestamp_sample", "u8"), ("x", "f4")])
    vlp["timestamp_sample"] = t_px4_us
    truth_t = np.arange(t_px4_us[0] - 1e6, t_px4_us[-1] + 1e6, 4_000.0)  # SIH's 4 ms steps
    g = np.zeros(len(truth_t), dtype=[(k, "f8") for k in ("timestamp", "x", "y", "z")])
    g["timestamp"] = truth_t
    for i, k in enumerate("xyz"):
        g[k] = np.interp(truth_t, t_px4_us, gt[:, i])
    g = g[rng.permutation(len(g))]  # the order of a log's messages is not assumed
    span = np.ones(len(gt), dtype=bool)
    span[:5] = False
    got = _px4_clock_truth(
        {"vehicle_local_position": vlp, "vehicle_local_position_groundtruth": g}, span
    )
    assert got is not None and np.max(np.abs(got - gt[span])) < 0.005  # (4 ms grid, corners)
    seg = np.zeros(int(span.sum()), dtype=np.int64)
    s: dict = {}
    segment_errors(s, est[span], got, seg)
    assert s["horizontal_error_m_p95"] < 0.03  # the noise alone
    # the same truth read through a clock 35 ms off: 0.1 m at 3 m/s
    late = np.column_stack([np.interp(t_px4_us + 35_000.0, t_px4_us, gt[:, i]) for i in range(3)])
    segment_errors(s, est[span], late[span], seg)
    assert s["horizontal_error_m_p95"] > 0.09
    assert _px4_clock_truth({"vehicle_local_position": vlp}, span) is None  # no truth topic
