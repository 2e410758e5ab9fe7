"""The Pipeline from the ground up (issue 18) and its frozen status snapshot: seeded SITL
flights that start on the ground, a metric map without parallax, a climb without a reset."""

from __future__ import annotations

import numpy as np
import pytest

from companion.config import load_config
from companion.geometry import se3, so3
from companion.offline import feed_step
from companion.pipeline import Pipeline, PipelineStatus
from companion.sitl.world.scenario import Scenario
from companion.types import AttitudeSample, CameraFrame, VoState


def _ground_flight(seconds: float, terrain: str = "hills", **extra: object):
    sitl = {"terrain": terrain, "trajectory": "hover", "seconds": seconds, "seed": 3}
    sitl["takeoff_landing"] = True
    over: dict = {"sitl": sitl, **extra}
    cfg = load_config(None, over)
    return cfg, Scenario(cfg)


def test_the_map_starts_metric_on_the_ground_within_one_percent() -> None:
    """At rest on the ground (no parallax at all), the first frames give a tracking VO whose
    unit is the metre: its points' depths against the ray-cast truth agree to 1 %."""
    cfg, sc = _ground_flight(6.0)
    p = Pipeline(cfg)
    first_pose_s = None
    ratios = []
    for k, st in enumerate(sc.steps()):
        pose = feed_step(p, st)
        p.background_work()
        if pose is not None and first_pose_s is None:
            first_pose_s = k / cfg.camera.rate_hz
            assert (
                np.allclose(pose.velocity_ned_m_s, 0.0, atol=0.05)
                or np.isnan(pose.velocity_ned_m_s).all()
            )
        out = p.vo_output
        if out is not None and out.state == VoState.TRACKING and k in (3, 20, 40):
            f = out.features
            has = f.point_ids >= 0
            z_vo = se3.transform(se3.inverse(out.T_vo_cam), f.points_vo[has])[:, 2]
            T_world_cam = st.T_world_body @ p.T_body_cam
            rays = p.camera.pixels_to_rays(f.pixels[has])
            hits = sc.world.raycast(
                np.repeat(T_world_cam[None, :3, 3], len(rays), axis=0), rays @ T_world_cam[:3, :3].T
            )
            z_true = (rays * hits.t_m[:, None])[:, 2]
            ratios.append(float(np.median(z_true / z_vo)))
        if k >= 45:  # still on the ground (take-off starts at 3.5 s)
            break
    assert first_pose_s is not None and first_pose_s <= 0.2  # well within the 2 s asked
    assert p.vo.resets == 0 and p.vo.metric_sigma_rel is not None
    assert len(ratios) == 3 and all(abs(r - 1.0) <= 0.01 for r in ratios), ratios


def test_no_reset_through_a_climb_to_six_metres_and_the_position_follows() -> None:
    """Take-off from 0.25 m to 6 m (the scene's scale changes thirty-fold): tracking on every
    frame, no VO reset, the published climb within 10 cm of the truth."""
    cfg, sc = _ground_flight(30.0)  # on the ground 3.5 s, at 6 m from about 8 s
    p = Pipeline(cfg)
    est, gt, states = [], [], []
    for k, st in enumerate(sc.steps()):
        if k >= 10 * cfg.camera.rate_hz:
            break
        pose = feed_step(p, st)
        p.background_work()
        states.append(p.vo_output.state if p.vo_output is not None else None)
        if pose is not None:
            est.append(pose.position_ned_m)
            gt.append(st.T_world_body[:3, 3].copy())
    est_a, gt_a = np.array(est), np.array(gt)
    climbed = gt_a[:, 2].max() - gt_a[:, 2].min()
    err = np.linalg.norm((est_a - est_a[0]) - (gt_a - gt_a[0]), axis=1)
    assert climbed > 5.0, climbed
    assert p.vo.resets == 0
    assert all(s == VoState.TRACKING for s in states[5:]), states.count(VoState.LOST)
    assert len(est) >= len(states) - 3
    assert err.max() <= 0.10, err.max()


