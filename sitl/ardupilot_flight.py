"""``companion sitl ardupilot``: the real ArduCopter flies on our estimate, ground to ground.

Processes (each in its own process group, all stopped on exit, Ctrl-C, SIGTERM or failure):

1. ArduCopter SITL (sitl/ardupilot_sitl.py, the ``odom`` profile: GPS off, EK3_SRC1_* = 6,
   VISO_TYPE = 1) with BOOT_PARAMS on top; this process is its ground station on SERIAL0.
2. ``companion autopilot configure --yes`` on SERIAL1 before the service holds it (reported;
   the flight goes on with the boot parameters when it fails).
3. The bridge (``python -m sitl.ardupilot_bridge`` on SERIAL2): SIM_STATE truth -> our camera
   stream and TFmini ptys (the PX4 bridge's code).
4. The service, unchanged: ``companion run --config OUT/service.toml`` on SERIAL1, sending
   ODOMETRY and the EKF origin ([service.ardupilot]).
5. This process: waits until the service tracks with a metric scale on the ground and EKF3 uses
   our external navigation (EKF_STATUS_REPORT: relative horizontal position, not constant-
   position mode), arms in GUIDED, takes off to 5 m (MAV_CMD_NAV_TAKEOFF), flies the mission
   with SET_POSITION_TARGET_LOCAL_NED (position + velocity, EKF3's local frame = ours), comes
   back to where the mission started, lands (LAND) and waits for the auto-disarm.

Afterwards: ``summary.json`` (the fields of the PX4 loop's summary where they apply;
sitl/ardupilot_results.py) from the truth the bridge logged and the ground station's telemetry.
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from companion.config import load_config, to_dict
from companion.errors import SitlError
from sitl.ardupilot_sitl import REPO, ArduPilotSitl, find_ardupilot, port
from sitl.px4_flight import Procs, leg_setpoints, mission_path

HOME = (-35.363261, 149.165230, 584.0)  # the launcher's --home: the EKF origin we send
BOOT_PARAMS: dict[str, float] = {
    # the odom profile's external navigation, spelled out (the check reads them back)
    "VISO_TYPE": 1,
    "GPS1_TYPE": 0,
    "SIM_GPS1_ENABLE": 0,
    "EK3_SRC1_POSXY": 6,
    "EK3_SRC1_VELXY": 6,
    "EK3_SRC1_POSZ": 6,
    "EK3_SRC1_VELZ": 6,
    "EK3_SRC1_YAW": 6,  # --heading extnav; --heading compass: HEADING_COMPASS_PARAMS
    # our exposure-to-send latency: the service's p50 was 36-46 ms in these runs (2 cores
    # shared with the renderer); EKF3 moves our samples back by it after its jitter correction
    # (docs/decisions.md, "ArduPilot's dialect")
    "VISO_DELAY_MS": 35,
    # the take-off climb at 1 m/s (default 2.5): the camera's view grows slowly enough for the
    # VO to keep its features (the PX4 loop climbs at 1 m/s too)
    "WPNAV_SPEED_UP": 100,
    # GUIDED keeps the heading (default 2 turns towards each target)
    "WP_YAW_BEHAVIOR": 0,
}
# The site's magnetic declination [deg, east positive] at the launcher's home in ArduPilot's own
# field model, as a user would look it up for their site (NOAA's or BGS's calculator): its
# compass reads the vehicle's true heading of -7.0 deg (SIM_STATE) as -19.8 deg magnetic
# (SCALED_IMU, tilt-compensated; EKF3 with COMPASS_DEC 0 said -19.8 to -19.9), and with 12.87
# EKF3's heading at rest is the truth's (docs/RESULTS.md, "Heading").
SITE_DECLINATION_DEG = 12.87
HEADING_COMPASS_PARAMS: dict[str, float] = {
    "EK3_SRC1_YAW": 1,  # compass: EKF3's north is true north (with the declination)
    "COMPASS_DEC": round(float(np.radians(SITE_DECLINATION_DEG)), 5),
    "COMPASS_AUTODEC": 0,
}
HEADINGS = ("compass", "extnav")
MODE_GUIDED, MODE_LAND = 4, 9
EKF_POS_HORIZ_REL, EKF_CONST_POS_MODE = 0x08, 0x80
CAMERA_PORT = 15700  # + instance


@dataclass
class FlightOptions:
    out: Path
    ardupilot: str | None = None
    mission: str = "square"
    seed: int = 1
    instance: int = 0
    config: Path = REPO / "config" / "px4_sitl.toml"  # the loop's camera and sensors
    altitude_m: float = 5.0
    speed_m_s: float = 3.0
    hover_s: float = 20.0
    square_m: float = 20.0
    terrain: str | None = None
    configure: bool = True  # run `companion autopilot configure` before the service
    settle_s: float = 6.0  # the service tracks this long with a scale before arming
    # EKF3's heading: "compass" (+ the site's declination: EKF3's north is true north) or
    # "extnav" (ours alone: EKF3's north is the vehicle's first heading)
    heading: str = "compass"
    params: dict[str, float] = field(default_factory=dict)  # on top of BOOT_PARAMS


@dataclass
class Telemetry:
    """What the ground station saw (arrival times: our monotonic clock [ns])."""

    lpos: list[tuple[int, int, float, float, float]] = field(default_factory=list)
    ekf: list[tuple[int, int]] = field(default_factory=list)  # (t, EKF_STATUS_REPORT.flags)
    yaw: list[tuple[int, float]] = field(default_factory=list)  # (t, ATTITUDE.yaw [rad])
    texts: list[tuple[float, int, str]] = field(default_factory=list)
    armed: bool = False
    custom_mode: int = -1
    heartbeat_ns: int = 0
    landed_state: int = 0
    version: str = ""
    phases: dict[str, float] = field(default_factory=dict)  # name -> monotonic [s]


class Gcs:
    """A minimal ground station on ArduCopter's SERIAL0 (pymavlink), pumped from this thread."""

    def __init__(self, url: str, tel: Telemetry) -> None:
        os.environ["MAVLINK20"] = "1"
        from pymavlink import mavutil

        self.conn = mavutil.mavlink_connection(
            url, source_system=255, source_component=190, dialect="ardupilotmega"
        )
        self.mav = self.conn.mav
        self.sysid = 1
        self.tel = tel
        self.setpoint: tuple[np.ndarray, np.ndarray] | None = None
        self._last_sp = 0.0
        self._last_hb = 0.0
        self.t0 = time.monotonic()

    def pump(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while True:
            now = time.monotonic()
            if now - self._last_hb > 1.0:
                self.mav.heartbeat_send(6, 8, 0, 0, 0)
                self._last_hb = now
            if self.setpoint is not None and now - self._last_sp > 0.05:
                p, v = self.setpoint
                self.mav.set_position_target_local_ned_send(
                    0,
                    self.sysid,
                    1,
                    1,  # MAV_FRAME_LOCAL_NED: from the EKF origin
                    0b0000_1101_1100_0000,  # position + velocity; no acceleration, no yaw
                    *(float(x) for x in p),
                    *(float(x) for x in v),
                    0,
                    0,
                    0,
                    0,
                    0,
                )
                self._last_sp = now
            if now >= end:
                return
            m = self.conn.recv_match(blocking=True, timeout=min(0.01, max(end - now, 0.001)))
            while m is not None:
                self._on(m)
                m = self.conn.recv_match(blocking=False)

    def _on(self, m: Any) -> None:
        kind = m.get_type()
        if m.get_srcSystem() != self.sysid or m.get_srcComponent() != 1:
            return
        t = time.monotonic_ns()
        if kind == "LOCAL_POSITION_NED":
            self.tel.lpos.append((t, int(m.time_boot_ms), m.x, m.y, m.z))
        elif kind == "EKF_STATUS_REPORT":
            self.tel.ekf.append((t, int(m.flags)))
        elif kind == "ATTITUDE":
            self.tel.yaw.append((t, float(m.yaw)))
        elif kind == "HEARTBEAT":
            self.tel.armed = bool(m.base_mode & 128)
            self.tel.custom_mode = int(m.custom_mode)
            self.tel.heartbeat_ns = t
        elif kind == "EXTENDED_SYS_STATE":
            self.tel.landed_state = int(m.landed_state)
        elif kind == "STATUSTEXT":
            self.tel.texts.append((time.monotonic() - self.t0, int(m.severity), str(m.text)))
        elif kind == "AUTOPILOT_VERSION":
            v = int(m.flight_sw_version)
            self.tel.version = f"ArduCopter {v >> 24 & 255}.{v >> 16 & 255}.{v >> 8 & 255}"

    def command(self, cmd: int, *params: float) -> None:
        p = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
        self.mav.command_long_send(self.sysid, 1, cmd, 0, *p)

    def set_mode(self, mode: int) -> None:
        self.command(176, 1, mode)  # MAV_CMD_DO_SET_MODE, custom

    def position(self) -> np.ndarray | None:
        return np.array(self.tel.lpos[-1][2:5]) if self.tel.lpos else None

    def ekf_uses_ours(self, within_s: float = 1.0) -> bool:
        if not self.tel.ekf:
            return False
        t, flags = self.tel.ekf[-1]
        fresh = time.monotonic_ns() - t < within_s * 1e9
        return fresh and bool(flags & EKF_POS_HORIZ_REL) and not flags & EKF_CONST_POS_MODE


def _companion() -> list[str]:
    exe = Path(sys.executable).parent / "companion"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "companion.cli"]


