"""Bad input against the service: 100,000 random and mutated MAVLink packets on its port, bad
distance readings, an autopilot serial port that vanishes and returns, a bad config, a kill
(the reset counter after it) and a packet flood."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import os
import socket
import struct
import subprocess
import sys
import time
import tty
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from peers import free_port, service_config
from pymavlink.dialects.v20 import common as mavlink

from companion.config import load_config
from companion.drivers.mavlink import MavlinkLink
from companion.drivers.status import read_status
from companion.offline import feed_step
from companion.pipeline import Pipeline
from companion.service.app import Service
from companion.sitl.world.scenario import Scenario
from companion.types import RangeSample


def _absurd_float(rng: np.random.Generator) -> float:
    return float(rng.choice([np.nan, np.inf, -np.inf, 1e38, -1e38, 0.0, rng.normal(0, 1e3)]))


def _random_message(mav: Any, rng: np.random.Generator) -> Any:
    """A well-formed message of a type the service handles (or ignores), absurd fields."""
    f = lambda: _absurd_float(rng)  # noqa: E731
    u = lambda bits: int(rng.integers(0, 2**bits))  # noqa: E731
    kind = int(rng.integers(0, 8))
    if kind == 0:
        return mav.heartbeat_encode(u(8), u(8), u(8), u(32), u(8))
    if kind == 1:
        return mav.timesync_encode(u(63) - 2**62, u(63) - 2**62)
    if kind == 2:
        return mav.attitude_encode(u(32), f(), f(), f(), f(), f(), f())
    if kind == 3:
        return mav.distance_sensor_encode(
            u(32), u(16), u(16), u(16), u(8), u(8), u(8), u(8), f(), f(), [f()] * 4, u(8)
        )
    if kind == 4:
        return mav.command_ack_encode(u(16), u(8), u(8), u(32) - 2**31, u(8), u(8))
    if kind == 5:
        return mav.command_long_encode(u(8), u(8), u(16), u(8), f(), f(), f(), f(), f(), f(), f())
    if kind == 6:
        return mav.param_value_encode(b"EKF2_EV_CTRL", f(), u(8), u(16), u(16))
    return mav.odometry_encode(
        u(32), u(8), u(8), f(), f(), f(), [f()] * 4, f(), f(), f(), f(), f(), f(),
        [f()] * 21, [f()] * 21, u(8), u(8), u(8) - 128,
    )  # fmt: skip


def fuzz_packets(n: int, seed: int) -> list[bytes]:
    """n datagrams: valid frames with absurd fields, flipped bytes, truncated frames, wrong
    length bytes, wrong CRCs, unknown message ids with a valid CRC, random bytes, and
    several frames glued into one datagram."""
    rng = np.random.default_rng(seed)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    out: list[bytes] = []
    for _ in range(n):
        mav.srcSystem = 1 if rng.uniform() < 0.8 else int(rng.integers(0, 256))
        buf = bytearray(_random_message(mav, rng).pack(mav))
        r = rng.uniform()
        if r < 0.25:
            pass  # well formed, absurd values
        elif r < 0.45:
            for i in rng.integers(0, len(buf), int(rng.integers(1, 4))):
                buf[i] ^= int(rng.integers(1, 256))
        elif r < 0.6:
            buf = buf[: int(rng.integers(1, len(buf)))]
        elif r < 0.7:
            buf[1] = int(rng.integers(0, 256))  # payload length
        elif r < 0.8:
            buf[-1] ^= 0x5A  # CRC
        elif r < 0.9:  # an id nobody knows, with a CRC computed without a CRC extra
            buf[7:10] = struct.pack("<I", int(rng.integers(20000, 2**24)))[:3]
            crc = mavlink.x25crc(bytes(buf[1:-2]))
            buf[-2:] = struct.pack("<H", crc.crc)
        elif r < 0.95:
            buf = bytearray(rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8))
        else:
            more = [_random_message(mav, rng).pack(mav) for _ in range(int(rng.integers(1, 4)))]
            buf += b"".join(more)
        out.append(bytes(buf))
    return out


@pytest.mark.timeout(300)
def test_100k_random_and_mutated_packets_on_its_port(tmp_path) -> None:
    packets = fuzz_packets(100_000, seed=11)
    port = free_port(socket.SOCK_DGRAM)
    # no camera (the camera loop keeps trying)
    cfg = service_config(tmp_path, mavlink_url=f"udpin:127.0.0.1:{port}")
    loop_errors: list[Any] = []

    async def main() -> tuple[dict, dict | None, bool, int]:
        asyncio.get_running_loop().set_exception_handler(lambda _l, ctx: loop_errors.append(ctx))
        async with Service(cfg) as service:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind(("127.0.0.1", 0))
            sent = 0
            for k in range(0, len(packets), 100):
                for p in packets[k : k + 100]:
                    sock.sendto(p, ("127.0.0.1", port))
                    sent += len(p)
                # paced by what the service has read (a loaded CI machine must not turn this
                # into a test of the kernel's socket buffer): wait for the burst, up to 2 s
                deadline = time.monotonic() + 2.0
                while service.link.stats.rx_bytes < sent and time.monotonic() < deadline:
                    await asyncio.sleep(0.001)
            await asyncio.sleep(0.5)
            status = await asyncio.to_thread(read_status, tmp_path / "status.sock")
            # still answering: a real TIMESYNC request after the storm
            mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
            sock.settimeout(0.1)
            answered = False
            sock.sendto(mav.timesync_encode(0, 424242).pack(mav), ("127.0.0.1", port))
            t0 = time.monotonic()  # still answering, however loaded the machine (not its speed)
            while time.monotonic() - t0 < 10 and not answered:
                with contextlib.suppress(TimeoutError):
                    data = await asyncio.to_thread(sock.recv, 4096)
                    answered = any(
                        m.get_type() == "TIMESYNC" and m.ts1 == 424242
                        for m in mav.parse_buffer(data) or []
                    )
            tasks_alive = [t.get_name() for t in service.tasks if not t.done()]
            tasks_dead = [t.get_name() for t in service.tasks if t.done()]
            queued_attitudes = list(service.session.attitudes)
            queued_ranges = list(service.session.ranges)
            summary = service.summary()
            sock.close()
        # whatever got through is plausible (the pipeline has no camera, so the queues hold
        # every accepted sample)
        for a in queued_attitudes:
            assert np.all(np.isfinite(a.quat_wxyz)) and np.all(np.abs(a.rates_rad_s) <= 50)
        assert all(r.is_valid for r in queued_ranges)
        return summary, status, (answered, tasks_alive, tasks_dead), sent

    summary, status, (answered, tasks_alive, tasks_dead), sent = asyncio.run(main())
    link = summary["link"]
    print(link, summary["ranges_rejected"], summary["attitudes_in"])
    assert answered, "no TIMESYNC answer within 10 s of the storm's end"
    assert tasks_alive and not tasks_dead, tasks_dead
    assert not loop_errors, loop_errors
    assert link["handler_errors"] == 0
    assert link["rx_bytes"] >= 0.99 * sent  # the storm was read, not lost in the socket
    assert link["rx_bad"] > 20_000 and link["rx_messages"] > 20_000
    assert status is not None and status["autopilot"]["rx_bad"] > 0
    assert status["autopilot"]["foreign_messages"] > 1000
    assert status["autopilot"]["attitudes_rejected"] > 100
    assert summary["ranges_rejected"] > 100


def test_bad_ranges_are_counted_and_do_not_move_the_scale() -> None:
    """Two pipelines fed the same flight; one also gets every kind of bad reading before each
    frame (NaN, infinite, negative, zero, below min, above max, invalid quality, unknown
    sensor, repeated and older time stamps). The scale must be identical to the bit."""
    cfg = load_config(
        overrides={"sitl": {"terrain": "hills", "trajectory": "lawnmower", "seconds": 8.0}}
    )
    clean, dirty = Pipeline(cfg), Pipeline(cfg)
    injected = 0
    for step in Scenario(cfg).steps():
        feed_step(clean, step)
        feed_step(dirty, step)
        a, b = clean.estimates[clean.method_name], dirty.estimates[dirty.method_name]
        assert (a is None) == (b is None)
        if a is not None and b is not None:
            assert a.scale == b.scale and a.sigma == b.sigma
        # after this frame's readings, before the next frame's: every kind of bad one
        t = step.frame.time_us
        for rf in cfg.rangefinders:
            lo, hi = rf.min_m, rf.max_m
            for d, q, sid, tt in (
                (np.nan, 100, rf.sensor_id, t),
                (np.inf, 100, rf.sensor_id, t),
                (-1.0, 100, rf.sensor_id, t),
                (0.0, 100, rf.sensor_id, t),
                (lo * 0.5, 100, rf.sensor_id, t),
                (hi * 2.0, 100, rf.sensor_id, t),
                (5.0, 1, rf.sensor_id, t),
                (5.0, 100, 200 + rf.sensor_id, t),
                (5.0, 100, rf.sensor_id, t - 10_000_000),  # older than the last one
            ):
                if tt < t and rf.sensor_id not in dirty.ranges.sensors():
                    continue  # nothing to be older than yet (the service refuses it by age)
                dirty.feed_range(RangeSample(tt, sid, d, lo, hi, q))
                injected += 1
        for r in step.ranges:  # the same readings again: refused
            if r.sample is not None:
                dirty.feed_range(r.sample)
                injected += 1
    assert clean.estimates[clean.method_name] is not None
    assert dirty.ranges.rejected - clean.ranges.rejected == injected


def test_the_autopilot_serial_port_vanishes_and_returns(tmp_path) -> None:
    """A USB serial adapter: its device path disappears (the pty closes, the symlink goes) and
    comes back as a new device under the same name; the link reopens it by itself."""
    dev = tmp_path / "ttyACM0"

    def plug() -> int:
        master, slave = os.openpty()
        tty.setraw(slave)
        if dev.is_symlink():
            dev.unlink()
        dev.symlink_to(os.ttyname(slave))
        os.close(slave)  # only the link holds the device open
        return master

    got: list[str] = []
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    hb = mav.heartbeat_encode(2, 12, 0, 0, 4).pack(mav)

    async def main() -> int:
        link = MavlinkLink(f"serial:{dev}:921600", 1, 197, lambda m, t: got.append(m.get_type()))
        master = plug()
        async with link:
            for _ in range(30):
                os.write(master, hb)
                await asyncio.sleep(0.05)
            before = len(got)
            os.close(master)  # unplugged
            dev.unlink()
            await asyncio.sleep(1.0)
            master = plug()  # back, a new device node behind the same name
            deadline = time.monotonic() + 10
            while len(got) < before + 10 and time.monotonic() < deadline:
                os.write(master, hb)
                await asyncio.sleep(0.05)
            os.close(master)
            assert before >= 20
            return link.stats.reconnects

    reconnects = asyncio.run(main())
    assert got.count("HEARTBEAT") >= 30 and reconnects >= 1


def test_a_bad_config_exits_2_naming_the_key_and_starts_nothing(tmp_path) -> None:
    sock = tmp_path / "status.sock"
    bad = tmp_path / "bad.toml"
    bad.write_text(f'[service]\nmavlink_url = "udp://nowhere"\nstatus_socket = "{sock}"\n')
    r = subprocess.run(
        [sys.executable, "-m", "companion.cli", "run", "--config", str(bad)],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert r.returncode == 2
    errors = [line for line in r.stderr.splitlines() if "service.mavlink_url" in line]
    assert len(errors) == 1 and "Traceback" not in r.stderr
    assert not sock.exists()


def test_reset_counter_after_a_kill_never_repeats_the_last_one_sent(tmp_path) -> None:
    """SIGKILL between two poses, then a restart: the first counter sent differs from the
    last one of the killed run (EKF2 would fuse the new origin as a jump otherwise)."""
    from companion.service.state import ResetCounter

    path = tmp_path / "state" / "reset_counter"
    script = (
        "import sys, time\n"
        "from pathlib import Path\n"
        "from companion.service.state import ResetCounter\n"
        f"rc = ResetCounter(Path({str(path)!r}))\n"
        "for k in range(int(sys.argv[1]) + 1):\n"
        "    sent = rc.wire(k)\n"
        "print(sent, flush=True)\n"
        "time.sleep(60)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    last_sent = []
    for resets in (21, 0, 0, 3):  # a run that re-initialised 21 times, then crashes at 0
        proc = subprocess.Popen(
            [sys.executable, "-c", script, str(resets)], stdout=subprocess.PIPE, env=env
        )
        assert proc.stdout is not None
        last_sent.append(int(proc.stdout.readline()))
        proc.kill()  # SIGKILL: no clean-up of any kind
        proc.wait()
    assert last_sent[0] == 21
    assert all(a != b for a, b in itertools.pairwise(last_sent)), last_sent
    assert ResetCounter(path).wire(0) == (last_sent[-1] + 1) % 256


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_poses_keep_flowing_through_a_5000_packet_per_second_flood(tmp_path) -> None:
    """A SITL flight in slow motion (16 s of flight in 32 s: the camera at 15 frames/s);
    from 6.5 to 15.5 s of flight (18 s) another process floods the service's port with 5,000
    datagrams/s (garbage, another system's frames, spoofed autopilot frames) from its own
    address. Before the fix the output stopped for ~45 s. Asserted at any load: the rate in
    the flood is >= 80 % of the rate before it (and >= half of what the pipeline could do, up
    to the camera's), no VO reset, and the flood was read (dropped by address, not lost in
    the socket buffer). The figure at 30 Hz on a quiet machine is in docs/BENCHMARKS.md.

    Slow motion, because the 80 % is about the service, not the machine: in real time on a
    2-core host that turns a frame over in 45 ms with the SITL autopilot in its process
    (2026-11-27), the pipeline had no time to spare before the flood, and the CPU the flood
    takes (its sender and the reading of 5,000 datagrams/s) came straight off the output
    rate (22.8 poses/s before, 14.5 in it). At half the camera rate the pipeline has the
    slack a vehicle's companion has; a service that stalls in the flood still fails."""
    from peers import sitl_flight

    from companion.sitl.stub.autopilot import SimAutopilot

    seconds, flood_s, scale = 16.0, (6.5, 15.5), 0.5
    cfg, opts = sitl_flight(tmp_path, seconds, small=True, time_scale=scale)  # 320x240
    port = int(cfg.service.mavlink_url.rsplit(":", 1)[1])

    async def fly() -> tuple[SimAutopilot, dict, dict, dict]:
        stub = SimAutopilot(cfg, opts)
        stub_task = asyncio.create_task(stub.run(tmp_path / "autopilot"))
        async with Service(cfg) as service:
            stub_task.add_done_callback(lambda _: service.stop())

            async def attack() -> dict:
                while stub.t_sim_of_mono(time.monotonic_ns()) < flood_s[0]:
                    await asyncio.sleep(0.05)
                proc = await asyncio.create_subprocess_exec(
                    sys.executable,
                    "-m",
                    "companion.sitl.stub.flood",
                    "--port",
                    str(port),
                    "--rate",
                    "5000",
                    "--seconds",
                    str((flood_s[1] - flood_s[0]) / scale),  # wall-clock
                    stdout=asyncio.subprocess.PIPE,
                    cwd=Path(__file__).resolve().parents[2],
                )
                out, _ = await proc.communicate()
                return dict(json.loads(out))

            attacker = asyncio.create_task(attack())
            await service.run()
            sent = await attacker
            summary = service.summary()
            link = vars(service.link.stats)
        report = await stub_task
        return stub, report, summary, {"flood": sent, "link": link}

    stub, report, summary, extra = asyncio.run(fly())
    rec = [r for r in stub.stats.received if r.kind == report["message"]]
    t_pose = np.array([r.t_sim_s for r in rec])

    def rate(lo: float, hi: float) -> float:
        return float(((t_pose >= lo) & (t_pose < hi)).sum() / (hi - lo))

    # poses per second of flight (twice those per wall-clock second)
    before, during = rate(3.0, flood_s[0]), rate(flood_s[0] + 0.5, flood_s[1] - 0.5)
    print(f"poses/s before {before:.1f}, in the flood {during:.1f}", extra, summary)
    assert extra["flood"]["rate"] >= 2500, extra["flood"]  # the attacker really flooded
    assert extra["link"]["rx_other_address"] >= 0.5 * extra["flood"]["sent"]
    # at least half of what the machine let the pipeline do, up to the camera's rate (a slow
    # host turned a frame over in 60-80 ms on 2026-11-27)
    keep_up = min(cfg.camera.rate_hz, summary["pipeline_capacity_hz"] / scale)
    assert during >= 0.8 * before and during >= 0.5 * keep_up, (before, during, keep_up)
    assert report["resets"] <= summary["vo_gaps"]
    assert summary["pipeline_errors"] == 0 and summary["link"]["handler_errors"] == 0
