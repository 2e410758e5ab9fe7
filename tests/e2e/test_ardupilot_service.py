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
import tomli_w
from peers import service_config
from peers.ardupilot import HOME, SKIP_REASON

from companion.autopilot.cli import detect
from companion.cli import main
from companion.config import load_config, to_dict
from companion.service.app import Service
from companion.sitl.loops import ardupilot_sitl
from companion.sitl.loops.ardupilot_sitl import ArduPilotSitl, port

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
def test_service_sets_the_ekf_origin_and_maps_ardupilots_rangefinder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    params = {
        "RNGFND1_TYPE": 100,  # SITL's own rangefinder
        "RNGFND1_ORIENT": 25,
        "RNGFND1_MIN": 0.05,
        "RNGFND1_MAX": 40.0,
    }
    cfg = _config(tmp_path, set_origin=True)
    with ArduPilotSitl(tmp_path / "ap", "odom", params, INSTANCE):
        st = asyncio.run(_serve(cfg, 60.0))
        # `companion autopilot check` asks the autopilot who it is and runs ArduPilot's check
        assert detect(f"tcp:127.0.0.1:{port(1, INSTANCE)}", 10.0) == "ArduPilot"
        toml = tmp_path / "service.toml"
        toml.write_bytes(tomli_w.dumps(to_dict(cfg)).encode())
        url = f"tcp:127.0.0.1:{port(2, INSTANCE)}"
        code = main(["autopilot", "check", "--config", str(toml), "--url", url, "--watch-s", "2"])
    out = capsys.readouterr().out
    assert "autopilot: ArduPilot system 1" in out and "RNGFND1_ORIENT" in out, out
    # RNGFND2-4 (our sensors 1-3 read from the autopilot) are off: problems, exit 1
    assert code == 1 and "RNGFND2_TYPE" in out, out
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
    # ArduPilot's own messages (EKF_STATUS_REPORT, SIMSTATE, ...) are its dialect, not bad
    # frames: the link parses ardupilotmega (7 % of an ArduCopter link counted as bad with
    # common; 0 of 7,800 in a flight with ardupilotmega). What is left here is ArduPilot's
    # boot banner ("Init ArduCopter V4.7.0-dev ...", plain text before MAVLink: 5 chunks)
    assert ap["rx_messages"] > 100 and ap["rx_bad"] <= 0.02 * ap["rx_messages"], str(ap)
