"""PX4's MAVLink shell (nsh over SERIAL_CONTROL): command output parsers.

``listener <topic>`` prints the last message of a uORB topic::

    TOPIC: vehicle_visual_odometry
     vehicle_odometry
        timestamp: 71100704 (0.004519 seconds ago)
        pose_frame: 2
        position: [1.20000, -0.40000, -5.90000]
        ...

or ``never published``. ``uorb top -1`` prints one table of publication rates. These parsers
take the text as it arrives (echoed command, ANSI erase sequences and the ``nsh>`` prompt
included) and keep what they recognise.
"""

from __future__ import annotations

import math
import re
from typing import Any

_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")
_FIELD = re.compile(r"^\s+([A-Za-z_][A-Za-z0-9_\[\]]*):\s*(.*?)\s*$")
_STAMP = re.compile(r"^(-?\d+)\s*\((-?[\d.]+)\s+seconds ago\)$")

Fields = dict[str, Any]


def clean(text: str) -> str:
    """Text without ANSI sequences and carriage returns."""
    return _ANSI.sub("", text).replace("\r", "")


def _scalar(raw: str) -> Any:
    if raw in ("True", "False"):
        return raw == "True"
    try:
        return int(raw)
    except ValueError:
        pass
    try:
        return float(raw)
    except ValueError:
        return raw


def parse_listener(text: str) -> Fields | None:
    """The fields of ``listener`` output; None when the topic was never published (or is not
    known to this firmware). Timestamps ``t (x seconds ago)`` give ``t`` and ``<name>_age_s``;
    arrays become lists of floats (``nan`` included)."""
    text = clean(text)
    if "never published" in text or "not found" in text or "TOPIC:" not in text:
        return None
    fields: Fields = {}
    for line in text.split("\n"):
        m = _FIELD.match(line)
        if not m:
            continue
        key, raw = m.groups()
        stamp = _STAMP.match(raw)
        if stamp:
            fields[key] = int(stamp.group(1))
            fields[f"{key}_age_s"] = float(stamp.group(2))
        elif raw.startswith("[") and raw.endswith("]"):
            items = [x.strip() for x in raw[1:-1].split(",") if x.strip()]
            fields[key] = [_float(x) for x in items]
        else:
            fields[key] = _scalar(raw)
    return fields


def _float(raw: str) -> float:
    try:
        return float(raw)
    except ValueError:
        return math.nan


def parse_uorb_top(text: str) -> dict[str, float]:
    """Topic name -> publication rate [Hz] from ``uorb top -1`` (first instance of each)."""
    lines = clean(text).split("\n")
    header = next((i for i, ln in enumerate(lines) if "TOPIC NAME" in ln and "RATE" in ln), None)
    if header is None:
        return {}
    cols = lines[header].replace("TOPIC NAME", "TOPIC_NAME").split()
    rate_col = cols.index("RATE")
    out: dict[str, float] = {}
    for ln in lines[header + 1 :]:
        words = ln.split()
        if len(words) <= rate_col or not re.match(r"^[a-z_0-9]+$", words[0]):
            continue
        try:
            out.setdefault(words[0], float(words[rate_col]))
        except ValueError:
            continue
    return out
