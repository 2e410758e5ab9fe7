"""What the operator must hear in the ground station, as STATUSTEXT events (issue 20).

Pure logic, no I/O and no clock of its own (every time is an argument, seconds of the
service's monotonic clock), so that it is tested with a fake clock:

- :class:`OperatorState` is a frozen snapshot of what an operator cares about (camera, VO,
  scale, attitude, autopilot link, serial rangefinders, d-Pose), built by the service from its
  own state every ``STATUSTEXT_PERIOD_S``;
- :func:`transitions` turns two successive snapshots into :class:`Event` s (a key, a
  MAV_SEVERITY and a short text): the events are a function of the state change only, never
  sent from scattered places in the service;
- :class:`Limiter` decides when an event goes on the wire: a per-key minimum interval (a
  flapping state is one message per interval, carrying the latest state and how many changes
  it stands for) and a global token bucket (all keys together never exceed ``burst`` messages
  at once and ``rate_hz`` on average), most severe first. An event is only ever replaced by a
  newer one of the same key, never dropped: the last state after a burst is always reported.

Texts are ASCII and at most ``MAX_TEXT_CHARS`` long so that with the prefix they fit one
STATUSTEXT (50 characters); a longer text (a config warning) goes out in chunks
(``drivers.messages.statustext``), each chunk costing one token.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

from companion.drivers.messages import statustext_chunk_count

STATUSTEXT_PERIOD_S = 0.1  # the service compares snapshots this often
AUTOPILOT_LOST_S = 3.0  # no autopilot HEARTBEAT this long: the link is lost
DPOSE_LOCK_HOLD_S = 1.0  # d-Pose is locked while it corrected the pose this recently
ATTITUDE_HOLD_S = 1.0  # the roll/pitch is "lost" only after this long without one
MAX_TEXT_CHARS = 45  # a state text (without the prefix) fits one STATUSTEXT with "CMP: "


class Severity(enum.IntEnum):
    """MAV_SEVERITY (MAVLink common.xml): lower is more severe."""

    EMERGENCY = 0
    ALERT = 1
    CRITICAL = 2
    ERROR = 3
    WARNING = 4
    NOTICE = 5
    INFO = 6
    DEBUG = 7


@dataclass(frozen=True, slots=True)
class Event:
    """One thing to tell the operator. ``key``: what it is about (a newer event of the same
    key replaces an unsent older one); ``text``: without the prefix."""

    key: str
    severity: Severity
    text: str


@dataclass(frozen=True, slots=True)
class OperatorState:
    """What the operator cares about at one instant (built by the service).

    ``camera``: None while frames are usable, else why not ("no frames", "no frames (1280x720,
    calibrated 640x480)" for a refused size, "frozen", "dark",
    "saturated", "blank", "out_of_order"); ``vo_state``: a VoState name; ``vo_resets``: VO
    re-initialisations so far; ``reset_counter``: the reset_counter of the last pose sent
    (None before the first); ``scale_ready``: tracking with a metric scale (poses can go
    out), ``scale_sensors``: the sensors in its last update; ``attitude_ready``: roll/pitch
    from the distance sensors available (held over short gaps); ``autopilot_silent_s``: since
    the autopilot's last HEARTBEAT (None: never heard); ``rangefinder_faults``: ids of serial
    rangefinders that cannot be read; ``dpose_armed`` / ``dpose_locked``: d-Pose's pattern is
    set / it corrects the pose now; ``armed``: the autopilot says it is armed (in flight);
    ``link_rival``: another source speaking as the autopilot; ``frame``: the GPS frame's
    state ([gps] align; None: off), its agreement and distance to its target [m]."""

    camera: str | None = None
    vo_state: str = "INITIALIZING"
    vo_resets: int = 0
    reset_counter: int | None = None
    scale_ready: bool = False
    scale_sensors: int = 0
    attitude_ready: bool = False
    autopilot_silent_s: float | None = None
    rangefinder_faults: frozenset[int] = frozenset()
    dpose_armed: bool = False
    dpose_locked: bool = False
    armed: bool = False
    # ``host:port`` of a source other than the autopilot's that sends as the autopilot (its
    # system id) within the last 10 s, None: nobody (drivers/mavlink.py rival_address)
    link_rival: str | None = None
    frame: str | None = None
    frame_agree_m: float | None = None
    frame_to_target_m: float | None = None
    # the in-flight lens check's finding, short ("k1 +0.021"); None: nothing found (yet)
    lens: str | None = None

    @property
    def tracking(self) -> bool:
        return self.vo_state == "TRACKING"

    @property
    def autopilot_lost(self) -> bool:
        s = self.autopilot_silent_s
        return s is not None and s > AUTOPILOT_LOST_S


INITIAL = OperatorState()  # what the service assumes before its first snapshot


def transitions(prev: OperatorState, cur: OperatorState) -> list[Event]:
    """The events between two snapshots (``prev`` = INITIAL at start), most severe first.

    Camera: lost (CRITICAL while armed, else WARNING) / problem changed / back (INFO). VO:
    lost (WARNING), tracking (INFO the first time, NOTICE again after a loss), re-initialised
    between two snapshots without a LOST in either (NOTICE). Pose reset: the reset_counter
    on the wire changed (NOTICE; EKF2 re-anchors its vision frame). Scale: ready (INFO) /
    lost while the VO still tracks (WARNING; a VO loss says it already). Attitude: ready
    (INFO) / lost while tracking (NOTICE). Autopilot link: silent (WARNING; said for when the
    link is one-way, replaced by "back" if it could not be sent) / back after N s (NOTICE).
    Serial rangefinders: fault (WARNING) / back (INFO). d-Pose: armed, lock (INFO), lock
    lost (NOTICE). A second source speaking as the autopilot: named when it appears or
    changes (CRITICAL while armed, else WARNING), sent to the autopilot the link follows. The
    lens check's finding (WARNING), once: "camera calibration off: k1 +0.021"."""
    out: list[Event] = []
    if cur.link_rival is not None and cur.link_rival != prev.link_rival:
        sev = Severity.CRITICAL if cur.armed else Severity.WARNING
        out.append(Event("rival", sev, f"second autopilot at {cur.link_rival}"))
    if cur.camera != prev.camera:
        if cur.camera is None:
            out.append(Event("camera", Severity.INFO, "camera ok"))
        else:
            sev = Severity.CRITICAL if cur.armed else Severity.WARNING
            no_frames = cur.camera.startswith("no frames")
            what = cur.camera if no_frames else f"{cur.camera} frames"
            out.append(Event("camera", sev, f"camera lost: {what}"))
    if prev.tracking and not cur.tracking:
        out.append(Event("vo", Severity.WARNING, "VO lost"))
    elif cur.tracking and not prev.tracking:
        if cur.vo_resets > 0:
            out.append(Event("vo", Severity.NOTICE, f"VO tracking again, reset {cur.vo_resets}"))
        else:
            out.append(Event("vo", Severity.INFO, "VO tracking"))
    elif cur.tracking and cur.vo_resets > prev.vo_resets:  # lost and back between snapshots
        out.append(Event("vo", Severity.NOTICE, f"VO re-initialised, reset {cur.vo_resets}"))
    if (
        cur.reset_counter is not None
        and prev.reset_counter is not None
        and cur.reset_counter != prev.reset_counter
    ):
        out.append(Event("reset", Severity.NOTICE, f"pose reset: counter {cur.reset_counter}"))
    if cur.scale_ready and not prev.scale_ready:
        n = cur.scale_sensors  # 0: from a map started on the ground (metric prior) alone
        more = f" ({n} sensor{'s' * (n != 1)})" if n else ""
        out.append(Event("scale", Severity.INFO, f"scale ready{more}"))
    elif prev.scale_ready and not cur.scale_ready and cur.tracking:
        out.append(Event("scale", Severity.WARNING, "scale lost: not publishing"))
    if cur.attitude_ready and not prev.attitude_ready:
        out.append(Event("attitude", Severity.INFO, "roll/pitch from rangefinders ready"))
    elif prev.attitude_ready and not cur.attitude_ready and cur.tracking:
        out.append(Event("attitude", Severity.NOTICE, "roll/pitch from rangefinders lost"))
    if cur.autopilot_lost and not prev.autopilot_lost:
        silent = cur.autopilot_silent_s or 0.0
        out.append(Event("link", Severity.WARNING, f"no autopilot heartbeat for {silent:.0f} s"))
    elif prev.autopilot_lost and not cur.autopilot_lost:
        gone = prev.autopilot_silent_s or 0.0
        out.append(Event("link", Severity.NOTICE, f"autopilot link back after {gone:.0f} s"))
    for sid in sorted(cur.rangefinder_faults - prev.rangefinder_faults):
        out.append(Event(f"rf{sid}", Severity.WARNING, f"rangefinder {sid}: serial fault"))
    for sid in sorted(prev.rangefinder_faults - cur.rangefinder_faults):
        out.append(Event(f"rf{sid}", Severity.INFO, f"rangefinder {sid}: serial ok"))
    if cur.dpose_armed and not prev.dpose_armed:
        out.append(Event("dpose-armed", Severity.INFO, "d-Pose armed: laser marks set"))
    if cur.dpose_locked and not prev.dpose_locked:
        out.append(Event("dpose", Severity.INFO, "d-Pose lock"))
    elif prev.dpose_locked and not cur.dpose_locked:
        out.append(Event("dpose", Severity.NOTICE, "d-Pose lock lost"))
    if cur.lens is not None and cur.lens != prev.lens:
        out.append(Event("lens", Severity.WARNING, f"camera calibration off: {cur.lens}"))
    out.sort(key=lambda e: e.severity)
    return out


