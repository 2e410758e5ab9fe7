"""The TFmini serial driver through a pty pair (the serial port that cannot exist here),
with recorded and corrupted byte streams."""

from __future__ import annotations

import os
import threading
import time
import tty

import numpy as np

from companion.drivers.rangefinder import TfminiParser, TfminiSerial, tfmini_frame, to_sample


def stream(distances_cm, strength=800) -> bytes:
    return b"".join(tfmini_frame(d, strength, 31.5) for d in distances_cm)


def test_frames_decode_and_checksums_are_checked() -> None:
    p = TfminiParser()
    got = p.feed(stream([612, 1500, 33]))
    assert [r.distance_cm for r in got] == [612, 1500, 33]
    assert got[0].strength == 800 and abs(got[0].temperature_c - 31.5) < 1e-9
    bad = bytearray(tfmini_frame(700, 800))
    bad[8] ^= 0x01
    assert p.feed(bytes(bad)) == [] and p.bad_checksums == 1


def test_resynchronises_after_garbage_and_split_frames() -> None:
    rng = np.random.default_rng(0)
    p = TfminiParser()
    want, data = [], bytearray()
    for k in range(300):
        d = int(rng.integers(10, 1200))
        want.append(d)
        data += tfmini_frame(d, 900)
        if k % 7 == 0:  # garbage, including stray headers and a truncated frame
            data += bytes(rng.integers(0, 256, int(rng.integers(1, 20)), dtype=np.uint8))
            data += b"\x59\x59\x10"
    got = []
    i = 0
    while i < len(data):  # arbitrary chunking, as a UART delivers it
        n = int(rng.integers(1, 40))
        got += [r.distance_cm for r in p.feed(bytes(data[i : i + n]))]
        i += n
    # every frame after a garbage burst may be lost only if the garbage forged its header;
    # with single-byte resync nearly all survive, and nothing is invented
    assert set(got) <= set(want)  # nothing invented
    assert len(got) >= 0.97 * len(want)
    assert p.skipped_bytes > 0


def test_unreliable_readings_are_flagged_invalid() -> None:
    ok = to_sample(TfminiParser().feed(tfmini_frame(612, 800))[0], 3, 10, 0.1, 12.0)
    assert ok.is_valid and ok.distance_m == 6.12 and ok.sensor_id == 3
    for d, s in ((612, 40), (612, 65535), (0, 800), (65535, 800)):
        r = TfminiParser().feed(tfmini_frame(d, s))[0]
        assert not to_sample(r, 3, 10, 0.1, 12.0).is_valid


def test_serial_driver_over_a_pty_pair() -> None:
    master, slave = os.openpty()
    got = []
    done = threading.Event()

    def on_sample(s) -> None:
        got.append(s)
        if len(got) >= 200:
            done.set()

    tty.setraw(slave)  # no line discipline between the two ends
    drv = TfminiSerial(os.ttyname(slave), 2, 0.1, 12.0, on_sample)
    drv.start()
    assert drv.opened.wait(5.0)
    try:
        t0 = time.monotonic_ns() // 1000
        data = stream(range(100, 300))
        corrupted = bytearray(stream([999]))
        corrupted[5] ^= 0xFF  # a bad checksum in the middle
        os.write(master, data[:900] + bytes(corrupted) + b"\x00\x59garbage" + data[900:])
        assert done.wait(5.0)
    finally:
        drv.close()
        os.close(master)
        os.close(slave)
    assert [s.distance_m for s in got[:3]] == [1.0, 1.01, 1.02]
    assert len(got) == 200 and all(s.is_valid for s in got)
    assert 999 not in [round(s.distance_m * 100) for s in got]
    assert drv.parser.bad_checksums >= 1
    # a frame is stamped back by the wire time of the bytes read after it (115200 baud), so
    # the burst written at once reaches back at most its own wire time before the write
    burst_us = len(data) * 10 / 115200 * 1e6 + 1000
    assert all(t0 - burst_us <= s.time_us <= time.monotonic_ns() // 1000 for s in got)


def test_each_frame_gets_its_own_stamp_as_it_arrives() -> None:
    """A TFmini streams a frame every 20 ms: each sample is stamped when its frame came, not
    when a buffer filled. ``read(256)`` with a 100 ms timeout handed five frames over at once
    under one stamp, up to 80 ms late (the PX4 loop's climb scale, docs/RESULTS.md); a burst
    written at once is spaced by the frames' wire time (9 bytes at 115200 baud: 781 us)."""
    master, slave = os.openpty()
    got: list = []
    done = threading.Event()

    def on_sample(s) -> None:
        got.append(s)
        if len(got) >= 45:
            done.set()

    tty.setraw(slave)
    drv = TfminiSerial(os.ttyname(slave), 2, 0.1, 12.0, on_sample)
    drv.start()
    assert drv.opened.wait(5.0)
    written_us = []
    try:
        for d in range(100, 140):  # 40 frames, one every 20 ms
            written_us.append(time.monotonic_ns() // 1000)
            os.write(master, tfmini_frame(d, 800))
            time.sleep(0.02)
        burst_us = time.monotonic_ns() // 1000
        os.write(master, stream(range(500, 505)))  # five frames in one write
        assert done.wait(5.0)
    finally:
        drv.close()
        os.close(master)
        os.close(slave)
    t = np.array([s.time_us for s in got], dtype=np.int64)
    assert [round(s.distance_m * 100) for s in got] == [*range(100, 140), *range(500, 505)]
    assert np.all(np.diff(t) > 0), "every frame its own, increasing stamp"
    # stamped no earlier than written (less the frame's own wire time, 781 us) ...
    wire_us = drv._frame_us
    assert np.all(t[:40] >= np.array(written_us) - wire_us - 1), t[:40] - written_us
    # ... and one by one: the stamps are spaced as they were written (a batching read gives
    # four of every five gaps under 1 ms, so its median gap is 0.8 ms)
    assert float(np.median(np.diff(t[:40]))) >= 10_000, np.diff(t[:40])
    # the burst: the wire time apart if read together, more if read apart
    assert np.all(np.diff(t[40:]) >= wire_us - 1) and t[40] >= burst_us - 5 * wire_us - 1


def test_the_service_reads_a_tfmini_wired_to_the_companion(tmp_path) -> None:
    import asyncio
    import dataclasses

    from peers import service_config

    from companion.service.app import Service

    master, slave = os.openpty()
    tty.setraw(slave)
    cfg = service_config(tmp_path)
    rfs = list(cfg.rangefinders)
    rfs[1] = dataclasses.replace(rfs[1], serial=f"{os.ttyname(slave)}:115200")
    cfg = dataclasses.replace(cfg, rangefinders=tuple(rfs))

    async def run() -> Service:
        async with Service(cfg) as service:
            assert service.tfminis[0].opened.wait(5.0)
            os.write(master, stream([500] * 50) + stream([500], strength=20))
            for _ in range(100):
                await asyncio.sleep(0.02)
                if service.stats.ranges_in >= 50:
                    break
            await asyncio.sleep(0.1)
        return service

    try:
        service = asyncio.run(run())
    finally:
        os.close(master)
        os.close(slave)
    assert service.stats.ranges_in == 50  # sensor 1's readings reach the pipeline's queue
    assert service.stats.ranges_rejected == 1  # the weak one is counted and dropped
