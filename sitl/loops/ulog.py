"""A minimal reader of PX4's ULog files (.ulg): the data of chosen topics as numpy arrays.

Format (PX4 docs, "ULog File Format"): a 16-byte header (magic ``ULog`` 0x01 0x12 0x35, version,
uint64 start time), then messages ``uint16 size, uint8 type, payload``. ``F`` defines a format
``name:type field;type field;...`` (types: the C integer types, float, double, bool, char,
arrays ``type[n]``, or another format's name), ``A`` subscribes a topic instance to a message id
(``uint8 multi_id, uint16 msg_id, name``), ``D`` carries ``uint16 msg_id`` + the packed fields
(trailing padding may be left out). Everything else (info, parameters, logging) is skipped.
A file cut short (PX4 stopped while writing) yields what was complete.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np

_BASIC = {
    "int8_t": "i1",
    "uint8_t": "u1",
    "int16_t": "<i2",
    "uint16_t": "<u2",
    "int32_t": "<i4",
    "uint32_t": "<u4",
    "int64_t": "<i8",
    "uint64_t": "<u8",
    "float": "<f4",
    "double": "<f8",
    "bool": "?",
    "char": "S1",
}
MAGIC = b"ULog\x01\x12\x35"


def _dtype(name: str, formats: dict[str, list[tuple[str, str]]], memo: dict[str, Any]) -> Any:
    if name in memo:
        return memo[name]
    fields = []
    for ftype, fname in formats[name]:
        count = 1
        if ftype.endswith("]"):
            ftype, _, n = ftype[:-1].partition("[")
            count = int(n)
        base = _BASIC[ftype] if ftype in _BASIC else _dtype(ftype, formats, memo)
        fields.append((fname, base, (count,)) if count > 1 else (fname, base))
    dt = np.dtype(fields)
    memo[name] = dt
    return dt


def read_topics(path: Path, topics: set[str]) -> dict[str, np.ndarray]:
    """{topic: structured array} of instance 0 of each wanted topic present in the log."""
    data = path.read_bytes()
    if not data.startswith(MAGIC):
        raise ValueError(f"{path}: not a ULog file")
    formats: dict[str, list[tuple[str, str]]] = {}
    subs: dict[int, str] = {}
    chunks: dict[str, list[bytes]] = {}
    pos = 16
    n = len(data)
    while pos + 3 <= n:
        size, kind = struct.unpack_from("<HB", data, pos)
        body = data[pos + 3 : pos + 3 + size]
        if len(body) < size:
            break
        pos += 3 + size
        if kind == ord("F"):
            text = body.decode("ascii", "replace")
            fname, _, rest = text.partition(":")
            formats[fname] = [
                (f.split(" ")[0], f.split(" ")[1]) for f in rest.split(";") if " " in f
            ]
        elif kind == ord("A"):
            multi_id, msg_id = struct.unpack_from("<BH", body, 0)
            name = body[3:].decode("ascii", "replace")
            if name in topics and multi_id == 0:
                subs[msg_id] = name
        elif kind == ord("D"):
            (msg_id,) = struct.unpack_from("<H", body, 0)
            topic = subs.get(msg_id)
            if topic is not None:
                chunks.setdefault(topic, []).append(body[2:])
    out: dict[str, np.ndarray] = {}
    memo: dict[str, Any] = {}
    for topic, parts in chunks.items():
        dt = _dtype(topic, formats, memo)
        raw = b"".join(p[: dt.itemsize].ljust(dt.itemsize, b"\0") for p in parts)
        out[topic] = np.frombuffer(raw, dtype=dt)
    return out
