"""MAVLink parameter values: PX4's byte-wise encoding and the float-encoded-integer trap.

PARAM_VALUE / PARAM_SET carry every value in a float32 field. PX4 (and MAVSDK talking to PX4)
copies an INT32's four bytes into it ("byte-wise"). A tool that converts the integer to a float
instead (a C cast, ArduPilot's convention; pymavlink's ``param_set_send(name, 3, INT32)``),
or writes a REAL32 into an INT32 on an old PX4, leaves PX4 with the integer whose bytes are
those of the float: 3 becomes 0x40400000 = 1077936128. The reverse mistake leaves a REAL32
holding an integer's bytes: 1 becomes 1.4e-45.
"""

from __future__ import annotations

import math
import struct


def int32_bits_as_float32(value: int) -> float:
    """The float32 whose 4 bytes are those of the INT32 ``value``."""
    return float(struct.unpack("<f", struct.pack("<i", int(value)))[0])


def float32_bits_as_int32(value: float) -> int:
    """The INT32 whose 4 bytes are those of the float32 ``value``."""
    return int(struct.unpack("<i", struct.pack("<f", float(value)))[0])


def float_encoded_int(value: int, lo: float, hi: float) -> float | None:
    """When the INT32 ``value`` is outside ``[lo, hi]`` but its bytes are those of a whole
    float32 inside it (a float written into an integer parameter), that float; else None."""
    if lo <= value <= hi:
        return None
    f = int32_bits_as_float32(value)
    if math.isfinite(f) and lo <= f <= hi and f == round(f):
        return f
    return None


def int_encoded_float(value: float) -> int | None:
    """When the REAL32 ``value`` is a denormal whose bytes are those of a small non-zero INT32
    (an integer written into a float parameter), that integer; else None."""
    if value == 0.0 or not math.isfinite(value) or abs(value) >= 1.17549435e-38:
        return None
    i = float32_bits_as_int32(value)
    return i if 0 < abs(i) < 1 << 23 else None
