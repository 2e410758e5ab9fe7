"""The closed loops' flight (``companion sitl px4``: sitl/loops/px4_flight.py, ``companion sitl
ardupilot``: sitl/loops/ardupilot_flight.py): :class:`LoopFlight`, the flight's skeleton (start,
fly, stop everything, summarise) with the steps both fly alike: the bridge and the service
started and waited for, the service's status socket polled until it tracks with a metric scale,
the autopilot's fusion of our estimate held, arming, the mission along its legs, the landing
and the disarm; the options both share and the command-line entry.

Positions are NED [m] in the autopilot's local frame (ours once its EKF fuses our estimate);
times [s] of our monotonic clock unless named ``*_ns``.
"""

from __future__ import annotations

import itertools
import json
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from companion.config import load_config, to_dict
from companion.errors import SitlError
from companion.sitl.loops import gps_missions
from companion.sitl.loops.ground_station import LoopTelemetry
from companion.sitl.loops.mission import leg_setpoints, mission_path
from companion.sitl.loops.processes import (
    BRIDGE_NICE,
    REPO,
    SERVICE_NICE,
    Procs,
    companion_argv,
    raise_interrupt,
)

# the mission's end: the autopilot's position within SETTLE_M [m] of the last waypoint for
# SETTLE_S [s] before the landing (at most SETTLE_TIMEOUT_S [s] of waiting)
SETTLE_M, SETTLE_S, SETTLE_TIMEOUT_S = 0.15, 1.0, 20.0


@dataclass
class LoopOptions:
    """What both loops fly (each loop's FlightOptions adds its own)."""

    out: Path
    mission: str = "square"  # one of MISSIONS
    seed: int = 1
    instance: int = 0  # the autopilot's instance: its ports shift by it
    config: Path = REPO / "config" / "px4_sitl.toml"  # the loop's camera and sensors
    altitude_m: float = 5.0
    speed_m_s: float = 3.0
    hover_s: float = 20.0
    square_m: float = 20.0
    terrain: str | None = None  # default: the config's (hills)
    configure: bool = True  # run the autopilot's `companion ... configure` before the service
    settle_s: float = 6.0  # the service tracks this long with a scale before EKF may fuse it


def options_from_args(cls: type[Any], args: Any, **own: Any) -> Any:
    """A loop's FlightOptions (``cls``) from the ``companion sitl px4|ardupilot`` arguments
    both share (--out, --mission, --seed, --instance, --no-configure, --config) and ``own``."""
    opts = cls(
        out=Path(args.out),
        mission=args.mission,
        seed=args.seed,
        instance=args.instance,
        configure=not args.no_configure,
        **own,
    )
    if args.config:
        opts.config = Path(args.config)
    return opts


