"""The bridge between PX4's SIH simulator and our sensors
(``python -m companion.sitl.loops.px4_bridge``).

PX4 SIH flies the vehicle; this process stands where the vehicle's hardware stands:

- Truth: HIL_STATE_QUATERNION on SIH's "display" link (PX4 sends to UDP 19410+N), stamped on
  arrival with our monotonic clock (its ``time_usec`` is 0); lat/lon/alt around the first
  sample (the vehicle at rest at home) -> local NED (azimuthal equidistant, PX4's Earth radius);
  attitude quaternion (body FRD -> NED, wxyz).
- World: our seeded terrain (sitl/world/terrain.py) with its heights clipped to <= 0 (the home
  level, h(0, 0) = 0): SIH's ground is flat at the home altitude, so the vehicle never flies
  into one of our hills and lands on our ground where it lands on SIH's. Around home it is flat, as
  SIH's is (a pad of PAD_FLAT_M, eased into the terrain over PAD_EASE_M more): clipped alone,
  home sat on the edge of a slope, and our sensors saw a 6 deg slope where SIH's vehicle stood
  level on its flat ground. SIH's body origin rests on its
  ground; ours rests ``gear_m`` above it (legs): the body is placed at truth NED - gear_m up,
  and never lower than that (SIH's vehicle sank below its start altitude at touch-down in some
  flights of this build; our ground stays solid).
- Camera: frame k is exposed at ``t0 + k / rate``; the bridge waits for the first truth sample
  after the exposure (<= 10 ms at 100 Hz; after 12 ms it extrapolates the latest with its
  velocity), interpolates the pose (linear position, slerp attitude), renders (sitl/world/render.py,
  live laser dots) and releases the frame on the SITL camera stream (drivers/camera.py format,
  TCP) at exposure + readout, or as soon as it is rendered. A frame that cannot be out within
  60 ms of its exposure (the service's frame_wait_ms) is dropped and counted.
- Distance sensors: one pseudo-terminal per configured sensor, TFmini frames (drivers/
  rangefinder.py) at the sensor's rate, ray cast at the current truth pose with the sensor's
  noise model: the service reads them as it reads TFminis on a UART (``rangefinders[i].serial``).

On start it writes ``bridge.json`` (the pty paths, the camera port) into ``--out`` once the world
is built and the kernels compiled; on SIGTERM it writes ``truth.csv`` and ``bridge-stats.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import socket
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from companion.config import Config, RangefinderConfig, load_config
from companion.drivers.camera import encode_frame
from companion.drivers.rangefinder import tfmini_frame
from companion.geometry import so3
from companion.sitl.world.render import Renderer
from companion.sitl.world.sensors import laser_hits
from companion.sitl.world.terrain import World, make_world
from companion.types import F64, CameraFrame

EARTH_RADIUS_M = 6371000.0  # PX4's CONSTANTS_RADIUS_OF_EARTH (map projection)
# our ground is flat (the home level, as SIH's) within PAD_FLAT_M of home, then eased into
# the clipped terrain over PAD_EASE_M: the take-off and the landing over one plane
PAD_FLAT_M = 3.0
PAD_EASE_M = 3.0
TRUTH_WAIT_MAX_S = 0.012  # no truth sample after an exposure this long: extrapolate (<= 2 mm)
LATE_MAX_NS = (
    60_000_000  # a frame not out 60 ms after its exposure is dropped (service.frame_wait_ms)
)


def ned_of(lat_e7: int, lon_e7: int, alt_mm: int, home: tuple[int, int, int]) -> F64:
    """Local NED [m] of a lat/lon/alt (1e-7 deg, mm) around ``home`` (azimuthal equidistant,
    as PX4's MapProjection; exact enough over the few hundred metres of a flight)."""
    lat0, lon0 = math.radians(home[0] * 1e-7), math.radians(home[1] * 1e-7)
    lat, lon = math.radians(lat_e7 * 1e-7), math.radians(lon_e7 * 1e-7)
    cos_c = math.sin(lat0) * math.sin(lat) + math.cos(lat0) * math.cos(lat) * math.cos(lon - lon0)
    c = math.acos(max(-1.0, min(1.0, cos_c)))
    k = c / math.sin(c) if c > 1e-12 else 1.0
    north = k * (
        math.cos(lat0) * math.sin(lat) - math.sin(lat0) * math.cos(lat) * math.cos(lon - lon0)
    )
    east = k * math.cos(lat) * math.sin(lon - lon0)
    return np.array([north * EARTH_RADIUS_M, east * EARTH_RADIUS_M, -(alt_mm - home[2]) * 1e-3])


def clipped_world(cfg: Config) -> World:
    """The configured terrain with its ground clipped to the home level (h <= 0), flat around
    home (PAD_FLAT_M, eased over PAD_EASE_M) and no buildings: SIH's own ground is flat at the
    home altitude (see the module docstring)."""
    s = cfg.sitl
    w = make_world(s.terrain, s.seed, s.world_size_m, s.height_resolution_m, s.ground)
    if w.h_max <= 0.0 and w.h_min >= 0.0 and len(w.boxes) == 0:
        return w
    rows, cols = w.heights.shape  # rows along east (y), columns along north (x)
    east = w.y0 + w.res_m * np.arange(rows, dtype=np.float64)
    north = w.x0 + w.res_m * np.arange(cols, dtype=np.float64)
    r = np.hypot(*np.meshgrid(east, north, indexing="ij"))
    u = np.clip((r - PAD_FLAT_M) / PAD_EASE_M, 0.0, 1.0)
    ease = u * u * (3.0 - 2.0 * u)  # 0 on the pad, 1 beyond its ease (smoothstep)
    heights = (np.minimum(w.heights, 0.0) * ease).astype(np.float32)
    return World(
        w.name, w.seed, w.size_m, heights, w.res_m, np.zeros((0, 6)), w.default_altitude_m, w.ground
    )


@dataclass
class TruthSample:
    t_ns: int  # arrival, our monotonic clock
    p_ned_m: F64  # body origin, SIH's frame (NED from home; home ground at z = 0)
    q_wxyz: F64  # body FRD -> NED
    v_ned_m_s: F64


class TruthTrack:
    """HIL_STATE_QUATERNION samples, appended by the receiver thread, read by the others."""

    def __init__(self) -> None:
        self.samples: list[TruthSample] = []
        self.home: tuple[int, int, int] | None = None
        self.lock = threading.Lock()
        self.new = threading.Condition(self.lock)

    def add(self, msg: Any, t_ns: int) -> None:
        if self.home is None:
            self.home = (int(msg.lat), int(msg.lon), int(msg.alt))
        q = np.array(msg.attitude_quaternion, dtype=np.float64)
        q = q / np.linalg.norm(q)
        if q[0] < 0:
            q = -q
        v = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64) * 0.01
        s = TruthSample(t_ns, ned_of(msg.lat, msg.lon, msg.alt, self.home), q, v)
        with self.new:
            self.samples.append(s)
            self.new.notify_all()

    def latest(self) -> TruthSample | None:
        with self.lock:
            return self.samples[-1] if self.samples else None

    def wait_after(self, t_ns: int, timeout_s: float) -> bool:
        """Wait until a sample arrived at or after ``t_ns``; False on timeout."""
        end = time.monotonic() + timeout_s
        with self.new:
            while not self.samples or self.samples[-1].t_ns < t_ns:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self.new.wait(left)
            return True

    def pose(self, t_ns: int) -> tuple[F64, F64] | None:
        """(position NED (3,), R_ned_body (3, 3)) at ``t_ns``: interpolated between the
        bracketing samples, else extrapolated from the nearest with its velocity."""
        with self.lock:
            n = len(self.samples)
            if n == 0:
                return None
            i = n - 1
            while i > 0 and self.samples[i - 1].t_ns > t_ns and n - i < 400:
                i -= 1
            b = self.samples[i]
            a = self.samples[i - 1] if i > 0 else b
        if a is b or not a.t_ns <= t_ns <= b.t_ns:
            s = b if t_ns >= b.t_ns else a
            dt = (t_ns - s.t_ns) * 1e-9
            return s.p_ned_m + s.v_ned_m_s * dt, so3.quat_to_matrix(s.q_wxyz)
        f = (t_ns - a.t_ns) / max(b.t_ns - a.t_ns, 1)
        p = a.p_ned_m + f * (b.p_ned_m - a.p_ned_m)
        Ra, Rb = so3.quat_to_matrix(a.q_wxyz), so3.quat_to_matrix(b.q_wxyz)
        R = Ra @ so3.exp(f * so3.log(Ra.T @ Rb))
        return p, R

    def write_csv(self, path: Path) -> None:
        with self.lock:
            rows = list(self.samples)
        with path.open("w") as fh:
            fh.write("t_ns,n_m,e_m,d_m,qw,qx,qy,qz,vn_m_s,ve_m_s,vd_m_s\n")
            for s in rows:
                vals = [*s.p_ned_m, *s.q_wxyz, *s.v_ned_m_s]
                fh.write(f"{s.t_ns}," + ",".join(f"{v:.5f}" for v in vals) + "\n")