def test_sensors_below_their_minimum_start_on_the_landing_gear_height() -> None:
    """Sensors that read less than their minimum on the ground (0.19 m < 0.3 m) are refused
    as readings, not fatal; with the landing-gear height configured the map starts on it."""
    rfs = [
        {"sensor_id": i, "mount": {"xyz_m": xyz, "rpy_deg": [0.0, 0.0, 0.0]}, "min_m": 0.3}
        for i, xyz in enumerate([[0.25, 0.1, 0.06], [-0.08, 0.27, 0.06], [-0.24, -0.12, 0.06]])
    ]
    cfg, sc = _ground_flight(2.0, terrain="flat", rangefinders=rfs)
    p = Pipeline(cfg)
    for k, st in enumerate(sc.steps()):
        feed_step(p, st)
        if k == 20:
            break
    assert p.vo.state != VoState.TRACKING  # no plane: waits for parallax (the default)
    assert p.ranges.rejected > 0 and len(p.ranges.too_close_us) == 3
    cfg2, sc2 = _ground_flight(
        2.0, terrain="flat", rangefinders=rfs, vo={"landed_camera_height_m": 0.17}
    )
    p2 = Pipeline(cfg2)
    tracking_at = None
    for k, st in enumerate(sc2.steps()):
        feed_step(p2, st)
        if p2.vo.state == VoState.TRACKING and tracking_at is None:
            tracking_at = k
        if k == 20:
            break
    assert tracking_at is not None and tracking_at <= 10
    R = p2.attitude_at(sc2.frame_time_us(20))
    plane = p2.ground.ground_plane(sc2.frame_time_us(20), R)
    assert plane is not None and plane.source == "landed"
    assert plane.distance_m == pytest.approx(0.17)


def test_the_status_snapshot_is_frozen_and_follows_the_pipeline() -> None:
    cfg, sc = _ground_flight(1.0)
    p = Pipeline(cfg)
    before = p.status()
    assert isinstance(before, PipelineStatus) and before.vo_state == "INITIALIZING"
    for k, st in enumerate(sc.steps()):
        feed_step(p, st)
        if k == 5:
            break
    after = p.status()
    assert after.vo_state == "TRACKING" and after.keyframes >= 1 and after.scale == 1.0
    assert before.vo_state == "INITIALIZING"  # an old snapshot never changes
    assert after.frames_refused == ()
    last = st.frame
    for dt_us, image in ((1, last.image_bgr), (2, last.image_bgr), (3, 0 * last.image_bgr)):
        p.feed_frame(CameraFrame(last.time_us + dt_us, last.seq + dt_us, image))
    p.feed_frame(last)  # its time again: out of order
    # the frame check's verdicts, as a status display shows them (a repeated image: frozen)
    assert p.status().frames_refused == (("out_of_order", 1), ("frozen", 2), ("dark", 1))
    assert after.frames_refused == ()
    with pytest.raises(AttributeError):
        after.vo_state = "LOST"  # type: ignore[misc]


