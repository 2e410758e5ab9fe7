"""A small part of PX4's MAVLink shell (nsh over SERIAL_CONTROL) for the SITL autopilot.

PX4 runs its shell on SERIAL_CONTROL with ``device = SERIAL_CONTROL_DEV_SHELL`` (10): the bytes
of a command line arrive in ``data`` (``count`` of them, 70 per message at most), the output
goes back in SERIAL_CONTROL messages flagged REPLY, ending with the ``nsh> `` prompt. This is
how one looks inside a real PX4 from a ground station (QGroundControl's MAVLink console,
``mavlink_shell.py``, MAVSDK's shell plugin).

Commands served here, in PX4's output format:
- ``listener <topic> [-n N]``: the last message of a uORB topic as PX4's
  ``orb_print_message_internal`` prints it: ``TOPIC: name``, `` name`` again, then
  ``    field: value`` lines (floats ``%.5f``, booleans ``True`` / ``False``, arrays
  ``[a, b, c]``); ``timestamp`` followed by ``(x.xxxxxx seconds ago)``, ``timestamp_sample`` by
  ``(N us before timestamp)`` (``timestamp`` minus it), a quaternion ``q`` by its Euler angles;
  or ``never published``;
- ``uorb top -1 [topic ...]``: one table of publication rates (TOPIC NAME, INST, #SUB, RATE,
  #Q, SIZE) of the published topics matching the filters;
- anything else: ``nsh: <command>: command not found``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

from companion.sitl.stub.ekf_fusion import Topic

SERIAL_CONTROL_DEV_SHELL = 10
SERIAL_CONTROL_FLAG_REPLY = 1
CHUNK = 70  # SERIAL_CONTROL.data
PROMPT = "nsh> "


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "True" if v else "False"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.5f}"
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    return str(v)


def _euler_deg(q: Any) -> tuple[float, float, float]:
    """Roll, pitch, yaw [deg] of a Hamilton w, x, y, z quaternion (matrix::Eulerf)."""
    w, x, y, z = (float(c) for c in q)
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return math.degrees(roll), math.degrees(pitch), math.degrees(yaw)


def format_listener(topic: Topic | None, name: str, now_us: int) -> str:
    """``listener <name>`` output, in PX4's format (``orb_print_message_internal``)."""
    if topic is None:
        return f"listener: topic {name} not found\n"
    if topic.fields is None:
        return "never published\n"
    lines = [f"TOPIC: {topic.name}", f" {topic.name}"]
    stamp = 0
    for key, v in topic.fields.items():
        text = f"    {key}: {_value(v)}"
        if key == "timestamp" and isinstance(v, int):
            stamp = v
            if v:
                text += f" ({(now_us - v) * 1e-6:.6f} seconds ago)"
        elif key == "timestamp_sample" and isinstance(v, int) and v and stamp:
            text += f" ({stamp - v} us before timestamp)"
        elif key == "q" and isinstance(v, (tuple, list)) and len(v) == 4:
            angles = _euler_deg(v)
            if all(math.isfinite(a) for a in angles):
                r, p, y = angles
                text += f" (Roll: {r:.1f} deg, Pitch: {p:.1f} deg, Yaw: {y:.1f} deg)"
        lines.append(text)
    return "\n" + "\n".join(lines) + "\n\n"


def format_uorb_top(topics: Mapping[str, Topic], filters: list[str], now_us: int) -> str:
    """``uorb top -1 [filters]`` output (rates over the last second)."""
    shown = [
        t
        for t in topics.values()
        if t.fields is not None and (not filters or any(f in t.name for f in filters))
    ]
    total = sum(len(t.published_us) for t in shown)
    lines = [
        f"update: 1s, topics: {len(shown)}, total publications: {total}, 0.0 kB/s",
        f"{'TOPIC NAME':<40} INST #SUB RATE #Q SIZE",
    ]
    for t in shown:
        lines.append(f"{t.name:<40} {0:4d} {1:4d} {round(t.rate_hz(now_us)):4d} {1:2d} {112:4d}")
    return "\n".join(lines) + "\n"


class NshShell:
    """One shell session per link: bytes in (``feed``), output through ``send(text)``."""

    def __init__(
        self,
        topics: Mapping[str, Topic],
        now_us: Callable[[], int],
        send: Callable[[str], None],
    ) -> None:
        self.topics = topics
        self.now_us = now_us
        self.send = send
        self._line = ""
        self.commands = 0

    def feed(self, data: bytes) -> None:
        """Input bytes (a command line may span several messages)."""
        self._line += data.decode("ascii", errors="replace")
        while "\n" in self._line:
            line, self._line = self._line.split("\n", 1)
            self.send(line.rstrip("\r") + "\n" + self.run(line.strip()) + PROMPT)

    def run(self, line: str) -> str:
        """The output of one command line."""
        if not line:
            return ""
        self.commands += 1
        words = line.split()
        now = self.now_us()
        if words[0] == "listener" and len(words) >= 2:
            return format_listener(self.topics.get(words[1]), words[1], now)
        if words[:2] == ["uorb", "top"]:
            filters = [w for w in words[2:] if not w.startswith("-")]
            return format_uorb_top(self.topics, filters, now)
        return f"nsh: {words[0]}: command not found\n"


def serial_control_replies(mav: Any, text: str) -> list[Any]:
    """SERIAL_CONTROL messages (REPLY, shell device) carrying ``text``, 70 bytes each."""
    raw = text.encode("ascii", errors="replace")
    out = []
    for i in range(0, len(raw), CHUNK):
        chunk = raw[i : i + CHUNK]
        out.append(
            mav.serial_control_encode(
                SERIAL_CONTROL_DEV_SHELL,
                SERIAL_CONTROL_FLAG_REPLY,
                0,
                0,
                len(chunk),
                list(chunk.ljust(CHUNK, b"\x00")),
            )
        )
    return out
