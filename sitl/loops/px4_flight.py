"""``companion sitl px4``: the real PX4 (SIH) flies on our estimate, from the ground to the ground.

Processes (each in its own process group, all stopped on exit, Ctrl-C, SIGTERM or failure):

1. PX4 SITL (``px4-sitl INSTANCE WORKDIR``) with GPS off and vision on at boot
   (SENS_EN_GPSSIM=0, SYS_HAS_GPS=0, EKF2_GPS_CTRL=0, EKF2_EV_CTRL=15, EKF2_HGT_REF=3) and
   EKF2_RNG_CTRL=0 (PX4's own simulated rangefinder measures SIH's flat ground; EKF2 does not
   use it: our distance sensors go to the companion), EKF2_MAG_DECL=3.3, EKF2_EVP_NOISE=0.03,
   EKF2_EVV_NOISE=0.05, EKF2_ABIAS_INIT=0.05, EKF2_DELAY_MAX=300 (docs/decisions.md, "PX4 SIH
   in the loop").
2. ``companion px4 configure`` on the onboard link (before the service holds it): reported,
   and the flight goes on with the boot parameters when it fails.
3. The bridge (``python -m companion.sitl.loops.px4_bridge``): SIH truth -> our camera stream
   and TFmini ptys.
4. The service, unchanged: ``companion run --config OUT/service.toml`` on PX4's onboard port.
5. This process: the ground station (pymavlink on PX4's GCS port 18570+N). By default (the
   ground start of issue 18) it starts the service on the ground, waits until the service has
   tracked with a metric scale for a while, EKF2 fuses our position, PX4's time sync converts
   our stamps and EKF2 has fused us for ``ground_hold_s`` (45 s), arms in Position mode,
   climbs to 5 m in Offboard mode on our estimate, flies the mission in Offboard mode
   (position + velocity setpoints in PX4's local frame, which after EKF2's reset to vision is
   our frame), comes back to where the mission started, lands (AUTO.LAND) and waits for the
   disarm. With ``--air-start`` (the take-off before the ground start existed) it arms in
   Altitude mode with EKF2_EV_CTRL=0, climbs to 5 m on the throttle stick watching PX4's own
   rangefinder, starts the service, sets EKF2_EV_CTRL=15 once the service has tracked for
   6 s and switches to Position mode once EKF2 fuses our position.

Afterwards: ``summary.json``, ``flight.png`` (PX4's estimate, ours as PX4 received it, and the
truth, top and side; EKF2's EV fusion flag and innovations; latency) from the truth the bridge
logged, the GCS telemetry and PX4's .ulg log (copied into the output folder).
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.drivers.px4_shell_text import parse_listener
from companion.errors import SitlError
from companion.sitl.loops import gps_missions
from companion.sitl.loops.ground_station import GcsBase, LoopTelemetry
from companion.sitl.loops.loop_flight import (
    LoopFlight,
    LoopOptions,
    fly_from_cli,
    options_from_args,
)
from companion.sitl.loops.processes import REPO, companion_argv

SHARED_PX4 = REPO.parent / "shared" / "px4-sitl" / "px4-sitl"
BUILD_HELP = (
    "PX4 SITL not found: pass --px4 PATH or set PX4_SITL to a launcher with the interface "
    "`px4-sitl INSTANCE WORKDIR` (../shared/px4-sitl/px4-sitl is used when present). To build "
    "one: clone PX4-Autopilot with its submodules, `make px4_sitl_default`, and run "
    "`PX4_SYS_AUTOSTART=10040 PX4_SIM_MODEL=sihsim_quadx build/px4_sitl_default/bin/px4 -i N "
    "-w WORKDIR build/px4_sitl_default/etc` from the launcher (docs/install.md, 'PX4 SITL')."
)
EV_CTRL_FLIGHT = 15
BOOT_PARAMS = {
    "SENS_EN_GPSSIM": "0",
    "SYS_HAS_GPS": "0",
    "EKF2_GPS_CTRL": "0",
    # 15: position, height, velocity (our ODOMETRY carries it: config/px4_sitl.toml) and yaw
    # (our NED frame's heading, LOCAL_NED); with VISION_POSITION_ESTIMATE bit 2 finds nothing
    "EKF2_EV_CTRL": str(EV_CTRL_FLIGHT),
    "EKF2_HGT_REF": "3",
    "EKF2_RNG_CTRL": "0",
    # without GPS EKF2 takes the declination from this parameter (default 0); a user sets their
    # site's: SIH's at its home, the same as our compass's (config/px4_sitl.toml,
    # vo.mag_declination_deg). From 2026-11-25 to e751c17 it was tuned (4.7, 3.5, 4.1) to PX4's
    # own heading error, which wanders from boot to boot; since 6059243 (2026-11-27) PX4's
    # heading before our start no longer matters: our frame takes our compass's, and EKF2 fuses
    # our yaw
    "EKF2_MAG_DECL": "3.3",
    # the floor EKF2 puts under our position variance (default 0.1 m): ours is ~4 cm here (as
    # its covariance says); with the floor PX4's position lagged ours more (docs/decisions.md)
    "EKF2_EVP_NOISE": "0.03",
    # the floor under our velocity variance (default 0.1 m/s): ours is 0.05 here
    # (service.odometry_velocity_sigma_m_s in config/px4_sitl.toml), measured 1-6 cm/s
    "EKF2_EVV_NOISE": "0.05",
    # the accelerometer's switch-on bias sigma (default 0.2 m/s^2, for an uncalibrated IMU):
    # without GNSS the bias is unobservable on the ground, and at the take-off EKF2 learnt our
    # climb's velocity errors (0.1-0.2 m/s) as 0.15-0.2 m/s^2 of bias, a 1 deg tilt error that
    # lasted the flight; SIH's accelerometer has none to speak of (its SCALED_IMU against the
    # truth: < 0.02 m/s^2). With 0.05, six missions: PX4's tilt error 1.01-1.10 deg RMS
    # against SIH's truth, 1.05-1.42 with 0.2 (docs/RESULTS.md, "2026-11-25 (c1a0250)")
    "EKF2_ABIAS_INIT": "0.05",
    # EKF2's fusion horizon, 300 ms back (default 200): EKF2 fuses a sample when its delayed
    # horizon passes the sample's stamp, measured at EKF2_DELAY_MAX - 44 ms (156 ms with 200,
    # 236 with 300: estimator_aid_src_ev_pos, fused minus sample time). Our samples reach PX4
    # at our latency plus half the ODOMETRY centring window (50 ms at 20 Hz); with 200 the
    # service had to drop every pose over 100 ms old (service.stale_frame_ms), and on this
    # 2-core host the bursts of them were EKF2's only unfused moments (0.5-1.6 s without a
    # sample). With 300 the service sends poses up to 200 ms old (config/px4_sitl.toml), all
    # still younger than the horizon (docs/decisions.md, "A longer fusion horizon")
    "EKF2_DELAY_MAX": "300",
    # the output predictor's time constants (default 0.25 s): PX4's published position is
    # EKF2's delayed state carried to the present on the IMU, pulled toward that state by
    # these; with SIH's noisy accelerometer (~1.4 m/s^2 on z) the 0.25 s pull let the
    # published height wander 3.2-3.5 cm RMS off the delayed state that matched ours to 9 mm
    # (six flights); 0.1 s: 2.3 cm (docs/decisions.md, "PX4's output predictor")
    "EKF2_TAU_POS": "0.1",
    "EKF2_TAU_VEL": "0.1",
}
SERIAL_CONTROL_DEV_SHELL = 10
SERIAL_CONTROL_FLAG_RESPOND, SERIAL_CONTROL_FLAG_EXCLUSIVE = 2, 4
# PX4 needs ~500 TIMESYNC answers after the service starts: 10.7 s measured with the TIMESYNC
# rate the service asks for (service.px4_timesync_rate_hz, 50 Hz), ~50 s at PX4's own 10 Hz
# (a PX4 that refused the rate); more than either, a cap
TIMESYNC_WAIT_S = 120.0
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
class FlightOptions(LoopOptions):
    """The PX4 loop's options (``configure``: `companion px4 configure`; with ``ground_start``
    off, ``settle_s`` is how long the VO tracks in the air before EKF2 may fuse it)."""

    px4: str | None = None
    ground_start: bool = True  # the companion initialises on the ground, PX4 arms in Position
    # arm only once PX4 converts our stamps through its time sync (as `companion px4 check`
    # advises): before, it stamps our samples at arrival and the latency is not compensated
    wait_timesync: bool = True
    # the ground start: EKF2 fuses our position on the ground at least this long before PX4
    # arms. The wait for PX4's time sync (~45 s at its own 10 Hz TIMESYNC) used to give this
    # time; with the TIMESYNC rate the service asks for it converges in ~11 s, and a hover
    # armed 5 s after EKF2 fused us drifted 0.8 m in the climb (0.575 m p95, against 0.215 m
    # with 50 s on the ground beside it: docs/decisions.md, "PX4's time sync, asked faster")
    ground_hold_s: float = 45.0


@dataclass
class Telemetry(LoopTelemetry):
    """What the ground station saw (arrival times: our monotonic clock [ns])."""

    est: list[tuple[int, int, float, float, float]] = field(default_factory=list)


class Gcs(GcsBase):
    """A minimal ground station on PX4's GCS port (pymavlink), pumped from this thread."""

    def __init__(self, instance: int, tel: Telemetry) -> None:
        from pymavlink import mavutil

        conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{18570 + instance}", source_system=255, source_component=190
        )
        super().__init__(conn, instance + 1, tel)  # PX4 SITL: MAV_SYS_ID = 1 + instance
        self.tel: Telemetry = tel
        self.sticks = (0, 0, 500, 0)  # x pitch, y roll, z throttle (500 = hold), r yaw
        self._last_manual = 0.0
        self.params: dict[str, float] = {}
        self.range_m: tuple[float, float] | None = None  # PX4's own rangefinder: (time, m)
        self.hold_range_m: float | None = None  # throttle stick holds this range (Altitude mode)
        self._shell_out: list[bytes] = []  # SERIAL_CONTROL replies of PX4's MAVLink shell

    def _send(self, now: float) -> None:
        """The sticks (MANUAL_CONTROL) and the setpoint at 20 Hz."""
        if now - self._last_manual > 0.05:
            x, y, z, r = self.sticks
            rng, hold = self.range_m, self.hold_range_m
            if hold is not None and rng is not None and now - rng[0] < 0.5:
                # a pilot watching the height: proportional on the throttle stick
                z = int(np.clip(500 + 200 * (hold - rng[1]), 300, 800))
            self.mav.manual_control_send(self.sysid, x, y, z, r, 0)
            self.send_setpoint()
            self._last_manual = now

    def _on_other(self, kind: str, m: Any, t: int) -> None:
        if kind == "ESTIMATOR_STATUS":
            self.tel.est.append(
                (t, int(m.flags), m.pos_horiz_ratio, m.pos_vert_ratio, m.hagl_ratio)
            )
        elif kind == "DISTANCE_SENSOR" and int(m.orientation) == 25:
            if 0 < int(m.current_distance) < 65535:
                self.range_m = (time.monotonic(), int(m.current_distance) * 0.01)
        elif kind == "PARAM_VALUE":
            self.params[str(m.param_id)] = float(m.param_value)
        elif kind == "SERIAL_CONTROL" and int(m.device) == SERIAL_CONTROL_DEV_SHELL:
            self._shell_out.append(bytes(m.data[: int(m.count)]))
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
            tail = text.rstrip()
            # the prompt after the output: pxh> on PX4 SITL (POSIX), nsh> on NuttX
            if tail.endswith(("pxh>", "nsh>")) and len(tail) > len("pxh>"):
                break
        return text

    def px4_stamps_converted(self) -> bool | None:
        """Whether PX4 converts our time_usec through its time sync (``listener
        vehicle_visual_odometry``: a converted stamp lies some latency before the message's
        arrival; before PX4's filter converges, after ~500 TIMESYNC answers (~10 s at the
        service's 50 Hz), it stamps our samples with their arrival: "0 us before timestamp").
        None: no answer."""
        fields = parse_listener(self.shell("listener vehicle_visual_odometry -n 1"))
        before = None if fields is None else fields.get("timestamp_sample_before_timestamp_us")
        return None if not isinstance(before, int) else before != 0

    def set_mode(self, main: int, sub: int = 0) -> None:
        self.command(176, 1, main, sub)  # MAV_CMD_DO_SET_MODE, custom

    def main_mode(self) -> int:
        return self.tel.custom_mode >> 16 & 0xFF

    def ev_fused(self, within_s: float = 0.5) -> bool:
        if not self.tel.est:
            return False
        t, flags = self.tel.est[-1][:2]
        return bool(flags & ESTIMATOR_POS_HORIZ_REL) and time.monotonic_ns() - t < within_s * 1e9


