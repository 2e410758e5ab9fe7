"""``companion sitl px4``: the real PX4 (SIH) flies on our estimate, from the ground to the ground.

Processes (each in its own process group, all stopped on exit, Ctrl-C, SIGTERM or failure):

1. PX4 SITL (``px4-sitl INSTANCE WORKDIR``) with GPS off and vision on at boot
   (SENS_EN_GPSSIM=0, SYS_HAS_GPS=0, EKF2_GPS_CTRL=0, EKF2_EV_CTRL=11, EKF2_HGT_REF=3) and
   EKF2_RNG_CTRL=0 (PX4's own simulated rangefinder measures SIH's flat ground; EKF2 does not
   use it: our distance sensors go to the companion), EKF2_MAG_DECL=4.7, EKF2_EVP_NOISE=0.03
   (docs/decisions.md, "PX4 SIH in the loop").
2. ``companion px4 configure`` on the onboard link (before the service holds it): reported,
   and the flight goes on with the boot parameters when it fails.
3. The bridge (``python -m sitl.px4_bridge``): SIH truth -> our camera stream and TFmini ptys.
4. The service, unchanged: ``companion run --config OUT/service.toml`` on PX4's onboard port.
5. This process: the ground station (pymavlink on PX4's GCS port 18570+N). By default (the
   ground start of issue 18) it starts the service on the ground, waits until the service has
   tracked with a metric scale for a while and EKF2 fuses our position, arms in Position mode,
   climbs to 5 m in Offboard mode on our estimate, flies the mission in Offboard mode
   (position + velocity setpoints in PX4's local frame, which after EKF2's reset to vision is
   our frame), comes back to where the mission started, lands (AUTO.LAND) and waits for the
   disarm. With ``--air-start`` (the take-off before the ground start existed) it arms in
   Altitude mode with EKF2_EV_CTRL=0, climbs to 5 m on the throttle stick watching PX4's own
   rangefinder, starts the service, sets EKF2_EV_CTRL=11 once the service has tracked for
   6 s and switches to Position mode once EKF2 fuses our position.

Afterwards: ``summary.json``, ``flight.png`` (PX4's estimate, ours as PX4 received it, and the
truth, top and side; EKF2's EV fusion flag and innovations; latency) from the truth the bridge
logged, the GCS telemetry and PX4's .ulg log (copied into the output folder).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from companion.config import load_config, to_dict
from companion.errors import SitlError

REPO = Path(__file__).resolve().parent.parent
SHARED_PX4 = REPO.parent / "shared" / "px4-sitl" / "px4-sitl"
BUILD_HELP = (
    "PX4 SITL not found: pass --px4 PATH or set PX4_SITL to a launcher with the interface "
    "`px4-sitl INSTANCE WORKDIR` (../shared/px4-sitl/px4-sitl is used when present). To build "
    "one: clone PX4-Autopilot with its submodules, `make px4_sitl_default`, and run "
    "`PX4_SYS_AUTOSTART=10040 PX4_SIM_MODEL=sihsim_quadx build/px4_sitl_default/bin/px4 -i N "
    "-w WORKDIR build/px4_sitl_default/etc` from the launcher (docs/install.md, 'PX4 SITL')."
)
BOOT_PARAMS = {
    "SENS_EN_GPSSIM": "0",
    "SYS_HAS_GPS": "0",
    "EKF2_GPS_CTRL": "0",
    "EKF2_EV_CTRL": "11",
    "EKF2_HGT_REF": "3",
    "EKF2_RNG_CTRL": "0",
    # without GPS EKF2 takes the declination from this parameter (default 0): SIH's magnetic
    # field at its home has 4.7 deg E (PX4's heading was 4.7 deg off the truth on the ground),
    # a user sets their site's declination the same way
    "EKF2_MAG_DECL": "4.7",
    # the floor EKF2 puts under our position variance (default 0.1 m): ours is ~4 cm here (as
    # its covariance says); with the floor PX4's position lagged ours more (docs/decisions.md)
    "EKF2_EVP_NOISE": "0.03",
}
SERIAL_CONTROL_DEV_SHELL = 10
SERIAL_CONTROL_FLAG_RESPOND, SERIAL_CONTROL_FLAG_EXCLUSIVE = 2, 4
_BEFORE_TIMESTAMP = re.compile(r"timestamp_sample:\s*\d+\s*\((-?\d+)\s+us before timestamp\)")
TIMESYNC_WAIT_S = 120.0  # PX4 needs ~500 TIMESYNC answers (~50 s at 10 Hz) after we start
# PX4 custom modes (main mode << 16 | sub mode << 24)
MODE_ALTCTL, MODE_POSCTL, MODE_AUTO, MODE_OFFBOARD = 2, 3, 4, 6
SUB_AUTO_LAND = 6
ESTIMATOR_POS_HORIZ_REL = 8
MISSIONS = ("square", "lawnmower", "hover")


def find_px4(path: str | None) -> Path:
    """--px4, else $PX4_SITL, else ../shared/px4-sitl/px4-sitl; SitlError saying how to build."""
    for cand in (path, os.environ.get("PX4_SITL")):
        if cand:
            p = Path(cand).expanduser()
            if p.is_file() and os.access(p, os.X_OK):
                return p.resolve()
            raise SitlError(f"PX4 SITL launcher {cand!r} is not an executable file. {BUILD_HELP}")
    if SHARED_PX4.is_file():
        return SHARED_PX4
    raise SitlError(BUILD_HELP)


@dataclass
class FlightOptions:
    out: Path
    px4: str | None = None
    mission: str = "square"
    seed: int = 1
    instance: int = 0
    config: Path = REPO / "config" / "px4_sitl.toml"
    altitude_m: float = 5.0
    speed_m_s: float = 3.0
    hover_s: float = 20.0
    square_m: float = 20.0
    terrain: str | None = None  # default: the config's (hills)
    configure: bool = True  # run `companion px4 configure` before the service
    ground_start: bool = True  # the companion initialises on the ground, PX4 arms in Position
    settle_s: float = 6.0  # the VO tracks this long in the air before EKF2 may fuse it
    # arm only once PX4 converts our stamps through its time sync (as `companion px4 check`
    # advises): before, it stamps our samples at arrival and the latency is not compensated
    wait_timesync: bool = True


@dataclass
class Telemetry:
    """What the ground station saw (arrival times: our monotonic clock [ns])."""

    lpos: list[tuple[int, int, float, float, float]] = field(default_factory=list)
    est: list[tuple[int, int, float, float, float]] = field(default_factory=list)
    texts: list[tuple[float, int, str]] = field(default_factory=list)
    landed_state: int = 0
    armed: bool = False
    custom_mode: int = 0
    heartbeat_ns: int = 0
    version: str = ""
    phases: dict[str, float] = field(default_factory=dict)  # name -> monotonic [s]


class Procs:
    """The processes this run started (own process groups), stopped in reverse order."""

    def __init__(self) -> None:
        self.items: list[tuple[str, subprocess.Popen[bytes], int]] = []

    def start(self, name: str, argv: list[str], log: Path, **kw: Any) -> subprocess.Popen[bytes]:
        fh = log.open("wb")
        p = subprocess.Popen(
            argv, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True, **kw
        )
        fh.close()
        self.items.append((name, p, signal.SIGTERM))
        return p

    def stop(self, name: str, sig: int = signal.SIGTERM, timeout_s: float = 15.0) -> None:
        for n, p, _ in self.items:
            if n == name and p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, sig)
                try:
                    p.wait(timeout_s)
                except subprocess.TimeoutExpired:
                    with contextlib.suppress(ProcessLookupError):
                        os.killpg(p.pid, signal.SIGKILL)
                    p.wait(5)

    def stop_all(self) -> None:
        for name, _, _ in reversed(self.items):
            self.stop(name)


class Gcs:
    """A minimal ground station on PX4's GCS port (pymavlink), pumped from this thread."""

    def __init__(self, instance: int, tel: Telemetry) -> None:
        from pymavlink import mavutil

        self.conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{18570 + instance}", source_system=255, source_component=190
        )
        self.mav = self.conn.mav
        self.sysid = instance + 1  # PX4 SITL: MAV_SYS_ID = 1 + instance
        self.tel = tel
        self.sticks = (0, 0, 500, 0)  # x pitch, y roll, z throttle (500 = hold), r yaw
        self.setpoint: tuple[np.ndarray, np.ndarray] | None = None  # NED position, velocity
        self._last_manual = 0.0
        self.params: dict[str, float] = {}
        self.range_m: tuple[float, float] | None = None  # PX4's own rangefinder: (time, m)
        self.hold_range_m: float | None = None  # throttle stick holds this range (Altitude mode)
        self._last_hb = 0.0
        self.t0 = time.monotonic()
        self._shell_out: list[bytes] = []  # SERIAL_CONTROL replies of PX4's MAVLink shell

    def pump(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while True:
            now = time.monotonic()
            if now - self._last_hb > 1.0:
                self.mav.heartbeat_send(6, 8, 0, 0, 0)  # GCS, INVALID autopilot
                self._last_hb = now
            if now - self._last_manual > 0.05:
                x, y, z, r = self.sticks
                rng, hold = self.range_m, self.hold_range_m
                if hold is not None and rng is not None and now - rng[0] < 0.5:
                    # a pilot watching the height: proportional on the throttle stick
                    z = int(np.clip(500 + 200 * (hold - rng[1]), 300, 800))
                self.mav.manual_control_send(self.sysid, x, y, z, r, 0)
                if self.setpoint is not None:
                    p, v = self.setpoint
                    # type_mask: position + velocity, no acceleration, no yaw rate (3576 - yaw)
                    self.mav.set_position_target_local_ned_send(
                        0,
                        self.sysid,
                        1,
                        1,
                        0b0000_1100_0000_0000 | 0b0001_1100_0000,
                        float(p[0]),
                        float(p[1]),
                        float(p[2]),
                        float(v[0]),
                        float(v[1]),
                        float(v[2]),
                        0,
                        0,
                        0,
                        0,
                        0,
                    )
                self._last_manual = now
            if now >= end:
                return
            m = self.conn.recv_match(blocking=True, timeout=min(0.01, max(end - now, 0.001)))
            while m is not None:
                self._on(m)
                m = self.conn.recv_match(blocking=False)

    def _on(self, m: Any) -> None:
        kind = m.get_type()
        t = time.monotonic_ns()
        if m.get_srcSystem() != self.sysid or m.get_srcComponent() != 1:
            return
        if kind == "LOCAL_POSITION_NED":
            self.tel.lpos.append((t, int(m.time_boot_ms), m.x, m.y, m.z))
        elif kind == "ESTIMATOR_STATUS":
            self.tel.est.append(
                (t, int(m.flags), m.pos_horiz_ratio, m.pos_vert_ratio, m.hagl_ratio)
            )
        elif kind == "HEARTBEAT":
            self.tel.armed = bool(m.base_mode & 128)
            self.tel.custom_mode = int(m.custom_mode)
            self.tel.heartbeat_ns = t
        elif kind == "EXTENDED_SYS_STATE":
            self.tel.landed_state = int(m.landed_state)
        elif kind == "DISTANCE_SENSOR" and int(m.orientation) == 25:
            if 0 < int(m.current_distance) < 65535:
                self.range_m = (time.monotonic(), int(m.current_distance) * 0.01)
        elif kind == "PARAM_VALUE":
            self.params[str(m.param_id)] = float(m.param_value)
        elif kind == "SERIAL_CONTROL" and int(m.device) == SERIAL_CONTROL_DEV_SHELL:
            self._shell_out.append(bytes(m.data[: int(m.count)]))
        elif kind == "STATUSTEXT":
            self.tel.texts.append((time.monotonic() - self.t0, int(m.severity), str(m.text)))
        elif kind == "AUTOPILOT_VERSION":
            v = int(m.flight_sw_version)
            git = bytes(m.flight_custom_version)[::-1].hex()[:10] if m.flight_custom_version else ""
            self.tel.version = f"v{v >> 24 & 255}.{v >> 16 & 255}.{v >> 8 & 255} ({git})"

    def shell(self, command: str, wait_s: float = 3.0) -> str:
        """Run one command in PX4's MAVLink shell (SERIAL_CONTROL, device SHELL); its output
        until the next prompt (or ``wait_s``)."""
        self._shell_out.clear()
        data = (command + "\n").encode()
        for k in range(0, len(data), 70):
            chunk = data[k : k + 70]
            self.mav.serial_control_send(
                SERIAL_CONTROL_DEV_SHELL,
                SERIAL_CONTROL_FLAG_RESPOND | SERIAL_CONTROL_FLAG_EXCLUSIVE,
                0,
                0,
                len(chunk),
                list(chunk.ljust(70, b"\0")),
            )
        end = time.monotonic() + wait_s
        text = ""
        while time.monotonic() < end:
            self.pump(0.1)
            text = b"".join(self._shell_out).decode(errors="replace")
            if text.rstrip().endswith("nsh>") and len(text.strip()) > len("nsh>"):
                break
        return text

    def px4_stamps_converted(self) -> bool | None:
        """Whether PX4 converts our time_usec through its time sync (``listener
        vehicle_visual_odometry``: a converted stamp lies some latency before the message's
        arrival; before PX4's filter converges, after ~500 TIMESYNC answers, it stamps our
        samples with their arrival: "0 us before timestamp"). None: no answer."""
        found = _BEFORE_TIMESTAMP.search(self.shell("listener vehicle_visual_odometry -n 1"))
        return None if found is None else int(found.group(1)) != 0

    def command(self, cmd: int, *params: float) -> None:
        p = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
        self.mav.command_long_send(self.sysid, 1, cmd, 0, *p)

    def set_mode(self, main: int, sub: int = 0) -> None:
        self.command(176, 1, main, sub)  # MAV_CMD_DO_SET_MODE, custom

    def main_mode(self) -> int:
        return self.tel.custom_mode >> 16 & 0xFF

    def position(self) -> np.ndarray | None:
        if not self.tel.lpos:
            return None
        return np.array(self.tel.lpos[-1][2:5])

    def ev_fused(self, within_s: float = 0.5) -> bool:
        if not self.tel.est:
            return False
        t, flags = self.tel.est[-1][:2]
        return bool(flags & ESTIMATOR_POS_HORIZ_REL) and time.monotonic_ns() - t < within_s * 1e9


def mission_path(name: str, start: np.ndarray, side_m: float) -> list[np.ndarray]:
    """Waypoints (NED) of a mission from ``start`` at its altitude: a square of side side_m
    (north, east, south, west, back), or a lawnmower of four 30 m legs 6 m apart and back."""
    if name == "square":
        offs = [(0, 0), (side_m, 0), (side_m, side_m), (0, side_m), (0, 0)]
    elif name == "lawnmower":
        offs = [(0, 0)]
        for k in range(4):
            e = 6.0 * k
            offs += [(30.0, e), (30.0, e + 6.0)] if k % 2 == 0 else [(0.0, e), (0.0, e + 6.0)]
        offs[-1] = (offs[-1][0], 18.0)
        offs += [(0.0, 18.0), (0.0, 0.0)]
    else:
        offs = [(0, 0)]
    return [start + np.array([n, e, 0.0]) for n, e in offs]


def leg_setpoints(
    a: np.ndarray, b: np.ndarray, speed: float, accel: float = 1.0
) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """(t, position, velocity) along a straight leg with a trapezoidal speed profile."""
    d = float(np.linalg.norm(b - a))
    if d < 1e-6:
        return []
    u = (b - a) / d
    v = min(speed, math.sqrt(accel * d))
    t_acc = v / accel
    d_acc = 0.5 * accel * t_acc**2
    t_cruise = (d - 2 * d_acc) / v
    total = 2 * t_acc + t_cruise
    out = []
    for t in np.arange(0.0, total + 1e-9, 0.05):
        if t < t_acc:
            s, sp = 0.5 * accel * t**2, accel * t
        elif t < t_acc + t_cruise:
            s, sp = d_acc + v * (t - t_acc), v
        else:
            tr = total - t
            s, sp = d - 0.5 * accel * tr**2, accel * tr
        out.append((float(t), a + u * s, u * sp))
    out.append((total, b.copy(), np.zeros(3)))
    return out


def _runtime_bin(px4: Path) -> Path | None:
    """The bin folder of the unpacked runtime of the shared launcher (its px4-* tools)."""
    tarball = px4.parent / "px4-sitl-runtime.tar.gz"
    if not tarball.is_file():
        return None
    key = (
        subprocess.run(["cksum"], stdin=tarball.open("rb"), capture_output=True, check=True)
        .stdout.split()[0]
        .decode()
    )
    cache = os.environ.get("PX4_SITL_CACHE") or (
        Path(os.environ["XDG_CACHE_HOME"]) / "px4-sitl"
        if os.environ.get("XDG_CACHE_HOME")
        else Path.home() / ".cache" / "px4-sitl"
    )
    b = Path(cache) / key / "px4-sitl-runtime" / "bin"
    return b if b.is_dir() else None


class Flight:
    def __init__(self, opts: FlightOptions) -> None:
        self.o = opts
        self.out = opts.out.resolve()
        self.procs = Procs()
        self.tel = Telemetry()
        self.notes: list[str] = []
        self.failsafes: list[str] = []

    def log(self, msg: str) -> None:
        t = time.monotonic() - self.t_start
        line = f"[{t:6.1f} s] {msg}"
        print(line, flush=True)
        with (self.out / "flight.log").open("a") as fh:
            fh.write(line + "\n")

    # ------------------------------------------------------------------ setup
    def run(self) -> dict[str, Any]:
        self.t_start = time.monotonic()
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "flight.log").write_text("")
        px4 = find_px4(self.o.px4)
        work = self.out / "px4"
        if work.exists():
            shutil.rmtree(work)
        work.mkdir()
        n = self.o.instance
        env = dict(os.environ)
        env.update({f"PX4_PARAM_{k}": v for k, v in BOOT_PARAMS.items()})
        old_term = signal.signal(signal.SIGTERM, _raise_interrupt)
        ok = False
        try:
            self.log(f"PX4 SITL {px4} instance {n}, work folder {work}")
            self.procs.start(
                "px4", [str(px4), str(n), str(work)], self.out / "px4-console.log", env=env
            )
            self._wait_console("Startup script returned successfully", 60.0)
            self.gcs = Gcs(n, self.tel)
            self.gcs.pump(1.0)
            # our ground station asks for what it plots (ESTIMATOR_STATUS 10 Hz, landed state)
            for msg_id, hz in ((230, 10.0), (245, 5.0), (32, 50.0), (132, 20.0)):
                self.gcs.command(511, msg_id, 1e6 / hz)
                self.gcs.pump(0.1)
            self.gcs.command(512, 148)  # MAV_CMD_REQUEST_MESSAGE AUTOPILOT_VERSION
            cfg_path = self._service_config_base()
            self._configure(cfg_path)
            self._start_bridge(cfg_path)
            self._fly()
            ok = True
        except KeyboardInterrupt:
            self.notes.append("interrupted (Ctrl-C / SIGTERM): everything stopped")
            self.log("interrupted")
        except SitlError as e:
            self.notes.append(f"failed: {e}")
            self.log(f"FAILED: {e}")
        finally:
            signal.signal(signal.SIGTERM, old_term)
            self.log("stopping the service, the bridge and PX4")
            self.procs.stop("service", signal.SIGINT)
            self.procs.stop("bridge")
            self.procs.stop("px4")
            self.procs.stop_all()
        summary = self.summarise(ok)
        (self.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        return summary

    def _wait_console(self, text: str, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        log = self.out / "px4-console.log"
        while time.monotonic() < end:
            if text in log.read_text(errors="replace"):
                return
            for name, p, _ in self.procs.items:
                if name == "px4" and p.poll() is not None:
                    raise SitlError(f"PX4 exited with {p.returncode}: see {log}")
            time.sleep(0.1)
        raise SitlError(f"PX4 did not print {text!r} within {timeout_s:g} s: see {log}")

    def _service_config_base(self) -> Path:
        """OUT/service.toml: our PX4-loop config with this instance's link (the TFmini ptys
        are added once the bridge made them)."""
        over: dict[str, Any] = {"sitl": {"seed": self.o.seed}}
        if self.o.terrain:
            over["sitl"]["terrain"] = self.o.terrain
        cfg = load_config(self.o.config, over)
        d = to_dict(cfg)
        d["service"]["mavlink_url"] = f"udpin:127.0.0.1:{14540 + self.o.instance}"
        d["service"]["system_id"] = 1 + self.o.instance  # PX4 SITL's MAV_SYS_ID
        d["service"]["camera_url"] = f"sitl://127.0.0.1:{15600 + self.o.instance}"
        d["service"]["status_socket"] = str(self.out / "status.sock")
        d["service"]["report_path"] = str(self.out / "service-report.json")
        # our TFminis are ids 1..n: PX4 SIH streams its own simulated rangefinder as
        # DISTANCE_SENSOR id 0 on the onboard link, and the service takes an autopilot
        # DISTANCE_SENSOR for any configured id, serial or not (it would be mixed into our
        # sensor 0: SIH's flat ground, not our terrain)
        for k, rf in enumerate(d["rangefinders"]):
            rf["sensor_id"] = k + 1
        path = self.out / "service.toml"
        path.write_bytes(tomli_w.dumps(d).encode())
        return path

    def _configure(self, cfg_path: Path) -> None:
        if not self.o.configure:
            return
        url = f"udpin:127.0.0.1:{14540 + self.o.instance}"
        argv = [
            *_companion(),
            "px4",
            "configure",
            "--config",
            str(cfg_path),
            "--url",
            url,
            "--yes",
            "--no-gnss",
            "--timeout-s",
            "10",
        ]
        self.log("companion px4 configure " + " ".join(argv[4:]))
        try:
            r = subprocess.run(
                argv, capture_output=True, text=True, timeout=60, start_new_session=True
            )
            text, code = r.stdout + r.stderr, r.returncode
        except subprocess.TimeoutExpired as e:
            text, code = str(e.stdout or "") + "\ntimed out after 60 s", -1
        (self.out / "px4-configure.log").write_text(text)
        self.configure_exit = code
        self.log(f"companion px4 configure exit {code} (px4-configure.log)")
        if code != 0:
            self.notes.append(
                f"companion px4 configure exited {code}: flown with the boot parameters "
                f"({', '.join(f'{k}={v}' for k, v in BOOT_PARAMS.items())}); see px4-configure.log"
            )

    def _start_bridge(self, cfg_path: Path) -> None:
        info = self.out / "bridge.json"
        info.unlink(missing_ok=True)
        argv = [
            sys.executable,
            "-m",
            "sitl.px4_bridge",
            "--config",
            str(cfg_path),
            "--instance",
            str(self.o.instance),
            "--camera-port",
            str(15600 + self.o.instance),
            "--out",
            str(self.out),
        ]
        self.procs.start("bridge", argv, self.out / "bridge.log", cwd=REPO)
        end = time.monotonic() + 120
        while not info.exists():
            if time.monotonic() > end:
                raise SitlError("the bridge did not start within 120 s: see bridge.log")
            if self.procs.items[-1][1].poll() is not None:
                raise SitlError("the bridge exited: see bridge.log")
            self.gcs.pump(0.2)
        ptys = json.loads(info.read_text())["rangefinder_ptys"]
        d = load_config(cfg_path)
        data = to_dict(d)
        for rf, dev in zip(data["rangefinders"], ptys, strict=True):
            rf["serial"] = dev
        cfg_path.write_bytes(tomli_w.dumps(data).encode())
        # SIH's true state at 50 Hz (25 Hz by default): a MAVLink command on the SIH link
        bin_dir = _runtime_bin(find_px4(self.o.px4))
        n = self.o.instance
        if bin_dir is not None:
            r = subprocess.run(
                [
                    str(bin_dir / "px4-mavlink"),
                    "--instance",
                    str(n),
                    "stream",
                    "-u",
                    str(19450 + n),
                    "-s",
                    "HIL_STATE_QUATERNION",
                    "-r",
                    "100",
                ],
                cwd=self.out / "px4",
                capture_output=True,
                text=True,
                timeout=20,
            )
            self.log(f"px4-mavlink stream HIL_STATE_QUATERNION 100 Hz: exit {r.returncode}")
        else:
            self.notes.append("px4-mavlink not found: HIL_STATE_QUATERNION left at PX4's rate")
        self.log(f"bridge up: camera on {15600 + n}, TFmini ptys {ptys}")

    def _start_service(self) -> None:
        argv = [*_companion(), "run", "--config", str(self.out / "service.toml")]
        self.procs.start("service", argv, self.out / "service.log", cwd=REPO)
        end = time.monotonic() + 60
        while not (self.out / "status.sock").exists():
            if time.monotonic() > end:
                raise SitlError("the service did not start within 60 s: see service.log")
            if self.procs.items[-1][1].poll() is not None:
                raise SitlError("the service exited: see service.log")
            self.gcs.pump(0.2)
        self.log("service up")

    # ------------------------------------------------------------------ flight
    def _check_alive(self) -> None:
        for name, p, _ in self.procs.items:
            if p.poll() is not None:
                raise SitlError(f"{name} exited with {p.returncode} during the flight")

    def _until(self, what: str, cond: Any, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while not cond():
            if time.monotonic() > end:
                raise SitlError(f"timed out after {timeout_s:g} s waiting for: {what}")
            self.gcs.pump(0.05)
            self._check_alive()

    def _phase(self, name: str) -> None:
        self.tel.phases[name] = time.monotonic()
        self.log(name)

    def _fly(self) -> None:
        g, o = self.gcs, self.o
        self._until("PX4's heartbeat", lambda: self.tel.heartbeat_ns > 0, 20)
        start = self._take_off_on_ours() if o.ground_start else self._take_off_in_altitude_mode()
        self._phase(f"mission {o.mission}")
        if o.mission == "hover":
            g.pump(o.hover_s)
        else:
            self._follow(mission_path(o.mission, start, o.square_m), o.speed_m_s)
        g.pump(2.0)
        self._phase("landing")
        g.set_mode(MODE_AUTO, SUB_AUTO_LAND)
        self._until("Land mode", lambda: g.main_mode() == MODE_AUTO, 10)
        g.setpoint = None
        self._until("disarmed after landing", lambda: not self.tel.armed, 90)
        self._phase("disarmed")
        g.pump(2.0)

    def _take_off_on_ours(self) -> np.ndarray:
        """The default take-off (the service's ground start, issue 18): the companion starts on
        the ground, EKF2 fuses it before arming, PX4 arms in Position mode and climbs in Offboard
        mode on our estimate. Returns the mission's start (NED, PX4's frame)."""
        g, o = self.gcs, self.o
        self._start_service()
        self._until("the service tracking on the ground", self._tracking_for(o.settle_s), 90)
        self._phase("service tracking")
        self._until("EKF2 fusing our position", self._fused_for(1.0), 60)
        self._phase("ev fused")
        self._wait_timesync()
        g.set_mode(MODE_POSCTL)
        self._until("Position mode", lambda: g.main_mode() == MODE_POSCTL, 10)
        self._arm()
        self.armed_mode = "POSCTL"
        here = g.position()
        assert here is not None
        g.setpoint = (here.copy(), np.zeros(3))
        g.pump(1.0)
        g.set_mode(MODE_OFFBOARD)
        self._until("Offboard mode", lambda: g.main_mode() == MODE_OFFBOARD, 10)
        top = here + np.array([0.0, 0.0, -o.altitude_m])
        self._phase("climb in Offboard")
        self._follow([here, top], 1.0)
        return top

    def _wait_timesync(self) -> None:
        """Before arming: until PX4 converts our exposure stamps through its time sync
        (TIMESYNC_WAIT_S at most; then flown anyway, noted). ``timesync_converged_at_arming``
        in the summary says which."""
        self.timesync_converged: bool | None = None
        if not self.o.wait_timesync:
            return
        t0 = time.monotonic()
        while time.monotonic() - t0 < TIMESYNC_WAIT_S:
            self.timesync_converged = self.gcs.px4_stamps_converted()
            if self.timesync_converged:
                break
            self.gcs.pump(2.0)
            self._check_alive()
        self.timesync_wait_s = time.monotonic() - t0
        if self.timesync_converged:
            self._phase(f"PX4's time sync converged (waited {self.timesync_wait_s:.0f} s)")
        else:
            self.notes.append(
                f"PX4's time sync had not converged after {TIMESYNC_WAIT_S:g} s "
                f"(shell said {self.timesync_converged}): flown with arrival stamps"
            )

    def _arm(self) -> None:
        """Send MAV_CMD_COMPONENT_ARM_DISARM until PX4 is armed (60 s at most)."""
        end = time.monotonic() + 60
        while not self.tel.armed:
            if time.monotonic() > end:
                raise SitlError("PX4 refused to arm for 60 s (see px4-console.log)")
            self.gcs.command(400, 1)
            self.gcs.pump(1.0)
        self._phase("armed")

    def _take_off_in_altitude_mode(self) -> np.ndarray:
        """Arm in Altitude mode, climb on the stick, start the companion in the air, fuse it,
        Position then Offboard mode. Returns the mission's start (NED, PX4's frame)."""
        g, o = self.gcs, self.o
        # arm in Altitude mode: no horizontal position yet (our VO starts in the air)
        self._set_param_int("EKF2_EV_CTRL", 0)  # until our VO has settled in the air
        g.set_mode(MODE_ALTCTL)
        self._until("Altitude mode", lambda: g.main_mode() == MODE_ALTCTL, 10)
        self._arm()
        self.armed_mode = "ALTCTL"
        # the climb and the hold before our estimate is fused are flown on PX4's own downward
        # rangefinder (SIH's, over its flat ground), as a pilot would watch the height: PX4's
        # height without vision drifts by metres here (baro)
        g.sticks = (0, 0, 800, 0)
        self._until(
            "climb on the stick",
            lambda: g.range_m is not None and g.range_m[1] >= o.altitude_m - 0.3,
            40,
        )
        g.hold_range_m = o.altitude_m
        self._phase("at the altitude (PX4's rangefinder)")
        g.pump(2.0)
        # the companion starts in the air (our VO cannot initialise on the ground yet), and
        # its estimate is fused only once the VO has tracked with a scale for a while:
        # EKF2_EV_CTRL was 0 since arming, 11 then (EKF2 resets its position and height to
        # ours); the vehicle drifts meanwhile (Altitude mode has no horizontal position)
        self._start_service()
        self._until("the service tracking with a scale", self._tracking_for(o.settle_s), 90)
        self._phase("service tracking")
        self._set_param_int("EKF2_EV_CTRL", 11)
        self._until("EKF2 fusing our position", self._fused_for(1.0), 60)
        self._phase("ev fused")
        g.set_mode(MODE_POSCTL)
        self._until("Position mode", lambda: g.main_mode() == MODE_POSCTL, 10)
        g.hold_range_m = None
        g.sticks = (0, 0, 500, 0)
        g.pump(2.0)
        here = g.position()
        assert here is not None
        g.setpoint = (here.copy(), np.zeros(3))
        g.pump(1.0)
        g.set_mode(MODE_OFFBOARD)
        self._until("Offboard mode", lambda: g.main_mode() == MODE_OFFBOARD, 10)
        return here

    def _follow(self, pts: list[np.ndarray], speed: float) -> None:
        """Offboard setpoints along the polyline (stop at each corner, 1 s to settle)."""
        g = self.gcs
        for a, b in itertools.pairwise(pts):
            t0 = time.monotonic()
            for t, p, v in leg_setpoints(a, b, speed):
                g.pump(max(0.0, t0 + t - time.monotonic()))
                g.setpoint = (p, v)
            g.pump(1.0)
            self._check_alive()

    def _set_param_int(self, name: str, value: int) -> None:
        """PARAM_SET of an INT32 (its bits in the float field, as PX4 expects), confirmed."""
        as_float = struct.unpack("<f", struct.pack("<i", value))[0]
        for _ in range(10):
            self.gcs.mav.param_set_send(self.gcs.sysid, 1, name.encode(), as_float, 6)
            self.gcs.pump(0.3)
            got = self.gcs.params.get(name)
            if got is not None and struct.unpack("<i", struct.pack("<f", got))[0] == value:
                self.log(f"{name} = {value}")
                return
        raise SitlError(f"PX4 did not confirm {name} = {value}")

    def _status(self) -> dict[str, Any]:
        """The service's `companion status` JSON (its status socket), {} when not answering."""
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sk:
                sk.settimeout(1.0)
                sk.connect(str(self.out / "status.sock"))
                buf = b""
                while not buf.endswith(b"\n"):
                    chunk = sk.recv(65536)
                    if not chunk:
                        break
                    buf += chunk
            data = json.loads(buf)
            return data if isinstance(data, dict) else {}
        except (OSError, ValueError):
            return {}

    def _tracking_for(self, seconds: float) -> Any:
        since: list[float] = []
        last = [0.0]

        def cond() -> bool:
            if time.monotonic() - last[0] < 0.5:
                return False
            last[0] = time.monotonic()
            st = self._status()
            vo = st.get("vo", {})
            ok = vo.get("state") == "TRACKING" and st.get("scale", {}).get("value") is not None
            if not ok or (since and vo.get("resets") != since[1]):
                since.clear()
                return False
            if not since:
                since.extend([time.monotonic(), vo.get("resets")])
            return time.monotonic() - since[0] >= seconds

        return cond

    def _fused_for(self, seconds: float) -> Any:
        since: list[float] = []

        def cond() -> bool:
            if not self.gcs.ev_fused():
                since.clear()
                return False
            if not since:
                since.append(time.monotonic())
            return time.monotonic() - since[0] >= seconds

        return cond

    # ------------------------------------------------------------------ results
    def summarise(self, ok: bool) -> dict[str, Any]:
        from sitl.px4_results import summarise

        return summarise(self, ok)


def _companion() -> list[str]:
    exe = Path(sys.executable).parent / "companion"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "companion.cli"]


def _raise_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def cli_main(args: Any) -> int:
    """``companion sitl px4``: fly, print the summary, exit 0 when landed without failsafe."""
    opts = FlightOptions(
        out=Path(args.out),
        px4=args.px4,
        mission=args.mission,
        seed=args.seed,
        instance=args.instance,
        configure=not args.no_configure,
        ground_start=not bool(getattr(args, "air_start", False)),
    )
    if args.config:
        opts.config = Path(args.config)
    try:
        find_px4(opts.px4)
    except SitlError as e:
        print(f"companion: {e}", file=sys.stderr)
        return 2
    summary = Flight(opts).run()
    print(
        json.dumps(
            {
                k: v
                for k, v in summary.items()
                if not isinstance(v, (list, dict)) or k == "failsafes"
            },
            indent=2,
        )
    )
    return 0 if summary.get("landed") and not summary.get("failsafes") else 1


def _asdict(o: Any) -> dict[str, Any]:
    return asdict(o)
