"""The service against the real ArduCopter (SITL): it tells ArduPilot from its HEARTBEAT, gives
EKF3 the origin until EKF3 holds it, and takes ArduPilot's own rangefinder (DISTANCE_SENSOR id 0,
orientation 25, time-synced) as our sensor 0. No camera: nothing is published, the rest runs.
Instance 4 (TCP 5800-5803); about 40 s.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import pytest
from ardupilot_peer import HOME, SKIP_REASON
from peers import service_config

from companion.config import load_config, to_dict
from companion.service.app import Service
from sitl import ardupilot_sitl
from sitl.ardupilot_sitl import ArduPilotSitl, port

INSTANCE = 4


def _config(tmp: Path, set_origin: bool) -> Any:
    base: Any = service_config(
        tmp,
        mavlink_url=f"tcp:127.0.0.1:{port(0, INSTANCE)}",
        ardupilot={
            "set_origin": set_origin,
            "origin_lat_deg": HOME.lat_deg,
            "origin_lon_deg": HOME.lon_deg,
            "origin_alt_m": HOME.alt_m,
        },
    )
    d = to_dict(base)
    d["rangefinders"][0]["min_m"] = 0.05  # the SITL rangefinder reads ~0.1 m on the ground
    return load_config(None, d)


async def _serve(cfg: Any, seconds: float) -> dict[str, Any]:
    async with Service(cfg) as s:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            st = s.status()
            seen = st["scale"]["ranges_in"] + st["scale"]["ranges_rejected"]
            if (
                st["autopilot"]["ekf_origin"]
                and st["autopilot"]["ekf_origin"]["held"]
                and seen > 20
            ):
                break
            await asyncio.sleep(0.5)
        return s.status()


@pytest.mark.skipif(not ardupilot_sitl.available(), reason=SKIP_REASON)
@pytest.mark.timeout(120)
def test_service_sets_the_ekf_origin_and_maps_ardupilots_rangefinder(tmp_path: Path) -> None:
    params = {
        "RNGFND1_TYPE": 100,  # SITL's own rangefinder
        "RNGFND1_ORIENT": 25,
        "RNGFND1_MIN": 0.05,
        "RNGFND1_MAX": 40.0,
    }
    with ArduPilotSitl(tmp_path / "ap", "odom", params, INSTANCE):
        st = asyncio.run(_serve(_config(tmp_path, set_origin=True), 60.0))
    ap = st["autopilot"]
    assert ap["type"] == "ArduPilot", st
    assert ap["ekf_origin"]["held"] and ap["ekf_origin"]["sent"] >= 1, st
    # ArduPilot's rangefinder instance 0 is DISTANCE_SENSOR id 0, orientation 25: taken as our
    # sensor 0 (on the ground SITL's reads 0 cm, below its minimum: "no reading"; a wrong id or
    # orientation would be counted as unknown_id / not_downward instead)
    by = st["scale"]["rejected_by"]
    assert by.get("no_reading", 0) + st["scale"]["ranges_in"] > 20, str(st["scale"])
    assert not by.get("unknown_id") and not by.get("not_downward"), str(st["scale"])
    assert ap["timesync_converged"] is True, str(ap)  # ArduPilot answers our TIMESYNC
