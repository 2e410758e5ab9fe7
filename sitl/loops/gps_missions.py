"""The closed loops' GPS missions (issue "GPS in, GPS out"): through a GPS-denied zone and back,
and GPS that appears mid-flight, flown the same way on PX4 and ArduPilot.

``gps-denied-zone``: the vehicle takes off with GPS and our estimate fused (the service's output
aligned to the autopilot's GPS frame before arming), flies a ZONE_LEG_M leg north into the zone,
where the GPS fails for DENIAL_S while it flies ZONE_SQUARE_M squares; the GPS returns, the
vehicle holds until the service has handed back (its frame ``aligned`` again, at most
HANDBACK_TIMEOUT_S), flies back and lands. ``gps-hover``: the same in a hover, the GPS off for
HOVER_DENIAL_S (short enough for `make test`). ``gps-appears``: the vehicle boots and takes off
without a GPS fix (indoors), flies the leg and one square, the GPS appears, it holds until the
service's frame is ``aligned`` (the GPS frame found and slewed onto), flies back and lands.

The loop (a :class:`~companion.sitl.loops.loop_flight.LoopFlight`) provides ``_set_gps(on)``
(PX4: SIM_GPS_USED; ArduPilot: SIM_GPS1_ENABLE) and records the phases "gps lost" and "gps back"
(its monotonic clock, s) that sitl/loops/gps_results.py measures the jumps around.
Positions NED [m] in the autopilot's local frame.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

GPS_MISSIONS = ("gps-denied-zone", "gps-appears", "gps-hover")
# the missions that take off with GPS (the service aligned to it before arming)
WITH_GPS_AT_START = ("gps-denied-zone", "gps-hover")
ZONE_LEG_M = 20.0  # the leg from the take-off point into the zone (north)
ZONE_SQUARE_M = 10.0  # the squares flown inside the zone
DENIAL_S = 60.0  # how long the GPS is off in the zone
HOVER_DENIAL_S = 15.0  # gps-hover: the GPS off this long in a hover (the test in make test)
HANDBACK_TIMEOUT_S = 60.0  # the hold after the GPS returns, until the service is aligned
ALIGN_BEFORE_ARMING_S = 120.0  # with GPS at start: the service aligned on the ground within this
AFTER_ALIGNED_S = 5.0  # the hold after the service said aligned


# PX4 (SIH) for the GPS missions, on top of the vision-only BOOT_PARAMS (px4_flight.py): its
# simulated GPS on, GNSS fused beside our position and velocity, no EV yaw (PX4's heading is its
# magnetometer's and GNSS's: the service aligns our output to it), our height the reference
# (GNSS height reset the height by 0.2-0.27 m at a return: docs/gps.md); what `companion px4
# configure --with-gps` writes. gps-appears boots with the receiver's fix off (SIM_GPS_USED 0)
PX4_GPS_BOOT_PARAMS = {
    "SENS_EN_GPSSIM": "1",
    "SYS_HAS_GPS": "1",
    "EKF2_GPS_CTRL": "7",
    "EKF2_EV_CTRL": "7",
    "EKF2_HGT_REF": "3",
    # the floor under our velocity variance back at PX4's default (the vision-only loop's 0.05
    # let EKF2 refuse our velocity at the zone's corners right after the GNSS stopped: 0.17-0.2
    # m/s innovations, EV fusion stopped and reset 3 times in the first zone flight)
    "EKF2_EVV_NOISE": "0.1",
}
PX4_GPS_SATELLITES = 10  # SIM_GPS_USED with the fix on (SIH's default)


def px4_boot_params(mission: str) -> dict[str, str]:
    """The PX4 boot parameters a mission adds ({} for a vision-only mission)."""
    if not is_gps_mission(mission):
        return {}
    fix = str(PX4_GPS_SATELLITES) if mission in WITH_GPS_AT_START else "0"
    return {**PX4_GPS_BOOT_PARAMS, "SIM_GPS_USED": fix}


# ArduPilot for the GPS missions, on top of the vision-only BOOT_PARAMS and the compass heading
# (ardupilot_flight.py): what `companion autopilot configure --with-gps` writes. Set 1 is the GPS
# set (ArduPilot's defaults), set 2 ours (ODOMETRY: position and velocity), the baro height and
# the compass heading in both (a switch resets only xy); VISO_TYPE 3 (VOXL): ArduPilot keeps our
# position aligned to its own while GPS is the active source (docs/gps.md). The service switches
# the sets with MAV_CMD_SET_EKF_SOURCE_SET
ARDUPILOT_GPS_BOOT_PARAMS: dict[str, float] = {
    "VISO_TYPE": 3,
    "GPS1_TYPE": 1,
    "SIM_GPS1_ENABLE": 1,
    "EK3_SRC1_POSXY": 3,
    "EK3_SRC1_VELXY": 3,
    "EK3_SRC1_POSZ": 1,
    "EK3_SRC1_VELZ": 3,
    "EK3_SRC1_YAW": 1,
    "EK3_SRC2_POSXY": 6,
    "EK3_SRC2_VELXY": 6,
    "EK3_SRC2_POSZ": 1,
    "EK3_SRC2_VELZ": 6,
    "EK3_SRC2_YAW": 1,
    "EK3_SRC_OPTIONS": 0,
}


# ARMING_CHECK: every check (bits 1-19) but the GPS lock (bit 3, 8): indoors with a receiver
# configured ArduPilot refused to arm ("Arm: GPS 1: Bad fix") although set 2 (ours) was active
ARMING_CHECK_BUT_GPS_LOCK = (1 << 20) - 2 - 8


def ardupilot_boot_params(mission: str) -> dict[str, float]:
    """The ArduPilot boot parameters a mission adds ({} for a vision-only mission)."""
    if not is_gps_mission(mission):
        return {}
    if mission in WITH_GPS_AT_START:
        return dict(ARDUPILOT_GPS_BOOT_PARAMS)
    indoors = {"SIM_GPS1_ENABLE": 0, "ARMING_CHECK": ARMING_CHECK_BUT_GPS_LOCK}
    return {**ARDUPILOT_GPS_BOOT_PARAMS, **indoors}


def is_gps_mission(mission: str) -> bool:
    return mission in GPS_MISSIONS


def service_gps_section(handover: str) -> dict[str, Any]:
    """The service's ``[gps]`` for a GPS mission: aligned output, the autopilot's hand-over."""
    return {"align": True, "handover": handover}


def frame_state(flight: Any) -> str | None:
    """The service's frame state (``companion status``'s ``frame.state``), None if unknown."""
    frame = flight._status().get("frame")
    state = frame.get("state") if isinstance(frame, dict) else None
    return state if isinstance(state, str) else None


def wait_aligned(flight: Any, what: str, timeout_s: float) -> bool:
    """Pump until the service's frame is ``aligned`` (status asked every 0.5 s); whether it was
    within ``timeout_s`` (else noted)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if frame_state(flight) == "aligned":
            flight._phase(what)
            return True
        flight.gcs.pump(0.5)
        flight._check_alive()
    flight.notes.append(f"the service's frame was not aligned within {timeout_s:g} s ({what})")
    return False