@pytest.mark.parametrize("autopilot_yaw_deg", [None, 0.0, 30.0, -150.0])
def test_the_vo_frame_takes_the_autopilots_heading_at_its_start(
    autopilot_yaw_deg: float | None,
) -> None:
    """The published frame's north is the autopilot's: the VO's frame gets the heading of the
    autopilot's attitude at initialisation (here the true one turned by a constant, as a
    magnetometer with a declination would give it), and says when it had none (heading 0 =
    the camera's first, the autopilot's frame turned against ours: docs/decisions.md)."""
    cfg, sc = _ground_flight(1.0)
    p = Pipeline(cfg)
    R_turn = so3.rot_z(np.radians(autopilot_yaw_deg or 0.0))
    pose = None
    for k, st in enumerate(sc.steps()):
        if autopilot_yaw_deg is not None:
            for a in st.attitudes:
                R = R_turn @ so3.quat_to_matrix(a.quat_wxyz)
                p.feed_attitude(AttitudeSample(a.time_us, so3.matrix_to_quat(R), a.rates_rad_s))
        for r in st.ranges:
            if r.sample is not None:
                p.feed_range(r.sample)
        pose = p.feed_frame(st.frame) or pose
        if k == 8:
            break
    assert pose is not None
    heading = p.status().vo_heading_deg
    yaw_sent_deg = np.degrees(so3.matrix_to_rpy(so3.quat_to_matrix(pose.quat_wxyz_ned_frd))[2])
    if autopilot_yaw_deg is None:
        assert heading is None
        assert abs(yaw_sent_deg) < 1.0  # the camera's first heading is our north
    else:
        assert heading is not None and abs(heading - autopilot_yaw_deg) < 0.5, heading
        wrapped = (yaw_sent_deg - autopilot_yaw_deg + 180.0) % 360.0 - 180.0
        assert abs(wrapped) < 1.0, (yaw_sent_deg, autopilot_yaw_deg)


def test_dpose_pins_the_published_position_to_the_pad_when_it_is_back_in_view() -> None:
    """Take off, hover at 3 m (d-Pose armed there on 0.4 s of averaged ranges, its four
    marks left on the ground), fly a 12 m square out of their view and back, hover: while the
    marks are in view again the published position is d-Pose's (relative to the arming pose,
    within 2 cm RMS), while the VO's own position has drifted further; big corrections come
    with a new reset_counter."""
    import dataclasses

    from companion.config import dpose_rangefinders

    cfg = load_config(
        None,
        {
            "sitl": {"terrain": "hills", "trajectory": "pad", "seconds": 40.0, "seed": 1},
            "dpose": {"enabled": True, "arm_after_s": 8.0},
        },
    )
    cfg = dataclasses.replace(
        cfg,
        rangefinders=dpose_rangefinders(),
        sitl=dataclasses.replace(
            cfg.sitl,
            takeoff_landing=True,
            altitude_m=3.0,
            render=dataclasses.replace(cfg.sitl.render, laser_marks="painted", painted_time_s=8.0),
        ),
    )
    sc = Scenario(cfg)
    p = Pipeline(cfg)
    rows = []
    for st in sc.steps(workers=2):  # rendered ahead on 2 threads (identical steps)
        used = p.dpose_stage.offset.updates
        pose = feed_step(p, st)
        p.background_work()
        if pose is not None:
            vo_own = pose.position_ned_m - p.dpose_stage.offset.offset_m
            rows.append((st.frame.time_us * 1e-6, pose, vo_own, st.T_world_body[:3, 3].copy()))
            rows[-1] += (p.dpose_stage.offset.updates > used,)
    t = np.array([r[0] for r in rows])
    pub = np.array([r[1].position_ned_m for r in rows])
    own = np.array([r[2] for r in rows])
    gt = np.array([r[3] for r in rows])
    in_view = np.array([r[4] for r in rows]) & (t > 20.0)  # back over the pad
    i = int(np.searchsorted(t, 8.0))  # the arming window's start: the pattern's reference

    def err(x: np.ndarray) -> np.ndarray:
        return np.linalg.norm((x - x[i]) - (gt - gt[i]), axis=1)

    assert p.dpose_stage.armed and in_view.sum() >= 60
    e_pub, e_own = err(pub)[in_view], err(own)[in_view]
    # 0.50 cm with the autopilot's attitude averaged over the arming window; 0.86 cm with its
    # one sample at the window's start (its noise a bias of every d-Pose position)
    assert float(np.sqrt(np.mean(e_pub**2))) <= 0.008, e_pub
    # issue 18: every pose while the marks are in view, the first frames back included (the
    # vehicle still braking from 1.8 m/s: 1.68 cm, 1.98 cm with the one attitude sample)
    assert float(np.max(e_pub)) <= 0.02, e_pub
    assert np.mean(e_pub) < np.mean(e_own)  # the drift the VO had is gone
    resets = {r[1].reset_counter for r in rows}
    # the VO comes back ~10 cm off: beyond dpose.reset_m, so with a new reset_counter (with
    # vo.axial_gravity_sigma_deg 0.5, not the default, it came back within 2.1-2.7 cm and
    # needed none)
    assert 1 <= p.dpose_stage.offset.resets <= 5 and len(resets) == p.dpose_stage.offset.resets + 1


