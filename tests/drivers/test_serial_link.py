"""The autopilot link over a serial port (a pty pair: pyserial on the slave end, the autopilot
on the master end, in its own process): messages reach the event loop as they arrive, stamped
then, so that PX4's TIMESYNC round trips stay within its 10 ms limit; a byte flood faster
than the parser never holds up the event loop (SIGTERM is handled within 1 s)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
import tty
from pathlib import Path

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

ROOT = Path(__file__).resolve().parents[2]

# The autopilot's side: PX4's TIMESYNC requests at 50 Hz (ts1 = its monotonic clock, which is
# the machine's, as ours) among an ATTITUDE stream; for every answer [ns], its round trip and
# how long after the request's sending we answered (tc1 - ts1: our share of the round trip).
AUTOPILOT = r"""
import json, os, select, sys, time
from pymavlink.dialects.v20 import common as mavlink
fd, n = int(sys.argv[1]), int(sys.argv[2])
mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
mav.robust_parsing = True
rtt_ns, sent, next_s = [], 0, time.monotonic()
end_s = next_s + n * 0.02 + 1.0
while time.monotonic() < end_s and len(rtt_ns) < n:
    if sent < n and time.monotonic() >= next_s:
        os.write(fd, mav.attitude_encode(sent, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0).pack(mav))
        os.write(fd, mav.timesync_encode(0, time.monotonic_ns()).pack(mav))
        sent += 1
        next_s += 0.02
    ready, _, _ = select.select([fd], [], [], max(0.0, min(0.005, next_s - time.monotonic())))
    if ready:
        data = os.read(fd, 4096)
        now_ns = time.monotonic_ns()
        for m in mav.parse_buffer(data) or []:
            if m.get_type() == "TIMESYNC" and m.tc1 != 0:
                rtt_ns.append((now_ns - m.ts1, m.tc1 - m.ts1))
print(json.dumps(rtt_ns))
"""

# The companion's side alone: a MavlinkLink on the serial port answering TIMESYNC as the
# service does, SIGTERM through the event loop as `companion run` takes it; prints when the
# handler ran [ns, monotonic] and the link's counters.
COMPANION = r"""
import asyncio, json, signal, sys, time
from companion.drivers.mavlink import MavlinkLink
from companion.drivers.timesync import reply_for
sys.setswitchinterval(0.0005)  # as the service sets it
dev = sys.argv[1]
handled = {}

async def main():
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    def on_term():
        handled["ns"] = time.monotonic_ns()
        stop.set()
    loop.add_signal_handler(signal.SIGTERM, on_term)
    def on_message(msg, rx_ns):
        if msg.get_type() == "TIMESYNC":
            reply = reply_for(msg.tc1, msg.ts1, time.monotonic_ns())
            if reply is not None:
                link.send(link.mav.timesync_encode(reply.tc1, reply.ts1))
    link = MavlinkLink(f"serial:{dev}:921600", 1, 197, on_message)
    async with link:
        print("ready", flush=True)
        await stop.wait()
    print(json.dumps({"handled_ns": handled["ns"], "stats": vars(link.stats)}), flush=True)

