"""ArduCopter SITL physics -> our sensors
(``python -m companion.sitl.loops.ardupilot_bridge``).

The same bridge as PX4's (:mod:`.px4_bridge`, reused: its world clipped to the home level,
camera rendering and release, TFmini pseudo-terminals, truth log), with the truth from
ArduPilot instead of SIH: SIM_STATE (id 108, asked at 100 Hz with MAV_CMD_SET_MESSAGE_INTERVAL
on a MAVLink link of its own, ArduCopter's SERIAL2 by default) stamped on arrival with our
monotonic clock; ``lat_int`` / ``lon_int`` (degE7) and ``alt`` (m AMSL) -> local NED around the
first sample (the vehicle at rest at home: px4_bridge.ned_of), ``q1..q4`` (body FRD -> NED,
wxyz), ``vn/ve/vd`` (m/s).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import Config
from companion.sitl.loops.px4_bridge import Bridge, TruthSample, ned_of, parse_bridge_args, serve

MSG_ID_SIM_STATE = 108
TRUTH_RATE_HZ = 100.0  # the camera waits for the first sample after each exposure: 10 ms at most


class ArduPilotBridge(Bridge):
    """:class:`companion.sitl.loops.px4_bridge.Bridge` with SIM_STATE as its truth."""

    def __init__(
        self, cfg: Config, truth_url: str, camera_port: int, out: Path, gear_m: float = 0.35
    ) -> None:
        super().__init__(cfg, 0, camera_port, out, gear_m)
        self.truth_url = truth_url

    def add_state(self, m: Any, t_ns: int) -> None:
        """One SIM_STATE, arrived at ``t_ns`` (our clock), into the truth track."""
        alt_mm = int(round(float(m.alt) * 1000.0))
        tr = self.truth
        if tr.home is None:
            tr.home = (int(m.lat_int), int(m.lon_int), alt_mm)
        q = np.array([m.q1, m.q2, m.q3, m.q4], dtype=np.float64)
        q = q / np.linalg.norm(q)
        if q[0] < 0:
            q = -q
        v = np.array([m.vn, m.ve, m.vd], dtype=np.float64)
        s = TruthSample(t_ns, ned_of(int(m.lat_int), int(m.lon_int), alt_mm, tr.home), q, v)
        with tr.new:
            tr.samples.append(s)
            tr.new.notify_all()

    def truth_loop(self) -> None:
        os.environ["MAVLINK20"] = "1"
        from pymavlink import mavutil

        conn = mavutil.mavlink_connection(
            self.truth_url, source_system=254, source_component=191, dialect="common"
        )
        last_ask = 0.0
        try:
            while not self.stop.is_set():
                now = time.monotonic()
                if now - last_ask > 2.0 and (not self.truth.samples or now - last_ask > 10.0):
                    last_ask = now  # again now and then: ArduPilot may have rebooted
                    conn.mav.heartbeat_send(18, 8, 0, 0, 4)
                    conn.mav.command_long_send(
                        1, 1, 511, 0, MSG_ID_SIM_STATE, 1e6 / TRUTH_RATE_HZ, 0, 0, 0, 0, 0
                    )
                m = conn.recv_match(type="SIM_STATE", blocking=True, timeout=0.2)
                while m is not None:
                    self.add_state(m, time.monotonic_ns())
                    m = conn.recv_match(type="SIM_STATE", blocking=False)
        finally:
            conn.close()


def main(argv: list[str] | None = None) -> int:
    args, cfg = parse_bridge_args(
        "python -m companion.sitl.loops.ardupilot_bridge",
        __doc__,
        argv,
        lambda ap: ap.add_argument(
            "--truth-url", required=True, help="pymavlink URL of an ArduPilot link"
        ),
    )
    return serve(ArduPilotBridge(cfg, args.truth_url, args.camera_port, args.out, args.gear_m))


if __name__ == "__main__":
    raise SystemExit(main())
