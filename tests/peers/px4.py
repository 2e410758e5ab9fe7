"""The real PX4 SITL (``../shared/px4-sitl/px4-sitl``) and a small vision sender for it.

``Px4Sitl`` starts PX4 (SIH quadrotor, headless) as its own process on one instance number (its
ports shift by it), in a fresh work folder, with parameters set at boot through PX4_PARAM_*;
``stop()`` ends that process only (by its id). ``VisionSender`` is a real MAVLink peer on PX4's
onboard link: it answers PX4's TIMESYNC requests at once (as the service does) and streams a
plausible constant pose (VISION_POSITION_ESTIMATE, or ODOMETRY with a chosen frame) at 30 Hz,
stamped in its monotonic clock; its heading follows PX4's own ATTITUDE, so that the NED pose it
sends agrees with what a magnetometer-aligned EKF2 believes.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from pymavlink.dialects.v20 import common as mavlink

from companion.drivers.timesync import RequesterModel

T = TypeVar("T")

REPO = Path(__file__).resolve().parents[2]
PX4_SITL = REPO.parent / "shared" / "px4-sitl" / "px4-sitl"
SKIP_REASON = (
    f"PX4 SITL not found at {PX4_SITL} (../shared/px4-sitl/px4-sitl beside the repository): "
    "these tests run the real PX4. Build it from PX4-Autopilot (main at 02e73e3b6f, with its "
    "submodules): `make px4_sitl_default`, then put a script there that runs "
    "`PX4_SYS_AUTOSTART=10040 PX4_SIM_MODEL=sihsim_quadx build/px4_sitl_default/bin/px4 -d -i N "
    "-w WORKDIR ROMFS/px4fmu_common` (see docs/install.md, 'PX4 SITL')"
)

# what "vision only" takes on this PX4 (../shared/px4-sitl/README.md)
GPS_OFF = {"SENS_EN_GPSSIM": 0, "SYS_HAS_GPS": 0, "EKF2_GPS_CTRL": 0}


def ports_free(instance: int) -> bool:
    """Nobody holds this instance's UDP ports on 127.0.0.1 (another PX4, another sender)."""
    for base in (14540, 14580, 18570, 18600, 19410, 19450, 14280, 14030, 13030, 13280):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(("127.0.0.1", base + instance))
            except OSError:
                return False
    return True


def free_instance(preferred: tuple[int, ...] = (8, 9, 7, 6, 5)) -> int:
    """An instance number whose ports are free (PX4_TEST_INSTANCE forces one)."""
    forced = os.environ.get("PX4_TEST_INSTANCE")
    if forced:
        return int(forced)
    for n in preferred:
        if ports_free(n):
            return n
    raise RuntimeError(f"no free PX4 SITL instance among {preferred}")


def available() -> bool:
    """The PX4 SITL launcher is there."""
    return PX4_SITL.is_file() and os.access(PX4_SITL, os.X_OK)


