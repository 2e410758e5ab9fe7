"""``companion sitl ardupilot``: the real ArduCopter flies on our estimate, ground to ground.

Processes (each in its own process group, all stopped on exit, Ctrl-C, SIGTERM or failure):

1. ArduCopter SITL (sitl/loops/ardupilot_sitl.py, the ``odom`` profile: GPS off, EK3_SRC1_* = 6,
   VISO_TYPE = 1) with BOOT_PARAMS on top; this process is its ground station on SERIAL0.
2. ``companion autopilot configure --yes`` on SERIAL1 before the service holds it (reported;
   the flight goes on with the boot parameters when it fails).
3. The bridge (``python -m companion.sitl.loops.ardupilot_bridge`` on SERIAL2): SIM_STATE
   truth -> our camera stream and TFmini ptys (the PX4 bridge's code).
4. The service, unchanged: ``companion run --config OUT/service.toml`` on SERIAL1, sending
   ODOMETRY and the EKF origin ([service.ardupilot]).
5. This process: waits until the service tracks with a metric scale on the ground and EKF3 uses
   our external navigation (EKF_STATUS_REPORT: relative horizontal position, not constant-
   position mode), arms in GUIDED, takes off to 5 m (MAV_CMD_NAV_TAKEOFF), flies the mission
   with SET_POSITION_TARGET_LOCAL_NED (position + velocity, EKF3's local frame = ours), comes
   back to where the mission started, lands (LAND) and waits for the auto-disarm.

Afterwards: ``summary.json`` (the fields of the PX4 loop's summary where they apply;
sitl/loops/ardupilot_results.py) from the truth the bridge logged and the ground station's
telemetry.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.drivers.ardupilot import ekf_navigates
from companion.errors import SitlError
from companion.sitl.loops import gps_missions, ground_station, loop_flight, processes
from companion.sitl.loops.ardupilot_sitl import ArduPilotSitl, find_ardupilot, port

HOME = (-35.363261, 149.165230, 584.0)  # the launcher's --home: the EKF origin we send
# the odom profile's external navigation, spelled out (the check reads them back;
# tests/companion/autopilot/ardupilot/test_ardupilot_check.py sets them as the right configuration)
EXTNAV_BOOT_PARAMS: dict[str, float] = {
    "VISO_TYPE": 1,
    "GPS1_TYPE": 0,
    "SIM_GPS1_ENABLE": 0,
    "EK3_SRC1_POSXY": 6,
    "EK3_SRC1_VELXY": 6,
    "EK3_SRC1_POSZ": 6,
    "EK3_SRC1_VELZ": 6,
    "EK3_SRC1_YAW": 6,  # --heading extnav; --heading compass: HEADING_COMPASS_PARAMS
}
BOOT_PARAMS: dict[str, float] = {
    **EXTNAV_BOOT_PARAMS,
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
CAMERA_PORT = 15700  # + instance


@dataclass
class FlightOptions(loop_flight.LoopOptions):
    """The ArduPilot loop's options (``configure``: `companion autopilot configure`;
    ``settle_s``: the service tracks this long with a scale before arming)."""

    ardupilot: str | None = None
    # EKF3's heading: "compass" (+ the site's declination: EKF3's north is true north) or
    # "extnav" (ours alone: EKF3's north is the vehicle's first heading)
    heading: str = "compass"
    params: dict[str, float] = field(default_factory=dict)  # on top of BOOT_PARAMS


@dataclass
class Telemetry(ground_station.LoopTelemetry):
    """What the ground station saw (arrival times: our monotonic clock [ns])."""

    ekf: list[tuple[int, int]] = field(default_factory=list)  # (t, EKF_STATUS_REPORT.flags)
    yaw: list[tuple[int, float]] = field(default_factory=list)  # (t, ATTITUDE.yaw [rad])
    custom_mode: int = -1


class Gcs(ground_station.GcsBase):
    """A minimal ground station on ArduCopter's SERIAL0 (pymavlink), pumped from this thread."""

    def __init__(self, url: str, tel: Telemetry) -> None:
        os.environ["MAVLINK20"] = "1"
        from pymavlink import mavutil

        conn = mavutil.mavlink_connection(
            url, source_system=255, source_component=190, dialect="ardupilotmega"
        )
        super().__init__(conn, 1, tel)
        self.tel: Telemetry = tel
        self._last_sp = 0.0

    def _send(self, now: float) -> None:
        """The setpoint at 20 Hz."""
        if self.setpoint is not None and now - self._last_sp > 0.05:
            self.send_setpoint()
            self._last_sp = now

    def _on_other(self, kind: str, m: Any, t: int) -> None:
        if kind == "EKF_STATUS_REPORT":
            self.tel.ekf.append((t, int(m.flags)))
        elif kind == "ATTITUDE":
            self.tel.yaw.append((t, float(m.yaw)))
        elif kind == "AUTOPILOT_VERSION":
            v = int(m.flight_sw_version)
            self.tel.version = f"ArduCopter {v >> 24 & 255}.{v >> 16 & 255}.{v >> 8 & 255}"

    def set_mode(self, mode: int) -> None:
        self.command(176, 1, mode)  # MAV_CMD_DO_SET_MODE, custom

    def ekf_uses_ours(self, within_s: float = 1.0) -> bool:
        if not self.tel.ekf:
            return False
        t, flags = self.tel.ekf[-1]
        fresh = time.monotonic_ns() - t < within_s * 1e9
        return fresh and bool(ekf_navigates(flags))