class Bridge:
    """Truth in; camera stream and TFmini ptys out (see the module docstring)."""

    def __init__(
        self, cfg: Config, instance: int, camera_port: int, out: Path, gear_m: float = 0.35
    ) -> None:
        self.cfg = cfg
        self.instance = instance
        self.camera_port = camera_port
        self.out = out
        self.gear_m = gear_m
        self.world = clipped_world(cfg)
        self.renderer = Renderer(
            self.world, cfg.camera, cfg.sitl.render, cfg.rangefinders, cfg.sitl.seed
        )
        self.T_body_cam = cfg.camera.T_body_cam()
        self.truth = TruthTrack()
        self.stop = threading.Event()
        self.stats: dict[str, Any] = {
            "frames_sent": 0,
            "frames_dropped": 0,
            "frames_extrapolated": 0,
            "render_ms": [],
            "release_late_ms": [],
            "range_frames": 0,
        }
        self.ptys: list[tuple[int, int, str]] = []  # master fd, slave fd, slave path
        for _ in cfg.rangefinders:
            master, slave = os.openpty()
            tty.setraw(slave)
            os.set_blocking(master, False)
            self.ptys.append((master, slave, os.ttyname(slave)))

    # ------------------------------------------------------------------ poses
    def T_world_body(self, t_ns: int) -> F64 | None:
        """Our world's body pose at ``t_ns`` (SIH truth, raised by the legs)."""
        got = self.truth.pose(t_ns)
        if got is None:
            return None
        p, R = got
        T = np.eye(4)
        T[:3, :3] = R
        # our ground is solid at the home level: SIH let the vehicle sink 0.1-3 m below its
        # start altitude at touch-down in this build, our sensors see it resting on the ground
        T[:3, 3] = p + np.array([0.0, 0.0, -self.gear_m])
        T[2, 3] = min(T[2, 3], -self.gear_m)
        return T

    # ------------------------------------------------------------------ threads
    def truth_loop(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 19410 + self.instance))
        sock.settimeout(0.2)
        mav = mavlink.MAVLink(None)
        mav.robust_parsing = True
        while not self.stop.is_set():
            try:
                data = sock.recv(65535)
            except TimeoutError:
                continue
            t_ns = time.monotonic_ns()
            try:
                msgs = mav.parse_buffer(data) or []
            except mavlink.MAVError:
                continue
            for m in msgs:
                if m.get_type() == "HIL_STATE_QUATERNION":
                    self.truth.add(m, t_ns)
        sock.close()

    def range_loop(self) -> None:
        """Every sensor at its own rate (phases spread), TFmini frames on its pty."""
        rfs = self.cfg.rangefinders
        periods = [int(1e9 / rf.rate_hz) for rf in rfs]
        start = time.monotonic_ns()
        due = [start + int(p * (k + 1) / (len(rfs) + 1)) for k, p in enumerate(periods)]
        rng = np.random.default_rng([self.cfg.sitl.seed, 202])
        while not self.stop.is_set():
            k = int(np.argmin(due))
            wait = (due[k] - time.monotonic_ns()) * 1e-9
            if wait > 0:
                time.sleep(wait)
            t_ns = due[k]
            due[k] += periods[k]
            T = self.T_world_body(t_ns)
            if T is None:
                continue
            frame = self.tfmini_reading(rfs[k], T, rng)
            if frame is None:
                continue
            with contextlib.suppress(BlockingIOError, OSError):
                os.write(self.ptys[k][0], frame)
                self.stats["range_frames"] += 1

    def tfmini_reading(
        self, rf: RangefinderConfig, T_world_body: F64, rng: np.random.Generator
    ) -> bytes | None:
        """One TFmini frame with the sensor's noise model (sitl/world/sensors.py's); None: a
        dropout."""
        t, _ = laser_hits(self.world, T_world_body, [rf])
        true_d = float(t[0])
        if rng.uniform() < rf.dropout_prob:
            return None
        if not np.isfinite(true_d) or true_d > rf.max_m or true_d < rf.min_m:
            return tfmini_frame(0xFFFF if true_d > rf.min_m else 0, 0)  # unreliable
        if rng.uniform() < rf.outlier_prob:
            d = rf.min_m + rng.uniform() * (rf.max_m - rf.min_m)
        else:
            d = true_d + (rf.sigma_a_m + rf.sigma_b * true_d) * rng.normal()
        d_cm = int(np.clip(round(d * 100), 1, 65534))
        return tfmini_frame(d_cm, 2000)

    def camera_loop(self) -> None:
        """Render and release frames at the camera rate (see the module docstring)."""
        srv = socket.create_server(("127.0.0.1", self.camera_port))
        srv.settimeout(0.2)
        client: socket.socket | None = None
        period_ns = int(1e9 / self.cfg.camera.rate_hz)
        readout_ns = 4_000_000
        while self.truth.latest() is None and not self.stop.is_set():
            time.sleep(0.01)
        t0 = time.monotonic_ns() + period_ns
        seq = 0
        while not self.stop.is_set():
            if client is None:
                try:
                    client, _ = srv.accept()
                    client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                except TimeoutError:
                    continue
                # start the frame clock again: frames of the past are not worth sending
                t0 = time.monotonic_ns() + period_ns
                seq = 0
            expose_ns = t0 + seq * period_ns
            release_ns = expose_ns + readout_ns
            wait = (expose_ns - time.monotonic_ns()) * 1e-9
            if wait > 0:
                time.sleep(wait)
            if not self.truth.wait_after(expose_ns, TRUTH_WAIT_MAX_S):
                self.stats["frames_extrapolated"] += 1
            if time.monotonic_ns() > expose_ns + LATE_MAX_NS - 10_000_000:
                self.stats["frames_dropped"] += 1  # behind: skip it, as a camera would
                seq += 1
                continue
            T = self.T_world_body(expose_ns)
            if T is None:
                seq += 1
                continue
            r0 = time.monotonic_ns()
            marks = self._marks(T)
            img = self.renderer.render_pose(T @ self.T_body_cam, seq, marks).image_bgr
            self.stats["render_ms"].append((time.monotonic_ns() - r0) * 1e-6)
            now = time.monotonic_ns()
            if now > expose_ns + LATE_MAX_NS:
                self.stats["frames_dropped"] += 1
                seq += 1
                continue
            if now < release_ns:
                time.sleep((release_ns - now) * 1e-9)
            self.stats["release_late_ms"].append(max(0.0, (now - release_ns) * 1e-6))
            try:
                client.sendall(encode_frame(CameraFrame(expose_ns // 1000, seq, img)))
                self.stats["frames_sent"] += 1
            except OSError:
                client.close()
                client = None
            seq += 1
        if client is not None:
            client.close()
        srv.close()

    def _marks(self, T_world_body: F64) -> F64 | None:
        if self.cfg.sitl.render.laser_marks != "live" or not self.cfg.rangefinders:
            return None
        t, pts = laser_hits(self.world, T_world_body, self.cfg.rangefinders)
        ok = np.isfinite(t) & np.array(
            [rf.min_m <= d <= rf.max_m for rf, d in zip(self.cfg.rangefinders, t, strict=True)]
        )
        return np.asarray(pts[ok], dtype=np.float64)

    # ------------------------------------------------------------------ run
    def run(self) -> None:
        # compile the kernels before anybody waits on us
        self.renderer.render_pose(
            np.array([[0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 1, -5.0], [0, 0, 0, 1.0]]), 0
        )
        threads = [
            threading.Thread(target=self.truth_loop, name="truth", daemon=True),
            threading.Thread(target=self.range_loop, name="ranges", daemon=True),
        ]
        for th in threads:
            th.start()
        info = {
            "camera_url": f"sitl://127.0.0.1:{self.camera_port}",
            "rangefinder_ptys": [p[2] for p in self.ptys],
            "gear_m": self.gear_m,
            "pid": os.getpid(),
        }
        (self.out / "bridge.json").write_text(json.dumps(info, indent=2) + "\n")
        try:
            self.camera_loop()
        finally:
            self.stop.set()
            for th in threads:
                th.join(1.0)
            self.write()
            for master, slave, _ in self.ptys:
                for fd in (master, slave):
                    with contextlib.suppress(OSError):
                        os.close(fd)

    def write(self) -> None:
        self.truth.write_csv(self.out / "truth.csv")
        r = np.array(self.stats["render_ms"] or [np.nan])
        late = np.array(self.stats["release_late_ms"] or [np.nan])
        stats = {k: v for k, v in self.stats.items() if k not in ("render_ms", "release_late_ms")}
        stats.update(
            {
                "render_ms_p50": float(np.percentile(r, 50)),
                "render_ms_p99": float(np.percentile(r, 99)),
                "release_late_ms_p99": float(np.percentile(late, 99)),
                "truth_samples": len(self.truth.samples),
                "camera": f"{self.cfg.camera.width}x{self.cfg.camera.height} "
                f"@ {self.cfg.camera.rate_hz:g} Hz",
            }
        )
        if len(self.truth.samples) > 2:
            t = np.array([s.t_ns for s in self.truth.samples]) * 1e-9
            stats["truth_rate_hz"] = float((len(t) - 1) / (t[-1] - t[0]))
            stats["truth_gap_ms_max"] = float(np.diff(t).max() * 1e3)
        (self.out / "bridge-stats.json").write_text(json.dumps(stats, indent=2) + "\n")


def parse_bridge_args(
    prog: str,
    description: str | None,
    argv: list[str] | None,
    add_truth_source: Callable[[argparse.ArgumentParser], Any],
) -> tuple[argparse.Namespace, Config]:
    """The command line of a bridge (``--config``, its truth source's flags as
    ``add_truth_source`` adds them, ``--camera-port``, ``--out``, ``--gear-m``): the arguments
    and the loaded config; ``--out`` is created."""
    ap = argparse.ArgumentParser(prog=prog, description=description)
    ap.add_argument("--config", type=Path, required=True)
    add_truth_source(ap)
    ap.add_argument("--camera-port", type=int, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--gear-m", type=float, default=0.35)
    args = ap.parse_args(argv)
    cfg = load_config(args.config)
    args.out.mkdir(parents=True, exist_ok=True)
    return args, cfg


def serve(bridge: Bridge) -> int:
    """Run ``bridge`` until SIGTERM or SIGINT (then it writes its truth and stats); exit 0."""

    def on_term(signum: int, frame: Any) -> None:
        bridge.stop.set()

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)
    bridge.run()
    return 0


def main(argv: list[str] | None = None) -> int:
    args, cfg = parse_bridge_args(
        "python -m companion.sitl.loops.px4_bridge",
        __doc__,
        argv,
        lambda ap: ap.add_argument("--instance", type=int, default=0),
    )
    return serve(Bridge(cfg, args.instance, args.camera_port, args.out, args.gear_m))


if __name__ == "__main__":
    raise SystemExit(main())