def test_the_attitude_at_a_time_is_the_slerp_of_the_samples_around_it() -> None:
    """Pipeline.attitude_at searches from the newest sample: at, between, before and after the
    samples it gives the rotation between the bracketing two (the geodesic at the time's
    fraction), the nearest one within ATTITUDE_MAX_GAP_US past either end or across a gap of
    more than ATTITUDE_MAX_SPAN_US (a stall), else None."""
    from companion.pipeline import ATTITUDE_MAX_GAP_US

    rng = np.random.default_rng(8)
    pipe = Pipeline(load_config(None))
    times = np.cumsum(rng.integers(2_000, 20_000, 600)) + 1_000_000
    Rs = [so3.rpy_to_matrix(*rng.normal(0.0, 0.3, 3)) for _ in times]
    for t, R in zip(times, Rs, strict=True):
        pipe.feed_attitude(AttitudeSample(int(t), so3.matrix_to_quat(R), np.zeros(3)))
    kept = times[-512:]  # the buffer holds the last 512
    R_kept = Rs[-512:]
    for _ in range(200):
        i = int(rng.integers(0, len(kept) - 1))
        a = float(rng.choice([0.0, rng.uniform(), 1.0]))
        t = int(round(kept[i] + a * (kept[i + 1] - kept[i])))
        a = (t - kept[i]) / (kept[i + 1] - kept[i])
        want = R_kept[i] @ so3.exp(a * so3.log(R_kept[i].T @ R_kept[i + 1]))
        got = pipe.attitude_at(t)
        assert got is not None and np.allclose(got, want, atol=1e-9), (i, a)
    after = pipe.attitude_at(int(kept[-1]) + ATTITUDE_MAX_GAP_US)
    assert after is not None and np.allclose(after, R_kept[-1], atol=1e-9)
    assert pipe.attitude_at(int(kept[-1]) + ATTITUDE_MAX_GAP_US + 1) is None
    before = pipe.attitude_at(int(kept[0]) - 5_000)
    assert before is not None and np.allclose(before, R_kept[0], atol=1e-9)
    # a stall: the stream resumes 2 s later; no rotation is made up across the gap
    t_gap = int(kept[-1]) + 2_000_000
    R_gap = so3.rpy_to_matrix(0.0, 0.0, 2.5)
    pipe.feed_attitude(AttitudeSample(t_gap, so3.matrix_to_quat(R_gap), np.zeros(3)))
    assert pipe.attitude_at(int(kept[-1]) + 1_000_000) is None
    near_end = pipe.attitude_at(int(kept[-1]) + 60_000)
    assert near_end is not None and np.allclose(near_end, R_kept[-1], atol=1e-9)
    near_new = pipe.attitude_at(t_gap - 60_000)
    assert near_new is not None and np.allclose(near_new, R_gap, atol=1e-9)


def _heading_error_deg(pose, R_world_body) -> float:
    yaw_sent = so3.matrix_to_rpy(so3.quat_to_matrix(pose.quat_wxyz_ned_frd))[2]
    yaw_true = so3.matrix_to_rpy(R_world_body)[2]
    return float(np.degrees(abs(np.remainder(yaw_sent - yaw_true + np.pi, 2 * np.pi) - np.pi)))