def start_events(version: str, output: str, warnings: list[str]) -> list[Event]:
    """The service started (NOTICE) and each config warning (WARNING, its own key: a long
    one goes out in chunks)."""
    short = {"vision_position_estimate": "VPE", "odometry": "ODOMETRY", "both": "VPE+ODOM"}
    out = [Event("service", Severity.NOTICE, f"started v{version}, {short.get(output, output)}")]
    out += [Event(f"config{i}", Severity.WARNING, f"config: {w}") for i, w in enumerate(warnings)]
    return out


def stop_event(error: str | None, armed: bool) -> Event:
    """The service stops: NOTICE, WARNING while armed (the autopilot loses its estimate), or
    ERROR / CRITICAL (armed) when it stops on an error (named by its type)."""
    if error:
        return Event(
            "service", Severity.CRITICAL if armed else Severity.ERROR, f"stopped on {error}"
        )
    return Event("service", Severity.WARNING if armed else Severity.NOTICE, "stopping")


def ascii_text(text: str) -> str:
    """``text`` with every non-printable or non-ASCII character as '?' (STATUSTEXT is char[])."""
    return "".join(c if " " <= c <= "~" else "?" for c in text)


class Held:
    """A boolean that turns True at once and False only after ``hold_s`` of False (a state
    that drops for a frame or two is not "lost")."""

    def __init__(self, hold_s: float) -> None:
        self.hold_s = hold_s
        self._true_at: float | None = None

    def update(self, value: bool, now_s: float) -> bool:
        if value:
            self._true_at = now_s
        return self._true_at is not None and now_s - self._true_at < self.hold_s


