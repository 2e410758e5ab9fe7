"""Where and how the SITL autopilot talks, and what it injects (``companion sitl run``'s flags,
tests/peers' flights): ports on 127.0.0.1, its clock's offset and drift, the camera's readout,
the time scale (flight seconds per wall-clock second), faults, signing, the ground-station
endpoint.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from companion.sitl.stub.faults import Fault


@dataclass(frozen=True, slots=True)
class AutopilotOptions:
    """Where and how the stub talks (PX4 SITL's onboard ports by default)."""

    host: str = "127.0.0.1"
    listen_port: int = 14580
    companion_port: int = 14540
    camera_port: int = 5600
    boot_offset_s: float = 37.25  # the autopilot booted this long before the stub started
    drift_ppm: float = 60.0  # its crystal against the companion's clock
    readout_ms: float = 4.0  # a frame leaves the camera this long after its exposure
    time_scale: float = 1.0  # flight seconds per wall-clock second (< 1: slow motion)
    warmup_s: float = 3.0  # the flight starts this long after the stub
    linger_s: float = 2.0  # keep listening this long after the flight
    # > 0: the flight ends at this flight time [s], before the scenario's end (its trajectory,
    # made for cfg.sitl.seconds, unchanged): a test that needs only a flight's first part
    end_s: float = 0.0
    prerender: bool = False  # render every frame before the flight (frees the CPU during it)
    faults: tuple[Fault, ...] = ()  # injected during the flight (sitl/stub/faults.py)
    loop_from_frame: int = 0  # with loop_frames: where the repeated stretch of frames starts
    loop_frames: int = 0  # > 0: frames repeat with this period (a periodic flight: soak runs)
    signing_key: bytes = b""  # MAVLink 2 signing with this 32-byte key (empty: unsigned)
    require_signed: bool = True  # with a key: refuse unsigned frames except HEARTBEAT
    gcs_listen_port: int = (
        18570  # the ground-station endpoint (sitl/stub/px4_services.py); 0 = none
    )
    gcs_port: int = 14550  # where the ground-station endpoint sends (QGroundControl, MAVSDK)
    armed: bool = False  # report the vehicle armed in HEARTBEAT
    has_mag: bool = True  # a magnetometer gives EKF2 a north-aligned heading
    camera: bool = True  # serve the camera stream (False: MAVLink only, no render process)
    # GPS_RAW_INT / GPS_GLOBAL_ORIGIN from the truth (sitl/stub/gps.py): the GPS frame is
    # the truth moved by gps_offset_ned_m [m], with gps_noise_m [m] of correlated noise per axis
    gps: bool = False
    gps_offset_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gps_noise_m: float = 0.3
    # awaited once the camera is ready (prerendered), before the flight clock starts: a test
    # run on several workers flies one real-time flight at a time (tests/peers/)
    flight_gate: Callable[[], Awaitable[None]] | None = None
    # awaited once the flight and its linger are over (the camera stopped), before the report
    # is made and written: a test run lets the other worker's tests in again (tests/peers/)
    flight_done: Callable[[], Awaitable[None]] | None = None