@dataclass
class Px4Sitl:
    """One PX4 SITL process (instance ``instance``) in ``workdir``."""

    instance: int
    workdir: Path
    params: dict[str, int | float] = field(default_factory=dict)
    proc: subprocess.Popen[bytes] | None = None

    @property
    def gcs_port(self) -> int:
        """PX4 listens for a ground station here (Normal mode)."""
        return 18570 + self.instance

    @property
    def gcs_client_port(self) -> int:
        """Our ground-station tools (MAVSDK in check / configure) listen here: PX4 on UDP keeps
        the first peer that spoke to it as its partner until it stops, so every tool of a test
        uses this one port, announced once at start (:meth:`announce_gcs`)."""
        return 18600 + self.instance

    @property
    def onboard_port(self) -> int:
        """PX4's onboard (API) link listens here ..."""
        return 14580 + self.instance

    @property
    def companion_port(self) -> int:
        """... and sends to here."""
        return 14540 + self.instance

    @property
    def log(self) -> Path:
        return self.workdir / "px4.log"

    def start(self, timeout_s: float = 60.0) -> None:
        """Start PX4 and wait for its start-up script to finish."""
        self.workdir.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ)
        env.update({f"PX4_PARAM_{k}": str(v) for k, v in self.params.items()})
        with self.log.open("wb") as out:
            self.proc = subprocess.Popen(
                [str(PX4_SITL), str(self.instance), str(self.workdir / "run")],
                stdout=out,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                env=env,
                start_new_session=True,
            )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if "Startup script returned successfully" in self.output():
                self.announce_gcs()
                return
            if self.proc.poll() is not None:
                raise RuntimeError(f"PX4 SITL exited at start:\n{self.output()[-3000:]}")
            time.sleep(0.1)
        self.stop()
        raise RuntimeError(f"PX4 SITL did not start in {timeout_s:g} s:\n{self.output()[-3000:]}")

    def announce_gcs(self) -> None:
        """A HEARTBEAT from gcs_client_port to PX4's ground-station port: PX4's partner."""
        mav = mavlink.MAVLink(None, srcSystem=245, srcComponent=190)
        beat = mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(("127.0.0.1", self.gcs_client_port))
            s.sendto(beat.pack(mav), ("127.0.0.1", self.gcs_port))

    def output(self) -> str:
        """What PX4 printed so far."""
        try:
            return self.log.read_text(errors="replace")
        except OSError:
            return ""

    def stop(self) -> None:
        """SIGTERM to our PX4 process (its own id), SIGKILL if it lingers."""
        p, self.proc = self.proc, None
        if p is None or p.poll() is not None:
            return
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(15)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)

    def console(self, command: str, *args: str) -> str:
        """A PX4 console command (``px4-<command> --instance N ...``) and its output."""
        assert self.proc is not None, "PX4 is not running"
        runtime_bin = Path(os.readlink(f"/proc/{self.proc.pid}/exe")).parent
        r = subprocess.run(
            [str(runtime_bin / f"px4-{command}"), "--instance", str(self.instance), *args],
            cwd=self.workdir / "run",
            capture_output=True,
            text=True,
            timeout=30,
        )
        return r.stdout

    def set_param(self, name: str, value: int | float) -> None:
        """Set a parameter at runtime (PX4's ``param set``)."""
        self.console("param", "set", name, str(value))

    def listener(self, topic: str) -> dict[str, Any] | None:
        """The last message of a uORB topic, parsed as ``companion px4 check`` parses it."""
        from companion.drivers.px4_shell_text import parse_listener

        return parse_listener(self.console("listener", topic))

    def restart(self, params: dict[str, int | float] | None = None) -> None:
        """Stop and start again (the same work folder: saved parameters stay), with more
        boot parameters."""
        self.stop()
        self.params.update(params or {})
        self.start()


@dataclass
class Pose:
    """What the sender says (one thing wrong at a time)."""

    kind: str = "vpe"  # "vpe" or "odometry"
    frame_id: int = mavlink.MAV_FRAME_LOCAL_FRD  # ODOMETRY only
    position_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    velocity_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)  # ODOMETRY only
    drift_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)  # position moves this fast
    yaw_offset_rad: float = 0.0  # added to PX4's own heading
    quality_pct: int = 100
    rate_hz: float = 30.0


