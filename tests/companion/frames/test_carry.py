"""EKF2's lag behind our output before a GPS loss (companion.frames.carry), on seeded tracks.

The autopilot's estimate is the vehicle 0.11 s late (what EKF2 did in the real-PX4 flights
while it fused GNSS), sampled at 20 Hz with its own stamps; our output is the vehicle on time at
30 Hz. The offset must be -velocity x 0.11 s horizontally (z 0), averaged over the window only.
"""

from __future__ import annotations

import numpy as np
import pytest

from companion.frames.carry import MIN_SAMPLES, autopilot_offset

LAG_S = 0.11


def track(t_s: np.ndarray, speed_m_s: float, heading_rad: float) -> np.ndarray:
    """A straight leg at constant speed, 5 m up: (N, 3) NED [m]."""
    d = np.array([np.cos(heading_rad), np.sin(heading_rad), 0.0])
    return np.outer(t_s * speed_m_s, d) + np.array([3.0, -2.0, -5.0])


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_offset_is_the_lag_times_the_velocity(seed: int) -> None:
    rng = np.random.default_rng(seed)
    speed, heading = rng.uniform(0.5, 4.0), rng.uniform(-np.pi, np.pi)
    t_out = np.arange(0.0, 3.0, 1 / 30)
    out = track(t_out, speed, heading) + rng.normal(0, 0.005, (len(t_out), 3))
    t_ap = np.arange(0.013, 3.0, 1 / 20)  # its own stamps, not ours
    ap = track(t_ap - LAG_S, speed, heading)
    ap[:, 2] += 0.3  # its height is its own: not carried
    offset = autopilot_offset(
        (t_ap * 1e6).astype(np.int64), ap, (t_out * 1e6).astype(np.int64), out, 2_900_000, 500_000
    )
    assert offset is not None
    want = -speed * LAG_S * np.array([np.cos(heading), np.sin(heading)])
    assert np.allclose(offset[:2], want, atol=0.01), (offset, want)
    assert offset[2] == 0.0


def test_only_the_window_before_the_loss_counts() -> None:
    t_out = np.arange(0.0, 4.0, 1 / 30)
    out = np.zeros((len(t_out), 3))
    t_ap = np.arange(0.0, 4.0, 1 / 20)
    ap = np.zeros((len(t_ap), 3))
    ap[t_ap > 2.0, 0] = 0.4  # the autopilot 0.4 m north after 2 s
    ap[t_ap > 3.0, 0] = 9.0  # after the loss (3 s): not looked at
    us = lambda t: (t * 1e6).astype(np.int64)  # noqa: E731
    offset = autopilot_offset(us(t_ap), ap, us(t_out), out, 3_000_000, 500_000)
    assert offset is not None and offset[0] == pytest.approx(0.4) and offset[1] == 0.0
    offset = autopilot_offset(us(t_ap), ap, us(t_out), out, 3_000_000, 2_000_000)
    assert offset is not None and 0.0 < offset[0] < 0.4  # half of a 2 s window at 0.4 m


def test_too_few_samples_outside_our_span_or_not_finite_give_none() -> None:
    t_out = np.array([1_000_000, 1_033_000, 1_066_000, 1_100_000])
    out = np.zeros((4, 3))
    few = np.array([1_040_000] * (MIN_SAMPLES - 1))
    assert autopilot_offset(few, np.zeros((len(few), 3)), t_out, out, 1_100_000, 500_000) is None
    before = np.array([500_000, 600_000, 700_000, 900_000])  # before our first output
    assert autopilot_offset(before, np.zeros((4, 3)), t_out, out, 1_100_000, 900_000) is None
    inside = np.array([1_010_000, 1_040_000, 1_070_000])
    nan = np.zeros((3, 3))
    nan[1, 0] = np.nan
    assert autopilot_offset(inside, nan, t_out, out, 1_100_000, 500_000) is None
    assert autopilot_offset(inside, np.ones((3, 3)), t_out[:1], out[:1], 1_100_000, 500_000) is None
    assert autopilot_offset(inside, np.ones((3, 3)), t_out, out, 1_100_000, 500_000) is not None
