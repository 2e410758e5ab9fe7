"""The publisher (companion.service.publisher): centred ODOMETRY, poses stamped at sending."""

from __future__ import annotations

import numpy as np
from peers.mavlink_peers import decode

from companion.service.runtime import AutopilotKind
from companion.types import CameraFrame, PoseEstimate


def test_centred_odometry_after_a_pause_is_never_stamped_across_it(tmp_path, monkeypatch) -> None:
    """The service's ODOMETRY with centred velocity (the PX4 loop's output): through a pause
    in publishing (frames too old on a slow moment) no message carries a stamp reaching back
    over it. Before 18cc29a (2026-11-27) the first poses after a 2 s pause went out 1.0 s and 0.98 s
    old (the mean of a window over the pause), which PX4 SITL received 1.5 s old."""
    from peers import service_config

    from companion.service import app
    from companion.types import PoseEstimate

    service = app.Service(service_config(tmp_path, output="odometry", odometry_centre_frames=3))
    sent: list = []
    monkeypatch.setattr(service.link, "send", lambda m: sent.append((clock["ns"], m)) or True)
    clock = {"ns": 10_000_000_000}
    service.runtime.clock = lambda: clock["ns"]
    image = np.zeros((4, 4, 3), np.uint8)

    def frame_at(t_us: int) -> None:
        clock["ns"] = (t_us + 40_000) * 1000  # published 40 ms after its exposure
        p = np.array([1e-6 * t_us, 0.0, -5.0])  # 1 m/s north
        pose = PoseEstimate(
            t_us, p, np.array([1.0, 0, 0, 0]), np.full(3, np.nan), np.eye(6) * 1e-4, 0, 90
        )
        service.publisher.publish(CameraFrame(t_us, t_us // 50_000, image), pose)

    times = [10_000_000 + k * 50_000 for k in range(10)]  # 20 Hz
    times += [times[-1] + 2_000_000 + k * 50_000 for k in range(10)]  # after a 2 s pause
    for t in times:
        frame_at(t)
    odo = [(t_ns, m) for t_ns, m in sent if m.get_type() == "ODOMETRY"]
    # 2 frames before a full window, and again after the pause: 16 of the 20 are sent
    assert len(odo) == 16
    for t_ns, m in odo:  # stamped one frame before the newest exposure (sent 40 ms after it)
        assert t_ns / 1e3 - 40_000 - m.time_usec == 50_000
        assert abs(m.vx - 1.0) < 1e-6  # the velocity of a window inside one stretch


def test_centred_odometry_is_never_older_than_its_oldest_stamp(tmp_path, monkeypatch) -> None:
    """ODOMETRY centred on N poses leaves at most ``Config.oldest_stamp_ms`` old: the age
    limit (``service.stale_frame_ms``) plus (N - 1) / 2 frames, what `companion px4 check`
    holds EKF2's horizon to. A window over a skipped frame is centred further back: published
    near the age limit, it would reach past EKF2's horizon (one went out 275 ms old against
    236 ms, 2026-11-27), so such a window sends the newest pose with the window's velocity."""
    from peers import service_config

    from companion.service import app
    from companion.types import PoseEstimate

    cfg = service_config(
        tmp_path, output="odometry", odometry_centre_frames=3, stale_frame_ms=200.0
    )
    oldest_ms = cfg.oldest_stamp_ms()
    assert oldest_ms == 200.0 + 1000.0 / cfg.camera.rate_hz  # one frame back
    frame_us = round(1e6 / cfg.camera.rate_hz)
    service = app.Service(cfg)
    sent: list = []
    monkeypatch.setattr(service.link, "send", lambda m: sent.append((clock["ns"], m)) or True)
    clock = {"ns": 10_000_000_000}
    service.runtime.clock = lambda: clock["ns"]
    image = np.zeros((4, 4, 3), np.uint8)

    def frame_at(t_us: int, delay_us: int) -> None:
        clock["ns"] = (t_us + delay_us) * 1000
        p = np.array([1e-6 * t_us, 0.0, -5.0])  # 1 m/s north
        pose = PoseEstimate(
            t_us, p, np.array([1.0, 0, 0, 0]), np.full(3, np.nan), np.eye(6) * 1e-4, 0, 90
        )
        service.publisher.publish(CameraFrame(t_us, t_us // frame_us, image), pose)

    def odometry() -> list:
        return [(t_ns, m) for t_ns, m in sent if m.get_type() == "ODOMETRY"]

    t0 = 10_000_000
    # each published 190 ms after its exposure (inside the 200 ms limit); the fourth comes
    # after a skipped frame, so its window would be centred 4/3 frames back
    times = [t0, t0 + frame_us, t0 + 2 * frame_us, t0 + 4 * frame_us]
    for t_us in times:
        frame_at(t_us, 190_000)
    odo = odometry()
    assert len(odo) == 2  # ODOMETRY needs a velocity: none before the window is full
    assert all((t_ns / 1e3 - m.time_usec) / 1e3 <= oldest_ms for t_ns, m in odo)
    # the full window without a skip: centred one frame back
    assert odo[0][1].time_usec == times[1] and abs(odo[0][1].vx - 1.0) < 1e-6
    assert abs(odo[0][1].x - 1e-6 * times[1]) < 1e-9
    # the window over the skip: the newest pose, the window's velocity
    assert odo[1][1].time_usec == times[3] and abs(odo[1][1].vx - 1.0) < 1e-6
    assert abs(odo[1][1].x - 1e-6 * times[3]) < 1e-9
    # the same skip published promptly stays centred (its mean time, its velocity)
    frame_at(t0 + 5 * frame_us, 40_000)
    frame_at(t0 + 7 * frame_us, 40_000)
    _, m = odometry()[-1]
    assert m.time_usec == round((times[3] + 2 * t0 + 12 * frame_us) / 3)
    assert abs(m.vx - 1.0) < 1e-6


def test_poses_go_out_as_of_their_sending_while_px4_stamps_them_on_arrival(
    tmp_path, monkeypatch
) -> None:
    """PX4 stamps our samples with their arrival until its time sync has converged on ~500 of
    our answers, and again for as long after a jump of its clock (a stalled SIH: 187 ms in
    lawnmower 1 on 2026-11-28, 0.3-0.5 m of error at 3 m/s for 10 s). Meanwhile the service
    sends each pose carried to its sending and stamped then (ODOMETRY and
    VISION_POSITION_ESTIMATE); once its model of PX4's filter has converged, the exposure's
    stamp again; PX4's clock jumping puts it back. Off (``px4_stamp_at_send`` false), or with
    an autopilot that is not PX4: the exposure's stamp always."""
    from peers import service_config
    from pymavlink.dialects.v20 import common as mavlink

    from companion.service import app

    clock = {"ns": 0}

    def run(autopilot: str, **kw) -> tuple[list, list, app.Service]:
        """(per frame: (sent at its sending, PX4 converting as modelled)), messages, service"""
        cfg = service_config(tmp_path, output="both", odometry_centre_frames=3, **kw)
        service = app.Service(cfg)
        service.runtime.clock = lambda: clock["ns"]
        service.stats.autopilot_kind = AutopilotKind(autopilot)
        sent: list = []
        monkeypatch.setattr(service.link, "send", lambda m: sent.append((clock["ns"], m)) or True)
        px4 = mavlink.MAVLink(None, srcSystem=cfg.service.system_id, srcComponent=1)
        image = np.zeros((4, 4, 3), np.uint8)
        frames: list = []
        px4_offset_ns = -3_000_000_000  # PX4's clock 3 s behind ours

        def frame_at(t_us: int) -> None:
            # one of our own requests a frame, answered in 0.5 ms (our estimate of PX4's
            # clock, by which the model judges the round trips of PX4's)
            ts1 = t_us * 1000 - 5_000_000
            service.session.timesync_sent.append(ts1)
            clock["ns"] = ts1 + 500_000
            answer = mavlink.MAVLink_timesync_message(ts1 + 250_000 + px4_offset_ns, ts1)
            service.session.on_message(decode(answer.pack(px4)), clock["ns"])
            # PX4 asks at 50 Hz: 2-3 requests a frame at 20 Hz, answered at once
            for k in range(3 if (t_us // 50_000) % 2 else 2):
                clock["ns"] = t_us * 1000 + k * 17_000_000
                request = mavlink.MAVLink_timesync_message(0, clock["ns"] + px4_offset_ns)
                service.session.on_message(decode(request.pack(px4)), clock["ns"])
            clock["ns"] = (t_us + 40_000) * 1000  # published 40 ms after its exposure
            p = np.array([1e-6 * t_us, 0.0, -5.0])  # 1 m/s north
            v = np.array([1.0, 0.0, 0.0])
            pose = PoseEstimate(t_us, p, np.array([1.0, 0, 0, 0]), v, np.eye(6) * 1e-4, 0, 90)
            n = len(sent)
            converts = service.px4_stamps.converts
            service.publisher.publish(CameraFrame(t_us, t_us // 50_000, image), pose)
            for t_ns, m in sent[n:]:  # both messages: where the vehicle was at their stamp
                stamp_us = m.time_usec if m.get_type() == "ODOMETRY" else m.usec
                assert abs(m.x - 1e-6 * stamp_us) < 1e-6, m
                frames.append((stamp_us == t_ns // 1000, converts))

        t0 = 10_000_000
        for k in range(300):  # 15 s at 20 Hz: 750 requests answered
            frame_at(t0 + k * 50_000)
        px4_offset_ns -= 187_000_000  # the simulator stalled: PX4's clock fell behind
        for k in range(300, 320):
            frame_at(t0 + k * 50_000)
        return frames, sent, service

    frames, _, service = run("PX4")
    assert all(at_send == (not converts) for at_send, converts in frames), frames
    modelled = [converts for _, converts in frames]
    # 600 answers (240 frames) to converge, 6 answers (3 frames) after the jump to reset
    first = modelled.index(True)
    assert not any(modelled[:first]) and 230 < first // 2 < 250, first
    after = len(modelled) - 1 - max(i for i, c in enumerate(modelled) if c)
    assert all(modelled[first:-after]) and 2 * 17 <= after <= 2 * 18, after  # of 20 frames
    model = service.px4_stamps
    assert model.resets == 1 and not model.converts
    report = service.summary()
    assert report["px4_timesync_resets"] == 1 and report["px4_converts_stamps"] is False
    assert report["stamped_at_send"] == sum(1 for at_send, _ in frames if at_send) // 2 + 1
    for autopilot, kw in (("PX4", {"px4_stamp_at_send": False}), ("ArduPilot", {})):
        frames, _, service = run(autopilot, **kw)
        assert len(frames) > 600 and not any(at_send for at_send, _ in frames)
        assert service.stats.stamped_at_send == 0
