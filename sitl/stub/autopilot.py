"""A PX4-like autopilot for software-in-the-loop runs (``companion sitl run``).

It plays PX4 SITL's onboard MAVLink instance on 127.0.0.1: it sends to UDP 14540 and listens
on 14580, as system 1 component 1 (MAV_AUTOPILOT_PX4, MAV_TYPE_QUADROTOR), and serves the
simulated camera on a TCP loopback stream (format in :mod:`drivers.camera`).

- Time scale: ``time_scale`` flight seconds pass per wall-clock second (1: real time; 0.5: a
  slow-motion flight for a host that cannot keep up with the camera, as `companion sitl run
  --time-scale` and the tests on a slow machine fly it). The world, the vehicle, the camera's
  frames and the sensors' readings all run slower (a 30 Hz camera sends 15 frames a second,
  the body rates in ATTITUDE are per wall-clock second); the autopilot's own clock, its
  streams, time sync and the link keep real time. Flight times (``t_sim``, fault windows)
  are flight seconds.
- Clock: its own boot clock, ``time_boot = (t_mono - t_boot) * (1 + drift_ppm 1e-6)``, started
  ``boot_offset_s`` before the process and drifting against the companion's monotonic clock, so
  that time sync is really needed.
- TIMESYNC: requests (tc1 = 0, ts1 = its clock in ns) as a stream, 10 Hz until asked for
  another rate (PX4's TIMESYNC stream on an onboard link); the companion's answers feed a
  :class:`ClockSync` (PX4's filter does the same: rtt gate, converging gain, reset after
  successive outliers); requests from the companion are answered at once.
- Streams: HEARTBEAT 1 Hz, ATTITUDE (truth + 0.1 deg noise) and DISTANCE_SENSOR for every
  sensor (cm, orientation 25, its id, the world's noise model), each at 10 Hz until the
  companion asks for another rate.
- With ``gps``: GPS_RAW_INT (5 Hz) and GPS_GLOBAL_ORIGIN (1 Hz) from the truth in its GPS
  frame, without a fix during a ``gps_loss`` fault (:mod:`companion.sitl.stub.gps`).
- MAV_CMD_SET_MESSAGE_INTERVAL as PX4's receiver answers it (COMMAND_ACK): for a stream it
  has (TIMESYNC, ATTITUDE, DISTANCE_SENSOR) ACCEPTED, the interval in us setting the rate (0:
  its default rate, < 0: stopped); for HEARTBEAT or a message it does not stream FAILED.
- Camera: a child process renders the flight ahead of time and releases frame k at its
  exposure time plus ``readout_ms`` (a real camera delivers a frame after its readout); a
  frame that is not ready in time is dropped and counted, as a camera would drop it
  (:mod:`companion.sitl.stub.camera`).
- Receives STATUSTEXT (kept in ``stats.statustexts``, forwarded to the ground-station endpoint
  as PX4 forwards an onboard link's messages with ``mavlink start -f``).
- Receives VISION_POSITION_ESTIMATE and ODOMETRY, moves their time_usec into its clock through
  its time sync (as PX4's mavlink_receiver does), looks up the true pose at that time and
  keeps live errors; at the end writes ``report.json``, ``received.csv`` and ``autopilot.png``
  (:mod:`companion.sitl.stub.report`).

Options: :mod:`companion.sitl.stub.options`; PX4's parameters, EV fusion, shell and the
ground-station endpoint: :mod:`companion.sitl.stub.px4_services`.
"""

from __future__ import annotations

import asyncio
import multiprocessing as mp
import time
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from companion.config import Config, to_dict
from companion.drivers.mavlink_parser import Parser
from companion.drivers.signing import Signing
from companion.drivers.timesync import ClockSync, reply_for
from companion.errors import SitlError
from companion.evaluation.trajectory import umeyama
from companion.geometry import so3
from companion.sitl.stub import gps
from companion.sitl.stub.camera import camera_process
from companion.sitl.stub.faults import active
from companion.sitl.stub.options import AutopilotOptions
from companion.sitl.stub.px4_services import Px4Services
from companion.sitl.stub.report import (
    AutopilotStats,
    Received,
    flight_report,
    main_kind,
    write_report,
)

MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_RESULT_ACCEPTED, MAV_RESULT_FAILED = 0, 4
MSG_ATTITUDE = 30
MSG_TIMESYNC = 111
MSG_DISTANCE_SENSOR = 132
# the streams whose rate MAV_CMD_SET_MESSAGE_INTERVAL sets, at their default rates [Hz] (PX4's
# onboard link: TIMESYNC at 10 Hz, mavlink_main.cpp's configure_stream_local)
DEFAULT_RATES_HZ = {MSG_ATTITUDE: 10.0, MSG_TIMESYNC: 10.0, MSG_DISTANCE_SENSOR: 10.0}


class SimAutopilot:
    """The stub: ``await SimAutopilot(cfg, opts).run(out_dir)``."""

    def __init__(self, cfg: Config, opts: AutopilotOptions | None = None) -> None:
        from companion.sitl.world.sensors import RangeSimulator
        from companion.sitl.world.terrain import make_world
        from companion.sitl.world.trajectory import Trajectory

        self.cfg = cfg
        self.opts = opts or AutopilotOptions()
        if not 0.0 < self.opts.time_scale <= 1.0:
            raise SitlError(f"time_scale {self.opts.time_scale}: must be in (0, 1]")
        s = cfg.sitl
        opts_gps = self.opts.gps
        self.world = make_world(s.terrain, s.seed, s.world_size_m, s.height_resolution_m, s.ground)
        self.trajectory = Trajectory(
            s.trajectory, self.world, s.seconds, s.altitude_m, s.speed_m_s, s.takeoff_landing
        )
        self.ranges = RangeSimulator(
            self.world, self.trajectory, cfg.rangefinders, s.seed, s.rangefinder
        )
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.parser = Parser()
        self.signing: Signing | None = None
        if self.opts.signing_key:  # as PX4 with a key: signs everything, refuses unsigned
            self.signing = Signing(self.opts.signing_key, None, 1, self.opts.require_signed)
            self.signing.apply(self.mav, self.parser.mav)
            self.parser.signing_state = self.mav.signing
        self.sync = ClockSync()
        self.stats = AutopilotStats()
        now = time.monotonic_ns()
        self.boot_ns = now - int(self.opts.boot_offset_s * 1e9)
        self.flight_start_ns = now + int(self.opts.warmup_s * 1e9)
        self.default_rates_hz = {**DEFAULT_RATES_HZ, **(gps.DEFAULT_RATES_HZ if opts_gps else {})}
        self.rates_hz = dict(self.default_rates_hz)  # 0: stopped
        self.gps_noise = gps.GpsNoise(self.opts.gps_noise_m, gps.NOISE_TAU_S, s.seed)
        self._transport: asyncio.DatagramTransport | None = None
        self._rng = np.random.default_rng([s.seed, 404])
        self.px4 = Px4Services(self)  # parameters, EV fusion, shell, ground-station endpoint

    # ------------------------------------------------------------------ clocks
    def clock_ns(self, mono_ns: int) -> int:
        """Our boot clock [ns] at a monotonic instant."""
        return int((mono_ns - self.boot_ns) * (1.0 + self.opts.drift_ppm * 1e-6))

    def mono_of_clock_ns(self, clock_ns: float) -> float:
        """The monotonic instant [ns] of a boot-clock time (the exact inverse)."""
        return clock_ns / (1.0 + self.opts.drift_ppm * 1e-6) + self.boot_ns

    def t_sim_of_mono(self, mono_ns: float) -> float:
        """Flight time [s] at a monotonic instant [ns] (scaled by ``time_scale``)."""
        return (mono_ns - self.flight_start_ns) * 1e-9 * self.opts.time_scale

    @property
    def end_s(self) -> float:
        """The flight's end [s of flight time]: the scenario's, or ``opts.end_s`` before it."""
        s = self.cfg.sitl.seconds
        return min(s, self.opts.end_s) if self.opts.end_s > 0 else s

    def mono_of_t_sim(self, t_sim_s: float) -> int:
        """The monotonic instant [ns] of a flight time [s] (the exact inverse)."""
        return self.flight_start_ns + int(round(t_sim_s * 1e9 / self.opts.time_scale))

    # ------------------------------------------------------------------ I/O
    def silent(self) -> bool:
        """A link fault (cable out, rebooting) is on: nothing is sent or heard."""
        t = self.t_sim_of_mono(time.monotonic_ns())
        return bool(active(self.opts.faults, t) & {"link_silence", "autopilot_reboot"})

    def send(self, msg: Any) -> None:
        if self._transport is None or self.silent():
            return
        try:
            buf = msg.pack(self.mav)
            self.mav.seq = (self.mav.seq + 1) % 256
            self._transport.sendto(buf, (self.opts.host, self.opts.companion_port))
            self.stats.link.tx_messages += 1
        except OSError:
            self.stats.link.tx_dropped += 1

    def _on_datagram(self, data: bytes) -> None:
        rx_ns = time.monotonic_ns()
        if self.silent():
            return
        for msg in self.parser.feed(data, self.stats.link, datagram=True):
            self._on_message(msg, rx_ns)

    def _on_message(self, msg: Any, rx_ns: int) -> None:
        if self.px4.handle(msg, False, rx_ns):
            return
        kind = msg.get_type()
        if kind == "TIMESYNC":
            reply = reply_for(msg.tc1, msg.ts1, self.clock_ns(time.monotonic_ns()))
            if reply is not None:
                self.send(self.mav.timesync_encode(reply.tc1, reply.ts1))
                self.stats.timesync_answers += 1
            else:
                now = self.clock_ns(rx_ns)
                if self.sync.on_reply(msg.tc1, msg.ts1, now):
                    self.stats.timesync_rtt_ns.append(now - msg.ts1)
        elif kind == "HEARTBEAT":
            self.stats.heartbeats_from_companion += 1
        elif kind == "COMMAND_LONG" and msg.command == MAV_CMD_SET_MESSAGE_INTERVAL:
            self.stats.rate_requests_s.append(self.t_sim_of_mono(rx_ns))
            msg_id = int(msg.param1 + 0.5)
            ok = self.set_message_interval(msg_id, float(msg.param2))
            ack = self.mav.command_ack_encode(
                MAV_CMD_SET_MESSAGE_INTERVAL,
                MAV_RESULT_ACCEPTED if ok else MAV_RESULT_FAILED,
                0,
                msg_id,
                msg.get_srcSystem(),
                msg.get_srcComponent(),
            )
            self.send(ack)
        elif kind in ("VISION_POSITION_ESTIMATE", "ODOMETRY"):
            self._on_pose(msg, kind, rx_ns)
        elif kind == "STATUSTEXT":
            text = (rx_ns, int(msg.severity), str(msg.text), int(msg.id), int(msg.chunk_seq))
            self.stats.statustexts.append(text)
            self.px4.forward_gcs(msg)

    def set_message_interval(self, msg_id: int, interval_us: float) -> bool:
        """PX4's MavlinkReceiver::set_message_interval for the streams we have: the interval
        [us] sets the rate, 0 the default rate, < 0 stops the stream. False (FAILED): HEARTBEAT
        or a message we do not stream."""
        if msg_id not in self.rates_hz:
            return False
        if interval_us > 1e-5:
            rate = 1e6 / interval_us
        elif interval_us < -1e-5:
            rate = 0.0
        else:
            rate = self.default_rates_hz[msg_id]
        self.rates_hz[msg_id] = rate
        self.stats.rates_set[msg_id] = rate
        return True

    def _period_s(self, msg_id: int) -> float | None:
        """A stream's period [s]; None while it is stopped."""
        rate = self.rates_hz[msg_id]
        return 1.0 / rate if rate > 0 else None

    def _on_pose(self, msg: Any, kind: str, rx_ns: int) -> None:
        self.px4.on_vision(msg, kind, rx_ns)  # what PX4 and EKF2 make of it
        if not self.sync.converged:
            return  # PX4 does not use the timestamps before its filter converged
        t_usec = int(msg.usec if kind == "VISION_POSITION_ESTIMATE" else msg.time_usec)
        here_ns = self.clock_ns(rx_ns)
        local_us = self.sync.remote_to_local_us(t_usec, here_ns)
        exact_us = self.clock_ns(t_usec * 1000) / 1000.0
        t_sim = self.t_sim_of_mono(self.mono_of_clock_ns(local_us * 1000.0))
        if not 0.0 <= t_sim <= self.end_s:
            return
        if kind == "VISION_POSITION_ESTIMATE":
            rpy = (float(msg.roll), float(msg.pitch), float(msg.yaw))
        else:
            rpy = so3.matrix_to_rpy(so3.quat_to_matrix(np.array(msg.q, dtype=np.float64)))
        T = self.trajectory.T_world_body(t_sim)
        self.stats.received.append(
            Received(
                rx_ns,
                kind,
                t_usec,
                t_sim,
                (float(msg.x), float(msg.y), float(msg.z)),
                rpy,
                int(msg.reset_counter),
                tuple(float(v) for v in T[:3, 3]),  # type: ignore[arg-type]
                so3.matrix_to_rpy(T[:3, :3]),
                float(local_us - exact_us),
            )
        )

    # ------------------------------------------------------------------ loops
    async def _every(self, period_s: float, fn: Any) -> None:
        next_t = time.monotonic()
        while True:
            fn()
            next_t += period_s
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))

    def _log_live(self) -> None:
        """A line every 5 s: the rate of the last 5 s and the position error of the current
        reset segment's last 100 s (SE(3)-aligned; bounded work however long the flight)."""
        rec = self.stats.received[-3000:]
        t = self.t_sim_of_mono(time.monotonic_ns())
        if not rec:
            return
        kind = self._main_kind()
        rec = [r for r in rec if r.kind == kind and r.reset_counter == rec[-1].reset_counter]
        if len(rec) < 10 or t < 0:
            return
        since = time.monotonic_ns() - 5_000_000_000
        recent = sum(1 for r in rec if r.rx_ns > since)
        est = np.array([r.position for r in rec])
        gt = np.array([r.true_position for r in rec])
        err = np.linalg.norm(umeyama(est, gt, with_scale=False).apply(est) - gt, axis=1)
        print(
            f"[sitl {t:5.1f} s] {recent / 5.0:4.1f} Hz {kind}, reset_counter "
            f"{rec[-1].reset_counter}, position error now {err[-1]:.3f} m, "
            f"RMS over the last {len(rec) / 30.0:.0f} s {np.sqrt(np.mean(err**2)):.3f} m",
            flush=True,
        )

    def _heartbeat(self) -> None:
        self.send(self.mav.heartbeat_encode(2, 12, self.px4.base_mode(), 0, 4))  # QUADROTOR, PX4

    async def _timesync_loop(self) -> None:
        """TIMESYNC requests at the stream's rate (a new rate acts from the next request). As
        a PX4 stream, one late request is sent, never a burst to catch up after a stall."""
        next_t = time.monotonic()
        while True:
            period = self._period_s(MSG_TIMESYNC)
            now = time.monotonic()
            if period is None:  # stopped: look again later
                next_t = now + 0.1
            else:
                self.send(self.mav.timesync_encode(0, self.clock_ns(time.monotonic_ns())))
                next_t = next_t + period if next_t + period > now else now + period
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))

    async def _attitude_loop(self) -> None:
        noise = np.radians(0.1)
        while True:
            now = time.monotonic_ns()
            t = self.t_sim_of_mono(now)
            period = self._period_s(MSG_ATTITUDE)
            if period is not None and 0.0 <= t <= self.end_s:
                s = self.trajectory.sample(np.array([t]))
                R = s.R_world_body[0] @ so3.exp(noise * self._rng.standard_normal(3))
                r, p, y = so3.matrix_to_rpy(R)
                w = s.omega_body_rad_s[0] * self.opts.time_scale  # per wall-clock second
                self.send(
                    self.mav.attitude_encode(
                        self.clock_ns(now) // 1_000_000,
                        r,
                        p,
                        y,
                        float(w[0]),
                        float(w[1]),
                        float(w[2]),
                    )
                )
            await asyncio.sleep(period or 0.1)  # stopped: look again later

    async def _gps_loop(self) -> None:
        """GPS_RAW_INT and GPS_GLOBAL_ORIGIN at their stream rates (sitl/stub/gps.py)."""
        next_due = {m: 0.0 for m in gps.DEFAULT_RATES_HZ}
        while True:
            now = time.monotonic_ns()
            for msg_id in next_due:
                period = self._period_s(msg_id)
                if period is None or now * 1e-9 < next_due[msg_id]:
                    continue
                next_due[msg_id] = now * 1e-9 + period
                boot_us = self.clock_ns(now) // 1000
                if msg_id == gps.MSG_GPS_GLOBAL_ORIGIN:
                    self.send(gps.gps_global_origin(self.mav, boot_us))
                    continue
                t = float(np.clip(self.t_sim_of_mono(now), 0.0, self.cfg.sitl.seconds))
                truth = self.trajectory.sample(np.array([t])).position_m[0]
                self.send(
                    gps.gps_raw_int(
                        self.mav,
                        boot_us,
                        truth + np.asarray(self.opts.gps_offset_ned_m, np.float64),
                        "gps_loss" in active(self.opts.faults, self.t_sim_of_mono(now)),
                        self.gps_noise.at(t),  # by flight time: the same noise each run
                    )
                )
            await asyncio.sleep(0.01)

    async def _distance_loop(self) -> None:
        """Every sensor's readings at their own times; decimated to the stream rate."""
        last_t = 0.0
        last_sent: dict[int, float] = {}
        while True:
            t = self.t_sim_of_mono(time.monotonic_ns())
            period = self._period_s(MSG_DISTANCE_SENSOR)
            if period is None:  # stopped: the readings meanwhile are not sent later
                last_t = max(last_t, t)
            elif 0.0 <= t <= self.end_s and t > last_t:
                for r in self.ranges.between(last_t, t):
                    smp = r.sample
                    if smp is None:
                        continue
                    sid = smp.sensor_id
                    t_s = smp.time_us * 1e-6
                    # the stream's period is wall-clock time, the readings' flight time
                    if t_s - last_sent.get(sid, -1e9) < period * 0.95 * self.opts.time_scale:
                        continue
                    last_sent[sid] = t_s
                    mono = self.mono_of_t_sim(t_s)
                    rf = next(x for x in self.cfg.rangefinders if x.sensor_id == sid)
                    sigma_cm = (rf.sigma_a_m + rf.sigma_b * smp.distance_m) * 100
                    self.send(
                        self.mav.distance_sensor_encode(
                            self.clock_ns(mono) // 1_000_000,
                            int(round(smp.min_m * 100)),
                            int(round(smp.max_m * 100)),
                            int(np.clip(round(smp.distance_m * 100), 0, 65534)),
                            0,  # MAV_DISTANCE_SENSOR_LASER
                            sid,
                            25,  # PITCH_270: downward
                            int(min(254, round(sigma_cm**2))),
                            signal_quality=int(smp.signal_quality),
                        )
                    )
                last_t = t
            await asyncio.sleep(0.004)

    async def _listen(self, port: int) -> None:
        """(Re)open our UDP socket on ``port`` (0: any free one); we send from it too."""
        stub = self

        class Proto(asyncio.DatagramProtocol):
            def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
                stub._on_datagram(data)

        old = self._transport
        transport, _ = await asyncio.get_running_loop().create_datagram_endpoint(
            Proto, local_addr=(self.opts.host, port)
        )
        self._transport = transport
        if old is not None:
            old.close()

    async def _fault_loop(self) -> None:
        """Link faults that happen at an instant: a new UDP port; the end of a reboot."""
        pending = sorted(
            (f for f in self.opts.faults if f.kind in ("link_port_change", "autopilot_reboot")),
            key=lambda f: f.end_s if f.kind == "autopilot_reboot" else f.start_s,
        )
        for f in pending:
            at = f.end_s if f.kind == "autopilot_reboot" else f.start_s
            while self.t_sim_of_mono(time.monotonic_ns()) < at:
                await asyncio.sleep(0.005)
            if f.kind == "link_port_change":
                await self._listen(0)
            else:  # back from a reboot: a new boot clock, time sync and default rates
                self.boot_ns = time.monotonic_ns()
                self.sync = ClockSync()
                self.rates_hz = dict(self.default_rates_hz)
                self.stats.reboots += 1

    async def _watch_camera(self, camera: Any) -> None:
        """The camera process failing (its port taken, a rendering error) ends the run with
        an error: a flight without our camera, or with somebody else's stream on its port,
        would be measured as if it were ours."""
        while True:
            await asyncio.sleep(0.2)
            if camera.exitcode not in (None, 0):
                raise SitlError(
                    f"the SITL camera process failed (exit code {camera.exitcode}; its "
                    f"traceback is above): is TCP port {self.opts.camera_port} taken?"
                )

    async def run(self, out: Path | None = None) -> dict[str, Any]:
        """Fly the scenario (camera ready, warm-up, flight, linger) and return the report.
        MAVLink runs from the start (heartbeats, time sync); the sensors and the camera only
        during the flight."""
        ctx = mp.get_context("spawn")
        counters = ctx.Array("q", 3)  # frames sent, frames dropped, flight start [ns]
        ready = ctx.Event()
        self.flight_start_ns = time.monotonic_ns() + 10**15  # not before the camera is ready
        camera = ctx.Process(
            target=camera_process,
            args=(
                to_dict(self.cfg),
                self.opts.camera_port,
                0,
                self.opts.readout_ms,
                counters,
                self.opts.prerender,
                ready,
                self.opts.faults,
                (self.opts.loop_from_frame, self.opts.loop_frames),
                self.opts.time_scale,
                self.end_s,
            ),
            daemon=True,
            name="sitl-camera",
        )
        if self.opts.camera:
            camera.start()
        else:
            ready.set()
        await self._listen(self.opts.listen_port)
        await self.px4.open_gcs()
        try:
            async with asyncio.TaskGroup() as tg:
                tasks = [
                    tg.create_task(self._every(1.0, self._heartbeat)),
                    tg.create_task(self._timesync_loop()),
                    tg.create_task(self._attitude_loop()),
                    tg.create_task(self._distance_loop()),
                    tg.create_task(self._every(5.0, self._log_live)),
                    tg.create_task(self._fault_loop()),
                    *(tg.create_task(c, name=n) for n, c in self.px4.loops().items()),
                ]
                if self.opts.camera:
                    tasks.append(tg.create_task(self._watch_camera(camera)))
                if self.opts.gps:
                    tasks.append(tg.create_task(self._gps_loop()))
                # the world is built (and, with prerender, every frame rendered)
                while not ready.is_set():
                    await asyncio.sleep(0.05)
                if self.opts.flight_gate is not None:
                    await self.opts.flight_gate()
                self.flight_start_ns = time.monotonic_ns() + int(self.opts.warmup_s * 1e9)
                counters[2] = self.flight_start_ns
                end_ns = self.mono_of_t_sim(self.end_s) + int(self.opts.linger_s * 1e9)
                await asyncio.sleep(max(0.0, (end_ns - time.monotonic_ns()) * 1e-9))
                for t in tasks:
                    t.cancel()
        except ExceptionGroup as group:  # a loop's own error (the camera died): say it plainly
            mine = [e for e in group.exceptions if isinstance(e, SitlError)]
            if mine:
                raise mine[0] from None
            raise
        finally:
            if self._transport is not None:
                self._transport.close()
            self.px4.close()
            if self.opts.camera:
                camera.join(timeout=5)
            if camera.is_alive():
                camera.terminate()
        if self.opts.flight_done is not None:
            await self.opts.flight_done()
        report = self.report(int(counters[0]), int(counters[1]))
        if out is not None:
            self.write(out, report)
        return report

    # ------------------------------------------------------------------ results
    def report(self, frames_sent: int = 0, frames_dropped: int = 0) -> dict[str, Any]:
        """Rates, latency, time-sync and accuracy figures of what was received
        (:func:`companion.sitl.stub.report.flight_report`)."""
        return flight_report(
            self.stats,
            self.opts,
            self.cfg.camera.rate_hz,
            self.t_sim_of_mono,
            self.signing.counters() if self.signing else None,
            frames_sent,
            frames_dropped,
        )

    def _main_kind(self) -> str:
        return main_kind(self.stats.received)

    def write(self, out: Path, report: dict[str, Any]) -> None:
        """``report.json``, ``received.csv`` and ``autopilot.png`` in ``out``."""
        write_report(out, report, self.stats.received)