def _runtime_bin(px4: Path) -> Path | None:
    """The bin folder of the unpacked runtime of the shared launcher (its px4-* tools)."""
    tarball = px4.parent / "px4-sitl-runtime.tar.gz"
    if not tarball.is_file():
        return None
    with tarball.open("rb") as fh:
        cksum = subprocess.run(["cksum"], stdin=fh, capture_output=True, check=True).stdout
    key = cksum.split()[0].decode()
    cache = os.environ.get("PX4_SITL_CACHE") or (
        Path(os.environ["XDG_CACHE_HOME"]) / "px4-sitl"
        if os.environ.get("XDG_CACHE_HOME")
        else Path.home() / ".cache" / "px4-sitl"
    )
    b = Path(cache) / key / "px4-sitl-runtime" / "bin"
    return b if b.is_dir() else None


class Flight(LoopFlight):
    """PX4 SITL (SIH) flown on our estimate (this module's docstring)."""

    AUTOPILOT, ARM_LOG, TELEMETRY = "PX4", "px4-console.log", Telemetry
    o: FlightOptions
    tel: Telemetry
    gcs: Gcs

    def __init__(self, opts: FlightOptions) -> None:
        super().__init__(opts)
        self.failsafes: list[str] = []

    # ------------------------------------------------------------------ setup
    def _prepare(self) -> None:
        self.px4 = find_px4(self.o.px4)
        self.work = self._cleared("px4")
        self.work.mkdir()

    def _start_and_fly(self) -> None:
        px4, work, n = self.px4, self.work, self.o.instance
        env = dict(os.environ)
        boot = {**BOOT_PARAMS, **gps_missions.px4_boot_params(self.o.mission)}
        env.update({f"PX4_PARAM_{k}": v for k, v in boot.items()})
        self.log(f"PX4 SITL {px4} instance {n}, work folder {work}")
        self.procs.start(
            "px4", [str(px4), str(n), str(work)], self.out / "px4-console.log", env=env
        )
        self._wait_console("Startup script returned successfully", 60.0)
        self.gcs = Gcs(n, self.tel)
        self.gcs.pump(1.0)
        # our ground station asks for what it plots (ESTIMATOR_STATUS 10 Hz, landed state)
        self.gcs.ask_streams(((230, 10.0), (245, 5.0), (32, 50.0), (132, 20.0)))
        cfg_path = self._service_config_base()
        self._configure(cfg_path)
        self._start_bridge(cfg_path)
        self._fly()

    def _stop_autopilot(self) -> None:
        self.procs.stop("px4")
        self.procs.stop_all()

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
        d = self._loop_config()
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
        if gps_missions.is_gps_mission(self.o.mission):
            d["gps"] = gps_missions.service_gps_section("px4")
        return self._write_service_config(d)

    def _configure(self, cfg_path: Path) -> None:
        if not self.o.configure:
            return
        url = f"udpin:127.0.0.1:{14540 + self.o.instance}"
        argv = [
            *companion_argv(),
            "px4",
            "configure",
            "--config",
            str(cfg_path),
            "--url",
            url,
            "--yes",
            "--with-gps" if gps_missions.is_gps_mission(self.o.mission) else "--no-gnss",
            "--timeout-s",
            "10",
        ]
        label, log_name = "companion px4 configure", "px4-configure.log"
        code = self._run_configure(label, argv, log_name, 60, start_new_session=True)
        if code != 0:
            self.notes.append(
                f"companion px4 configure exited {code}: flown with the boot parameters "
                f"({', '.join(f'{k}={v}' for k, v in BOOT_PARAMS.items())}); see px4-configure.log"
            )

    def _start_bridge(self, cfg_path: Path) -> None:
        argv = [
            sys.executable,
            "-m",
            "companion.sitl.loops.px4_bridge",
            "--config",
            str(cfg_path),
            "--instance",
            str(self.o.instance),
            "--camera-port",
            str(15600 + self.o.instance),
            "--out",
            str(self.out),
        ]
        ptys = self._start_bridge_with(argv, cfg_path)
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

    # ------------------------------------------------------------------ flight
    def _fly(self) -> None:
        g = self.gcs
        self._wait_heartbeat(20)
        start = (
            self._take_off_on_ours() if self.o.ground_start else self._take_off_in_altitude_mode()
        )
        self._fly_mission(start)
        g.set_mode(MODE_AUTO, SUB_AUTO_LAND)
        self._until("Land mode", lambda: g.main_mode() == MODE_AUTO, 10)
        g.setpoint = None
        self._wait_disarmed()

    def _take_off_on_ours(self) -> np.ndarray:
        """The default take-off (the service's ground start, issue 18): the companion starts on
        the ground, EKF2 fuses it before arming, PX4 arms in Position mode and climbs in Offboard
        mode on our estimate. Returns the mission's start (NED, PX4's frame)."""
        g, o = self.gcs, self.o
        self._start_service()
        self._wait_tracking("the service tracking on the ground", 90)
        self._wait_fused("EKF2 fusing our position", 1.0)
        self._wait_timesync()
        self._hold_on_ground()
        if (
            self.o.mission in gps_missions.WITH_GPS_AT_START
        ):  # our output in PX4's GPS frame before arming
            gps_missions.wait_aligned(
                self, "service aligned to GPS", gps_missions.ALIGN_BEFORE_ARMING_S
            )
        g.set_mode(MODE_POSCTL)
        self._until("Position mode", lambda: g.main_mode() == MODE_POSCTL, 10)
        self._arm()
        self.armed_mode = "POSCTL"
        here = self._offboard_here()
        top: np.ndarray = here + np.array([0.0, 0.0, -o.altitude_m])
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

    def _hold_on_ground(self) -> None:
        """Before arming (the ground start): until EKF2 has fused our position on the ground
        for ``ground_hold_s`` since the phase "ev fused", however soon the time sync converged."""
        end = self.tel.phases["ev fused"] + self.o.ground_hold_s
        if time.monotonic() >= end:
            return
        self.log(f"on the ground until EKF2 fused us for {self.o.ground_hold_s:g} s")
        while time.monotonic() < end:
            self.gcs.pump(min(1.0, max(0.0, end - time.monotonic())))
            self._check_alive()
        self._phase("ground hold done")

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
        # EKF2_EV_CTRL was 0 since arming, 15 then (EKF2 resets its position and height to
        # ours); the vehicle drifts meanwhile (Altitude mode has no horizontal position)
        self._start_service()
        self._wait_tracking("the service tracking with a scale", 90)
        self._set_param_int("EKF2_EV_CTRL", EV_CTRL_FLIGHT)
        self._wait_fused("EKF2 fusing our position", 1.0)
        g.set_mode(MODE_POSCTL)
        self._until("Position mode", lambda: g.main_mode() == MODE_POSCTL, 10)
        g.hold_range_m = None
        g.sticks = (0, 0, 500, 0)
        g.pump(2.0)
        return self._offboard_here()

    def _offboard_here(self) -> np.ndarray:
        """Hold where PX4 is now (a setpoint there for 1 s), then Offboard mode; that place."""
        g = self.gcs
        here = g.position()
        assert here is not None
        g.setpoint = (here.copy(), np.zeros(3))
        g.pump(1.0)
        g.set_mode(MODE_OFFBOARD)
        self._until("Offboard mode", lambda: g.main_mode() == MODE_OFFBOARD, 10)
        return here

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

    def _ev_fused(self) -> bool:
        if gps_missions.is_gps_mission(self.o.mission):  # GNSS alone sets the flag
            fields = parse_listener(self.gcs.shell("listener estimator_status_flags -n 1", 2.0))
            return bool(fields and fields.get("cs_ev_pos"))
        return self.gcs.ev_fused()

    def _set_gps(self, on: bool) -> None:
        """SIH's GPS fix on or off (SIM_GPS_USED; PX4's `failure gps` does nothing here)."""
        self._set_param_int("SIM_GPS_USED", gps_missions.PX4_GPS_SATELLITES if on else 0)

    # ------------------------------------------------------------------ results
    def summarise(self, ok: bool) -> dict[str, Any]:
        from companion.sitl.loops.px4_results import summarise

        return summarise(self, ok)


def cli_main(args: Any) -> int:
    """``companion sitl px4``: fly, print the summary, exit 0 when landed without failsafe."""
    ground_start = not bool(getattr(args, "air_start", False))
    opts = options_from_args(FlightOptions, args, px4=args.px4, ground_start=ground_start)
    return fly_from_cli(Flight(opts), lambda: find_px4(opts.px4))


def _asdict(o: Any) -> dict[str, Any]:
    return asdict(o)
