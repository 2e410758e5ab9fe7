"""A MAVLink flood, as an attacker or a broken radio would send it
(``python -m companion.sitl.stub.flood``).

From its own UDP socket (a process of its own, so that it takes no time from the process it
floods), ``rate`` datagrams per second for ``seconds``, in a seeded mix:
- garbage (random bytes, sometimes starting with a MAVLink 2 marker);
- well-formed frames of another system (a second vehicle, a ground station);
- well-formed frames with the autopilot's own system id (HEARTBEAT, ATTITUDE, TIMESYNC
  requests, COMMAND_ACK, DISTANCE_SENSOR), i.e. spoofed ones.
It paces itself in 10 ms batches and prints one JSON line: what it sent and how fast.
"""

from __future__ import annotations

import argparse
import json
import socket
import time
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink


def packets(n: int, seed: int, system_id: int = 1) -> list[bytes]:
    """``n`` datagrams of the mix above (seeded)."""
    rng = np.random.default_rng(seed)
    own = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=1)
    other = mavlink.MAVLink(None, srcSystem=(system_id % 250) + 2, srcComponent=1)

    def frame(mav: Any, k: int) -> bytes:
        kind = k % 5
        if kind == 0:
            msg = mav.heartbeat_encode(2, 12, 0, 0, 4)
        elif kind == 1:
            msg = mav.attitude_encode(k, 0.3, -0.2, 1.0, 0.0, 0.0, 0.0)
        elif kind == 2:
            msg = mav.timesync_encode(0, k)
        elif kind == 3:
            msg = mav.command_ack_encode(511, 0, 0, 0, system_id, 197)
        else:
            msg = mav.distance_sensor_encode(k, 10, 4000, 123, 0, k % 4, 25, 0)
        return bytes(msg.pack(mav))

    out = []
    for k in range(n):
        r = k % 3
        if r == 0:
            junk = rng.integers(0, 256, int(rng.integers(8, 280)), dtype=np.uint8).tobytes()
            out.append((b"\xfd" + junk) if k % 2 else junk)
        elif r == 1:
            out.append(frame(other, k))
        else:
            out.append(frame(own, k))
    return out


def flood(host: str, port: int, rate: float, seconds: float, seed: int = 0) -> dict[str, Any]:
    """Send the mix to host:port at ``rate`` datagrams/s for ``seconds``."""
    pool = packets(4096, seed)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    batch_s = 0.01
    per_batch = max(1, round(rate * batch_s))
    sent = errors = 0
    t0 = time.monotonic()
    next_t = t0
    while time.monotonic() - t0 < seconds:
        for _ in range(per_batch):
            try:
                sock.sendto(pool[sent % len(pool)], (host, port))
            except OSError:
                errors += 1
            sent += 1
        next_t += batch_s
        time.sleep(max(0.0, next_t - time.monotonic()))
    elapsed = time.monotonic() - t0
    sock.close()
    return {"sent": sent, "errors": errors, "seconds": elapsed, "rate": sent / elapsed}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--rate", type=float, default=5000.0, help="datagrams per second")
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    print(json.dumps(flood(a.host, a.port, a.rate, a.seconds, a.seed)), flush=True)


if __name__ == "__main__":
    main()