class VisionSender:
    """A MAVLink peer on PX4's onboard port (a thread): answers TIMESYNC, streams ``pose``."""

    def __init__(self, listen_port: int, px4_port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", listen_port))
        self.sock.settimeout(0.01)
        self.px4 = ("127.0.0.1", px4_port)
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=197)
        self.mav.robust_parsing = True
        self.pose = Pose()
        self.sending = True  # poses (False: "our sender stopped")
        self.answering = True  # TIMESYNC answers
        self.attitude: tuple[float, float, float] | None = None  # PX4's roll, pitch, yaw
        self.timesync_requests = 0
        self.px4_system_id = 0  # from PX4's HEARTBEAT (its instance + 1)
        self.clock_jump_ns = 0  # added to our clock (answers and stamps): a jump of it
        self.model = RequesterModel()  # PX4's time sync as our answers drive it
        self.sent = 0
        self.started = time.monotonic()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="vision-sender", daemon=True)

    def __enter__(self) -> VisionSender:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)
        self.sock.close()

    def now_ns(self) -> int:
        """Our clock [ns]: monotonic, plus the jump the test put in it."""
        return time.monotonic_ns() + self.clock_jump_ns

    def _send(self, msg: Any) -> None:
        with contextlib.suppress(OSError):
            self.sock.sendto(msg.pack(self.mav), self.px4)

    def _receive(self) -> None:
        try:
            data, _ = self.sock.recvfrom(65535)
        except (TimeoutError, OSError):
            return
        for msg in self.mav.parse_buffer(data) or []:
            kind = msg.get_type()
            if kind == "TIMESYNC" and msg.tc1 == 0:
                self.timesync_requests += 1
                if self.answering:
                    tc1 = self.now_ns()
                    self._send(self.mav.timesync_encode(tc1, msg.ts1))
                    self.model.on_answer(msg.ts1, tc1)
            elif kind == "HEARTBEAT" and msg.get_srcComponent() == 1:
                self.px4_system_id = msg.get_srcSystem()
            elif kind == "ATTITUDE":
                self.attitude = (msg.roll, msg.pitch, msg.yaw)

    def _message(self, now_s: float) -> Any:
        p = self.pose
        t = now_s - self.started
        x, y, z = (a + d * t for a, d in zip(p.position_ned_m, p.drift_m_s, strict=True))
        roll, pitch, yaw = self.attitude or (0.0, 0.0, 0.0)
        yaw += p.yaw_offset_rad
        usec = self.now_ns() // 1000
        cov = [math.nan] + [0.0] * 20  # NaN: "use EKF2's noise parameters"
        if p.kind == "vpe":
            return self.mav.vision_position_estimate_encode(usec, x, y, z, roll, pitch, yaw, cov, 0)
        cr, sr = math.cos(roll / 2), math.sin(roll / 2)
        cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
        cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
        q = [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
        vn, ve, vd = (a + d for a, d in zip(p.velocity_ned_m_s, p.drift_m_s, strict=True))
        # body FRD velocity: rotate NED by -yaw (roll and pitch are ~0 on the ground)
        vb = (math.cos(yaw) * vn + math.sin(yaw) * ve, -math.sin(yaw) * vn + math.cos(yaw) * ve, vd)
        return self.mav.odometry_encode(
            usec,
            p.frame_id,
            mavlink.MAV_FRAME_BODY_FRD,
            x,
            y,
            z,
            q,
            vb[0],
            vb[1],
            vb[2],
            0.0,
            0.0,
            0.0,
            cov,
            cov,
            0,
            mavlink.MAV_ESTIMATOR_TYPE_VISION,
            p.quality_pct,
        )

    def _run(self) -> None:
        next_pose = next_beat = time.monotonic()
        while not self._stop.is_set():
            self._receive()
            now = time.monotonic()
            if now >= next_beat:
                next_beat = now + 1.0
                self._send(
                    self.mav.heartbeat_encode(
                        mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4
                    )
                )
            if now >= next_pose:
                next_pose = max(next_pose + 1.0 / self.pose.rate_hz, now - 0.1)
                if self.sending:
                    self._send(self._message(now))
                    self.sent += 1


def ev_pos(px4: Px4Sitl) -> bool | None:
    """EKF2's cs_ev_pos (fusing our position), None when the topic did not say."""
    f = px4.listener("estimator_status_flags")
    v = f.get("cs_ev_pos") if f else None
    return v if isinstance(v, bool) else None


def ev_pos_while(px4: Px4Sitl, work: Callable[[], T]) -> tuple[set[bool | None], T]:
    """Run ``work`` while another thread samples :func:`ev_pos` (before, every 0.2 s during,
    after): the states EKF2 was seen in, and what ``work`` returned."""
    seen: set[bool | None] = {ev_pos(px4)}
    done = threading.Event()

    def sample() -> None:
        while not done.wait(0.2):
            seen.add(ev_pos(px4))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        out = work()
    finally:
        done.set()
        sampler.join()
    seen.add(ev_pos(px4))
    return seen, out