@pytest.mark.parametrize("stall_s", [2.0, 5.0])
def test_after_a_stall_the_new_map_takes_the_autopilots_heading_and_continues(
    stall_s: float,
) -> None:
    """A stalled process (SIGSTOP) wakes to a camera backlog and a link backlog that arrive in
    any order: here the attitudes of the first 0.4 s after the stall reach the pipeline after
    the frames of that time, so no attitude is at hand when the VO starts its new map. That
    map must not take the camera's heading as north (it did: every later pose turned by the
    vehicle's heading, -172 to -180 deg after a stall over a 180 deg heading, a fly-away with
    EKF2 fusing our yaw). The autopilot's frame is turned 150 deg from the world's (a compass with
    a declination), so a map on the camera's heading is 150 deg off. Every pose of every map:
    heading within 2 deg of the autopilot's; the first pose after the stall continues from
    the last one before it (a new reset_counter)."""
    sitl = {"terrain": "hills", "trajectory": "lawnmower", "seconds": 16.0 + stall_s, "seed": 2}
    cfg = load_config(None, {"sitl": sitl, **_small_camera()})
    sc = Scenario(cfg)
    p = Pipeline(cfg)
    R_turn = so3.rot_z(np.radians(150.0))
    stall_us = (int(7e6), int((7.0 + stall_s) * 1e6))
    backlog_us = 400_000  # the attitudes of this long after the stall arrive after its frames
    waiting: list[AttitudeSample] = []
    errors_deg: dict[int, list[float]] = {}
    before_after: list = []
    for st in sc.steps():
        t = st.frame.time_us
        if stall_us[0] <= t < stall_us[1]:
            continue  # the process was stopped: nothing came in
        for a in st.attitudes:
            if stall_us[0] <= a.time_us < stall_us[1]:
                continue
            R = R_turn @ so3.quat_to_matrix(a.quat_wxyz)
            waiting.append(AttitudeSample(a.time_us, so3.matrix_to_quat(R), a.rates_rad_s))
        backlog = stall_us[1] <= t < stall_us[1] + backlog_us  # attitudes not in yet
        while waiting and not backlog and waiting[0].time_us <= t:
            p.feed_attitude(waiting.pop(0))
        for r in st.ranges:
            if r.sample is not None:
                p.feed_range(r.sample)
        pose = p.feed_frame(st.frame)
        p.background_work()
        if pose is None:
            continue
        R_true = R_turn @ st.T_world_body[:3, :3]
        errors_deg.setdefault(pose.reset_counter, []).append(_heading_error_deg(pose, R_true))
        if t < stall_us[0] or len(before_after) < 2:  # the last pose before, the first after
            before_after[int(t >= stall_us[0]) :] = [(t, pose.reset_counter, pose.position_ned_m)]
    assert p.vo.resets >= 1 and len(errors_deg) >= 2, (p.vo.resets, errors_deg.keys())
    assert p.held_for_attitude > 0  # the race happened: frames with no attitude at hand
    worst = {rc: max(e) for rc, e in errors_deg.items()}
    assert all(w <= 2.0 for w in worst.values()), worst
    counts = {rc: len(e) for rc, e in errors_deg.items()}
    assert all(n >= 30 for n in counts.values()), counts
    (t0, rc0, p0), (t1, rc1, p1) = before_after
    assert t0 < stall_us[0] <= t1 and rc1 != rc0
    assert np.linalg.norm(p1 - p0) < 0.05, (p0, p1)  # continued from the last one sent


def _small_camera() -> dict:
    from peers import small_camera

    return small_camera()