class Flight(loop_flight.LoopFlight):
    """ArduCopter SITL flown on our estimate (this module's docstring)."""

    AUTOPILOT, ARM_LOG, TELEMETRY = "ArduPilot", "statustext.log", Telemetry
    o: FlightOptions
    tel: Telemetry
    gcs: Gcs

    # ------------------------------------------------------------------ setup
    def _prepare(self) -> None:
        self.wall_minus_mono_s = time.time() - time.monotonic()  # the service logs wall time
        work = self._cleared("ardupilot")
        if self.o.heading not in HEADINGS:
            raise SitlError(f"heading {self.o.heading!r}: one of {', '.join(HEADINGS)}")
        params = dict(BOOT_PARAMS)
        gps = gps_missions.is_gps_mission(self.o.mission)
        if self.o.heading == "compass" or gps:  # with GPS EKF3's heading is the compass's
            params.update(HEADING_COMPASS_PARAMS)
        params.update(gps_missions.ardupilot_boot_params(self.o.mission))
        n = self.o.instance
        self.ap = ArduPilotSitl(work, "odom", {**params, **self.o.params}, n, self.o.ardupilot)

    def _start_and_fly(self) -> None:
        n = self.o.instance
        self.log(f"ArduPilot SITL {self.ap.launcher} instance {n}, work folder {self.ap.work}")
        self.ap.start()
        self.gcs = Gcs(f"tcp:127.0.0.1:{port(0, n)}", self.tel)
        self.gcs.pump(1.0)
        # LOCAL_POSITION_NED, EKF_STATUS_REPORT, EXTENDED_SYS_STATE, ATTITUDE
        self.gcs.ask_streams(((32, 50.0), (193, 10.0), (245, 5.0), (30, 10.0)))
        cfg_path = self._service_config_base()
        self._start_bridge(cfg_path)  # first: configure judges the final sensor set
        self._configure(cfg_path)
        self._fly()

    def _stop_autopilot(self) -> None:
        self.procs.stop_all()
        self.ap.stop()

    def summarise(self, ok: bool) -> dict[str, Any]:
        from companion.sitl.loops.ardupilot_results import summarise

        return summarise(self, ok)

    def _write_telemetry(self) -> None:
        with (self.out / "ekf.csv").open("w") as fh:  # EKF3's position and flags as received
            fh.write("t_ns,time_boot_ms,n_m,e_m,d_m\n")
            fh.writelines(f"{t},{b},{x:.4f},{y:.4f},{z:.4f}\n" for t, b, x, y, z in self.tel.lpos)
        with (self.out / "ekf-status.csv").open("w") as fh:
            fh.write("t_ns,flags\n")
            fh.writelines(f"{t},{f}\n" for t, f in self.tel.ekf)
        (self.out / "statustext.log").write_text(
            "".join(f"{t:7.1f} {sev} {text}\n" for t, sev, text in self.tel.texts)
        )

    def _service_config_base(self) -> Path:
        d = self._loop_config()
        n = self.o.instance
        svc = d["service"]
        svc["mavlink_url"] = f"tcp:127.0.0.1:{port(1, n)}"
        svc["system_id"] = 1
        svc["output"] = "odometry"
        # ArduPilot reads ODOMETRY in LOCAL_FRD only; the newest pose with its 150 ms velocity,
        # as measured for issue 21 (the PX4 loop's config asks for LOCAL_NED, centred)
        svc["odometry_frame"] = "local_frd"
        svc["odometry_centre_frames"] = 0
        svc["camera_url"] = f"sitl://127.0.0.1:{CAMERA_PORT + n}"
        svc["status_socket"] = str(self.out / "status.sock")
        svc["report_path"] = str(self.out / "service-report.json")
        svc["state_dir"] = str(self.out / "state")
        gps = gps_missions.is_gps_mission(self.o.mission)
        if gps:
            d["gps"] = gps_missions.service_gps_section("ardupilot")
        svc["ardupilot"] = {
            # with GPS at boot EKF3 takes its origin from it (docs/gps.md); indoors ours
            "set_origin": self.o.mission not in gps_missions.WITH_GPS_AT_START,
            "origin_lat_deg": HOME[0],
            "origin_lon_deg": HOME[1],
            "origin_alt_m": HOME[2],
            "set_declination": self.o.heading == "compass" or gps,
            "declination_deg": SITE_DECLINATION_DEG,
        }
        return self._write_service_config(d)

    def _configure(self, cfg_path: Path) -> None:
        if not self.o.configure:
            return
        url = f"tcp:127.0.0.1:{port(1, self.o.instance)}"
        argv = [*processes.companion_argv(), "autopilot", "configure", "--config", str(cfg_path)]
        gnss = "--with-gps" if gps_missions.is_gps_mission(self.o.mission) else "--no-gnss"
        argv += ["--url", url, "--yes", gnss, "--timeout-s", "15"]
        label, log_name = "companion autopilot configure", "autopilot-configure.log"
        code = self._run_configure(label, argv, log_name, 90)
        if code != 0:
            self.notes.append(
                f"companion autopilot configure exited {code}: flown with the boot parameters; "
                "see autopilot-configure.log"
            )

    def _start_bridge(self, cfg_path: Path) -> None:
        n = self.o.instance
        argv = [
            sys.executable,
            "-m",
            "companion.sitl.loops.ardupilot_bridge",
            "--config",
            str(cfg_path),
        ]
        argv += ["--truth-url", f"tcp:127.0.0.1:{port(2, n)}"]
        argv += ["--camera-port", str(CAMERA_PORT + n), "--out", str(self.out)]
        ptys = self._start_bridge_with(argv, cfg_path)
        self.log(f"bridge up: camera on {CAMERA_PORT + n}, TFmini ptys {ptys}")

    # ------------------------------------------------------------------ flight
    def _check_alive(self) -> None:
        super()._check_alive()
        if not self.ap.alive():
            raise SitlError("ArduPilot SITL exited during the flight")

    def _fly(self) -> None:
        g, o = self.gcs, self.o
        self._wait_heartbeat(30)
        self._start_service()
        self._wait_tracking("the service tracking with a scale", 120)
        self._wait_fused("EKF3 using our external navigation", 2.0)
        if (
            o.mission in gps_missions.WITH_GPS_AT_START
        ):  # our output in EKF3's GPS frame before arming
            gps_missions.wait_aligned(
                self, "service aligned to GPS", gps_missions.ALIGN_BEFORE_ARMING_S
            )
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
        self._fly_mission(start)
        g.setpoint = None
        g.set_mode(MODE_LAND)
        self._until("LAND mode", lambda: self.tel.custom_mode == MODE_LAND, 10)
        self._wait_disarmed()

    def _ev_fused(self) -> bool:
        return self.gcs.ekf_uses_ours()

    def _set_gps(self, on: bool) -> None:
        """The simulated receiver on or off (SIM_GPS1_ENABLE; no SIM_GPS_DISABLE here)."""
        for _ in range(3):
            self.gcs.mav.param_set_send(1, 1, b"SIM_GPS1_ENABLE", float(on), 9)
            self.gcs.pump(0.2)
        self.log(f"SIM_GPS1_ENABLE = {int(on)}")


def cli_main(args: Any) -> int:
    """``companion sitl ardupilot``: fly, print the summary, exit 0 when landed without
    failsafe."""
    opts = loop_flight.options_from_args(
        FlightOptions, args, ardupilot=args.ardupilot, heading=args.heading
    )
    return loop_flight.fly_from_cli(Flight(opts), lambda: find_ardupilot(opts.ardupilot))
