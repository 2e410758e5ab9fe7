"""MAVLink 2 message signing: the key, the timestamp that never goes back, pymavlink's setup.

Signing (https://mavlink.io/en/guide/message_signing.html) appends 13 bytes to each MAVLink 2
frame: link id, a 48-bit timestamp in 10 us units since 2015-01-01 00:00 UTC, and the first
6 bytes of SHA-256(key | frame | link id | timestamp). A receiver rejects a frame whose
timestamp is not newer than the last one of its (link, system, component) stream, so a sender
whose timestamp goes back (a board without a real-time clock that booted with an old date, a
restored image) is locked out until its clock passes the old value again. Therefore:

- the key is a 32-byte secret in a file (raw 32 bytes, or 64 hex digits), refused unless only
  its owner may read it (mode 0600 or 0400);
- the timestamp starts at max(wall clock, the persisted value) and the persisted value is kept
  ahead of every timestamp used (written ``RESERVE_UNITS`` ahead, atomically: temporary file,
  fsync, rename, fsync of the directory), so a crash or a power cut never makes it go back;
- one signing state (``SigningState``) is shared by the sender and the parser of a link, so a
  valid signed frame from the autopilot with a newer timestamp moves our own forward (as the
  specification asks), but only a plausible one: a frame stamped more than
  ``PEER_AHEAD_MAX_UNITS`` (30 days) ahead of both our wall clock and our own timestamp, or
  beyond what our next start accepts, is refused, counted (``far_ahead`` in the status) and
  logged once. The specification bounds how far *behind* a new stream may start (1 minute)
  but not how far ahead a key holder may push everybody; accepted, one frame from an
  autopilot with a wrong real-time clock moved us years ahead (the next start refused the
  persisted value) or to the 48-bit edge (our own timestamp then wrapped: replays to all);
- our own timestamp never passes ``OWN_LIMIT_UNITS`` (a day below 2**48) through the wall
  clock, a peer or the stored value, so what we persist always passes the start-up check;
- with ``require_signed``, unsigned or badly signed frames are refused, except HEARTBEAT (as
  PX4 does, so that a peer with the wrong key is still visible as a peer).
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import logging
import os
import stat
import struct
import time
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.bounded import read_regular_file
from companion.drivers.files import atomic_write
from companion.errors import ConfigError
from companion.service_options import SigningOptions

EPOCH_2015_S = 1_420_070_400  # 2015-01-01 00:00:00 UTC, the signing timestamp's origin
UNITS_PER_S = 100_000  # the timestamp counts 10 us units
RESERVE_UNITS = 60 * UNITS_PER_S  # the persisted value runs this far ahead of the one used
ALLOWED_UNSIGNED = frozenset({mavlink.MAVLINK_MSG_ID_HEARTBEAT})
NEW_STREAM_WINDOW_UNITS = 60 * UNITS_PER_S  # a new stream may start this far behind us
MAX_TIMESTAMP = 1 << 48  # the signing timestamp has 48 bits
CLOCK_SET_UNITS = (1_704_067_200 - EPOCH_2015_S) * UNITS_PER_S  # 2024-01-01: a wall clock set
MAX_AHEAD_UNITS = 366 * 86400 * UNITS_PER_S  # a stored value this far ahead of a set clock: bad
DAY_UNITS = 86400 * UNITS_PER_S
OWN_LIMIT_UNITS = MAX_TIMESTAMP - DAY_UNITS  # ours is never set past this (a day of headroom)
STORED_LIMIT_UNITS = MAX_TIMESTAMP - DAY_UNITS // 2  # a stored value from here on: refused
# a genuine peer may be this far ahead of max(our wall clock, our own timestamp): a companion
# without a real-time clock restores an old time at boot while a GPS-timed autopilot is right
PEER_AHEAD_MAX_UNITS = 30 * DAY_UNITS

log = logging.getLogger("companion.signing")


class VerifyingMAVLink(mavlink.MAVLink):  # type: ignore[misc]
    """pymavlink's parser with the signature verified *before* the replay state changes.

    pymavlink's ``check_signature`` records a stream's timestamp before it compares the MAC,
    so one forged frame (any signature) with timestamp 2**48 - 2 locks the real sender's
    stream out until restart, and forged frames can grow the stream table without bound.
    Here the MAC is checked first (constant-time), and only a genuine frame moves the
    stream's timestamp and ours (the specification's order)."""

    def check_signature(self, msgbuf: bytearray, srcSystem: int, srcComponent: int) -> bool:
        s = self.signing
        digest = hashlib.sha256(bytes(s.secret_key) + bytes(msgbuf[:-6])).digest()[:6]
        if not hmac.compare_digest(digest, bytes(msgbuf[-6:])):
            return False
        tlow, thigh = struct.unpack("<IH", bytes(msgbuf[-12:-6]))
        timestamp = tlow + (thigh << 32)
        stream = (msgbuf[-13], srcSystem, srcComponent)
        last = s.stream_timestamps.get(stream)
        if last is not None and timestamp <= last:
            return False  # a replay, or older than what this stream already sent
        if last is None and timestamp + NEW_STREAM_WINDOW_UNITS < s.timestamp:
            return False  # a "new" stream from long ago: a recorded frame
        if isinstance(s, SigningState) and not s.admit_peer(timestamp, stream):
            return False  # implausibly far ahead: neither the stream nor ours moves
        s.stream_timestamps[stream] = timestamp
        s.timestamp = max(s.timestamp, timestamp)
        return True


def load_key(path: str | Path, key: str = "service.signing.key_file") -> bytes:
    """The 32-byte secret in ``path``; ConfigError naming ``key`` when the file is missing,
    readable by others than its owner, or not 32 bytes / 64 hex digits."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError as e:
        raise ConfigError(f"{key}: cannot read {p}: {e.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        raise ConfigError(f"{key}: {p} is not a regular file")
    if st.st_mode & 0o077:
        raise ConfigError(
            f"{key}: {p} has mode {stat.S_IMODE(st.st_mode):04o}; a signing key must be "
            f"readable by its owner only (chmod 600 {p})"
        )
    data = read_regular_file(p, 4096)  # checked again on the open descriptor: no FIFO
    if len(data) == 32:
        return data
    text = data.strip()
    if len(text) == 64:
        with contextlib.suppress(ValueError):
            return bytes.fromhex(text.decode("ascii"))
    raise ConfigError(f"{key}: {p} must hold 32 bytes or 64 hex digits, it holds {len(data)} bytes")


def wall_units(now_s: float | None = None) -> int:
    """The wall clock in signing units (10 us since 2015-01-01 UTC)."""
    now = time.time() if now_s is None else now_s
    return max(0, int((now - EPOCH_2015_S) * UNITS_PER_S))


def clock_is_set(wall: int) -> bool:
    """Whether a wall clock reading ``wall`` (signing units) looks set: 2024 or later. A board
    without a real-time clock boots at 1970 (or at its image's date) until NTP or GPS sets it."""
    return wall >= CLOCK_SET_UNITS


class SigningState(mavlink.MAVLinkSigning):  # type: ignore[misc]
    """pymavlink's signing state of one link (shared by its sender and its parser), which
    refuses a peer's timestamp too far ahead to be a clock that is right.

    The bound, in signing units (10 us): ``PEER_AHEAD_MAX_UNITS`` ahead of the later of our
    wall clock and our *own* timestamp (where we started plus the monotonic time since: a
    peer's frames do not move this reference, so a key holder cannot walk us forward one
    step at a time); never beyond what our next start accepts (``MAX_AHEAD_UNITS`` ahead of
    a set wall clock, less the reserve) nor ``OWN_LIMIT_UNITS``."""

    def __init__(self, first_units: int) -> None:
        super().__init__()
        self.timestamp = first_units
        self.own_start_units = first_units
        self.own_start_ns = time.monotonic_ns()
        self.far_ahead = 0  # genuine frames refused for a timestamp too far ahead
        self.far_ahead_s = 0.0  # how far ahead of our reference the last one was [s]

    def own_units(self) -> int:
        """Our own timestamp as peers cannot move it: the first one plus the monotonic time
        since [signing units]."""
        return self.own_start_units + (time.monotonic_ns() - self.own_start_ns) // 10_000

    def peer_limit_units(self, wall: int | None = None) -> int:
        """The newest timestamp a peer may send us now [signing units]; ``wall``: the wall
        clock in signing units (default: now)."""
        wall = wall_units() if wall is None else wall
        limit = max(wall, self.own_units()) + PEER_AHEAD_MAX_UNITS
        if clock_is_set(wall):  # what we persist after it must pass TimestampStore.read()
            limit = min(limit, wall + MAX_AHEAD_UNITS - 2 * RESERVE_UNITS)
        return min(limit, OWN_LIMIT_UNITS)

    def admit_peer(self, timestamp: int, stream: tuple[int, int, int]) -> bool:
        """Whether a genuine frame's ``timestamp`` (signing units) of ``stream`` (link,
        system, component) may move ours; the first refusal is logged, all are counted."""
        wall = wall_units()
        if timestamp <= self.peer_limit_units(wall):
            return True
        self.far_ahead += 1
        self.far_ahead_s = (timestamp - max(wall, self.own_units())) / UNITS_PER_S
        if self.far_ahead == 1:
            log.warning(
                "signing: a frame signed with our key (link %d, system %d, component %d) is "
                "stamped %.1f days ahead of our clock: refused, as is every frame more than "
                "%d days ahead (the autopilot's clock wrong, or ours far behind: set it by "
                "NTP or GPS; until then the autopilot may refuse what we send as too old)",
                *stream,
                self.far_ahead_s / 86400,
                PEER_AHEAD_MAX_UNITS // DAY_UNITS,
            )
        return False


class TimestampStore:
    """The persisted signing timestamp: ``start()`` once, ``keep_ahead(ts)`` as it advances."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.persisted = 0
        self.writes = 0
        self.write_errors = 0

    def read(self, now_s: float | None = None) -> int:
        """The stored value (0 when there is none: a fresh board). ConfigError naming
        ``service.signing.timestamp_file`` when it cannot be read or cannot be right: not a
        number, negative, with no room left below 2**48, or (with a wall clock that is set)
        more than ``MAX_AHEAD_UNITS`` ahead of it. Accepting such a value would make every
        genuine signed frame look like a replay to the autopilot, so nothing would be sent."""
        key = "service.signing.timestamp_file"
        if not self.path.exists() and not self.path.is_symlink():
            return 0
        try:  # a regular file only, opened without blocking (a FIFO planted there: refused)
            text = read_regular_file(self.path, 64).decode("ascii").strip()
        except (ConfigError, UnicodeDecodeError) as e:
            raise ConfigError(f"{key}: cannot read {self.path}: {e}") from None
        if not text.isdigit() or len(text) > 20:
            raise ConfigError(f"{key}: {self.path} does not hold a timestamp: {text[:40]!r}")
        value = int(text)
        if value >= STORED_LIMIT_UNITS:
            raise ConfigError(
                f"{key}: {self.path} holds {value}, at or beyond the 48-bit limit of a signing "
                f"timestamp ({MAX_TIMESTAMP}); a corrupt or forged file"
            )
        wall = wall_units(now_s)
        if clock_is_set(wall) and value > wall + MAX_AHEAD_UNITS:
            days = (value - wall) / UNITS_PER_S / 86400
            raise ConfigError(
                f"{key}: {self.path} holds a timestamp {days:.0f} days ahead of the wall clock; "
                "a corrupt or forged file (remove it only if the wall clock is right)"
            )
        return value

    def start(self, now_s: float | None = None) -> int:
        """The first timestamp to use: after everything used before, and not behind the wall
        clock (up to ``OWN_LIMIT_UNITS``). Persists the reserve ahead of it before it is used."""
        first = max(min(wall_units(now_s), OWN_LIMIT_UNITS), self.read(now_s) + 1)
        try:
            self._write(first + RESERVE_UNITS)
        except OSError as e:
            raise ConfigError(
                f"service.signing.timestamp_file: cannot write {self.path}: {e.strerror}"
            ) from None
        return first

    def keep_ahead(self, timestamp: int) -> None:
        """Called as the timestamp advances: rewrites the file when the reserve is half used
        (a rare write: about once per 30 s of wall-clock advance)."""
        if timestamp > self.persisted - RESERVE_UNITS // 2:
            try:
                self._write(timestamp + RESERVE_UNITS)
            except OSError as e:  # a full or read-only disk: say so, keep signing
                if not self.write_errors:
                    log.warning("signing timestamp not persisted (%s): %s", self.path, e)
                self.write_errors += 1

    def _write(self, value: int) -> None:
        value = min(value, MAX_TIMESTAMP - 1)  # never past 48 bits
        atomic_write(self.path, f"{value}\n".encode())
        self.persisted = value
        self.writes += 1


def default_timestamp_file(opts: SigningOptions) -> Path:
    """Where the timestamp persists when ``timestamp_file`` is empty."""
    if opts.timestamp_file:
        return Path(opts.timestamp_file)
    state = os.environ.get("STATE_DIRECTORY")
    if state:
        return Path(state.split(":")[0]) / "signing_timestamp"
    return Path(opts.key_file).with_name("signing_timestamp")


class Signing:
    """Signing of one link: ``apply(sender_mav, parser_mav)`` then ``tick()`` about once a
    second (wall-clock advance and persistence). Without a store (a simulator) the timestamp
    starts at the wall clock and is not persisted."""

    def __init__(
        self,
        key: bytes,
        store: TimestampStore | None,
        link_id: int = 0,
        require_signed: bool = True,
    ) -> None:
        if len(key) != 32:
            raise ValueError("a MAVLink signing key has 32 bytes")
        self.key = key
        self.store = store
        self.link_id = link_id
        self.require_signed = require_signed
        self.state: SigningState | None = None

    @staticmethod
    def from_options(opts: SigningOptions) -> Signing | None:
        """None when signing is off (no key file configured)."""
        if not opts.key_file:
            return None
        key = load_key(opts.key_file)
        return Signing(
            key, TimestampStore(default_timestamp_file(opts)), opts.link_id, opts.require_signed
        )

    def apply(self, sender: Any, parser: Any) -> None:
        """Set up pymavlink's signing on a link's sender and parser (one shared state)."""
        first = self.store.start() if self.store is not None else min(wall_units(), OWN_LIMIT_UNITS)
        s = SigningState(first)
        s.secret_key = self.key
        s.link_id = self.link_id
        s.sign_outgoing = True
        s.allow_unsigned_callback = self._allow_unsigned
        sender.signing = s
        parser.signing = s
        self.state = s

    def _allow_unsigned(self, _mav: Any, msg_id: int) -> bool:
        return not self.require_signed or msg_id in ALLOWED_UNSIGNED

    def tick(self) -> None:
        """Advance the timestamp to the wall clock (never back, never past
        ``OWN_LIMIT_UNITS``) and keep the file ahead."""
        if self.state is None:
            return
        self.state.timestamp = max(self.state.timestamp, min(wall_units(), OWN_LIMIT_UNITS))
        if self.store is not None:
            self.store.keep_ahead(self.state.timestamp)

    def counters(self) -> dict[str, int]:
        """pymavlink's counts: frames signed correctly, badly, and unsigned ones refused; of
        the bad ones, those signed right but stamped implausibly far ahead (``far_ahead``,
        the last one ``far_ahead_s`` seconds ahead of our clock)."""
        s = self.state
        if s is None:
            return {}
        return {
            "good_signatures": int(s.goodsig_count),
            "bad_signatures": int(s.badsig_count),
            "unsigned_accepted": int(s.unsigned_count),
            "refused": int(s.reject_count),
            "timestamp_write_errors": self.store.write_errors if self.store else 0,
            "far_ahead": s.far_ahead,
            "far_ahead_s": int(s.far_ahead_s),
        }
