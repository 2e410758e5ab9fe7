"""A small companion stand-in for the real ArduPilot SITL (``sitl/loops/ardupilot_sitl.py``).

``TruthSender`` is a real MAVLink peer (system 1, component 197) on one of ArduCopter's TCP
ports: it asks ArduPilot for its true state (SIM_STATE, 30 Hz) and sends it back as our external
navigation at 30 Hz, as the README's hand-written sender did: ODOMETRY (frame ids chosen by the
test; the right ones are LOCAL_FRD / BODY_FRD, velocity in the body frame) in the local NED
frame of the first true position. It sends the EKF origin exactly as the service does (the
service's own :class:`drivers.ardupilot.OriginKeeper` and encoder) when asked to.
"""

from __future__ import annotations

import contextlib
import math
import os
import threading
import time
from typing import Any

import numpy as np

from companion.drivers.ardupilot import Origin, OriginKeeper, set_gps_global_origin
from companion.geometry import so3
from companion.sitl.loops import ardupilot_sitl

SKIP_REASON = (
    f"ArduPilot SITL not found at {ardupilot_sitl.SHARED_ARDUPILOT} (the shared folder beside "
    "the repository) and ARDUPILOT_SITL is not set: these tests run the real ArduCopter. Build "
    "it from ArduPilot (`./waf configure --board sitl && ./waf copter`) and point ARDUPILOT_SITL "
    "at a launcher `ardupilot-sitl PROFILE WORKDIR -- ARGS` (docs/install.md, 'ArduPilot SITL')"
)
HOME = Origin(-35.363261, 149.165230, 584.0)  # the launcher's --home
MAV_FRAME_LOCAL_NED, MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD = 1, 20, 12
EARTH_RADIUS_M = 6371000.0


class TruthSender:
    """``with TruthSender(port, ...) as s:`` ODOMETRY from the true state at 30 Hz."""

    def __init__(
        self,
        port: int,
        frame_id: int = MAV_FRAME_LOCAL_FRD,
        child_frame_id: int = MAV_FRAME_BODY_FRD,
        set_origin: bool = True,
        quality: int = 80,
    ) -> None:
        self.port = port
        self.frame_id, self.child_frame_id = frame_id, child_frame_id
        self.set_origin = set_origin
        self.quality = quality
        self.origin = OriginKeeper()
        self.sent = 0
        self.texts: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="truth-sender", daemon=True)
        self._conn: Any = None
        self._home: tuple[int, int, float] | None = None

    def __enter__(self) -> TruthSender:
        os.environ["MAVLINK20"] = "1"  # ODOMETRY and SET_GPS_GLOBAL_ORIGIN's time_usec need v2
        from pymavlink import mavutil

        self._conn = mavutil.mavlink_connection(
            f"tcp:127.0.0.1:{self.port}", source_system=1, source_component=197, dialect="common"
        )
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)
        with contextlib.suppress(Exception):
            self._conn.close()

    def _ned(self, st: Any) -> np.ndarray:
        if self._home is None:
            self._home = (int(st.lat_int), int(st.lon_int), float(st.alt))
        lat0 = math.radians(self._home[0] * 1e-7)
        dn = math.radians((int(st.lat_int) - self._home[0]) * 1e-7) * EARTH_RADIUS_M
        de = (
            math.radians((int(st.lon_int) - self._home[1]) * 1e-7) * EARTH_RADIUS_M * math.cos(lat0)
        )
        return np.array([dn, de, -(float(st.alt) - self._home[2])])

    def _run(self) -> None:
        c = self._conn
        last_send = last_hb = last_ask = 0.0
        state: Any = None
        while not self._stop.is_set():
            now = time.monotonic()
            if now - last_ask > 2.0 and state is None:
                last_ask = now
                for msg_id, hz in ((108, 30.0), (33, 2.0)):  # SIM_STATE, GLOBAL_POSITION_INT
                    c.mav.command_long_send(1, 1, 511, 0, msg_id, 1e6 / hz, 0, 0, 0, 0, 0)
            if now - last_hb > 1.0:
                last_hb = now
                c.mav.heartbeat_send(18, 8, 0, 0, 4)
            if self.set_origin and self.origin.due(time.monotonic_ns()):
                c.mav.send(set_gps_global_origin(c.mav, 1, HOME, time.monotonic_ns() // 1000))
                self.origin.mark_sent(time.monotonic_ns())
            if state is not None and now - last_send >= 1 / 30:
                last_send = now
                self._send(state)
            m = c.recv_match(blocking=True, timeout=0.005)
            while m is not None:
                kind = m.get_type()
                if kind == "SIM_STATE":
                    state = m
                elif kind == "GLOBAL_POSITION_INT":
                    self.origin.position(int(m.lat), int(m.lon), time.monotonic_ns())
                elif kind == "STATUSTEXT":
                    self.texts.append(str(m.text))
                m = c.recv_match(blocking=False)

    def _send(self, st: Any) -> None:
        q = np.array([st.q1, st.q2, st.q3, st.q4], dtype=np.float64)
        q /= np.linalg.norm(q)
        v_body = so3.quat_to_matrix(q).T @ np.array([st.vn, st.ve, st.vd])
        p = self._ned(st)
        cov = [
            0.02**2,
            0,
            0,
            0,
            0,
            0,
            0.02**2,
            0,
            0,
            0,
            0,
            0.02**2,
            0,
            0,
            0,
            1e-4,
            0,
            0,
            1e-4,
            0,
            1e-4,
        ]
        self._conn.mav.odometry_send(
            time.monotonic_ns() // 1000,
            self.frame_id,
            self.child_frame_id,
            float(p[0]),
            float(p[1]),
            float(p[2]),
            [float(x) for x in q],
            float(v_body[0]),
            float(v_body[1]),
            float(v_body[2]),
            float(st.xgyro),
            float(st.ygyro),
            float(st.zgyro),
            cov,
            [0.01 if i in (0, 6, 11) else 0.0 for i in range(21)],
            0,
            1,  # MAV_ESTIMATOR_TYPE_VISION
            self.quality,
        )
        self.sent += 1