def _raise_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


class Flight:
    def __init__(self, opts: FlightOptions) -> None:
        self.o = opts
        self.out = opts.out.resolve()
        self.procs = Procs()
        self.tel = Telemetry()
        self.notes: list[str] = []
        self.configure_exit: int | None = None

    def log(self, msg: str) -> None:
        line = f"[{time.monotonic() - self.t_start:6.1f} s] {msg}"
        print(line, flush=True)
        with (self.out / "flight.log").open("a") as fh:
            fh.write(line + "\n")

    # ------------------------------------------------------------------ setup
    def run(self) -> dict[str, Any]:
        self.t_start = time.monotonic()
        self.wall_minus_mono_s = time.time() - time.monotonic()  # the service logs wall time
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "flight.log").write_text("")
        work = self.out / "ardupilot"
        if work.exists():
            shutil.rmtree(work)
        n = self.o.instance
        if self.o.heading not in HEADINGS:
            raise SitlError(f"heading {self.o.heading!r}: one of {', '.join(HEADINGS)}")
        params = dict(BOOT_PARAMS)
        if self.o.heading == "compass":
            params.update(HEADING_COMPASS_PARAMS)
        self.ap = ArduPilotSitl(work, "odom", {**params, **self.o.params}, n, self.o.ardupilot)
        old_term = signal.signal(signal.SIGTERM, _raise_interrupt)
        ok = False
        try:
            self.log(f"ArduPilot SITL {self.ap.launcher} instance {n}, work folder {work}")
            self.ap.start()
            self.gcs = Gcs(f"tcp:127.0.0.1:{port(0, n)}", self.tel)
            self.gcs.pump(1.0)
            for msg_id, hz in ((32, 50.0), (193, 10.0), (245, 5.0), (30, 10.0)):
                self.gcs.command(511, msg_id, 1e6 / hz)
                self.gcs.pump(0.1)
            self.gcs.command(512, 148)  # AUTOPILOT_VERSION
            cfg_path = self._service_config_base()
            self._start_bridge(cfg_path)  # first: configure judges the final sensor set
            self._configure(cfg_path)
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
            self.log("stopping the service, the bridge and ArduPilot")
            self.procs.stop("service", signal.SIGINT)
            self.procs.stop("bridge")
            self.procs.stop_all()
            self.ap.stop()
        from sitl.ardupilot_results import summarise

        summary = summarise(self, ok)
        (self.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        with (self.out / "ekf.csv").open("w") as fh:  # EKF3's position and flags as received
            fh.write("t_ns,time_boot_ms,n_m,e_m,d_m\n")
            fh.writelines(f"{t},{b},{x:.4f},{y:.4f},{z:.4f}\n" for t, b, x, y, z in self.tel.lpos)
        with (self.out / "ekf-status.csv").open("w") as fh:
            fh.write("t_ns,flags\n")
            fh.writelines(f"{t},{f}\n" for t, f in self.tel.ekf)
        (self.out / "statustext.log").write_text(
            "".join(f"{t:7.1f} {sev} {text}\n" for t, sev, text in self.tel.texts)
        )
        return summary

    def _service_config_base(self) -> Path:
        over: dict[str, Any] = {"sitl": {"seed": self.o.seed}}
        if self.o.terrain:
            over["sitl"]["terrain"] = self.o.terrain
        d = to_dict(load_config(self.o.config, over))
        n = self.o.instance
        svc = d["service"]
        svc["mavlink_url"] = f"tcp:127.0.0.1:{port(1, n)}"
        svc["system_id"] = 1
        svc["output"] = "odometry"
        svc["camera_url"] = f"sitl://127.0.0.1:{CAMERA_PORT + n}"
        svc["status_socket"] = str(self.out / "status.sock")
        svc["report_path"] = str(self.out / "service-report.json")
        svc["state_dir"] = str(self.out / "state")
        svc["ardupilot"] = {
            "set_origin": True,
            "origin_lat_deg": HOME[0],
            "origin_lon_deg": HOME[1],
            "origin_alt_m": HOME[2],
            "set_declination": self.o.heading == "compass",
            "declination_deg": SITE_DECLINATION_DEG,
        }
        path = self.out / "service.toml"
        path.write_bytes(tomli_w.dumps(d).encode())
        return path

    def _configure(self, cfg_path: Path) -> None:
        if not self.o.configure:
            return
        url = f"tcp:127.0.0.1:{port(1, self.o.instance)}"
        argv = [*_companion(), "autopilot", "configure", "--config", str(cfg_path)]
        argv += ["--url", url, "--yes", "--no-gnss", "--timeout-s", "15"]
        self.log("companion autopilot configure " + " ".join(argv[4:]))
        try:
            r = subprocess.run(argv, capture_output=True, text=True, timeout=90)
            text, code = r.stdout + r.stderr, r.returncode
        except subprocess.TimeoutExpired as e:
            text, code = str(e.stdout or "") + "\ntimed out after 90 s", -1
        (self.out / "autopilot-configure.log").write_text(text)
        self.configure_exit = code
        self.log(f"companion autopilot configure exit {code} (autopilot-configure.log)")
        if code != 0:
            self.notes.append(
                f"companion autopilot configure exited {code}: flown with the boot parameters; "
                "see autopilot-configure.log"
            )

    def _start_bridge(self, cfg_path: Path) -> None:
        info = self.out / "bridge.json"
        info.unlink(missing_ok=True)
        n = self.o.instance
        argv = [sys.executable, "-m", "sitl.ardupilot_bridge", "--config", str(cfg_path)]
        argv += ["--truth-url", f"tcp:127.0.0.1:{port(2, n)}"]
        argv += ["--camera-port", str(CAMERA_PORT + n), "--out", str(self.out)]
        self.procs.start("bridge", argv, self.out / "bridge.log", cwd=REPO)
        end = time.monotonic() + 120
        while not info.exists():
            if time.monotonic() > end:
                raise SitlError("the bridge did not start within 120 s: see bridge.log")
            if self.procs.items[-1][1].poll() is not None:
                raise SitlError("the bridge exited: see bridge.log")
            self.gcs.pump(0.2)
        ptys = json.loads(info.read_text())["rangefinder_ptys"]
        data = to_dict(load_config(cfg_path))
        for rf, dev in zip(data["rangefinders"], ptys, strict=True):
            rf["serial"] = dev
        cfg_path.write_bytes(tomli_w.dumps(data).encode())
        self.log(f"bridge up: camera on {CAMERA_PORT + n}, TFmini ptys {ptys}")

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
        if not self.ap.alive():
            raise SitlError("ArduPilot SITL exited during the flight")

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
        self._until("ArduPilot's heartbeat", lambda: self.tel.heartbeat_ns > 0, 30)
        self._start_service()
        self._until("the service tracking with a scale", self._tracking_for(o.settle_s), 120)
        self._phase("service tracking")
        self._until("EKF3 using our external navigation", self._fused_for(2.0), 60)
        self._phase("ev fused")
        g.set_mode(MODE_GUIDED)
        self._until("GUIDED mode", lambda: self.tel.custom_mode == MODE_GUIDED, 10)
        self._arm()
        g.command(22, 0, 0, 0, 0, 0, 0, o.altitude_m)  # MAV_CMD_NAV_TAKEOFF
        self._phase("take-off")

        def high() -> bool:
            p = g.position()
            return p is not None and -p[2] >= o.altitude_m - 0.3

        self._until(f"{o.altitude_m:g} m (EKF3's height)", high, 40)
        g.pump(2.0)
        here = g.position()
        assert here is not None
        start = np.array([here[0], here[1], -o.altitude_m])
        g.setpoint = (start.copy(), np.zeros(3))
        g.pump(1.0)
        self._phase(f"mission {o.mission}")
        if o.mission == "hover":
            g.pump(o.hover_s)
        else:
            self._follow(mission_path(o.mission, start, o.square_m), o.speed_m_s)
        g.pump(2.0)
        self._phase("landing")
        g.setpoint = None
        g.set_mode(MODE_LAND)
        self._until("LAND mode", lambda: self.tel.custom_mode == MODE_LAND, 10)
        self._until("disarmed after landing", lambda: not self.tel.armed, 90)
        self._phase("disarmed")
        g.pump(2.0)

    def _arm(self) -> None:
        """MAV_CMD_COMPONENT_ARM_DISARM until ArduPilot is armed (60 s at most)."""
        end = time.monotonic() + 60
        while not self.tel.armed:
            if time.monotonic() > end:
                raise SitlError("ArduPilot refused to arm for 60 s (see statustext.log)")
            self.gcs.command(400, 1)
            self.gcs.pump(1.0)
        self._phase("armed")

    def _follow(self, pts: list[np.ndarray], speed: float) -> None:
        """Setpoints along the polyline (stop at each corner, 1 s to settle)."""
        g = self.gcs
        for a, b in itertools.pairwise(pts):
            t0 = time.monotonic()
            for t, p, v in leg_setpoints(a, b, speed):
                g.pump(max(0.0, t0 + t - time.monotonic()))
                g.setpoint = (p, v)
            g.pump(1.0)
            self._check_alive()

    def _status(self) -> dict[str, Any]:
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
        since: list[Any] = []
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
            if not self.gcs.ekf_uses_ours():
                since.clear()
                return False
            if not since:
                since.append(time.monotonic())
            return time.monotonic() - since[0] >= seconds

        return cond


def cli_main(args: Any) -> int:
    """``companion sitl ardupilot``: fly, print the summary, exit 0 when landed without
    failsafe."""
    opts = FlightOptions(
        out=Path(args.out),
        ardupilot=args.ardupilot,
        mission=args.mission,
        seed=args.seed,
        instance=args.instance,
        configure=not args.no_configure,
        heading=args.heading,
    )
    if args.config:
        opts.config = Path(args.config)
    try:
        find_ardupilot(opts.ardupilot)
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