asyncio.run(main())
"""


def _pty() -> tuple[int, str]:
    """(the master's descriptor, the slave's device path): a raw serial line."""
    master, slave = os.openpty()
    tty.setraw(slave)
    tty.setraw(master)
    path = os.ttyname(slave)
    os.close(slave)  # the link opens it by its path, as a device
    return master, path


def test_timesync_round_trips_over_a_serial_link_stay_within_px4s_limit() -> None:
    """PX4 fuses an answer only when its round trip is below 10 ms (MAX_RTT_SAMPLE). Through
    MavlinkLink's serial reader on a pty (no wire delay), our share of it (the request's
    sending to our answer, tc1 - ts1: the reader and our loop) is p50 <= 2 ms and p90 <= 5
    ms, and 90 % of the round trips are within PX4's limit. Before, ``read(4096)`` returned
    at its 0.1 s time-out: round trips p50 52 ms, p90 91 ms (8-9 % of answers fused; PX4
    converged in ~2 min instead of ~10 s). The bounds leave room for a loaded host (alone:
    p99 under 5 ms and 98 % within the limit; beside a full test run the p99 reached 9.9 ms)
    and none for the time-out: its answers wait 50-100 ms."""
    import asyncio

    from companion.drivers.mavlink import MavlinkLink
    from companion.drivers.timesync import reply_for

    master, dev = _pty()
    arrivals_ms: list[float] = []  # the request's stamp at reception - its sending

    async def main() -> list[list[int]]:
        def on_message(msg, rx_ns: int) -> None:
            if msg.get_type() == "TIMESYNC":
                reply = reply_for(msg.tc1, msg.ts1, time.monotonic_ns())
                if reply is not None:
                    link.send(link.mav.timesync_encode(reply.tc1, reply.ts1))
                    arrivals_ms.append((rx_ns - msg.ts1) * 1e-6)

        link = MavlinkLink(f"serial:{dev}:921600", 1, 197, on_message)
        switch_s = sys.getswitchinterval()
        sys.setswitchinterval(0.0005)  # as the service runs
        try:
            async with link:
                await asyncio.sleep(0.3)  # the port is open
                peer = await asyncio.create_subprocess_exec(
                    sys.executable,
                    "-c",
                    AUTOPILOT,
                    str(master),
                    "500",
                    pass_fds=(master,),
                    stdout=subprocess.PIPE,
                    cwd=ROOT,
                )
                out, _ = await asyncio.wait_for(peer.communicate(), 60)
        finally:
            sys.setswitchinterval(switch_s)
            os.close(master)
        return list(json.loads(out))

    answers = np.array(asyncio.run(main())) * 1e-6
    assert len(answers) >= 490, len(answers)  # every answer came back (a few may be cut)
    rtt_ms, answered_ms = answers[:, 0], answers[:, 1]
    p50, p90, p99 = np.percentile(answered_ms, [50, 90, 99])
    rtt_p50, rtt_p99 = np.percentile(rtt_ms, [50, 99])
    print(
        f"serial TIMESYNC: answered p50 {p50:.2f} ms, p99 {p99:.2f} ms after the request; "
        f"round trip p50 {rtt_p50:.2f} ms, p99 {rtt_p99:.2f} ms, max {rtt_ms.max():.1f} ms"
    )
    assert p50 <= 2.0 and p90 <= 5.0, (p50, p90, p99)  # our share: the reader and the loop
    assert p99 < 50.0, (p50, p90, p99)  # no answer waits for a read's time-out
    # the whole round trip also counts the peer's own wake-up on this shared machine: PX4's
    # limit, nearly always
    assert np.mean(rtt_ms < 10.0) >= 0.9, (rtt_p50, rtt_p99)
    # each chunk is stamped at its arrival, not when the loop got to it
    assert np.percentile(arrivals_ms, 90) <= 5.0, np.percentile(arrivals_ms, [50, 90, 99])


def _flood(master: int, seconds: float, written: list[int]) -> None:
    """Write MAVLink frames (the autopilot's, parsed in full) and garbage as fast as the pty
    takes them, for ``seconds``."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frames = b"".join(
        mav.attitude_encode(k, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0).pack(mav) for k in range(200)
    )
    rng = np.random.default_rng(3)
    blob = frames + rng.integers(0, 256, 8192, dtype=np.uint8).tobytes() + frames
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            written[0] += os.write(master, blob)
        except BlockingIOError:  # the pty is full: the reader is behind
            time.sleep(0.001)
        except OSError:  # closed
            return


def test_a_serial_byte_flood_never_delays_sigterm_by_more_than_1_s() -> None:
    """Bytes faster than the parser (35 MB in 10 s in the attack; here as fast as the pty
    takes them): before, every 4 KiB the reader thread read was queued on the event loop, the
    queue outgrew the parser and SIGTERM waited behind it (lost for the flight). Now one
    wake-up at a time parses at most 4 KiB, the rest waits in a bounded backlog (the oldest
    dropped, counted), so the signal is handled within 1 s while the flood goes on."""
    master, dev = _pty()
    child = subprocess.Popen(
        [sys.executable, "-c", COMPANION, dev],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    written = [0]
    flooder = threading.Thread(target=_flood, args=(master, 6.0, written), daemon=True)
    try:
        assert child.stdout is not None
        assert child.stdout.readline().strip() == "ready"
        flooder.start()
        time.sleep(3.0)  # the flood is on
        sent_ns = time.monotonic_ns()
        child.send_signal(signal.SIGTERM)
        try:
            out, _ = child.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            child.kill()
            child.communicate()
            raise AssertionError("SIGTERM not handled within 10 s of a serial flood") from None
    finally:
        if child.poll() is None:
            child.kill()
        flooder.join(10)
        os.close(master)
    report = json.loads(out.strip().splitlines()[-1])
    delay_s = (report["handled_ns"] - sent_ns) * 1e-9
    stats = report["stats"]
    print(
        f"flood: {written[0] / 1e6:.1f} MB written, {stats['rx_bytes'] / 1e6:.1f} MB parsed, "
        f"{stats['rx_overflow_bytes'] / 1e6:.1f} MB dropped; SIGTERM handled after "
        f"{delay_s * 1e3:.0f} ms"
    )
    assert delay_s <= 1.0, delay_s
    assert stats["rx_messages"] > 1000  # the flood did reach the parser...
    assert stats["rx_overflow_bytes"] > 0  # ...faster than it parses
