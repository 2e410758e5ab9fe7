"""PX4's MAVLink shell (nsh over SERIAL_CONTROL): command output parsers (the text
PX4 prints; `companion px4 check` reads it, and so does the PX4 SIH loop in sitl/).

``listener <topic>`` prints the last message of a uORB topic as PX4's
``orb_print_message_internal`` formats it (PX4's listener_main.cpp and uORB.cpp)::

    TOPIC: vehicle_visual_odometry
     vehicle_visual_odometry
        timestamp: 71100704 (0.004519 seconds ago)
        timestamp_sample: 71090001 (10703 us before timestamp)
        device_id: 8682243 (Type: 0x84, UAVCAN:0 (0x7B))
        position: [1.20000, -0.40000, -5.90000]
        q: [0.70697, 0.00669, -0.00373, 0.70720] (Roll: 0.2 deg, Pitch: -0.8 deg, Yaw: 90.0 deg)
        pose_frame: 2
        cs_ev_pos: True
        ...

Floats ``%.5f`` (doubles ``%.6f``), booleans ``True`` / ``False``, arrays ``[a, b]``, char
arrays in quotes; a value may carry a suffix in parentheses: ``(x seconds ago)`` after
``timestamp``, ``(N us before timestamp)`` after ``timestamp_sample`` (``timestamp`` minus it,
as an int), ``(Type: ...)`` after a ``device_id``, ``(0b...)`` after a ``*flags*`` field, the Euler
angles after a quaternion. With several instances the header reads ``TOPIC: name N instances``
and each instance follows an ``Instance i:`` line; an unpublished topic prints
``never published`` (or nothing). ``uorb top -1`` prints one table of publication rates.

These parsers take the text as it arrives (echoed command, ANSI erase sequences and the
``nsh>`` prompt included), keep what they recognise, and never raise on what they do not: a
value they cannot read stays a string, which the diagnosis treats as unknown.
"""

from __future__ import annotations

import math
import re
from typing import Any

_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")
_FIELD = re.compile(r"^[ \t]+([A-Za-z_][A-Za-z0-9_\[\]]*):[ \t]*(.*?)\s*$")
_SUFFIXED = re.compile(r"^(\S+)\s*\((.*)\)$")  # "N (anything)": PX4's annotated values
_AGO = re.compile(r"^(-?[\d.]+(?:e-?\d+)?)\s+seconds ago$")
_BEFORE = re.compile(r"^(-?\d+)\s+us before timestamp$")
_INSTANCE = re.compile(r"^Instance (\d+):\s*$")

Fields = dict[str, Any]


def clean(text: str) -> str:
    """Text without ANSI sequences and carriage returns."""
    return _ANSI.sub("", text).replace("\r", "")


def _scalar(raw: str) -> Any:
    """bool, int, float (nan included) or, when none of them, the text itself."""
    if raw in ("True", "False"):
        return raw == "True"
    if len(raw) >= 2 and raw[0] == raw[-1] == '"':
        return raw[1:-1]
    try:
        return int(raw)
    except ValueError:
        pass
    try:
        return float(raw)
    except ValueError:
        return raw


def _float(raw: str) -> float:
    try:
        return float(raw)
    except ValueError:
        return math.nan


def number(fields: Fields | None, key: str) -> float | None:
    """A numeric field (int or float, not a bool), or None when absent or not a number."""
    if fields is None:
        return None
    v = fields.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return v


def flag(fields: Fields | None, key: str) -> bool | None:
    """A boolean field, or None when absent or not a boolean."""
    if fields is None:
        return None
    v = fields.get(key)
    return v if isinstance(v, bool) else None


def _value(fields: Fields, key: str, raw: str) -> None:
    """Store one ``key: raw`` line (with its annotation, if any)."""
    if raw.startswith('"'):
        fields[key] = _scalar(raw)  # a char array, parentheses and all
        return
    if raw.startswith("["):
        end = raw.find("]")
        if end > 0:  # an array, possibly followed by an annotation (a quaternion's angles)
            items = [x.strip() for x in raw[1:end].split(",") if x.strip()]
            fields[key] = [_float(x) for x in items]
            return
    m = _SUFFIXED.match(raw)
    if m is None:
        fields[key] = _scalar(raw)
        return
    value, note = m.groups()
    fields[key] = _scalar(value)
    ago = _AGO.match(note.strip())
    before = _BEFORE.match(note.strip())
    if ago:
        fields[f"{key}_age_s"] = float(ago.group(1))
    elif before:
        fields[f"{key}_before_timestamp_us"] = int(before.group(1))


def parse_listener(text: str) -> Fields | None:
    """The fields of ``listener`` output (the first instance when PX4 prints several); None
    when the topic was never published (or is not known to this firmware). ``timestamp: t (x
    seconds ago)`` gives ``timestamp`` and ``timestamp_age_s``; ``timestamp_sample: s (d us
    before timestamp)`` gives ``timestamp_sample`` and ``timestamp_sample_before_timestamp_us``;
    other annotations are dropped; arrays become lists of floats (``nan`` included);
    ``_instances`` counts the instances printed."""
    text = clean(text)
    if "never published" in text or "not found" in text or "TOPIC:" not in text:
        return None
    fields: Fields = {}
    instances = 0
    for line in text.split("\n"):
        if _INSTANCE.match(line.strip()):
            instances += 1
            continue
        if instances > 1:
            continue  # only the first instance's fields
        m = _FIELD.match(line)
        if m:
            _value(fields, *m.groups())
    if not fields:
        return None
    fields["_instances"] = max(1, instances)
    return fields


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