class LoopFlight:
    """A closed-loop flight's skeleton and the steps both loops fly alike. A subclass sets
    ``gcs`` (a :class:`GcsBase`) and provides :meth:`_prepare`, :meth:`_start_and_fly`,
    :meth:`_stop_autopilot`, :meth:`_ev_fused` and :meth:`summarise`."""

    AUTOPILOT = "the autopilot"  # in log lines and errors: "PX4", "ArduPilot"
    ARM_LOG = "flight.log"  # where to look when it refuses to arm
    TELEMETRY: type[LoopTelemetry] = LoopTelemetry  # the loop's Telemetry
    gcs: Any

    def __init__(self, opts: Any) -> None:
        self.o = opts
        self.out: Path = opts.out.resolve()
        self.procs = Procs()
        self.tel = self.TELEMETRY()
        self.notes: list[str] = []
        self.configure_exit: int | None = None

    def log(self, msg: str) -> None:
        line = f"[{time.monotonic() - self.t_start:6.1f} s] {msg}"
        print(line, flush=True)
        with (self.out / "flight.log").open("a") as fh:
            fh.write(line + "\n")

    # ------------------------------------------------------------------ the skeleton
    def run(self) -> dict[str, Any]:
        """Start everything, fly, stop everything (also on Ctrl-C, SIGTERM or failure, noted),
        write ``summary.json`` and the subclass's telemetry files; the summary."""
        self.t_start = time.monotonic()
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "flight.log").write_text("")
        self._prepare()
        old_term = signal.signal(signal.SIGTERM, raise_interrupt)
        ok = False
        try:
            self._start_and_fly()
            ok = True
        except KeyboardInterrupt:
            self.notes.append("interrupted (Ctrl-C / SIGTERM): everything stopped")
            self.log("interrupted")
        except SitlError as e:
            self.notes.append(f"failed: {e}")
            self.log(f"FAILED: {e}")
        finally:
            signal.signal(signal.SIGTERM, old_term)
            self.log(f"stopping the service, the bridge and {self.AUTOPILOT}")
            self.procs.stop("service", signal.SIGINT)
            self.procs.stop("bridge")
            self._stop_autopilot()
        summary = self.summarise(ok)
        (self.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        self._write_telemetry()
        return summary

    def _cleared(self, name: str) -> Path:
        """OUT/name, removed if it was there (the autopilot's work folder)."""
        work = self.out / name
        if work.exists():
            shutil.rmtree(work)
        return work

    def _prepare(self) -> None:
        """After OUT and its empty flight.log are made, before the signal handler: what may
        fail (SitlError, raised from run) before anything is started."""
        raise NotImplementedError

    def _start_and_fly(self) -> None:
        """Start the autopilot, the bridge, the service; fly (SitlError on failure)."""
        raise NotImplementedError

    def _stop_autopilot(self) -> None:
        """Stop the autopilot and whatever else is left (the service and bridge are)."""
        raise NotImplementedError

    def _ev_fused(self) -> bool:
        """Whether the autopilot's EKF fuses our position now (its latest status)."""
        raise NotImplementedError

    def _set_gps(self, on: bool) -> None:
        """The simulated GPS receiver's fix on or off (the GPS missions: gps_missions.py)."""
        raise NotImplementedError

    def summarise(self, ok: bool) -> dict[str, Any]:
        raise NotImplementedError

    def _write_telemetry(self) -> None:
        """Files of what the ground station saw, after summary.json (none by default)."""

    # ------------------------------------------------------------------ setup
    def _loop_config(self) -> dict[str, Any]:
        """The loop's config (``config``) with the flight's seed and terrain, as a dict for
        the loop to point at its autopilot (then :meth:`_write_service_config`)."""
        over: dict[str, Any] = {"sitl": {"seed": self.o.seed}}
        if self.o.terrain:
            over["sitl"]["terrain"] = self.o.terrain
        loop: dict[str, Any] = to_dict(load_config(self.o.config, over))
        return loop

    def _write_service_config(self, d: dict[str, Any]) -> Path:
        """OUT/service.toml from ``d``; its path."""
        path = self.out / "service.toml"
        path.write_bytes(tomli_w.dumps(d).encode())
        return path

    def _run_configure(
        self, label: str, argv: list[str], log_name: str, timeout_s: float, **kw: Any
    ) -> int:
        """Run ``label`` (a ``companion ... configure``: ``argv``) to its end, its output into
        OUT/``log_name``; its exit code (-1: timed out after ``timeout_s``), also in
        ``configure_exit``."""
        self.log(f"{label} " + " ".join(argv[4:]))
        try:
            r = subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s, **kw)
            text, code = r.stdout + r.stderr, r.returncode
        except subprocess.TimeoutExpired as e:
            text, code = str(e.stdout or "") + f"\ntimed out after {timeout_s:g} s", -1
        (self.out / log_name).write_text(text)
        self.configure_exit = code
        self.log(f"{label} exit {code} ({log_name})")
        return code

    def _start_bridge_with(self, argv: list[str], cfg_path: Path) -> list[str]:
        """Start the bridge (``argv``), wait for its bridge.json and write its TFmini ptys into
        the service config at ``cfg_path``; the ptys."""
        info = self.out / "bridge.json"
        info.unlink(missing_ok=True)
        self.procs.start("bridge", argv, self.out / "bridge.log", nice=BRIDGE_NICE, cwd=REPO)
        self._wait_started(info, "the bridge", 120, "bridge.log")
        ptys: list[str] = json.loads(info.read_text())["rangefinder_ptys"]
        data = to_dict(load_config(cfg_path))
        for rf, dev in zip(data["rangefinders"], ptys, strict=True):
            rf["serial"] = dev
        cfg_path.write_bytes(tomli_w.dumps(data).encode())
        return ptys

    def _start_service(self) -> None:
        argv = [*companion_argv(), "run", "--config", str(self.out / "service.toml")]
        self.procs.start("service", argv, self.out / "service.log", nice=SERVICE_NICE, cwd=REPO)
        self._wait_started(self.out / "status.sock", "the service", 60, "service.log")
        self.log("service up")

    def _wait_started(self, path: Path, what: str, timeout_s: float, log_name: str) -> None:
        """Until the last started process made ``path`` (pumping the ground station)."""
        end = time.monotonic() + timeout_s
        while not path.exists():
            if time.monotonic() > end:
                raise SitlError(f"{what} did not start within {timeout_s:g} s: see {log_name}")
            if self.procs.items[-1][1].poll() is not None:
                raise SitlError(f"{what} exited: see {log_name}")
            self.gcs.pump(0.2)

    # ------------------------------------------------------------------ flight
    def _check_alive(self) -> None:
        for name, p, _ in self.procs.items:
            if p.poll() is not None:
                raise SitlError(f"{name} exited with {p.returncode} during the flight")

    def _until(self, what: str, cond: Callable[[], bool], timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while not cond():
            if time.monotonic() > end:
                raise SitlError(f"timed out after {timeout_s:g} s waiting for: {what}")
            self.gcs.pump(0.05)
            self._check_alive()

    def _phase(self, name: str) -> None:
        self.tel.phases[name] = time.monotonic()
        self.log(name)

    def _wait_heartbeat(self, timeout_s: float) -> None:
        self._until(f"{self.AUTOPILOT}'s heartbeat", lambda: self.tel.heartbeat_ns > 0, timeout_s)

    def _wait_tracking(self, what: str, timeout_s: float) -> None:
        """Until the service tracked with a scale for ``settle_s``: phase "service tracking"."""
        self._until(what, self._tracking_for(self.o.settle_s), timeout_s)
        self._phase("service tracking")

    def _wait_fused(self, what: str, seconds: float) -> None:
        """Until the autopilot fused our position for ``seconds`` (60 s at most): phase
        "ev fused"."""
        self._until(what, self._fused_for(seconds), 60)
        self._phase("ev fused")

    def _arm(self) -> None:
        """MAV_CMD_COMPONENT_ARM_DISARM until the autopilot is armed (60 s at most)."""
        end = time.monotonic() + 60
        while not self.tel.armed:
            if time.monotonic() > end:
                raise SitlError(f"{self.AUTOPILOT} refused to arm for 60 s (see {self.ARM_LOG})")
            self.gcs.command(400, 1)
            self.gcs.pump(1.0)
        self._phase("armed")

    def _fly_mission(self, start: np.ndarray) -> None:
        """The mission from ``start`` (hover: hold there for ``hover_s``), then the phase
        "landing" (the caller lands)."""
        o = self.o
        self._phase(f"mission {o.mission}")
        if gps_missions.is_gps_mission(o.mission):
            gps_missions.fly(self, start)
        elif o.mission == "hover":
            self.gcs.pump(o.hover_s)
            self.gcs.pump(2.0)
        else:
            pts = mission_path(o.mission, start, o.square_m)
            self._follow(pts, o.speed_m_s)
            self._settle_over(pts[-1])
        self._phase("landing")

    def _settle_over(self, target: np.ndarray) -> None:
        """Hold the last waypoint until the autopilot's own position has stayed within
        SETTLE_M of it horizontally for SETTLE_S (a mission's end, as a return-to-home waits
        over home before it descends: the landing then starts where the mission ended, not
        where the braking overshoot put the vehicle); at most SETTLE_TIMEOUT_S, then a note."""
        g = self.gcs
        g.setpoint = (target.copy(), np.zeros(3))
        end_s = time.monotonic() + SETTLE_TIMEOUT_S
        while time.monotonic() < end_s:
            g.pump(0.1)
            self._check_alive()
            since_ns = time.monotonic_ns() - int(SETTLE_S * 1e9)
            recent = [r for r in self.tel.lpos if r[0] >= since_ns]  # (arrival ns, ..., x, y, z)
            if not recent or recent[0][0] - since_ns > 0.2e9:
                continue  # not a whole SETTLE_S of positions yet
            off = np.array([r[2:4] for r in recent]) - target[:2]
            if float(np.max(np.hypot(off[:, 0], off[:, 1]))) <= SETTLE_M:
                return
        self.notes.append(f"did not settle within {SETTLE_M} m of the mission's end")

    def _wait_disarmed(self) -> None:
        self._until("disarmed after landing", lambda: not self.tel.armed, 90)
        self._phase("disarmed")
        self.gcs.pump(2.0)

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

    def _tracking_for(self, seconds: float) -> Callable[[], bool]:
        """A condition: the service has tracked with a metric scale, without a VO reset, for
        ``seconds`` (its status asked every 0.5 s at most)."""
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
            return bool(time.monotonic() - since[0] >= seconds)

        return cond

    def _fused_for(self, seconds: float) -> Callable[[], bool]:
        """A condition: the autopilot has fused our position (:meth:`_ev_fused`) for
        ``seconds`` without a break."""
        since: list[float] = []

        def cond() -> bool:
            if not self._ev_fused():
                since.clear()
                return False
            if not since:
                since.append(time.monotonic())
            return time.monotonic() - since[0] >= seconds

        return cond


def fly_from_cli(flight: LoopFlight, find_autopilot: Callable[[], Any]) -> int:
    """``companion sitl px4|ardupilot``: exit 2 when the autopilot is not found (said on
    stderr), else fly and print the summary's scalars and failsafes; exit 0 when landed without
    a failsafe, else 1."""
    try:
        find_autopilot()
    except SitlError as e:
        print(f"companion: {e}", file=sys.stderr)
        return 2
    summary = flight.run()
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
