"""Rangefinders wired to the companion: the Benewake TFmini / TFmini-S / TFmini Plus serial
protocol (pyserial). DISTANCE_SENSOR from the autopilot is in :mod:`drivers.messages`.

Frame (9 bytes, 115200 baud by default): 0x59 0x59, distance (uint16 LE, cm), strength (uint16
LE), two model-specific bytes (TFmini-S/Plus: temperature, raw/8 - 256 degC), checksum = low
byte of the sum of the first eight bytes. Readings with strength < 100 or 65535, or a distance
of 0 or 65535, are unreliable (Benewake's manuals): they become RangeSample with
signal_quality 1 (invalid), so the pipeline counts and ignores them.

The parser resynchronises after garbage: it looks for the 0x59 0x59 header, checks the
checksum, and on a bad one skips a single byte (not the whole claimed frame), so a corrupted
frame costs at most itself.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from companion.drivers.backoff import Backoff
from companion.types import RangeSample

HEADER = b"\x59\x59"
FRAME_LEN = 9


@dataclass(frozen=True, slots=True)
class TfminiReading:
    distance_cm: int
    strength: int
    temperature_c: float


def tfmini_frame(distance_cm: int, strength: int, temperature_c: float = 25.0) -> bytes:
    """Encode one frame (for tests and recordings)."""
    raw_t = int(round((temperature_c + 256.0) * 8)) & 0xFFFF
    body = HEADER + bytes(
        [
            distance_cm & 0xFF,
            (distance_cm >> 8) & 0xFF,
            strength & 0xFF,
            (strength >> 8) & 0xFF,
            raw_t & 0xFF,
            (raw_t >> 8) & 0xFF,
        ]
    )
    return body + bytes([sum(body) & 0xFF])


class TfminiParser:
    """Bytes -> readings, resynchronising after garbage; counts what it dropped."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.frames = 0
        self.bad_checksums = 0
        self.skipped_bytes = 0

    @property
    def pending(self) -> int:
        """Bytes held for the next frame (a frame split across reads)."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[TfminiReading]:
        buf = self._buf
        buf.extend(data)
        out: list[TfminiReading] = []
        while True:
            start = buf.find(HEADER)
            if start < 0:
                keep = 1 if buf.endswith(HEADER[:1]) else 0
                self.skipped_bytes += len(buf) - keep
                del buf[: len(buf) - keep]
                return out
            if start:
                self.skipped_bytes += start
                del buf[:start]
            if len(buf) < FRAME_LEN:
                return out
            if sum(buf[:8]) & 0xFF != buf[8]:
                self.bad_checksums += 1
                self.skipped_bytes += 1
                del buf[:1]  # resync from the next byte, not after the claimed frame
                continue
            dist = buf[2] | (buf[3] << 8)
            strength = buf[4] | (buf[5] << 8)
            temp = (buf[6] | (buf[7] << 8)) / 8.0 - 256.0
            del buf[:FRAME_LEN]
            self.frames += 1
            out.append(TfminiReading(dist, strength, temp))


def to_sample(
    r: TfminiReading, sensor_id: int, time_us: int, min_m: float, max_m: float
) -> RangeSample:
    """A RangeSample (metres; signal_quality 1 for an unreliable reading, else 100)."""
    unreliable = r.strength < 100 or r.strength == 0xFFFF or r.distance_cm in (0, 0xFFFF)
    return RangeSample(
        time_us, sensor_id, r.distance_cm * 0.01, min_m, max_m, 1 if unreliable else 100
    )


class TfminiSerial:
    """A TFmini on a serial port, read in a daemon thread; every sample goes to ``on_sample``
    stamped with our monotonic clock at reception minus the wire time of the frame and of every
    byte that came after it in the same read. A port that fails (unplugged adapter) is closed
    and reopened with capped, jittered backoff.

    A read returns as soon as bytes have arrived (the first byte, then whatever is waiting):
    ``read(256)`` with a 100 ms timeout waits for 256 bytes, so at 50 Hz it handed over five
    frames every 100 ms under one stamp, up to 80 ms late (measured in the PX4 loop, where it
    made the metric scale 15 % short in the climb: docs/RESULTS.md)."""

    def __init__(
        self,
        device: str,
        sensor_id: int,
        min_m: float,
        max_m: float,
        on_sample: Callable[[RangeSample], None],
        baud: int = 115200,
    ) -> None:
        self.device, self.baud = device, baud
        self.sensor_id, self.min_m, self.max_m = sensor_id, min_m, max_m
        self.on_sample = on_sample
        self.parser = TfminiParser()
        self.reopens = 0
        self.last_error = ""  # why the port is not open (empty while it is)
        self.samples = 0  # samples handed to on_sample
        self._closing = False
        self.opened = threading.Event()  # set once the port is open (raw mode)
        self._thread: threading.Thread | None = None
        self._byte_us = 10 / baud * 1e6  # 10 bits per byte on the wire
        self._frame_us = int(FRAME_LEN * self._byte_us)

    def start(self) -> None:
        self._thread = threading.Thread(
            target=self._run, name=f"tfmini-{self.sensor_id}", daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        self._closing = True
        if self._thread is not None:
            self._thread.join(2.0)

    def _run(self) -> None:
        import serial  # pyserial

        port = None
        backoff = Backoff(0.2, 5.0)
        while not self._closing:
            if port is None:
                try:
                    port = serial.Serial(self.device, self.baud, timeout=0.1)
                    backoff.reset()
                    self.last_error = ""
                    self.opened.set()
                except (OSError, serial.SerialException) as e:
                    self.last_error = f"cannot open {self.device}: {e}"
                    time.sleep(backoff.next_s())
                    continue
            try:
                data = port.read(1)  # blocks until a byte comes (or the timeout)
                if data and port.in_waiting:
                    data += port.read(port.in_waiting)
            except (OSError, serial.SerialException) as e:
                self.last_error = f"{self.device} failed: {e}"
                self.reopens += 1
                with contextlib.suppress(Exception):
                    port.close()
                port = None
                continue
            if not data:
                continue
            now_us = time.monotonic_ns() // 1000
            readings = self.parser.feed(data)
            for k, r in enumerate(readings):
                # bytes on the wire after this frame's end: later frames, then a partial one
                after = (len(readings) - 1 - k) * FRAME_LEN + self.parser.pending
                time_us = now_us - int(after * self._byte_us) - self._frame_us
                self.samples += 1
                self.on_sample(to_sample(r, self.sensor_id, time_us, self.min_m, self.max_m))
        if port is not None:
            port.close()