class RecentIncrease:
    """Whether a counter rose within the last ``hold_s`` (d-Pose lock: it corrected the pose
    recently); its first value is the baseline."""

    def __init__(self, hold_s: float) -> None:
        self.hold_s = hold_s
        self._count: int | None = None
        self._rose_at: float | None = None

    def update(self, count: int, now_s: float) -> bool:
        if self._count is not None and count > self._count:
            self._rose_at = now_s
        self._count = count
        return self._rose_at is not None and now_s - self._rose_at < self.hold_s


@dataclass
class _Pending:
    event: Event
    since_s: float  # when the first event it stands for was offered
    changes: int  # offers of its key since the last send (this one included)


@dataclass
class LimiterStats:
    offered: int = 0
    sent: int = 0  # events sent
    messages: int = 0  # STATUSTEXT messages (chunks) sent
    coalesced: int = 0  # events replaced by a newer one of their key before being sent
    last_sent: dict[str, str] = field(default_factory=dict)  # key -> last text sent


class Limiter:
    """When each event goes out (see the module docstring).

    Rules, with now_s from the caller's monotonic clock:
    - an event replaces the unsent event of its key (the latest state wins; the count of
      changes it stands for is appended: "camera ok [12 changes]");
    - a key sends at most once per ``key_interval_s``; its pending event waits for that;
    - a token bucket of ``burst`` tokens refilled at ``rate_hz`` pays one token per
      STATUSTEXT message (a chunk); when tokens are short the most severe pending event goes
      first (then the oldest), and nothing overtakes an event it is waiting for;
    - nothing is dropped: pending events are bounded by the number of keys.
    So over any window of W seconds at most ``burst + rate_hz * W`` messages are sent, and an
    event offered at t is sent by t + key_interval_s + (messages pending before it) / rate_hz.
    """

    def __init__(
        self, key_interval_s: float = 2.0, burst: int = 5, rate_hz: float = 1.0, prefix: str = ""
    ) -> None:
        if key_interval_s < 0 or burst < 1 or rate_hz <= 0:
            raise ValueError("key_interval_s >= 0, burst >= 1, rate_hz > 0")
        self.key_interval_s = key_interval_s
        self.burst = burst
        self.rate_hz = rate_hz
        self.prefix = prefix
        self.stats = LimiterStats()
        self._tokens = float(burst)
        self._tokens_at: float | None = None
        self._pending: dict[str, _Pending] = {}
        self._sent_at: dict[str, float] = {}

    @property
    def pending(self) -> int:
        return len(self._pending)

    def offer(self, event: Event, now_s: float) -> None:
        """Queue ``event`` (replacing its key's unsent one)."""
        self.stats.offered += 1
        old = self._pending.get(event.key)
        if old is not None:
            self.stats.coalesced += 1
        since = old.since_s if old is not None else now_s
        changes = old.changes + 1 if old is not None else 1
        self._pending[event.key] = _Pending(event, since, changes)

    def wire_text(self, p: _Pending) -> str:
        """What goes on the wire for a pending event: prefix, text, the changes it stands for."""
        text = p.event.text if p.changes == 1 else f"{p.event.text} [{p.changes} changes]"
        return ascii_text(self.prefix + text)

    def take(self, now_s: float) -> list[tuple[Severity, str]]:
        """The (severity, wire text) to send now; the caller sends them in this order."""
        self._refill(now_s)
        ready = [
            (k, p)
            for k, p in self._pending.items()
            if now_s - self._sent_at.get(k, -math.inf) >= self.key_interval_s
        ]
        ready.sort(key=lambda kp: (kp[1].event.severity, kp[1].since_s))
        out: list[tuple[Severity, str]] = []
        for key, p in ready:
            text = self.wire_text(p)
            cost = statustext_chunk_count(text)
            if cost > self._tokens:
                break  # a less severe one may not overtake it
            self._tokens -= cost
            out.append((p.event.severity, text))
            self._sent(key, p, cost, now_s)
        return out

    def drain(self, now_s: float) -> list[tuple[Severity, str]]:
        """Every pending event, most severe first, ignoring the limits (the service stops:
        a bounded last word)."""
        items = sorted(self._pending.items(), key=lambda kp: (kp[1].event.severity, kp[1].since_s))
        out = []
        for key, p in items:
            text = self.wire_text(p)
            out.append((p.event.severity, text))
            self._sent(key, p, statustext_chunk_count(text), now_s)
        return out

    def _sent(self, key: str, p: _Pending, cost: int, now_s: float) -> None:
        del self._pending[key]
        self._sent_at[key] = now_s
        self.stats.sent += 1
        self.stats.messages += cost
        self.stats.last_sent[key] = p.event.text

    def _refill(self, now_s: float) -> None:
        if self._tokens_at is not None:
            elapsed = max(0.0, now_s - self._tokens_at)
            self._tokens = min(float(self.burst), self._tokens + elapsed * self.rate_hz)
        self._tokens_at = now_s
