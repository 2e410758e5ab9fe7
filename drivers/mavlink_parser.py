"""Bytes -> MAVLink messages for the links (drivers/mavlink.py) and the simulator's autopilot:
``frame_spans`` (a datagram's whole frames by their headers), ``Parser`` (pymavlink's robust
parser with signing, a header prefilter and resynchronisation on byte streams) and the counters
of a link (``LinkStats``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.drivers.signing import VerifyingMAVLink

MAX_RESYNCS = 16  # per received chunk: byte-stream resynchronisations inside failed frames


@dataclass
class LinkStats:
    """Counters of one link (read by the status)."""

    rx_messages: int = 0
    rx_bad: int = 0  # BAD_DATA frames and parser exceptions
    rx_bytes: int = 0
    tx_messages: int = 0
    tx_dropped: int = 0  # nothing to send to yet, or the transport failed
    reconnects: int = 0
    handler_errors: int = 0  # exceptions raised by on_message (a bug, but the link lives)
    rx_skipped: int = 0  # whole frames of message ids nobody here reads: never parsed
    rx_foreign: int = 0  # whole frames of another system id: never parsed
    rx_other_address: int = 0  # datagrams from an address that is not the autopilot's: dropped
    peer_changes: int = 0  # udpin: the autopilot's address changed (after its silence)
    last_error: str = ""  # why the transport is down (serial: cannot open; tcp: refused)
    rx_overflow_bytes: int = 0  # serial: received faster than parsed, the oldest dropped
    rival_datagrams: int = 0  # udpin: from another address, claiming the autopilot's id
    rivals_seen: int = 0  # udpin: addresses other than the autopilot's that claimed its id


def frame_spans(data: bytes) -> list[tuple[int, int, int, int]] | None:
    """``(start, end, system_id, message_id)`` of each frame when ``data`` is exactly a run of
    whole MAVLink 1/2 frames (by their headers; nothing is checked), else None. A few
    microseconds per datagram: the cheap first look before pymavlink's parser."""
    out = []
    i, n = 0, len(data)
    while i < n:
        magic = data[i]
        if magic == 0xFD:  # v2: magic len incompat compat seq sys comp id(3) payload crc(2) [sig]
            if n - i < 12:
                return None
            end = i + 12 + data[i + 1] + (13 if data[i + 2] & 0x01 else 0)
            sysid, msgid = data[i + 5], data[i + 7] | data[i + 8] << 8 | data[i + 9] << 16
        elif magic == 0xFE:  # v1: magic len seq sys comp id payload crc(2)
            if n - i < 8:
                return None
            end = i + 8 + data[i + 1]
            sysid, msgid = data[i + 3], data[i + 5]
        else:
            return None
        if end > n:
            return None
        out.append((i, end, sysid, msgid))
        i = end
    return out


class Parser:
    """Bytes -> MAVLink messages (robust: bad frames are counted and skipped). With a signing
    state (``drivers.signing``), frames are checked against it; refused ones are bad data.

    ``wanted`` (message ids) and ``system_id``: on datagrams made of whole frames, the frames
    of other message ids or other systems are skipped by their header alone (counted, never
    CRC-checked or unpacked): a link that reads five message types does not pay for the
    autopilot's other streams, nor for a flood of frames it would throw away."""

    def __init__(
        self,
        signing_state: Any = None,
        wanted: frozenset[int] | None = None,
        system_id: int | None = None,
    ) -> None:
        self.signing_state = signing_state
        self.wanted = wanted
        self.system_id = system_id
        self.mav = self._new()

    def _prefilter(self, data: bytes, stats: LinkStats) -> bytes:
        """The frames of ``data`` worth parsing (all of it unless it is whole frames)."""
        spans = frame_spans(data)
        if spans is None:
            return data  # garbage or a partial frame: pymavlink's robust parser decides
        keep = []
        for start, end, sysid, msgid in spans:
            if self.system_id is not None and sysid != self.system_id:
                stats.rx_foreign += 1
            elif self.wanted is not None and msgid not in self.wanted:
                stats.rx_skipped += 1
            else:
                keep.append(data[start:end])
        return data if len(keep) == len(spans) else b"".join(keep)

    def _new(self) -> Any:
        mav = VerifyingMAVLink(None)
        mav.robust_parsing = True
        if self.signing_state is not None:
            mav.signing = self.signing_state
        return mav

    def _restart_at(self, data: bytes) -> None:
        """Parse from the next start-of-frame marker in ``data`` (the state reset in place)."""
        starts = [i for i in (data.find(b"\xfd"), data.find(b"\xfe")) if i >= 0]
        mav = self.mav
        mav.buf = bytearray(data[min(starts) :]) if starts else bytearray()
        mav.buf_index = 0
        mav.expected_length = mavlink.HEADER_LEN_V1 + 2

    def feed(self, data: bytes, stats: LinkStats, datagram: bool = False) -> list[Any]:
        """The messages in ``data`` (bad frames counted in ``stats.rx_bad``; frames of a
        message id we do not know are bad too: pymavlink returns them before checking their
        CRC or signature).

        ``datagram``: ``data`` is one UDP datagram, a unit of its own: bytes left over at its
        end (a truncated frame, a length byte that promised more) are dropped instead of
        swallowing the start of the next datagram. On a byte stream (serial, TCP), a frame
        that fails its CRC is searched again from its next start marker: its length byte may
        be the corrupted one, and then good frames start inside what pymavlink took for it
        (at most ``MAX_RESYNCS`` times per call, so that a flood of markers costs no more
        than pymavlink's own parsing)."""
        out: list[Any] = []
        resyncs = 0
        if datagram and (self.wanted is not None or self.system_id is not None):
            data = self._prefilter(data, stats)
            if not data:
                return out
        try:
            msg = self.mav.parse_char(data)
            while msg is not None:
                kind = msg.get_type()
                if kind != "BAD_DATA" and not kind.startswith("UNKNOWN_"):
                    out.append(msg)
                else:
                    stats.rx_bad += 1
                    raw = bytes(getattr(msg, "data", b"") or b"")
                    if (
                        not datagram
                        and kind == "BAD_DATA"
                        and resyncs < MAX_RESYNCS
                        and len(raw) > 1
                        and raw[0] in (0xFD, 0xFE)
                        and "signature" not in str(getattr(msg, "reason", ""))
                    ):
                        resyncs += 1
                        self._restart_at(raw[1:] + bytes(self.mav.buf[self.mav.buf_index :]))
                msg = self.mav.parse_char(b"")
        except Exception:  # pymavlink raises on some malformed payloads: count, go on
            stats.rx_bad += 1
            self.mav = self._new()
        if datagram and self.mav.buf_len() > 0:
            stats.rx_bad += 1
            self._restart_at(b"")
        stats.rx_messages += len(out)
        return out