def test_the_pipeline_holds_frames_for_the_autopilots_attitude_then_goes_without() -> None:
    """Pipeline.hold_for_attitude (the service's wait rule, 2026-11-28 in the pipeline): with
    an autopilot but no attitude yet, frames are held from a VO that has not started, up to
    service.attitude_wait_s after the first one held; an attitude at hand ends the wait;
    without an autopilot (a replay) nothing is held. Samples of every kind go in by feed."""
    from companion.types import CameraFrame, RangeSample

    cfg = load_config(None, {"service": {"attitude_wait_s": 2.0}})
    image = np.zeros((4, 4, 3), np.uint8)
    t0 = 5_000_000_000
    frames = [CameraFrame(t0 + k * 100_000, k, image) for k in range(40)]  # 10 Hz, 4 s
    p = Pipeline(cfg)
    assert p.hold_for_attitude(frames[0], autopilot_seen=False) is False
    held = [p.hold_for_attitude(f, autopilot_seen=True) for f in frames]
    assert held == [True] * 21 + [False] * 19  # frame 20 exactly at the limit
    assert p.waited_for_attitude == 21 and p.status().waited_for_attitude == 21

    late = Pipeline(cfg)
    assert late.hold_for_attitude(frames[0], autopilot_seen=True) is True
    q = np.array([1.0, 0.0, 0.0, 0.0])
    late.feed(AttitudeSample(frames[1].time_us - 5_000, q, np.zeros(3)))
    assert late.vo.heading_required
    assert late.hold_for_attitude(frames[1], autopilot_seen=True) is False  # at hand
    assert late.hold_for_attitude(frames[15], autopilot_seen=True) is True  # too far
    late.feed(RangeSample(frames[1].time_us, 99, 1.0, 0.1, 12.0, 0))  # no such sensor: dropped
    assert late.ranges.rejected == 1

    off = Pipeline(load_config(None, {"service": {"attitude_wait_s": 0.0}}))
    assert off.hold_for_attitude(frames[0], autopilot_seen=True) is False


def test_a_pose_goes_out_on_the_frame_befores_scale_and_tilt_and_its_own_update_follows() -> None:
    """The frame's own scale and roll/pitch update is work after its pose: at a map's first
    tracked frame it runs before the pose (the estimate is the frame's); on every later
    frame of the map the pose takes the frame before's estimate and roll/pitch, and the
    frame's update comes with background_work (or, without it, first in the next frame);
    the published position moves by the VO's motion at the scale of the frame before."""
    cfg, sc = _ground_flight(3.0)
    p = Pipeline(cfg)
    first, deferred, by_next_frame = 0, 0, 0
    last = None  # (time_us, the pose's metric position, camera VO position, lever arm)
    for k, st in enumerate(sc.steps()):
        pose = feed_step(p, st)
        out = p.vo_output
        if out is None or out.state != VoState.TRACKING:
            continue
        est = p.estimates[p.method_name]
        position = p.metric_positions[p.method_name]
        lever = out.T_vo_cam[:3, :3] @ p.T_cam_body[:3, 3]
        assert est is not None and pose is not None and position is not None
        if last is None:  # the map's first frame: its update ran before the pose
            first += 1
            assert est.time_us == st.frame.time_us and p.tilt is not None
            assert p.pose_tilt is p.tilt
        else:
            deferred += 1
            time_us, position_before, c_vo_before, lever_before = last
            assert est.time_us == time_us  # the frame before's
            assert p.tilt is None and p.pose_tilt is not None
            moved = est.scale * (out.T_vo_cam[:3, 3] - c_vo_before) + lever - lever_before
            assert np.allclose(position - position_before, moved, rtol=0, atol=1e-12)
        if k % 2:  # the service's order: the update after the pose
            p.background_work()
            assert p.background_laps.ms.keys() >= {"scale update", "roll/pitch update"}
            new = p.estimates[p.method_name]
            assert new is not None and new.time_us == st.frame.time_us
            assert p.tilt is not None and p.pose_tilt is p.tilt
        elif last is not None:
            by_next_frame += 1  # the next feed_frame runs this frame's update first
        last = (st.frame.time_us, position.copy(), out.T_vo_cam[:3, 3].copy(), lever)
    assert first == 1 and deferred >= 60 and by_next_frame >= 30
