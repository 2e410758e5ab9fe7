"""Trajectories: smooth, within speed limits, multirotor-consistent attitude, patterns as named."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from companion.geometry import so3
from companion.sitl.world.terrain import World
from companion.sitl.world.trajectory import (
    BOB_MID_M,
    GRAVITY_M_S2,
    LANDED_HEIGHT_M,
    TRAJECTORIES,
    Trajectory,
)


@pytest.mark.parametrize("name", TRAJECTORIES)
def test_smooth_bounded_and_multirotor_consistent(
    name: str, world: Callable[[str, int], World]
) -> None:
    w = world("hills", 1)
    traj = Trajectory(name, w, 40.0, speed_m_s=4.0)
    dt = 0.001
    s = traj.sample(np.arange(0.0, 40.0, dt))
    # horizontal speed never exceeds cruise (Gaussian smoothing of a constant-speed path);
    # terrain following adds a little vertical speed
    assert np.linalg.norm(s.velocity_m_s[:, :2], axis=1).max() <= 4.0 + 1e-6
    assert np.linalg.norm(s.velocity_m_s, axis=1).max() <= 4.5
    # continuous acceleration: no jumps between 1 ms samples
    assert np.abs(np.diff(s.accel_m_s2, axis=0)).max() < 0.02
    # velocity is the derivative of position
    v_fd = np.diff(s.position_m, axis=0) / dt
    assert np.abs(v_fd - 0.5 * (s.velocity_m_s[1:] + s.velocity_m_s[:-1])).max() < 1e-3
    # thrust along body -z: the specific force has no body x/y component (a hand has none)
    f_body = np.einsum("nji,nj->ni", s.R_world_body, s.accel_m_s2 - [0, 0, GRAVITY_M_S2])
    if name != "handheld":
        assert np.abs(f_body[:, :2]).max() < 1e-9 and (f_body[:, 2] < 0).all()
    # a rotation matrix at every sample
    RtR = np.einsum("nji,njk->nik", s.R_world_body, s.R_world_body)
    assert np.abs(RtR - np.eye(3)).max() < 1e-9
    # body rates integrate to the attitude (the rate at the middle of the 10 ms step)
    for i in range(0, len(s.time_s) - 10, 4000):
        R_next = s.R_world_body[i] @ so3.exp(s.omega_body_rad_s[i + 5] * 10 * dt)  # midpoint
        assert so3.angle_between(R_next, s.R_world_body[i + 10]) < 1e-4
    # stays above the ground (bob: low indoors by design)
    agl = -s.position_m[:, 2] - w.surface_height(s.position_m[:, 0], s.position_m[:, 1])
    assert agl.min() > (0.3 if name == "bob" else 1.5)


def test_moving_patterns_reach_cruise_speed_and_head_along_track(
    world: Callable[[str, int], World],
) -> None:
    w = world("flat", 1)
    for name in ("circle", "lawnmower", "figure8"):
        s = Trajectory(name, w, 60.0, speed_m_s=3.0).sample(np.arange(5.0, 55.0, 0.1))
        speed = np.linalg.norm(s.velocity_m_s[:, :2], axis=1)
        assert speed.max() > 2.7  # the smoothing slows tight curves a little (circle: 2.87)
        cruising = speed > 2.5
        heading = np.arctan2(s.velocity_m_s[:, 1], s.velocity_m_s[:, 0])
        yaw = np.array([so3.matrix_to_rpy(R)[2] for R in s.R_world_body])
        err = np.angle(np.exp(1j * (yaw - heading)))[cruising]
        assert np.degrees(np.abs(err)).mean() < 10.0
        # accelerating forward pitches the nose down, roll/pitch follow acceleration
        tilt = np.degrees(np.arccos(s.R_world_body[:, 2, 2]))
        assert tilt.max() > 2.0


def test_hover_is_still(world: Callable[[str, int], World]) -> None:
    s = Trajectory("hover", world("hills", 1), 30.0).sample(np.arange(0, 30, 0.05))
    assert np.abs(s.velocity_m_s).max() < 1e-9
    assert np.ptp(s.position_m, axis=0).max() < 1e-9


def test_climb_goes_from_2_to_15_m_and_back(world: Callable[[str, int], World]) -> None:
    w = world("flat", 1)
    s = Trajectory("climb", w, 60.0).sample(np.arange(0, 60, 0.05))
    agl = -s.position_m[:, 2]
    assert abs(agl[0] - 2.0) < 0.05 and abs(agl[-1] - 2.0) < 0.05
    assert 14.0 < agl.max() <= 15.0


def test_takeoff_and_landing(world: Callable[[str, int], World]) -> None:
    w = world("slope", 1)
    traj = Trajectory("circle", w, 60.0, altitude_m=5.0, takeoff_landing=True)
    s = traj.sample(np.arange(0, 60.0 + 1e-9, 0.05))
    agl = -s.position_m[:, 2] - w.height(s.position_m[:, 0], s.position_m[:, 1])
    assert abs(agl[0] - LANDED_HEIGHT_M) < 0.05
    assert abs(agl[-1] - LANDED_HEIGHT_M) < 0.1
    assert 4.5 < agl.max() < 5.5
    assert np.linalg.norm(s.velocity_m_s[0]) < 0.05 and np.linalg.norm(s.velocity_m_s[-1]) < 0.05


def test_bob_goes_up_and_down_low_over_a_small_patch(world: Callable[[str, int], World]) -> None:
    """The real downward flight's motion (docs/RESULTS.md, "Real sequences"): 0.13-1.31 m,
    within a 0.3 x 0.7 m patch, about 0.5 m/s (22 m in ~45 s of flight)."""
    w = world("flat", 1)
    traj = Trajectory("bob", w, 60.0, altitude_m=6.0, takeoff_landing=True)  # altitude ignored
    s = traj.sample(np.arange(0, 60.0 + 1e-9, 0.01))
    agl = -s.position_m[:, 2]
    flying = (s.time_s > 10.0) & (s.time_s < 50.0)
    assert 0.25 < agl[flying].min() < 0.4 and 1.1 < agl[flying].max() < 1.3
    speed = np.linalg.norm(s.velocity_m_s[flying], axis=1)
    assert 0.3 < speed.mean() < 0.7
    assert np.ptp(s.position_m[:, 0]) < 0.4 and np.ptp(s.position_m[:, 1]) < 0.8
    # the nose stays put (a heading held by hand), on the ground at both ends
    yaw = np.array([so3.matrix_to_rpy(R)[2] for R in s.R_world_body[::50]])
    assert np.degrees(np.abs(yaw)).max() < 1.0  # the tilt's ZYX yaw: 0.4 deg
    assert abs(agl[0] - LANDED_HEIGHT_M) < 0.05 and abs(agl[-1] - LANDED_HEIGHT_M) < 0.1
    assert agl.max() < BOB_MID_M + 0.5


def test_handheld_turns_like_a_hand_in_place(world: Callable[[str, int], World]) -> None:
    """The real hand-held sequence's motion (docs/RESULTS.md, "Real sequences"): 64 deg/s
    median and 119 deg/s p95 about every axis, within a 0.15-0.19 m box."""
    w = world("hills", 1)
    traj = Trajectory("handheld", w, 24.0, altitude_m=1.2)
    s = traj.sample(np.arange(0.0, 24.0, 0.01))
    rate = np.degrees(np.linalg.norm(s.omega_body_rad_s, axis=1))
    turning = (s.time_s > 4.0) & (s.time_s < 20.0)
    assert 40.0 < np.median(rate[turning]) < 90.0 and 80.0 < np.percentile(rate, 95) < 150.0
    rpy = np.degrees(np.array([so3.matrix_to_rpy(R) for R in s.R_world_body]))
    assert (np.ptp(rpy, axis=0) > [50.0, 40.0, 90.0]).all()  # every axis turns
    assert np.ptp(s.position_m, axis=0).max() < 0.2
    speed = np.linalg.norm(s.velocity_m_s[turning], axis=1)
    assert 0.06 < speed.mean() < 0.14  # the real: 1.6-2.2 m of path in 24 s
    # still at both ends (the sines fade in and out)
    assert rate[0] < 1.0 and rate[-1] < 1.0