def _square(corner: np.ndarray, side_m: float) -> list[np.ndarray]:
    offs = [(0.0, 0.0), (side_m, 0.0), (side_m, side_m), (0.0, side_m), (0.0, 0.0)]
    return [corner + np.array([n, e, 0.0]) for n, e in offs]


def _hold(flight: Any, where: np.ndarray, seconds: float) -> None:
    flight.gcs.setpoint = (where.copy(), np.zeros(3))
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        flight.gcs.pump(min(0.5, max(0.0, end - time.monotonic())))
        flight._check_alive()


def fly(flight: Any, start: np.ndarray) -> None:
    """The GPS mission ``flight.o.mission`` from ``start`` (the mission's start, at altitude);
    the phases "gps lost" / "gps back" are set where the GPS changes. Ends over ``start``
    (the caller lands)."""
    o = flight.o
    if o.mission == "gps-hover":
        _hold(flight, start, AFTER_ALIGNED_S)
        flight._phase("gps lost")  # the switch's first PARAM_SET follows at once
        flight._set_gps(False)
        _hold(flight, start, HOVER_DENIAL_S)
        flight._phase("gps back")
        flight._set_gps(True)
        if wait_aligned(flight, "service aligned to GPS again", HANDBACK_TIMEOUT_S):
            _hold(flight, start, AFTER_ALIGNED_S)
        flight._settle_over(start)
        return
    zone = start + np.array([ZONE_LEG_M, 0.0, 0.0])
    flight._follow([start, zone], o.speed_m_s)
    if o.mission == "gps-denied-zone":
        flight._phase("gps lost")
        flight._set_gps(False)
        t_lost = time.monotonic()
        while time.monotonic() - t_lost < DENIAL_S - 10.0:
            flight._follow(_square(zone, ZONE_SQUARE_M), o.speed_m_s)
        _hold(flight, zone, max(0.0, DENIAL_S - (time.monotonic() - t_lost)))
    else:
        flight._follow(_square(zone, ZONE_SQUARE_M), o.speed_m_s)
    flight._phase("gps back")
    flight._set_gps(True)
    flight.gcs.setpoint = (zone.copy(), np.zeros(3))
    if wait_aligned(flight, "service aligned to GPS again", HANDBACK_TIMEOUT_S):
        _hold(flight, zone, AFTER_ALIGNED_S)
    flight._follow([zone, start], o.speed_m_s)
    flight._settle_over(start)
